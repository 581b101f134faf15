"""The mission loop: every strategy runs the same mission (terrain, starts, seeds, link).

One step, for every rover in turn: drive up to ``speed`` cells along the planned path,
observing the footprint from every cell entered (the next cell is always observed
before the move, so a rover never enters a cell that is impassable in the truth: the
loop checks it against the truth and stops with an error if it ever would). At every
``sync_every``-th step each rover offers its uplink to the link; the base station runs
its round when the uplinks arrive (``latency`` steps later) and its downlinks arrive
``latency`` steps after that. See :mod:`fedmap.mission.strategies` for what each
strategy sends and :mod:`fedmap.mission.link` for the link.

Time series (:attr:`StrategyRun.series`): per step, team coverage, redundant
observation, each rover's belief accuracy, distance and cumulative bytes, messages
delivered and dropped; per evaluation step (every sync and the last step), the base's
global map scores (PSNR, SSIM, strict and tolerant path F1) and each rover's belief
strict path F1.
"""

from __future__ import annotations

import hashlib
import heapq
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fedmap.errors import FedmapError
from fedmap.evaluation.paths import path_f1
from fedmap.evaluation.scores import score_map
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.planning import path_is_valid
from fedmap.mission.frontiers import choose_target, plan_path
from fedmap.mission.link import DOWN, UP, Link, Message
from fedmap.mission.sensing import disk_offsets, footprint
from fedmap.mission.settings import MissionConfig
from fedmap.mission.strategies import Strategy, make_strategy

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


@dataclass
class StrategyRun:
    """One strategy's mission: time series, summary, ledger, and what the animation draws."""

    name: str
    series: dict
    summary: dict
    ledger: list[Message]
    frames: list[dict]
    trails: list[list[Cell]]
    seconds: float
    extra: dict = field(default_factory=dict)  # strategy-specific records for metrics.json
    strategy: Strategy | None = None  # the final state (for inspection; not written)


@dataclass
class MissionResult:
    config: MissionConfig
    truth: GridMap
    starts: list[Cell]
    base: Cell
    runs: dict[str, StrategyRun]
    seconds: float


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
        self.full: dict[bytes, dict] = {}
        self.f1: dict[bytes, float] = {}

    @staticmethod
    def _key(classes: np.ndarray) -> bytes:
        return hashlib.blake2b(np.ascontiguousarray(classes).tobytes(), digest_size=16).digest()

    def scores(self, classes: np.ndarray) -> dict:
        key = self._key(classes)
        if key not in self.full:
            s = score_map(self.truth.classes, classes, pairs=self.pairs, seed=self.seed)
            self.full[key] = {"psnr": s.psnr, "ssim": s.ssim, "accuracy": s.accuracy, "f1": s.path.f1,
                              "f1_tolerant": s.path.tolerant.f1}
            self.f1[key] = s.path.f1
        return self.full[key]

    def strict_f1(self, classes: np.ndarray) -> float:
        key = self._key(classes)
        if key not in self.f1:
            self.f1[key] = path_f1(self.truth.classes, classes, n_pairs=self.pairs, seed=self.seed).f1
        return self.f1[key]


