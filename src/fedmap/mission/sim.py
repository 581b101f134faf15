"""The mission loop: every strategy runs the same mission (terrain, starts, seeds, link).

Every step each member of the team drives (or flies) and senses (:mod:`fedmap.mission.world.world`).
At every ``sync_every``-th step the topology runs a sync round over the strategy's ends
(:mod:`fedmap.mission.network.topology`): on the star each rover offers its uplink to the link, the
base runs its round when the uplinks arrive (``latency`` steps later) and its downlinks
arrive ``latency`` steps after that. The ends (:mod:`fedmap.mission.ends.registry`) say what is
sent; :mod:`fedmap.mission.network.link` decides each message's fate. The loop records every step
and scores every evaluation step (every sync and the last step) into the typed results of
:mod:`fedmap.mission.results`.
"""

from __future__ import annotations

import math
import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, wait
from dataclasses import dataclass, replace
from functools import cached_property
from queue import Empty

import numpy as np

from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import prediction_scores
from fedmap.maps.grid import FREE, IMPASSABLE, GridMap
from fedmap.maps.orbital import orbital_prior
from fedmap.maps.sources import TerrainSource, load_terrain, needs_dem
from fedmap.maps.traversability import (
    TraversabilityThresholds,
    dem_to_traversability,
    resolved_slope,
    rover_profile,
)
from fedmap.mission.ends.framed import registrations
from fedmap.mission.ends.registry import Setup, Sharing, build, names_that
from fedmap.mission.network.link import BASE, DOWN, UP, Link, Message
from fedmap.mission.network.nodes import team_nodes
from fedmap.mission.network.topology import make_topology
from fedmap.mission.network.transport import Exchange
from fedmap.mission.results import (
    COVERAGE_LEVELS,
    F1_GOAL,
    EvalRow,
    EvalSeries,
    Frame,
    MissionResult,
    MissionSummary,
    Scorer,
    Snapshot,
    StepRow,
    StrategyRun,
    TimeSeries,
    false_free,
    series_of,
    share,
    summarise,
)
from fedmap.mission.settings import MissionConfig
from fedmap.mission.world.frames import FramedWorld, check_frames
from fedmap.mission.world.world import (
    Rover,
    World,
    place_starts,
    plan_waypoints,
    reachable_cells,
    start_pocket_warning,
)

Cell = tuple[int, int]
#: The smallest side of a mission's map, in cells (a rover's sensor and a plan need room).
MIN_SIDE = 8
#: What one step's record of one strategy holds in memory at most, bytes: a fixed part and a
#: part per team member (measured: 0.92, 1.37 and 2.12 kB a step for 1, 3 and 6 rovers,
#: ``python benchmarks/mission_memory.py``).
STEP_RECORD_BYTES = (800, 300)


def check_memory(config: MissionConfig, available: int | None = None) -> None:
    """One line before a mission starts whose per-step records cannot fit in this machine's
    available memory (``available`` bytes; None: what the system says, where it says it)."""
    if available is None:
        available = available_memory()
        if available is None:
            return
    per_step = STEP_RECORD_BYTES[0] + STEP_RECORD_BYTES[1] * (config.rovers + config.helicopters)
    need = (config.steps + 1) * per_step * max(len(config.strategies), 1)
    if need > 0.8 * available:
        raise FedmapError(f"a mission of {config.steps:,} steps keeps about {need / 2**30:,.1f} GiB of per-step "
                          f"records for its {len(config.strategies)} strategies; this machine has "
                          f"{available / 2**30:,.1f} GiB available: run fewer steps or strategies")


