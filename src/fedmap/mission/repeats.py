"""A mission repeated with other seeds, and what its numbers are worth: a mean with a 95 %
interval per strategy and per value.

One run's figures hold for one draw of the evaluation pairs, the link's losses and the
rovers' starts: changing only the evaluation pairs moved a global path F1 from 0.86 to 0.73.
:func:`repeat_configs` gives repeat ``i`` the mission seed ``seed + i`` (evaluation pairs,
height noise, waypoints, the networks' seeds) and the link seed ``link.seed + i`` (losses,
drops), and draws the starts in the start area (``start_spread`` cells around the lander,
:data:`REPEAT_SPREAD` when the mission sets none). The terrain stays the one loaded: the
repeats ask how the ways of sharing compare on this site, not on other sites.

:func:`interval` is Student's t interval of the mean over the repeats (the values are
independent draws of one mission); with one value it is that value.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.mission.results import MissionResult, MissionSummary
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import run_mission

#: The start area's radius (cells around the lander) of repeats of a mission that sets none.
REPEAT_SPREAD = 8
#: The confidence level of every interval.
LEVEL = 0.95


@dataclass(frozen=True)
class Interval:
    """The mean of ``values`` with its :data:`LEVEL` interval ``[lo, hi]`` (Student's t).
    ``n`` counts the values (a value that was never reached is not one: ``missing``)."""

    mean: float
    lo: float
    hi: float
    n: int
    missing: int = 0
    values: tuple[float, ...] = ()

    def separated_above(self, other: Interval) -> bool:
        """Whether this interval lies wholly above ``other`` (they do not overlap)."""
        return self.n > 1 and other.n > 1 and self.lo > other.hi

    def to_dict(self) -> dict:
        return {"mean": self.mean, "lo": self.lo, "hi": self.hi, "n": self.n, "missing": self.missing,
                "values": list(self.values)}


def interval(values: Sequence[float | None], level: float = LEVEL,
             bounds: tuple[float, float] = (-math.inf, math.inf)) -> Interval | None:
    """The mean of the values that are not None, with its Student's t interval at ``level``
    (None when every value is None), clipped to the values' possible range ``bounds`` (a
    share is never below 0). One value: the interval is that value."""
    got = [float(v) for v in values if v is not None]
    missing = len(values) - len(got)
    if not got:
        return None
    n = len(got)
    mean = math.fsum(got) / n
    if n == 1:
        return Interval(mean, mean, mean, 1, missing, tuple(got))
    sd = math.sqrt(math.fsum((v - mean) ** 2 for v in got) / (n - 1))
    from scipy import stats  # here: scipy.stats is 0.7 s of CPU that every fedmap command would import

    half = float(stats.t.ppf(0.5 + level / 2, n - 1)) * sd / math.sqrt(n)
    return Interval(mean, max(mean - half, bounds[0]), min(mean + half, bounds[1]), n, missing, tuple(got))


def repeat_configs(config: MissionConfig, repeats: int) -> list[MissionConfig]:
    """The missions of ``repeats`` repeats of ``config`` (see the module docstring). Repeat 0
    keeps ``config``'s seeds; the starts are drawn unless ``config`` gives them."""
    if not (isinstance(repeats, int) and repeats >= 1):
        raise FedmapError(f"repeats must be a whole number >= 1, got {repeats!r}")
    if repeats == 1:
        return [config]
    spread = config.start_spread or (0 if config.starts is not None else REPEAT_SPREAD)
    # an unset link seed follows the mission's seed (so it is seed + i too)
    return [replace(config, seed=config.seed + i, start_spread=spread,
                    link=config.link if config.link.seed is None else replace(config.link, seed=config.link.seed + i))
            for i in range(repeats)]


def what_varies(config: MissionConfig, repeats: int) -> str:
    """One line: what the repeats vary, and what they keep."""
    configs = repeat_configs(config, repeats)
    c = configs[-1]
    starts = ("the starts given by [mission] starts" if config.starts is not None else
              f"starts drawn within {c.start_spread} cells of the lander")
    return (f"{repeats} repeats, seeds {configs[0].seed}..{c.seed}, link seeds {configs[0].link_seed}..{c.link_seed}: "
            f"each draws its own evaluation pairs, losses, height noise and {starts}; the terrain is the same")


def run_repeats(config: MissionConfig, truth: GridMap, repeats: int, *,
                on_repeat: Callable[[int, MissionConfig], None] | None = None, **kw) -> list[MissionResult]:
    """Every repeat of the mission (:func:`repeat_configs`) on the same ``truth``, in order;
    ``kw`` goes to :func:`~fedmap.mission.sim.run_mission` (elevation, prior, profiles,
    thresholds, progress callbacks, frames) and ``on_repeat(i, config)`` announces each."""
    out = []
    for i, c in enumerate(repeat_configs(config, repeats)):
        if on_repeat is not None:
            on_repeat(i, c)
        out.append(run_mission(c, truth, **kw))
    return out


#: The values an interval is given for: name -> how to read it from a summary (None: not reached).
VALUES: dict[str, Callable[[MissionSummary], float | int | None]] = {
    "coverage": lambda s: s.final_coverage,
    "belief accuracy": lambda s: s.final_belief_accuracy_mean,
    "belief F1": lambda s: s.final_belief_f1_mean,
    "path success": lambda s: s.final_path_success_mean,
    "false-free": lambda s: s.final_false_free_mean,
    "global F1": lambda s: s.final_global_f1,
    "team bytes": lambda s: s.bytes_up + s.bytes_down,
    "steps to 95 %": lambda s: s.coverage_reachable_steps[0.95],
    "team F1≥0.9 at": lambda s: s.team_f1_step,
    "plannable at": lambda s: s.ready_step,
    "bytes to plannable": lambda s: s.ready_bytes,
}


#: Values of missions with a predictor (``predictor = "learned"``), after :data:`VALUES`: the
#: first step the rovers' beliefs with the guesses filled in reached a mean F1 of 0.9.
PREDICTED_VALUES: dict[str, Callable[[MissionSummary], float | int | None]] = {
    "guessed F1≥0.9 at": lambda s: None if s.predicted_belief is None else s.predicted_belief["f1_step"],
}

#: Values that are shares (0..1); the others are counts (steps, bytes), never below 0.
SHARES = ("coverage", "belief accuracy", "belief F1", "path success", "false-free", "global F1")


def values_of(results: Sequence[MissionResult]) -> dict[str, Callable[[MissionSummary], float | int | None]]:
    """:data:`VALUES`, and :data:`PREDICTED_VALUES` when the missions ran with a predictor."""
    guessed = any(run.summary.predicted_belief is not None for r in results for run in r.runs.values())
    return {**VALUES, **PREDICTED_VALUES} if guessed else dict(VALUES)


def intervals(results: Sequence[MissionResult]) -> dict[str, dict[str, Interval | None]]:
    """``{strategy: {value: interval over the repeats}}`` for every value of :func:`values_of`."""
    names = list(results[0].runs)
    return {n: {v: interval([get(r.runs[n].summary) for r in results],
                            bounds=(0.0, 1.0) if v in SHARES else (0.0, math.inf))
                for v, get in values_of(results).items()}
            for n in names}


__all__ = ["LEVEL", "PREDICTED_VALUES", "REPEAT_SPREAD", "SHARES", "VALUES", "Interval", "interval", "intervals",
           "repeat_configs", "run_repeats", "values_of", "what_varies"]
