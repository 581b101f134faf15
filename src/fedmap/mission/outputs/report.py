"""A mission's outputs, in one atomic folder.

* ``metrics.json``: the mission and link settings, and per strategy its summary, its
  time series and its ledger (one row per message);
* ``report.md``: the strategies side by side (:func:`side_by_side`);
* ``coverage.png`` (coverage vs step), ``f1.png`` (the base's global map and the best
  rover belief, strict path F1 vs step), ``accuracy_bytes.png`` (mean belief accuracy
  vs cumulative bytes per rover, both directions), ``knowing.png`` (accuracy on observed
  and on unobserved cells, false-free rate, executed path success, vs step);
* ``maps/``: each strategy's final global map (``<strategy>_global``; with ``beliefs``, each
  rover's final belief, ``<strategy>_rover<k>``) as ``.png``, ``.tif`` (GeoTIFF, the truth's
  CRS and transform) and ``.yaml`` + ``.pgm`` (ROS map_server);
* ``mission_<strategy>.gif`` (and ``.mp4`` when ``ffmpeg`` is on the PATH): the truth,
  every rover's belief with its path, position and sensor footprint, and the global map.
"""

from __future__ import annotations

import io
import shutil
import subprocess
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from skimage.draw import line as draw_line

from fedmap._util import AtomicDir, atomic_write_bytes
from fedmap.maps.grid import PALETTE
from fedmap.mission.ends.registry import role_of
from fedmap.mission.network.link import BASE
from fedmap.mission.network.topology import TOPOLOGIES
from fedmap.mission.outputs.maps_out import write_mission_maps
from fedmap.mission.repeats import Interval, interval, intervals, values_of, what_varies
from fedmap.mission.results import READY_COVERAGE, first_step
from fedmap.mission.sim import COVERAGE_LEVELS, F1_GOAL, MissionResult, MissionSummary
from fedmap.mission.world.sensing import disk_offsets
from fedmap.outputs import write_metrics