def available_memory() -> int | None:
    """The memory available to a new allocation, bytes (Linux's MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None
#: A strategy's ends for one run: ``ends(name, setup) -> Sharing``.
Ends = Callable[[str, Setup], Sharing]


@dataclass
class TeamState:
    """What the record of one step reads of the team (team order: rovers, then helicopters)."""

    beliefs: list[np.ndarray]  #: every member's belief (classes)
    views: list[np.ndarray]  #: every member's view: its belief in its own classes
    observed: np.ndarray  #: ``(members, h, w)`` bool: the cells each has observed itself
    positions: list[Cell]
    targets: list[Cell | None]
    distances: list[float]  #: cells driven (or flown) so far
    trail_len: list[int]  #: cells in its trail so far


class Scoring:
    """The record of one strategy's run, scored against the truth: the same whether it is
    taken live (:class:`_Run`, in process) or from what the nodes wrote to their own logs
    afterwards (:func:`fedmap.mission.scoring.score_strategy`). ``world`` gives what the
    scoring needs of the team (each member's kind, profile, planning map and predictor)."""

    def __init__(self, name: str, mission: Mission, world: World,
                 on_snapshot: Callable[[Snapshot], None] | None = None) -> None:
        config, truth = mission.config, mission.truth
        self.name, self.config, self.truth, self.elevation = name, config, truth, mission.elevation
        self.scorer, self.frame_every, self.world = mission.scorer, mission.frame_every, world
        self.reachable = mission.reachable
        self.own_scorer = [self.scorer if p == "team" else mission.profile_scorers[p] for p in world.profiles]
        self.on_snapshot = on_snapshot
        self._seen = 0  # ledger entries already handed to on_snapshot
        self.views: list[np.ndarray] = []  # every member's view at the last recorded step
        self.prediction: dict[str, float] | None = None  # the predictor's guesses scored at the last step
        self.rows: list[StepRow] = []
        self.evals: list[EvalRow] = []
        self.frames: list[Frame] = []
        #: the step the stop rule (``stop_coverage``) ended the run at (None: not reached yet, or no rule)
        self.stopped: int | None = None

    def record(self, t: int, evaluate: bool, team: TeamState, global_map: np.ndarray, ledger: list[Message], *,
               global_heights: Callable[[], np.ndarray | None] = lambda: None,
               links: tuple[tuple[int, int], ...] = (), leaders: tuple[int, ...] = ()) -> None:
        """Record step ``t`` (score it when ``evaluate``) from ``team``, the ``global_map`` the
        base (or lander) held then and the ``ledger`` (what was sent by step ``t`` counts)."""
        w, truth = self.world, self.truth.classes
        n_seen = team.observed.sum(axis=0)
        beliefs = team.beliefs
        members = self.world.team
        n = len(members)
        up, down = [0] * n, [0] * n
        delivered, dropped = {UP: 0, DOWN: 0}, {UP: 0, DOWN: 0}
        for m in ledger:
            if m.step > t:
                continue  # sent after this step (a ledger read after the run)
            side = UP if m.sender != BASE else DOWN
            if m.rover_side != BASE:
                (up if side == UP else down)[m.rover_side] += m.bytes
            ok = m.status == "delivered" and (m.arrival is None or m.arrival <= t)
            if m.status == "delivered" and not ok:
                continue  # still on its way
            (delivered if ok else dropped)[side] += 1
        self.views = views = team.views
        free = [w.planning_map(v) == FREE for v in views]
        truths = [truth if o is None else o for o in w.own_truth]  # a profile rover's own classes
        self.rows.append(StepRow(
            step=t, coverage=float((n_seen > 0).mean()), redundant=float((n_seen > 1).mean()),
            coverage_reachable=share(n_seen > 0, self.reachable),
            accuracy=tuple(float((b == truth).mean()) for b in beliefs),
            accuracy_observed=tuple(share(b == truth, n_seen > 0) for b in beliefs),
            accuracy_unobserved=tuple(share(b == truth, n_seen == 0) for b in beliefs),
            false_free=tuple(false_free(f, o) for f, o in zip(free, truths)),
            distance=tuple(team.distances), bytes_up=tuple(up), bytes_down=tuple(down),
            up_delivered=delivered[UP], up_dropped=dropped[UP],
            down_delivered=delivered[DOWN], down_dropped=dropped[DOWN]))
        if self.config.stops(t, self.rows[-1].coverage_reachable):
            self.stopped = t  # the stop rule: this step is the run's last
        last = t == self.config.steps or self.stopped == t
        evaluate = evaluate or last
        if last and w.predictor is not None:  # ([frames] refuses a predictor)
            nobody = n_seen == 0
            if nobody.any():
                self.prediction = prediction_scores(
                    np.concatenate([w.predicted(k, b).p_impassable[nobody] for k, b in enumerate(beliefs)]),
                    np.tile(truth[nobody] == IMPASSABLE, len(beliefs)))
        if evaluate:
            g = self.scorer.scores(global_map)
            own = [self.own_scorer[k].path(v) for k, v in enumerate(views)]
            guessed: dict[str, tuple[float, ...]] = {}
            if w.predictor is not None:  # the belief each rover plans paths on
                filled = [w.predicted(k, v).classes for k, v in enumerate(views)]
                paths = [self.own_scorer[k].path(f) for k, f in enumerate(filled)]
                guessed = {"predicted_f1": tuple(p.f1 for p in paths),
                           "predicted_success": tuple(p.success for p in paths),
                           "predicted_false_free": tuple(false_free(f == FREE, o) for f, o in zip(filled, truths)),
                           "predicted_accuracy_unobserved": tuple(share(f == o, n_seen == 0)
                                                                  for f, o in zip(filled, truths))}
            self.evals.append(EvalRow(step=t, psnr=g.psnr, ssim=g.ssim, accuracy=g.accuracy, f1=g.path.f1,
                                      f1_tolerant=g.path.tolerant.f1, belief_f1=tuple(p.f1 for p in own),
                                      belief_success=tuple(p.success for p in own), **guessed))
        if self.on_snapshot is not None:
            c = self.config
            self.on_snapshot(Snapshot(
                strategy=self.name, step=t, truth=self.truth, beliefs=beliefs,
                views=views, global_map=global_map,
                global_heights=global_heights(), positions=list(team.positions), targets=list(team.targets),
                kinds=[r.kind for r in members],
                sensor_radius=[c.helicopter.sensor_radius if r.kind == "helicopter" else c.sensor_radius
                               for r in members],
                base=w.base, links=links, leaders=leaders,
                messages=ledger[self._seen:], row=self.rows[-1],
                eval=self.evals[-1] if evaluate else None))
            self._seen = len(ledger)
        if t % self.frame_every == 0 or last:
            self.frames.append(Frame(step=t, beliefs=beliefs, global_map=global_map.copy(),
                                     positions=list(team.positions), trail_len=list(team.trail_len),
                                     links=links, leaders=leaders))

    def result(self, seconds: float, trails: list[list[Cell]], ledger: list[Message], slots: int, *,
               final_heights: np.ndarray | None = None, dropped: list | None = None, lags: list | None = None,
               registrations: tuple[dict, ...] | None = None, sharing: Sharing | None = None,
               wire: dict | None = None) -> StrategyRun:
        """The run's record once its last step is recorded (``trails``: every member's cells
        driven; the rest: what the base (or lander) held at the end)."""
        c = self.config
        series = series_of(self.rows, self.evals)
        summary = summarise(series, ledger, c, slots, reachable_share=float(self.reachable.mean()))
        z = final_heights
        if z is not None and self.elevation is not None:
            held = np.isfinite(z)
            err = (z[held] - self.elevation[held]).astype(np.float64)
            summary = replace(summary, final_height_rmse_m=float(np.sqrt(np.mean(err ** 2))) if held.any() else 0.0,
                              final_height_coverage=float(held.mean()))
        if self.prediction is not None:
            summary = replace(summary, final_prediction=self.prediction)
        return StrategyRun(self.name, series, summary, ledger, self.frames, trails, seconds,
                           dropped_updates=None if dropped is None else tuple(dropped),
                           model_lag=None if lags is None else tuple(lags),
                           registrations=registrations, sharing=sharing,
                           views=tuple(self.views), wire=wire)  # the last step's, recorded after its deliveries


class _Run:
    """One strategy's mission, step by step: the world, a node per agent (each owning one
    of the strategy's ends) on the in-process transport, and the record."""

    def __init__(self, name: str, mission: Mission, ends: Ends | None = None,
                 on_snapshot: Callable[[Snapshot], None] | None = None) -> None:
        config, truth = mission.config, mission.truth
        self.name, self.config = name, config
        self.topology = make_topology(config.link, mission.base)
        self.world = world = mission.world(self.topology)
        self.team = world.team
        self.link = Link(replace(config.link, seed=config.link_seed), self.topology)
        self.sharing = (ends or build)(
            name, Setup(config, truth, self.team, self.topology))
        world.ends = self.sharing.rovers

        def replan(k: int | None) -> None:
            for r in (self.team if k is None else [self.team[k]]):
                r.replan = True

        s = self.sharing
        self.rovers, self.base, self.peers = team_nodes(s, world, self.topology)
        self.exchange = Exchange(self.topology, self.link, rovers=self.rovers, base=self.base, peers=self.peers,
                                 positions=world.positions, replan=replan, on_sync=s.on_sync, on_link=s.on_link)
        self.scoring = Scoring(name, mission, world, on_snapshot)

    def observe(self) -> TeamState:
        """What the record reads of the team now: every member's belief and view (its belief
        in its own classes, computed once per step: what it plans on and is scored on), what
        it has observed, where it is and how far it has come."""
        s, w = self.sharing, self.world
        # scored in the true frame (rovers that do not know their poses: by the transforms the team estimated)
        beliefs = [w.in_true_frame(k, s.belief(k), s.base) for k in range(len(self.team))]
        return TeamState(beliefs=beliefs, views=[w.own_view(k, b) for k, b in enumerate(beliefs)],
                         observed=w.observed(), positions=w.positions(),
                         targets=[r.target for r in self.team], distances=[r.distance for r in self.team],
                         trail_len=[len(r.trail) for r in self.team])

    def record(self, t: int, evaluate: bool) -> None:
        """Record step ``t`` (score it when ``evaluate``)."""
        s, x = self.sharing, self.exchange
        self.scoring.record(t, evaluate, self.observe(), s.global_map(), self.link.ledger,
                            global_heights=s.global_heights, links=x.links, leaders=x.leaders)

    def run(self, on_step: Callable[[str, int, float], None] | None = None) -> StrategyRun:
        t0 = time.perf_counter()
        c, w = self.config, self.world
        for k in range(len(self.team)):
            w.sense(k, 0)
        self.record(0, evaluate=True)  # step 0 too: a score owed to the initial model shows as such
        for t in range(1, c.steps + 1):
            for k in range(len(self.team)):
                w.drive(k, t)
            round_no = c.sync_round(t)
            if round_no is not None:
                self.exchange.sync(t, round_no)
            self.exchange.deliver(t)
            self.record(t, evaluate=c.evaluated(t))
            if on_step is not None:
                on_step(self.name, t, self.scoring.rows[-1].coverage_reachable)
            if self.scoring.stopped is not None:
                break
        s, journal = self.sharing, self.sharing.journal
        return self.scoring.result(time.perf_counter() - t0, [list(r.trail) for r in self.team], self.link.ledger,
                                   self.link.slots, final_heights=s.global_heights(), dropped=journal.dropped,
                                   lags=journal.lags, registrations=registrations(s), sharing=s,
                                   wire=dict(self.exchange.wire) if s.on_link else None)


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
    # the prior is classified with the truth's slope limit in degrees, not a percentile of its coarse slopes
    prior = orbital_prior(dem, resolved_slope(source.thresholds, truth), config.prior.factor) \
        if dem is not None and config.prior.kind == "orbital" else None
    profiles = {p: dem_to_traversability(dem, rover_profile(p)).classes for p in own} if dem is not None else {}
    return truth, elevation, prior, profiles


def run_mission(config: MissionConfig, truth: GridMap, *, elevation: np.ndarray | None = None,
                prior: np.ndarray | None = None, profiles: dict[str, np.ndarray] | None = None,
                thresholds: TraversabilityThresholds | None = None,
                on_strategy: Callable[[str], None] | None = None,
                on_step: Callable[[str, int, float], None] | None = None,
                frames: int = 60, ends: Ends | None = None,
                on_snapshot: Callable[[Snapshot], None] | None = None, workers: int = 1) -> MissionResult:
    """Run every strategy of ``config`` on the same mission over ``truth``.

    ``elevation`` (metres, the truth's grid) is needed for ``line_of_sight``; ``prior``
    (classes, the truth's grid) is what every rover plans on where it has no observation
    (:class:`~fedmap.mission.settings.PriorConfig`); ``profiles`` the classes of the terrain under
    each rover profile of ``config.profiles`` but ``team`` (:func:`mission_terrain` builds all three);
    ``thresholds`` the team's limits, with which a ``team`` rover derives classes from an
    elevation layer (None: the defaults; the truth must have been classified with them); a
    percentile slope limit is resolved once, into the degrees it gave on the truth
    (:func:`~fedmap.maps.traversability.resolved_slope`), never re-taken on a rover's heights.
    ``on_strategy(name)`` announces each strategy and ``on_step(name, step, coverage)``
    follows it (progress bars; ``coverage``: of the cells the team can reach, which the stop
    rule reads); ``frames`` bounds the animation's frames per strategy.
    ``ends(name, setup)`` builds a strategy's ends (default: the registry's
    :func:`~fedmap.mission.ends.registry.build`, every end in this process; a mission whose
    rovers run elsewhere is :mod:`fedmap.mission.network.remote`).
    ``on_snapshot(snapshot)`` gets every strategy's :class:`~fedmap.mission.results.Snapshot`
    at every step as it runs (a recording, a live view).
    ``workers`` > 1 runs the strategies side by side in that many forked processes (each
    strategy's run is independent of the others': the same runs, bit for bit, as one after
    another; see :func:`_runs_in_processes`); with ``ends`` or ``on_snapshot``, or where
    processes cannot be forked, they run one after another here.
    """
    t0 = time.perf_counter()
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles, thresholds=thresholds,
                        frames=frames)
    names = list(config.strategies)
    if workers > 1 and len(names) > 1 and ends is None and on_snapshot is None and can_fork():
        runs = _runs_in_processes(m, names, workers, on_strategy, on_step)
    else:
        runs = {}
        for name in names:
            if on_strategy is not None:
                on_strategy(name)
            runs[name] = m.new_run(name, ends=ends, on_snapshot=on_snapshot).run(on_step)
    return MissionResult(config, truth, m.starts, m.base, runs, time.perf_counter() - t0)