class _Run:
    """One strategy's mission, step by step."""

    def __init__(self, name: str, config: MissionConfig, truth: GridMap, elevation: np.ndarray | None,
                 starts: list[Cell], base: Cell, waypoints: list[list[Cell]], scorer: _Scorer,
                 frame_every: int) -> None:
        self.name, self.config, self.truth, self.elevation = name, config, truth, elevation
        self.scorer, self.frame_every = scorer, frame_every
        shape = truth.shape
        self.team = [Rover(s, np.full(shape, UNKNOWN, dtype=np.uint8), np.full(shape, -1, dtype=np.int64),
                           trail=[s], waypoints=list(w) if config.mode == "waypoints" else [])
                     for s, w in zip(starts, waypoints)]
        self.link = Link(config.link, base)
        self.origin = (float(np.mean([s[0] for s in starts])), float(np.mean([s[1] for s in starts])))
        budget = {"up": config.link.uplink_bytes, "down": config.link.downlink_bytes}
        self.strategy: Strategy = make_strategy(name, truth, self.team, budget, methods=config.methods,
                                                seed=config.seed)
        self.allowed = None
        if config.stay_in_range and config.link.max_range is not None:
            rows, cols = np.indices(shape)
            self.allowed = np.hypot(rows - base[0], cols - base[1]) <= config.link.max_range
        self.queue: list = []
        self.seq = 0
        self.series: dict = {"step": [], "coverage": [], "redundant": [], "accuracy": [], "distance": [],
                             "bytes_up": [], "bytes_down": [], "up_delivered": [], "up_dropped": [],
                             "down_delivered": [], "down_dropped": [],
                             "eval": {"step": [], "psnr": [], "ssim": [], "accuracy": [], "f1": [], "f1_tolerant": [],
                                      "belief_f1": []}}
        self.frames: list[dict] = []

    # -- sensing and driving
    def sense(self, k: int, t: int) -> None:
        r = self.team[k]
        c = self.config
        mask = footprint(r.pos, self.truth.shape, c.sensor_radius,
                         elevation=self.elevation if c.line_of_sight else None, height_m=c.sensor_height_m)
        new = mask & (r.local == UNKNOWN)
        r.local[new] = self.truth.classes[new]
        r.obs_step[new] = t

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
        heading = (*self.origin, 2 * math.pi * k / len(self.team))
        return choose_target(belief, r.pos, radius=self.config.sensor_radius, unknown_cost=self.config.unknown_cost,
                             others=self.strategy.others(k), allowed=self.allowed, excluded=r.excluded,
                             heading=heading)

    def plan(self, k: int, belief: np.ndarray) -> None:
        r = self.team[k]
        passable = (belief == FREE) | (belief == UNKNOWN)
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
            path = plan_path(belief, r.pos, target)
            if path:
                r.target, r.path = target, path
                return
            r.excluded.add(target)

    def drive(self, k: int, t: int) -> None:
        r = self.team[k]
        for _ in range(self.config.speed):
            belief = self.strategy.belief(k)
            self.plan(k, belief)
            if not r.path:
                return
            nxt = r.path[0]
            if belief[nxt] == IMPASSABLE:  # revealed on the way: replan next time
                r.replan = True
                return
            if self.truth.classes[nxt] == IMPASSABLE:
                raise RuntimeError(f"rover {k} would enter impassable cell {nxt}: the planner broke its contract")
            r.path.pop(0)
            r.distance += math.hypot(nxt[0] - r.pos[0], nxt[1] - r.pos[1])
            r.pos = nxt
            r.trail.append(nxt)
            self.sense(k, t)

    # -- the link
    def _push(self, due: int, kind: str, *data) -> None:
        heapq.heappush(self.queue, (due, self.seq, kind, data))
        self.seq += 1

    def sync(self, t: int, round_no: int) -> None:
        s = self.strategy
        if not s.shares:
            return
        for k, r in enumerate(self.team):
            if not self.link.in_range(r.pos):
                self.link.send(None, round_no=round_no, step=t, rover=k, direction=UP, kind="-", pos=r.pos)
                continue
            out = s.uplink(k, round_no)
            if out is None:
                self.link.ledger.append(Message(round_no, t, k, UP, "update", 0, "rejected"))
                continue
            msg = self.link.send(out.payload, round_no=round_no, step=t, rover=k, direction=UP, kind=out.kind,
                                 pos=r.pos)
            if msg.arrival is not None:  # delivered
                self._push(msg.arrival, "up", k, out.payload, out.ctx, round_no)
        self._push(t + self.config.link.latency, "base", round_no)

    def deliver(self, t: int) -> None:
        s = self.strategy
        while self.queue and self.queue[0][0] <= t:
            due, _, kind, data = heapq.heappop(self.queue)
            if kind == "up":
                k, payload, ctx, round_no = data
                s.receive_uplink(k, payload, ctx, round_no)
                s.uplink_acked(k, ctx)
            elif kind == "base":
                (round_no,) = data
                for k, out in s.base_round(round_no).items():
                    msg = self.link.send(out.payload, round_no=round_no, step=due, rover=k, direction=DOWN,
                                         kind=out.kind, pos=self.team[k].pos)
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
        s, se, truth = self.strategy, self.series, self.truth.classes
        observed = np.stack([r.local != UNKNOWN for r in self.team])
        n_seen = observed.sum(axis=0)
        beliefs = [s.belief(k) for k in range(len(self.team))]
        se["step"].append(t)
        se["coverage"].append(float((n_seen > 0).mean()))
        se["redundant"].append(float((n_seen > 1).mean()))
        se["accuracy"].append([float((b == truth).mean()) for b in beliefs])
        se["distance"].append([r.distance for r in self.team])
        n = len(self.team)
        up, down = [0] * n, [0] * n
        counts = {"up_delivered": 0, "up_dropped": 0, "down_delivered": 0, "down_dropped": 0}
        for m in self.link.ledger:
            (up if m.direction == UP else down)[m.rover] += m.bytes
            ok = m.status == "delivered" and (m.arrival is None or m.arrival <= t)
            if m.status == "delivered" and not ok:
                continue  # still on its way
            counts[f"{m.direction}_{'delivered' if ok else 'dropped'}"] += 1
        se["bytes_up"].append(up)
        se["bytes_down"].append(down)
        for key, v in counts.items():
            se[key].append(v)
        if evaluate:
            ev = se["eval"]
            g = self.scorer.scores(s.global_map())
            ev["step"].append(t)
            for key in ("psnr", "ssim", "accuracy", "f1", "f1_tolerant"):
                ev[key].append(g[key])
            ev["belief_f1"].append([self.scorer.strict_f1(b) for b in beliefs])
        if t % self.frame_every == 0 or t == self.config.steps:
            self.frames.append({"step": t, "beliefs": beliefs, "global": s.global_map().copy(),
                                "pos": [r.pos for r in self.team], "trail_len": [len(r.trail) for r in self.team]})

    def run(self, on_step: Callable[[str, int, float], None] | None = None) -> StrategyRun:
        t0 = time.perf_counter()
        c = self.config
        for k in range(len(self.team)):
            self.sense(k, 0)
        self.record(0, evaluate=False)
        syncs = {t: i + 1 for i, t in enumerate(c.sync_steps)}
        for t in range(1, c.steps + 1):
            for k in range(len(self.team)):
                self.drive(k, t)
            if t in syncs:
                self.sync(t, syncs[t])
            self.deliver(t)
            self.record(t, evaluate=t in syncs or t == c.steps)
            if on_step is not None:
                on_step(self.name, t, self.series["coverage"][-1])
        seconds = time.perf_counter() - t0
        extra = {}
        if hasattr(self.strategy, "dropped"):
            extra["dropped_updates"] = self.strategy.dropped
        return StrategyRun(self.name, self.series, summarise(self.series, self.link.ledger, c), self.link.ledger,
                           self.frames, [list(r.trail) for r in self.team], seconds, extra, self.strategy)


