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

Payload: ``b"FMCM"``, format version, flags (bit 0: coded against a reference), height,
width and a CRC-32 of the map's class bytes (uint32 little-endian), the range coder's
32-bit words, and a CRC-32 of everything before it. The first CRC catches a decode that
went wrong for any reason, e.g. a reference other than the encoder's. A payload that fails any check raises
:class:`~fedmap.errors.RejectedUpdate` (``malformed map payload: ...``).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator

import constriction
import numpy as np

from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import UNKNOWN, check_classes

MAGIC = b"FMCM"
VERSION = 1
_F_REFERENCE = 1
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


def encode_map(classes: np.ndarray, *, reference: np.ndarray | None = None) -> bytes:
    """Code a class map losslessly; with ``reference`` (same shape) the decoder needs it too."""
    m = _check_classes(classes, "map")
    ref = None if reference is None else _check_classes(reference, "reference map")
    if ref is not None and ref.shape != m.shape:
        raise FedmapError(f"reference map is {ref.shape[0]}x{ref.shape[1]}, the map is {m.shape[0]}x{m.shape[1]}")
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
    body = enc.get_compressed().astype("<u4").tobytes()
    head = _HEADER.pack(MAGIC, VERSION, _F_REFERENCE if ref is not None else 0, h, w, _map_crc(m))
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
    if version != VERSION:
        raise RejectedUpdate(f"malformed map payload: format version {version}, this fedmap reads version {VERSION}")
    (crc,) = struct.unpack("<I", buf[-_CRC:])
    if zlib.crc32(buf[:-_CRC]) != crc:
        raise RejectedUpdate(f"malformed map payload: CRC mismatch ({len(buf)} bytes; truncated or corrupted)")
    if flags & ~_F_REFERENCE or h == 0 or w == 0 or h * w > MAX_CELLS or (len(buf) - _HEADER.size - _CRC) % 4:
        raise RejectedUpdate(f"malformed map payload: bad header (flags {flags:#x}, {h}x{w})")
    if expected_shape is not None and (h, w) != tuple(expected_shape):
        raise RejectedUpdate(f"malformed map payload: a {h}x{w} map, expected {expected_shape[0]}x{expected_shape[1]}")
    ref = None
    if flags & _F_REFERENCE:
        if reference is None:
            raise RejectedUpdate("malformed map payload: it was coded against a reference map; pass the same "
                                 "reference")
        ref = _check_classes(reference, "reference map")
        if ref.shape != (h, w):
            raise RejectedUpdate(f"malformed map payload: it is {h}x{w}, the reference is {ref.shape[0]}x{ref.shape[1]}")
    words = np.frombuffer(buf[_HEADER.size:-_CRC], dtype="<u4").astype(np.uint32)
    try:
        m = _decode_body(words, h, w, ref)
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
