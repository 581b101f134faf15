"""The mission loop: every strategy runs the same mission (terrain, starts, seeds, link).

One step, for every rover in turn: drive up to ``speed`` cells along the planned path,
observing the footprint from every cell entered (the next cell is always observed
before the move, so a rover never enters a cell that is impassable in the truth: the
loop checks it against the truth and stops with an error if it ever would). At every
``sync_every``-th step each rover offers its uplink to the link; the base station runs
its round when the uplinks arrive (``latency`` steps later) and its downlinks arrive
``latency`` steps after that. See :mod:`fedmap.mission.strategies` for what each
strategy sends and :mod:`fedmap.mission.link` for the link.

Results are typed: :class:`StrategyRun` holds a strategy's :class:`TimeSeries` (per
step: team coverage, redundant observation, each rover's belief accuracy, distance and
cumulative bytes, messages delivered and dropped; per evaluation step, every sync and the
last step, its :class:`EvalSeries`: the base's global map scores, PSNR, SSIM, strict and
tolerant path F1, and each rover's belief strict path F1) and its :class:`MissionSummary`.
They become dicts only for ``metrics.json`` (``to_dict``).
"""

from __future__ import annotations

import hashlib
import heapq
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.evaluation.paths import PathScores, path_f1
from fedmap.evaluation.scores import MapScores, score_map
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.orbital import orbital_prior
from fedmap.maps.planning import path_is_valid
from fedmap.maps.sources import TerrainSource, load_terrain, needs_dem
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, rover_profile
from fedmap.mission.frontiers import choose_target, plan_path
from fedmap.mission.link import (
    BASE,
    DOWN,
    UP,
    Link,
    MeshTopology,
    Message,
    StarTopology,
    Topology,
    components,
    elect_leaders,
    route,
)
from fedmap.mission.peers import Admm, ModelGossip, PeerStrategy, RawGossip
from fedmap.mission.sensing import block_classes, coarse_footprint, disk_offsets, footprint
from fedmap.mission.settings import MissionConfig
from fedmap.mission.strategies import DroppedUpdate, Strategy, make_strategy

Cell = tuple[int, int]
#: Coverage levels whose first step is reported.
COVERAGE_LEVELS = (0.5, 0.8, 0.95)
#: A rover's belief "good enough to plan on": strict path F1 at least this.
F1_GOAL = 0.9


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
    #: helicopter: every landing, ``(step, cell, steps flown that sortie, "lander" or "observed free")``
    landings: list = field(default_factory=list)
    airborne: list = field(default_factory=list)  #: helicopter: per step from step 1, whether it flew


@dataclass(frozen=True)
class EvalSeries:
    """The scores at every evaluation step (every sync and the last step), one entry per
    evaluation step. The global map is the base station's; path F1 plans strict A* on
    ``eval_pairs`` seeded start/goal pairs, UNKNOWN impassable."""

    step: tuple[int, ...]  #: the evaluation steps
    psnr: tuple[float, ...]  #: PSNR of the base's global map against the truth, dB
    ssim: tuple[float, ...]  #: SSIM of the base's global map
    accuracy: tuple[float, ...]  #: share of the base's global map's cells equal to the truth (0..1)
    f1: tuple[float, ...]  #: strict path F1 of the base's global map
    f1_tolerant: tuple[float, ...]  #: tolerant path F1 of the base's global map
    belief_f1: tuple[tuple[float, ...], ...]  #: per rover: strict path F1 of its belief
    #: per rover: executed path success of its belief: the share of the pairs the truth
    #: connects whose path planned on the belief, driven on the truth, reaches the goal
    #: without entering an impassable cell
    belief_success: tuple[tuple[float, ...], ...]

    def to_dict(self) -> dict[str, list]:
        return {"step": list(self.step), "psnr": list(self.psnr), "ssim": list(self.ssim),
                "accuracy": list(self.accuracy), "f1": list(self.f1), "f1_tolerant": list(self.f1_tolerant),
                "belief_f1": [list(f) for f in self.belief_f1],
                "belief_success": [list(f) for f in self.belief_success]}


@dataclass(frozen=True)
class TimeSeries:
    """One strategy's mission, step by step: one entry per step, 0 (the start) to ``steps``.

    Shares are of the map's cells (0..1); distances are in cells; bytes and message counts
    are cumulative since the start. Per-rover entries are tuples in team order.
    """

    step: tuple[int, ...]  #: the steps, 0 to ``steps``
    coverage: tuple[float, ...]  #: share of cells any rover has observed
    redundant: tuple[float, ...]  #: share of cells two or more rovers have observed
    accuracy: tuple[tuple[float, ...], ...]  #: per rover: share of its belief's cells equal to the truth (UNKNOWN wrong)
    #: per rover: its belief's accuracy on the cells some rover has observed (knowing)
    accuracy_observed: tuple[tuple[float, ...], ...]
    #: per rover: its belief's accuracy on the cells no rover has observed (guessing; UNKNOWN
    #: is wrong, so a strategy that shares only observations scores 0 here)
    accuracy_unobserved: tuple[tuple[float, ...], ...]
    #: per rover: share of the cells it plans on as FREE (its belief, and the prior where it
    #: has none) that are impassable in the truth: the hazards it would drive into
    false_free: tuple[tuple[float, ...], ...]
    distance: tuple[tuple[float, ...], ...]  #: per rover: distance driven, cells
    bytes_up: tuple[tuple[int, ...], ...]  #: per rover: bytes it spent on the uplink
    bytes_down: tuple[tuple[int, ...], ...]  #: per rover: bytes the base spent on its downlink
    up_delivered: tuple[int, ...]  #: whole team: uplink messages delivered (arrived by this step)
    up_dropped: tuple[int, ...]  #: whole team: uplink messages not delivered (lost, over budget, out of range, ...)
    down_delivered: tuple[int, ...]  #: whole team: downlink messages delivered (arrived by this step)
    down_dropped: tuple[int, ...]  #: whole team: downlink messages not delivered
    eval: EvalSeries  #: the scores at every evaluation step

    def to_dict(self) -> dict[str, Any]:
        """The ``series`` of ``metrics.json``."""
        return {"step": list(self.step), "coverage": list(self.coverage), "redundant": list(self.redundant),
                "accuracy": [list(a) for a in self.accuracy],
                "accuracy_observed": [list(a) for a in self.accuracy_observed],
                "accuracy_unobserved": [list(a) for a in self.accuracy_unobserved],
                "false_free": [list(f) for f in self.false_free],
                "distance": [list(d) for d in self.distance],
                "bytes_up_per_rover": [list(b) for b in self.bytes_up],
                "bytes_down_per_rover": [list(b) for b in self.bytes_down],
                "up_delivered": list(self.up_delivered), "up_dropped": list(self.up_dropped),
                "down_delivered": list(self.down_delivered), "down_dropped": list(self.down_dropped),
                "eval": self.eval.to_dict()}


