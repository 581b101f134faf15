"""Payload codecs: what a rover or the base station puts on the link, as real bytes.

Every path (the in-process runner, the Flower apps) encodes weights with an
:class:`Encoder` and decodes them with :func:`decode`; payload sizes are ``len(bytes)``.

Codecs (:class:`CodecSpec`, text form in :meth:`CodecSpec.parse`)
------------------------------------------------------------------
``fp32``
    float32 values as they are (exact).
``fp16``
    ``astype(float16)`` (round to nearest even). Values beyond the fp16 range
    (|x| > 65504 after rounding) are refused with :class:`~fedmap.errors.RejectedUpdate`.
``bf16``
    The upper 16 bits of the float32 pattern after round-to-nearest-even (numpy only,
    the same rounding as ``torch.bfloat16``).
``int8`` / ``int4``
    Symmetric linear quantisation, ``q = clip(rint(x / s), -Q, Q)`` with ``Q = 127`` (int8)
    or ``Q = 7`` (int4, two values per byte, low nibble first, two's complement),
    ``s = max|x| / Q`` as float32, one scale per output row (dim 0) of every tensor with
    ``ndim >= 2`` (``per_channel``, the default; 1-D and 0-D tensors get one scale) or one
    scale per tensor (``-tensor``). Scales travel as **float32**. The decoded value is
    ``float32(q) * s``, so **|x - x̂| <= s/2 for every entry** (plus float32 rounding of
    the product, a few ulp of |x|). A row of zeros has ``s = 0`` and decodes to zeros.
``topk``
    Sparse update: ``delta = weights - reference``. With DGC momentum correction
    (Lin et al. 2018, ``momentum = m > 0``) ``u <- m*u + delta``, else ``u = delta``; with
    error feedback ``v <- residual + u`` (else ``v = u``). The ``k = max(1,
    round(fraction * n))`` entries of largest ``|v|`` over all tensors together are sent
    (ties: lower flat index first, flat index = position in the concatenation of the
    tensors in payload order). After sending, ``v[sent] -= value actually sent`` (so the
    residual keeps exactly what was not delivered, including the rounding of the sent
    values to fp16/int8) and ``u[sent] = 0`` (momentum factor masking). Without error
    feedback the residual is dropped every round. Decoded weights are
    ``reference + sparse delta``. The sent values are fp32, fp16 or int8 (int8: one
    float32 scale per tensor over that tensor's sent values, ``s = max|v_sent| / 127``).
``update``
    Dense codecs can send ``weights - reference`` instead of the weights (``update-int8``);
    decoded weights are ``reference + decoded delta``. With error feedback (default) the
    sender adds its residual (what earlier rounds failed to deliver, i.e. the quantisation
    error) to the delta before quantising. ``topk`` is always an update.
``+zstd``
    A final lossless stage: everything after the 7-byte prefix and before the CRC is one
    zstd frame (level 3 unless ``+zstd:LEVEL``). Decoding is bit-exact with and without.

Sender state (residual ``v`` and momentum ``u``, kept in float64) lives in the
:class:`Encoder`: use one encoder per (agent, direction). Its tensor layout (names,
shapes, order) is fixed by the first call that needs state; later calls must send the same
tensors. Decoding is stateless: :func:`decode` reads everything it needs from the payload.
Encoding is deterministic: the same spec, inputs (dict order included) and encoder state
give the same bytes.

Payload format (version 1; all integers little-endian; "varint" = unsigned LEB128)
-----------------------------------------------------------------------------------
::

    offset 0   4 B   magic b"FMWP"
           4   1 B   format version (1)
           5   1 B   codec id: 0 fp32, 1 fp16, 2 bf16, 3 int8, 4 int4, 5 topk
           6   1 B   flags: bit0 update (delta from a reference), bit1 per-channel scales,
                     bit2 zstd, bits3-4 topk value type (0 fp32, 1 fp16, 2 int8);
                     other bits must be 0
           7   ...   CONTENT, or one zstd frame holding CONTENT when bit2 is set
         end-4 4 B   CRC32 (zlib) of every byte before it (the bytes on the wire)

    CONTENT = HEADER BODY
    HEADER  = varint n_tensors, then per tensor (payload order):
                varint shared-prefix length with the previous name,
                varint suffix length, suffix (UTF-8),
                u8 ndim, ndim varints (the shape)
              topk only: varint k, u8 index coding (0 varint gaps, 1 bitmap),
                varint length of the index block
    BODY    fp32 / fp16 / bf16: n values (<f4, <f2, upper halves of <f4 as <u2)
            int8: scales (<f4, one per row or tensor), then n int8 values
            int4: scales (<f4), then ceil(n/2) bytes of nibbles (a pad nibble is 0)
            topk: index block, then k values (<f4 or <f2), or for int8 values
                  n_tensors scales (<f4) then k int8 values

``n`` is the total number of entries; tensors are concatenated in header order. topk
indices are the sorted flat indices, stored either as varints of ``first, gap-1, gap-1,
...`` or as an n-bit bitmap (bit i of byte j is entry 8j+i), whichever is smaller (the
varint gaps for k/n below about 10 %; fixed-width uint16 gaps would cost 2 B per index
where the varints cost about 1.3 B at k/n = 1 %, measured).

Names share prefixes (``mlp.0.weight``, ``mlp.0.bias``), so the tensor table of the paper
network is 165 B and the whole fixed overhead of a dense payload (prefix + table + CRC) is
176 B: the paper network's fp16 payload is 199,683 * 2 + 176 = 399,542 B (see
:func:`payload_header_bytes` and :func:`dense_model_bytes`).

Every decoded array is a fresh, writable float32 array. A truncated, extended or corrupted
payload fails the length, magic, version or CRC check (or, past those, the exact-length
checks of the header and body) and raises ``FedmapError("malformed payload: ...")``.
"""

