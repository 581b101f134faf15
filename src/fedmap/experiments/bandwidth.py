"""Bytes on the link: the paper's Table III, and image codecs as the baseline to a model.

The paper argues that sending the mapping network (199,683 parameters in fp16 =
399,366 B) beats sending the map. This module redoes that argument with real bytes.

Table III (:func:`paper_table3`)
--------------------------------
Every size is computed from first principles: cells x bytes per cell (grayscale 1 B/px,
OMG 6 B/cell, CADRE CCM 18 B/cell) and ``model_bytes = 199,683 x 2``. The paper mixes
units, and both readings are given:

* The grayscale map is 2,000 x 2,000 x 1 B = 4,000,000 B, which the paper shows as
  "3.81 MB": that is MiB (4,000,000 / 2**20 = 3.8147). Every other size is decimal:
  960,000 B = "960 KB", 2,160,000 B = "2.16 MB", the model's 399,366 B = "399 KB"
  (in KiB it would be 390).
* The paper's reduction is ``1 - 399 / 3810`` etc.: the displayed numbers, with
  "MB" = 1000 "KB" whatever the prefix meant. :func:`paper_table3` reproduces the shown
  89.53 / 0.7 / 58.4 / 81.5 / 86.1 / 93.8 % exactly that way.
* In consistent bytes the grayscale reduction is ``1 - 399,366 / 4,000,000`` =
  **90.02 %**, not 89.53 % (the MiB/KB mix understates it by 0.49 points). The OMG and
  CCM rows are decimal throughout and agree to the shown decimal both ways.
* The JPEG row (402 KB) is a measured file size, not cells x bytes; it is read as
  402,000 B (decimal, like the other KB), giving 0.7 % both ways. Read as KiB
  (411,648 B) it would be 3.0 %.
* The model's 399,366 B counts parameter values only; a real payload adds framing
  (fedmap's own fp16 payload format adds 176 B, see ``fedmap.federation.codecs``), as every image
  file below carries its own header.

Image codecs (:class:`ImageCodec`)
----------------------------------
A class map is turned into bytes and back. Lossy codecs and the grayscale formats work
on a **grayscale image of the classes**: free = 255, impassable = 0, unknown = 128
(monotone: unknown lies between the two, so lossy ringing at a free/impassable edge
decodes as unknown; a planner treats unknown as impassable, so that thickens obstacles).
A decoded grey image goes back to classes by the nearest class grey level (ties to the
lower class value, as :func:`fedmap.maps.grid.classes_from_rgb`). This costs lossy codecs
a lot on a map without unknown cells (JPEG Q=26 of the 2000 x 2000 mars map: 1.9 % of
the cells decode as unknown, class PSNR 23.3 dB); a receiver told that the map is
complete can snap to free/impassable only (``ImageCodec(..., two_level=True)``: grey
>= 128 is free), which is the fairer baseline for complete maps (same JPEG: 0.03 %
wrong cells, 36.8 dB).

===================  ======  ===================================================================
name                 lossy   payload
===================  ======  ===================================================================
``raw-gray``         no      the grey image as H*W bytes, no header (the paper's "1 B/px")
``jpeg``             yes     baseline JPEG of the grey image (Pillow/libjpeg, IJG quality
                             scale, standard Huffman tables: ``optimize=False``, as OpenCV's
                             default)
``webp``             yes     lossy WebP of the grey image (``method=6``)
``webp-lossless``    no      lossless WebP of the grey image (``quality=100, method=6``)
``png-gray``         no      8-bit grayscale PNG (``optimize=True``)
``png-palette``      no      2-bit palette PNG: index = class, palette = the paper's colours
``zstd-2bit``        no      zstd (level 19, with checksum) of the classes packed 4 per byte,
                             2 bits each, first cell in the high bits (like ``np.packbits``)
``zstd-uint8``       no      zstd (level 19, with checksum) of the classes as H*W uint8 bytes
``context``          no      fedmap's context-model range coder (:mod:`fedmap.coding.mapcodec`):
                             shape and CRC-32 in the payload
===================  ======  ===================================================================

``raw-gray``, ``zstd-2bit`` and ``zstd-uint8`` carry no shape: both ends share the global
grid (:func:`fedmap.maps.grid.check_same_frame`), so the decoder is given the shape; the
image formats carry their size and the decoder checks it. A payload that is truncated,
not of its format, of the wrong size or holding values that are no class raises
:class:`~fedmap.errors.FedmapError`. Integrity is only what each format has: zstd frames
carry a checksum and PNG a zlib check, but a flipped bit in JPEG or WebP (lossy or
lossless: a quarter of single-byte flips went unnoticed in a test) entropy data,
or a raw byte flipped to another class's grey level, decodes silently to a wrong map,
exactly as those files would on a real link.

Comparison (:func:`compare_image_codecs`) scores each decoded class map against the truth
with :func:`fedmap.evaluation.metrics.image_scores` (PSNR/SSIM on the paper-colour
renderings) and :func:`fedmap.evaluation.paths.path_f1`, plus PSNR/SSIM of the decoded
grey image before snapping (``psnr_gray``/``ssim_gray``, data range 255), which is what
an image-compression paper usually reports.
"""