def first_step(steps: list[int], values: list[float], level: float) -> int | None:
    """The first step whose value is at least ``level`` (None: never)."""
    for t, v in zip(steps, values):
        if v >= level - 1e-12:
            return t
    return None


def summarise(series: dict, ledger: list[Message], config: MissionConfig) -> dict:
    """Steps to the coverage levels, first step a belief reaches :data:`F1_GOAL`, finals, bytes."""
    ev = series["eval"]
    per_rover_f1 = [first_step(ev["step"], [f[k] for f in ev["belief_f1"]], F1_GOAL) for k in range(config.rovers)]
    reached = [t for t in per_rover_f1 if t is not None]
    status: dict[str, int] = {}
    for m in ledger:
        key = f"{m.direction}_{m.status}"
        status[key] = status.get(key, 0) + 1
    return {
        "coverage_steps": {f"{int(level * 100)}%": first_step(series["step"], series["coverage"], level)
                           for level in COVERAGE_LEVELS},
        "belief_f1_goal": F1_GOAL,
        "first_belief_f1_step": min(reached) if reached else None,
        "first_belief_f1_step_per_rover": per_rover_f1,
        "final": {"coverage": series["coverage"][-1], "redundant": series["redundant"][-1],
                  "belief_accuracy_mean": float(np.mean(series["accuracy"][-1])),
                  "distance_total": float(np.sum(series["distance"][-1])),
                  **{f"global_{k}": ev[k][-1] for k in ("psnr", "ssim", "accuracy", "f1", "f1_tolerant")},
                  "belief_f1_mean": float(np.mean(ev["belief_f1"][-1]))},
        "bytes": {"up": int(np.sum(series["bytes_up"][-1])), "down": int(np.sum(series["bytes_down"][-1]))},
        "messages": dict(sorted(status.items())),
    }


def run_mission(config: MissionConfig, truth: GridMap, *, elevation: np.ndarray | None = None,
                on_strategy: Callable[[str], None] | None = None,
                on_step: Callable[[str, int, float], None] | None = None,
                frames: int = 60) -> MissionResult:
    """Run every strategy of ``config`` on the same mission over ``truth``.

    ``elevation`` (metres, the truth's grid) is needed for ``line_of_sight``.
    ``on_strategy(name)`` announces each strategy and ``on_step(name, step, coverage)``
    follows it (progress bars); ``frames`` bounds the animation's frames per strategy.
    """
    t0 = time.perf_counter()
    if config.line_of_sight and elevation is None:
        raise FedmapError("line of sight needs the terrain's elevation (a DEM or built-in source, not a class map)")
    if elevation is not None and np.shape(elevation) != truth.shape:
        raise FedmapError(f"elevation grid {np.shape(elevation)} does not match the map {truth.shape}")
    starts, base = place_starts(truth, config)
    waypoints = plan_waypoints(truth, config) if config.mode == "waypoints" else [[] for _ in starts]
    scorer = _Scorer(truth, config.eval_pairs, config.seed)
    frame_every = max(1, math.ceil(config.steps / max(frames, 1)))
    runs = {}
    for name in config.strategies:
        if on_strategy is not None:
            on_strategy(name)
        runs[name] = _Run(name, config, truth, elevation, starts, base, waypoints, scorer, frame_every).run(on_step)
    return MissionResult(config, truth, starts, base, runs, time.perf_counter() - t0)


__all__ = ["COVERAGE_LEVELS", "F1_GOAL", "MissionResult", "Rover", "StrategyRun", "place_starts", "run_mission"]