from __future__ import annotations

import math
import re
import struct
import zlib
from dataclasses import dataclass

import numpy as np
import zstandard

from fedmap._util import inflate_zstd, varint
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.nets.model import Weights

MAGIC = b"FMWP"
VERSION = 1
KINDS = ("fp32", "fp16", "bf16", "int8", "int4", "topk")
VALUE_TYPES = ("fp32", "fp16", "int8")
DENSE_KINDS = KINDS[:5]
_CODEC_ID = {k: i for i, k in enumerate(KINDS)}
_F_UPDATE, _F_PER_CHANNEL, _F_ZSTD = 1, 2, 4
_VALUES_SHIFT = 3
_KNOWN_FLAGS = _F_UPDATE | _F_PER_CHANNEL | _F_ZSTD | (3 << _VALUES_SHIFT)
_PREFIX = 7  # magic + version + codec + flags
_CRC = 4
_QMAX = {"int8": 127, "int4": 7}
_IDX_VARINT, _IDX_BITMAP = 0, 1
_ZSTD_DEFAULT = 3
_MAX_CONTENT = 1 << 31  # refuse to inflate a zstd frame claiming more than this

GRAMMAR = (
    "[update-]fp32|fp16|bf16|int8[-tensor]|int4[-tensor][,noef] or "
    "topk[:FRACTION][,values=fp32|fp16|int8][,momentum=M][,noef], "
    "optionally followed by +zstd[:LEVEL] "
    "(e.g. fp16, fp16+zstd, int8-tensor, int4+zstd, topk:0.01, topk:0.005,values=int8+zstd, update-int8+zstd)"
)


# -- the spec ----------------------------------------------------------------------------