from __future__ import annotations

import hashlib
import io
import math
import time
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zstandard
from PIL import Image, UnidentifiedImageError, features

from fedmap.coding.mapcodec import decode_map, encode_map
from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import image_scores
from fedmap.evaluation.paths import PathScores, path_f1
from fedmap.maps.grid import FREE, IMPASSABLE, PALETTE, UNKNOWN, GridMap, check_classes

# -- Table III ---------------------------------------------------------------------------

#: Trainable parameters of the paper's network.
PAPER_PARAMS: int = 199_683
#: The paper's model payload: fp16 values only.
PAPER_MODEL_BYTES: int = PAPER_PARAMS * 2

#: Table III as printed: (map, cells, bytes per cell or None, data size, reduction).
PAPER_TABLE3_PRINTED: tuple[tuple[str, int, int | None, str, str], ...] = (
    ("Grayscale 2,000 x 2,000 px", 2000 * 2000, 1, "3.81 MB", "89.53 %"),
    ("- as JPEG (Q=26)", 2000 * 2000, None, "402 KB", "0.7 %"),
    ("OMG map 400 x 400 cells", 400 * 400, 6, "960 KB", "58.4 %"),
    ("OMG map 600 x 600", 600 * 600, 6, "2.16 MB", "81.5 %"),
    ("CADRE CCM 400 x 400", 400 * 400, 18, "2.88 MB", "86.1 %"),
    ("CADRE CCM 600 x 600", 600 * 600, 18, "6.48 MB", "93.8 %"),
)
#: The JPEG size the paper reports, read as decimal KB like its other KB.
PAPER_JPEG_Q26_BYTES: int = 402_000
#: What the paper reports for that JPEG (PSNR dB, SSIM, path F1).
PAPER_JPEG_Q26_SCORES: dict = {"psnr": 25.88, "ssim": 0.90, "f1": 0.96}


def _display(n_bytes: int, binary_mb: bool = False) -> tuple[str, float]:
    """The paper's way of showing a size: ``(text, value in its 'KB')``.

    Below 1e6 B: whole decimal KB. Above: MB with 2 decimals, decimal unless
    ``binary_mb`` (MiB labelled "MB", as the paper's grayscale row). The value in "KB"
    treats "MB" as 1000 "KB" whatever the prefix meant, as the paper's reductions do.
    """
    if binary_mb:
        mb = round(n_bytes / 2**20, 2)
        return f"{mb:.2f} MB", mb * 1000
    if n_bytes < 1_000_000:
        kb = round(n_bytes / 1000)
        return f"{kb:d} KB", float(kb)
    mb = round(n_bytes / 1e6, 2)
    return f"{mb:.2f} MB", mb * 1000


def _pct(x: float, decimals: int) -> str:
    return f"{100 * x:.{decimals}f} %"


