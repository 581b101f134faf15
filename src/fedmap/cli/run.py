"""``fedmap demo`` / ``run`` / ``terrain`` / ``evaluate``: map terrain with a federated team.

``demo`` is ``run`` with the demo's defaults (built-in mars, its own output folder) over
two presets on the same rovers, ``paper`` and ``fedmap``, side by side (``--method`` picks
one). Both build their configuration with :mod:`fedmap.config` and run
:func:`fedmap.pipeline.run_pipeline`; this module only wires options to them.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from fedmap import _schema
from fedmap._util import atomic_write_bytes, check_output_dir, clean_json, to_json
from fedmap.cli.options import SHORTCUT_FLAGS, parameters, with_settings
from fedmap.cli.ui import F1_CAPTION, comparison_table, console, progress_bar, scores_table, stage_callbacks, terrain_line
from fedmap.config import dumps_toml, load_run, parse_set
from fedmap.errors import FedmapError
from fedmap.evaluation.scores import score_map
from fedmap.maps.export import EXPORT_FORMATS, check_formats
from fedmap.maps.io import load_map, save_map
from fedmap.maps.sources import terrain_notes
from fedmap.maps.terrain import generate_dem
from fedmap.maps.traversability import dem_to_traversability
from fedmap.nets.training import precision_reason
from fedmap.outputs import comparison_rows, write_comparison, write_outputs
from fedmap.pipeline import PipelineConfig, run_pipeline


def execute(config: Path | None, settings: dict[str, Any], *, set_: list[str] | None = None, export: list[str] | None = None,
            terrain: dict | None = None, out: Path, methods: list[str] | None = None) -> None:
    """Resolve, load, run, write and report one run (``demo`` and ``run``). ``settings``
    is a partial run config (the options given), laid over ``--set`` assignments.

    With several ``methods`` (presets) each runs on the same terrain and rovers, and the
    outputs are written side by side (:func:`fedmap.outputs.write_comparison`).
    """
    overrides = [parse_set(s) for s in set_ or []] + [settings]
    check_output_dir(out)  # before the work: a folder that is not fedmap's, or cannot be written, is refused
    if methods and len(methods) > 1:
        return _execute_many(methods, overrides, out=out, export=export)
    export = list(check_formats(export))  # a bad format stops the run before it starts
    t0 = time.perf_counter()
    with progress_bar() as progress:
        on_stage, on_step = stage_callbacks(progress)
        on_stage("load terrain", 0)
        resolved, source, truth, pconfig = load_run(config, overrides, terrain=terrain)
        for warning in terrain_notes(truth):
            if warning:
                console.print(f"warning: {warning}", soft_wrap=True)  # one line, however wide
        console.print(precision_line(resolved, pconfig))
        result = run_pipeline(pconfig, truth=truth, on_stage=on_stage, on_step=on_step)
        on_stage("write outputs", 0)
        write_outputs(result, out, extra={"config.toml": dumps_toml(resolved), "run_config.json": to_json(resolved)},
                      export=export)
        on_stage(None, 0)
    fed = pconfig.federation
    console.print(terrain_line(source.label, truth, pconfig.thresholds))
    console.print(f"method: {resolved['method']} ({pconfig.model.net} net, {pconfig.model.start}, {fed.aggregator} x "
                  f"{fed.rounds} round(s), {pconfig.train.epochs} local epochs)")
    console.print(scores_table(result))
    ev = pconfig.evaluate
    console.print(f"PSNR in dB on RGB renderings; P/R/F1: A* path planning over {ev.pairs} start/goal pairs "
                  f"(UNKNOWN {'passable' if ev.unknown_passable else 'impassable'}). {F1_CAPTION}")
    b = result.federation.total_bytes()
    console.print(f"link: {b.uplink:,} B uplink ({fed.uplink}), {b.downlink:,} B downlink ({fed.downlink}) in "
                  f"total; {b.uplink_per_agent_round:,.0f} B per rover per round uplink")
    if result.elevation is not None:
        e = result.elevation
        console.print(f"elevation: height grids {e['resolutions']}, {e['codec']}: RMSE {e['observed']['rmse_m']:.4f} m "
                      f"(max {e['observed']['max_error_m']:.4f} m) on the observed cells, {e['bytes']['uplink']:,} B "
                      f"uplink (a lossless 1 cm share: {e['bytes']['lossless_1cm_uplink']:,} B), "
                      f"{e['bytes']['downlink']:,} B downlink; classes re-derived from it: strict path F1 "
                      f"{e['rederived_classes']['path']['f1']:.2f}", soft_wrap=True)
    console.print(f"outputs: {out}/  (config.toml, metrics.json, figure.png, global_model.safetensors, maps)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


def _execute_many(methods: list[str], overrides: list[dict], *, out: Path, export: list[str] | None = None) -> None:
    """Each method on the same built-in terrain and rovers; one table, one figure."""
    export = list(check_formats(export))  # a bad format stops the run before it starts
    t0 = time.perf_counter()
    results, resolved_by = {}, {}
    with progress_bar() as progress:
        on_stage, on_step = stage_callbacks(progress)
        for method in methods:
            def stage(name: str | None, total: int, method: str = method) -> None:
                on_stage(None if name is None else f"{name} ({method})", total)

            stage("load terrain", 0)
            resolved, source, truth, pconfig = load_run(None, [*overrides, {"method": method}])
            console.print(precision_line(resolved, pconfig, method=method))
            results[method] = run_pipeline(pconfig, truth=truth, on_stage=stage, on_step=on_step)
            resolved_by[method] = {"config.toml": dumps_toml(resolved), "run_config.json": to_json(resolved)}
        on_stage("write outputs", 0)
        write_comparison(results, out, extra=resolved_by, export=export)
        on_stage(None, 0)
    console.print(f"{terrain_line(source.label, truth, pconfig.thresholds)}; {pconfig.explore.agents} rovers "
                  f"({pconfig.explore.mode}), the same for every method")
    console.print(comparison_table(comparison_rows(results)))
    console.print(f"PSNR in dB; F1: strict A* path F1 over {pconfig.evaluate.pairs} start/goal pairs (an identical path "
                  "is a TP, a different path both an FP and an FN); B/rover: uplink bytes per rover per round, as "
                  "encoded. paper: the source paper's network and FedAvg from its meta-init; fedmap: feature grids "
                  "with coverage-aware FedAvg. Each method's full scores are in its metrics.json.")
    console.print(f"outputs: {out}/  (figure.png, metrics.json; {', '.join(f'{m}/' for m in methods)} with each "
                  "method's maps, model and config)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


def precision_line(resolved: dict, pconfig: PipelineConfig, method: str | None = None) -> str:
    """The line saying which precision a run trains in and why, printed before it trains:
    ``training precision (paper): fp32 (auto): this CPU has no native bf16 ...``. ``resolved``
    is the run's settings as given (``precision`` may be ``auto``), ``pconfig`` the built run."""
    asked = resolved.get("train", {}).get("precision", pconfig.train.precision)
    head = "training precision" + (f" ({method})" if method else "")
    return f"{head}: {precision_reason(asked, grid=pconfig.model.net == 'grid')}"


