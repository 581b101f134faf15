"""A mission's typed results: per strategy a :class:`TimeSeries` (per step, and per
evaluation step its :class:`EvalSeries`) and a :class:`MissionSummary`, in a
:class:`StrategyRun`; every strategy's runs in a :class:`MissionResult`. They become dicts
only for ``metrics.json`` (``to_dict``). Also the scorer the runs share, and the rows a run
records step by step.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from fedmap.evaluation.paths import PathScores, path_f1
from fedmap.evaluation.scores import MapScores, score_map
from fedmap.maps.grid import IMPASSABLE, GridMap
from fedmap.mission.ends.protocol import DroppedUpdate
from fedmap.mission.network.link import Message
from fedmap.mission.settings import MissionConfig

Cell = tuple[int, int]
#: Coverage levels whose first step is reported.
COVERAGE_LEVELS = (0.5, 0.8, 0.95)
#: A rover's belief "good enough to plan on": strict path F1 at least this.
F1_GOAL = 0.9
#: The coverage a team's map needs, beside a mean belief F1 of :data:`F1_GOAL`, to count as a
#: plannable map of the site (:attr:`MissionSummary.ready_step`).
READY_COVERAGE = 0.95


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
    #: with ``predictor = "learned"``, per rover, the same scores of its belief with the
    #: predictor's guesses filled in (every unknown cell its likelier class: the map it plans
    #: paths on), scored as strictly: its path F1, executed path success and false-free rate
    #: (the share of its FREE cells, observed or guessed, that are impassable in the truth),
    #: and the share of the cells nobody had observed that its guesses got right (1.0 when
    #: there are none). None (and not written) without a predictor.
    predicted_f1: tuple[tuple[float, ...], ...] | None = None
    predicted_success: tuple[tuple[float, ...], ...] | None = None
    predicted_false_free: tuple[tuple[float, ...], ...] | None = None
    predicted_accuracy_unobserved: tuple[tuple[float, ...], ...] | None = None

    def to_dict(self) -> dict[str, list]:
        out: dict[str, list] = {
            "step": list(self.step), "psnr": list(self.psnr), "ssim": list(self.ssim), "accuracy": list(self.accuracy),
            "f1": list(self.f1), "f1_tolerant": list(self.f1_tolerant), "belief_f1": [list(f) for f in self.belief_f1],
            "belief_success": [list(f) for f in self.belief_success]}
        for name in PREDICTED_SERIES:  # missions without a predictor keep the metrics they had
            values = getattr(self, name)
            if values is not None:
                out[name] = [list(f) for f in values]
        return out


#: The :class:`EvalSeries` of the belief with the predictor's guesses filled in.
PREDICTED_SERIES = ("predicted_f1", "predicted_success", "predicted_false_free", "predicted_accuracy_unobserved")


@dataclass(frozen=True)
class TimeSeries:
    """One strategy's mission, step by step: one entry per step, 0 (the start) to ``steps``.

    Shares are of the map's cells (0..1); distances are in cells; bytes and message counts
    are cumulative since the start. Per-rover entries are tuples in team order.
    """

    step: tuple[int, ...]  #: the steps, 0 to ``steps``
    coverage: tuple[float, ...]  #: share of cells any rover has observed
    #: share of the cells the team can observe (:func:`~fedmap.mission.world.world.reachable_cells`) any rover has observed
    coverage_reachable: tuple[float, ...]
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
        return {"step": list(self.step), "coverage": list(self.coverage),
                "coverage_reachable": list(self.coverage_reachable), "redundant": list(self.redundant),
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


#: The summary values that ``metrics.json`` leaves out when they are None (no predictor, no stop rule).
UNWRITTEN_WHEN_NONE = ("final_prediction", "predicted_belief", "stopped_step")


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
    #: first evaluation step the rovers' belief F1 (their mean) reached the goal (None: never)
    team_f1_step: int | None = None
    #: first evaluation step the team had a plannable map: its mean belief F1 at the goal and
    #: its coverage of the cells it can reach at :data:`READY_COVERAGE` (None: never)
    ready_step: int | None = None
    ready_bytes: int | None = None  #: the team's bytes, both ways, spent up to :attr:`ready_step`
    #: with ``predictor = "learned"``: the predictor's guesses at the last step on the cells
    #: nobody had observed, every rover's on the map it held, pooled
    #: (:func:`~fedmap.evaluation.metrics.prediction_scores`); None (and not written) without one
    final_prediction: dict[str, float] | None = None
    #: with ``predictor = "learned"``: the rovers' beliefs with the guesses filled in
    #: (:attr:`EvalSeries.predicted_f1`): ``f1_step``, the first evaluation step their mean
    #: strict path F1 reached :data:`F1_GOAL` (None: never), and at the last step the means
    #: over the rovers ``final_f1``, ``final_success`` and ``final_false_free``; None (and not
    #: written) without one
    predicted_belief: dict[str, float | int | None] | None = None
    #: the share of the map's cells the team can observe at all (the rest is walled off)
    reachable_share: float = 1.0
    final_coverage_reachable: float = 0.0  #: share of the cells the team can observe that some rover observed
    #: first step its coverage of the cells it can observe reached each of COVERAGE_LEVELS
    coverage_reachable_steps: dict[float, int | None] = field(default_factory=dict)
    #: the step the stop rule (``stop_coverage``) ended the run at; None (and not written): it took every step
    stopped_step: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """The ``summary`` of ``metrics.json``: every field under its own name (so
        ``summary["final_global_f1"]`` in the file is ``summary.final_global_f1`` in Python);
        ``coverage_steps`` is keyed by the level in per cent (``"95%"``)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["coverage_steps"] = {f"{int(level * 100)}%": t for level, t in self.coverage_steps.items()}
        out["coverage_reachable_steps"] = {f"{int(level * 100)}%": t for level, t in
                                           self.coverage_reachable_steps.items()}
        out["first_belief_f1_step_per_rover"] = list(self.first_belief_f1_step_per_rover)
        out["messages"] = dict(self.messages)
        out["ready_coverage"] = READY_COVERAGE
        for name in UNWRITTEN_WHEN_NONE:  # missions without a predictor or stop rule keep their metrics.json
            if out[name] is None:
                del out[name]
        return out


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
class Snapshot:
    """Everything a viewer draws of one strategy at one step, handed to ``run_mission``'s
    ``on_snapshot`` as the mission runs (a recording or a live view). Arrays are the run's
    own: copy what you keep."""

    strategy: str  #: the strategy running
    step: int  #: the mission clock (0 to ``steps``)
    truth: GridMap  #: the ground truth (the same object every step)
    beliefs: list[np.ndarray]  #: every member's belief (classes), team order: rovers, then helicopters
    views: list[np.ndarray]  #: every member's view: its belief in its own classes, what it plans on
    global_map: np.ndarray  #: the base's global map (classes)
    global_heights: np.ndarray | None  #: the heights the base holds (metres, NaN elsewhere; None: no layer)
    positions: list[Cell]  #: every member's cell
    targets: list[Cell | None]  #: every member's current target (None: none)
    kinds: list[str]  #: every member's kind (rover, helicopter)
    sensor_radius: list[float]  #: every member's sensor radius, cells
    base: Cell  #: the base station's cell
    links: tuple[tuple[int, int], ...]  #: peer topologies: the links up at the last sync (agents; -1: lander)
    leaders: tuple[int, ...]  #: leader topology: the agents leading at the last sync
    messages: list[Message]  #: the ledger entries added since the previous snapshot
    row: StepRow  #: this step's scores (coverage, accuracy, bytes, ...)
    eval: EvalRow | None  #: this step's map scores when it is an evaluation step, else None


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
    #: the journal's :attr:`~fedmap.mission.ends.protocol.Journal.dropped` (None: it sends no model updates)
    dropped_updates: tuple[DroppedUpdate, ...] | None = None
    #: model strategies: at every sync, before training, how many models behind the base each rover is
    #: (``{"round": r, "lag": [...]}``; None in ``lag``: it holds none the base still keeps)
    model_lag: tuple[dict, ...] | None = None
    #: with ``[frames]``: the base's registrations, one per rover and sync (``Placing.to_dict``; None: known poses)
    registrations: tuple[dict, ...] | None = None
    sharing: Any = None  #: the ends' final state (:class:`~fedmap.mission.ends.registry.Sharing`; not written)
    #: every member's final view: its belief in its own classes, what it plans on and is scored on
    views: tuple[np.ndarray, ...] = ()
    #: what its transport carried, beside the ledger's strategy bytes: ``frames`` and their
    #: ``bytes``, framing included (on processes also ``orders`` and ``reports``, bytes each);
    #: None for a strategy that sends nothing
    wire: dict | None = None

    def to_dict(self) -> dict[str, Any]:
        """The strategy's entry of ``metrics.json`` (no frames, trails or strategy state)."""
        out: dict[str, Any] = {"summary": self.summary.to_dict(), "seconds": self.seconds,
                               "series": self.series.to_dict(), "ledger": [m.to_dict() for m in self.ledger]}
        if self.dropped_updates is not None:
            out["dropped_updates"] = [d.to_dict() for d in self.dropped_updates]
        if self.model_lag is not None:
            out["model_lag"] = list(self.model_lag)
        if self.registrations is not None:
            out["registrations"] = list(self.registrations)
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
    #: on processes: one record per fault met and how it was handled (``{"strategy", "rover", "fault"}``)
    faults: tuple[dict, ...] = ()