def paper_table3(model_bytes: int = PAPER_MODEL_BYTES) -> list[dict]:
    """The rows of the paper's Table III, recomputed.

    Each row holds ``map``, ``cells``, ``bytes_per_cell`` (None for the JPEG, a measured
    file), ``data_bytes``, ``data_display`` (the paper's units) and ``data_display_unit``,
    ``data_display_decimal`` (the same size in decimal units), ``model_bytes`` and
    ``model_display``, ``reduction_paper`` (fraction, from the displayed numbers as the
    paper does) with ``reduction_paper_display`` at the paper's decimals,
    ``reduction_bytes`` (fraction, ``1 - model_bytes / data_bytes``) with
    ``reduction_bytes_display``, ``paper_printed`` (the row as printed) and a ``note``.
    """
    if isinstance(model_bytes, bool) or not isinstance(model_bytes, (int, np.integer)) or model_bytes <= 0:
        raise FedmapError(f"model_bytes must be a positive integer, got {model_bytes!r}")
    model_bytes = int(model_bytes)
    model_text, model_k = _display(model_bytes)
    rows = []
    for name, cells, per_cell, printed_size, printed_red in PAPER_TABLE3_PRINTED:
        decimals = len(printed_red.split()[0].split(".")[1])
        if per_cell is None:
            data_bytes = PAPER_JPEG_Q26_BYTES
            binary = False
            unit = "KB (decimal; a measured file size, not cells x bytes)"
            note = ("measured file, read as decimal KB; as KiB (411,648 B) the reduction would be "
                    f"{_pct(1 - model_bytes / (402 * 1024), 1)}")
        else:
            data_bytes = cells * per_cell
            binary = per_cell == 1
            unit = "MiB (2**20 B) labelled MB" if binary else ("KB (1000 B)" if data_bytes < 1_000_000 else "MB (10**6 B)")
            note = ""
        text, data_k = _display(data_bytes, binary_mb=binary)
        red_paper = 1 - model_k / data_k
        red_bytes = 1 - model_bytes / data_bytes
        if binary:
            note = (f"{data_bytes:,} B shown in MiB but the model in decimal KB: the paper's "
                    f"{_pct(red_paper, decimals)} is {_pct(red_bytes, decimals)} in consistent bytes")
        rows.append({
            "map": name,
            "cells": cells,
            "bytes_per_cell": per_cell,
            "data_bytes": data_bytes,
            "data_display": text,
            "data_display_unit": unit,
            "data_display_decimal": _display(data_bytes)[0],
            "model_bytes": model_bytes,
            "model_display": model_text,
            "reduction_paper": red_paper,
            "reduction_paper_display": _pct(red_paper, decimals),
            "reduction_bytes": red_bytes,
            "reduction_bytes_display": _pct(red_bytes, decimals),
            "paper_printed": {"data": printed_size, "model": "399 KB", "reduction": printed_red},
            "note": note,
        })
    return rows


# -- codecs ------------------------------------------------------------------------------

#: Grey level of each class, indexed by class value: free 255, impassable 0, unknown 128.
GRAY_LEVELS = np.array([255, 0, 128], dtype=np.uint8)
_GRAY_TO_CLASS = np.argmin(np.abs(np.arange(256)[:, None] - GRAY_LEVELS[None, :].astype(int)), axis=1).astype(np.uint8)
_IS_LEVEL = np.isin(np.arange(256), GRAY_LEVELS)
_PALETTE_BYTES = [int(round(v * 255)) for v in PALETTE.ravel()]  # 0,255,0, 255,0,0, 128,128,128
_ZSTD_LEVEL = 19

CODEC_NAMES: tuple[str, ...] = ("raw-gray", "jpeg", "webp", "webp-lossless", "png-gray", "png-palette", "zstd-2bit",
                                "zstd-uint8", "context")
LOSSY: frozenset[str] = frozenset({"jpeg", "webp"})
DEFAULT_QUALITIES: tuple[int, ...] = (10, 26, 50, 75, 90)


def classes_to_gray(classes: np.ndarray) -> np.ndarray:
    """Class map -> grey image (uint8): free 255, impassable 0, unknown 128."""
    return GRAY_LEVELS[check_classes(classes)]


def gray_to_classes(gray: np.ndarray) -> np.ndarray:
    """Grey image (uint8) -> classes by the nearest class grey level (ties to the lower class)."""
    gray = np.asarray(gray)
    if gray.dtype != np.uint8:
        raise FedmapError(f"a grey image must be uint8, got {gray.dtype}")
    return _GRAY_TO_CLASS[gray]


def _check_shape(shape: Sequence[int]) -> tuple[int, int]:
    if len(shape) != 2 or any(isinstance(s, bool) or int(s) != s or s <= 0 for s in shape):
        raise FedmapError(f"shape must be two positive integers, got {tuple(shape)}")
    return int(shape[0]), int(shape[1])


def pack_2bit(classes: np.ndarray) -> bytes:
    """Classes (values 0..3) packed 4 per byte, 2 bits each, first cell in the high bits;
    the last byte is padded with zeros."""
    flat = check_classes(classes).ravel()
    pad = (-flat.size) % 4
    if pad:
        flat = np.concatenate([flat, np.zeros(pad, np.uint8)])
    q = flat.reshape(-1, 4)
    return ((q[:, 0] << 6) | (q[:, 1] << 4) | (q[:, 2] << 2) | q[:, 3]).astype(np.uint8).tobytes()