def _pyplot():
    """matplotlib's pyplot on the file-only Agg backend, imported when a plot is drawn
    (as in fedmap.outputs): not at ``fedmap`` start-up, and no backend switch on import."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def without_timings(data):
    """``metrics.json`` data (or any part of it) without its wall times (every ``seconds``):
    what two runs of the same mission must agree on."""
    if isinstance(data, dict):
        return {k: without_timings(v) for k, v in data.items() if k != "seconds"}
    if isinstance(data, list):
        return [without_timings(v) for v in data]
    return data


def metrics(result: MissionResult, *, settings: dict | None = None) -> dict:
    """The ``metrics.json`` of a mission."""
    h, w = result.truth.shape
    return {
        "settings": settings or {"mission": result.config.to_dict()},
        "truth": {"shape": [h, w], "pixel_size_m": result.truth.pixel_size, "source": result.truth.source,
                  **result.truth.fractions()},
        "starts": [list(s) for s in result.starts], "base": list(result.base),
        "seconds": result.seconds,
        "strategies": {name: run.to_dict() for name, run in result.runs.items()},
        **({"faults": list(result.faults)} if result.faults else {}),
        # what the transport carried, framing included, beside each ledger
        **({"wire": {name: run.wire for name, run in result.runs.items() if run.wire is not None}}
           if any(run.wire is not None for run in result.runs.values()) else {}),
    }


def _fmt(v, nd: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if v == float("inf"):
            return "inf"
        if nd and 0 < abs(v) < 0.5 * 10 ** -nd:  # a small rate keeps two significant digits, never "0.000"
            return f"{v:.2g}"
        return f"{v:.{nd}f}"
    return f"{v:,}" if isinstance(v, int) else str(v)


def _fmt_interval(iv: Interval | None, nd: int) -> str:
    """``0.53 [0.48, 0.58]``; a value some repeats never reached adds how many did (``3/5``)."""
    if iv is None:
        return "-"
    small = nd and 0 < max(abs(iv.mean), abs(iv.hi)) < 0.5 * 10 ** -nd  # small rates: two significant digits
    fmt = ((lambda v: f"{round(v):,}") if nd == 0 else (lambda v: f"{v:.2g}") if small  # noqa: E731
           else (lambda v: _fmt(float(v), nd)))
    out = fmt(iv.mean) if iv.n == 1 or iv.lo == iv.hi else f"{fmt(iv.mean)} [{fmt(iv.lo)}, {fmt(iv.hi)}]"
    return out + (f" ({iv.n}/{iv.n + iv.missing})" if iv.missing else "")


def _steps_to(level: float) -> Callable[[MissionSummary], int | None]:
    """The first step the team observed ``level`` of the cells it can reach."""
    return lambda s: s.coverage_reachable_steps[level]


#: The side-by-side columns: header -> (how to read it from a summary, decimals).
COLUMNS: dict[str, tuple[Callable[[MissionSummary], Any], int]] = {
    **{f"steps to {int(lv * 100)} %": (_steps_to(lv), 0) for lv in COVERAGE_LEVELS},
    f"belief F1≥{F1_GOAL} at": (lambda s: s.first_belief_f1_step, 0),
    "coverage": (lambda s: s.final_coverage, 3),
    "reachable coverage": (lambda s: s.final_coverage_reachable, 3),
    "redundant": (lambda s: s.final_redundant, 3),
    "belief acc.": (lambda s: s.final_belief_accuracy_mean, 3),
    "acc. observed": (lambda s: s.final_accuracy_observed_mean, 3),
    "acc. unobserved": (lambda s: s.final_accuracy_unobserved_mean, 3),
    "false-free": (lambda s: s.final_false_free_mean, 3),
    "belief F1": (lambda s: s.final_belief_f1_mean, 2),
    "path success": (lambda s: s.final_path_success_mean, 2),
    "global PSNR": (lambda s: s.final_global_psnr, 2),
    "global SSIM": (lambda s: s.final_global_ssim, 3),
    "global F1": (lambda s: s.final_global_f1, 2),
    "global tol.F1": (lambda s: s.final_global_f1_tolerant, 2),
    "team bytes up": (lambda s: s.bytes_up, 0),
    "team bytes down": (lambda s: s.bytes_down, 0),
    "B/link/round": (lambda s: round(s.bytes_per_link_round), 0),
}

#: A share of the map the team can reach below which the report says part of it is walled off.
WALLED_BELOW = 0.995

#: Ledger statuses of a message that did not arrive, in the order the report names them.
UNDELIVERED = ("over budget", "lost", "stale", "out of range", "link down", "rejected", "no sync")


def undelivered(summary: MissionSummary, direction: str) -> str:
    """``"30 over budget, 2 lost"``: the messages of one direction (``up``, ``down``, ``peer``) that
    did not arrive, by why (``-``: none)."""
    parts = [f"{summary.messages[f'{direction}_{st}']} {st}" for st in UNDELIVERED
             if summary.messages.get(f"{direction}_{st}")]
    return ", ".join(parts) or "-"


def _winner(ivs: dict[str, Interval], *, high: bool) -> tuple[str | None, list[str]]:
    """The strategy whose interval lies wholly beyond every other's (the highest when ``high``,
    else the lowest), or None and the strategies that tie with the best mean. One value each
    (a single run): the best mean wins, ties by name order."""
    if not ivs:
        return None, []
    sign = 1.0 if high else -1.0
    best = max(ivs, key=lambda n: sign * ivs[n].mean)
    if all(iv.n == 1 for iv in ivs.values()):
        return best, []
    b = ivs[best]
    tied = [n for n, iv in ivs.items() if n != best and not (
        b.separated_above(iv) if high else iv.separated_above(b))]
    return (None, [best, *tied]) if tied else (best, [])


def plannable(results: Sequence[MissionResult]) -> str:
    """One computed line: when each strategy's rovers first had a plannable map (their mean
    belief F1 at least :data:`F1_GOAL` and their coverage of the cells they can reach at least
    :data:`READY_COVERAGE`; the share of the map those are is said when it is not all of it), the
    bytes spent to get there, the soonest and the fewest bytes among those that got there in
    every repeat (``central``, pooling every observation at once for free, is shown but is no
    candidate). A winner is named only where the intervals separate."""
    n = len(results)
    names = list(results[0].runs)
    steps = {k: interval([r.runs[k].summary.ready_step for r in results]) for k in names}
    spent = {k: interval([r.runs[k].summary.ready_bytes for r in results]) for k in names}
    reach = float(np.mean([r.runs[k].summary.reachable_share for r in results for k in names]))
    goal = (f"the rovers' mean belief F1 ≥ {F1_GOAL} and {READY_COVERAGE:.0%} coverage of the cells they can reach"
            + (f", {reach:.0%} of the map" if reach < WALLED_BELOW else ""))
    reached = [k for k in names if steps[k] is not None]
    if not reached:
        return (f"No strategy gave the team a plannable map ({goal}) in {results[0].config.steps} steps"
                + (f" in any of {n} repeats" if n > 1 else "") + ".")
    parts = []
    for k in names:
        iv, b = steps[k], spent[k]
        who = f"{k} (every observation pooled at once, free)" if role_of(k) == "reference" else k
        if iv is None:
            parts.append(f"{who} never")
            continue
        some = f" in {iv.n}/{n} repeats" if iv.missing else ""
        parts.append(f"{who} at step {_fmt_interval(replace(iv, missing=0), 0)} for "
                     f"{_fmt_interval(replace(b, missing=0), 0) if b else '-'} B{some}")
    line = f"Plannable map ({goal}): " + "; ".join(parts) + "."
    every: dict[str, Interval] = {}  # the candidates: those that got there in every repeat
    costs: dict[str, Interval] = {}
    for k in reached:
        iv, b = steps[k], spent[k]
        if role_of(k) != "reference" and iv is not None and b is not None and not iv.missing:
            every[k], costs[k] = iv, b
    if not every:
        return line + " No strategy but the central oracle got there" + (" in every repeat." if n > 1 else ".")
    soon, tie_s = _winner(every, high=False)
    cheap, tie_b = _winner(costs, high=False)
    line += (f" Soonest: **{soon}**." if soon else f" Soonest: no clear difference between {', '.join(tie_s)}.")
    line += (f" Fewest bytes to get there: **{cheap}**." if cheap else
             f" Fewest bytes to get there: no clear difference between {', '.join(tie_b)}.")
    return line


#: The coverage of the cells the team can reach that :func:`stop_rule` names, when no stop rule ran.
STOP_HINT = 0.99


def stop_rule(results: Sequence[MissionResult]) -> str:
    """One computed sentence on the stop rule: with ``stop_coverage``, the step each strategy's
    run ended at; without one (the default: every run takes all its steps), the first step by
    which every strategy's team had observed :data:`STOP_HINT` of the cells it can reach, when
    one did before the end, and the option that would have ended the runs there."""
    c = results[0].config
    names = list(results[0].runs)
    n = len(results)
    if c.stop_coverage is not None:
        parts = []
        for k in names:
            ends = [r.runs[k].summary.stopped_step for r in results]
            got = [t for t in ends if t is not None]
            if not got:
                parts.append(f"{k} took all {c.steps} steps")
                continue
            span = f"{got[0]}" if len(set(got)) == 1 else f"{min(got)}-{max(got)}"
            parts.append(f"{k} at step{'s' if len(set(got)) > 1 else ''} {span}"
                         + (f" in {len(got)}/{n} repeats" if n > 1 else ""))
        return (f" Stop rule: a run ends once its team has observed {c.stop_coverage:.0%} of the cells it can "
                f"reach: " + "; ".join(parts) + ".")
    firsts = [first_step(r.runs[k].series.step, r.runs[k].series.coverage_reachable, STOP_HINT)
              for r in results for k in names]
    known = [t for t in firsts if t is not None]
    if not known or len(known) < len(firsts) or max(known) >= c.steps:
        return ""
    return (f" No stop rule (the default: every run takes all {c.steps} steps); every strategy's team had observed "
            f"{STOP_HINT:.0%} of the cells it can reach by step {max(known)}"
            + (" in every repeat" if n > 1 else "")
            + f": --stop-coverage {STOP_HINT:g} ends each run there.")


def verdict(result: MissionResult, repeats: Sequence[MissionResult] | None = None) -> str:
    """:func:`_verdict`, then :func:`stop_rule`'s sentence."""
    results = list(repeats) if repeats is not None and len(repeats) > 1 else [result]
    return _verdict(result, repeats) + stop_rule(results)


