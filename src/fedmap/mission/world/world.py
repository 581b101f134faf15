"""The rovers' world: where each rover is, what it observes, and how it drives, flies and
plans on its belief. A rover's belief, and what it knows of the others, come from its own
end of the strategy (:attr:`World.ends`); nothing here knows which strategy that is.

One step, for every rover in turn: drive up to ``speed`` cells along the planned path,
observing the footprint from every cell entered (the next cell is always observed before
the move, so a rover never enters a cell that is impassable in the truth: the world checks
it against the truth and stops with an error if it ever would).

With ``[mission] predictor = "learned"`` every rover also runs the shipped map predictor
(:mod:`fedmap.nets.predictor`) on the map it holds (:meth:`World.predicted`) and plans
with the guesses (:mod:`fedmap.mission.world.frontiers`). The guesses live only in this
planning view: they never enter a rover's observations, what it shares, or its belief.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.planning import path_is_valid
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, rover_profile
from fedmap.mission.settings import MissionConfig
from fedmap.mission.world.flight import fly
from fedmap.mission.world.frontiers import cheapest_path, choose_target, plan_path
from fedmap.mission.world.sensing import block_classes, coarse_footprint, disk_offsets, footprint
from fedmap.nets.predictor import MapPredictor, adapt_predictor, check_guesses, predict, shipped_predictor

Cell = tuple[int, int]


@dataclass
class Rover:
    """One rover's state during a run."""

    pos: Cell
    local: np.ndarray  # its own observations (classes, UNKNOWN elsewhere)
    obs_step: np.ndarray  # step each cell was first observed by it (-1: never)
    target: Cell | None = None
    path: list[Cell] = field(default_factory=list)
    trail: list[Cell] = field(default_factory=list)
    distance: float = 0.0
    waypoints: list[Cell] = field(default_factory=list)
    excluded: set = field(default_factory=set)
    replan: bool = True
    kind: str = "rover"  #: rover, or helicopter (its observations are coarse: HelicopterConfig)
    flight: int = 0  #: helicopter: steps in the air this sortie
    charging: int = 0  #: helicopter: steps left on the ground before it may take off
    returning: bool = False  #: helicopter: heading for a landing site
    #: with a profile of its own: the classes it observed under its own limits (None: it has none)
    own: np.ndarray | None = None
    #: with an elevation layer: the heights it observed (metres, its noise included; NaN elsewhere)
    heights: np.ndarray | None = None
    n_sensed: int = 0  #: how many times it has sensed (seeds its height noise)
    #: every write to ``local``: a box ``(row0, row1, col0, col1)`` holding the cells written
    #: (half-open; None: anywhere), in order (what the team's map is built from is kept on it)
    writes: list = field(default_factory=list)
    #: helicopter: every landing, ``(step, cell, steps flown that sortie, "lander" or "observed free")``
    landings: list = field(default_factory=list)
    airborne: list = field(default_factory=list)  #: helicopter: per step from step 1, whether it flew

    def wrote(self, center: Cell | None = None, reach: int = 0) -> None:
        """Record a write to ``local``: its cells are within ``reach`` rows and columns of
        ``center`` (None: anywhere)."""
        if center is None:
            self.writes.append(None)
            return
        h, w = self.local.shape
        r, c = center
        self.writes.append((max(r - reach, 0), min(r + reach + 1, h), max(c - reach, 0), min(c + reach + 1, w)))



def reachable_cells(truth: GridMap, starts: list[Cell], config: MissionConfig,
                    allowed: np.ndarray | None = None) -> np.ndarray:
    """The cells the team can observe (boolean map): every known cell within a rover's sensor
    radius of the free cells it can drive to from its start (8-connected, within ``allowed``
    when the rovers must stay in range), by the team's classes; with helicopters, every known
    cell (they fly over what the rovers cannot cross). Line of sight may hide some of them: it
    is the most the team could see, the share coverage targets are measured against."""
    known = truth.classes != UNKNOWN
    if config.helicopters:
        return known.copy()
    free = truth.classes == FREE
    if allowed is not None:
        free &= allowed
    labels, _ = ndimage.label(free, structure=np.ones((3, 3), bool))
    ids = sorted({int(labels[s]) for s in starts if labels[s]})
    drive = np.isin(labels, ids)
    offsets = disk_offsets(config.sensor_radius)  # what a rover's sensor reaches, as sensing has it
    n = int(np.abs(offsets).max())
    disk = np.zeros((2 * n + 1, 2 * n + 1), bool)
    disk[offsets[:, 0] + n, offsets[:, 1] + n] = True
    return ndimage.binary_dilation(drive, structure=disk) & known


