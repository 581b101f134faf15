"""What the commands show people: the console, progress (bars or log lines), score tables.

In a terminal, progress is a transient rich bar per stage. Without one (stdout piped to a
file, CI, ``nohup``) a :class:`LogProgress` prints plain lines instead: one when a stage
starts and ends, and one at least every 10 s in between (stage, done/total, elapsed, ETA).
``fedmap --quiet ...`` prints no progress; ``fedmap --log-json ...`` prints each progress
event as one JSON object per line (see :func:`set_output`).

Without a terminal the console is also :data:`LOG_WIDTH` columns wide, so that a table in a
log file is whole (not cut to 80 columns with ``…``) and a line of text is one line.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

from rich.console import Console, ConsoleDimensions
from rich.measure import Measurement
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from fedmap.evaluation.scores import MapScores
from fedmap.maps.grid import GridMap
from fedmap.maps.traversability import TraversabilityThresholds
from fedmap.pipeline import PipelineResult

#: Columns of the console when its output is not a terminal (a file, a pipe, CI): wide
#: enough that no table is cut, since nobody's window is there to fit.
LOG_WIDTH = 10_000


class _Console(Console):
    """A rich console whose width is the terminal's, or :data:`LOG_WIDTH` without one (rich
    would take 80 columns, or ``$COLUMNS``, and cut a wider table's cells to ``…``).
    ``$COLUMNS`` and ``$LINES`` are read when the size is asked for, not once at import (rich
    would fix them at construction: under pytest-xdist a worker's ``COLUMNS=80`` stuck)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._width = self._height = None  # no fixed size: Console.size reads the terminal and $COLUMNS each time

    @property
    def size(self) -> ConsoleDimensions:
        size = super().size
        return size if self.is_terminal else ConsoleDimensions(LOG_WIDTH, size.height)

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        self._width, self._height = new_size


console: Console = _Console()


def terrain_line(label: str, truth: GridMap, thresholds: TraversabilityThresholds) -> str:
    """One line on the ground truth: size, cell size, class shares, and the slope limit used
    (a percentile's resolved to degrees, so ``--max-slope p75`` says what it meant)."""
    f = truth.fractions()
    line = (f"terrain: {label}, {truth.shape[0]}x{truth.shape[1]} cells of {truth.pixel_size:.3g} m; "
            f"{f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown")
    limit = truth.meta.get("slope_limit_deg")
    if limit is not None and thresholds.max_slope_percentile is not None:
        line += f"; slope limit {limit:.3g} deg (p{thresholds.max_slope_percentile:g} of the map's slopes)"
    elif limit is not None:
        line += f"; slope limit {limit:.3g} deg"
    return line

#: How progress is shown, set once per command by the ``fedmap`` callback (:func:`set_output`).
_OUTPUT: dict[str, bool] = {"quiet": False, "json": False}

#: Seconds between two plain progress lines within a stage.
LOG_INTERVAL = 10.0


def set_output(*, quiet: bool = False, log_json: bool = False) -> None:
    """``quiet``: no progress output at all; ``log_json``: progress events as JSON lines on
    stdout, even in a terminal, and everything else a command prints on stderr (so stdout
    is pure JSON lines)."""
    _OUTPUT["quiet"], _OUTPUT["json"] = quiet, log_json
    console.file = sys.stderr if log_json else None  # type: ignore[assignment]  # None: follow sys.stdout


class LogProgress:
    """Progress as log lines, for runs without a terminal. It has the part of rich's
    :class:`~rich.progress.Progress` interface the commands use (``add_task``, ``update``,
    a context manager), so :func:`stage_callbacks` and the commands drive either.

    A line is written when a stage starts, when it ends (its task completes, a new task is
    added, its description changes, or the display closes), and during a stage whenever
    ``interval`` seconds have passed since the last line: on a step, or from a heartbeat
    thread so that a long step still logs. ``clock`` and ``heartbeat=False`` let tests
    drive time by hand (:meth:`tick`).
    """

    def __init__(self, *, json_lines: bool = False, quiet: bool = False, interval: float = LOG_INTERVAL,
                 clock: Callable[[], float] = time.monotonic, stream: TextIO | None = None,
                 heartbeat: bool = True) -> None:
        self.json_lines, self.quiet, self.interval, self.clock = json_lines, quiet, interval, clock
        self.stream = stream
        self.heartbeat = heartbeat and not quiet
        self._tasks: dict[int, dict[str, Any]] = {}
        self._current: int | None = None
        self._alongside: list[int] = []  # tasks running side by side with the current one (not ended by it)
        self._last = clock()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> LogProgress:
        if self.heartbeat:
            self._thread = threading.Thread(target=self._beat, name="fedmap-progress", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if exc_type is None:
            for task_id in self._running():
                self._end(task_id)

    def _beat(self) -> None:
        while not self._stop.wait(min(1.0, self.interval)):
            self.tick()

    def _running(self) -> list[int]:
        """Every stage still open: those side by side, then the current one."""
        return [*self._alongside, *([] if self._current is None else [self._current])]

    def add_task(self, description: str, start: bool = True, total: float | None = 100.0, completed: int = 0,
                 visible: bool = True, alongside: bool = False, **fields: Any) -> TaskID:
        """A new stage. It ends the running one, unless both are ``alongside``: stages that run
        side by side (a mission's strategies on several cores) each end when their own count is done."""
        with self._lock:
            if alongside and self._current is not None and self._tasks[self._current]["alongside"]:
                self._alongside.append(self._current)
            else:
                for running in self._running():
                    self._end(running)
                self._alongside = []
            task_id = len(self._tasks)
            self._tasks[task_id] = {"stage": description, "total": total, "done": completed, "counted": bool(total),
                                    "start": self.clock(), "fields": fields, "ended": False, "alongside": alongside}
            self._current = task_id
            self._emit(self._tasks[task_id], "start")
            return TaskID(task_id)

    def update(self, task_id: TaskID, *, total: float | None = None, completed: float | None = None,
               advance: float | None = None, description: str | None = None, visible: bool | None = None,
               refresh: bool = False, **fields: Any) -> None:
        with self._lock:
            t = self._tasks[task_id]
            renamed = description is not None and description != t["stage"]
            if renamed:  # a new stage in the same task: the old one ends here
                if self._current is not None:
                    self._end(self._current)
            if total is not None:
                t["total"] = total
                t["counted"] = t["counted"] or bool(total) and (completed is None or completed < total)
            if completed is not None:
                t["done"] = completed
            if advance is not None:
                t["done"] += advance
            t["fields"].update(fields)
            if renamed:
                t.update(stage=description, start=self.clock(), ended=False)
                self._current = task_id
                self._emit(t, "start")
            if t["ended"]:
                return
            if t["total"] and t["done"] >= t["total"]:
                self._end(task_id)
            elif self.clock() - self._last >= self.interval:
                self._emit(t, "step")

    def tick(self) -> None:
        """Write a line for the running stage if none was written for ``interval`` seconds."""
        with self._lock:
            if self._current is not None and self.clock() - self._last >= self.interval:
                self._emit(self._tasks[self._current], "step")

    def _end(self, task_id: int) -> None:
        t = self._tasks[task_id]
        if not t["ended"]:
            t["ended"] = True
            self._emit(t, "end")
        if self._current == task_id:
            self._current = self._alongside.pop() if self._alongside else None
        elif task_id in self._alongside:
            self._alongside.remove(task_id)

    def event(self, t: dict[str, Any], phase: str) -> dict[str, Any]:
        """The progress event of a stage: what a JSON line holds."""
        now = self.clock()
        elapsed = now - t["start"]
        done, total = (t["done"], t["total"] or None) if t["counted"] else (None, None)
        eta = 0.0 if phase == "end" else (elapsed / done * (total - done) if total and done else None)
        info = " ".join(str(v) for v in t["fields"].values() if v not in ("", None))
        return {"event": "progress", "phase": phase, "stage": t["stage"], "done": done, "total": total,
                "elapsed_s": round(elapsed, 1), "eta_s": None if eta is None else round(eta, 1),
                "info": info or None, "time": time.strftime("%H:%M:%S")}

    def line(self, ev: dict[str, Any]) -> str:
        """The plain line of an event, e.g. ``[12:00:10] stage 'federated training' 120/400 (30%)
        elapsed 12.3 s eta 28.7 s``."""
        done, total, phase = ev["done"], ev["total"], ev["phase"]
        count = f" {done:g}/{total:g} ({done / total:.0%})" if total else ""
        info = f", {ev['info']}" if ev["info"] else ""
        head = f"[{ev['time']}] stage {ev['stage']!r}"
        if phase == "start":
            return f"{head} started{count}"
        if phase == "end":
            return f"{head} done{count} in {ev['elapsed_s']:.1f} s{info}"
        eta = "" if ev["eta_s"] is None else f" eta {ev['eta_s']:.1f} s"
        return f"{head}{count} elapsed {ev['elapsed_s']:.1f} s{eta}{info}"

    def _emit(self, t: dict[str, Any], phase: str) -> None:
        self._last = self.clock()
        if self.quiet:
            return
        ev = self.event(t, phase)
        stream = self.stream or sys.stdout
        stream.write((json.dumps(ev) if self.json_lines else self.line(ev)) + "\n")
        stream.flush()


def progress_bar() -> Progress | LogProgress:
    """The progress display of a command: a transient rich bar per stage, with the last loss,
    in a terminal; :class:`LogProgress` lines otherwise, or with ``--log-json`` / ``--quiet``."""
    if _OUTPUT["quiet"] or _OUTPUT["json"] or not console.is_terminal:
        return LogProgress(json_lines=_OUTPUT["json"], quiet=_OUTPUT["quiet"])
    return Progress(
        TextColumn("{task.description:<26}"), BarColumn(bar_width=24), MofNCompleteColumn(),
        TextColumn("{task.fields[loss]}"), TimeElapsedColumn(), TimeRemainingColumn(), console=console,
        transient=True,
    )


def stage_callbacks(progress: Progress | LogProgress) -> tuple[Callable[[str | None, int], None],
                                                                Callable[[int, float], None]]:
    """``on_stage(name, total)`` closes the running bar and opens the next (``name=None``
    only closes); ``on_step(step, loss)`` advances the current bar."""
    current: dict[str, Any] = {"task": None, "total": 0}

    def on_stage(name: str | None, total: int) -> None:
        if current["task"] is not None:
            progress.update(current["task"], total=current["total"] or 1, completed=current["total"] or 1)
        current["task"] = progress.add_task(name, total=total or None, loss="") if name is not None else None
        current["total"] = total

    def on_step(step: int, loss: float) -> None:
        progress.update(current["task"], advance=1, loss=f"loss {loss:.4f}")

    return on_stage, on_step


def fmt(x: float | None, nd: int = 2) -> str:
    """A number for tables: ``-`` for none, ``inf`` for an exact map's PSNR."""
    if x is None:
        return "-"
    if isinstance(x, float) and x == float("inf"):
        return "inf"
    return f"{x:.{nd}f}"


def scores_table(result: PipelineResult) -> Table:
    """Every map of a run against the ground truth (:data:`F1_CAPTION` says what each F1 is)."""
    t = Table(title="maps vs ground truth", header_style="bold")
    for col in ("map", "PSNR", "SSIM", "acc.", "P", "R", "F1", "tol.F1", "paperF1", "paperF1\nu.p."):
        t.add_column(col, justify="right" if col != "map" else "left", no_wrap=True)
    rows: list[tuple[str, MapScores]] = [("federated", result.global_scores), ("fed.+refined", result.refined_scores)]
    if result.central_scores is not None:
        rows.append(("central (bound)", result.central_scores))
    rows += [(f"rover {k} alone", s) for k, s in enumerate(result.agent_scores)]
    for name, m in rows:
        p, imp, pas = m.path, m.paper_unknown_impassable, m.paper_unknown_passable
        t.add_row(name, fmt(m.psnr), fmt(m.ssim, 3), fmt(m.accuracy, 3), fmt(p.precision), fmt(p.recall), fmt(p.f1),
                  fmt(p.tolerant.f1), fmt(None if imp is None else imp.f1), fmt(None if pas is None else pas.f1))
    return fit(t)


def comparison_table(rows: list[dict]) -> Table:
    """Methods side by side (:func:`fedmap.outputs.comparison_rows`): map quality and bytes."""
    t = Table(title="methods side by side, same rovers", header_style="bold")
    for col in ("method", "PSNR", "SSIM", "acc.", "F1", "refined\nPSNR", "refined\nF1", "central\nPSNR",
                "B/rover", "seconds"):
        t.add_column(col, justify="right" if col != "method" else "left", no_wrap=True)
    for r in rows:
        t.add_row(r["method"], fmt(r["psnr"]), fmt(r["ssim"], 3), fmt(r["accuracy"], 3), fmt(r["f1"]),
                  fmt(r["refined_psnr"]), fmt(r["refined_f1"]), fmt(r["central_psnr"]),
                  f"{r['uplink_bytes_per_rover_round']:,.0f}", f"{r['seconds']:.1f}")
    return fit(t)


def fit(table: Table) -> Table:
    """Drop the cell padding of a table wider than the console, so that a narrow terminal
    shows every number whole rather than cut (without a terminal the console is
    :data:`LOG_WIDTH` wide and the table is printed as it is)."""
    if Measurement.get(console, console.options.update_width(10_000), table).maximum > console.width:
        table.padding = (0, 0)
    return table


#: What the F1 columns of :func:`scores_table` mean, for the line printed under it.
F1_CAPTION = ("F1: strict, an identical path is a TP and a different path both an FP and an FN; tol.F1: a "
              "collision-free path within 5% of the true length is a TP; paperF1: the paper's text read literally "
              "(TP identical path, FP a path where the truth has none, FN no path where the truth has one; a "
              "different path is not counted), UNKNOWN cells impassable; paperF1 u.p.: the same with UNKNOWN "
              "cells passable")