#: The settings ``demo`` and ``run`` take as options: the run config's, derived from its fields.
_RUN_SETTINGS = [s for s in _schema.walk(PipelineConfig) if s.section != "thresholds"]
_DEMO = with_settings(parameters(_RUN_SETTINGS, presets=True))
_RUN = with_settings(parameters(_schema.walk(PipelineConfig), presets=True, skip=SHORTCUT_FLAGS), terrain=True)


@_DEMO
def demo(
    out: Path = typer.Option(Path("fedmap-out/demo"), "--out", "-o", help="Output folder (replaced atomically)."),
    export: Optional[list[str]] = typer.Option(None, "--export", help=f"Also write every map as {', '.join(EXPORT_FORMATS)}; repeatable."),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Any config key: section.key=value (TOML value), repeatable."),
    settings: Optional[dict] = None,
) -> None:
    """Built-in terrain -> 4 rovers explore -> fit -> federate -> refine -> evaluate, with the paper's method and fedmap's side by side (--method picks one)."""
    settings = settings or {}
    execute(None, settings, set_=set_, out=out, methods=None if "method" in settings else ["paper", "fedmap"],
            export=export)


@_RUN
def run(
    config: Optional[Path] = typer.Argument(None, help="Run config (TOML); options below override it."),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Any config key: section.key=value (TOML value), repeatable."),
    out: Path = typer.Option(Path("fedmap-out/run"), "--out", "-o", help="Output folder (replaced atomically)."),
    export: Optional[list[str]] = typer.Option(None, "--export", help=f"Also write every map as {', '.join(EXPORT_FORMATS)} (geotiff: georeferenced like the DEM; ros: map_server YAML + PGM); repeatable."),
    settings: Optional[dict] = None,
    terrain: Optional[dict] = None,
) -> None:
    """Map any terrain (DEM, class map, tiles or built-in) with a federated team; config from TOML + options."""
    execute(config, settings or {}, set_=set_, terrain=terrain, out=out, export=export)


