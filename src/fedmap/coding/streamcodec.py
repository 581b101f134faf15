"""``predictive``: lossless messages of newly observed cells, coded with a probability
model that both ends of a link keep, message after message.

The ``context`` codec (:mod:`fedmap.coding.mapcodec`) starts every message from
nothing: its counts, its headers, and the mask of *which* cells are new. Here:

* **The model persists.** Each direction of each link has a :class:`CoderState`: the
  counts of the cell model (the ``context`` codec's contexts), of trail moves and of
  marks. A message is coded with the state both ends hold; the sender folds the
  message's counts into its state when it learns the message was delivered, the receiver
  when it decodes it, so a lost message never desynchronises them (counts add, so the
  order of folding does not matter). Each message names the state it was coded with
  (:attr:`CoderState.seq`, one byte); a receiver holding another state rejects it.
* **It starts learned.** :func:`initial_state` starts from counts learned offline on the
  Earth-like map collections of the meta-initialisation (never on a test site), shipped
  in ``fedmap/weights/cell_prior.npz``; :func:`fedmap.training.coderprior.learn_coder_prior`
  retrains them (``fedmap meta-coder``).
* **The mask is derived where it can be.** A message carries *tracks* (positions, each an
  8-neighbour step from the previous, coded as moves in context of the previous move),
  and the cells it may carry (the *candidates*) are derived by the caller from the
  tracks (e.g. every cell within sensor range of a new position that the receiver does
  not hold). Only candidate cells are coded: each as FREE, IMPASSABLE or "not carried"
  (UNKNOWN), predicted from its four neighbours at distance ``s`` in the map the receiver
  already holds plus the cells decoded so far (coarse to fine, as ``context``). Without
  line of sight every candidate is carried, and "not carried" soon costs almost nothing.
  Cells outside the candidates are allowed too (one flag, then coded in their own
  contexts), so the format never depends on the caller's derivation being complete.
* **Headers are bits, not bytes.** Everything after the state byte goes through one
  range coder: counts with Elias-gamma lengths, marks (a cell such as a target: "same
  as last acknowledged", "none", or a new cell at ``log2(H W)`` bits), moves, cells.

* **A guess can join the context** (optional, ``guess=``): a probability of IMPASSABLE for
  every cell, computed by both ends from what both already hold before the message (in
  fedmap, the map predictor's P(impassable) on the receiver's map,
  :mod:`fedmap.nets.predictor`). It enters in one of two ways, set by the state
  (:func:`guessing_state`):

  - **mix** (a state without ``binned`` counts): logistic mixing of the carried cells'
    split. The count model's P(IMPASSABLE | carried) and the guess are mixed as
    ``sigmoid(a logit(p) + b logit(guess) + c)`` with fixed weights per level
    (:data:`MIX`); P(not carried) stays the count model's. Nothing new is learned, so the
    state's counts are those of a coder without the guess.
  - **bins** (a state with ``binned`` counts): the guess, quantised into
    ``len(GUESS_EDGES) + 1`` bins, is one more context digit: every (table, context) has
    its own counts per bin, all starting from the counts of the state they were made
    from, and learning apart.

  The guess is first quantised to the centres of :data:`GUESS_STEPS` equal steps, so two
  ends whose guesses differ in the last bits (float32 arithmetic on another CPU) almost
  always still agree. Otherwise both ends must pass the same guess (the same input map and
  a deterministic computation): a decoder with another guess decodes other cells, and the
  check byte rejects the message (all but one time in 256).

Layout: ``seq & 0xFF`` (1 byte), the range coder's 32-bit words (big-endian, trailing
zero bytes dropped; the decoder pads them back), and one check byte (CRC-32 of the
decoded content, low byte) that catches a decode against the wrong state or map.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from importlib import resources

import constriction
import numpy as np

from fedmap.coding.mapcodec import KINDS, LEVELS, N_CLASSES, N_CTX, context_rounds, contexts, phases
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import UNKNOWN

Cell = tuple[int, int]
#: Contexts per table: 256 neighbour contexts, in candidates (0) or outside them (1).
N_FEATURES = 2
N_TABLES = 1 + len(KINDS) * LEVELS
#: The 8 moves between neighbouring cells, and the "no previous move" context.
MOVES: tuple[Cell, ...] = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
_MOVE_INDEX = {m: i for i, m in enumerate(MOVES)}
_NO_MOVE = len(MOVES)
#: Mark symbols: the same cell as the reference, no cell, a new cell.
SAME, NONE, NEW = 0, 1, 2
_MAX_LEN_BITS = 24  # Elias-gamma lengths (counts up to 2**24 - 1)
#: Additive prior on every count (as the ``context`` codec).
ALPHA = 0.25
#: The fewest bytes of a message: its state byte and its check byte (the words may all drop).
LEAST_BYTES = 2
#: A context's counts are halved when its total passes this (both ends, at folding), so the
#: model keeps adapting to the site instead of freezing.
COUNT_LIMIT = 1 << 12
PRIOR_FILE = "cell_prior.npz"
#: The count arrays of a :class:`CoderState` (and of a :class:`Fold`), as the prior file names them.
PARTS: tuple[str, ...] = ("cells", "moves", "lengths", "marks")
#: Upper edges of the guess bins (P(impassable)) of a ``bins`` state: 7 bins.
GUESS_EDGES = np.array([0.05, 0.1, 0.2, 0.4, 0.6, 0.8])
N_BINS = GUESS_EDGES.size + 1
#: A guess is used quantised to the centres of this many equal steps of [0, 1].
GUESS_STEPS = 64
#: ``mix``: per level (s = 1, s = 2, s >= 4; cell (0, 0) is not mixed) the weights ``(a, b,
#: c)`` of ``sigmoid(a logit(p) + b logit(guess) + c)``, p the count model's P(IMPASSABLE |
#: carried). Fitted (logistic regression, rounded) on the default mission's uplink cells
#: only (built-in mars); ``benchmarks/predictor_coding.py`` measures them elsewhere. Next to
#: its four neighbours a guess made before the message adds nothing at s = 1.
MIX: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.85, 0.15, 0.0), (0.45, 0.45, -0.25))
_CLIP = 1e-4  # probabilities are clipped to [_CLIP, 1 - _CLIP] before a logit


@dataclass
class CoderState:
    """The model of one direction of one link; both ends hold an identical copy.

    ``cells``: (table, feature x 256 contexts, 3 classes) counts; ``moves``: (previous
    move or none, move) counts; ``lengths``: counts of Elias-gamma length prefixes;
    ``marks``: counts of SAME / NONE / NEW. ``seq`` counts the messages folded in."""

    cells: np.ndarray
    moves: np.ndarray
    lengths: np.ndarray
    marks: np.ndarray
    seq: int = 0
    #: a ``bins`` state's cell counts per guess bin: (table, feature x 256 contexts x bin, 3
    #: classes); None: a guess, if given, is mixed (see the module notes)
    binned: np.ndarray | None = None

    def copy(self) -> CoderState:
        return replace(self, **{n: getattr(self, n).copy() for n in PARTS},
                       binned=None if self.binned is None else self.binned.copy())

    def fold(self, delta: Fold) -> None:
        """Add an acknowledged message's counts (both ends, once per delivered message)."""
        for name in PARTS:
            a = getattr(self, name)
            a += getattr(delta, name)
            _halve(a, COUNT_LIMIT)
        if self.binned is not None and delta.binned is not None:
            self.binned += delta.binned
            _halve(self.binned, COUNT_LIMIT)
        self.seq += 1

    def same_as(self, other: CoderState) -> bool:
        if (self.binned is None) != (other.binned is None):
            return False
        if self.binned is not None and other.binned is not None and not np.array_equal(self.binned, other.binned):
            return False
        return self.seq == other.seq and all(np.array_equal(getattr(self, n), getattr(other, n)) for n in PARTS)


