"""``predictive``: lossless sharing of new cells with a persistent, learned probability
model (:mod:`fedmap.coding.streamcodec`), as a rover end and a base end.

Per rover, each direction of its link has a coder state on both ends. An uplink carries
the rover's trail since the last one the base acknowledged (its moves), its target, and
its observed cells within sensor range of that trail that the base does not hold: neither
from this rover nor in the global map the rover holds. A downlink carries the other
rovers' trails the rover does not hold, their targets, and every cell of the global map
the rover does not hold (cells within sensor range of those trails cost least). The
receiver derives which cells are candidates from the trails. **Over budget**, an uplink
carries the longest prefix of its trail that fits (and the cells in range of it), a
downlink the same share of every other rover's trail.

A sender folds what a message taught its coder state only when the message was delivered
and used (the acknowledgement), the receiver when it decoded it: so both ends of a link
keep the same state.

With ``[strategies.predictive] predictor = "mix"`` or ``"bins"``, both ends of a message
also run the shipped map predictor (:mod:`fedmap.nets.predictor`, deterministic, one
thread) on the map the receiver holds before the message (the ``known`` map both ends
already pass to the coder), and the coder takes its P(impassable) as one more context of
every cell (:mod:`fedmap.coding.streamcodec`: mixed into the probability, or as bins).
It costs no bytes; it costs one predictor call per message at each end.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fedmap._schema import setting
from fedmap.coding import streamcodec
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import UNKNOWN
from fedmap.mission.ends.protocol import BaseEnd, Cell, Outgoing, RoverEnd, cover, largest_fitting
from fedmap.nets.predictor import MapPredictor, predict, shipped_predictor

PRIORS, MASKS, STATES = ("learned", "none"), ("derived", "coded"), ("persistent", "per-message")
#: How the map predictor's guess enters the coder: not at all, mixed, or as context bins.
GUESSES = ("none", "mix", "bins")


@dataclass(frozen=True)
class PredictiveOptions:
    """``[strategies.predictive]``: the parts of the predictive coder, each with its default
    first (the others are ablations, for measuring what each part saves)."""

    prior: str = setting("learned", help="The coder's initial state: the shipped learned one, or none",
                         choices=PRIORS)
    mask: str = setting("derived", help="Which cells a message codes: those derived from the trails, or every "
                        "cell the receiver lacks", choices=MASKS)
    state: str = setting("persistent", help="Whether both ends keep the model from message to message",
                         choices=STATES)
    predictor: str = setting("none", help="Whether each cell's probability also takes the shipped map predictor's "
                             "P(impassable) on the map the receiver holds: mixed into it, or as context bins",
                             choices=GUESSES)

    def __post_init__(self) -> None:
        for name, allowed in (("prior", PRIORS), ("mask", MASKS), ("state", STATES), ("predictor", GUESSES)):
            if getattr(self, name) not in allowed:
                raise FedmapError(f"[strategies.predictive] {name} must be one of {', '.join(allowed)}, "
                                  f"got {getattr(self, name)!r}")

    def initial(self) -> streamcodec.CoderState:
        """A fresh copy of the coder's initial state."""
        init = streamcodec.initial_state() if self.prior == "learned" else streamcodec.blank_state()
        return init if self.predictor == "none" else streamcodec.guessing_state(init, self.predictor)


class _Coding:
    """What both ends of a predictive link do alike: derive the candidate cells from trails,
    and fold what a message taught into a coder state."""

    def __init__(self, shape: tuple[int, int], radius: float, options: PredictiveOptions) -> None:
        self.shape, self.radius = shape, radius
        self.derive_mask = options.mask == "derived"
        self.persist = options.state == "persistent"
        self.predictor: MapPredictor | None = None if options.predictor == "none" else shipped_predictor()
        self._guessed: tuple[bytes, np.ndarray] | None = None

    def guess(self, known: np.ndarray) -> np.ndarray | None:
        """The predictor's P(impassable) on ``known``, the map the receiver holds before a
        message (both ends compute it alike), or None without a predictor."""
        if self.predictor is None:
            return None
        key = np.ascontiguousarray(known, dtype=np.uint8).tobytes()
        if self._guessed is None or self._guessed[0] != key:
            self._guessed = (key, predict(self.predictor, known)[1])
        return self._guessed[1]

    def candidates(self, anchors: list[Cell]):
        def derive(tracks: list[list[Cell]]) -> np.ndarray:
            if not self.derive_mask:
                return np.ones(self.shape, dtype=bool)
            return cover([*anchors, *(p for t in tracks for p in t)], self.shape, self.radius)
        return derive

    def fold(self, state: streamcodec.CoderState, fold: streamcodec.Fold) -> None:
        if self.persist:
            state.fold(fold)