def terrain(
    kind: str = typer.Argument(..., help="mars, moon or ice."),
    out: Path = typer.Argument(..., help="Output map (.png, .npy, .tif GeoTIFF or ROS .yaml)."),
    size: int = typer.Option(256, help="Map side in cells (64..4096)."),
    seed: int = typer.Option(0, min=0),
    dem_out: Optional[Path] = typer.Option(None, "--dem", help="Also save the DEM as .npy."),
) -> None:
    """Generate a built-in terrain's traversability map."""
    if dem_out is not None:
        if dem_out.suffix.lower() != ".npy":
            raise FedmapError(f"--dem {dem_out}: the DEM is written as a NumPy array; give a .npy path")
        if dem_out.expanduser().resolve() == out.expanduser().resolve():
            raise FedmapError(f"--dem {dem_out} is the map's own path; give the DEM another name")
    dem = generate_dem(kind, size, seed=seed)
    grid = dem_to_traversability(dem)
    save_map(grid, out)
    if dem_out is not None:
        buf = io.BytesIO()
        np.save(buf, dem.elevation)
        atomic_write_bytes(dem_out, buf.getvalue())
    f = grid.fractions()
    console.print(f"{out}: {size}x{size} {kind}, {f['free']:.1%} free, {f['impassable']:.1%} impassable, "
                  f"{f['unknown']:.1%} unknown", soft_wrap=True)  # one line, whatever the path's length


def evaluate(
    learned: Path = typer.Argument(..., help="Learned map (.png, .npy, .tif or ROS .yaml)."),
    truth: Path = typer.Argument(..., help="Ground-truth map (.png, .npy, .tif or ROS .yaml)."),
    pairs: int = typer.Option(75, min=1, max=100_000, help="Random start/goal pairs."),
    seed: int = typer.Option(0, min=0),
    unknown_passable: bool = typer.Option(False, help="Let the planner cross UNKNOWN cells."),
) -> None:
    """PSNR, SSIM and A* path F1 of a map against ground truth (strict, tolerant and paper-literal)."""
    a, b = load_map(learned), load_map(truth)
    if a.shape != b.shape:
        raise FedmapError(f"{learned} is {a.shape[0]}x{a.shape[1]} but {truth} is {b.shape[0]}x{b.shape[1]}")
    scores = score_map(b.classes, a.classes, pairs=pairs, seed=seed, unknown_passable=unknown_passable)
    console.print_json(json.dumps(clean_json(scores.to_dict())))