def can_fork() -> bool:
    """Whether strategies can run in forked processes here (Linux and other POSIX systems)."""
    return "fork" in multiprocessing.get_all_start_methods()


#: What a forked strategy process inherits from its parent: the mission and the progress queue.
_FORKED: tuple[Mission, object] | None = None


def _one_thread() -> None:
    """A forked strategy process trains on one torch thread: the strategies share the cores,
    and OpenMP threads started in the parent do not survive a fork."""
    import torch

    torch.set_num_threads(1)


def _run_forked(name: str) -> StrategyRun:
    """Strategy ``name``'s run in a forked process; its progress goes to the parent's queue."""
    assert _FORKED is not None, "a strategy process must be forked from run_mission"
    mission, queue = _FORKED
    put = queue.put  # type: ignore[attr-defined]
    put((name, 0, -1.0))  # started

    def on_step(n: str, t: int, coverage: float) -> None:
        put((n, t, coverage))

    run = mission.new_run(name).run(on_step)
    return replace(run, sharing=None)  # the ends' state stays in the process (a model's hooks do not pickle)


def _runs_in_processes(m: Mission, names: list[str], workers: int,
                       on_strategy: Callable[[str], None] | None,
                       on_step: Callable[[str, int, float], None] | None) -> dict[str, StrategyRun]:
    """Every strategy of ``names`` in up to ``workers`` forked processes, their progress
    reported here as they go; the runs in ``names``' order, without their ends' state
    (:attr:`StrategyRun.sharing` is None). A strategy's error is raised here."""
    global _FORKED
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    m.scorer, m.profile_scorers, m.reachable  # noqa: B018  (computed once here, inherited by every process)
    _FORKED = (m, queue)

    def report() -> None:
        while True:
            try:
                n, t, coverage = queue.get_nowait()
            except Empty:
                return
            if t == 0 and coverage < 0:
                if on_strategy is not None:
                    on_strategy(n)
            elif on_step is not None:
                on_step(n, t, coverage)

    try:
        with ProcessPoolExecutor(max_workers=min(workers, len(names)), mp_context=ctx,
                                 initializer=_one_thread) as pool:
            futures = {name: pool.submit(_run_forked, name) for name in names}
            pending = set(futures.values())
            while pending:
                _, pending = wait(pending, timeout=0.2)
                report()
            runs = {name: f.result() for name, f in futures.items()}
        time.sleep(0.05)  # the feeder threads' last items
        report()
    finally:
        _FORKED = None
    return runs