def _verdict(result: MissionResult, repeats: Sequence[MissionResult] | None = None) -> str:
    """Computed lines: when each strategy's team first had a plannable map and for how many
    bytes (:func:`plannable`); which strategy left the rovers the best map, and which gained
    the most map per byte on the link (``central``, the free oracle, is left out of both).
    With ``repeats`` (more than one), every value is a mean with its 95 % interval and a
    winner is named only where the intervals separate ("no clear difference" otherwise)."""
    results = list(repeats) if repeats is not None and len(repeats) > 1 else [result]
    others = {n: r for n, r in result.runs.items() if role_of(n) != "reference"}
    # a strategy that got nothing through the link holds its own observations over its
    # initial model's rendering: a score from the latter is a guess, so it is no candidate
    silent = [n for n in others if role_of(n) != "baseline" and all(
        r.runs[n].summary.bytes_up + r.runs[n].summary.bytes_down == 0 for r in results)]
    runs = [n for n in others if n not in silent]
    low = next((n for n in runs if role_of(n) == "baseline"), None)  # sharing nothing, if it ran
    notes = "".join(f" {n} got nothing through the link (uplinks: {undelivered(others[n].summary, 'up')}): its "
                    f"{others[n].summary.final_belief_accuracy_mean:.3f} is what each rover observed itself (over "
                    f"its initial rendering, for a model strategy: {float(np.mean(others[n].series.accuracy[0])):.3f} "
                    "at step 0), not shared knowledge." for n in silent)
    first = plannable(results) + " "
    if not runs:
        return first + ("Only the central oracle ran: nothing to compare." if not others else
                        "No strategy got anything through the link." + notes)
    acc = {n: interval([r.runs[n].summary.final_belief_accuracy_mean for r in results], bounds=(0.0, 1.0))
           for n in runs}
    spent = {n: [r.runs[n].summary.bytes_up + r.runs[n].summary.bytes_down for r in results] for n in runs}
    if len(results) == 1:  # one run: the best mean wins; a tie as printed is named as one
        top_acc = max(round(acc[n].mean, 3) for n in runs)  # type: ignore[union-attr]
        level = [n for n in runs if round(acc[n].mean, 3) == top_acc]  # type: ignore[union-attr]
        best: str | None = min(level, key=lambda n: spent[n][0])
        tied: list[str] = level if len(level) > 1 else []
    else:
        best, tied = _winner(acc, high=True)  # type: ignore[arg-type]
    if best is None:
        line = ("Best map: no clear difference between " + ", ".join(
            f"{n} ({_fmt_interval(acc[n], 3)})" for n in tied) + " (belief accuracy, 95 % intervals overlap).")
    elif tied:  # one run, several at the top
        line = (f"Best map: a tie between {_and(tied)} (belief accuracy {_fmt_interval(acc[best], 3)}); **{best}** "
                f"spent the fewest bytes ({spent[best][0]:,} B)")
        if low is not None and low not in tied:
            line += f", against {_fmt_interval(acc[low], 3)} sharing nothing"
        line += "."
    else:
        line = f"Best map: **{best}** (belief accuracy {_fmt_interval(acc[best], 3)}"
        if low is not None and best != low:
            line += f", against {_fmt_interval(acc[low], 3)} sharing nothing"
        line += ")."
    # what the bytes bought: the accuracy above sharing nothing (the same mission's `none`), and only that
    if low is None:
        if any(max(b) for b in spent.values()):
            line += " Best map per byte: needs none (sharing nothing) among the strategies, its baseline."
        return first + line + notes
    gains = {n: [(r.runs[n].summary.final_belief_accuracy_mean - r.runs[low].summary.final_belief_accuracy_mean) / b
                 for r, b in zip(results, spent[n])] for n in runs if min(spent[n]) > 0}
    gain = {n: interval(g) for n, g in gains.items() if np.mean(g) > 0}
    if gain:
        top, tied_g = _winner(gain, high=True)  # type: ignore[arg-type]
        if top is not None:  # the mean over the repeats (one run: its own figures)
            points = float(np.mean([(r.runs[top].summary.final_belief_accuracy_mean
                                     - r.runs[low].summary.final_belief_accuracy_mean) * 100 for r in results]))
            line += (f" Best map per byte: **{top}** (+{points:.2f} accuracy points over sharing nothing "
                     f"for {round(float(np.mean(spent[top]))):,} B of the team's traffic).")
        else:
            line += f" Best map per byte: no clear difference between {', '.join(tied_g)}."
    elif any(max(b) for b in spent.values()):
        line += " No strategy that used the link gave a better map than sharing nothing."
    return first + line + notes


def _reach_text(result: MissionResult) -> str:
    """What share of the map the team can reach, in words."""
    share = next(iter(result.runs.values())).summary.reachable_share if result.runs else 1.0
    return "all of the map" if share >= WALLED_BELOW else f"{share:.1%} of the map; the rest is walled off"


def _wall_time(result: MissionResult, repeats: Sequence[MissionResult] | None) -> str:
    """The run's wall time and each strategy's; with repeats, all of them together (the
    whole run) and the per-strategy sums over the repeats."""
    results = list(repeats) if repeats is not None and len(repeats) > 1 else [result]
    per = {n: sum(r.runs[n].seconds for r in results) for n in result.runs}
    total = sum(r.seconds for r in results)
    over = f" over {len(results)} repeats" if len(results) > 1 else ""
    return f"Wall time: {total:.1f} s{over} (" + ", ".join(f"{n} {t:.1f} s" for n, t in per.items()) + ")."


