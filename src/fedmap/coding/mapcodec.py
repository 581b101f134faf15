"""``context``: a lossless codec for class maps (FREE / IMPASSABLE / UNKNOWN).

An adaptive context model drives a range coder (``constriction``): every cell's class is
predicted from cells both ends already hold, with counts that both ends update in the
same way, so the decoder reproduces the encoder's probabilities exactly.

Coding order (coarse to fine, like JBIG's resolution layers, so that most cells are
predicted from neighbours on *every* side):

* ``S`` is the smallest power of two >= max(H, W). Cell (0, 0) comes first.
* For ``s = S/2, S/4, ..., 1``, with every cell on the lattice of step ``2s`` known:

  - phase A, centres ``(r, c) = (s, s) mod 2s``: context = the 4 diagonal neighbours at
    distance ``s`` (all on the ``2s`` lattice);
  - phase B, ``(0, s) mod 2s``: context = left/right (lattice) and up/down (phase A);
  - phase C, ``(s, 0) mod 2s``: context = up/down (lattice) and left/right (phase A).

  After the three phases the lattice of step ``s`` is known.

A context is the four neighbours at distance ``s`` (256 contexts). A neighbour outside
the map reads as the opposite neighbour, as if the map were mirrored at its edge (so a
border cell shares the contexts of the interior), or as a fourth value when both are
outside (strips one cell wide). (Adding four further neighbours, or folding contexts by
the square's symmetries, changed the size by -3 % to +14 % on the built-in maps: the
extra contexts cost more to learn than they predict.) Each (phase, level) pair has its own count table, with the levels
``s = 1``, ``s = 2`` and ``s >= 4`` kept apart. With a ``reference`` map that both ends
hold (e.g. the last global map, to code a rover's update), a cell the reference knows
(FREE or IMPASSABLE) is predicted from its reference class and how many of its four
neighbours differ from the reference (10 contexts: unchanged ground costs almost
nothing), and a cell the reference does not know from its neighbours as above.

Probabilities are ``(count + ALPHA) / (total + 3 ALPHA)`` in float64, computed from
integer counts in the same order on both ends; ``constriction``'s categorical model
quantises them deterministically. Every context of a phase is known before the phase is
coded, so a phase is coded grouped by context, in rounds: the k-th cell of each context
in round ``k.bit_length()``, with the counts as they were after the previous round. Each
context thus learns from its first cells (1, 1, 2, 4, 8, ... cells between updates), and
each round is one vectorised call on both ends.

Only the **window that changed** is coded: the smallest rectangle holding every cell that
differs from the background both ends already hold (the reference map, or UNKNOWN without
one). The window is coded as a map of its own (against the reference's window), and every
cell outside it is the background, so a rover's update of a few new cells on a large grid
costs the work of those cells' rectangle, not of the grid.

Payload (format version 2): ``b"FMCM"``, format version, flags (bit 0: coded against a
reference; bit 1: a window), height, width and a CRC-32 of the whole map's class bytes
(uint32 little-endian); with bit 1, the window's top row, left column, height and width
(LEB128 varints; a window of height 0: nothing differs, no coder words); the range coder's
32-bit words, and a CRC-32 of everything before it. Version 1 payloads (the whole grid, no
window bit) still decode; any other version is refused in one line. The first CRC catches a decode that
went wrong for any reason, e.g. a reference other than the encoder's. A payload that fails any check raises
:class:`~fedmap.errors.RejectedUpdate` (``malformed map payload: ...``).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator

import constriction
import numpy as np

from fedmap._util import varint
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import UNKNOWN, check_classes

MAGIC = b"FMCM"
VERSION = 2
#: Format versions this module decodes (1: the whole grid, before windows).
READS = (1, 2)
_F_REFERENCE = 1
_F_WINDOW = 2
_HEADER = struct.Struct("<4sBBIII")  # magic, version, flags, height, width, CRC-32 of the map
_CRC = 4

#: The model settings both ends use (part of format VERSION).
ALPHA = 0.25  # additive prior on every count
N_CLASSES = 3
_OUTSIDE = 3  # a neighbour outside the map
N_CTX = 4**4  # four base-4 neighbour digits
_REF_KNOWN = 2 * 5  # with a reference: (its class FREE / IMPASSABLE) x (0..4 neighbours changed)
LEVELS = 3  # s = 1, s = 2, s >= 4
#: Largest map a payload may declare (cells, 4096²); bounds what a decoder allocates before
#: the map's CRC can be checked. Pass ``expected_shape`` to bound it to the map you expect.
MAX_CELLS = 1 << 24

#: Per phase: the four neighbours at distance ``s`` (all known when the phase is coded).
_OFFSETS = {
    "A": lambda s: ((-s, -s), (-s, s), (s, -s), (s, s)),
    "B": lambda s: ((0, -s), (0, s), (-s, 0), (s, 0)),
    "C": lambda s: ((-s, 0), (s, 0), (0, -s), (0, s)),
}
KINDS = ("A", "B", "C")
#: For each offset of a phase, the index of the opposite one (``(-dr, -dc)``).
_OPPOSITE = {"A": (3, 2, 1, 0), "B": (1, 0, 3, 2), "C": (1, 0, 3, 2)}


def _check_classes(classes: np.ndarray, what: str) -> np.ndarray:
    a = check_classes(classes, what)
    if a.size > MAX_CELLS:
        raise FedmapError(f"{what} has {a.size} cells, more than the codec's {MAX_CELLS}")
    return a


def _map_crc(m: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(m, dtype=np.uint8).tobytes())


def phases(h: int, w: int) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """``(table, s, rows, cols)`` for every phase after cell (0, 0), coarse to fine."""
    s = (1 << max(0, (max(h, w) - 1).bit_length())) // 2
    while s >= 1:
        level = min(s.bit_length() - 1, LEVELS - 1)
        for k, kind in enumerate(KINDS):
            rows = np.arange(s if kind in ("A", "C") else 0, h, 2 * s)
            cols = np.arange(s if kind in ("A", "B") else 0, w, 2 * s)
            if rows.size and cols.size:
                yield 1 + k * LEVELS + level, s, rows, cols
        s //= 2


def contexts(m: np.ndarray, kind_table: int, s: int, rows: np.ndarray, cols: np.ndarray,
              reference: np.ndarray | None) -> np.ndarray:
    """Context of every cell of a phase, row-major: ``(len(rows) * len(cols),)`` int64."""
    h, w = m.shape
    kind = KINDS[(kind_table - 1) // LEVELS]
    digits, inside, refs = [], [], []
    for dr, dc in _OFFSETS[kind](s):
        rr, cc = rows + dr, cols + dc
        r_ok, c_ok = (rr >= 0) & (rr < h), (cc >= 0) & (cc < w)
        ix = np.ix_(np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1))
        digits.append(m[ix].astype(np.int64))
        inside.append(r_ok[:, None] & c_ok[None, :])
        if reference is not None:
            refs.append(reference[ix].astype(np.int64))
    ctx = np.zeros((rows.size, cols.size), dtype=np.int64)
    for i, j in enumerate(_OPPOSITE[kind]):
        # outside the map: mirror the opposite neighbour (known too), else a fourth value
        vals = np.where(inside[i], digits[i], np.where(inside[j], digits[j], _OUTSIDE))
        ctx = ctx * 4 + vals
    if reference is not None:
        # where the receiver's map knows the cell: its class and how many neighbours
        # changed; where it does not: the neighbours, as without a reference
        here = reference[np.ix_(rows, cols)].astype(np.int64)
        changed = sum(((d != r) & ok).astype(np.int64) for d, r, ok in zip(digits, refs, inside))
        ctx = np.where(here == UNKNOWN, _REF_KNOWN + ctx, here * 5 + changed)
    return ctx.ravel()


class _Model:
    """Adaptive counts per (table, context); the same arithmetic on both ends."""

    def __init__(self, with_reference: bool) -> None:
        n_ctx = _REF_KNOWN + N_CTX if with_reference else N_CTX
        self.counts = np.zeros((1 + len(KINDS) * LEVELS, n_ctx, N_CLASSES), dtype=np.int64)
        self.family = constriction.stream.model.Categorical(perfect=False)

    def probabilities(self, table: int, ctx: np.ndarray) -> np.ndarray:
        c = self.counts[table, ctx].astype(np.float64) + ALPHA  # (n, 3)
        return c / c.sum(axis=1, keepdims=True)

    def update(self, table: int, ctx: np.ndarray, symbols: np.ndarray) -> None:
        np.add.at(self.counts[table], (ctx, symbols), 1)


def context_rounds(ctx: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The coding order of a phase: ``(order, rounds)``.

    Cells are grouped by context (raster order within a group). The k-th cell of a group
    is coded in round ``k.bit_length()`` (rounds of 1, 1, 2, 4, 8, ... cells per group),
    with the counts as they were after the previous round: every context learns from its
    first cells, and a round of all groups is one vectorised call. ``order`` sorts the
    phase's cells into groups; ``rounds[r]`` indexes ``order`` for round ``r``.
    """
    order = np.argsort(ctx, kind="stable")
    c = ctx[order]
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    k = np.arange(c.size) - np.repeat(starts, np.diff(np.r_[starts, c.size]))
    rnd = np.frexp(k.astype(np.float64))[1].astype(np.int64)  # k.bit_length(), exact for k < 2**53
    return order, [np.flatnonzero(rnd == r) for r in range(int(rnd.max()) + 1)]


