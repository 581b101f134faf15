"""``fedmap mission``: rovers explore over time and share maps over a constrained link; the
ways of sharing side by side (:mod:`fedmap.mission`). This module only wires options."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from fedmap._util import to_json
from fedmap.cli.ui import console, fit, progress_bar
from fedmap.config import dumps_toml, terrain_table
from fedmap.maps.sources import load_source_dem, load_truth
from fedmap.mission import load_mission, run_mission
from fedmap.mission.report import table_rows, write_mission


def mission(
    config: Optional[Path] = typer.Argument(None, help="Mission TOML ([terrain], [thresholds], [mission], [link], [strategies.*]); default: built-in mars 128²."),
    preset: Optional[str] = typer.Option(None, help="A shipped mission preset laid under the file, e.g. cadre."),
    strategies: Optional[str] = typer.Option(None, help="Comma-separated: none, raw, paper, fedmap, central [none,raw,fedmap,central]."),
    steps: Optional[int] = typer.Option(None, help="Mission steps [150]."),
    sync_every: Optional[int] = typer.Option(None, "--sync-every", help="Steps between sync rounds [10]."),
    rovers: Optional[int] = typer.Option(None, help="Number of rovers [4]."),
    speed: Optional[int] = typer.Option(None, help="Cells driven per step [2]."),
    sensor_radius: Optional[float] = typer.Option(None, "--sensor-radius", help="Sensor range in cells [8]."),
    line_of_sight: Optional[bool] = typer.Option(None, "--line-of-sight/--no-line-of-sight", help="Observe only cells in line of sight over the DEM [off]."),
    mode: Optional[str] = typer.Option(None, help="frontier (coordinated frontier exploration) or waypoints (a fixed traverse)."),
    stay_in_range: Optional[bool] = typer.Option(None, "--stay-in-range/--roam", help="Pick only targets within the link's range of the base."),
    uplink_bytes: Optional[int] = typer.Option(None, "--uplink-bytes", help="Uplink budget per rover per round, bytes [unlimited]."),
    downlink_bytes: Optional[int] = typer.Option(None, "--downlink-bytes", help="Downlink budget per rover per round, bytes [unlimited]."),
    loss: Optional[float] = typer.Option(None, help="Probability that a message is lost [0.1]."),
    latency: Optional[int] = typer.Option(None, help="Steps a message takes, each way [0]."),
    max_range: Optional[float] = typer.Option(None, "--max-range", help="Link range from the base, cells [unlimited]."),
    seed: Optional[int] = typer.Option(None, help="Seed of the terrain, the waypoints and the scoring [0]."),
    terrain: Optional[str] = typer.Option(None, help="Built-in terrain (mars, moon, ice) instead of the file's."),
    dem: Optional[Path] = typer.Option(None, help="A DEM file instead of the file's terrain."),
    map_path: Optional[Path] = typer.Option(None, "--map", help="A class map (PNG/NPY) instead of the file's terrain."),
    size: Optional[int] = typer.Option(None, help="Resample the terrain to size x size cells."),
    animation: bool = typer.Option(True, "--animation/--no-animation", help="Write the GIF (and MP4 with ffmpeg) of each strategy."),
    out: Path = typer.Option(Path("fedmap-out/mission"), "--out", "-o", help="Output folder (replaced atomically)."),
) -> None:
    """Run one mission with every sharing strategy; write metrics.json, report.md, plots and animations."""
    t0 = time.perf_counter()
    table = terrain_table(dem=dem, map_path=map_path, builtin=terrain)
    m = {"strategies": strategies, "steps": steps, "sync_every": sync_every, "rovers": rovers, "speed": speed,
         "sensor_radius": sensor_radius, "line_of_sight": line_of_sight, "mode": mode, "stay_in_range": stay_in_range}
    link = {"uplink_bytes": uplink_bytes, "downlink_bytes": downlink_bytes, "loss": loss, "latency": latency,
            "max_range": max_range}
    cfg, source, resolved = load_mission(config, preset=preset, mission=m, link=link, terrain=table, size=size,
                                         seed=seed)
    with progress_bar() as progress:
        task = progress.add_task("load terrain", total=None, loss="")
        truth = load_truth(source, seed=cfg.seed)
        elevation = load_source_dem(source, seed=cfg.seed).elevation if cfg.line_of_sight else None

        def on_strategy(name: str) -> None:
            nonlocal task
            task = progress.add_task(f"mission: {name}", total=cfg.steps, loss="")

        def on_step(name: str, step: int, coverage: float) -> None:
            progress.update(task, completed=step, loss=f"coverage {coverage:.0%}")

        result = run_mission(cfg, truth, elevation=elevation, on_strategy=on_strategy, on_step=on_step)
        task = progress.add_task("write outputs", total=None, loss="")
        title = f"{source.label}, {truth.shape[0]}x{truth.shape[1]}"
        write_mission(result, out, title=title, settings=resolved, animation=animation,
                      extra={"mission.toml": dumps_toml(_toml_ready(resolved)), "mission.json": to_json(resolved)})
        progress.update(task, total=1, completed=1)
    header, rows = table_rows(result)
    t = Table(title=f"mission on {title}: strategies side by side", header_style="bold")
    keep = [i for i, h in enumerate(header) if h in _CONSOLE]
    for i in keep:
        t.add_column(_CONSOLE[header[i]], justify="left" if i == 0 else "right", no_wrap=True)
    for r in rows:
        t.add_row(*(r[i] for i in keep))
    console.print(fit(t))
    console.print("50/80/95 %: first step the team's coverage reached it; F1>=.9: first step a rover's belief gave "
                  "strict A* path F1 >= 0.9; cov., acc.: coverage and mean belief accuracy at the end; glob.F1: the "
                  "base's map, strict; up/down: bytes of the whole team. All columns: report.md.")
    console.print(f"outputs: {out}/  (metrics.json, report.md, coverage.png, f1.png, accuracy_bytes.png"
                  f"{', mission_<strategy>.gif' if animation else ''})")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


#: Columns of the console table (report.md has them all) -> their short headers.
_CONSOLE = {"strategy": "strategy", "steps to 50 %": "50 %", "steps to 80 %": "80 %", "steps to 95 %": "95 %",
            "belief F1≥0.9 at": "F1>=.9", "coverage": "cov.", "belief acc.": "acc.", "global F1": "glob.F1",
            "bytes up": "up B", "bytes down": "down B"}


def _toml_ready(d: dict) -> dict:
    """The resolved settings without None values (TOML has no null)."""
    if isinstance(d, dict):
        return {k: _toml_ready(v) for k, v in d.items() if v is not None}
    if isinstance(d, (list, tuple)):
        return [_toml_ready(v) for v in d]
    return d