@dataclass(frozen=True)
class MissionSummary:
    """One strategy's mission in a few values: when levels were first reached, and the
    values at the last step (``final_*``). Steps are None when the level was never reached.
    """

    coverage_steps: dict[float, int | None]  #: first step the team's coverage reached each of COVERAGE_LEVELS
    belief_f1_goal: float  #: the strict path F1 a belief must reach (:data:`F1_GOAL`)
    first_belief_f1_step: int | None  #: first evaluation step any rover's belief reached the goal
    first_belief_f1_step_per_rover: tuple[int | None, ...]  #: the same, per rover
    final_coverage: float  #: share of cells any rover observed
    final_redundant: float  #: share of cells two or more rovers observed
    final_belief_accuracy_mean: float  #: belief accuracy (share of cells), mean over the rovers
    final_false_free_mean: float  #: false-free rate (TimeSeries.false_free), mean over the rovers
    final_accuracy_observed_mean: float  #: belief accuracy on the cells observed, mean over the rovers
    final_accuracy_unobserved_mean: float  #: belief accuracy on the cells nobody observed, mean over the rovers
    final_path_success_mean: float  #: executed path success of the beliefs (EvalSeries.belief_success), mean
    final_distance_total: float  #: distance driven by the whole team, cells
    final_global_psnr: float  #: the base's global map: PSNR, dB
    final_global_ssim: float  #: the base's global map: SSIM
    final_global_accuracy: float  #: the base's global map: share of cells equal to the truth
    final_global_f1: float  #: the base's global map: strict path F1
    final_global_f1_tolerant: float  #: the base's global map: tolerant path F1
    final_belief_f1_mean: float  #: strict path F1 of the rovers' beliefs, mean over the rovers
    bytes_up: int  #: uplink bytes of the whole team (sum over the rovers)
    bytes_down: int  #: downlink bytes of the whole team (sum over the rovers)
    #: mean bytes per message offered on a link that was up (in range, not down), each hop of a
    #: relayed message counted: one message per link, direction and round, as RAMEN reports it
    bytes_per_link_round: float
    messages: dict[str, int]  #: ledger entries per ``<direction>_<status>``, e.g. ``up_lost``
    #: with an elevation layer: RMSE (metres) of the heights the base holds, on the cells it
    #: holds, against the true elevation, and the share of the map's cells it holds (None: no layer)
    final_height_rmse_m: float | None = None
    final_height_coverage: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The ``summary`` of ``metrics.json``."""
        return {
            "coverage_steps": {f"{int(level * 100)}%": t for level, t in self.coverage_steps.items()},
            "belief_f1_goal": self.belief_f1_goal,
            "first_belief_f1_step": self.first_belief_f1_step,
            "first_belief_f1_step_per_rover": list(self.first_belief_f1_step_per_rover),
            "final": {"coverage": self.final_coverage, "redundant": self.final_redundant,
                      "belief_accuracy_mean": self.final_belief_accuracy_mean,
                      "false_free_mean": self.final_false_free_mean,
                      "accuracy_observed_mean": self.final_accuracy_observed_mean,
                      "accuracy_unobserved_mean": self.final_accuracy_unobserved_mean,
                      "path_success_mean": self.final_path_success_mean,
                      "distance_total": self.final_distance_total, "global_psnr": self.final_global_psnr,
                      "global_ssim": self.final_global_ssim, "global_accuracy": self.final_global_accuracy,
                      "global_f1": self.final_global_f1, "global_f1_tolerant": self.final_global_f1_tolerant,
                      "belief_f1_mean": self.final_belief_f1_mean},
            "team_bytes": {"up": self.bytes_up, "down": self.bytes_down},
            "bytes_per_link_round": self.bytes_per_link_round,
            "messages": dict(self.messages),
            **({"elevation": {"rmse_m": self.final_height_rmse_m, "coverage": self.final_height_coverage}}
               if self.final_height_rmse_m is not None else {}),
        }


@dataclass(frozen=True)
class Frame:
    """What the animation draws at one step."""

    step: int
    beliefs: list[np.ndarray]  #: every rover's belief (classes)
    global_map: np.ndarray  #: the base's global map (classes)
    positions: list[Cell]  #: every rover's cell
    trail_len: list[int]  #: how much of each rover's trail it has driven (cells of the trail)
    links: tuple[tuple[int, int], ...] = ()  #: peer topologies: the links up at the last sync (agents; -1: lander)
    leaders: tuple[int, ...] = ()  #: leader topology: the agents leading at the last sync


@dataclass(frozen=True)
class StrategyRun:
    """One strategy's mission: time series, summary, ledger, and what the animation draws."""

    name: str  #: the strategy (none, raw, predictive, paper, fedmap, central)
    series: TimeSeries  #: per step (0 to steps) and per evaluation step
    summary: MissionSummary  #: first steps a level was reached, and the final values
    ledger: list[Message]  #: one entry per message, with its bytes and its fate
    frames: list[Frame]  #: what the animation draws, one per step
    trails: list[list[Cell]]  #: each rover's cells driven, in order
    seconds: float  #: wall time of this strategy's run, seconds
    #: the strategy's :attr:`~fedmap.mission.strategies.Strategy.dropped` (None: it sends no model updates)
    dropped_updates: tuple[DroppedUpdate, ...] | None = None
    #: model strategies: at every sync, before training, how many models behind the base each rover is
    #: (``{"round": r, "lag": [...]}``; None in ``lag``: it holds none the base still keeps)
    model_lag: tuple[dict, ...] | None = None
    strategy: Strategy | None = None  # the final state (for inspection; not written)

    def to_dict(self) -> dict[str, Any]:
        """The strategy's entry of ``metrics.json`` (no frames, trails or strategy state)."""
        out: dict[str, Any] = {"summary": self.summary.to_dict(), "seconds": self.seconds,
                               "series": self.series.to_dict(), "ledger": [m.to_dict() for m in self.ledger]}
        if self.dropped_updates is not None:
            out["dropped_updates"] = [d.to_dict() for d in self.dropped_updates]
        if self.model_lag is not None:
            out["model_lag"] = list(self.model_lag)
        return out