def unpack_2bit(data: bytes, shape: Sequence[int]) -> np.ndarray:
    """Inverse of :func:`pack_2bit`; checks the length and that every code is a class."""
    h, w = _check_shape(shape)
    n = h * w
    need = (n + 3) // 4
    if len(data) != need:
        raise FedmapError(f"malformed payload: {len(data)} packed bytes, a {h}x{w} map needs {need}")
    b = np.frombuffer(data, dtype=np.uint8)
    codes = np.stack([(b >> 6) & 3, (b >> 4) & 3, (b >> 2) & 3, b & 3], axis=1).ravel()
    if codes[n:].any():
        raise FedmapError("malformed payload: non-zero padding bits")
    codes = codes[:n]
    if (codes > UNKNOWN).any():
        raise FedmapError("malformed payload: 2-bit code 3 is no class")
    return codes.reshape(h, w).copy()


def _zstd_compress(data: bytes) -> bytes:
    return zstandard.ZstdCompressor(level=_ZSTD_LEVEL, write_checksum=True, write_content_size=True).compress(data)


def _zstd_decompress(payload: bytes, expected: int) -> bytes:
    try:
        size = zstandard.frame_content_size(payload)
        if size != expected:
            raise FedmapError(f"malformed payload: zstd frame holds {size} bytes, expected {expected}")
        out = zstandard.ZstdDecompressor().decompress(payload, max_output_size=expected)
    except zstandard.ZstdError as e:
        raise FedmapError(f"malformed payload: zstd: {e}") from None
    if len(out) != expected:
        raise FedmapError(f"malformed payload: zstd frame decoded to {len(out)} bytes, expected {expected}")
    return out


def _pil_encode(img: Image.Image, fmt: str, **opts) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **opts)
    return buf.getvalue()


def _pil_open(payload: bytes, fmt: str, shape: tuple[int, int]) -> Image.Image:
    """Open and fully decode an image payload of format ``fmt`` and size ``shape``."""
    try:
        img = Image.open(io.BytesIO(payload), formats=[fmt])
        if img.size != (shape[1], shape[0]):
            raise FedmapError(f"malformed payload: {fmt} image is {img.size[1]}x{img.size[0]}, "
                              f"expected {shape[0]}x{shape[1]}")
        img.load()
    except FedmapError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError) as e:
        raise FedmapError(f"malformed payload: {fmt}: {e}") from None
    return img


def _gray_from_image(img: Image.Image) -> np.ndarray:
    if img.mode == "L":
        return np.asarray(img, dtype=np.uint8)
    if img.mode in ("RGB", "RGBA"):
        # Lossy WebP of a grey image decodes to (nearly) equal channels; use the luma.
        return np.asarray(img.convert("L"), dtype=np.uint8)
    raise FedmapError(f"malformed payload: unexpected image mode {img.mode}")


