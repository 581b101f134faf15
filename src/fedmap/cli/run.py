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

from fedmap._util import atomic_write_bytes, clean_json, to_json
from fedmap.cli.ui import F1_CAPTION, comparison_table, console, progress_bar, scores_table, stage_callbacks
from fedmap.config import dumps_toml, load_run, overrides_from, parse_set, terrain_table
from fedmap.errors import FedmapError
from fedmap.evaluation.scores import score_map
from fedmap.maps.export import EXPORT_FORMATS, check_formats
from fedmap.maps.io import load_map, save_map
from fedmap.maps.terrain import generate_dem
from fedmap.maps.traversability import dem_to_traversability, parse_slope_limit
from fedmap.outputs import comparison_rows, write_comparison, write_outputs
from fedmap.pipeline import run_pipeline


def execute(config: Path | None, settings: dict[str, Any], *, set_: list[str] | None = None, export: list[str] | None = None,
            terrain: dict | None = None, out: Path, methods: list[str] | None = None) -> None:
    """Resolve, load, run, write and report one run (``demo`` and ``run``).

    With several ``methods`` (presets) each runs on the same terrain and rovers, and the
    outputs are written side by side (:func:`fedmap.outputs.write_comparison`).
    """
    if methods and len(methods) > 1:
        return _execute_many(methods, settings, out=out, export=export)
    export = list(check_formats(export))  # a bad format stops the run before it starts
    t0 = time.perf_counter()
    overrides = [parse_set(s) for s in set_ or []] + [overrides_from(settings)]
    with progress_bar() as progress:
        on_stage, on_step = stage_callbacks(progress)
        on_stage("load terrain", 0)
        resolved, source, truth, pconfig = load_run(config, overrides, terrain=terrain)
        if truth.meta.get("warning"):
            console.print(f"warning: {truth.meta['warning']}", soft_wrap=True)  # one line, however wide
        result = run_pipeline(pconfig, truth=truth, on_stage=on_stage, on_step=on_step)
        on_stage("write outputs", 0)
        write_outputs(result, out, extra={"config.toml": dumps_toml(resolved), "run_config.json": to_json(resolved)},
                      export=export)
        on_stage(None, 0)
    f = truth.fractions()
    fed = pconfig.federation
    console.print(f"terrain: {source.label}, {truth.shape[0]}x{truth.shape[1]} cells of {truth.pixel_size:.3g} m; "
                  f"{f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown")
    console.print(f"method: {resolved['method']} ({pconfig.net} net, init {pconfig.init}, {fed.aggregator} x "
                  f"{fed.rounds} round(s), {fed.local.epochs} local epochs)")
    console.print(scores_table(result))
    console.print(f"PSNR in dB on RGB renderings; P/R/F1: A* path planning over {pconfig.eval_pairs} start/goal pairs "
                  f"(UNKNOWN {'passable' if pconfig.unknown_passable else 'impassable'}). {F1_CAPTION}")
    b = result.federation.total_bytes()
    console.print(f"link: {b['uplink']:,} B uplink ({fed.uplink}), {b['downlink']:,} B downlink ({fed.downlink}) in "
                  f"total; {b['uplink_per_agent_round']:,.0f} B per rover per round uplink")
    console.print(f"outputs: {out}/  (config.toml, metrics.json, figure.png, global_model.safetensors, maps)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


def _execute_many(methods: list[str], settings: dict[str, Any], *, out: Path, export: list[str] | None = None) -> None:
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
            resolved, source, truth, pconfig = load_run(None, [overrides_from({**settings, "method": method})])
            results[method] = run_pipeline(pconfig, truth=truth, on_stage=stage, on_step=on_step)
            resolved_by[method] = {"config.toml": dumps_toml(resolved), "run_config.json": to_json(resolved)}
        on_stage("write outputs", 0)
        write_comparison(results, out, extra=resolved_by, export=export)
        on_stage(None, 0)
    f = truth.fractions()
    console.print(f"terrain: {source.label}, {truth.shape[0]}x{truth.shape[1]} cells of {truth.pixel_size:.3g} m; "
                  f"{f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown; "
                  f"{pconfig.agents} rovers ({pconfig.explore}), the same for every method")
    console.print(comparison_table(comparison_rows(results)))
    console.print(f"PSNR in dB; F1: strict A* path F1 over {pconfig.eval_pairs} start/goal pairs (an identical path "
                  "is a TP, a different path both an FP and an FN); B/rover: uplink bytes per rover per round, as "
                  "encoded. paper: the source paper's network and FedAvg from its meta-init; fedmap: feature grids "
                  "with coverage-aware FedAvg. Each method's full scores are in its metrics.json.")
    console.print(f"outputs: {out}/  (figure.png, metrics.json; {', '.join(f'{m}/' for m in methods)} with each "
                  "method's maps, model and config)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


_PRECISION = "Training arithmetic: auto (bf16 matrix products where the CPU has native bf16, else fp32), bf16 or fp32 [auto]."
_METHOD = "Preset: paper (Fourier MLP from the shipped meta-init, FedAvg, fp32) or fedmap (feature grids, coverage-aware FedAvg, masked loss, int4/int8 update payloads). Options below override it."  # noqa: E501


def demo(
    terrain: Optional[str] = typer.Option(None, help="Built-in terrain: mars, moon or ice [mars]."),
    size: Optional[int] = typer.Option(None, help="Map side in cells (64..2048) [128]."),
    agents: Optional[int] = typer.Option(None, help="Number of rovers [4]."),
    explore: Optional[str] = typer.Option(None, help="Exploration: quadrants, strips, grid or traverse."),
    method: Optional[str] = typer.Option(None, help=_METHOD + " [both, side by side]"),
    rounds: Optional[int] = typer.Option(None, help="Communication rounds R [1]."),
    local_epochs: Optional[int] = typer.Option(None, "--local-epochs", help="Local epochs per round E [100]."),
    lr: Optional[float] = typer.Option(None, help="Local Adam learning rate [paper 1e-3, fedmap 0.05]."),
    aggregator: Optional[str] = typer.Option(None, help="fedavg, fedadam, fedyogi or coverage (coverage-aware FedAvg)."),
    net: Optional[str] = typer.Option(None, help="Network: paper (Fourier MLP, 199,683 params), small, or grid (feature grids)."),
    central: Optional[bool] = typer.Option(None, help="Also fit one network to the union of the local maps (the upper bound) [on]."),
    uplink: Optional[str] = typer.Option(None, help="Rover -> base codec: fp32, fp16, bf16, int8, int4, topk:0.01, update-int4, ... (+zstd)."),
    downlink: Optional[str] = typer.Option(None, help="Base -> rover codec (same grammar)."),
    eta: Optional[float] = typer.Option(None, help="Server learning rate for fedadam/fedyogi [0.01]."),
    init: Optional[str] = typer.Option(None, help="Initial weights: random, empty (empty-map prior) or meta (shipped meta-init) [paper: meta; fedmap: random = zero grids]."),
    init_weights: Optional[Path] = typer.Option(None, "--init-weights", help="With --init meta: a weights file from fedmap meta-train instead of the shipped one."),
    masked: Optional[bool] = typer.Option(None, help="Loss on known cells only [paper: off, unknown is trained as grey; fedmap: on]."),
    min_size: Optional[int] = typer.Option(None, "--min-size", help="Refinement: remove impassable blobs smaller than this many cells (paper: 200; default 0 = off)."),
    pairs: Optional[int] = typer.Option(None, help="Random start/goal pairs for the path F1 [75]."),
    seed: Optional[int] = typer.Option(None, help="Seed for terrain, exploration, initialisation, training and evaluation [0]."),
    precision: Optional[str] = typer.Option(None, help=_PRECISION),
    out: Path = typer.Option(Path("fedmap-out/demo"), "--out", "-o", help="Output folder (replaced atomically)."),
    export: Optional[list[str]] = typer.Option(None, "--export", help=f"Also write every map as {', '.join(EXPORT_FORMATS)}; repeatable."),
) -> None:
    """Built-in terrain -> 4 rovers explore -> fit -> federate -> refine -> evaluate, with the paper's method and fedmap's side by side."""
    settings = dict(method=method, terrain=terrain, size=size, agents=agents, explore=explore, rounds=rounds,
                    epochs=local_epochs, lr=lr, aggregator=aggregator, net=net, central=central, uplink=uplink,
                    downlink=downlink, eta=eta, init=init, init_weights=None if init_weights is None else
                    str(init_weights.resolve()), masked=masked, min_size=min_size, pairs=pairs, seed=seed,
                    precision=precision)
    execute(None, settings, out=out, methods=None if method else ["paper", "fedmap"], export=export)


def run(
    config: Optional[Path] = typer.Argument(None, help="Run config (TOML); options below override it."),
    dem: Optional[Path] = typer.Option(None, "--dem", help="DEM file: any raster GDAL reads (GeoTIFF, ISIS3 .cub, PDS3 .lbl, PDS4 .xml, .asc, ...), a .png heightmap or .npy."),
    map_: Optional[Path] = typer.Option(None, "--map", help="Traversability class map (.png, .npy, .tif GeoTIFF or ROS .yaml)."),
    terrain: Optional[str] = typer.Option(None, "--terrain", help="Built-in terrain: mars, moon or ice."),
    pixel_size: Optional[float] = typer.Option(None, "--pixel-size", help="Metres per cell of the file (overrides it)."),
    crop: Optional[int] = typer.Option(None, help="Centred square crop of the terrain, in cells, before resampling."),
    size: Optional[int] = typer.Option(None, help="Resample the terrain to size x size cells (64..2048)."),
    max_slope: Optional[str] = typer.Option(None, "--max-slope", help="Traversability: max slope in degrees (25), or a percentile of the map's slopes (p75) for coarse DEMs."),
    rover: Optional[str] = typer.Option(None, "--rover", help="Traversability limits of a rover: cadre, mer or msl (options above override them)."),
    max_step: Optional[float] = typer.Option(None, "--max-step", help="Traversability: max step height in metres."),
    max_roughness: Optional[float] = typer.Option(None, "--max-roughness", help="Traversability: max roughness (m)."),
    method: Optional[str] = typer.Option(None, help="Preset: paper or fedmap (defaults below it)."),
    agents: Optional[int] = typer.Option(None, help="Number of rovers."),
    explore: Optional[str] = typer.Option(None, help="Exploration: quadrants, strips, grid or traverse."),
    overlap: Optional[int] = typer.Option(None, help="Cells of overlap between neighbouring rovers' blocks."),
    net: Optional[str] = typer.Option(None, help="Network: paper, small or grid."),
    init: Optional[str] = typer.Option(None, help="Initial weights: random, empty (empty-map prior) or meta (shipped meta-init)."),
    init_weights: Optional[Path] = typer.Option(None, "--init-weights", help="With init meta: a weights file from fedmap meta-train."),
    local_epochs: Optional[int] = typer.Option(None, "--local-epochs", help="Local epochs per round E."),
    lr: Optional[float] = typer.Option(None, help="Local Adam learning rate."),
    masked: Optional[bool] = typer.Option(None, help="Loss on known cells only."),
    rounds: Optional[int] = typer.Option(None, help="Communication rounds R."),
    aggregator: Optional[str] = typer.Option(None, help="fedavg, fedadam, fedyogi or coverage."),
    eta: Optional[float] = typer.Option(None, help="Server learning rate (fedadam/fedyogi)."),
    beta1: Optional[float] = typer.Option(None, help="Server first-moment decay (fedadam/fedyogi)."),
    beta2: Optional[float] = typer.Option(None, help="Server second-moment decay (fedadam/fedyogi)."),
    tau: Optional[float] = typer.Option(None, help="Server adaptivity epsilon (fedadam/fedyogi)."),
    uplink: Optional[str] = typer.Option(None, help="Rover -> base codec (fp32, fp16, int8, update-int4+zstd, ...)."),
    downlink: Optional[str] = typer.Option(None, help="Base -> rover codec."),
    min_size: Optional[int] = typer.Option(None, "--min-size", help="Refinement: drop impassable blobs under this size."),
    pairs: Optional[int] = typer.Option(None, help="Random start/goal pairs for the path F1."),
    central: Optional[bool] = typer.Option(None, help="Also fit the centralised upper bound."),
    seed: Optional[int] = typer.Option(None, help="Seed for terrain, exploration, training and evaluation."),
    precision: Optional[str] = typer.Option(None, help=_PRECISION),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Any config key: section.key=value (TOML value), repeatable."),
    out: Path = typer.Option(Path("fedmap-out/run"), "--out", "-o", help="Output folder (replaced atomically)."),
    export: Optional[list[str]] = typer.Option(None, "--export", help=f"Also write every map as {', '.join(EXPORT_FORMATS)} (geotiff: georeferenced like the DEM; ros: map_server YAML + PGM); repeatable."),
) -> None:
    """Map any terrain (DEM, class map, tiles or built-in) with a federated team; config from TOML + options."""
    settings = dict(method=method, seed=seed, size=size, rover=rover, max_step_m=max_step,
                    max_roughness_m=max_roughness, agents=agents, explore=explore, overlap=overlap, net=net,
                    init=init, init_weights=None if init_weights is None else str(init_weights.resolve()),
                    epochs=local_epochs, lr=lr, masked=masked, rounds=rounds, aggregator=aggregator, eta=eta,
                    beta1=beta1, beta2=beta2, tau=tau, uplink=uplink, downlink=downlink, min_size=min_size,
                    pairs=pairs, central=central, precision=precision)
    table = terrain_table(dem=dem, map_path=map_, builtin=terrain)
    if max_slope is not None:
        settings.update(parse_slope_limit(max_slope))
    if pixel_size is not None:
        set_ = [*(set_ or []), f"terrain.options.pixel_size={pixel_size!r}"]
    if crop is not None:  # a file's crop: not a method_config keyword (built-in terrain has none)
        set_ = [*(set_ or []), f"terrain.crop={crop}"]
    execute(config, settings, set_=set_, terrain=table, out=out, export=export)


def terrain(
    kind: str = typer.Argument(..., help="mars, moon or ice."),
    out: Path = typer.Argument(..., help="Output map (.png, .npy, .tif GeoTIFF or ROS .yaml)."),
    size: int = typer.Option(256, help="Map side in cells (64..2048)."),
    seed: int = typer.Option(0),
    dem_out: Optional[Path] = typer.Option(None, "--dem", help="Also save the DEM as .npy."),
) -> None:
    """Generate a built-in terrain's traversability map."""
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
    pairs: int = typer.Option(75, help="Random start/goal pairs."),
    seed: int = typer.Option(0),
    unknown_passable: bool = typer.Option(False, help="Let the planner cross UNKNOWN cells."),
) -> None:
    """PSNR, SSIM and A* path F1 of a map against ground truth (strict, tolerant and paper-literal)."""
    a, b = load_map(learned), load_map(truth)
    if a.shape != b.shape:
        raise FedmapError(f"{learned} is {a.shape[0]}x{a.shape[1]} but {truth} is {b.shape[0]}x{b.shape[1]}")
    scores = score_map(b.classes, a.classes, pairs=pairs, seed=seed, unknown_passable=unknown_passable)
    console.print_json(json.dumps(clean_json(scores.to_dict())))
