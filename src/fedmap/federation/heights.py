"""Codecs for an elevation layer: heights in metres, NaN where unknown, as real bytes.

Every payload starts with one header, then the NaN mask, then the codec's body::

    kind (u8) | rows (u16) | cols (u16) | z0 (f64) | step (f64) | param (f64) | mask length (u32)
    mask: the NaN cells, packed bits, zstd (0 bytes when there is none)

``z0`` and ``step`` map a height to the integer a codec stores, ``round((z - z0) / step)``.
The known cells are coded; each unknown one is filled with the last known height before it
in its row (``z0`` before the first) before coding, and set back to NaN on decoding.

* ``lossless`` (``param`` = ``q``, metres): heights quantised to a step of ``q``, then
  zstd of the row-wise first differences (int32). The error is at most ``q / 2``. With
  ``q = 0`` it is exact: the float32 heights, their four byte planes, zstd (the classes a
  receiver derives from them are the sender's, bit for bit).
* ``lerc`` (``param`` = the max error, metres): Esri's LERC through imagecodecs, the format
  GDAL uses for elevation; the error is at most ``param``.
* ``jxl`` (``param`` = the JPEG XL distance; 0 is lossless): the heights quantised to 16
  bits over their range, through imagecodecs' libjxl.
* ``j2k`` (``param`` = the target PSNR, whole dB, of the 16-bit image): JPEG 2000 (OpenJPEG).

:func:`residual_encode` makes any prediction exact to a max error ``e``: the residual
``z - prediction`` quantised to steps of ``2 e`` (so it is within ``e``), zstd.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zstandard

from fedmap._util import inflate_zstd
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import MAX_WIRE_SIDE

KINDS: tuple[str, ...] = ("lossless", "lerc", "jxl", "j2k")
_HEAD = struct.Struct("<BHHdddI")
_ZSTD = 19
#: Largest map side a height payload may claim.
MAX_SIDE = MAX_WIRE_SIDE


def _zstd(data: bytes) -> bytes:
    return zstandard.ZstdCompressor(level=_ZSTD).compress(data)


def _unzstd(data: bytes, expected: int, what: str) -> bytes:
    try:
        out = inflate_zstd(data, expected)
    except ValueError as exc:
        raise RejectedUpdate(f"height payload: damaged {what} ({exc})") from exc
    if len(out) != expected:
        raise RejectedUpdate(f"height payload: the {what} holds {len(out)} bytes, expected {expected}")
    return out


def _check(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 1 or max(z.shape) > MAX_SIDE:
        raise FedmapError(f"an elevation layer must be a 2-D array of sides 1..{MAX_SIDE}, got shape {z.shape}")
    if np.isinf(z).any():
        raise FedmapError("an elevation layer holds infinite heights (unknown cells must be NaN)")
    return z


@dataclass(frozen=True)
class HeightCodec:
    """One way of sending an elevation layer: ``kind`` (:data:`KINDS`) and its ``param``
    (see the module docstring)."""

    kind: str
    param: float

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise FedmapError(f"unknown height codec {self.kind!r}; choose one of {', '.join(KINDS)}")
        if not np.isfinite(self.param) or self.param < 0 or (self.kind == "lerc" and self.param <= 0):
            raise FedmapError(f"height codec {self.kind}: bad parameter {self.param!r}")

    @property
    def label(self) -> str:
        if self.kind == "lossless" and self.param == 0:
            return "lossless float32"
        unit = {"lossless": "q {:g} m", "lerc": "max err {:g} m", "jxl": "distance {:g}", "j2k": "{:g} dB"}[self.kind]
        return f"{self.kind} {unit.format(self.param)}"

    def encode(self, z: np.ndarray) -> bytes:
        z = _check(z)
        known = np.isfinite(z)
        h, w = z.shape
        z0 = float(z[known].min()) if known.any() else 0.0
        top = float(z[known].max()) if known.any() else 0.0
        filled = _forward_fill(z, known, z0)
        mask = b"" if known.all() else _zstd(np.packbits(~known).tobytes())
        if self.kind == "lossless" and self.param == 0:
            step = 0.0
            planes = np.ascontiguousarray(filled.astype("<f4")).view(np.uint8).reshape(-1, 4).T
            body = _zstd(np.ascontiguousarray(planes).tobytes())
        elif self.kind == "lossless":
            step = float(self.param)
            q = np.round((filled - z0) / step)
            if q.max(initial=0) >= 2**31:
                raise FedmapError(f"heights span {top - z0:.3g} m: too many steps of {step:g} m for 32 bits")
            d = np.diff(q.astype(np.int64), axis=1, prepend=0).astype(np.int32)
            body = _zstd(d.tobytes())
        elif self.kind == "lerc":
            import imagecodecs  # an optional heavy binding, loaded only by the codecs that use it

            step = 0.0
            body = bytes(imagecodecs.lerc_encode(filled.astype(np.float32), level=float(self.param)))
        else:
            import imagecodecs

            step = max((top - z0) / 65535, 1e-9)
            u = np.round((filled - z0) / step).astype(np.uint16)
            if self.kind == "jxl":
                body = bytes(imagecodecs.jpegxl_encode(u, distance=float(self.param), lossless=self.param == 0, effort=7))
            else:
                body = bytes(imagecodecs.jpeg2k_encode(u, level=int(round(self.param)), reversible=False))
        return _HEAD.pack(KINDS.index(self.kind), h, w, z0, step, float(self.param), len(mask)) + mask + bytes(body)

    @staticmethod
    def decode(payload: bytes) -> np.ndarray:
        """The heights a payload carries (float64, NaN where unknown)."""
        if len(payload) < _HEAD.size:
            raise RejectedUpdate(f"height payload of {len(payload)} bytes is shorter than its header")
        kind_i, h, w, z0, step, param, n_mask = _HEAD.unpack_from(payload)
        if kind_i >= len(KINDS) or not (1 <= h <= MAX_SIDE and 1 <= w <= MAX_SIDE):
            raise RejectedUpdate("height payload: bad header (kind or shape)")
        if not (np.isfinite(z0) and np.isfinite(step)) or step < 0:
            raise RejectedUpdate("height payload: bad header (offset or step)")
        off = _HEAD.size + n_mask
        if off > len(payload):
            raise RejectedUpdate("height payload: truncated mask")
        known = np.ones((h, w), dtype=bool)
        if n_mask:
            bits = np.frombuffer(_unzstd(payload[_HEAD.size:off], -(-h * w // 8), "mask"), dtype=np.uint8)
            known = ~np.unpackbits(bits)[: h * w].astype(bool).reshape(h, w)
        body = payload[off:]
        kind = KINDS[kind_i]
        try:
            if kind == "lossless" and param == 0:
                planes = np.frombuffer(_unzstd(body, 4 * h * w, "body"), dtype=np.uint8).reshape(4, -1)
                z = np.ascontiguousarray(planes.T).view("<f4").reshape(h, w).astype(np.float64)
            elif kind == "lossless":
                d = np.frombuffer(_unzstd(body, 4 * h * w, "body"), dtype=np.int32).reshape(h, w)
                z = z0 + np.cumsum(d.astype(np.int64), axis=1) * step
            else:
                import imagecodecs

                decoders: dict[str, Callable[..., Any]] = {
                    "lerc": imagecodecs.lerc_decode, "jxl": imagecodecs.jpegxl_decode, "j2k": imagecodecs.jpeg2k_decode}
                raw = np.asarray(decoders[kind](body))
                if raw.shape != (h, w):
                    raise RejectedUpdate(f"height payload: the body decodes to {raw.shape}, the header says {(h, w)}")
                z = raw.astype(np.float64) if kind == "lerc" else z0 + raw.astype(np.float64) * step
        except RejectedUpdate:
            raise
        except Exception as exc:  # the bindings raise their own error types on damaged data
            raise RejectedUpdate(f"height payload: damaged {kind} body ({type(exc).__name__})") from exc
        return np.where(known, z, np.nan)


def _forward_fill(z: np.ndarray, known: np.ndarray, default: float) -> np.ndarray:
    """``z`` with each unknown cell set to the last known height before it in its row
    (``default`` before the first), so row differences are 0 across unknown stretches."""
    if known.all():
        return z
    h, w = z.shape
    idx = np.where(known, np.arange(w)[None, :], -1)
    np.maximum.accumulate(idx, axis=1, out=idx)
    out = z[np.arange(h)[:, None], np.maximum(idx, 0)]
    return np.where(idx >= 0, out, default)


def residual_encode(z: np.ndarray, prediction: np.ndarray, max_error: float) -> bytes:
    """The residual that makes ``prediction`` within ``max_error`` of ``z`` on its known
    cells: ``round((z - prediction) / (2 max_error))``, int32, zstd (NaN cells: 0)."""
    if not max_error > 0:
        raise FedmapError(f"the residual's max error must be > 0, got {max_error!r}")
    z = _check(z)
    r = np.where(np.isfinite(z), np.round((z - prediction) / (2 * max_error)), 0)
    return _zstd(r.astype(np.int32).tobytes())


def residual_apply(prediction: np.ndarray, payload: bytes, max_error: float) -> np.ndarray:
    """``prediction`` corrected by a :func:`residual_encode` payload."""
    p = np.asarray(prediction, dtype=np.float64)
    r = np.frombuffer(_unzstd(payload, 4 * p.size, "residual"), dtype=np.int32).reshape(p.shape)
    return p + r * (2 * max_error)