@dataclass(frozen=True)
class CodecSpec:
    """What a payload codec does. Fields that do not apply to ``kind`` are reset to their
    defaults (``per_channel`` outside int8/int4; ``fraction``, ``values``, ``momentum``
    outside topk; ``error_feedback`` outside update mode), and ``update`` is always True
    for topk, so two specs that encode alike compare equal and ``parse(label())`` is the
    identity."""

    kind: str = "fp32"
    per_channel: bool = True
    fraction: float = 0.01
    values: str = "fp16"
    error_feedback: bool = True
    momentum: float = 0.0
    update: bool = False
    zstd: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise FedmapError(f"unknown codec kind {self.kind!r}; choose one of {', '.join(KINDS)}")
        topk = self.kind == "topk"
        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731 (frozen)
        put("update", True if topk else bool(self.update))
        put("per_channel", bool(self.per_channel) if self.kind in _QMAX else True)
        put("error_feedback", bool(self.error_feedback) if self.update else True)
        if topk:
            try:
                put("fraction", float(self.fraction))
                put("momentum", float(self.momentum))
            except (TypeError, ValueError):
                raise FedmapError("topk fraction and momentum must be numbers, "
                                  f"got {self.fraction!r}, {self.momentum!r}") from None
            if not 0.0 < self.fraction <= 1.0:
                raise FedmapError(f"topk fraction must be in (0, 1], got {self.fraction}")
            if not 0.0 <= self.momentum < 1.0:
                raise FedmapError(f"momentum must be in [0, 1), got {self.momentum}")
            if self.values not in VALUE_TYPES:
                raise FedmapError(f"unknown topk value type {self.values!r}; choose one of {', '.join(VALUE_TYPES)}")
        else:
            put("fraction", 0.01)
            put("values", "fp16")
            put("momentum", 0.0)
        if self.zstd is not None:
            if isinstance(self.zstd, bool) or not isinstance(self.zstd, (int, np.integer)) or not 1 <= self.zstd <= 22:
                raise FedmapError(f"zstd level must be an integer in 1..22 (or None), got {self.zstd!r}")
            put("zstd", int(self.zstd))

    @classmethod
    def parse(cls, text: str) -> CodecSpec:
        """``fp16``, ``fp16+zstd``, ``int8``, ``int8-tensor``, ``int4+zstd``, ``topk:0.01``,
        ``topk:0.005,values=int8,momentum=0.9+zstd:9``, ``update-int8,noef``, ... (see
        :data:`GRAMMAR`)."""

        def bad(why: str) -> FedmapError:
            return FedmapError(f"bad codec {text!r}: {why}; expected {GRAMMAR}")

        if not isinstance(text, str):
            raise bad("not a string")
        s = text.strip().lower()
        kw: dict = {}
        main, plus, zpart = s.partition("+")
        if plus:
            m = re.fullmatch(r"zstd(?::(\d+))?", zpart)
            if not m:
                raise bad(f"unknown stage {'+' + zpart!r}")
            kw["zstd"] = int(m.group(1)) if m.group(1) else _ZSTD_DEFAULT
        head, *opts = main.split(",")
        if head.startswith("update-"):
            kw["update"] = True
            head = head[len("update-"):]
        m = re.fullmatch(r"(fp32|fp16|bf16|int8|int4|topk)(-tensor|:[^,]*)?", head)
        if not m:
            raise bad(f"unknown kind {head!r}")
        kind, suffix = m.group(1), m.group(2)
        kw["kind"] = kind
        if suffix == "-tensor":
            if kind not in _QMAX:
                raise bad("-tensor applies to int8/int4 only")
            kw["per_channel"] = False
        elif suffix:
            if kind != "topk":
                raise bad(f"{kind} takes no :FRACTION")
            try:
                kw["fraction"] = float(suffix[1:])
            except ValueError:
                raise bad(f"fraction {suffix[1:]!r} is not a number") from None
            if not math.isfinite(kw["fraction"]):
                raise bad("fraction must be finite")
        seen = set()
        for opt in opts:
            name, eq, value = opt.partition("=")
            if name in seen:
                raise bad(f"option {name!r} given twice")
            seen.add(name)
            if opt == "noef":
                if not (kw.get("update") or kind == "topk"):
                    raise bad("noef applies to update-* and topk only")
                kw["error_feedback"] = False
            elif kind == "topk" and name == "values" and eq:
                kw["values"] = value
            elif kind == "topk" and name == "momentum" and eq:
                try:
                    kw["momentum"] = float(value)
                except ValueError:
                    raise bad(f"momentum {value!r} is not a number") from None
            else:
                raise bad(f"unknown option {opt!r} for {kind}")
        try:
            return cls(**kw)
        except FedmapError as e:
            raise bad(str(e)) from None

    def label(self) -> str:
        """The text form; ``CodecSpec.parse(spec.label()) == spec``."""
        if self.kind == "topk":
            s = f"topk:{self.fraction!r}"
            if self.values != "fp16":
                s += f",values={self.values}"
            if self.momentum:
                s += f",momentum={self.momentum!r}"
        else:
            s = ("update-" if self.update else "") + self.kind
            if self.kind in _QMAX and not self.per_channel:
                s += "-tensor"
        if not self.error_feedback:
            s += ",noef"
        if self.zstd is not None:
            s += "+zstd" if self.zstd == _ZSTD_DEFAULT else f"+zstd:{self.zstd}"
        return s

    def __str__(self) -> str:
        return self.label()


# -- sizes (Table III) ---------------------------------------------------------------------

def dense_model_bytes(n_params: int, kind: str) -> int:
    """Raw value bytes of ``n_params`` numbers: fp32 4 B, fp16/bf16 2 B, int8 1 B, int4 1/2 B
    (rounded up). Scales, header and CRC are not included (see :func:`payload_header_bytes`;
    an int8/int4 payload adds 4 B per scale)."""
    per = {"fp32": 4, "fp16": 2, "bf16": 2, "int8": 1}
    if n_params < 0:
        raise FedmapError(f"n_params must be >= 0, got {n_params}")
    if kind == "int4":
        return (int(n_params) + 1) // 2
    if kind not in per:
        raise FedmapError(f"dense_model_bytes: unknown dense kind {kind!r}; choose one of {', '.join(DENSE_KINDS)}")
    return per[kind] * int(n_params)


def payload_header_bytes(weights: Weights) -> int:
    """Bytes of an uncompressed dense payload of ``weights`` that are not values or scales:
    the 7-byte prefix, the tensor table and the 4-byte CRC. So
    ``len(Encoder(CodecSpec("fp16")).encode(w)) == dense_model_bytes(n, "fp16") +
    payload_header_bytes(w)`` (int8/int4 add 4 B per scale)."""
    return _PREFIX + len(_encode_table(_Layout.of(weights))) + _CRC


def scale_count(weights: Weights, per_channel: bool = True) -> int:
    """How many float32 scales an int8/int4 payload of ``weights`` carries."""
    return len(_Layout.of(weights).segments(per_channel))


# -- layout and small binary helpers ---------------------------------------------------------

class _Malformed(Exception):
    pass