def guessing_state(state: CoderState, mode: str) -> CoderState:
    """A copy of ``state`` that takes a guess as ``mode``: ``mix`` (the same counts) or
    ``bins`` (every context's cell counts copied into each guess bin)."""
    if mode not in ("mix", "bins"):
        raise FedmapError(f"a guess enters the coder by mix or bins, not {mode!r}")
    out = replace(state.copy(), binned=None)
    if mode == "bins":
        out.binned = np.repeat(state.cells, N_BINS, axis=1)
    return out


def _halve(a: np.ndarray, limit: int) -> None:
    """Halve (rounding up) every context (last axis) whose total passes ``limit``."""
    total = a.sum(axis=-1, keepdims=True)
    big = np.broadcast_to(total > limit, a.shape)
    a[big] = (a[big] + 1) // 2


@dataclass
class Fold:
    """A message's counts, to fold into both ends' states once it is delivered."""

    cells: np.ndarray
    moves: np.ndarray
    lengths: np.ndarray
    marks: np.ndarray
    binned: np.ndarray | None = None

    @classmethod
    def empty(cls, binned: bool = False) -> Fold:
        return cls(np.zeros((N_TABLES, N_FEATURES * N_CTX, N_CLASSES), np.int64),
                   np.zeros((_NO_MOVE + 1, len(MOVES)), np.int64), np.zeros(_MAX_LEN_BITS + 1, np.int64),
                   np.zeros(3, np.int64),
                   np.zeros((N_TABLES, N_FEATURES * N_CTX * N_BINS, N_CLASSES), np.int64) if binned else None)