def _read_varint(buf: bytes, off: int, end: int) -> tuple[int, int]:
    n = shift = 0
    while off < end and shift < 35:
        b = buf[off]
        off += 1
        n |= (b & 0x7F) << shift
        if not b & 0x80:
            return n, off
        shift += 7
    raise RejectedUpdate("malformed map payload: its window is cut short")


def changed_window(m: np.ndarray, reference: np.ndarray | None) -> tuple[int, int, int, int]:
    """``(top, left, height, width)`` of the smallest rectangle holding every cell of ``m``
    that differs from the background (``reference``, or UNKNOWN); height 0 when none does."""
    diff = m != (UNKNOWN if reference is None else reference)
    rows, cols = np.flatnonzero(diff.any(axis=1)), np.flatnonzero(diff.any(axis=0))
    if rows.size == 0:
        return 0, 0, 0, 0
    return int(rows[0]), int(cols[0]), int(rows[-1] - rows[0] + 1), int(cols[-1] - cols[0] + 1)


def _encode_body(m: np.ndarray, ref: np.ndarray | None) -> bytes:
    h, w = m.shape
    model = _Model(ref is not None)
    enc = constriction.stream.queue.RangeEncoder()
    root_ctx = np.zeros(1, dtype=np.int64) if ref is None else ref[:1, 0].astype(np.int64)
    enc.encode(m[:1, 0].astype(np.int32), model.family, model.probabilities(0, root_ctx))
    for table, s, rows, cols in phases(h, w):
        ctx = contexts(m, table, s, rows, cols, ref)
        sym = m[np.ix_(rows, cols)].ravel().astype(np.int64)
        order, rounds = context_rounds(ctx)
        ctx, sym = ctx[order], sym[order]
        for part in rounds:
            enc.encode(sym[part].astype(np.int32), model.family, model.probabilities(table, ctx[part]))
            model.update(table, ctx[part], sym[part])
    return enc.get_compressed().astype("<u4").tobytes()