def place_starts(truth: GridMap, config: MissionConfig) -> tuple[list[Cell], Cell]:
    """Start cells (one per rover) and the base station cell, checked against the truth."""
    h, w = truth.shape
    free = truth.classes == FREE

    def inside(cell: Cell, what: str) -> Cell:
        if not (0 <= cell[0] < h and 0 <= cell[1] < w):
            raise FedmapError(f"{what} {list(cell)} is outside the {h}x{w} map")
        return cell

    lander = inside(config.lander, "lander") if config.lander is not None else (h // 2, w // 2)
    base = inside(config.base, "base") if config.base is not None else lander
    if config.starts is not None:
        starts = [inside(s, f"start of rover {k}") for k, s in enumerate(config.starts)]
        for k, s in enumerate(starts):
            if not free[s]:
                raise FedmapError(f"start of rover {k} {list(s)} is impassable (or unknown) in the truth")
        if len(set(starts)) != len(starts):
            raise FedmapError("two rovers are given the same start cell")
        return starts, base
    cells = np.argwhere(free)
    if len(cells) < config.rovers:
        raise FedmapError(f"{config.rovers} rovers but only {len(cells)} free start cells on the map")
    d = (cells[:, 0] - lander[0]) ** 2 + (cells[:, 1] - lander[1]) ** 2
    order = np.lexsort((cells[:, 1], cells[:, 0], d))[: config.rovers]
    if config.start_spread > 0:  # a seeded draw in the start area
        area = np.flatnonzero(d <= config.start_spread ** 2)
        if len(area) < config.rovers:
            raise FedmapError(f"the start area (free cells within {config.start_spread} cells of the lander "
                              f"{list(lander)}) holds {len(area)} cells for {config.rovers} rovers: widen start_spread")
        rng = np.random.default_rng(np.random.SeedSequence([config.seed, 11]))
        order = rng.choice(area, size=config.rovers, replace=False)
    return [(int(cells[i][0]), int(cells[i][1])) for i in order], base


#: A start whose free ground reaches less than this share of the map's free cells is flagged.
SMALL_POCKET = 0.05


def start_pocket_warning(truth: GridMap, config: MissionConfig) -> str | None:
    """A one-line warning when the rovers start on a free pocket cut off from most of the
    map's free ground (they can explore only that pocket), else None. Reachability is
    4-connectivity, the planner's (:mod:`fedmap.maps.planning`)."""
    starts, _ = place_starts(truth, config)
    free = truth.classes == FREE
    labels, _ = ndimage.label(free)
    sizes = np.bincount(labels.ravel())
    reach = int(sum(sizes[lab] for lab in {labels[s] for s in starts} if lab))
    total = int(free.sum())
    if total and reach < SMALL_POCKET * total:
        return (f"the rovers start on free ground of {reach:,} cells, cut off from the rest of the map's "
                f"{total:,} free cells: they can explore only that pocket (set [mission] lander or starts, or "
                f"another terrain or slope limit)")
    return None


def plan_waypoints(truth: GridMap, config: MissionConfig) -> list[list[Cell]]:
    """The fixed traverse of every rover (``mode = "waypoints"``): given, or seeded random
    free cells (as a planner would pick them from orbital maps)."""
    if config.waypoints is not None:
        return [list(w) for w in config.waypoints]
    cells = np.argwhere(truth.classes == FREE)
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([config.seed, 7]).spawn(config.rovers)]
    return [[(int(cells[i][0]), int(cells[i][1])) for i in g.choice(len(cells), size=config.n_waypoints)]
            for g in rngs]



#: Steps between two checks of a rover's guesses on its own map (``[mission] predictor_check``).
GUESS_CHECK_EVERY = 10


@dataclass(frozen=True)
class PredictedView:
    """A map with the predictor's guesses, for planning only: ``classes`` is the map with
    every unknown cell filled with its likelier class, ``predicted`` marks those cells, and
    ``p_impassable`` is P(impassable) of every cell (0 or 1 where the map knows the cell).
    A predicted cell is never an observation: nothing here is shared or scored as observed."""

    classes: np.ndarray
    predicted: np.ndarray
    p_impassable: np.ndarray

    @classmethod
    def of(cls, predictor: MapPredictor, belief: np.ndarray) -> PredictedView:
        _, p_imp = predict(predictor, belief)
        predicted = belief == UNKNOWN
        classes = np.where(predicted, np.where(p_imp > 0.5, IMPASSABLE, FREE), belief).astype(np.uint8)
        return cls(classes, predicted, p_imp)