@dataclass(frozen=True)
class ImageCodec:
    """One way to put a class map on the link (see the module doc for each ``name``).

    ``quality`` (1..100) is required by the lossy ``jpeg`` and ``webp`` and must be None
    for the others.

    ``two_level`` (lossy codecs only): the receiver knows the map has no unknown cells
    (a complete ground-truth map) and snaps the decoded grey to free (>= 128) or
    impassable (< 128) only, so coding noise at a free/impassable edge cannot turn into
    spurious unknown cells. Encoding such a codec refuses a map with unknown cells.
    """

    name: str
    quality: int | None = None
    two_level: bool = False

    def __post_init__(self) -> None:
        if self.name not in CODEC_NAMES:
            raise FedmapError(f"unknown image codec {self.name!r}; choose one of {', '.join(CODEC_NAMES)}")
        if self.name in LOSSY:
            q = self.quality
            if isinstance(q, bool) or not isinstance(q, (int, np.integer)) or not 1 <= q <= 100:
                raise FedmapError(f"{self.name} needs a quality in 1..100, got {q!r}")
        elif self.quality is not None:
            raise FedmapError(f"{self.name} is lossless and takes no quality")
        if self.two_level and self.name not in LOSSY:
            raise FedmapError(f"two_level applies to the lossy codecs only, not {self.name}")
        if self.name.startswith("webp") and not features.check("webp"):
            raise FedmapError("this Pillow has no WebP support")

    @property
    def lossless(self) -> bool:
        return self.name not in LOSSY

    @property
    def family(self) -> str:
        return self.name + (" 2-level" if self.two_level else "")

    @property
    def label(self) -> str:
        if self.quality is None:
            return self.name
        return f"{self.name} q{self.quality}" + (" 2-level" if self.two_level else "")

    # -- encode / decode -------------------------------------------------------------------
    def encode(self, classes: np.ndarray) -> bytes:
        """The exact bytes put on the link."""
        c = check_classes(classes)
        n = self.name
        if self.two_level and (c == UNKNOWN).any():
            raise FedmapError(f"{self.label} decodes free/impassable only, but the map has unknown cells")
        if n == "zstd-2bit":
            return _zstd_compress(pack_2bit(c))
        if n == "context":
            return encode_map(c)
        if n == "zstd-uint8":
            return _zstd_compress(np.ascontiguousarray(c).tobytes())
        if n == "png-palette":
            img = Image.fromarray(np.ascontiguousarray(c), mode="P")
            img.putpalette(_PALETTE_BYTES)
            return _pil_encode(img, "PNG", optimize=True)
        gray = np.ascontiguousarray(GRAY_LEVELS[c])
        if n == "raw-gray":
            return gray.tobytes()
        img = Image.fromarray(gray, mode="L")
        if n == "png-gray":
            return _pil_encode(img, "PNG", optimize=True)
        if n == "jpeg":
            assert self.quality is not None  # __post_init__ requires a quality for the lossy codecs
            return _pil_encode(img, "JPEG", quality=int(self.quality), optimize=False)
        if n == "webp":
            assert self.quality is not None
            return _pil_encode(img, "WEBP", quality=int(self.quality), method=6)
        if n == "webp-lossless":
            return _pil_encode(img, "WEBP", lossless=True, quality=100, method=6)
        raise AssertionError(n)  # pragma: no cover

    def decode_gray(self, payload: bytes, shape: Sequence[int]) -> np.ndarray:
        """The decoded grey image (uint8, before snapping to classes)."""
        shape = _check_shape(shape)
        n = self.name
        payload = bytes(payload)
        if n in ("zstd-2bit", "zstd-uint8", "png-palette", "context"):
            return GRAY_LEVELS[self.decode(payload, shape)]
        if n == "raw-gray":
            if len(payload) != shape[0] * shape[1]:
                raise FedmapError(f"malformed payload: {len(payload)} bytes, "
                                  f"a {shape[0]}x{shape[1]} grey map needs {shape[0] * shape[1]}")
            return np.frombuffer(payload, dtype=np.uint8).reshape(shape).copy()
        fmt = {"png-gray": "PNG", "jpeg": "JPEG", "webp": "WEBP", "webp-lossless": "WEBP"}[n]
        return _gray_from_image(_pil_open(payload, fmt, shape))

    def decode(self, payload: bytes, shape: Sequence[int]) -> np.ndarray:
        """The decoded class map (H, W) uint8. Lossless codecs reject values that are no
        class; lossy ones snap every grey value to the nearest class level."""
        shape = _check_shape(shape)
        n = self.name
        payload = bytes(payload)
        if n == "zstd-2bit":
            return unpack_2bit(_zstd_decompress(payload, (shape[0] * shape[1] + 3) // 4), shape)
        if n == "context":
            return decode_map(payload, expected_shape=(shape[0], shape[1]))
        if n == "zstd-uint8":
            c = np.frombuffer(_zstd_decompress(payload, shape[0] * shape[1]), dtype=np.uint8).reshape(shape).copy()
            if (c > UNKNOWN).any():
                raise FedmapError("malformed payload: a byte is no class")
            return c
        if n == "png-palette":
            img = _pil_open(payload, "PNG", shape)
            if img.mode != "P" or (img.getpalette() or [])[:9] != _PALETTE_BYTES:
                raise FedmapError("malformed payload: not a class-palette PNG")
            c = np.asarray(img, dtype=np.uint8).copy()
            if (c > UNKNOWN).any():
                raise FedmapError("malformed payload: palette index is no class")
            return c
        gray = self.decode_gray(payload, shape)
        if self.two_level:
            return np.where(gray >= 128, FREE, IMPASSABLE).astype(np.uint8)
        if self.lossless and not _IS_LEVEL[gray].all():
            raise FedmapError("malformed payload: a grey value is no class level (255 free, 0 impassable, 128 unknown)")
        return _GRAY_TO_CLASS[gray]

    def roundtrip(self, classes: np.ndarray) -> tuple[bytes, np.ndarray]:
        """``(payload, decoded class map)``."""
        payload = self.encode(classes)
        return payload, self.decode(payload, np.shape(classes))


def image_codecs(qualities: Iterable[int] = DEFAULT_QUALITIES, *, webp: bool | None = None,
                 two_level: bool = False) -> list[ImageCodec]:
    """Every codec: the lossless ones, then JPEG and lossy WebP at each quality (and,
    with ``two_level``, each lossy codec again with two-level snapping).

    WebP codecs are included when Pillow supports WebP (``webp=None``), always
    (``True``: an error without support) or never (``False``).
    """
    qualities = sorted({int(q) for q in qualities})
    with_webp = features.check("webp") if webp is None else webp
    out = [ImageCodec(n) for n in ("raw-gray", "png-gray", "png-palette", "zstd-uint8", "zstd-2bit", "context")]
    if with_webp:
        out.append(ImageCodec("webp-lossless"))
    out += [ImageCodec("jpeg", q) for q in qualities]
    if with_webp:
        out += [ImageCodec("webp", q) for q in qualities]
    if two_level:
        out += [ImageCodec(c.name, c.quality, True) for c in out if not c.lossless]
    return out


# -- comparison --------------------------------------------------------------------------

def _path_scores(args: tuple) -> PathScores:
    truth, decoded, n_pairs, seed = args
    return path_f1(truth, decoded, n_pairs=n_pairs, seed=seed)


def compare_image_codecs(
    truth: GridMap | np.ndarray,
    *,
    qualities: Iterable[int] = DEFAULT_QUALITIES,
    codecs: Sequence[ImageCodec] | None = None,
    n_pairs: int = 75,
    seed: int = 0,
    path_scores: bool = True,
    workers: int = 1,
    two_level: bool = False,
) -> list[dict]:
    """Encode ``truth`` with every codec, decode it, and score the decoded class map.

    Each row: ``codec`` (label), ``family``, ``quality``, ``lossless``, ``bytes``
    (``len`` of the payload), ``bits_per_cell``, ``raw_fraction`` (bytes / cells, i.e.
    relative to the 1 B/px grayscale map), ``exact`` (decoded == truth), ``psnr``,
    ``ssim``, ``accuracy``, ``iou_free``, ``iou_impassable`` (from ``image_scores``),
    ``psnr_gray`` / ``ssim_gray`` (decoded grey image vs the true one, data range 255),
    ``f1``, ``f1_tolerant``, ``mean_length_ratio`` (from ``path_f1`` with ``n_pairs`` and
    ``seed``; None when ``path_scores`` is False), ``encode_s``, ``decode_s`` and
    ``seconds`` (their sum; one run each, wall clock).

    ``codecs`` defaults to ``image_codecs(qualities, two_level=two_level)``. Decoded maps
    that are identical share their scores (all lossless codecs give the
    truth itself), so path planning runs once per distinct map; ``workers > 1`` runs
    those path evaluations in parallel processes (path F1 dominates on large maps: about
    3 minutes per distinct 2000 x 2000 map, single-threaded). The pool uses the
    platform's default start method (fork on Linux).
    """
    classes = check_classes(truth.classes if isinstance(truth, GridMap) else truth)
    if codecs is None:
        codecs = image_codecs(qualities, two_level=two_level)
    if workers < 1:
        raise FedmapError(f"workers must be >= 1, got {workers}")
    true_gray = GRAY_LEVELS[classes]
    rows: list[dict] = []
    decoded_by_key: dict[str, np.ndarray] = {}
    image_by_key: dict[str, dict] = {}
    row_keys: list[str] = []
    for codec in codecs:
        t0 = time.perf_counter()
        payload = codec.encode(classes)
        t1 = time.perf_counter()
        decoded = codec.decode(payload, classes.shape)
        t2 = time.perf_counter()
        gray = codec.decode_gray(payload, classes.shape)
        exact = bool(np.array_equal(decoded, classes))
        if codec.lossless and not exact:
            raise AssertionError(f"lossless codec {codec.label} did not round-trip")  # pragma: no cover
        key = hashlib.sha256(decoded.tobytes()).hexdigest()
        if key not in image_by_key:
            image_by_key[key] = image_scores(classes, decoded)
            decoded_by_key[key] = decoded
        sg: float | None
        if np.array_equal(gray, true_gray):
            pg, sg = math.inf, 1.0
        else:
            # imported here: skimage.metrics imports scipy.stats (0.6 s of every fedmap command)
            from skimage.metrics import peak_signal_noise_ratio, structural_similarity

            pg = float(peak_signal_noise_ratio(true_gray, gray, data_range=255))
            sg = float(structural_similarity(true_gray, gray, data_range=255)) if min(classes.shape) >= 7 else None
        sc = image_by_key[key]
        rows.append({
            "codec": codec.label,
            "family": codec.family,
            "quality": codec.quality,
            "lossless": codec.lossless,
            "bytes": len(payload),
            "bits_per_cell": 8 * len(payload) / classes.size,
            "raw_fraction": len(payload) / classes.size,
            "exact": exact,
            "psnr": sc["psnr"],
            "ssim": sc["ssim"],
            "accuracy": sc["accuracy"],
            "iou_free": sc["iou_free"],
            "iou_impassable": sc["iou_impassable"],
            "psnr_gray": pg,
            "ssim_gray": sg,
            "f1": None,
            "f1_tolerant": None,
            "mean_length_ratio": None,
            "encode_s": t1 - t0,
            "decode_s": t2 - t1,
            "seconds": t2 - t0,
        })
        row_keys.append(key)
    if path_scores:
        keys = list(decoded_by_key)
        jobs = [(classes, decoded_by_key[k], n_pairs, seed) for k in keys]
        if workers == 1 or len(jobs) == 1:
            results = [_path_scores(j) for j in jobs]
        else:
            with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as ex:
                results = list(ex.map(_path_scores, jobs))
        by_key = dict(zip(keys, results))
        for row, key in zip(rows, row_keys):
            pf = by_key[key]
            row["f1"] = pf.f1
            row["f1_tolerant"] = pf.tolerant.f1
            row["mean_length_ratio"] = pf.mean_length_ratio
    return rows


# -- figure and table --------------------------------------------------------------------

_FAMILY_STYLE = {"jpeg": ("tab:blue", "o", "-"), "webp": ("tab:orange", "s", "-"),
                 "jpeg 2-level": ("tab:cyan", "o", "--"), "webp 2-level": ("tab:pink", "s", "--")}
_MODEL_COLORS = ("black", "magenta", "darkcyan", "goldenrod", "navy")
_LOSSLESS_STYLE = {
    "raw-gray": ("0.3", ":"), "png-gray": ("tab:green", "--"), "png-palette": ("tab:olive", "-."),
    "zstd-uint8": ("tab:purple", "--"), "zstd-2bit": ("tab:red", "-"), "webp-lossless": ("tab:brown", "-."),
    "context": ("black", "-"),
}


def rd_figure(rows: Sequence[dict], path: str | Path, *, model_points: list[dict] | None = None, title: str = "") -> None:
    """Rate-distortion figure: bytes (log x) vs PSNR (left) and vs path F1 (right).

    Lossy codecs are lines with markers per family, annotated with their quality; a lossy
    point that decodes exactly (PSNR inf) is drawn at the top edge as a triangle.
    Lossless codecs are vertical lines at their size. ``model_points`` are extra labelled
    points (dicts with ``label``, ``bytes``, ``psnr``, ``f1``; a None score draws a
    vertical dashed line in that panel instead), e.g. a learned model's payload.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    if not rows and not model_points:
        raise FedmapError("nothing to plot: no rows and no model points")
    model_points = list(model_points or [])
    for p in model_points:
        if "label" not in p or "bytes" not in p or not p["bytes"] or p["bytes"] <= 0:
            raise FedmapError(f"a model point needs a label and positive bytes, got {p}")
    fig, axes = plt.subplots(1, 2, figsize=(12, 6.0), dpi=110)
    panels = (("psnr", "PSNR of the decoded class map (dB)"), ("f1", "path-planning F1"))
    finite = {k: [r[k] for r in rows if r.get(k) is not None and math.isfinite(r[k])]
              + [p[k] for p in model_points if p.get(k) is not None and math.isfinite(p[k])] for k, _ in panels}
    for ax, (key, ylabel) in zip(axes, panels):
        vals = finite[key]
        if key == "psnr":
            lo, hi = (min(vals), max(vals)) if vals else (0.0, 40.0)
            span = max(hi - lo, 1.0)
            ymin, ymax = lo - 0.08 * span, hi + 0.15 * span
        else:
            lo = min(vals) if vals else 0.0
            ymin, ymax = max(0.0, lo - 0.08 * (1.0 - lo) - 0.02), 1.04
        top = ymax - 0.03 * (ymax - ymin)
        families = [f for f in dict.fromkeys(r["family"] for r in rows if not r["lossless"])]
        for fam in families:
            color, marker, line = _FAMILY_STYLE.get(fam, ("tab:gray", "D", "-"))
            pts = sorted((r for r in rows if r["family"] == fam and not r["lossless"]), key=lambda r: r["bytes"])
            xs = [r["bytes"] for r in pts]
            ys = [r[key] if r[key] is not None and math.isfinite(r[key]) else top for r in pts]
            ax.plot(xs, ys, color=color, marker=marker, ms=5, lw=1.4, ls=line, label=f"{fam} (lossy)")
            for r, x, y in zip(pts, xs, ys):
                exact_pt = r[key] is None or not math.isfinite(r[key])
                if exact_pt:
                    ax.plot([x], [y], marker="^", color=color, ms=8, ls="none")
                ax.annotate(f"q{r['quality']}", (x, y), textcoords="offset points", xytext=(3, -10 if exact_pt else 4),
                            fontsize=7, color=color)
        for r in rows:
            if r["lossless"]:
                color, ls = _LOSSLESS_STYLE.get(r["family"], ("0.5", "--"))
                ax.axvline(r["bytes"], color=color, ls=ls, lw=1.2, label=f"{r['codec']} (lossless, {_human(r['bytes'])})")
        exact_row = key == "psnr" and any(r["psnr"] is not None and math.isinf(r["psnr"]) for r in rows if not r["lossless"])
        if exact_row:
            ax.axhline(top, color="0.6", lw=0.8, ls=":")
        for i, p in enumerate(model_points):
            style = dict(color=_MODEL_COLORS[i % len(_MODEL_COLORS)], label=f"{p['label']} ({_human(p['bytes'])})")
            v = p.get(key)
            if v is None:
                ax.axvline(p["bytes"], ls=(0, (5, 2)), lw=2.0, **style)
            else:
                y = v if math.isfinite(v) else top
                ax.plot([p["bytes"]], [y], marker="*", ms=15, ls="none", markeredgecolor="k", **style)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: _human(x, short=True)))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(ymin, ymax)
        if exact_row:  # label the top line "exact" (PSNR inf) instead of a number
            ticks = [t for t in ax.get_yticks() if ymin <= t < top - 0.06 * (ymax - ymin)]
            ax.set_yticks(ticks + [top], [f"{t:g}" for t in ticks] + ["exact"])
        ax.set_xlabel("bytes on the link (log)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    ncol = 4
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=7.5, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    bottom = 0.02 + 0.032 * math.ceil(len(labels) / ncol)
    fig.tight_layout(rect=(0, bottom, 1, 0.95 if title else 1))
    fig.savefig(path)
    plt.close(fig)


def _human(n: float, short: bool = False) -> str:
    """Decimal units; ``short`` drops trailing zeros (axis ticks)."""
    for scale, unit in ((1e6, "MB"), (1e3, "KB"), (1.0, "B")):
        if n >= scale or unit == "B":
            v = n / scale
            if short:
                return f"{v:.3g} {unit}"
            return f"{v:.2f} {unit}" if unit == "MB" else (f"{v:.1f} {unit}" if unit == "KB" else f"{v:.0f} {unit}")
    raise AssertionError  # pragma: no cover


def _fmt(v, digits: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        if math.isinf(v):
            return "inf"
        return f"{v:.{digits}f}"
    if isinstance(v, (int, np.integer)):
        return f"{v:,}"
    return str(v)


def markdown_table(rows: Sequence[dict]) -> str:
    """A Markdown table of :func:`compare_image_codecs` rows (or of :func:`paper_table3`
    rows, recognised by their ``reduction_paper`` key)."""
    if not rows:
        return ""
    if "reduction_paper" in rows[0]:
        head = ["map", "data bytes", "paper shows", "model bytes", "paper shows", "reduction (paper's way)",
                "reduction (bytes)", "printed"]
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for r in rows:
            lines.append("| " + " | ".join([
                r["map"], f"{r['data_bytes']:,}", r["data_display"], f"{r['model_bytes']:,}", r["model_display"],
                r["reduction_paper_display"], r["reduction_bytes_display"], r["paper_printed"]["reduction"],
            ]) + " |")
        return "\n".join(lines) + "\n"
    head = ["codec", "bytes", "bits/cell", "PSNR (dB)", "SSIM", "path F1", "F1 tol.", "accuracy", "grey PSNR (dB)",
            "grey SSIM", "enc (s)", "dec (s)"]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for r in rows:
        lines.append("| " + " | ".join([
            r["codec"] + ("" if not r["lossless"] else " (lossless)"), _fmt(int(r["bytes"])), _fmt(r["bits_per_cell"], 3),
            _fmt(r["psnr"]), _fmt(r["ssim"], 4), _fmt(r["f1"], 3), _fmt(r["f1_tolerant"], 3), _fmt(r["accuracy"], 5),
            _fmt(r["psnr_gray"]), _fmt(r["ssim_gray"], 4), _fmt(r["encode_s"], 3), _fmt(r["decode_s"], 3),
        ]) + " |")
    return "\n".join(lines) + "\n"


__all__ = [
    "PAPER_PARAMS", "PAPER_MODEL_BYTES", "PAPER_TABLE3_PRINTED", "PAPER_JPEG_Q26_BYTES", "PAPER_JPEG_Q26_SCORES",
    "paper_table3", "GRAY_LEVELS", "classes_to_gray", "gray_to_classes", "pack_2bit", "unpack_2bit",
    "CODEC_NAMES", "DEFAULT_QUALITIES", "ImageCodec", "image_codecs", "compare_image_codecs", "rd_figure",
    "markdown_table",
]