def encode_map(classes: np.ndarray, *, reference: np.ndarray | None = None, window: bool = True) -> bytes:
    """Code a class map losslessly; with ``reference`` (same shape) the decoder needs it too.
    Only the window that differs from the background is coded (see the module's docstring);
    ``window=False`` codes the whole grid (the ablation ``benchmarks/codec_window.py`` measures:
    the same map, decoded the same way)."""
    m = _check_classes(classes, "map")
    ref = None if reference is None else _check_classes(reference, "reference map")
    if ref is not None and ref.shape != m.shape:
        raise FedmapError(f"reference map is {ref.shape[0]}x{ref.shape[1]}, the map is {m.shape[0]}x{m.shape[1]}")
    h, w = m.shape
    flags = _F_REFERENCE if ref is not None else 0
    top, left, wh, ww = changed_window(m, ref) if window else (0, 0, h, w)
    place = b""
    if (wh, ww) != (h, w):  # a window: the rest of the grid is the background
        flags |= _F_WINDOW
        place = b"".join(varint(v) for v in (top, left, wh, ww))
    if wh == 0:
        body = b""
    else:
        sl = np.s_[top:top + wh, left:left + ww]
        body = _encode_body(np.ascontiguousarray(m[sl]), None if ref is None else np.ascontiguousarray(ref[sl]))
    head = _HEADER.pack(MAGIC, VERSION, flags, h, w, _map_crc(m)) + place
    return head + body + struct.pack("<I", zlib.crc32(head + body))