class PredictiveRover(RoverEnd):
    """A rover's end of ``predictive``: its two coder states, its copy of every trail, and
    what it knows the base holds."""

    def __init__(self, k: int, rover: Any, starts: list[Cell], *, budget: int | None, radius: float,
                 options: PredictiveOptions | None = None) -> None:
        super().__init__(k, rover, starts)
        opts = options or PredictiveOptions()
        self.budget, self.coding = budget, _Coding(self.shape, radius, opts)
        init = opts.initial()
        self.up, self.down = init.copy(), init.copy()
        self.sent = 1  # entries of its own trail the base holds (the start is known)
        self.delivered_cells = np.zeros(self.shape, dtype=bool)  # own cells the base holds
        self._held = np.full(self.shape, UNKNOWN, dtype=np.uint8)
        self.target_held: Cell | None = None  # its own target as the base holds it
        self.trails = [[s] for s in starts]  # its copy of every trail
        self.targets: list[Cell | None] = [None] * len(starts)
        self._pending: dict[int, tuple[int, streamcodec.Fold, np.ndarray, Cell | None]] = {}

    def held(self) -> np.ndarray:
        return self._held

    def known(self) -> np.ndarray:
        """The cells it knows the base holds."""
        return np.where(self._held != UNKNOWN, self._held,
                        np.where(self.delivered_cells, self.rover.local, UNKNOWN)).astype(np.uint8)

    def known_up(self) -> np.ndarray:
        """What its uplink is coded against: the cells it knows the base holds."""
        return self.known()

    def known_down(self) -> np.ndarray:
        """What a downlink to it is coded against: the cells it knows the base holds."""
        return self.known()

    def trail(self) -> list[Cell]:
        """Its trail as its uplinks carry it (its start first)."""
        return self.rover.trail

    def uplink(self, round_no: int) -> Outgoing | None:
        r = self.rover
        known = self.known_up()
        trail = self.trail()
        anchor = trail[self.sent - 1]
        pending = trail[self.sent:]
        derive = self.coding.candidates([anchor])
        guess = self.coding.guess(known)

        def make(n: int) -> tuple[bytes, streamcodec.Fold, np.ndarray]:
            cand = derive([pending[:n]]) & (known == UNKNOWN)
            cells = np.where(cand, r.local, UNKNOWN).astype(np.uint8)
            content = streamcodec.Content([list(pending[:n])], [r.target], cells)
            payload, fold = streamcodec.encode(content, state=self.up, anchors=[anchor],
                                               mark_refs=[self.target_held], known=known, candidates=derive,
                                               guess=guess)
            return payload, fold, cells

        n, made = largest_fitting(make, len(pending), self.budget)
        if n is None:
            return Outgoing(None, "cells")
        payload, fold, cells = made
        self._pending[round_no] = (n, fold, cells, r.target)
        return Outgoing(payload, "cells")

    def delivered(self, round_no: int, ok: bool) -> None:
        sent = self._pending.pop(round_no, None)
        if not ok or sent is None:
            return
        n, fold, cells, target = sent
        self.coding.fold(self.up, fold)
        self.sent += n
        self.delivered_cells |= cells != UNKNOWN
        self.target_held = target

    def receive(self, payload: bytes) -> bool:
        others = [j for j in range(len(self.trails)) if j != self.k]
        anchors = [self.trails[j][-1] for j in others]
        known = self.known_down()
        try:
            got = streamcodec.decode(payload, state=self.down, anchors=anchors,
                                     mark_refs=[self.targets[j] for j in others], known=known,
                                     candidates=self.coding.candidates(anchors), guess=self.coding.guess(known))
        except RejectedUpdate:  # coded against a state or map this rover no longer holds
            return False
        self.coding.fold(self.down, got.fold)
        carried = got.cells != UNKNOWN
        self._held = np.where(carried, got.cells, self._held).astype(np.uint8)
        for j, track, mark in zip(others, got.tracks, got.marks):
            self.trails[j].extend(track)
            self.targets[j] = mark
            self.reports[j] = (self.trails[j][-1], mark)
        return True