@dataclass(frozen=True)
class MissionResult:
    """Every strategy's run of one mission (same terrain, starts, base and link).

    A final value is ``result.runs["raw"].summary.final_global_f1``; a curve is
    ``result.runs["raw"].series.coverage`` (one value per step); every message is in
    ``result.runs["raw"].ledger``.
    """

    config: MissionConfig  #: the mission as run
    truth: GridMap  #: the ground truth the rovers explore
    starts: list[Cell]  #: each rover's start cell (row, col)
    base: Cell  #: the base station's cell (row, col)
    runs: dict[str, StrategyRun]  #: strategy name -> its run, in the order they ran
    seconds: float  #: wall time of the whole mission, seconds


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


class _Scorer:
    """Map scores, cached by the map's bytes (unchanged maps are not planned on again)."""

    def __init__(self, truth: GridMap, pairs: int, seed: int) -> None:
        self.truth, self.pairs, self.seed = truth, pairs, seed
        self.full: dict[bytes, MapScores] = {}
        self.paths: dict[bytes, PathScores] = {}

    @staticmethod
    def _key(classes: np.ndarray) -> bytes:
        return hashlib.blake2b(np.ascontiguousarray(classes).tobytes(), digest_size=16).digest()

    def scores(self, classes: np.ndarray) -> MapScores:
        key = self._key(classes)
        if key not in self.full:
            s = score_map(self.truth.classes, classes, pairs=self.pairs, seed=self.seed)
            self.full[key] = s
            self.paths[key] = s.path
        return self.full[key]

    def path(self, classes: np.ndarray) -> PathScores:
        """Strict path scores of a map (F1, and the executed success rate)."""
        key = self._key(classes)
        if key not in self.paths:
            self.paths[key] = path_f1(self.truth.classes, classes, n_pairs=self.pairs, seed=self.seed)
        return self.paths[key]


@dataclass(frozen=True)
class _StepRow:
    """One step's entry of every :class:`TimeSeries` series (see there)."""

    step: int
    coverage: float
    redundant: float
    accuracy: tuple[float, ...]
    accuracy_observed: tuple[float, ...]
    accuracy_unobserved: tuple[float, ...]
    false_free: tuple[float, ...]
    distance: tuple[float, ...]
    bytes_up: tuple[int, ...]
    bytes_down: tuple[int, ...]
    up_delivered: int
    up_dropped: int
    down_delivered: int
    down_dropped: int


@dataclass(frozen=True)
class _EvalRow:
    """One evaluation step's entry of every :class:`EvalSeries` series (see there)."""

    step: int
    psnr: float
    ssim: float
    accuracy: float
    f1: float
    f1_tolerant: float
    belief_f1: tuple[float, ...]
    belief_success: tuple[float, ...]


def _series(rows: list[_StepRow], evals: list[_EvalRow]) -> TimeSeries:
    """The time series of the recorded rows (one per step, one per evaluation step)."""
    ev = EvalSeries(step=tuple(e.step for e in evals), psnr=tuple(e.psnr for e in evals),
                    ssim=tuple(e.ssim for e in evals), accuracy=tuple(e.accuracy for e in evals),
                    f1=tuple(e.f1 for e in evals), f1_tolerant=tuple(e.f1_tolerant for e in evals),
                    belief_f1=tuple(e.belief_f1 for e in evals), belief_success=tuple(e.belief_success for e in evals))
    return TimeSeries(step=tuple(r.step for r in rows), coverage=tuple(r.coverage for r in rows),
                      redundant=tuple(r.redundant for r in rows), accuracy=tuple(r.accuracy for r in rows),
                      accuracy_observed=tuple(r.accuracy_observed for r in rows),
                      accuracy_unobserved=tuple(r.accuracy_unobserved for r in rows),
                      false_free=tuple(r.false_free for r in rows), distance=tuple(r.distance for r in rows),
                      bytes_up=tuple(r.bytes_up for r in rows), bytes_down=tuple(r.bytes_down for r in rows),
                      up_delivered=tuple(r.up_delivered for r in rows), up_dropped=tuple(r.up_dropped for r in rows),
                      down_delivered=tuple(r.down_delivered for r in rows),
                      down_dropped=tuple(r.down_dropped for r in rows), eval=ev)