@dataclass
class Mission:
    """What every strategy's run of one mission shares: the terrain, the starts and the
    base station, the waypoints, the team's limits and the scorers (:func:`prepare_mission`)."""

    config: MissionConfig
    truth: GridMap
    elevation: np.ndarray | None
    prior: np.ndarray | None
    profiles: dict[str, np.ndarray]
    thresholds: TraversabilityThresholds | None
    starts: list[Cell]
    base: Cell
    waypoints: list[list[Cell]]
    frame_every: int

    @cached_property
    def reachable(self) -> np.ndarray:
        """The cells the team can observe at all (:func:`~fedmap.mission.world.world.reachable_cells`):
        what coverage targets are measured against."""
        c = self.config
        allowed = make_topology(c.link, self.base).region(self.truth.shape) if c.stay_in_range else None
        return reachable_cells(self.truth, self.starts, c, allowed)

    @cached_property
    def scorer(self) -> Scorer:
        return Scorer(self.truth, self.config.eval_pairs, self.config.seed)

    @cached_property
    def profile_scorers(self) -> dict[str, Scorer]:
        """One scorer per rover profile, shared by every strategy and rover (the truth's paths are planned once)."""
        c = self.config
        return {p: Scorer(self.truth.with_classes(k, p), c.eval_pairs, c.seed) for p, k in self.profiles.items()}

    def new_run(self, name: str, *, ends: Ends | None = None,
                on_snapshot: Callable[[Snapshot], None] | None = None) -> _Run:
        """Strategy ``name``'s run, before its first step."""
        return _Run(name, self, ends, on_snapshot)

    def world(self, topology) -> World:
        """The team on the terrain (as every run builds it; a rover on a machine of its own builds one too)."""
        c = self.config
        allowed = topology.region(self.truth.shape) if c.stay_in_range else None
        kind = FramedWorld if c.frames.enabled else World
        return kind(c, self.truth, self.elevation, self.starts, self.base, self.waypoints, prior=self.prior,
                    profiles=self.profiles, thresholds=self.thresholds, allowed=allowed)


