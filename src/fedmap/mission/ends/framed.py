"""The ends of ``raw`` and ``predictive`` when every rover maps in its own frame
(``[frames]``; the world's side, poses and drift, is :mod:`fedmap.mission.world.frames`).

A rover's uplink is its cells in its own frame; the base (on the mesh, every agent) keeps
each rover's cells in that frame and merges them into the global map only through a
transform it estimated and checked (:func:`track`, gated by :func:`verdict`). A downlink
carries the transform the base holds for the rover (:data:`TRANSFORM_BYTES`, counted) and
the global cells it lacks; the rover lays them into its own frame. :func:`framed_raw` and
:func:`framed_predictive` build them; the registry's specs name them.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from fedmap.coding.mapcodec import decode_map
from fedmap.maps.grid import IMPASSABLE, UNKNOWN
from fedmap.maps.registration import (
    Agreement,
    RigidTransform,
    agreement,
    combine,
)
from fedmap.mission.ends.predictive import PredictiveBase, PredictiveOptions, PredictiveRover
from fedmap.mission.ends.protocol import BaseEnd, Outgoing, PeerEnd, RoverEnd, pack_down, unpack_down, unpack_up
from fedmap.mission.ends.raw import RawBase, RawPeer, RawRover
from fedmap.mission.ends.sharing import Setup, Sharing
from fedmap.mission.network.link import BASE

Cell = tuple[int, int]
#: How far past its sensor's range a rover in its own frame writes what it senses (cells): it
#: looks up, for every cell of its frame near its estimate, the true cell it shows.
SENSED_BEYOND = 1.5
_TRANSFORM = struct.Struct("<Bhhh")  # placed, dy and dx in 1/16 cell, heading in 1/100 degree (-180..180)
#: Bytes of the transform each downlink carries.
TRANSFORM_BYTES = _TRANSFORM.size


def rotation(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def pack_transform(t: RigidTransform | None) -> bytes:
    """``t`` (None: not placed) in :data:`TRANSFORM_BYTES` bytes: shifts to 1/16 cell, heading to 0.01 degree."""
    if t is None:
        return _TRANSFORM.pack(0, 0, 0, 0)
    h = (t.heading_deg + 180.0) % 360.0 - 180.0
    return _TRANSFORM.pack(1, int(np.clip(round(t.dy * 16), -32768, 32767)),
                           int(np.clip(round(t.dx * 16), -32768, 32767)), int(round(h * 100)))


def unpack_transform(raw: bytes) -> RigidTransform | None:
    placed, dy, dx, h = _TRANSFORM.unpack_from(raw)
    return RigidTransform(dy / 16.0, dx / 16.0, h / 100.0) if placed else None


# --------------------------------------------------------------------------- tracking


def _kappas(base: np.ndarray, pts: np.ndarray, imp: np.ndarray, q: np.ndarray,
            min_class: int) -> tuple[np.ndarray, np.ndarray]:
    """Score and kappa of every candidate: ``q`` ``(C, N, 2)`` float cells of the base where
    the ``N`` points (impassable: ``imp``) land. The base is read between its cells
    (bilinear: a point a third of the way to a rock is a third impassable), so the kappa
    changes smoothly with a shift below a cell and its best is not a plateau of equal
    nearest-cell fits. The score is the kappa where the overlap is enough to register on
    (:data:`MIN_OVERLAP` cells, ``min_class`` of each class), else -inf: near the estimate
    agreement decides, not the overlap's size (a placement that laps over more known cells
    is not better for it)."""
    coords = q.reshape(-1, 2).T
    known = (base != UNKNOWN).astype(np.float64)
    rock = (base == IMPASSABLE).astype(np.float64)
    wk = ndimage.map_coordinates(known, coords, order=1, mode="constant", cval=0.0).reshape(q.shape[:2])
    wi = ndimage.map_coordinates(rock, coords, order=1, mode="constant", cval=0.0).reshape(q.shape[:2])
    wi = np.minimum(wi, wk)
    ia = imp[None, :].astype(np.float64)
    n = wk.sum(axis=1)
    na, nb = (ia * wk).sum(axis=1), wi.sum(axis=1)
    agree = ((ia * wi) + (1 - ia) * (wk - wi)).sum(axis=1) / np.maximum(n, 1e-9)
    pa, pb = na / np.maximum(n, 1e-9), nb / np.maximum(n, 1e-9)
    chance = pa * pb + (1 - pa) * (1 - pb)
    kappa = np.where(chance < 1 - 1e-12, (agree - chance) / np.maximum(1 - chance, 1e-12), 0.0)
    minority = np.minimum.reduce([na, n - na, nb, n - nb])
    score = np.where((minority >= min_class) & (n >= MIN_OVERLAP), kappa, -np.inf)
    return score, kappa


#: Known cells a rover's cells and the global map must share to be registered near the
#: odometry's estimate, and cells of each class on each side (the search is confined near
#: the estimate, so fewer than a search over every placement needs: 400 and 50).
MIN_OVERLAP, MIN_CLASS = 150, 15
#: The kappa a placement must gain over the current estimate's for the estimate to move.
MOVE_BY = 0.02


def verdict(check: Agreement, gate: float, min_overlap: int = MIN_OVERLAP,
            min_class: int = MIN_CLASS) -> tuple[str, str]:
    """``(verdict, reason)`` of a registration near the estimate: ``accepted``; ``unsure``
    (too few shared cells, or of one class, to tell); ``refused`` (enough of both, but a
    kappa below ``gate``: the maps disagree)."""
    if check.overlap < min_overlap:
        return "unsure", f"{check.overlap} shared cells, fewer than {min_overlap}"
    if check.minority < min_class:
        return "unsure", f"{check.minority} shared cells of one class in one map, fewer than {min_class}"
    if check.kappa < gate:
        return "refused", f"confidence {check.kappa:.2f} below the gate {gate:.2f} ({check.overlap} shared cells)"
    return "accepted", ""


def track(base: np.ndarray, window: np.ndarray, prior: RigidTransform, *, gate: float = 0.5,
          span_deg: float = 3.0, span_cells: int = 3, min_class: int = MIN_CLASS,
          move_by: float = MOVE_BY) -> tuple[RigidTransform, Agreement, str, str]:
    """Register ``window`` (a rover's recent cells, its frame) against ``base`` near ``prior``:
    headings within ``span_deg`` and shifts within ``span_cells`` of where ``prior`` puts the
    window's middle, by 1 degree and 1 cell, then by a quarter around the best; the best
    is checked (:func:`~fedmap.maps.registration.agreement`, :func:`verdict`). The
    best placement is the one of highest kappa (ties: the nearest to ``prior``); it replaces
    ``prior`` only when its kappa is ``move_by`` higher. Too little overlap under
    ``prior`` to tell placements apart: ``unsure``, and ``prior`` stays.
    Returns ``(transform, check, verdict, reason)``."""
    pts = np.argwhere(window != UNKNOWN).astype(np.float64)
    if len(pts) == 0:
        return prior, Agreement(0, 0.0, 0.0, 0.0), "unsure", "no cells to register"
    imp = window[window != UNKNOWN] == IMPASSABLE
    c = pts.mean(axis=0)
    c_at = prior.map_points(c)[0]

    def best(headings: np.ndarray, shifts: np.ndarray, centre: np.ndarray) -> tuple[float, float, np.ndarray]:
        top = (-np.inf, prior.heading_deg, centre)
        shifts = shifts[np.argsort(np.hypot(shifts[:, 0], shifts[:, 1]), kind="stable")]  # ties: the nearest
        mid = float(np.mean(headings))
        for hd in sorted(headings, key=lambda x: abs(x - mid)):
            turned = (pts - c) @ rotation(float(hd)).T + centre
            sc, _ = _kappas(base, pts, imp, turned[None] + shifts[:, None, :], min_class)
            i = int(np.argmax(sc))
            if sc[i] > top[0]:
                top = (float(sc[i]), float(hd), centre + shifts[i])
        return top

    at_prior = agreement(base, prior.apply(window, base.shape))
    v, why = verdict(at_prior, gate)
    if v == "unsure":  # too little under the estimate to tell placements apart
        return prior, at_prior, v, why
    grid = np.arange(-span_cells, span_cells + 1, dtype=np.float64)
    shifts = np.stack(np.meshgrid(grid, grid, indexing="ij"), axis=-1).reshape(-1, 2)
    ev, hd, at = best(prior.heading_deg + np.arange(-span_deg, span_deg + 0.5, 1.0), shifts, c_at)
    if not np.isfinite(ev):
        hd, at = prior.heading_deg, c_at
    fine = np.arange(-0.75, 0.76, 0.25)
    shifts = np.stack(np.meshgrid(fine, fine, indexing="ij"), axis=-1).reshape(-1, 2)
    _, hd, at = best(hd + np.arange(-0.75, 0.76, 0.25), shifts, at)
    shift = at - rotation(hd) @ c
    t = RigidTransform(float(shift[0]), float(shift[1]), hd)
    check = agreement(base, t.apply(window, base.shape))
    if check.kappa < at_prior.kappa + move_by:  # no clear gain: the estimate stays
        t, check = prior, at_prior
    return (t, check, *verdict(check, gate))


# --------------------------------------------------------------------------- raw's ends


class _FramedView:
    """What a rover end in its own frame adds to its strategy's end: the transform of its
    frame into the global frame (sent by the base with every downlink), and a belief that
    lays the global map it holds (``_held``, global frame) into its frame.

    Its frame drifts, so its older cells sit where its odometry put them then, not where they
    are relative to it now; the base placed them in the global map with the transform of
    their time. So the cells it observed in the last ``recent`` steps win, then the global
    map laid into its frame with its transform now, then its older cells."""

    rover: Any
    shape: tuple[int, int]
    _held: np.ndarray

    def _frame_init(self, recent: int) -> None:
        self.recent = recent
        self.transform = RigidTransform()  #: its frame -> the global frame, as the team estimated it
        self.placed = False
        self._version = 0
        self._view: tuple[tuple, np.ndarray] | None = None

    def belief(self) -> np.ndarray:
        local = self.rover.local
        if not self.placed:
            return local.copy()
        key = (self._version, self.transform)
        if self._view is None or self._view[0] != key:
            self._view = (key, self.transform.inverse().apply(self._held, self.shape))
        view = self._view[1]
        steps = self.rover.obs_step
        fresh = steps >= int(steps.max()) - self.recent  # what it saw lately: in its frame as it is now
        out = np.where(view != UNKNOWN, view, local)  # older cells: as the base placed them, where it has them
        return np.where(fresh & (local != UNKNOWN), local, out).astype(np.uint8)

    def others(self) -> list[Cell]:
        theirs = super().others()  # type: ignore[misc]
        if not self.placed:
            return theirs
        inv = self.transform.inverse()
        return [_through(inv, p) for p in theirs]

    def _received(self, t: RigidTransform | None) -> None:
        """A downlink was taken, carrying the transform ``t`` (None: not placed yet)."""
        self._version += 1
        if t is not None:
            self.transform, self.placed = t, True


class FramedRawRover(_FramedView, RawRover):
    """A rover's end of ``raw`` when it maps in its own frame (see :class:`_FramedView`)."""

    def __init__(self, *args, recent: int, **kw) -> None:
        super().__init__(*args, **kw)
        self._frame_init(recent)

    def receive(self, payload: bytes) -> bool:
        kind, ref, reports, body = unpack_down(payload)
        t = unpack_transform(body[:TRANSFORM_BYTES])
        ok = super().receive(pack_down(kind, ref, reports, body[TRANSFORM_BYTES:]))
        if ok:
            self._received(t)
        return ok


def _through(t: RigidTransform, c: Cell, shape: tuple[int, int] | None = None) -> Cell:
    """Cell ``c`` through ``t``, to the nearest cell (clipped to a ``shape`` grid if given)."""
    r, cc = np.rint(t.map_points(np.array(c, dtype=np.float64))[0]).astype(int)
    if shape is not None:
        r, cc = np.clip(r, 0, shape[0] - 1), np.clip(cc, 0, shape[1] - 1)
    return (int(r), int(cc))


def _report_through(t: RigidTransform, pos: Cell, target: Cell | None,
                    shape: tuple[int, int] | None = None) -> tuple[Cell, Cell | None]:
    """A rover's reported position and target through ``t`` (:func:`_through`)."""
    return _through(t, pos, shape), None if target is None else _through(t, target, shape)


def chain(a: Cell, b: Cell) -> list[Cell]:
    """The cells from ``a`` (excluded) to ``b`` (included) by steps between neighbouring cells:
    diagonal first, then straight (an estimated cell can jump, a coded trail cannot)."""
    out, (r, c) = [], a
    while (r, c) != b:
        r += (b[0] > r) - (b[0] < r)
        c += (b[1] > c) - (b[1] < c)
        out.append((r, c))
    return out


class FramedPredictiveRover(_FramedView, PredictiveRover):
    """A rover's end of ``predictive`` when it maps in its own frame.

    Its uplink is its own frame's: the trail it believes it drove (its estimated cells, from
    its deployment cell, chained into steps between neighbouring cells) and its cells, coded
    against the cells of its own it knows the base holds (the global map is in another frame).
    Its downlinks are the global frame's, after the 7-byte transform: the others' trails as
    the base placed them and the global map's cells it lacks, coded against what it holds."""

    def __init__(self, *args, recent: int, **kw) -> None:
        super().__init__(*args, **kw)
        self._frame_init(recent)
        self.own = [self.trails[self.k][0]]  # its trail in its own frame, from the cell it was told it starts at
        self._seen = 0  # its pose's estimated cells taken into ``own``
        self._mine = np.full(self.shape, UNKNOWN, dtype=np.uint8)  # its own cells the base holds

    def trail(self) -> list[Cell]:
        cells = self.rover.frame.cells
        for c in cells[self._seen:]:
            self.own.extend(chain(self.own[-1], c))
        self._seen = len(cells)
        return self.own

    def known_up(self) -> np.ndarray:
        return self._mine

    def known_down(self) -> np.ndarray:
        return self._held

    def delivered(self, round_no: int, ok: bool) -> None:
        sent = self._pending.get(round_no)
        if ok and sent is not None:
            cells = sent[2]
            self._mine = np.where(cells != UNKNOWN, cells, self._mine).astype(np.uint8)
        super().delivered(round_no, ok)

    def receive(self, payload: bytes) -> bool:
        t = unpack_transform(payload[:TRANSFORM_BYTES])
        ok = super().receive(payload[TRANSFORM_BYTES:])
        if ok:
            self._received(t)
        return ok


@dataclass
class Placing:
    """One registration at the base, for the record."""

    round: int
    rover: int
    action: str  #: anchor, placed, tracked, carried (too little to register: its odometry), waiting, refused
    kappa: float
    overlap: int
    transform: tuple[float, float, float] | None
    reason: str = ""

    def to_dict(self) -> dict:
        return {"round": self.round, "rover": self.rover, "action": self.action, "kappa": round(self.kappa, 4),
                "overlap": self.overlap, "transform": self.transform, "reason": self.reason}


@dataclass(frozen=True)
class WhatIf:
    """What-ifs of the framed star's base, for ablations (``benchmarks/mission_frames.py``);
    never a mission's own behaviour, which no setting changes. ``oracle``: the base places
    every rover's cells by its *true* transform (its frame into the true frame, as its pose
    is at that sync) wherever it would register them, also with nothing to register on.
    ``send_back``: a downlink sends a rover the global cells it gave too."""

    oracle: bool = False
    send_back: bool = False


_WHAT_IF = WhatIf()


@contextmanager
def what_if(change: WhatIf) -> Iterator[None]:
    """Every framed star base built while the ``with`` block runs follows ``change``."""
    global _WHAT_IF
    before, _WHAT_IF = _WHAT_IF, change
    try:
        yield
    finally:
        _WHAT_IF = before


class _Placer:
    """What a base end adds when every rover maps in its own frame (see the module): each
    rover's cells kept in its frame, and merged into the global map (``base``, stamped by
    round in ``base_stamp``) only through a transform the base estimated and checked."""

    base: np.ndarray
    base_stamp: np.ndarray
    shape: tuple[int, int]

    def _placer_init(self, n: int, *, frames, reference: np.ndarray | None) -> None:
        shape = self.shape
        self.frames = frames
        #: what the lander imaged around itself, in the true frame (registered on, never merged; None: none)
        self.reference = reference
        self.sub = [np.full(shape, UNKNOWN, dtype=np.uint8) for _ in range(n)]  # each rover's cells, its frame
        self.sub_round = [np.full(shape, -1, dtype=np.int64) for _ in range(n)]
        self.pending = [np.zeros(shape, dtype=bool) for _ in range(n)]
        self.transforms: list[RigidTransform | None] = [None] * n
        self.first: list[RigidTransform | None] = [None] * n  # each rover's placement at its start
        self.owner = np.full(shape, -1, dtype=np.int64)  # the rover whose cell each global cell first was
        self.owner_round = np.full(shape, -1, dtype=np.int64)  # and the round it was merged
        self.log: list[Placing] = []
        self.what_if = _WHAT_IF
        #: :attr:`WhatIf.oracle`: every rover's true pose (set by :func:`build`; None: registration, as ever)
        self.true_poses: list[Any] | None = None

    def withheld(self, k: int) -> np.ndarray | None:
        """A downlink leaves out the global cells rover ``k`` gave: it holds them in its own frame."""
        return None if self.what_if.send_back else self.owner == k

    def _take(self, k: int, cells: np.ndarray, round_no: int) -> None:
        """Rover ``k``'s cells (its frame) arrived: keep them, and place them if it can."""
        carried = cells != UNKNOWN
        self.sub[k][carried] = cells[carried]
        self.sub_round[k][carried] = round_no
        self.pending[k] |= carried
        self._place(k, round_no)

    def _place(self, k: int, round_no: int) -> None:
        f, sub, pend = self.frames, self.sub[k], self.pending[k]
        if not pend.any():
            return
        if self.true_poses is not None:  # the oracle's what-if: placed exactly
            exact = self.true_poses[k].to_own().inverse()  # the rover's frame -> the true frame, now
            self.log.append(Placing(round_no, k, "oracle", 1.0, 0, (exact.dy, exact.dx, exact.heading_deg)))
            if self.transforms[k] is None:
                self.first[k] = exact
            self._merge(k, exact, round_no)
            return
        oldest = int(self.sub_round[k][pend].min())
        window = np.where((self.sub_round[k] > oldest - f.window) & (sub != UNKNOWN), sub, UNKNOWN).astype(np.uint8)
        t = self.transforms[k]
        # registered on the global map without its own cells of the window: those sit where its
        # last transform put them and would only confirm it (its older cells are fair: a loop closure)
        mine = (self.owner == k) & (self.owner_round > oldest - f.window)
        others = np.where(mine, UNKNOWN, self.base)
        target = others if self.reference is None else np.where(self.reference != UNKNOWN, self.reference, others)
        if self.reference is None and all(x is None for x in self.transforms):  # the first rover's frame is the team's
            self._merge(k, RigidTransform(), round_no)
            self.first[k] = RigidTransform()
            self.log.append(Placing(round_no, k, "anchor", 1.0, int(pend.sum()), (0.0, 0.0, 0.0)))
            return
        if t is None:  # never placed: near its deployment estimate (its frame is the lander's, within the spreads)
            span_deg = 3 * f.start_heading + 1.0
            span_cells = int(math.ceil(3 * f.start_offset)) + 1
            t2, check, v, why = track(target, sub, RigidTransform(), gate=f.gate, span_deg=span_deg,
                                      span_cells=span_cells, move_by=0.0)
            action = "placed"
        else:  # placed: its recent cells again, near where they were (the loop closure), wider once lost a while
            lost = round_no - oldest >= f.window
            t2, check, v, why = track(target, window, t, gate=f.gate, span_deg=6.0 if lost else 3.0,
                                      span_cells=6 if lost else 3)
            action = "tracked"
            if v == "unsure":  # too little to register on: its odometry carries the last transform
                t2, action = t, "carried"
        ok = v == "accepted" or action == "carried"
        self.log.append(Placing(round_no, k, action if ok else ("waiting" if v == "unsure" else "refused"),
                                check.kappa, check.overlap, (t2.dy, t2.dx, t2.heading_deg), why))
        if ok:
            if t is None:
                self.first[k] = t2
            self._merge(k, t2, round_no)

    def team_frame(self) -> RigidTransform:
        """The team's estimate of the transform of the global frame into the true frame
        (the lander's): with the lander's image, the identity (every rover was placed on it);
        else each rover's frame was the lander's at its start within the spreads, so the mean
        of the placements of the rovers at their start, turned back (identity before any
        placement)."""
        placed = [t for t in self.first if t is not None]
        if not placed or self.reference is not None:  # placed on the lander's image: the global frame is the lander's
            return RigidTransform()
        inv = [t.inverse() for t in placed]
        h = math.degrees(math.atan2(np.mean([math.sin(math.radians(t.heading_deg)) for t in inv]),
                                    np.mean([math.cos(math.radians(t.heading_deg)) for t in inv])))
        return RigidTransform(float(np.mean([t.dy for t in inv])), float(np.mean([t.dx for t in inv])), h)

    def global_map(self) -> np.ndarray:
        """The global map put in the true frame by the team's estimate (:meth:`team_frame`): what is scored."""
        return self.team_frame().apply(self.base, self.shape)

    def _merge(self, k: int, t: RigidTransform, round_no: int) -> None:
        self.transforms[k] = t
        cells = t.apply(np.where(self.pending[k], self.sub[k], UNKNOWN).astype(np.uint8), self.shape)
        merged = combine(self.base, cells)
        changed = merged != self.base
        fresh = (self.base == UNKNOWN) & (merged != UNKNOWN)
        self.owner[fresh] = k
        self.owner_round[fresh] = round_no
        self.base = merged
        self.base_stamp[changed] = round_no
        self.pending[k][:] = False

    def _in_global(self, j: int, pos: Cell, target: Cell | None) -> tuple[Cell, Cell | None]:
        t = self.transforms[j]
        return (pos, target) if t is None else _report_through(t, pos, target)


class FramedRawBase(_Placer, RawBase):
    """The base's end of ``raw`` when every rover maps in its own frame (see the module)."""

    def __init__(self, shape, starts, *, budget, frames, journal=None, reference: np.ndarray | None = None) -> None:
        super().__init__(shape, starts, budget=None if budget is None else budget - TRANSFORM_BYTES,
                         journal=journal)
        self._placer_init(len(starts), frames=frames, reference=reference)

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        _, pos, target, body = unpack_up(payload)
        cells = decode_map(body, expected_shape=self.shape)
        self.journal.received.append((round_no, k, payload))
        self.reports[k] = (pos, target)
        self._take(k, cells, round_no)
        return True

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        own = self.reports
        self.reports = {j: self._in_global(j, p, tg) for j, (p, tg) in own.items()}
        try:
            out = super().downlinks(round_no)
        finally:
            self.reports = own
        for k, o in out.items():
            if o.payload is not None:
                kind, ref, reports, body = unpack_down(o.payload)
                out[k] = Outgoing(pack_down(kind, ref, reports, pack_transform(self.transforms[k]) + body), o.kind)
        return out



class FramedPredictiveBase(_Placer, PredictiveBase):
    """The base's end of ``predictive`` when every rover maps in its own frame: per rover, its
    trail and cells in its own frame (what its uplinks are coded against), and its trail as
    placed in the global frame by its transform (what the other rovers' downlinks carry)."""

    def __init__(self, shape, starts, *, budget, radius: float, frames, options=None,
                 reference: np.ndarray | None = None) -> None:
        super().__init__(shape, starts, budget=None if budget is None else budget - TRANSFORM_BYTES,
                         radius=radius, options=options)
        self._placer_init(len(starts), frames=frames, reference=reference)
        self.base_stamp = np.full(shape, -1, dtype=np.int64)
        self.own = [[s] for s in starts]  # each rover's trail in its own frame
        self.own_targets: list[Cell | None] = [None] * len(starts)
        self.laid = [1] * len(starts)  # entries of each own trail laid into the global trail
        self.told: list[RigidTransform | None] = [None] * len(starts)  # the transform each rover holds
        self._told: dict[tuple[int, int], RigidTransform | None] = {}

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        got = self.decode_up(k, payload, self.own[k], self.own_targets[k], self.sub[k])
        if got is None:
            return False
        self.own_targets[k] = got.marks[0]
        self._take(k, got.cells, round_no)
        self._lay(k)
        return True

    def _lay(self, k: int) -> None:
        """Rover ``k``'s trail and target since the last placing, into the global frame by its transform."""
        t = self.transforms[k]
        if t is None:
            return
        for c in self.own[k][self.laid[k]:]:
            self.trails[k].extend(chain(self.trails[k][-1], _through(t, c, self.shape)))
        self.laid[k] = len(self.own[k])
        mark = self.own_targets[k]
        self.targets[k] = None if mark is None else _through(t, mark, self.shape)

    def must_send(self, k: int) -> bool:
        return self.told[k] != self.transforms[k]

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        out = super().downlinks(round_no)
        for k, o in out.items():
            if o.payload is not None:
                out[k] = Outgoing(pack_transform(self.transforms[k]) + o.payload, o.kind)
                self._told[k, round_no] = self.transforms[k]
        return out

    def delivered(self, k: int, round_no: int, ok: bool) -> None:
        told = self._told.pop((k, round_no), self.told[k])
        if ok:
            self.told[k] = told
        super().delivered(k, round_no, ok)


class FramedRawPeer(RawPeer):
    """An agent's end of ``raw`` gossip on the mesh when every rover maps in its own frame.

    There is no base to place the maps: every agent places what it receives. A message is
    the sender's cells in the sender's frame, coded as ever (it carries every cell the
    sender does not know the receiver holds): a rover's own observations only
    (:meth:`shared`), the lander's everything it holds. The receiver registers them on what
    it holds (its own cells, and the cells others gave it, without those the sender gave it
    before: they would only confirm its last estimate), with :func:`track` near its last
    estimate of the sender's frame (the first time, near the identity: every frame is the
    lander's within the spreads), and merges them through the estimate when the gate accepts
    it (impassable wins). Too little shared to tell: a sender placed before keeps its last
    estimate (``carried``); one never placed, or one the gate refuses, is not used
    (``waiting`` / ``refused``): the sender keeps them as not delivered and sends them
    again.

    The lander (an agent that never moves) holds the global frame: what it imaged at landing
    (``reference``) is registered on, never merged or sent, and its held map is the global
    map; without that image, the first rover whose cells reach it fixes the global frame. A
    rover that placed a message of the lander's knows its own frame in the global one
    (:attr:`transform`, :attr:`placed`): its belief is scored through it (identity until
    then). No transform crosses the mesh's links: sent with the lander's messages, the
    lander's estimate of a rover's frame changed its belief accuracy by -0.0003 (3 seeds)
    for 1 % more bytes; sent as a receiver's starting point for registering, a sender's
    estimate was worse on one seed of three (0.602 against 0.659)."""

    def __init__(self, agent: int, rover: Any, shape: tuple[int, int], starts: list[Cell], *,
                 agents: tuple[int, ...], journal=None, frames, reference: np.ndarray | None = None) -> None:
        super().__init__(agent, rover, shape, starts, agents=agents, journal=journal)
        self.frames = frames
        self.reference = reference if rover is None else None
        self.est: dict[int, RigidTransform] = {}  #: each sender's frame -> its own, as last accepted
        self.given = {j: np.zeros(shape, dtype=bool) for j in agents}  # its cells each agent gave it
        self.transform = RigidTransform()  #: its frame -> the global (lander's) frame, as it estimated it
        self.placed = rover is None
        self.log: list[Placing] = []

    def shared(self) -> np.ndarray:
        """A rover shares only what it observed itself: a cell it relayed would cross one more
        estimated transform at each hop (on three seeds of the default mission, relaying gave
        0.030 less belief accuracy and 0.039 more false-free, for twice the bytes). The lander
        shares what it holds, in the global frame."""
        return self.hold if self.rover is None else self.rover.local

    def receive(self, frm: int, payload: bytes, round_no: int, step: int) -> bool:
        _, _, reports, body = unpack_down(payload)
        cells = decode_map(body, expected_shape=self.shape)
        if not (cells != UNKNOWN).any():
            return True
        f = self.frames
        mine = np.where(self.given[frm], UNKNOWN, self.belief())
        target = mine if self.reference is None else np.where(self.reference != UNKNOWN, self.reference, mine)
        prior = self.est.get(frm)
        if self.rover is None and self.reference is None and not self.est:  # the first rover's frame is the global one
            self.log.append(Placing(round_no, frm, "anchor", 1.0, int((cells != UNKNOWN).sum()), (0.0, 0.0, 0.0)))
            return self._merge_from(frm, RigidTransform(), cells, reports, round_no, step)
        if prior is None:  # two frames, each the lander's within the spreads (and drift since)
            t, check, v, why = track(target, cells, RigidTransform(), gate=f.gate,
                                     span_deg=6 * f.start_heading + 2.0,
                                     span_cells=int(math.ceil(6 * f.start_offset)) + 2, move_by=0.0)
            action = "placed"
        else:
            t, check, v, why = track(target, cells, prior, gate=f.gate)
            action = "tracked"
            if v == "unsure":
                t, action = prior, "carried"
        ok = v == "accepted" or action == "carried"
        self.log.append(Placing(round_no, frm, action if ok else ("waiting" if v == "unsure" else "refused"),
                                check.kappa, check.overlap, (t.dy, t.dx, t.heading_deg), why))
        if not ok:
            return False
        return self._merge_from(frm, t, cells, reports, round_no, step)

    def _merge_from(self, frm: int, t: RigidTransform, cells: np.ndarray, reports: dict, round_no: int,
                    step: int) -> bool:
        """Merge ``frm``'s ``cells`` through ``t`` (its frame -> this agent's), impassable winning."""
        self.est[frm] = t
        if frm == BASE and self.rover is not None:  # the lander's frame is the global one
            self.transform, self.placed = t.inverse(), True
        placed = t.apply(cells, self.shape)
        carried = placed != UNKNOWN
        merged = combine(self.hold, placed)
        self.got[merged != self.hold] = step
        self.hold = merged
        self.given[frm] |= carried
        self.has[frm] |= carried
        self.heard({j: _report_through(t, p, tg, self.shape) for j, (p, tg) in reports.items()})
        self.journal.deliveries.append((round_no, frm, self.agent, np.flatnonzero(carried)))
        return True


def registrations(sharing: Sharing) -> tuple[dict, ...] | None:
    """Every registration a framed base made (:class:`Placing` as dicts, in order), or on the
    mesh every agent's (each with ``by``, the agent that placed the cells); None otherwise
    (known poses, or ``none``)."""
    if isinstance(sharing.base, _Placer):
        return tuple(p.to_dict() for p in sharing.base.log)
    peers = [e for e in (sharing.peers or {}).values() if isinstance(e, FramedRawPeer)]
    if not peers:
        return None
    return tuple(sorted(({**p.to_dict(), "by": e.agent} for e in peers for p in e.log),
                        key=lambda d: (d["round"], d["by"], d["rover"])))


def _lander_image(setup: Setup) -> np.ndarray | None:
    """What the lander imaged around itself at landing (``[frames] lander_view``), or None."""
    f = setup.config.frames
    if f.lander_view <= 0:
        return None
    h, w = setup.truth.shape
    rows, cols = np.ogrid[:h, :w]
    lander = setup.topology.base
    near = np.hypot(rows - lander[0], cols - lander[1]) <= f.lander_view
    return np.where(near, setup.truth.classes, UNKNOWN).astype(np.uint8)


def framed_raw(setup: Setup) -> Sharing:
    """``raw``'s ends with ``[frames]``: on the star the base merges through registration, on
    the mesh every agent places what it receives."""
    lc, f, name, reference = setup.config.link, setup.config.frames, setup.name, _lander_image(setup)
    if lc.topology == "mesh":  # raw gossip: every agent places what it receives
        agents = setup.topology.peer_agents(len(setup.team))
        peers: dict[int, PeerEnd] = {
            a: FramedRawPeer(a, None if a == BASE else setup.team[a], setup.truth.shape, setup.starts, agents=agents,
                             journal=setup.journal, frames=f, reference=reference) for a in agents}
        return Sharing(name, setup.team, [peers[k] for k in range(len(setup.team))], peers=peers,
                       journal=setup.journal)
    rovers: list[RoverEnd] = [FramedRawRover(k, r, setup.starts, budget=lc.uplink_bytes,
                                             recent=2 * setup.config.sync_every) for k, r in enumerate(setup.team)]
    base = FramedRawBase(setup.truth.shape, setup.starts, budget=lc.downlink_bytes, frames=f, journal=setup.journal,
                         reference=reference)
    return _with_what_if(Sharing(name, setup.team, rovers, base, journal=setup.journal), setup)


def framed_predictive(setup: Setup) -> Sharing:
    """``predictive``'s ends with ``[frames]`` (the star): the base merges through registration."""
    lc, f = setup.config.link, setup.config.frames
    # a rover writes what it senses around its estimated cell, up to SENSED_BEYOND past its sensor's range
    radius, opts = setup.config.sensor_radius + SENSED_BEYOND, PredictiveOptions(**setup.options)
    rovers: list[RoverEnd] = [FramedPredictiveRover(k, r, setup.starts, budget=lc.uplink_bytes, radius=radius,
                                                    options=opts, recent=2 * setup.config.sync_every)
                              for k, r in enumerate(setup.team)]
    base: BaseEnd = FramedPredictiveBase(setup.truth.shape, setup.starts, budget=lc.downlink_bytes,
                                         radius=radius, frames=f, options=opts, reference=_lander_image(setup))
    return _with_what_if(Sharing(setup.name, setup.team, rovers, base, journal=setup.journal), setup)


def _with_what_if(sharing: Sharing, setup: Setup) -> Sharing:
    """``sharing`` with the oracle's true poses given to its base under :class:`WhatIf`."""
    if isinstance(sharing.base, _Placer) and sharing.base.what_if.oracle:
        sharing.base.true_poses = [r.frame for r in setup.team]
    return sharing


__all__ = ["SENSED_BEYOND", "TRANSFORM_BYTES", "FramedPredictiveBase", "FramedPredictiveRover", "FramedRawBase",
           "FramedRawPeer", "FramedRawRover", "Placing", "WhatIf", "chain", "framed_predictive", "framed_raw",
           "pack_transform", "registrations", "rotation", "track", "unpack_transform", "verdict", "what_if"]