def _and(names: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


#: Decimals of each value of a repeats table (:data:`~fedmap.mission.repeats.VALUES`).
_REPEAT_DECIMALS = {"coverage": 3, "belief accuracy": 3, "belief F1": 2, "path success": 2, "false-free": 3,
                    "global F1": 2, "team bytes": 0, "steps to 95 %": 0, "team F1≥0.9 at": 0, "plannable at": 0,
                    "bytes to plannable": 0, "guessed F1≥0.9 at": 0}


def repeat_rows(results: Sequence[MissionResult]) -> tuple[list[str], list[list[str]]]:
    """Header and one row per strategy: each value's mean over the repeats with its 95 %
    interval, ``mean [lo, hi]`` (a step some repeats never reached says in how many it was)."""
    ivs = intervals(results)
    values = list(values_of(results))
    header = ["strategy", *values]
    return header, [[name, *(_fmt_interval(ivs[name][v], _REPEAT_DECIMALS[v]) for v in values)] for name in ivs]


def table_rows(result: MissionResult) -> tuple[list[str], list[list[str]]]:
    """Header and one row per strategy of the side-by-side table (final values, the belief
    accuracy at step 0 before any message, and the messages that did not arrive)."""
    peer = has_peers(result)
    heights = "elevation" in result.config.layers
    header = ["strategy", *COLUMNS, "belief acc. at step 0", "uplinks not delivered", "downlinks not delivered",
              *(["peer messages not delivered"] if peer else []),
              *(["base height RMSE m", "base height coverage"] if heights else [])]
    rows = []
    for name, run in result.runs.items():
        s = run.summary
        rows.append([name, *(_fmt(get(s), nd) for get, nd in COLUMNS.values()),
                     _fmt(float(np.mean(run.series.accuracy[0])), 3),
                     undelivered(s, "up"), undelivered(s, "down"),
                     *([undelivered(s, "peer")] if peer else []),
                     *([_fmt(s.final_height_rmse_m, 3), _fmt(s.final_height_coverage, 3)] if heights else [])])
    return header, rows


def has_peers(result: MissionResult) -> bool:
    """Whether the mission has peer messages: a mesh or leader topology, or ``gossip``."""
    return not TOPOLOGIES[result.config.link.topology].has_base or any(
        m.direction == "peer" for r in result.runs.values() for m in r.ledger)


def global_meaning(result: MissionResult) -> str:
    """What the "global map" of this mission is."""
    link = result.config.link
    if TOPOLOGIES[link.topology].has_base:
        return "the base station's map"
    if link.lander_agent:
        return "the lander's map (an agent of the mesh)"
    return "the map every rover agrees on (no base station: each cell all beliefs hold with the same class)"


def side_by_side(result: MissionResult, repeats: Sequence[MissionResult] | None = None) -> str:
    """The strategies side by side, as a Markdown table (with ``repeats``: means and intervals)."""
    header, rows = repeat_rows(repeats) if repeats is not None and len(repeats) > 1 else table_rows(result)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def report_md(result: MissionResult, *, title: str, animations: list[str] | None = None,
              repeats: Sequence[MissionResult] | None = None) -> str:
    """The mission's ``report.md``; ``animations`` are the animation files written beside it
    (None: one GIF per strategy), so the report links only files that exist. With
    ``repeats`` (more than one, ``result`` the first), the table and verdict give each value's
    mean over the repeats with its 95 % interval; the animations show the first repeat."""
    if animations is None:
        animations = [f"mission_{n}.gif" for n in result.runs]
    c, link = result.config, result.config.link
    topology = TOPOLOGIES[link.topology]
    h, w = result.truth.shape
    budget = lambda b: "unlimited" if b is None else f"{b:,} B"  # noqa: E731
    lines = [
        f"# Mission: {title}", "",
        f"{h}x{w} cells of {result.truth.pixel_size:.3g} m; {c.rovers} rovers from {[list(s) for s in result.starts]}, "
        f"base station at {list(result.base)}; {c.steps} steps at {c.speed} cell(s) per step, sensor radius "
        f"{c.sensor_radius:g} cells{' (line of sight)' if c.line_of_sight else ''}, {c.mode} exploration; "
        f"a sync every {c.sync_every} steps ({len(c.sync_steps):,} rounds)"
        + (f"; a run ends once its team has observed {c.stop_coverage:.0%} of the cells it can reach "
           "(`stop_coverage`), and its final values are that step's" if c.stop_coverage is not None else "") + ".", "",
        f"Link (seed {c.link_seed}): uplink {budget(link.uplink_bytes)} and downlink {budget(link.downlink_bytes)} per "
        f"rover per round, loss {link.loss:g}, latency {link.latency} step(s), range "
        f"{'unlimited' if link.max_range is None else f'{link.max_range:g} cells'}"
        + (f", each link down for a round with probability {link.drop:g}" if link.drop else "")
        + (f", the lander's links down in steps {link.lander_cut[0]}-{link.lander_cut[1] - 1}" if link.lander_cut else "")
        + ".", "",
        *([f"Topology: **{link.topology}**: " + topology.describe(link) + ". The lander is "
           + ("an agent that never moves" if link.lander_agent else "not an agent: there is no base station")
           + ". *B/link/round*: mean bytes per message offered on a link that was up (in range, not down), each "
           "relay hop counted, as RAMEN reports per link per round.", ""]
          if not topology.has_base else []),
        *([f"Helicopters: {c.helicopters} (after the rovers), {c.helicopter.speed} cells per step over any terrain, "
           f"seeing {c.helicopter.resolution}x{c.helicopter.resolution}-cell blocks within "
           f"{c.helicopter.sensor_radius:g} cells (a block of one class is observed, a mixed block stays unknown), "
           f"{c.helicopter.flight_budget} steps per sortie and {c.helicopter.recharge} steps recharging, landing at "
           "the lander or on cells it observed free. Belief columns and *F1≥ at* cover the rovers and helicopters; "
           "*belief F1≥0.9 at* is the first rover's.", ""] if c.helicopters else []),
        *([f"Layers: classes and elevation. Rovers measure heights with noise of std {c.elevation_noise_m:g} m; "
           f"`raw` shares them with the classes, quantised to {c.elevation_q_m:g} m "
           "(0: exact float32), and `central` pools them; the other strategies share classes only. Each rover "
           "derives its own classes from every height it holds, with its own limits, and plans on them. "
           "*base height RMSE*: the heights the base holds against the true elevation, on the cells it holds.", ""]
          if "elevation" in c.layers else []),
        *([f"Rover profiles: {', '.join(f'rover {k} {p}' for k, p in enumerate(c.rover_profiles))}. The shared classes "
           "(what every strategy sends, the global map, coverage and accuracy) follow the mission's `[thresholds]` "
           "(`team`). Each rover classifies the cells it observes itself under its own limits too and plans on "
           "those; elsewhere it plans on the shared classes. Its belief F1 and false-free rate are scored against "
           "the truth under its own profile.", ""] if c.profiles else []),
        f"*global* columns score {global_meaning(result)}.", "",
        "Final values at the last step; *steps to* and *at* columns are the first step a level was reached "
        "(`-`: never); *steps to* a coverage and *reachable coverage* count the cells the team can reach "
        f"({_reach_text(result)}: the free cells a rover can drive to from its start, grown by its sensor radius), "
        "*coverage* the whole map's. "
        f"Path F1 is strict (A*, {c.eval_pairs} seeded start/goal pairs, UNKNOWN impassable), "
        "scored at step 0, at every sync and at the last step; belief columns average the rovers; *belief acc. at step 0* "
        "is before any message (a model strategy's starts from its initial model's rendering). "
        "*acc. observed* / *acc. unobserved*: belief accuracy on the cells some rover observed (knowing) and on "
        "those no rover observed (guessing: a strategy that shares only observations leaves them UNKNOWN and "
        "scores 0). *path success*: the share of the pairs "
        "the truth connects whose path, planned on a rover's belief and driven on the truth, reaches the goal "
        "without entering an impassable cell, mean over the rovers. *false-free*: the "
        "share of the cells a rover plans on as FREE (its belief, and the prior where it has no observation) that "
        "are impassable in the truth, mean over the rovers: hazards it would drive into. Bytes are the "
        "whole team's, summed over the rovers and the mission; *not delivered* counts messages by why.", "",
        *([f"Prior: orbital, the DEM {c.prior.factor}x coarser, held by every rover and the base before the mission "
           "and never sent (no bytes on the link); rovers plan paths on it where they have no observation.", ""]
          if c.prior.kind == "orbital" else []),
        *([f"**Repeats**: {what_varies(result.config, len(repeats))}. Each value is the mean over the repeats "
           "with its 95 % interval (Student's t); a step some repeats never reached gives the mean of those that "
           "did and how many. *team F1≥0.9 at*: first step the rovers' mean belief F1 reached 0.9; "
           + ("*guessed F1≥0.9 at*: the same, of their beliefs with the predictor's guesses filled in; "
              if c.predictor != "none" else "")
           + "*plannable at*: "
           f"first step it had and the coverage was {READY_COVERAGE:.0%}. Per-repeat values: `metrics.json` "
           "(`repeats`). The animations show the first repeat.", ""] if repeats is not None and len(repeats) > 1
          else []),
        *_prediction_lines(result, repeated=repeats is not None and len(repeats) > 1),
        *_frames_lines(result),
        *_wire_lines(result),
        side_by_side(result, repeats),
        verdict(result, repeats), "",
        _wall_time(result, repeats), "",
        "Plots: `coverage.png`, `f1.png`, `accuracy_bytes.png`, `knowing.png`; animations: "
        + (", ".join(f"`{name}`" for name in animations) if animations else "none (not asked for)") + ".", "",
    ]
    return "\n".join(lines)


def _wire_lines(result: MissionResult) -> list[str]:
    """What the transport carried (fedmap's frames, framing included) beside the ledger."""
    runs = [(n, r) for n, r in result.runs.items() if r.wire is not None]
    if not runs:
        return []
    parts = []
    for n, r in runs:
        w, counted = r.wire, sum(m.bytes for m in r.ledger)
        assert w is not None
        how = f" ({w['orders']:,} B of orders, {w['reports']:,} B of reports)" if "orders" in w else ""
        if "mail_bytes" in w:  # a peer mission on processes: the mail the agents posted, positions included
            how = f" (agents posted {w['mail_bytes']:,} B of mail in {w['mails']:,} posts, positions included)"
        parts.append(f"{n} {w['bytes']:,} B in {w['frames']:,} frames{how} for {counted:,} B of the strategy's own")
    deployed = any("orders" in (r.wire or {}) for _, r in runs)
    peers = any("mail_bytes" in (r.wire or {}) for _, r in runs)
    return [("**On processes**: every rover and the base ran as processes of their own, exchanging only fedmap's "
             "frames (the strategy's messages inside orders and reports); scores come from each node's own log, off "
             "the link (`fedmap score`). " if deployed else "")
            + ("**On processes, as peers**: every agent ran as a process of its own, with no base giving orders: "
               "each ran its side of every round, exchanging only fedmap's mail (positions, the strategy's messages "
               "and the receivers' answers); scores come from each agent's own log, off the link (`fedmap score`). "
               if peers else "")
            + "*Wire bytes*, every frame the transport carried with its framing (the table's bytes are the "
            "strategy's own, as the ledger counts them): " + "; ".join(parts) + ".", ""]


def _frames_lines(result: MissionResult) -> list[str]:
    """With ``[frames]``: what the rovers did not know, and how often the base placed their cells."""
    f = result.config.frames
    if not f.enabled:
        return []
    out = [f"**Unknown poses** (`[frames]`): each rover's start off by std {f.start_offset:g} cells and "
           f"{f.start_heading:g} degrees, its odometry's scale off by std {f.drift:.1%} and its heading drifting "
           f"by std {f.heading_drift:g} degrees per metre; "
           + (f"the lander imaged {f.lander_view:g} cells around itself. " if f.lander_view else "no lander image. ")
           + "Each rover maps in its own frame; the base merges its cells only through a transform it estimated "
           f"and checked (kappa gate {f.gate:g}); scores are taken through the team's estimates, never the true "
           "poses. Registrations, one per rover and sync: *placed* (first placement), *tracked* (its transform "
           "re-estimated), *carried* (too little overlap: the last transform kept), *waiting* / *refused* (not "
           "merged yet).", ""]
    rows = [(n, Counter(p["action"] for p in r.registrations)) for n, r in result.runs.items()
            if r.registrations is not None]
    if rows:
        acts = [a for a in ("anchor", "placed", "tracked", "carried", "waiting", "refused")
                if any(c[a] for _, c in rows)]
        out += ["| strategy | " + " | ".join(acts) + " |", "|---|" + "---|" * len(acts)]
        out += [f"| {n} | " + " | ".join(str(c[a]) for a in acts) + " |" for n, c in rows]
        out.append("")
    return out


def _prediction_lines(result: MissionResult, *, repeated: bool = False) -> list[str]:
    """With ``predictor = "learned"``: a table of the guesses on the cells nobody observed at the
    last step (when some were left), and one of the beliefs with the guesses filled in
    (``repeated``: both of the first repeat)."""
    rows = [(n, r.summary.final_prediction) for n, r in result.runs.items() if r.summary.final_prediction]
    filled = [(n, r.summary) for n, r in result.runs.items() if r.summary.predicted_belief]
    if not rows and not filled:
        return []
    out = [] if not repeated else ["The predictor's tables below are the first repeat's (the repeats table gives "
                                   "*guessed F1≥0.9 at* over every repeat).", ""]
    if rows:
        out += ["**The map predictor's guesses** at the last step, on the cells no rover had observed (every "
                "rover's guesses on the map it held, pooled; a guess is impassable above P = 1/2). They are used for "
                "planning only, never counted as observed or shared. *all free*: the accuracy of guessing FREE "
                "everywhere.", "", "| strategy | cells | accuracy | all free | impassable IoU | Brier | ECE |",
                "|---|---|---|---|---|---|---|"]
        out += [f"| {n} | {int(p['cells']):,} | {p['accuracy']:.3f} | {p['accuracy_all_free']:.3f} | "
                f"{p['iou_impassable']:.3f} | {p['brier']:.3f} | {p['ece']:.3f} |" for n, p in rows]
        out.append("")
    if filled:
        out += ["**The beliefs with the guesses filled in** (every unknown cell its likelier class: the map a "
                "rover plans paths on), scored as strictly as the beliefs (the guessed cells count as what they "
                "guess), mean over the rovers; *F1≥0.9 at*: the first evaluation step their mean reached it, "
                "against the observed beliefs' (*observed*). *false-free*: the share of the FREE cells, observed or "
                "guessed, that are impassable in the truth (the observed beliefs': the side-by-side table).", "",
                f"| strategy | F1≥{F1_GOAL} at | observed | path F1 | path success | false-free |",
                "|---|---|---|---|---|---|"]
        out += [f"| {n} | {_fmt(p['f1_step'], 0)} | {_fmt(s.team_f1_step, 0)} | {_fmt(p['final_f1'], 2)} | "
                f"{_fmt(p['final_success'], 2)} | {_fmt(p['final_false_free'], 3)} |"
                for n, s in filled if (p := s.predicted_belief) is not None]
        out.append("")
    return out


# --------------------------------------------------------------------------- plots


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    _pyplot().close(fig)
    return buf.getvalue()


def _line(ax, x, ys: Sequence[Sequence[float]], *, xs: Sequence[Sequence[int]] | None = None, **kw) -> None:
    """One strategy's curve: the value (one run), or the mean over the repeats with its 95 %
    interval shaded, step by step. Repeats the stop rule ended at different steps are drawn
    over the steps they all reached: those in every one of ``xs`` (each repeat's own steps)
    or, without ``xs``, the points they all have."""
    if xs is not None and any(list(steps) != list(x) for steps in xs):
        x = sorted(set(x).intersection(*map(set, xs)))
        ys = [[dict(zip(steps, y))[t] for t in x] for steps, y in zip(xs, ys)]
    n = min(len(x), *(len(y) for y in ys))
    x, ys = x[:n], [y[:n] for y in ys]
    if len(ys) == 1:
        ax.plot(x, ys[0], **kw)
        return
    ivs = [interval(col, bounds=(0.0, 1.0)) for col in zip(*ys)]  # every curve drawn so is a share
    ax.plot(x, [iv.mean for iv in ivs], **kw)  # type: ignore[union-attr]
    ax.fill_between(x, [iv.lo for iv in ivs], [iv.hi for iv in ivs], color=kw.get("color"),  # type: ignore[union-attr]
                    alpha=0.2, lw=0)


def _repeats_note(results: Sequence[MissionResult]) -> str:
    return f" (mean of {len(results)} repeats, 95 % interval shaded)" if len(results) > 1 else ""


def plot_coverage(results: Sequence[MissionResult]) -> bytes:
    fig, ax = _pyplot().subplots(figsize=(6, 3.6))
    walled = any(run.summary.reachable_share < WALLED_BELOW for run in results[0].runs.values())
    for i, name in enumerate(results[0].runs):
        steps = [r.runs[name].series.step for r in results]
        _line(ax, steps[0], [r.runs[name].series.coverage_reachable for r in results], xs=steps,
              label=name, color=f"C{i}")
        if walled:  # the whole map's, where part of it cannot be reached
            _line(ax, steps[0], [r.runs[name].series.coverage for r in results], xs=steps, ls=":", color=f"C{i}")
    syncs = results[0].config.sync_steps
    for t in (syncs if len(syncs) <= 200 else ()):  # (more would be a grey wash)
        ax.axvline(t, color="0.9", lw=0.6, zorder=0)
    ax.set(xlabel="step", ylabel="team coverage of the cells it can reach", ylim=(0, 1),
           title="Coverage (grey lines: syncs" + ("; dotted: of the whole map" if walled else "") + ")"
           + _repeats_note(results))
    ax.legend()
    return _png(fig)


def plot_f1(results: Sequence[MissionResult]) -> bytes:
    fig, axes = _pyplot().subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for i, name in enumerate(results[0].runs):
        steps = [r.runs[name].series.eval.step for r in results]
        step = steps[0]
        _line(axes[0], step, [r.runs[name].series.eval.f1 for r in results], xs=steps, marker=".", label=name,
              color=f"C{i}")
        _line(axes[1], step, [[max(f) for f in r.runs[name].series.eval.belief_f1] for r in results], xs=steps,
              marker=".", label=name, color=f"C{i}")
        if all(r.runs[name].series.eval.predicted_f1 is not None for r in results):  # with the guesses filled in
            _line(axes[1], step, [[max(f) for f in r.runs[name].series.eval.predicted_f1 or ()] for r in results],
                  xs=steps, marker=".", ls="--", label=f"{name}, with the guesses", color=f"C{i}")
    axes[0].set(xlabel="step", ylabel="strict path F1", ylim=(0, 1.02), title="Base's global map"
                + _repeats_note(results))
    axes[1].set(xlabel="step", title="Best rover belief")
    axes[1].axhline(F1_GOAL, color="0.6", ls="--", lw=0.8)
    axes[0].legend()
    if any(r.runs[name].series.eval.predicted_f1 is not None for r in results for name in r.runs):
        axes[1].legend(fontsize=7)
    return _png(fig)


def plot_accuracy_bytes(results: Sequence[MissionResult]) -> bytes:
    fig, ax = _pyplot().subplots(figsize=(6, 3.6))
    n = results[0].config.rovers
    for i, name in enumerate(results[0].runs):
        runs = [r.runs[name] for r in results]
        xs = [[(sum(u) + sum(d)) / n for u, d in zip(run.series.bytes_up, run.series.bytes_down)] for run in runs]
        x = [float(np.mean(col)) for col in zip(*xs)]  # the mean bytes per rover at each step
        ys = [[float(np.mean(a)) for a in run.series.accuracy] for run in runs]
        lost = undelivered(runs[0].summary, "up")
        label = name if lost == "-" else f"{name} (uplinks: {lost})"  # a silent strategy says why
        if max(x) > 0:
            _line(ax, x, ys, label=label, color=f"C{i}")
        else:  # no bytes: one point at the end (the bound it reaches for free or alone)
            ax.scatter([0.0], [float(np.mean([y[-1] for y in ys]))], label=f"{label} (0 B, final)", zorder=3,
                       color=f"C{i}")
        # its value at step 0, before any message (a model strategy's comes from its initial model)
        ax.scatter([0.0], [float(np.mean([y[0] for y in ys]))], marker="o", facecolors="none", edgecolors=f"C{i}",
                   zorder=3, label="step 0 (before any message)" if i == 0 else None)
    ax.set(xlabel="cumulative bytes per rover (up + down)", ylabel="mean belief accuracy", ylim=(0, 1),
           title="Map accuracy vs bytes" + _repeats_note(results))
    ax.set_xscale("symlog", linthresh=100)
    ax.set_xlim(left=0)
    ax.legend()
    return _png(fig)


def plot_knowing(results: Sequence[MissionResult]) -> bytes:
    """Knowing vs guessing, per strategy over the mission: belief accuracy on the cells some
    rover observed, on those nobody observed, the false-free rate, and executed path success."""
    fig, axes = _pyplot().subplots(1, 4, figsize=(16, 3.6))
    for i, name in enumerate(results[0].runs):
        runs = [r.runs[name] for r in results]
        s, ev = runs[0].series, runs[0].series.eval
        kw: dict[str, Any] = {"label": name, "color": f"C{i}", "xs": [run.series.step for run in runs]}
        _line(axes[0], s.step, [[float(np.mean(a)) for a in run.series.accuracy_observed] for run in runs], **kw)
        _line(axes[1], s.step, [[float(np.mean(a)) for a in run.series.accuracy_unobserved] for run in runs], **kw)
        _line(axes[2], s.step, [[float(np.mean(f)) for f in run.series.false_free] for run in runs], **kw)
        kw["xs"] = evs = [run.series.eval.step for run in runs]
        _line(axes[3], ev.step, [[float(np.mean(f)) for f in run.series.eval.belief_success] for run in runs],
              marker=".", **kw)
        if all(run.series.eval.predicted_success is not None for run in runs):  # with the guesses filled in
            dashed: dict[str, Any] = {"color": f"C{i}", "ls": "--", "label": f"{name}, with the guesses", "xs": evs}
            _line(axes[1], ev.step, [[float(np.mean(f)) for f in run.series.eval.predicted_accuracy_unobserved or ()]
                                     for run in runs], marker=".", **dashed)
            _line(axes[2], ev.step, [[float(np.mean(f)) for f in run.series.eval.predicted_false_free or ()]
                                     for run in runs], marker=".", **dashed)
            _line(axes[3], ev.step, [[float(np.mean(f)) for f in run.series.eval.predicted_success or ()]
                                     for run in runs], marker=".", **dashed)
    axes[0].set(xlabel="step", ylabel="mean over the rovers", ylim=(0, 1.02), title="Accuracy, observed cells")
    axes[1].set(xlabel="step", ylim=(0, 1.02), title="Accuracy, cells nobody observed")
    axes[2].set(xlabel="step", ylim=(0, None), title="False-free rate\n(hazards planned as FREE)")
    axes[3].set(xlabel="step", ylim=(0, 1.02), title="Executed path success" + _repeats_note(results))
    for ax in axes:
        ax.title.set_fontsize(10)
    fig.tight_layout()
    axes[0].legend()
    if any(r.runs[name].series.eval.predicted_success is not None for r in results for name in r.runs):
        axes[3].legend(fontsize=7)
    return _png(fig)


# --------------------------------------------------------------------------- animation

_COLOURS = np.array([[0.1, 0.4, 1.0], [1.0, 0.6, 0.0], [0.8, 0.0, 0.8], [0.0, 0.8, 0.8], [1.0, 1.0, 0.0],
                     [0.5, 0.25, 0.0]], dtype=np.float32)


def _panel(classes: np.ndarray) -> np.ndarray:
    return PALETTE[np.asarray(classes, dtype=np.intp)].copy()


def _mark(img: np.ndarray, cells, colour, alpha: float = 1.0) -> None:
    if len(cells) == 0:
        return
    cells = np.asarray(cells)
    r, c = cells[:, 0], cells[:, 1]
    img[r, c] = (1 - alpha) * img[r, c] + alpha * np.asarray(colour)


def frames_rgb(result: MissionResult, name: str, *, scale: int = 2) -> list[np.ndarray]:
    """The animation frames of one strategy: truth | each rover's belief | global map, under a
    band naming the panels and above one with the step, the team's bytes so far and the legend."""
    run = result.runs[name]
    h, w = result.truth.shape
    def rim(radius: float) -> np.ndarray:  # the footprint's outline
        ring = disk_offsets(radius)
        return ring[(ring ** 2).sum(axis=1) > (radius - 1) ** 2]

    c = result.config
    edges = [rim(c.sensor_radius if k < c.rovers else c.helicopter.sensor_radius)
             for k in range(c.rovers + c.helicopters)]
    out = []
    gap = np.ones((h, 2, 3), dtype=np.float32)
    for f in run.frames:
        panels = [_panel(result.truth.classes)]
        for k, (belief, pos, n) in enumerate(zip(f.beliefs, f.positions, f.trail_len)):
            img = _panel(belief)
            colour = _COLOURS[k % len(_COLOURS)]
            _mark(img, run.trails[k][:n], colour, 0.6)
            fp = edges[k] + np.asarray(pos)
            fp = fp[(fp[:, 0] >= 0) & (fp[:, 0] < h) & (fp[:, 1] >= 0) & (fp[:, 1] < w)]
            _mark(img, fp, (1.0, 1.0, 1.0), 0.8)
            _mark(img, [pos], (0.0, 0.0, 0.0))
            panels.append(img)
        g = _panel(f.global_map)
        where = {**dict(enumerate(f.positions)), BASE: result.base}
        for a, b in f.links:  # the links up at the last sync: white lines
            rr, cc = draw_line(*where[a], *where[b])
            _mark(g, np.stack([rr, cc], axis=1), (1.0, 1.0, 1.0), 0.7)
        for k, pos in enumerate(f.positions):
            _mark(g, [pos], _COLOURS[k % len(_COLOURS)])
        _mark(g, [result.base], (0.0, 0.0, 0.0))
        for a in f.leaders:  # who leads: a black ring
            ring8 = np.asarray(where[a]) + np.array([(-2, -2), (-2, 0), (-2, 2), (0, -2), (0, 2), (2, -2), (2, 0),
                                                     (2, 2)])
            ring8 = ring8[(ring8[:, 0] >= 0) & (ring8[:, 0] < h) & (ring8[:, 1] >= 0) & (ring8[:, 1] < w)]
            _mark(g, ring8, (0.0, 0.0, 0.0))
        panels.append(g)
        row = np.concatenate([x for p in panels for x in (p, gap)][:-1], axis=1)
        frame = (np.clip(row, 0, 1) * 255).astype(np.uint8)
        up, down = (sum(b[f.step]) for b in (run.series.bytes_up, run.series.bytes_down))
        out.append(_labelled(np.repeat(np.repeat(frame, scale, axis=0), scale, axis=1),
                             ["truth", *(f"{'rover' if k < result.config.rovers else 'helicopter'} {k}"
                                         for k in range(len(f.beliefs))),
                              "global map" + (", links, leaders" if f.leaders else ", links" if f.links else "")],
                             (w + 2) * scale,
                             f"{name}  step {f.step}/{result.config.steps}  team bytes so far: {up:,} up, {down:,} down"
                             "   green free, red impassable, grey unknown"))
    return out


#: Heights in pixels of a frame's title band (panel names) and footer (step, bytes, legend).
LABEL_BAND = 14


def _labelled(frame: np.ndarray, titles: list[str], stride: int, footer: str) -> np.ndarray:
    """``frame`` with a white band above it naming each panel (panels every ``stride``
    pixels) and one below it with ``footer``."""
    from PIL import ImageDraw

    h, w, _ = frame.shape
    canvas = Image.new("RGB", (w, h + 2 * LABEL_BAND), (255, 255, 255))
    canvas.paste(Image.fromarray(frame), (0, LABEL_BAND))
    draw = ImageDraw.Draw(canvas)
    for i, t in enumerate(titles):
        draw.text((i * stride + 2, 1), t, fill=(0, 0, 0))
    draw.text((2, h + LABEL_BAND + 1), footer, fill=(0, 0, 0))
    return np.asarray(canvas)


def gif_bytes(frames: list[np.ndarray], *, ms: int = 120) -> bytes:
    images = [Image.fromarray(f) for f in frames]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=ms, loop=0, optimize=False)
    return buf.getvalue()