class PredictiveBase(BaseEnd):
    """The base station's end of ``predictive``: per rover, its two coder states, that
    rover's trail, and what it knows that rover holds."""

    def __init__(self, shape: tuple[int, int], starts: list[Cell], *, budget: int | None, radius: float,
                 options: PredictiveOptions | None = None) -> None:
        super().__init__(shape, starts)
        opts = options or PredictiveOptions()
        self.budget, self.coding = budget, _Coding(shape, radius, opts)
        self.initial = init = opts.initial()
        n = self.n
        self.up = [init.copy() for _ in range(n)]
        self.down = [init.copy() for _ in range(n)]
        self.trails = [[s] for s in starts]
        self.from_rover = [np.zeros(shape, dtype=bool) for _ in range(n)]
        self.held_by = [np.full(shape, UNKNOWN, dtype=np.uint8) for _ in range(n)]
        self.targets: list[Cell | None] = [None] * n
        self.fwd = [[1] * n for _ in range(n)]  # entries of rover j's trail that rover k holds
        self.fwd_targets: list[list[Cell | None]] = [[None] * n for _ in range(n)]
        self.base = np.full(shape, UNKNOWN, dtype=np.uint8)
        self._pending: dict[tuple[int, int], tuple[streamcodec.Fold, list[list[Cell]], np.ndarray, list, list]] = {}

    def global_map(self) -> np.ndarray:
        return self.base

    def known(self, k: int) -> np.ndarray:
        """The cells it knows rover ``k`` holds."""
        return np.where(self.held_by[k] != UNKNOWN, self.held_by[k],
                        np.where(self.from_rover[k], self.base, UNKNOWN)).astype(np.uint8)

    def must_send(self, k: int) -> bool:
        """Whether rover ``k`` needs a downlink even when it holds everything the base has."""
        return False

    def decode_up(self, k: int, payload: bytes, trail: list[Cell], mark: Cell | None,
                  known: np.ndarray) -> streamcodec.Content | None:
        """Rover ``k``'s uplink, coded after ``trail``'s last cell and against ``mark`` and
        ``known``; its trail and state taken in. None when it does not decode against them."""
        a = trail[-1]
        try:
            got = streamcodec.decode(payload, state=self.up[k], anchors=[a], mark_refs=[mark], known=known,
                                     candidates=self.coding.candidates([a]), guess=self.coding.guess(known))
        except RejectedUpdate:
            return None
        self.coding.fold(self.up[k], got.fold)
        trail.extend(got.tracks[0])
        return got

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        known = self.known(k)
        got = self.decode_up(k, payload, self.trails[k], self.targets[k], known)
        if got is None:
            return False
        self.targets[k] = got.marks[0]
        carried = got.cells != UNKNOWN
        self.from_rover[k] |= carried
        self.base = np.where(carried, got.cells, self.base).astype(np.uint8)
        return True

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        out = {}
        for k in range(self.n):
            others = [j for j in range(self.n) if j != k]
            known = self.known(k)
            anchors = [self.trails[j][self.fwd[k][j] - 1] for j in others]
            news = [self.trails[j][self.fwd[k][j]:] for j in others]
            marks = [self.targets[j] for j in others]
            refs = [self.fwd_targets[k][j] for j in others]
            lacking = self.lacking(k, self.base, known)
            if not lacking.any() and not any(news) and marks == refs and not self.must_send(k):
                continue  # it holds everything the base has
            derive = self.coding.candidates(anchors)
            longest = max((len(t) for t in news), default=0)
            guess = self.coding.guess(known)

            def make(n: int, news=news, derive=derive, known=known, lacking=lacking, anchors=anchors, marks=marks,
                     refs=refs, k=k, longest=longest,
                     guess=guess) -> tuple[bytes, streamcodec.Fold, list[list[Cell]], np.ndarray]:
                share = [t[:-(-len(t) * n // longest)] if longest else [] for t in news]
                if n == longest:
                    cells = np.where(lacking, self.base, UNKNOWN).astype(np.uint8)
                else:
                    cells = np.where(lacking & derive(share), self.base, UNKNOWN).astype(np.uint8)
                content = streamcodec.Content(share, marks, cells)
                payload, fold = streamcodec.encode(content, state=self.down[k], anchors=anchors, mark_refs=refs,
                                                   known=known, candidates=derive, guess=guess)
                return payload, fold, share, cells

            n, made = largest_fitting(make, longest, self.budget)
            if n is None:
                out[k] = Outgoing(None, "map")
                continue
            payload, fold, share, cells = made
            self._pending[k, round_no] = (fold, share, cells, marks, others)
            out[k] = Outgoing(payload, "map")
        return out

    def delivered(self, k: int, round_no: int, ok: bool) -> None:
        sent = self._pending.pop((k, round_no), None)
        if not ok or sent is None:
            return
        fold, share, cells, marks, others = sent
        self.coding.fold(self.down[k], fold)
        self.held_by[k] = np.where(cells != UNKNOWN, cells, self.held_by[k]).astype(np.uint8)
        for j, track, mark in zip(others, share, marks):
            self.fwd[k][j] += len(track)
            self.fwd_targets[k][j] = mark