def blank_state() -> CoderState:
    """A state with no counts (every probability from the prior ``ALPHA``)."""
    f = Fold.empty()
    return CoderState(f.cells, f.moves, f.lengths, f.marks)


def initial_state() -> CoderState:
    """The shipped learned initial state (:func:`fedmap.training.coderprior.learn_coder_prior`), or a
    blank one without it."""
    path = resources.files("fedmap.weights").joinpath(PRIOR_FILE)
    if not path.is_file():
        return blank_state()
    with path.open("rb") as f, np.load(f) as z:
        s = CoderState(*(z[n].astype(np.int64) for n in PARTS))
    b = blank_state()
    if any(getattr(s, n).shape != getattr(b, n).shape for n in PARTS):
        raise FedmapError(f"{PRIOR_FILE} does not match this fedmap's coder (reinstall fedmap)")
    return s


@dataclass
class Content:
    """What one message carries.

    ``tracks``: per track, the new positions (each an 8-neighbour step from the previous
    position, the track's anchor); ``marks``: cells or None (e.g. targets), each coded
    against a reference cell the receiver already holds; ``cells``: (H, W) classes,
    UNKNOWN where the message carries nothing."""

    tracks: list[list[Cell]]
    marks: list[Cell | None]
    cells: np.ndarray
    fold: Fold = field(default_factory=Fold.empty)


# -- the symmetric walk: one description of the format for both ends -------------------
class _Io:
    """Encoder or decoder behind one call: ``sym(values or None, probabilities)``."""

    def __init__(self, words: np.ndarray | None = None) -> None:
        self.enc = constriction.stream.queue.RangeEncoder() if words is None else None
        self.dec = None if words is None else constriction.stream.queue.RangeDecoder(words)
        self.cat = constriction.stream.model.Categorical(perfect=False)
        self.uni = constriction.stream.model.Uniform()

    def sym(self, values: np.ndarray | None, probs: np.ndarray) -> np.ndarray:
        if self.enc is not None:
            assert values is not None
            self.enc.encode(np.asarray(values, dtype=np.int32), self.cat, probs)
            return np.asarray(values, dtype=np.int64)
        assert self.dec is not None
        return np.asarray(self.dec.decode(self.cat, probs), dtype=np.int64)

    def uniform(self, value: int | None, size: int) -> int:
        if size < 2:
            return 0
        sizes = np.array([size], dtype=np.int32)
        if self.enc is not None:
            assert value is not None
            self.enc.encode(np.array([value], dtype=np.int32), self.uni, sizes)
            return int(value)
        assert self.dec is not None
        return int(self.dec.decode(self.uni, sizes)[0])


def _p(counts: np.ndarray) -> np.ndarray:
    c = counts.astype(np.float64) + ALPHA
    return c / c.sum(axis=-1, keepdims=True)


def _count(io: _Io, value: int | None, state: CoderState, fold: Fold) -> int:
    """A non-negative integer: its bit length (adaptive), then the bits below the top one."""
    n_bits = None if value is None else int(value).bit_length()
    if n_bits is not None and n_bits > _MAX_LEN_BITS:
        raise FedmapError(f"a count of {value} is too large for a message")
    counts = state.lengths + fold.lengths
    n_bits = int(io.sym(None if n_bits is None else np.array([n_bits]), _p(counts)[None, :])[0])
    fold.lengths[n_bits] += 1
    if n_bits <= 1:
        return n_bits
    low = io.uniform(None if value is None else value - (1 << (n_bits - 1)), 1 << (n_bits - 1))
    return (1 << (n_bits - 1)) + low


def _mark(io: _Io, value: Cell | None | str, reference: Cell | None, shape: tuple[int, int],
          state: CoderState, fold: Fold) -> Cell | None:
    """A cell or None, against a ``reference`` the receiver holds (``value`` "?" to decode)."""
    decoding = isinstance(value, str)
    kind = None if decoding else (SAME if value == reference else NONE if value is None else NEW)
    kind = int(io.sym(None if kind is None else np.array([kind]), _p(state.marks + fold.marks)[None, :])[0])
    fold.marks[kind] += 1
    if kind == SAME:
        return reference
    if kind == NONE:
        return None
    v = value if isinstance(value, tuple) else None
    r = io.uniform(None if v is None else v[0], shape[0])
    c = io.uniform(None if v is None else v[1], shape[1])
    return (r, c)