def mp4_bytes(frames: list[np.ndarray], *, fps: int = 8) -> bytes | None:
    """H.264 MP4 through ``ffmpeg`` when it is on the PATH (None otherwise or on failure)."""
    exe = shutil.which("ffmpeg")
    if exe is None or not frames:
        return None
    h, w, _ = frames[0].shape
    h2, w2 = h - h % 2, w - w % 2  # yuv420p needs even sides
    raw = b"".join(np.ascontiguousarray(f[:h2, :w2]).tobytes() for f in frames)
    cmd = [exe, "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w2}x{h2}", "-r", str(fps),
           "-i", "-", "-pix_fmt", "yuv420p", "-vcodec", "libx264", "-f", "mp4", "-movflags", "frag_keyframe", "-"]
    try:
        done = subprocess.run(cmd, input=raw, capture_output=True, check=True, timeout=300)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout or None


def repeats_metrics(results: Sequence[MissionResult]) -> dict:
    """The ``repeats`` entry of ``metrics.json``: what varied, each value's interval per
    strategy, and every repeat's seeds, starts and summaries."""
    return {"n": len(results), "what_varies": what_varies(results[0].config, len(results)),
            "level": 0.95,
            "intervals": {n: {v: (None if iv is None else iv.to_dict()) for v, iv in ivs.items()}
                          for n, ivs in intervals(results).items()},
            "runs": [{"seed": r.config.seed, "link_seed": r.config.link_seed, "seconds": r.seconds,
                      "starts": [list(c) for c in r.starts],
                      "summaries": {n: run.summary.to_dict() for n, run in r.runs.items()}} for r in results]}