def decode_map(data: bytes, *, reference: np.ndarray | None = None,
               expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """The ``(H, W)`` uint8 class map of a :func:`encode_map` payload.

    ``expected_shape``: refuse, before decoding, a payload that declares another shape
    (a receiver that knows the global grid should pass it)."""
    buf = bytes(data)
    if len(buf) < _HEADER.size + _CRC:
        raise RejectedUpdate(f"malformed map payload: {len(buf)} bytes is shorter than the header")
    magic, version, flags, h, w, map_crc = _HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise RejectedUpdate("malformed map payload: bad magic (not a fedmap map payload)")
    if version not in READS:
        raise RejectedUpdate(f"malformed map payload: format version {version}, this fedmap reads versions "
                             f"{', '.join(map(str, READS))}")
    (crc,) = struct.unpack("<I", buf[-_CRC:])
    if zlib.crc32(buf[:-_CRC]) != crc:
        raise RejectedUpdate(f"malformed map payload: CRC mismatch ({len(buf)} bytes; truncated or corrupted)")
    known = _F_REFERENCE | (_F_WINDOW if version >= 2 else 0)
    if flags & ~known or h == 0 or w == 0 or h * w > MAX_CELLS:
        raise RejectedUpdate(f"malformed map payload: bad header (flags {flags:#x}, {h}x{w})")
    if expected_shape is not None and (h, w) != tuple(expected_shape):
        raise RejectedUpdate(f"malformed map payload: a {h}x{w} map, expected {expected_shape[0]}x{expected_shape[1]}")
    off, end = _HEADER.size, len(buf) - _CRC
    top, left, wh, ww = 0, 0, h, w
    if flags & _F_WINDOW:
        fields = []
        for _ in range(4):
            v, off = _read_varint(buf, off, end)
            fields.append(v)
        top, left, wh, ww = fields
        if top + wh > h or left + ww > w or (wh == 0) != (ww == 0) or (wh, ww) == (h, w):
            raise RejectedUpdate(f"malformed map payload: bad window ({wh}x{ww} at {top},{left} of {h}x{w})")
    if (end - off) % 4 or (wh == 0) != (end == off):
        raise RejectedUpdate(f"malformed map payload: bad header (flags {flags:#x}, {h}x{w})")
    ref = None
    if flags & _F_REFERENCE:
        if reference is None:
            raise RejectedUpdate("malformed map payload: it was coded against a reference map; pass the same "
                                 "reference")
        ref = _check_classes(reference, "reference map")
        if ref.shape != (h, w):
            raise RejectedUpdate(f"malformed map payload: it is {h}x{w}, the reference is {ref.shape[0]}x{ref.shape[1]}")
    words = np.frombuffer(buf[off:end], dtype="<u4").astype(np.uint32)
    m = np.full((h, w), UNKNOWN, dtype=np.uint8) if ref is None else ref.astype(np.uint8, copy=True)
    try:
        if wh:
            sl = np.s_[top:top + wh, left:left + ww]
            m[sl] = _decode_body(words, wh, ww, None if ref is None else np.ascontiguousarray(ref[sl]))
    except (AssertionError, ValueError, RuntimeError) as e:  # constriction: data invalid for the model
        what = "the reference map differs from the encoder's" if ref is not None else "the data does not decode"
        raise RejectedUpdate(f"malformed map payload: {what} ({' '.join(str(e).split())})") from None
    if _map_crc(m) != map_crc:
        what = "the reference map differs from the encoder's" if ref is not None else "the decoded map fails its CRC"
        raise RejectedUpdate(f"malformed map payload: {what}")
    return m


def _decode_body(words: np.ndarray, h: int, w: int, ref: np.ndarray | None) -> np.ndarray:
    model = _Model(ref is not None)
    dec = constriction.stream.queue.RangeDecoder(words)
    m = np.zeros((h, w), dtype=np.uint8)
    root_ctx = np.zeros(1, dtype=np.int64) if ref is None else ref[:1, 0].astype(np.int64)
    m[0, 0] = dec.decode(model.family, model.probabilities(0, root_ctx))[0]
    for table, s, rows, cols in phases(h, w):
        ctx = contexts(m, table, s, rows, cols, ref)
        order, rounds = context_rounds(ctx)
        ctx = ctx[order]
        sym = np.empty(ctx.size, dtype=np.int64)
        for part in rounds:
            sym[part] = dec.decode(model.family, model.probabilities(table, ctx[part]))
            model.update(table, ctx[part], sym[part])
        phase = np.empty(ctx.size, dtype=np.int64)
        phase[order] = sym
        m[np.ix_(rows, cols)] = phase.reshape(rows.size, cols.size)
    return m