def start_team(config: MissionConfig, shape: tuple[int, int], starts: list[Cell], base: Cell,
               waypoints: list[list[Cell]]) -> list[Rover]:
    """The team before its first step, knowing nothing: a rover at each start (its
    ``waypoints`` in ``waypoints`` mode; with an elevation layer, no heights yet), then the
    helicopters at the base."""
    team = [Rover(s, np.full(shape, UNKNOWN, dtype=np.uint8), np.full(shape, -1, dtype=np.int64),
                  trail=[s], waypoints=list(w) if config.mode == "waypoints" else [])
            for s, w in zip(starts, waypoints)]
    if "elevation" in config.layers:  # what each rover measures of the elevation layer
        for r in team:
            r.heights = np.full(shape, np.nan, dtype=np.float32)
    team += [Rover(base, np.full(shape, UNKNOWN, dtype=np.uint8), np.full(shape, -1, dtype=np.int64),
                   trail=[base], kind="helicopter") for _ in range(config.helicopters)]
    return team


class World:
    """Every member of the team on ``truth``: rovers from ``starts`` (their ``waypoints`` in
    ``waypoints`` mode), then the helicopters from the base. ``ends[k]`` is member ``k``'s
    end of the strategy (set by the run before the first step): its belief and what it
    heard of the others."""

    def __init__(self, config: MissionConfig, truth: GridMap, elevation: np.ndarray | None, starts: list[Cell],
                 base: Cell, waypoints: list[list[Cell]], *, prior: np.ndarray | None = None,
                 profiles: dict[str, np.ndarray] | None = None, thresholds: TraversabilityThresholds | None = None,
                 allowed: np.ndarray | None = None) -> None:
        self.config, self.truth, self.elevation, self.prior, self.base = config, truth, elevation, prior, base
        shape = truth.shape
        self.team = start_team(config, shape, starts, base, waypoints)
        f = config.helicopter.resolution
        self.coarse = np.repeat(np.repeat(block_classes(truth.classes, f, UNKNOWN), f, axis=0), f,
                                axis=1)[:shape[0], :shape[1]] if config.helicopters else None
        self.origin = (float(np.mean([s[0] for s in starts])), float(np.mean([s[1] for s in starts])))
        # each member's own classes of the terrain (None: it follows the shared thresholds)
        #: every member's traversability profile (helicopters follow the team's)
        self.profiles = names = [*config.rover_profiles, *(["team"] * config.helicopters)]
        self.own_truth = [None if p == "team" else (profiles or {})[p] for p in names]
        for r, t in zip(self.team, self.own_truth):
            r.own = None if t is None else np.full(shape, UNKNOWN, dtype=np.uint8)
        # the elevation layer's thresholds, with which each rover derives its classes
        self.own_thresholds = [thresholds if p == "team" else rover_profile(p) for p in names]
        self._derived: dict[int, tuple[tuple, np.ndarray]] = {}
        self.allowed = allowed
        self.ends: list = []
        #: the map predictor every rover runs on the map it holds (None: plan without guesses)
        self.predictor: MapPredictor | None = shipped_predictor() if config.predictor == "learned" else None
        #: per member: the predictor it plans with (the shipped one, or its own copy adapted
        #: to its map with ``predictor_adapt``; never the coder's, which stays the shipped one)
        self.models: list[MapPredictor | None] = [self.predictor] * len(self.team)
        self._predicted: dict[int, tuple[bytes, PredictedView]] = {}
        #: per member: whether it plans with the guesses now (with ``predictor_check`` it starts
        #: aside and joins once a check says they beat "all free" on its own map by 3 points)
        self.guessing = [self.predictor is not None and not config.predictor_check] * len(self.team)
        #: every check of the guesses: (step, member, cells, accuracy, all free, guessing after it)
        self.checks: list[tuple[int, int, int, float, float, bool]] = []

    def positions(self) -> list[Cell]:
        """Every member's cell now, in team order."""
        return [r.pos for r in self.team]

    def observed(self) -> np.ndarray:
        """``(members, h, w)``: the cells each member has observed (its own map's known cells)."""
        return np.stack([r.local != UNKNOWN for r in self.team])

    def in_true_frame(self, k: int, belief: np.ndarray, base: Any = None) -> np.ndarray:
        """Member ``k``'s belief in the true frame, where it is scored: with known poses, as it is."""
        return belief

    # -- sensing and driving
    def sense(self, k: int, t: int) -> None:
        r = self.team[k]
        c = self.config
        if r.kind == "helicopter":
            assert self.coarse is not None
            hc = c.helicopter
            seen = coarse_footprint(r.pos, self.truth.shape, hc.sensor_radius, hc.resolution) & (self.coarse != UNKNOWN)
            new = seen & (r.local == UNKNOWN)
            r.local[new] = self.coarse[new]
            r.obs_step[new] = t
            r.wrote(r.pos, int(hc.sensor_radius) + hc.resolution)  # a block whose centre is in range
            return
        mask = footprint(r.pos, self.truth.shape, c.sensor_radius,
                         elevation=self.elevation if c.line_of_sight else None, height_m=c.sensor_height_m)
        new = mask & (r.local == UNKNOWN)
        r.local[new] = self.truth.classes[new]
        r.obs_step[new] = t
        r.wrote(r.pos, int(c.sensor_radius))
        own = self.own_truth[k]
        if r.own is not None and own is not None:
            r.own[new] = own[new]
        if r.heights is not None and self.elevation is not None:
            r.n_sensed += 1
            z = self.elevation[new]
            if c.elevation_noise_m > 0:
                rng = np.random.default_rng(np.random.SeedSequence([c.seed, k, r.n_sensed, 5]))
                z = z + rng.normal(0.0, c.elevation_noise_m, size=z.shape)
            r.heights[new] = z

    def target_done(self, r: Rover, belief: np.ndarray) -> bool:
        if r.target is None or r.pos == r.target:
            return True
        if self.config.mode == "waypoints":
            return False
        off = disk_offsets(self.config.sensor_radius)
        rr, cc = off[:, 0] + r.target[0], off[:, 1] + r.target[1]
        h, w = belief.shape
        ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        return not (belief[rr[ok], cc[ok]] == UNKNOWN).any()

    def _pick(self, k: int, belief: np.ndarray) -> Cell | None:
        r = self.team[k]
        if self.config.mode == "waypoints":
            while r.waypoints and (r.waypoints[0] in r.excluded or belief[r.waypoints[0]] == IMPASSABLE
                                   or r.waypoints[0] == r.pos):
                r.waypoints.pop(0)
            return r.waypoints[0] if r.waypoints else None
        heading = (*self.origin, 2 * math.pi * k / self.config.rovers)
        guess = self.predicted(k, belief).p_impassable if self.guessing[k] else None
        return choose_target(belief, r.pos, radius=self.config.sensor_radius, unknown_cost=self.config.unknown_cost,
                             others=self.ends[k].others(), allowed=self.allowed, excluded=r.excluded,
                             heading=heading, p_impassable=guess)

    def predicted(self, k: int, belief: np.ndarray) -> PredictedView:
        """Rover ``k``'s planning view with the predictor's guesses (cached while its map and
        its copy of the predictor are unchanged): the map it holds, every unknown cell filled
        with its likelier class and marked as predicted. Needs ``predictor = "learned"``."""
        model = self.models[k]
        assert model is not None
        b = np.ascontiguousarray(belief, dtype=np.uint8)
        key = hashlib.blake2b(b.tobytes(), digest_size=16).digest()
        hit = self._predicted.get(k)
        if hit is not None and hit[0] == key:
            return hit[1]
        view = PredictedView.of(model, b)
        self._predicted[k] = (key, view)
        return view

    def own_view(self, k: int, belief: np.ndarray) -> np.ndarray:
        """Rover ``k``'s belief with the cells it observed itself in its own classes (its
        profile's limits); with an elevation layer, the classes it derives with its own
        limits from the heights it holds (its own and those shared with it); the shared
        classes elsewhere.

        Derived classes replace shared ones only for a rover with a profile of its own: the
        shared classes are the team's, not its limits. A ``team`` rover's shared classes
        are already the team's limits applied to exact observations, while classes derived
        from shared heights carry the heights' quantisation and noise (a cell at a limit
        flips), so for it they fill only cells whose class it does not hold."""
        r = self.team[k]
        view = belief
        if r.heights is not None:
            derived = self.derived(k)
            use = derived != UNKNOWN
            if self.own_truth[k] is None:  # a team rover: its shared classes win where it holds them
                use &= view == UNKNOWN
            view = np.where(use, derived, view)
            view = np.where(r.local != UNKNOWN, r.local if r.own is None else r.own, view)
        elif r.own is not None:
            view = np.where(r.own != UNKNOWN, r.own, view)
        return view.astype(np.uint8, copy=False)

    def derived(self, k: int) -> np.ndarray:
        """The classes rover ``k`` derives, with its own thresholds, from every height it
        holds (cached until they change)."""
        r = self.team[k]
        assert r.heights is not None
        key = (r.n_sensed, self.ends[k].heights_version())
        hit = self._derived.get(k)
        if hit is not None and hit[0] == key:
            return hit[1]
        shared = self.ends[k].heights()
        z = r.heights if shared is None else np.where(np.isfinite(r.heights), r.heights, shared)
        if np.isfinite(z).any() and min(z.shape) >= 3:
            out = dem_to_traversability(Dem(z, self.truth.pixel_size), self.own_thresholds[k]).classes
        else:
            out = np.full(z.shape, UNKNOWN, dtype=np.uint8)
        self._derived[k] = (key, out)
        return out

    def planning_map(self, belief: np.ndarray, k: int | None = None) -> np.ndarray:
        """What a rover plans its path on: its belief (its own classes where it has them), and
        the prior where it has no observation."""
        if k is not None:
            belief = self.own_view(k, belief)
        if self.prior is None:
            return belief
        return np.where(belief == UNKNOWN, self.prior, belief).astype(np.uint8)

    def plan(self, k: int, belief: np.ndarray) -> None:
        r = self.team[k]
        on = self.planning_map(belief, k)
        passable = (on == FREE) | (on == UNKNOWN)
        if (not r.replan and r.path and not self.target_done(r, belief)
                and path_is_valid(passable, [r.pos, *r.path])):
            return
        if self.config.mode == "waypoints" and r.target is not None and r.pos == r.target and r.waypoints:
            r.waypoints.pop(0)
        r.replan, r.path, r.target = False, [], None
        for _ in range(8):
            target = self._pick(k, belief)
            if target is None:
                return
            if not self.guessing[k]:
                path = plan_path(on, r.pos, target)
            else:
                path = cheapest_path(on, r.pos, target, self.config.unknown_cost,
                                     self.predicted(k, belief).p_impassable)
            if not path and self.prior is not None:  # the prior is a guess: never let it trap a rover
                path = plan_path(self.own_view(k, belief), r.pos, target)
            if path:
                r.target, r.path = target, path
                return
            r.excluded.add(target)

    def check_guesses(self, k: int, t: int) -> None:
        """Rover ``k`` checks the guesses on its own map at step ``t``
        (:func:`~fedmap.nets.predictor.check_guesses`, seeded by the mission, the rover and the
        step) and plans with them from now on only if they beat "all free" there by
        :data:`~fedmap.nets.predictor.CHECK_MARGIN`; a check with
        too few cells changes nothing."""
        model = self.models[k]
        assert model is not None
        c = self.config
        rng = np.random.default_rng(np.random.SeedSequence([c.seed, k, t, 68]))
        got = check_guesses(model, self.ends[k].belief(), rng, radius=c.sensor_radius)
        pays = got.pays
        if pays is not None and pays != self.guessing[k]:
            self.guessing[k] = pays
            self.team[k].replan = True
        self.checks.append((t, k, got.cells, got.accuracy, got.all_free, self.guessing[k]))

    def adapt(self, k: int, t: int) -> None:
        """Rover ``k`` fine-tunes its copy of the predictor on its own map at step ``t``
        (:func:`~fedmap.nets.predictor.adapt_predictor` in a window around it, seeded by the
        mission, the rover and the step), for planning only: the shipped weights (the coder's)
        are never changed."""
        model = self.models[k]
        assert model is not None
        c = self.config
        rng = np.random.default_rng(np.random.SeedSequence([c.seed, k, t, 69]))
        self.models[k] = adapt_predictor(model, self.ends[k].belief(), rng, radius=c.sensor_radius,
                                         around=self.team[k].pos)
        self._predicted.pop(k, None)  # its guesses were the old copy's

    def drive(self, k: int, t: int) -> None:
        r = self.team[k]
        if r.kind == "helicopter":
            fly(self, k, t)
            return
        if self.predictor is not None and t % GUESS_CHECK_EVERY == 0:
            if self.config.predictor_check:
                self.check_guesses(k, t)
            if self.config.predictor_adapt:  # after the check: it scores the copy adapted 10 steps ago
                self.adapt(k, t)
        for _ in range(self.config.speed):
            belief = self.ends[k].belief()
            self.plan(k, belief)
            if not r.path:
                return
            nxt = r.path[0]
            if self.own_view(k, belief)[nxt] == IMPASSABLE:  # revealed on the way: replan next time
                r.replan = True
                return
            own = self.own_truth[k]
            if (self.truth.classes if own is None else own)[nxt] == IMPASSABLE:
                raise RuntimeError(f"rover {k} would enter impassable cell {nxt}: the planner broke its contract")
            r.path.pop(0)
            r.distance += math.hypot(nxt[0] - r.pos[0], nxt[1] - r.pos[1])
            r.pos = nxt
            r.trail.append(nxt)
            self.sense(k, t)