class Scorer:
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
class StepRow:
    """One step's entry of every :class:`TimeSeries` series (see there)."""

    step: int
    coverage: float
    coverage_reachable: float
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
class EvalRow:
    """One evaluation step's entry of every :class:`EvalSeries` series (see there)."""

    step: int
    psnr: float
    ssim: float
    accuracy: float
    f1: float
    f1_tolerant: float
    belief_f1: tuple[float, ...]
    belief_success: tuple[float, ...]
    predicted_f1: tuple[float, ...] | None = None
    predicted_success: tuple[float, ...] | None = None
    predicted_false_free: tuple[float, ...] | None = None
    predicted_accuracy_unobserved: tuple[float, ...] | None = None


def series_of(rows: list[StepRow], evals: list[EvalRow]) -> TimeSeries:
    """The time series of the recorded rows (one per step, one per evaluation step)."""
    ev = EvalSeries(step=tuple(e.step for e in evals), psnr=tuple(e.psnr for e in evals),
                    ssim=tuple(e.ssim for e in evals), accuracy=tuple(e.accuracy for e in evals),
                    f1=tuple(e.f1 for e in evals), f1_tolerant=tuple(e.f1_tolerant for e in evals),
                    belief_f1=tuple(e.belief_f1 for e in evals), belief_success=tuple(e.belief_success for e in evals),
                    **{name: tuple(getattr(e, name) for e in evals) if evals and all(getattr(e, name) is not None
                                                                                    for e in evals) else None
                       for name in PREDICTED_SERIES})
    return TimeSeries(step=tuple(r.step for r in rows), coverage=tuple(r.coverage for r in rows),
                      redundant=tuple(r.redundant for r in rows), accuracy=tuple(r.accuracy for r in rows),
                      accuracy_observed=tuple(r.accuracy_observed for r in rows),
                      accuracy_unobserved=tuple(r.accuracy_unobserved for r in rows),
                      false_free=tuple(r.false_free for r in rows), distance=tuple(r.distance for r in rows),
                      bytes_up=tuple(r.bytes_up for r in rows), bytes_down=tuple(r.bytes_down for r in rows),
                      up_delivered=tuple(r.up_delivered for r in rows), up_dropped=tuple(r.up_dropped for r in rows),
                      down_delivered=tuple(r.down_delivered for r in rows),
                      down_dropped=tuple(r.down_dropped for r in rows), eval=ev,
                      coverage_reachable=tuple(r.coverage_reachable for r in rows))