def _track(io: _Io, positions: Sequence[Cell] | None, anchor: Cell, shape: tuple[int, int], state: CoderState,
           fold: Fold) -> list[Cell]:
    moves = None
    if positions is not None:
        moves, prev = [], anchor
        for cell in positions:
            step = (cell[0] - prev[0], cell[1] - prev[1])
            if step not in _MOVE_INDEX:
                raise FedmapError(f"a track steps from {prev} to {cell}: tracks move between neighbouring cells")
            moves.append(_MOVE_INDEX[step])
            prev = cell
    n = _count(io, None if moves is None else len(moves), state, fold)
    if n > shape[0] * shape[1]:
        raise FedmapError(f"a track of {n} moves on a {shape[0]}x{shape[1]} map")
    out, prev_move, pos = [], _NO_MOVE, anchor
    for i in range(n):
        probs = _p(state.moves[prev_move] + fold.moves[prev_move])[None, :]
        m = int(io.sym(None if moves is None else np.array([moves[i]]), probs)[0])
        fold.moves[prev_move, m] += 1
        prev_move = m
        pos = (pos[0] + MOVES[m][0], pos[1] + MOVES[m][1])
        if not (0 <= pos[0] < shape[0] and 0 <= pos[1] < shape[1]):
            raise FedmapError(f"a track leaves the map at {pos}")
        out.append(pos)
    return out


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, _CLIP, 1.0 - _CLIP)
    return np.log(p) - np.log1p(-p)


@dataclass(frozen=True)
class CellSymbols:
    """Cells a coder has just coded, as an observer sees them (:func:`observe_cells`)."""

    encoding: bool  #: an encoder (else a decoder, which codes the same symbols)
    anchors: int  #: the trails the message carries (1: a rover's uplink; more: a downlink)
    level: int  #: the scale level of the cells' context table (0: s=1, 1: s=2, 2: s>=4)
    probs: np.ndarray  #: ``(n, 3)`` the probabilities they were coded with
    symbols: np.ndarray  #: ``(n,)`` their classes (or UNKNOWN's symbol)
    #: with a guess mixed in: the count model's own probabilities before mixing, and the guess
    counts: np.ndarray | None = None
    guess: np.ndarray | None = None

    def bits(self) -> float:
        """The ideal bits of these symbols under ``probs``."""
        p = np.asarray(self.probs, dtype=np.float64)
        return float(-np.log2(p[np.arange(self.symbols.size), self.symbols]).sum())


#: Who is told of every batch of cells coded (:func:`observe_cells`).
_OBSERVERS: list[Callable[[CellSymbols], None]] = []


@contextmanager
def observe_cells(observer: Callable[[CellSymbols], None]) -> Iterator[None]:
    """Tell ``observer`` of every batch of cells any coder of this process codes while the
    ``with`` block runs (:class:`CellSymbols`): an ablation's or a benchmark's view of the
    coder, without changing what it codes."""
    _OBSERVERS.append(observer)
    try:
        yield
    finally:
        _OBSERVERS.remove(observer)


def _tell(io: _Io, anchors: int, table: int, probs: np.ndarray, symbols: np.ndarray,
          counts: np.ndarray | None = None, guess: np.ndarray | None = None) -> None:
    seen = CellSymbols(io.enc is not None, anchors, (table - 1) % LEVELS, probs, symbols, counts, guess)
    for observer in list(_OBSERVERS):
        observer(seen)


def _mixed(probs: np.ndarray, guess: np.ndarray, table: int) -> np.ndarray:
    """``probs`` (n, 3) with the carried cells' split mixed with ``guess`` (n,) (:data:`MIX`)."""
    a, b, c = MIX[(table - 1) % LEVELS]
    if b == 0.0 and c == 0.0 and a == 1.0:
        return probs
    carried = probs[:, 0] + probs[:, 1]
    z = a * _logit(probs[:, 1] / carried) + b * _logit(guess) + c
    imp = carried / (1.0 + np.exp(-z))
    out = np.empty_like(probs)
    out[:, 0], out[:, 1], out[:, 2] = carried - imp, imp, probs[:, 2]
    return out


