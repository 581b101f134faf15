"""A mission's outputs, in one atomic folder.

* ``metrics.json``: the mission and link settings, and per strategy its summary, its
  time series and its ledger (one row per message);
* ``report.md``: the strategies side by side (:func:`side_by_side`);
* ``coverage.png`` (coverage vs step), ``f1.png`` (the base's global map and the best
  rover belief, strict path F1 vs step), ``accuracy_bytes.png`` (mean belief accuracy
  vs cumulative bytes per rover, both directions), ``knowing.png`` (accuracy on observed
  and on unobserved cells, false-free rate, executed path success, vs step);
* ``mission_<strategy>.gif`` (and ``.mp4`` when ``ffmpeg`` is on the PATH): the truth,
  every rover's belief with its path, position and sensor footprint, and the global map.
"""

from __future__ import annotations

import io
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from skimage.draw import line as draw_line

from fedmap._util import AtomicDir, atomic_write_bytes
from fedmap.maps.grid import PALETTE
from fedmap.mission.link import BASE
from fedmap.mission.sensing import disk_offsets
from fedmap.mission.sim import COVERAGE_LEVELS, F1_GOAL, MissionResult, MissionSummary
from fedmap.mission.topology import TOPOLOGIES
from fedmap.outputs import write_metrics


def _pyplot():
    """matplotlib's pyplot on the file-only Agg backend, imported when a plot is drawn
    (as in fedmap.outputs): not at ``fedmap`` start-up, and no backend switch on import."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


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
    }


def _fmt(v, nd: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "inf" if v == float("inf") else f"{v:.{nd}f}"
    return f"{v:,}" if isinstance(v, int) else str(v)


def _steps_to(level: float) -> Callable[[MissionSummary], int | None]:
    return lambda s: s.coverage_steps[level]


#: The side-by-side columns: header -> (how to read it from a summary, decimals).
COLUMNS: dict[str, tuple[Callable[[MissionSummary], Any], int]] = {
    **{f"steps to {int(lv * 100)} %": (_steps_to(lv), 0) for lv in COVERAGE_LEVELS},
    f"belief F1≥{F1_GOAL} at": (lambda s: s.first_belief_f1_step, 0),
    "coverage": (lambda s: s.final_coverage, 3),
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

#: Ledger statuses of a message that did not arrive, in the order the report names them.
UNDELIVERED = ("over budget", "lost", "stale", "out of range", "link down", "rejected")


def undelivered(summary: MissionSummary, direction: str) -> str:
    """``"30 over budget, 2 lost"``: the messages of one direction (``up``, ``down``, ``peer``) that
    did not arrive, by why (``-``: none)."""
    parts = [f"{summary.messages[f'{direction}_{st}']} {st}" for st in UNDELIVERED
             if summary.messages.get(f"{direction}_{st}")]
    return ", ".join(parts) or "-"


def verdict(result: MissionResult) -> str:
    """One computed line: which strategy left the rovers the best map, and which gained the
    most map per byte on the link (``central``, the free oracle, is left out of both)."""
    others = {n: r for n, r in result.runs.items() if n != "central"}
    # a strategy that got nothing through the link holds its own observations over its
    # initial model's rendering: a score from the latter is a guess, so it is no candidate
    silent = [n for n, r in others.items() if n != "none" and r.summary.bytes_up + r.summary.bytes_down == 0]
    runs = {n: r for n, r in others.items() if n not in silent}
    notes = "".join(f" {n} got nothing through the link (uplinks: {undelivered(others[n].summary, 'up')}): its "
                    f"{others[n].summary.final_belief_accuracy_mean:.3f} is its own observations over its initial "
                    f"model ({float(np.mean(others[n].series.accuracy[0])):.3f} at step 0), not shared knowledge."
                    for n in silent)
    if not runs:
        return ("Only the central oracle ran: nothing to compare." if not others else
                "No strategy got anything through the link." + notes)
    acc = {n: r.summary.final_belief_accuracy_mean for n, r in runs.items()}
    best = max(acc, key=lambda n: (acc[n], -(runs[n].summary.bytes_up + runs[n].summary.bytes_down)))
    line = f"Best map: **{best}** (belief accuracy {acc[best]:.3f}"
    if "none" in runs and best != "none":
        line += f", against {acc['none']:.3f} sharing nothing"
    line += ")."
    # what the bytes bought: the accuracy above sharing nothing (or, without `none`, above step 0)
    spent = {n: r.summary.bytes_up + r.summary.bytes_down for n, r in runs.items()}
    base = {n: acc["none"] if "none" in runs else float(np.mean(r.series.accuracy[0])) for n, r in runs.items()}
    gain = {n: (acc[n] - base[n]) / spent[n] for n in runs if spent[n] > 0 and acc[n] > base[n]}
    than = "sharing nothing" if "none" in runs else "step 0"
    if gain:
        top = max(gain, key=lambda n: gain[n])
        line += (f" Best map per byte: **{top}** (+{(acc[top] - base[top]) * 100:.2f} accuracy points over {than} "
                 f"for {spent[top]:,} B of the team's traffic).")
    elif any(spent.values()):
        line += f" No strategy that used the link gave a better map than {than}."
    return line + notes


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


def side_by_side(result: MissionResult) -> str:
    """The strategies side by side, as a Markdown table."""
    header, rows = table_rows(result)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def report_md(result: MissionResult, *, title: str, animations: list[str] | None = None) -> str:
    """The mission's ``report.md``; ``animations`` are the animation files written beside it
    (None: one GIF per strategy), so the report links only files that exist."""
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
        f"a sync every {c.sync_every} steps ({len(c.sync_steps)} rounds).", "",
        f"Link (seed {link.seed}): uplink {budget(link.uplink_bytes)} and downlink {budget(link.downlink_bytes)} per "
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
        f"(`-`: never). Path F1 is strict (A*, {c.eval_pairs} seeded start/goal pairs, UNKNOWN impassable), "
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
        side_by_side(result),
        verdict(result), "",
        f"Wall time: {result.seconds:.1f} s ("
        + ", ".join(f"{n} {r.seconds:.1f} s" for n, r in result.runs.items()) + ").", "",
        "Plots: `coverage.png`, `f1.png`, `accuracy_bytes.png`, `knowing.png`; animations: "
        + (", ".join(f"`{name}`" for name in animations) if animations else "none (not asked for)") + ".", "",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- plots


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    _pyplot().close(fig)
    return buf.getvalue()


def plot_coverage(result: MissionResult) -> bytes:
    fig, ax = _pyplot().subplots(figsize=(6, 3.6))
    for i, (name, run) in enumerate(result.runs.items()):
        ax.plot(run.series.step, run.series.coverage, label=name, color=f"C{i}")
    for t in result.config.sync_steps:
        ax.axvline(t, color="0.9", lw=0.6, zorder=0)
    ax.set(xlabel="step", ylabel="team coverage", ylim=(0, 1), title="Coverage (grey lines: syncs)")
    ax.legend()
    return _png(fig)


def plot_f1(result: MissionResult) -> bytes:
    fig, axes = _pyplot().subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for i, (name, run) in enumerate(result.runs.items()):
        ev = run.series.eval
        axes[0].plot(ev.step, ev.f1, marker=".", label=name, color=f"C{i}")
        axes[1].plot(ev.step, [max(f) for f in ev.belief_f1], marker=".", label=name, color=f"C{i}")
    axes[0].set(xlabel="step", ylabel="strict path F1", ylim=(0, 1.02), title="Base's global map")
    axes[1].set(xlabel="step", title="Best rover belief")
    axes[1].axhline(F1_GOAL, color="0.6", ls="--", lw=0.8)
    axes[0].legend()
    return _png(fig)


def plot_accuracy_bytes(result: MissionResult) -> bytes:
    fig, ax = _pyplot().subplots(figsize=(6, 3.6))
    for i, (name, run) in enumerate(result.runs.items()):
        s = run.series
        n = result.config.rovers
        x = [(sum(u) + sum(d)) / n for u, d in zip(s.bytes_up, s.bytes_down)]
        y = [float(np.mean(a)) for a in s.accuracy]
        lost = undelivered(run.summary, "up")
        label = name if lost == "-" else f"{name} (uplinks: {lost})"  # a silent strategy says why
        if max(x) > 0:
            ax.plot(x, y, label=label, color=f"C{i}")
        else:  # no bytes: one point at the end (the bound it reaches for free or alone)
            ax.scatter([0.0], [y[-1]], label=f"{label} (0 B, final)", zorder=3, color=f"C{i}")
        # its value at step 0, before any message (a model strategy's comes from its initial model)
        ax.scatter([0.0], [y[0]], marker="o", facecolors="none", edgecolors=f"C{i}", zorder=3,
                   label="step 0 (before any message)" if i == 0 else None)
    ax.set(xlabel="cumulative bytes per rover (up + down)", ylabel="mean belief accuracy", ylim=(0, 1),
           title="Map accuracy vs bytes")
    ax.set_xscale("symlog", linthresh=100)
    ax.set_xlim(left=0)
    ax.legend()
    return _png(fig)


def plot_knowing(result: MissionResult) -> bytes:
    """Knowing vs guessing, per strategy over the mission: belief accuracy on the cells some
    rover observed, on those nobody observed, the false-free rate, and executed path success."""
    fig, axes = _pyplot().subplots(1, 4, figsize=(16, 3.6))
    for i, (name, run) in enumerate(result.runs.items()):
        s, ev = run.series, run.series.eval
        axes[0].plot(s.step, [float(np.mean(a)) for a in s.accuracy_observed], label=name, color=f"C{i}")
        axes[1].plot(s.step, [float(np.mean(a)) for a in s.accuracy_unobserved], label=name, color=f"C{i}")
        axes[2].plot(s.step, [float(np.mean(f)) for f in s.false_free], label=name, color=f"C{i}")
        axes[3].plot(ev.step, [float(np.mean(f)) for f in ev.belief_success], marker=".", label=name, color=f"C{i}")
    axes[0].set(xlabel="step", ylabel="mean over the rovers", ylim=(0, 1.02), title="Accuracy on observed cells")
    axes[1].set(xlabel="step", ylim=(0, 1.02), title="Accuracy on cells nobody observed")
    axes[2].set(xlabel="step", ylim=(0, None), title="False-free rate (hazards planned as FREE)")
    axes[3].set(xlabel="step", ylim=(0, 1.02), title="Executed path success")
    axes[0].legend()
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


def write_mission(result: MissionResult, out_dir: str | Path, *, title: str, settings: dict | None = None,
                  animation: bool = True, extra: dict[str, str] | None = None) -> Path:
    """Write a mission's outputs as one atomic folder (see the module docstring)."""
    out_dir = Path(out_dir)
    with AtomicDir(out_dir) as tmp:
        write_metrics(tmp, metrics(result, settings=settings))
        atomic_write_bytes(tmp / "coverage.png", plot_coverage(result))
        atomic_write_bytes(tmp / "f1.png", plot_f1(result))
        atomic_write_bytes(tmp / "accuracy_bytes.png", plot_accuracy_bytes(result))
        atomic_write_bytes(tmp / "knowing.png", plot_knowing(result))
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
        atomic_write_bytes(tmp / "report.md", report_md(result, title=title, animations=written).encode())
    return out_dir
