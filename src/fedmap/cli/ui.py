"""What the commands show people: the console, progress bars, score tables."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rich.console import Console
from rich.measure import Measurement
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from fedmap.evaluation.scores import MapScores
from fedmap.pipeline import PipelineResult

console = Console()


def progress_bar() -> Progress:
    """A transient progress display: one bar per stage, with the last loss."""
    return Progress(
        TextColumn("{task.description:<26}"), BarColumn(bar_width=24), MofNCompleteColumn(),
        TextColumn("{task.fields[loss]}"), TimeElapsedColumn(), TimeRemainingColumn(), console=console,
        transient=True,
    )


def stage_callbacks(progress: Progress) -> tuple[Callable[[str | None, int], None], Callable[[int, float], None]]:
    """``on_stage(name, total)`` closes the running bar and opens the next (``name=None``
    only closes); ``on_step(step, loss)`` advances the current bar."""
    current: dict[str, Any] = {"task": None}

    def on_stage(name: str | None, total: int) -> None:
        if current["task"] is not None:
            progress.update(current["task"], total=1, completed=1)
        current["task"] = progress.add_task(name, total=total or None, loss="") if name is not None else None

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
    rows += [(f"rover {k + 1} alone", s) for k, s in enumerate(result.agent_scores)]
    for name, m in rows:
        p, imp, pas = m.path, m.paper_unknown_impassable, m.paper_unknown_passable
        t.add_row(name, fmt(m.psnr), fmt(m.ssim, 3), fmt(m.accuracy, 3), fmt(p.precision), fmt(p.recall), fmt(p.f1),
                  fmt(p.tolerant.f1), fmt(None if imp is None else imp.f1), fmt(None if pas is None else pas.f1))
    return fit(t)


def fit(table: Table) -> Table:
    """Drop the cell padding of a table wider than the console (80 columns when piped), so
    that narrow consoles show every number whole rather than cut."""
    if Measurement.get(console, console.options.update_width(10_000), table).maximum > console.width:
        table.padding = (0, 0)
    return table


#: What the F1 columns of :func:`scores_table` mean, for the line printed under it.
F1_CAPTION = ("F1: strict, an identical path is a TP and a different path both an FP and an FN; tol.F1: a "
              "collision-free path within 5% of the true length is a TP; paperF1: the paper's text read literally "
              "(TP identical path, FP a path where the truth has none, FN no path where the truth has one; a "
              "different path is not counted), UNKNOWN cells impassable; paperF1 u.p.: the same with UNKNOWN "
              "cells passable")