def share(hit: np.ndarray, where: np.ndarray) -> float:
    """The share of the ``where`` cells that are ``hit`` (1.0 when there are none: nothing to get wrong)."""
    n = int(where.sum())
    return float((hit & where).sum() / n) if n else 1.0


def false_free(free: np.ndarray, truth: np.ndarray) -> float:
    """The share of the ``free`` cells (a map's FREE cells) that are impassable in ``truth``
    (0.0 when there are none: nothing planned as free)."""
    return float((free & (truth == IMPASSABLE)).sum() / max(int(free.sum()), 1))



def first_step(steps: Sequence[int], values: Sequence[float], level: float) -> int | None:
    """The first step whose value is at least ``level`` (None: never)."""
    for t, v in zip(steps, values):
        if v >= level - 1e-12:
            return t
    return None


def summarise(series: TimeSeries, ledger: list[Message], config: MissionConfig, slots: int = 0, *,
              reachable_share: float = 1.0) -> MissionSummary:
    """Steps to the coverage levels (of the whole map, and of the share ``reachable_share``
    of it the team can observe), first step a belief reaches :data:`F1_GOAL`, finals, bytes."""
    ev = series.eval
    per_rover_f1 = tuple(first_step(ev.step, [f[k] for f in ev.belief_f1], F1_GOAL) for k in range(config.rovers))
    reached = [t for t in per_rover_f1 if t is not None]
    team_f1 = [float(np.mean(f[:config.rovers])) for f in ev.belief_f1]  # the rovers' (helicopters plan no paths)
    at = {t: i for i, t in enumerate(series.step)}
    reach = series.coverage_reachable
    ready = next((t for t, f in zip(ev.step, team_f1)
                  if f >= F1_GOAL - 1e-12 and reach[at[t]] >= READY_COVERAGE - 1e-12), None)
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
        team_f1_step=first_step(ev.step, team_f1, F1_GOAL),
        ready_step=ready,
        ready_bytes=None if ready is None else int(np.sum(series.bytes_up[at[ready]]) +
                                                   np.sum(series.bytes_down[at[ready]])),
        predicted_belief=predicted_belief(ev, config.rovers),
        reachable_share=reachable_share,
        final_coverage_reachable=reach[-1],
        coverage_reachable_steps={level: first_step(series.step, reach, level) for level in COVERAGE_LEVELS},
        stopped_step=series.step[-1] if series.step[-1] < config.steps else None,
    )