def _share(hit: np.ndarray, where: np.ndarray) -> float:
    """The share of the ``where`` cells that are ``hit`` (1.0 when there are none: nothing to get wrong)."""
    n = int(where.sum())
    return float((hit & where).sum() / n) if n else 1.0


class _Run:
    """One strategy's mission, step by step."""

    def __init__(self, name: str, config: MissionConfig, truth: GridMap, elevation: np.ndarray | None,
                 starts: list[Cell], base: Cell, waypoints: list[list[Cell]], scorer: _Scorer,
                 frame_every: int, prior: np.ndarray | None = None,
                 profiles: dict[str, np.ndarray] | None = None,
                 thresholds: TraversabilityThresholds | None = None,
                 profile_scorers: dict[str, _Scorer] | None = None) -> None:
        self.name, self.config, self.truth, self.elevation = name, config, truth, elevation
        self.prior = prior
        self.scorer, self.frame_every = scorer, frame_every
        shape = truth.shape
        self.team = [Rover(s, np.full(shape, UNKNOWN, dtype=np.uint8), np.full(shape, -1, dtype=np.int64),
                           trail=[s], waypoints=list(w) if config.mode == "waypoints" else [])
                     for s, w in zip(starts, waypoints)]
        self.team += [Rover(base, np.full(shape, UNKNOWN, dtype=np.uint8), np.full(shape, -1, dtype=np.int64),
                            trail=[base], kind="helicopter") for _ in range(config.helicopters)]
        hc = config.helicopter
        f = hc.resolution
        self.coarse = np.repeat(np.repeat(block_classes(truth.classes, f, UNKNOWN), f, axis=0), f,
                                axis=1)[:shape[0], :shape[1]] if config.helicopters else None
        lc = config.link
        self.topology: Topology = StarTopology(base, lc.max_range) if lc.topology == "star" else \
            MeshTopology(base, lc.peer_range, lc.lander_agent)
        self.base = base
        self.link = Link(lc, self.topology)
        self.origin = (float(np.mean([s[0] for s in starts])), float(np.mean([s[1] for s in starts])))
        budget = {"up": lc.uplink_bytes, "down": lc.downlink_bytes, "peer": lc.peer_bytes}
        lander_agent = lc.lander_agent or lc.topology == "star"
        self.strategy: Strategy
        if name in ("gossip", "admm"):
            self.strategy = (ModelGossip if name == "gossip" else Admm)(
                truth, self.team, budget, base=base, lander_agent=lander_agent,
                settings=dict(config.methods.get(name, {})), seed=config.seed)
        elif name == "raw" and lc.topology != "star":
            self.strategy = RawGossip(truth, self.team, budget, base=base, lander_agent=lander_agent)
        else:
            self.strategy = make_strategy(name, truth, self.team, budget, methods=config.methods,
                                          seed=config.seed, radius=config.sensor_radius,
                                          height_q=config.elevation_q_m if "elevation" in config.layers else None,
                                          train_on=config.train_on, replay=config.replay)
        self.links: tuple[tuple[int, int], ...] = ()
        # each rover's own classes of the terrain (None: it follows the shared thresholds), and its scorer
        names = [*config.rover_profiles, *(["team"] * config.helicopters)]
        self.own_truth = [None if p == "team" else (profiles or {})[p] for p in names]
        self.own_scorer = [scorer if p == "team" else (profile_scorers or {})[p] for p in names]
        for r, t in zip(self.team, self.own_truth):
            r.own = None if t is None else np.full(shape, UNKNOWN, dtype=np.uint8)
        # the elevation layer: what each rover measures, and the thresholds it derives its classes with
        self.with_heights = "elevation" in config.layers
        if self.with_heights:
            for r in self.team[:config.rovers]:
                r.heights = np.full(shape, np.nan, dtype=np.float32)
        self.own_thresholds = [thresholds if p == "team" else rover_profile(p) for p in names]
        self._derived: dict[int, tuple[tuple, np.ndarray]] = {}
        self.leaders: tuple[int, ...] = ()
        self.allowed = self.topology.region(shape) if config.stay_in_range else None
        self.queue: list = []
        self.seq = 0
        self.rows: list[_StepRow] = []
        self.evals: list[_EvalRow] = []
        self.frames: list[Frame] = []

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
            return
        mask = footprint(r.pos, self.truth.shape, c.sensor_radius,
                         elevation=self.elevation if c.line_of_sight else None, height_m=c.sensor_height_m)
        new = mask & (r.local == UNKNOWN)
        r.local[new] = self.truth.classes[new]
        r.obs_step[new] = t
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

    def _target_done(self, r: Rover, belief: np.ndarray) -> bool:
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
        return choose_target(belief, r.pos, radius=self.config.sensor_radius, unknown_cost=self.config.unknown_cost,
                             others=self.strategy.others(k), allowed=self.allowed, excluded=r.excluded,
                             heading=heading)

    def own_view(self, k: int, belief: np.ndarray) -> np.ndarray:
        """Rover ``k``'s belief with the cells it observed itself in its own classes (its
        profile's limits); with an elevation layer, the classes it derives with its own
        limits from the heights it holds (its own and those shared with it) where they
        allow it; the shared classes elsewhere."""
        r = self.team[k]
        view = belief
        if r.heights is not None:
            derived = self.derived(k)
            view = np.where(derived != UNKNOWN, derived, view)
            view = np.where(r.local != UNKNOWN, r.local if r.own is None else r.own, view)
        elif r.own is not None:
            view = np.where(r.own != UNKNOWN, r.own, view)
        return view.astype(np.uint8, copy=False)

    def derived(self, k: int) -> np.ndarray:
        """The classes rover ``k`` derives, with its own thresholds, from every height it
        holds (cached until they change)."""
        r = self.team[k]
        assert r.heights is not None
        key = (r.n_sensed, self.strategy.heights_version(k))
        hit = self._derived.get(k)
        if hit is not None and hit[0] == key:
            return hit[1]
        shared = self.strategy.heights(k)
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
        if (not r.replan and r.path and not self._target_done(r, belief)
                and path_is_valid(passable, [r.pos, *r.path])):
            return
        if self.config.mode == "waypoints" and r.target is not None and r.pos == r.target and r.waypoints:
            r.waypoints.pop(0)
        r.replan, r.path, r.target = False, [], None
        for _ in range(8):
            target = self._pick(k, belief)
            if target is None:
                return
            path = plan_path(on, r.pos, target)
            if not path and self.prior is not None:  # the prior is a guess: never let it trap a rover
                path = plan_path(self.own_view(k, belief), r.pos, target)
            if path:
                r.target, r.path = target, path
                return
            r.excluded.add(target)

    def fly(self, k: int, t: int) -> None:
        """One step of a helicopter: see :class:`~fedmap.mission.settings.HelicopterConfig`.

        Its rule keeps ``flight + ceil(d / speed) <= flight_budget`` at every step, ``d``
        the Chebyshev distance to its nearest landing site: a step that would break it is
        flown towards that site instead (8-connected moves shorten it by one cell each), and
        it lands on arriving there. The loop checks the budget and the site and stops with
        an error if the rule ever broke."""
        r, hc = self.team[k], self.config.helicopter
        r.airborne.append(False)
        if r.charging > 0:
            r.charging -= 1
            return
        sites = r.local == FREE
        sites[self.base] = True
        dist = ndimage.distance_transform_cdt(~sites, metric="chessboard")
        budget, speed = hc.flight_budget, hc.speed

        def after(goal: Cell) -> Cell:
            dr, dc = goal[0] - r.pos[0], goal[1] - r.pos[1]
            n = min(speed, max(abs(dr), abs(dc)))
            return (r.pos[0] + int(np.clip(dr, -n, n)), r.pos[1] + int(np.clip(dc, -n, n)))

        def affordable(cell: Cell) -> bool:
            return r.flight + 1 + -(-int(dist[cell]) // speed) <= budget

        if not r.returning:
            belief = self.strategy.belief(k)
            if r.target is None or self._target_done(r, belief) or r.pos == r.target:
                flyer = np.where(belief == UNKNOWN, UNKNOWN, FREE).astype(np.uint8)
                reach = dist * 2 <= speed * (budget - 2)
                r.target = choose_target(flyer, r.pos, radius=hc.sensor_radius, unknown_cost=1.0,
                                         others=self.strategy.others(k), allowed=reach)
            if r.target is None or not affordable(after(r.target)):
                r.returning = True
                r.target = None
        if r.returning and dist[r.pos] == 0:  # on a site: land (or stay landed) this step
            if r.flight > 0:
                self._land(k, t)
            r.returning = False
            return
        if r.returning:
            near = np.argwhere(sites)
            d = np.maximum(np.abs(near[:, 0] - r.pos[0]), np.abs(near[:, 1] - r.pos[1]))
            i = int(np.lexsort((near[:, 1], near[:, 0], d))[0])
            goal = (int(near[i, 0]), int(near[i, 1]))
        else:
            assert r.target is not None
            goal = r.target
        for _ in range(speed):
            if r.pos == goal:
                break
            nxt = (r.pos[0] + int(np.sign(goal[0] - r.pos[0])), r.pos[1] + int(np.sign(goal[1] - r.pos[1])))
            r.distance += math.hypot(nxt[0] - r.pos[0], nxt[1] - r.pos[1])
            r.pos = nxt
            r.trail.append(nxt)
            self.sense(k, t)
        r.flight += 1
        r.airborne[-1] = True
        if r.flight > budget:
            raise RuntimeError(f"helicopter {k} flew {r.flight} steps, over its budget of {budget}")
        if r.returning and r.pos == goal:
            self._land(k, t)

    def _land(self, k: int, t: int) -> None:
        r = self.team[k]
        site = "lander" if r.pos == self.base else "observed free"
        if site != "lander" and r.local[r.pos] != FREE:
            raise RuntimeError(f"helicopter {k} landed on {r.pos}, which is not a landing site")
        r.landings.append((t, r.pos, r.flight, site))
        r.flight, r.charging, r.returning = 0, self.config.helicopter.recharge, False

    def drive(self, k: int, t: int) -> None:
        r = self.team[k]
        if r.kind == "helicopter":
            self.fly(k, t)
            return
        for _ in range(self.config.speed):
            belief = self.strategy.belief(k)
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

    # -- the link
    def positions(self) -> list[Cell]:
        """Every rover's cell now, in team order."""
        return [r.pos for r in self.team]

    def _push(self, due: int, kind: str, *data) -> None:
        heapq.heappush(self.queue, (due, self.seq, kind, data))
        self.seq += 1

    def sync(self, t: int, round_no: int) -> None:
        s = self.strategy
        if not s.shares:
            return
        if isinstance(s, PeerStrategy):
            self.peer_sync(t, round_no, s)
            return
        s.at_sync(round_no)
        positions = self.positions()
        reachable = self.topology.reachable(positions)
        for k in range(len(self.team)):
            if not reachable[k]:  # recorded as out of range
                self.link.send(None, round_no=round_no, step=t, rover=k, direction=UP, kind="-", positions=positions)
                continue
            out = s.uplink(k, round_no)
            if out is None:
                self.link.ledger.append(Message(round_no, t, k, UP, "update", 0, "rejected"))
                continue
            msg = self.link.send(out.payload, round_no=round_no, step=t, rover=k, direction=UP, kind=out.kind,
                                 positions=positions)
            if msg.arrival is not None:  # delivered
                self._push(msg.arrival, "up", k, out.payload, out.ctx, round_no)
        self._push(t + self.config.link.latency, "base", round_no)

    def peer_pairs(self, round_no: int, step: int) -> list[tuple[int, int]]:
        """The links up this round: star, each rover in range of the base; else every pair of
        agents in range of each other; either way, less the links down this round."""
        positions = self.positions()
        if isinstance(self.topology, MeshTopology):
            return self.link.up_pairs(round_no, step, positions)
        reach = self.topology.reachable(positions)
        return [(BASE, k) for k in range(len(self.team))
                if reach[k] and not self.link.down(round_no, k, BASE, step)]

    def _budget(self, a: int, b: int, role: str) -> int | None:
        lc = self.config.link
        if lc.topology == "mesh":
            return lc.peer_bytes
        if lc.topology == "star":
            return lc.uplink_bytes if b == BASE else lc.downlink_bytes
        return lc.uplink_bytes if role == "up" else lc.downlink_bytes

    def _offer(self, s: PeerStrategy, path: list[int], t: int, round_no: int, role: str) -> int:
        """Offer agent ``path[0]``'s message to ``path[-1]`` along ``path``; its arrival step (or t)."""
        a, b = path[0], path[-1]
        budget = self._budget(a, b, role)
        out = s.peer_message(a, b, round_no, t, budget)
        msg = self.link.send_route(out.payload, path, round_no=round_no, step=t, kind=out.kind, budget=budget)
        if msg.arrival is not None and msg.to == b:
            self._push(msg.arrival, "peer", a, b, out.payload, out.ctx, round_no, msg)
            return msg.arrival
        return t

    def peer_sync(self, t: int, round_no: int, s: PeerStrategy) -> None:
        """A round on a peer topology (or ``gossip`` on the star): see :mod:`fedmap.mission.peers`."""
        s.at_sync(round_no)
        pairs = self.peer_pairs(round_no, t)
        self.links = tuple(pairs)
        lat = self.config.link.latency
        if self.config.link.topology != "leader":
            self.leaders = ()
            s.peer_links(round_no, pairs)
            for a, b in pairs:
                self._offer(s, [a, b], t, round_no, "peer")
                self._offer(s, [b, a], t, round_no, "peer")
            self._push(t + lat, "peer_round", round_no, None)
            return
        mesh = self.topology
        assert isinstance(mesh, MeshTopology)
        leader = elect_leaders(components(mesh.agents(len(self.team)), pairs))
        self.leaders = tuple(sorted(set(leader.values())))
        routes = {m: route(m, ld, pairs) for m, ld in leader.items() if m != ld}
        s.peer_links(round_no, [(m, leader[m]) for m in routes])
        hops = max((len(r) - 1 for r in routes.values() if r), default=0)
        for _m, r in routes.items():
            assert r is not None
            self._offer(s, r, t, round_no, "up")
        self._push(t + lat * hops, "lead", round_no, routes, hops, self.leaders)

    def deliver(self, t: int) -> None:
        s = self.strategy
        while self.queue and self.queue[0][0] <= t:
            due, _, kind, data = heapq.heappop(self.queue)
            if kind == "peer":
                a, b, payload, ctx, round_no, msg = data
                assert isinstance(s, PeerStrategy)
                if s.receive_peer(b, a, payload, ctx, round_no, due):
                    s.peer_acked(a, b, ctx)
                    if b != BASE:
                        self.team[b].replan = True
                else:
                    msg.status = "stale"
            elif kind == "lead":  # leaders have what their members sent: they mix, and answer
                round_no, routes, hops, leaders = data
                assert isinstance(s, PeerStrategy)
                s.peer_round(round_no, agents=leaders)
                for _m, r in routes.items():
                    self._offer(s, r[::-1], due, round_no, "down")
                members = tuple(a for a in (BASE, *range(len(self.team))) if a not in leaders)
                self._push(due + self.config.link.latency * hops, "peer_round", round_no, members)
            elif kind == "peer_round":
                round_no, closing = data
                assert isinstance(s, PeerStrategy)
                s.peer_round(round_no, agents=closing)
                for r in self.team:
                    r.replan = True
            elif kind == "up":
                k, payload, ctx, round_no = data
                s.receive_uplink(k, payload, ctx, round_no)
                s.uplink_acked(k, ctx)
            elif kind == "base":
                (round_no,) = data
                for k, out in s.base_round(round_no).items():
                    msg = self.link.send(out.payload, round_no=round_no, step=due, rover=k, direction=DOWN,
                                         kind=out.kind, positions=self.positions())
                    if msg.arrival is not None:  # delivered
                        self._push(msg.arrival, "down", k, out.payload, out.ctx, msg)
            else:
                k, payload, ctx, msg = data
                if s.receive_downlink(k, payload, ctx):
                    self.team[k].replan = True
                else:
                    msg.status = "stale"

    # -- the record
    def record(self, t: int, evaluate: bool) -> None:
        s, truth = self.strategy, self.truth.classes
        observed = np.stack([r.local != UNKNOWN for r in self.team])
        n_seen = observed.sum(axis=0)
        beliefs = [s.belief(k) for k in range(len(self.team))]
        n = len(self.team)
        up, down = [0] * n, [0] * n
        delivered, dropped = {UP: 0, DOWN: 0}, {UP: 0, DOWN: 0}
        for m in self.link.ledger:
            side = UP if m.sender != BASE else DOWN
            if m.rover_side != BASE:
                (up if side == UP else down)[m.rover_side] += m.bytes
            ok = m.status == "delivered" and (m.arrival is None or m.arrival <= t)
            if m.status == "delivered" and not ok:
                continue  # still on its way
            (delivered if ok else dropped)[side] += 1
        free = [self.planning_map(b, k) == FREE for k, b in enumerate(beliefs)]
        self.rows.append(_StepRow(
            step=t, coverage=float((n_seen > 0).mean()), redundant=float((n_seen > 1).mean()),
            accuracy=tuple(float((b == truth).mean()) for b in beliefs),
            accuracy_observed=tuple(_share(b == truth, n_seen > 0) for b in beliefs),
            accuracy_unobserved=tuple(_share(b == truth, n_seen == 0) for b in beliefs),
            false_free=tuple(float((f & ((truth if o is None else o) == IMPASSABLE)).sum() / max(int(f.sum()), 1))
                             for f, o in zip(free, self.own_truth)),
            distance=tuple(r.distance for r in self.team),
            bytes_up=tuple(up), bytes_down=tuple(down), up_delivered=delivered[UP], up_dropped=dropped[UP],
            down_delivered=delivered[DOWN], down_dropped=dropped[DOWN]))
        if evaluate:
            g = self.scorer.scores(s.global_map())
            own = [self.own_scorer[k].path(self.own_view(k, b)) for k, b in enumerate(beliefs)]
            self.evals.append(_EvalRow(step=t, psnr=g.psnr, ssim=g.ssim, accuracy=g.accuracy, f1=g.path.f1,
                                       f1_tolerant=g.path.tolerant.f1, belief_f1=tuple(p.f1 for p in own),
                                       belief_success=tuple(p.success for p in own)))
        if t % self.frame_every == 0 or t == self.config.steps:
            self.frames.append(Frame(step=t, beliefs=beliefs, global_map=s.global_map().copy(),
                                     positions=self.positions(), trail_len=[len(r.trail) for r in self.team],
                                     links=self.links, leaders=self.leaders))

    def run(self, on_step: Callable[[str, int, float], None] | None = None) -> StrategyRun:
        t0 = time.perf_counter()
        c = self.config
        for k in range(len(self.team)):
            self.sense(k, 0)
        self.record(0, evaluate=True)  # step 0 too: a score owed to the initial model shows as such
        syncs = {t: i + 1 for i, t in enumerate(c.sync_steps)}
        for t in range(1, c.steps + 1):
            for k in range(len(self.team)):
                self.drive(k, t)
            if t in syncs:
                self.sync(t, syncs[t])
            self.deliver(t)
            self.record(t, evaluate=t in syncs or t == c.steps)
            if on_step is not None:
                on_step(self.name, t, self.rows[-1].coverage)
        seconds = time.perf_counter() - t0
        series = _series(self.rows, self.evals)
        dropped = self.strategy.dropped
        summary = summarise(series, self.link.ledger, c, self.link.slots)
        z = self.strategy.global_heights()
        if z is not None and self.elevation is not None:
            held = np.isfinite(z)
            err = (z[held] - self.elevation[held]).astype(np.float64)
            summary = replace(summary, final_height_rmse_m=float(np.sqrt(np.mean(err ** 2))) if held.any() else 0.0,
                              final_height_coverage=float(held.mean()))
        return StrategyRun(self.name, series, summary,
                           self.link.ledger, self.frames,
                           [list(r.trail) for r in self.team], seconds,
                           dropped_updates=None if dropped is None else tuple(dropped),
                           model_lag=None if self.strategy.lags is None else tuple(self.strategy.lags),
                           strategy=self.strategy)


def first_step(steps: Sequence[int], values: Sequence[float], level: float) -> int | None:
    """The first step whose value is at least ``level`` (None: never)."""
    for t, v in zip(steps, values):
        if v >= level - 1e-12:
            return t
    return None


def summarise(series: TimeSeries, ledger: list[Message], config: MissionConfig, slots: int = 0) -> MissionSummary:
    """Steps to the coverage levels, first step a belief reaches :data:`F1_GOAL`, finals, bytes."""
    ev = series.eval
    per_rover_f1 = tuple(first_step(ev.step, [f[k] for f in ev.belief_f1], F1_GOAL) for k in range(config.rovers))
    reached = [t for t in per_rover_f1 if t is not None]
    status: dict[str, int] = {}
    for m in ledger:
        key = f"{m.direction}_{m.status}"
        status[key] = status.get(key, 0) + 1
    return MissionSummary(
        coverage_steps={level: first_step(series.step, series.coverage, level) for level in COVERAGE_LEVELS},
        belief_f1_goal=F1_GOAL,
        first_belief_f1_step=min(reached) if reached else None,
        first_belief_f1_step_per_rover=per_rover_f1,
        final_coverage=series.coverage[-1],
        final_redundant=series.redundant[-1],
        final_belief_accuracy_mean=float(np.mean(series.accuracy[-1])),
        final_false_free_mean=float(np.mean(series.false_free[-1])),
        final_accuracy_observed_mean=float(np.mean(series.accuracy_observed[-1])),
        final_accuracy_unobserved_mean=float(np.mean(series.accuracy_unobserved[-1])),
        final_path_success_mean=float(np.mean(ev.belief_success[-1])),
        final_distance_total=float(np.sum(series.distance[-1])),
        final_global_psnr=ev.psnr[-1],
        final_global_ssim=ev.ssim[-1],
        final_global_accuracy=ev.accuracy[-1],
        final_global_f1=ev.f1[-1],
        final_global_f1_tolerant=ev.f1_tolerant[-1],
        final_belief_f1_mean=float(np.mean(ev.belief_f1[-1])),
        bytes_up=int(np.sum(series.bytes_up[-1])),
        bytes_down=int(np.sum(series.bytes_down[-1])),
        bytes_per_link_round=sum(m.bytes for m in ledger) / slots if slots else 0.0,
        messages=dict(sorted(status.items())),
    )


def mission_terrain(config: MissionConfig, source: TerrainSource) -> tuple[GridMap, np.ndarray | None,
                                                                           np.ndarray | None, dict[str, np.ndarray]]:
    """``(truth, elevation, prior, profiles)`` of a mission on ``source``: the elevation when
    line of sight needs it, the orbital prior when ``[prior]`` asks for one (else None each),
    and the classes of the terrain under each rover profile of ``[mission] profiles`` but
    ``team`` (``{profile: classes}``, empty when there are none)."""
    own = sorted({p for p in config.profiles if p != "team"})
    layer = "elevation" in config.layers
    needs_dem = config.line_of_sight or config.prior.kind == "orbital" or bool(own) or layer
    truth, dem = load_terrain(source, seed=config.seed, with_dem=needs_dem)
    elevation = dem.elevation if dem is not None and (config.line_of_sight or layer) else None
    prior = orbital_prior(dem, source.thresholds, config.prior.factor) if dem is not None and \
        config.prior.kind == "orbital" else None
    profiles = {p: dem_to_traversability(dem, rover_profile(p)).classes for p in own} if dem is not None else {}
    return truth, elevation, prior, profiles


def run_mission(config: MissionConfig, truth: GridMap, *, elevation: np.ndarray | None = None,
                prior: np.ndarray | None = None, profiles: dict[str, np.ndarray] | None = None,
                thresholds: TraversabilityThresholds | None = None,
                on_strategy: Callable[[str], None] | None = None,
                on_step: Callable[[str, int, float], None] | None = None,
                frames: int = 60) -> MissionResult:
    """Run every strategy of ``config`` on the same mission over ``truth``.

    ``elevation`` (metres, the truth's grid) is needed for ``line_of_sight``; ``prior``
    (classes, the truth's grid) is what every rover plans on where it has no observation
    (:class:`~fedmap.mission.settings.PriorConfig`); ``profiles`` the classes of the terrain under
    each rover profile of ``config.profiles`` but ``team`` (:func:`mission_terrain` builds all three);
    ``thresholds`` the team's limits, with which a ``team`` rover derives classes from an
    elevation layer (None: the defaults; the truth must have been classified with them).
    ``on_strategy(name)`` announces each strategy and ``on_step(name, step, coverage)``
    follows it (progress bars); ``frames`` bounds the animation's frames per strategy.
    """
    t0 = time.perf_counter()
    if config.line_of_sight and elevation is None:
        raise needs_dem("line of sight")
    if "elevation" in config.layers and elevation is None:
        raise needs_dem("an elevation layer")
    if elevation is not None and np.shape(elevation) != truth.shape:
        raise FedmapError(f"elevation grid {np.shape(elevation)} does not match the map {truth.shape}")
    if prior is not None and np.shape(prior) != truth.shape:
        raise FedmapError(f"prior map {np.shape(prior)} does not match the map {truth.shape}")
    own = {p for p in config.profiles if p != "team"}
    profiles = profiles or {}
    if own - set(profiles):
        raise FedmapError(f"no classes given for rover profile(s) {', '.join(sorted(own - set(profiles)))}: pass "
                          "profiles= (mission_terrain builds them)")
    for name, classes in profiles.items():
        if np.shape(classes) != truth.shape:
            raise FedmapError(f"profile {name!r} classes {np.shape(classes)} do not match the map {truth.shape}")
    starts, base = place_starts(truth, config)
    waypoints = plan_waypoints(truth, config) if config.mode == "waypoints" else [[] for _ in starts]
    scorer = _Scorer(truth, config.eval_pairs, config.seed)
    # one scorer per rover profile, shared by every strategy and rover (the truth's paths are planned once)
    profile_scorers = {p: _Scorer(truth.with_classes(c, p), config.eval_pairs, config.seed) for p, c in profiles.items()}
    frame_every = max(1, math.ceil(config.steps / max(frames, 1)))
    runs = {}
    for name in config.strategies:
        if on_strategy is not None:
            on_strategy(name)
        runs[name] = _Run(name, config, truth, elevation, starts, base, waypoints, scorer, frame_every,
                          prior, profiles, thresholds, profile_scorers).run(on_step)
    return MissionResult(config, truth, starts, base, runs, time.perf_counter() - t0)


__all__ = ["COVERAGE_LEVELS", "F1_GOAL", "EvalSeries", "Frame", "MissionResult", "MissionSummary", "Rover",
           "StrategyRun", "TimeSeries", "place_starts", "run_mission"]