def prepare_mission(config: MissionConfig, truth: GridMap, *, elevation: np.ndarray | None = None,
                    prior: np.ndarray | None = None, profiles: dict[str, np.ndarray] | None = None,
                    thresholds: TraversabilityThresholds | None = None, frames: int = 60) -> Mission:
    """Check a mission's inputs (see :func:`run_mission`) and place its starts, base and waypoints."""
    check_memory(config)
    if min(truth.shape) < MIN_SIDE:
        raise FedmapError(f"the map is {truth.shape[0]}x{truth.shape[1]} cells, too small for a mission: both sides "
                          f"need at least {MIN_SIDE} cells")
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
    if thresholds is not None and "elevation" in config.layers:
        thresholds = resolved_slope(thresholds, truth)
    check_frames(config, names_that("framed"))
    starts, base = place_starts(truth, config)
    waypoints = plan_waypoints(truth, config) if config.mode == "waypoints" else [[] for _ in starts]
    frame_every = max(1, math.ceil(config.steps / max(frames, 1)))
    return Mission(config, truth, elevation, prior, profiles, thresholds, starts, base, waypoints, frame_every)


__all__ = ["COVERAGE_LEVELS", "F1_GOAL", "EvalSeries", "Frame", "Mission", "MissionResult", "MissionSummary", "Rover",
           "Snapshot", "StrategyRun", "TimeSeries", "mission_terrain", "place_starts", "plan_waypoints",
           "prepare_mission", "run_mission", "start_pocket_warning"]