def _cells(io: _Io, cells: np.ndarray | None, known: np.ndarray, todo: np.ndarray, feature: int,
           state: CoderState, fold: Fold, guess: np.ndarray | None = None, anchors: int = 0) -> None:
    """Code the classes of the ``todo`` cells (a class or UNKNOWN each) into ``known`` in place;
    with a ``guess`` (P(IMPASSABLE) of every cell, float64) as the state says (mix or bins)."""
    h, w = known.shape
    binned, fold_binned = state.binned, fold.binned
    if guess is not None and binned is not None:
        assert fold_binned is not None
        digit = np.searchsorted(GUESS_EDGES, guess, side="right")
    if todo[0, 0]:
        p = _p(state.cells[0, feature * N_CTX] + fold.cells[0, feature * N_CTX])[None, :]
        v = int(io.sym(None if cells is None else np.array([cells[0, 0]]), p)[0])
        if _OBSERVERS:
            _tell(io, anchors, 0, p, np.array([v]))
        fold.cells[0, feature * N_CTX, v] += 1
        known[0, 0] = v
    for table, s, rows, cols in phases(h, w):
        sub = todo[np.ix_(rows, cols)].ravel()
        if not sub.any():
            continue
        ctx = contexts(known, table, s, rows, cols, None)[sub] + feature * N_CTX
        rr = np.repeat(rows, cols.size)[sub]
        cc = np.tile(cols, rows.size)[sub]
        order, rounds = context_rounds(ctx)
        ctx, rr, cc = ctx[order], rr[order], cc[order]
        truth = None if cells is None else cells[rr, cc].astype(np.int64)
        sym = np.empty(ctx.size, dtype=np.int64)
        if guess is None:
            for part in rounds:
                probs = _p(state.cells[table, ctx[part]] + fold.cells[table, ctx[part]])
                sym[part] = io.sym(None if truth is None else truth[part], probs)
                if _OBSERVERS:
                    _tell(io, anchors, table, probs, sym[part])
                np.add.at(fold.cells[table], (ctx[part], sym[part]), 1)
        elif binned is not None and fold_binned is not None:
            # the same grouping by neighbour context (rounds), each cell's own bin
            bctx = ctx * N_BINS + digit[rr, cc]
            for part in rounds:
                probs = _p(binned[table, bctx[part]] + fold_binned[table, bctx[part]])
                sym[part] = io.sym(None if truth is None else truth[part], probs)
                if _OBSERVERS:
                    _tell(io, anchors, table, probs, sym[part])
                np.add.at(fold_binned[table], (bctx[part], sym[part]), 1)
                np.add.at(fold.cells[table], (ctx[part], sym[part]), 1)
        else:
            g = guess[rr, cc]
            for part in rounds:
                counts = _p(state.cells[table, ctx[part]] + fold.cells[table, ctx[part]])
                probs = _mixed(counts, g[part], table)
                sym[part] = io.sym(None if truth is None else truth[part], probs)
                if _OBSERVERS:
                    _tell(io, anchors, table, probs, sym[part], counts, g[part])
                np.add.at(fold.cells[table], (ctx[part], sym[part]), 1)
        known[rr, cc] = sym


def quantised_guess(guess: np.ndarray) -> np.ndarray:
    """``guess`` (probabilities) as the coder uses it: the centre of its step of
    :data:`GUESS_STEPS`, float64."""
    g = np.clip(np.asarray(guess, dtype=np.float64), 0.0, 1.0)
    return (np.minimum(np.floor(g * GUESS_STEPS), GUESS_STEPS - 1) + 0.5) / GUESS_STEPS


def _walk(io: _Io, content: Content | None, *, anchors: Sequence[Cell], mark_refs: Sequence[Cell | None],
          known: np.ndarray, candidates: Callable[[list[list[Cell]]], np.ndarray], state: CoderState,
          guess: np.ndarray | None = None) -> Content:
    if guess is not None:
        guess = quantised_guess(guess)
        if guess.shape != known.shape:
            raise FedmapError(f"a guess of shape {guess.shape} for a {known.shape[0]}x{known.shape[1]} map")
    elif state.binned is not None:
        raise FedmapError("a coder state with guess bins codes only with a guess")
    fold = Fold.empty(binned=guess is not None and state.binned is not None)
    tracks = [_track(io, None if content is None else content.tracks[i], a, known.shape, state, fold)
              for i, a in enumerate(anchors)]
    marks = [_mark(io, "?" if content is None else content.marks[i], ref, known.shape, state, fold)
             for i, ref in enumerate(mark_refs)]
    cand = np.asarray(candidates(tracks), dtype=bool) & (known == UNKNOWN)
    held = known.copy()
    cells = None if content is None else content.cells
    if cells is not None:
        carried = cells != UNKNOWN
        if (carried & (known != UNKNOWN)).any():
            raise FedmapError("a message would carry cells the receiver already holds")
    _cells(io, cells, held, cand, 0, state, fold, guess, len(anchors))
    outside = None if cells is None else int((carried & ~cand).any())
    if io.uniform(outside, 2):
        _cells(io, cells, held, (held == UNKNOWN) & ~cand, 1, state, fold, guess, len(anchors))
    out = np.where(known == UNKNOWN, held, UNKNOWN).astype(np.uint8)
    return Content(tracks, marks, out, fold)