def predicted_belief(ev: EvalSeries, rovers: int) -> dict[str, float | int | None] | None:
    """:attr:`MissionSummary.predicted_belief` of the evaluation series (None without a predictor)."""
    if ev.predicted_f1 is None or ev.predicted_success is None or ev.predicted_false_free is None or not ev.step:
        return None
    team = [float(np.mean(f[:rovers])) for f in ev.predicted_f1]  # the rovers' (helicopters plan no paths)
    return {"f1_step": first_step(ev.step, team, F1_GOAL), "final_f1": team[-1],
            "final_success": float(np.mean(ev.predicted_success[-1][:rovers])),
            "final_false_free": float(np.mean(ev.predicted_false_free[-1][:rovers]))}



#: A rover or helicopter that moved less than this share of its range is flagged (:func:`movement_warnings`).
MOVED_LITTLE = 0.1


def movement_warnings(result: MissionResult) -> list[str]:
    """One line per member of the team that moved less than :data:`MOVED_LITTLE` of its range
    under some strategy: its near-empty map still counts in every mean over the team. A
    rover's range is ``steps * speed`` cells; a helicopter's counts only the share of the
    steps it may fly (``flight_budget / (flight_budget + recharge)``) at its own speed."""
    c = result.config
    hc = c.helicopter
    out = []
    for k in range(c.rovers + c.helicopters):
        heli = k >= c.rovers
        reach = c.steps * (hc.speed * hc.flight_budget / (hc.flight_budget + hc.recharge) if heli else c.speed)
        moved = {name: run.series.distance[-1][k] for name, run in result.runs.items()}
        low = {name: d for name, d in moved.items() if d < MOVED_LITTLE * reach}
        if low:
            who = f"helicopter {k}" if heli else f"rover {k}"
            out.append(f"{who} moved only {', '.join(f'{d:.0f} cells ({n})' for n, d in low.items())} in {c.steps} "
                       f"steps, under {MOVED_LITTLE:.0%} of its {reach:.0f}-cell range: its near-empty map still "
                       "counts in the team's belief columns")
    return out