class _Layout:
    """Names and shapes of the tensors in payload order, with flat offsets."""

    def __init__(self, names: tuple[str, ...], shapes: tuple[tuple[int, ...], ...]) -> None:
        self.names, self.shapes = names, shapes
        self.sizes = np.array([math.prod(s) for s in shapes], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)]).astype(np.int64)
        self.total = int(self.offsets[-1])

    @classmethod
    def of(cls, weights: Weights) -> _Layout:
        if not isinstance(weights, dict):
            raise FedmapError(f"weights must be a dict of arrays, got {type(weights).__name__}")
        for k in weights:
            if not isinstance(k, str):
                raise FedmapError(f"weight names must be strings, got {k!r}")
        return cls(tuple(weights), tuple(tuple(int(d) for d in np.shape(v)) for v in weights.values()))

    def key(self) -> tuple:
        return tuple(zip(self.names, self.shapes))

    def segments(self, per_channel: bool) -> np.ndarray:
        """Lengths of the rows that share a scale, in flat order."""
        segs: list[np.ndarray] = []
        for shape, size in zip(self.shapes, self.sizes):
            if per_channel and len(shape) >= 2:
                rows = shape[0]
                segs.append(np.full(rows, size // rows if rows else 0, dtype=np.int64))
            else:
                segs.append(np.array([size], dtype=np.int64))
        return np.concatenate(segs) if segs else np.zeros(0, dtype=np.int64)

    def flat(self, weights: Weights, dtype: type, what: str) -> np.ndarray:
        """The tensors of ``weights`` (same names and shapes) concatenated in layout order."""
        _check_fits(self, weights, what)
        parts = [np.asarray(weights[n], dtype=np.float32).reshape(-1) for n in self.names]
        out: np.ndarray = np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(0, dtype=dtype)
        if not np.all(np.isfinite(out)):
            bad = next(n for n in self.names if not np.all(np.isfinite(weights[n])))
            raise FedmapError(f"{what} {bad!r} holds NaN or infinite values")
        return out

    def split(self, flat: np.ndarray) -> Weights:
        return {n: flat[a:b].reshape(s) for n, s, a, b in zip(self.names, self.shapes, self.offsets[:-1], self.offsets[1:])}


def _check_fits(layout: _Layout, weights: Weights, what: str) -> None:
    if not isinstance(weights, dict) or set(weights) != set(layout.names):
        have = set(weights) if isinstance(weights, dict) else set()
        missing, extra = sorted(set(layout.names) - have), sorted(have - set(layout.names))
        raise FedmapError(f"{what} does not match: missing {missing}, unexpected {extra}")
    for n, s in zip(layout.names, layout.shapes):
        got = tuple(np.shape(weights[n]))
        if got != s:
            raise FedmapError(f"{what} {n!r} has shape {got}, expected {s}")


class _Reader:
    def __init__(self, buf: memoryview) -> None:
        self.buf, self.pos = buf, 0

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            raise _Malformed(f"needs {n} more bytes at offset {self.pos}, has {len(self.buf) - self.pos}")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def u8(self) -> int:
        return self.take(1)[0]

    def varint(self) -> int:
        x = shift = 0
        while True:
            b = self.u8()
            x |= (b & 0x7F) << shift
            if not b & 0x80:
                return x
            shift += 7
            if shift > 63:
                raise _Malformed("varint too long")

    def rest(self) -> int:
        return len(self.buf) - self.pos


def _encode_table(layout: _Layout) -> bytes:
    out = bytearray(varint(len(layout.names)))
    prev = b""
    for name, shape in zip(layout.names, layout.shapes):
        nb = name.encode("utf-8")
        common = 0
        for a, b in zip(prev, nb):
            if a != b:
                break
            common += 1
        out += varint(common) + varint(len(nb) - common) + nb[common:]
        if len(shape) > 255:
            raise FedmapError(f"weight {name!r} has {len(shape)} dimensions; at most 255 fit a payload")
        out.append(len(shape))
        for d in shape:
            out += varint(d)
        prev = nb
    return bytes(out)


def _decode_table(r: _Reader) -> _Layout:
    n = r.varint()
    if n > r.rest():
        raise _Malformed(f"{n} tensors cannot fit")
    names: list[str] = []
    shapes: list[tuple[int, ...]] = []
    prev = b""
    total = 0
    for _ in range(n):
        common = r.varint()
        if common > len(prev):
            raise _Malformed("bad name prefix")
        nb = prev[:common] + bytes(r.take(r.varint()))
        try:
            names.append(nb.decode("utf-8"))
        except UnicodeDecodeError:
            raise _Malformed("tensor name is not UTF-8") from None
        shape = tuple(r.varint() for _ in range(r.u8()))
        if any(d > 8 * _MAX_CONTENT for d in shape):
            raise _Malformed(f"a tensor of shape {shape} is implausible")
        total += math.prod(shape)
        if total > 8 * _MAX_CONTENT:
            raise _Malformed(f"{total} entries is implausible")
        shapes.append(shape)
        prev = nb
    if len(set(names)) != len(names):
        raise _Malformed("duplicate tensor names")
    return _Layout(tuple(names), tuple(shapes))


# -- value coders ----------------------------------------------------------------------------

def _to_fp16(x: np.ndarray, what: str) -> np.ndarray:
    with np.errstate(over="ignore"):
        h = x.astype("<f2")
    if not np.all(np.isfinite(h)):
        raise RejectedUpdate(f"{what} exceed the fp16 range (|x| > 65504); use fp32, bf16 or int8")
    return h


def _to_bf16(x: np.ndarray) -> np.ndarray:
    """float32 -> bf16 bit patterns (uint16), round to nearest even."""
    u = np.ascontiguousarray(x, dtype=np.float32).view(np.uint32)
    r = ((u + (np.uint32(0x7FFF) + ((u >> 16) & 1))) >> 16).astype("<u2")
    if np.any((r & 0x7F80) == 0x7F80):
        raise FedmapError("values exceed the bf16 range (|x| > 3.39e38)")
    return r


def _from_bf16(b: np.ndarray) -> np.ndarray:
    return (b.astype(np.uint32) << 16).view(np.float32)


def _segment_amax(absx: np.ndarray, seg: np.ndarray) -> np.ndarray:
    amax = np.zeros(len(seg), dtype=absx.dtype)
    nz = seg > 0
    if nz.any():
        starts = np.concatenate([[0], np.cumsum(seg)[:-1]])[nz]
        amax[nz] = np.maximum.reduceat(absx, starts)
    return amax


def _quantise(x: np.ndarray, seg: np.ndarray, qmax: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symmetric quantisation of ``x`` in segments ``seg`` -> (scales <f4, q int8, x̂ float32)."""
    scales = (_segment_amax(np.abs(x), seg) / qmax).astype(np.float32)
    rep = np.repeat(scales, seg)
    q = np.zeros(len(x), dtype=x.dtype)
    np.divide(x, rep, out=q, where=rep > 0)
    np.rint(q, out=q)  # in place: the same values as np.clip(np.rint(q), ...) without two copies
    np.clip(q, -qmax, qmax, out=q)
    q8 = q.astype(np.int8)
    del q
    sent = q8.astype(np.float32)
    sent *= rep
    return scales.astype("<f4"), q8, sent


def _pack_int4(q: np.ndarray) -> bytes:
    nib = (q.astype(np.uint8) & 0x0F)
    if len(nib) % 2:
        nib = np.concatenate([nib, np.zeros(1, np.uint8)])
    return (nib[0::2] | (nib[1::2] << 4)).tobytes()


def _unpack_int4(raw: np.ndarray, n: int) -> np.ndarray:
    nib = np.empty(2 * len(raw), dtype=np.uint8)
    nib[0::2], nib[1::2] = raw & 0x0F, raw >> 4
    if len(nib) > n and nib[n:].any():
        raise _Malformed("int4 pad nibble is not zero")
    q = nib[:n].astype(np.int8)
    return np.where(q > 7, q - 16, q).astype(np.int8)


def _varints(x: np.ndarray) -> bytes:
    """Vectorised unsigned LEB128 of a uint64 array."""
    x = x.astype(np.uint64)
    nb = np.ones(len(x), dtype=np.int64)
    for j in range(1, 10):
        nb += x >= np.uint64(1) << np.uint64(7 * j)
    owner = np.repeat(np.arange(len(x)), nb)
    starts = np.concatenate([[0], np.cumsum(nb)[:-1]])
    j = np.arange(int(nb.sum())) - np.repeat(starts, nb)
    byte = (x[owner] >> (7 * j).astype(np.uint64)) & np.uint64(0x7F)
    byte |= (j < nb[owner] - 1).astype(np.uint64) << np.uint64(7)
    return byte.astype(np.uint8).tobytes()


def _unvarints(raw: np.ndarray, count: int) -> np.ndarray:
    ends = np.flatnonzero(raw < 0x80)
    if len(ends) != count or (count and ends[-1] != len(raw) - 1) or (not count and len(raw)):
        raise _Malformed("index block does not hold exactly k varints")
    starts = np.concatenate([[0], ends[:-1] + 1])
    lens = ends - starts + 1
    if count and lens.max() > 9:
        raise _Malformed("index varint too long")
    j = np.arange(len(raw)) - np.repeat(starts, lens)
    parts = (raw.astype(np.uint64) & np.uint64(0x7F)) << (7 * j).astype(np.uint64)
    return np.add.reduceat(parts, starts) if count else np.zeros(0, np.uint64)


def _topk_indices(v: np.ndarray, k: int) -> np.ndarray:
    """Sorted flat indices of the k largest |v|; ties go to the lower index."""
    n = len(v)
    if k >= n:
        return np.arange(n, dtype=np.int64)
    a = np.abs(v)
    t = np.partition(a, n - k)[n - k]
    above = np.flatnonzero(a > t)
    at = np.flatnonzero(a == t)[: k - len(above)]
    return np.sort(np.concatenate([above, at]))


# -- encoder ---------------------------------------------------------------------------------

class Encoder:
    """Sender side, one per (agent, direction); holds error-feedback residual and momentum state."""

    def __init__(self, spec: CodecSpec | str = CodecSpec()) -> None:
        self.spec = CodecSpec.parse(spec) if isinstance(spec, str) else spec
        self.reset()

    def reset(self) -> None:
        """Forget the residual, the momentum and the tensor layout."""
        self._layout: _Layout | None = None
        self._residual: np.ndarray | None = None  # float64, flat
        # float64, flat; only a top-k codec with momentum has one (others' would stay zero:
        # 8 bytes a parameter, 0.7 GB for a 4096² GridNet, per rover and direction)
        self._momentum: np.ndarray | None = None

    def residual(self) -> Weights | None:
        """What has not been delivered yet (float64 copies), or None before any update."""
        if self._layout is None or self._residual is None:
            return None
        return {k: v.copy() for k, v in self._layout.split(self._residual).items()}

    def state(self) -> Weights | None:
        """The sender state to checkpoint (float64 ``residual`` and ``momentum``, flat, plus
        the tensor layout as ``layout/<name>`` shape arrays in payload order), or None when
        the encoder has none yet. :meth:`restore` puts it back bit for bit."""
        if self._layout is None or self._residual is None:
            return None
        momentum = self._momentum.copy() if self._momentum is not None else np.zeros_like(self._residual)
        out: Weights = {"residual": self._residual.copy(), "momentum": momentum}
        for i, (name, shape) in enumerate(zip(self._layout.names, self._layout.shapes)):
            out[f"layout/{i:05d}/{name}"] = np.asarray(shape, dtype=np.int64)
        return out

    def restore(self, state: Weights | None) -> None:
        """Continue from :meth:`state` (None: no state, as a new encoder)."""
        self.reset()
        if state is None:
            return
        keys = sorted(k for k in state if k.startswith("layout/"))
        names = tuple(k.split("/", 2)[2] for k in keys)
        shapes = tuple(tuple(int(d) for d in np.asarray(state[k]).reshape(-1)) for k in keys)
        layout = _Layout(names, shapes)
        residual = np.asarray(state["residual"], dtype=np.float64).reshape(-1)
        momentum = np.asarray(state["momentum"], dtype=np.float64).reshape(-1)
        if residual.size != layout.total or momentum.size != layout.total:
            raise FedmapError(f"encoder state holds {residual.size} values, its layout {layout.total}")
        self._layout, self._residual = layout, residual.copy()
        self._momentum = momentum.copy() if self._has_momentum() else None

    def encode(self, weights: Weights, reference: Weights | None = None) -> bytes:
        spec = self.spec
        if not spec.update:
            layout = _Layout.of(weights)
            return self._frame(layout, self._dense_body(spec.kind, layout.flat(weights, np.float32, "weight"), layout)[0])
        if reference is None:
            raise FedmapError(f"codec {spec.label()} sends updates; encode needs the reference weights")
        layout = self._state_layout(weights)
        delta = layout.flat(weights, np.float64, "weight")
        delta -= layout.flat(reference, np.float64, "reference weight")  # in place: a model-sized float64 less
        if spec.kind == "topk":
            return self._encode_topk(layout, delta)
        v = delta
        if spec.error_feedback:
            v += self._residual
        body, sent = self._dense_body(spec.kind, v, layout)
        if spec.error_feedback:
            v -= sent  # v is this call's own array: the new residual
            self._residual = v
        return self._frame(layout, body)

    # state ---------------------------------------------------------------------------------

    def _has_momentum(self) -> bool:
        return self.spec.kind == "topk" and self.spec.momentum > 0

    def _state_layout(self, weights: Weights) -> _Layout:
        given = _Layout.of(weights)
        if self._layout is None:
            self._layout = given
            self._residual = np.zeros(given.total, dtype=np.float64)
            self._momentum = np.zeros(given.total, dtype=np.float64) if self._has_momentum() else None
            return given
        if set(given.key()) != set(self._layout.key()):
            raise FedmapError(
                "this encoder's residual is for a different set of tensors; use a new Encoder or reset() it"
            )
        return self._layout

    # bodies --------------------------------------------------------------------------------

    def _dense_body(self, kind: str, x: np.ndarray, layout: _Layout) -> tuple[bytes, np.ndarray]:
        """Body bytes and the values the receiver will decode (float32, flat)."""
        if kind == "fp32":
            w = x.astype("<f4")
            return w.tobytes(), w.astype(np.float32)
        if kind == "fp16":
            h = _to_fp16(x, "values")
            return h.tobytes(), h.astype(np.float32)
        if kind == "bf16":
            b = _to_bf16(x.astype(np.float32))
            return b.tobytes(), _from_bf16(b)
        scales, q, sent = _quantise(x, layout.segments(self.spec.per_channel), _QMAX[kind])
        packed = q.tobytes() if kind == "int8" else _pack_int4(q)
        return scales.tobytes() + packed, sent

    def _encode_topk(self, layout: _Layout, delta: np.ndarray) -> bytes:
        assert self._residual is not None  # set by _state_layout
        spec = self.spec
        n = layout.total
        k = min(n, max(1, round(spec.fraction * n)))
        if spec.momentum > 0:
            assert self._momentum is not None  # set by _state_layout
            u = spec.momentum * self._momentum + delta
        else:
            u = delta
        v = self._residual + u if spec.error_feedback else u.copy()
        idx = _topk_indices(v, k)
        vals = v[idx]
        if spec.values == "fp32":
            w = vals.astype("<f4")
            value_bytes, sent = w.tobytes(), w.astype(np.float64)
        elif spec.values == "fp16":
            h = _to_fp16(vals, "topk values")
            value_bytes, sent = h.tobytes(), h.astype(np.float64)
        else:
            tid = np.searchsorted(layout.offsets, idx, side="right") - 1
            seg = np.bincount(tid, minlength=len(layout.names)).astype(np.int64)
            scales, q, deq = _quantise(vals, seg, 127)
            value_bytes, sent = scales.tobytes() + q.tobytes(), deq.astype(np.float64)
        v[idx] -= sent
        if spec.momentum > 0:
            u[idx] = 0.0  # momentum factor masking (u is a fresh array here)
            self._momentum = u
        self._residual = v if spec.error_feedback else np.zeros(n, dtype=np.float64)
        # indices: varint gaps or a bitmap, whichever is smaller
        gaps = np.diff(idx, prepend=-1) - 1  # first entry: idx[0] itself
        vi = _varints(gaps.astype(np.uint64))
        if len(vi) <= (n + 7) // 8:
            mode, index_bytes = _IDX_VARINT, vi
        else:
            mask = np.zeros(n, dtype=bool)
            mask[idx] = True
            mode, index_bytes = _IDX_BITMAP, np.packbits(mask, bitorder="little").tobytes()
        extra = varint(k) + bytes([mode]) + varint(len(index_bytes))
        return self._frame(layout, index_bytes + value_bytes, extra)

    def _frame(self, layout: _Layout, body: bytes, extra: bytes = b"") -> bytes:
        spec = self.spec
        flags = (_F_UPDATE if spec.update else 0) | (_F_PER_CHANNEL if spec.per_channel else 0)
        if spec.kind == "topk":
            flags |= VALUE_TYPES.index(spec.values) << _VALUES_SHIFT
        content = _encode_table(layout) + extra + body
        if spec.zstd is not None:
            flags |= _F_ZSTD
            content = zstandard.ZstdCompressor(level=spec.zstd, write_checksum=False,
                                               write_content_size=True).compress(content)
        head = MAGIC + bytes([VERSION, _CODEC_ID[spec.kind], flags])
        crc = zlib.crc32(content, zlib.crc32(head))
        return head + content + struct.pack("<I", crc)


# -- decoder ---------------------------------------------------------------------------------

def decode(data: bytes, reference: Weights | None = None) -> Weights:
    """Weights from a payload; update payloads (topk, update-*) need the ``reference``
    the sender used (names and shapes are checked)."""
    buf = memoryview(data).cast("B")
    if len(buf) < _PREFIX + _CRC:
        raise RejectedUpdate(f"malformed payload: {len(buf)} bytes is shorter than the smallest payload")
    if bytes(buf[:4]) != MAGIC:
        raise RejectedUpdate("malformed payload: bad magic (not a fedmap payload)")
    if buf[4] != VERSION:
        raise RejectedUpdate(f"malformed payload: format version {buf[4]}, this fedmap reads version {VERSION}")
    (crc,) = struct.unpack("<I", buf[-_CRC:])
    if zlib.crc32(buf[:-_CRC]) != crc:
        raise RejectedUpdate(f"malformed payload: CRC mismatch ({len(buf)} bytes; truncated or corrupted)")
    codec, flags = buf[5], buf[6]
    try:
        if codec >= len(KINDS) or flags & ~_KNOWN_FLAGS:
            raise _Malformed(f"unknown codec {codec} or flags {flags:#x}")
        content = buf[_PREFIX:-_CRC]
        if flags & _F_ZSTD:
            try:
                size = zstandard.frame_content_size(content)
                if size < 0 or size > _MAX_CONTENT:
                    raise _Malformed("zstd frame without a plausible content size")
                # streamed and bounded by the size its header claims: memory grows with what the
                # frame decodes to, and stops there (a damaged header claiming 1.5 GB made one-shot
                # decompress allocate it all before failing; a bomb decodes to far more than it claims)
                inflated = inflate_zstd(content, size)
                if len(inflated) != size:
                    raise _Malformed(f"zstd frame decoded to {len(inflated)} bytes, its header says {size}")
                content = memoryview(inflated)
            except (zstandard.ZstdError, ValueError) as e:
                raise _Malformed(f"zstd: {e}") from None
        # a scale that overflows decodes to inf, as a NaN sent in fp32 decodes to NaN: the
        # receiver's finiteness check (runner.base_step, rover_step) drops such an update
        with np.errstate(over="ignore", invalid="ignore"):
            return _decode_content(KINDS[codec], flags, content, reference)
    except _Malformed as e:
        raise RejectedUpdate(f"malformed payload: {e}") from None


def _decode_content(kind: str, flags: int, content: memoryview, reference: Weights | None) -> Weights:
    r = _Reader(content)
    layout = _decode_table(r)
    n = layout.total
    update = bool(flags & _F_UPDATE)
    ref = None
    if update:  # checked against the model it updates before anything of the table's size is made
        if reference is None:
            raise FedmapError(f"this payload is a {kind} update; decode needs the reference weights")
        try:
            ref = layout.flat(reference, np.float32, "reference weight")
        except FedmapError as e:  # the update was made against another model: it does not fit here
            raise RejectedUpdate(f"malformed payload: {e}") from None
    if kind == "topk" and not update:
        raise _Malformed("topk payload without the update flag")
    if kind == "topk":
        k = r.varint()
        mode = r.u8()
        index_len = r.varint()
        if k > n or mode not in (_IDX_VARINT, _IDX_BITMAP):
            raise _Malformed(f"k = {k} of {n} entries, index coding {mode}")
        values = VALUE_TYPES[(flags >> _VALUES_SHIFT) & 3] if (flags >> _VALUES_SHIFT) & 3 < 3 else None
        if values is None:
            raise _Malformed("unknown topk value type")
        value_len = {"fp32": 4 * k, "fp16": 2 * k, "int8": 4 * len(layout.names) + k}[values]
        if r.rest() != index_len + value_len:
            raise _Malformed(f"body is {r.rest()} bytes, the header says {index_len + value_len}")
        raw = np.frombuffer(r.take(index_len), dtype=np.uint8)
        if mode == _IDX_VARINT:
            stored = _unvarints(raw, k)
            idx = np.cumsum(stored + np.uint64(1)) - np.uint64(1) if k else stored
            if k and int(idx[-1]) >= n:
                raise _Malformed("index past the end")
            idx = idx.astype(np.int64)
            if k > 1 and not np.all(np.diff(idx) > 0):
                raise _Malformed("indices not increasing")
        else:
            if index_len != (n + 7) // 8:
                raise _Malformed("bitmap of the wrong length")
            bits = np.unpackbits(raw, bitorder="little")
            if bits[n:].any():
                raise _Malformed("bitmap padding is not zero")
            idx = np.flatnonzero(bits[:n])
            if len(idx) != k:
                raise _Malformed("bitmap does not hold k entries")
        if values == "fp32":
            vals = np.frombuffer(r.take(4 * k), dtype="<f4").astype(np.float32)
        elif values == "fp16":
            vals = np.frombuffer(r.take(2 * k), dtype="<f2").astype(np.float32)
        else:
            scales = np.frombuffer(r.take(4 * len(layout.names)), dtype="<f4").astype(np.float32)
            q: np.ndarray = np.frombuffer(r.take(k), dtype=np.int8)
            tid = np.searchsorted(layout.offsets, idx, side="right") - 1
            vals = q.astype(np.float32) * scales[tid]
        delta = np.zeros(n, dtype=np.float32)
        delta[idx] = vals
    else:
        if kind in _QMAX:  # the scales come first: a table that declares more than the body holds is malformed
            per_channel = bool(flags & _F_PER_CHANNEL)
            rows = sum(sh[0] if per_channel and len(sh) >= 2 else 1 for sh in layout.shapes)
            if 4 * rows > r.rest():
                raise _Malformed(f"{rows} scales do not fit in a body of {r.rest()} bytes")
        seg = layout.segments(bool(flags & _F_PER_CHANNEL)) if kind in _QMAX else None
        n_scales = 0 if seg is None else len(seg)
        width = {"fp32": 4 * n, "fp16": 2 * n, "bf16": 2 * n, "int8": n, "int4": (n + 1) // 2}[kind]
        if r.rest() != 4 * n_scales + width:
            raise _Malformed(f"body is {r.rest()} bytes, {kind} of {n} entries needs {4 * n_scales + width}")
        if kind == "fp32":
            delta = np.frombuffer(r.take(width), dtype="<f4").astype(np.float32)
        elif kind == "fp16":
            delta = np.frombuffer(r.take(width), dtype="<f2").astype(np.float32)
        elif kind == "bf16":
            delta = _from_bf16(np.frombuffer(r.take(width), dtype="<u2"))
        else:
            scales = np.frombuffer(r.take(4 * n_scales), dtype="<f4").astype(np.float32)
            raw = np.frombuffer(r.take(width), dtype=np.int8 if kind == "int8" else np.uint8)
            q = raw if kind == "int8" else _unpack_int4(raw, n)
            if np.any(np.abs(q.astype(np.int16)) > _QMAX[kind]):
                raise _Malformed(f"{kind} value out of range")
            assert seg is not None  # int8 and int4 are in _QMAX
            delta = q.astype(np.float32) * np.repeat(scales, seg)
    if ref is None:
        return {k_: v.copy() for k_, v in layout.split(delta).items()}
    out = ref + delta
    return {k_: v.copy() for k_, v in layout.split(out).items()}


__all__ = [
    "CodecSpec", "Encoder", "decode", "dense_model_bytes", "payload_header_bytes", "scale_count",
    "KINDS", "VALUE_TYPES", "DENSE_KINDS", "GRAMMAR", "MAGIC", "VERSION",
]