def _check(content: Content, seq: int) -> int:
    h = zlib.crc32(content.cells.tobytes(), seq & 0xFF)
    h = zlib.crc32(np.asarray([p for t in content.tracks for p in t] or [(0, 0)], dtype=np.int32).tobytes(), h)
    h = zlib.crc32(np.asarray([m if m is not None else (-1, -1) for m in content.marks] or [(0, 0)],
                              dtype=np.int32).tobytes(), h)
    return h & 0xFF


def encode(content: Content, *, state: CoderState, anchors: Sequence[Cell], mark_refs: Sequence[Cell | None],
           known: np.ndarray, candidates: Callable[[list[list[Cell]]], np.ndarray],
           guess: np.ndarray | None = None) -> tuple[bytes, Fold]:
    """Code ``content`` for a receiver that holds ``known`` (classes) and ``state``.

    ``anchors``: each track's previous position (the receiver holds it); ``mark_refs``: each
    mark's reference cell; ``candidates(tracks)``: the boolean map of cells the message may
    carry, derived from the tracks (both ends call it); ``guess``: optionally, P(IMPASSABLE) of
    every cell, which the receiver computes alike from what it holds before the message
    (see the module notes). Returns the payload and the counts to :meth:`CoderState.fold`
    into the sender's state when it is delivered."""
    if len(content.tracks) != len(anchors) or len(content.marks) != len(mark_refs):
        raise FedmapError("a message's tracks and marks must match its anchors and references")
    if content.cells.shape != known.shape:
        raise FedmapError(f"a message's cells are {content.cells.shape}, the map is {known.shape}")
    io = _Io()
    done = _walk(io, content, anchors=anchors, mark_refs=mark_refs, known=known, candidates=candidates, state=state,
                 guess=guess)
    assert io.enc is not None
    raw = io.enc.get_compressed().astype(">u4").tobytes().rstrip(b"\0")
    return bytes([state.seq & 0xFF]) + raw + bytes([_check(done, state.seq)]), done.fold


def decode(payload: bytes, *, state: CoderState, anchors: Sequence[Cell], mark_refs: Sequence[Cell | None],
           known: np.ndarray, candidates: Callable[[list[list[Cell]]], np.ndarray],
           guess: np.ndarray | None = None) -> Content:
    """The :class:`Content` of an :func:`encode` payload, for the receiver's ``state`` and
    ``known`` map (and the same ``guess`` as the sender's); raises
    :class:`~fedmap.errors.RejectedUpdate` (one line) when the payload does not decode against them."""
    buf = bytes(payload)
    if len(buf) < 2:
        raise RejectedUpdate(f"malformed cell message: {len(buf)} bytes is shorter than its two framing bytes")
    if buf[0] != state.seq & 0xFF:
        raise RejectedUpdate(f"malformed cell message: coded with coder state {buf[0]}, the receiver holds "
                             f"{state.seq & 0xFF}")
    body = buf[1:-1]
    body += b"\0" * (-len(body) % 4)
    words = np.frombuffer(body, dtype=">u4").astype(np.uint32)
    if words.size == 0:
        words = np.zeros(1, dtype=np.uint32)
    try:
        done = _walk(_Io(words), None, anchors=anchors, mark_refs=mark_refs, known=known, candidates=candidates,
                     state=state, guess=guess)
    except (AssertionError, ValueError, RuntimeError, IndexError, FedmapError) as e:
        raise RejectedUpdate(f"malformed cell message: it does not decode ({' '.join(str(e).split())})") from None
    if _check(done, state.seq) != buf[-1]:
        raise RejectedUpdate("malformed cell message: check byte mismatch (another state or map than the sender's)")
    return done