def write_mission(result: MissionResult, out_dir: str | Path, *, title: str, settings: dict | None = None,
                  animation: bool = True, extra: dict[str, str] | None = None,
                  repeats: Sequence[MissionResult] | None = None, beliefs: bool = False) -> Path:
    """Write a mission's outputs as one atomic folder (see the module docstring). With
    ``repeats`` (more than one run of the mission, ``result`` the first), ``metrics.json``
    adds ``repeats`` (:func:`repeats_metrics`), and the report and plots give means with
    95 % intervals. ``maps/`` holds each strategy's final global map (and with ``beliefs``
    every rover's final belief) as PNG, GeoTIFF in the truth's CRS and ROS map_server YAML + PGM
    (:func:`~fedmap.mission.outputs.maps_out.write_mission_maps`)."""
    out_dir = Path(out_dir)
    results = list(repeats) if repeats is not None and len(repeats) > 1 else [result]
    with AtomicDir(out_dir) as tmp:
        data = metrics(result, settings=settings)
        if len(results) > 1:
            data["repeats"] = repeats_metrics(results)
        write_metrics(tmp, data)
        write_mission_maps(result, tmp, beliefs=beliefs)
        atomic_write_bytes(tmp / "coverage.png", plot_coverage(results))
        atomic_write_bytes(tmp / "f1.png", plot_f1(results))
        atomic_write_bytes(tmp / "accuracy_bytes.png", plot_accuracy_bytes(results))
        atomic_write_bytes(tmp / "knowing.png", plot_knowing(results))
        for name, text in (extra or {}).items():
            atomic_write_bytes(tmp / name, text.encode())
        if animation:
            for name in result.runs:
                frames = frames_rgb(result, name)
                atomic_write_bytes(tmp / f"mission_{name}.gif", gif_bytes(frames))
                mp4 = mp4_bytes(frames)
                if mp4 is not None:
                    atomic_write_bytes(tmp / f"mission_{name}.mp4", mp4)
        written = [f"mission_{n}.{ext}" for n in result.runs for ext in ("gif", "mp4")
                   if (tmp / f"mission_{n}.{ext}").is_file()]
        atomic_write_bytes(tmp / "report.md", report_md(result, title=title, animations=written,
                                                        repeats=results).encode())
    return out_dir
