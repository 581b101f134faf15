"""``fedmap run``: the demo's pipeline on any terrain source, configured by TOML and options.

Registered on the CLI app in :mod:`fedmap.cli`; the work is in :mod:`fedmap.config`,
:mod:`fedmap.sources` and :mod:`fedmap.pipeline`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from fedmap.errors import FedmapError

#: CLI option -> (section, key) of the run config.
OPTION_KEYS: dict[str, tuple[str | None, str]] = {
    "method": (None, "method"), "seed": (None, "seed"),
    "size": ("terrain", "size"), "crop": ("terrain", "crop"),
    "max_slope": ("thresholds", "max_slope_deg"), "max_step": ("thresholds", "max_step_m"),
    "max_roughness": ("thresholds", "max_roughness_m"),
    "agents": ("explore", "agents"), "explore": ("explore", "mode"), "overlap": ("explore", "overlap"),
    "net": ("model", "net"), "init": ("model", "init"),
    "local_epochs": ("train", "epochs"), "lr": ("train", "lr"), "masked": ("train", "masked"),
    "rounds": ("federation", "rounds"), "aggregator": ("federation", "aggregator"), "eta": ("federation", "eta"),
    "beta1": ("federation", "beta1"), "beta2": ("federation", "beta2"), "tau": ("federation", "tau"),
    "uplink": ("federation", "uplink"), "downlink": ("federation", "downlink"),
    "min_size": ("refine", "min_size"), "pairs": ("evaluate", "pairs"), "central": ("evaluate", "central"),
}

#: Side limits of the map the pipeline trains on.
MIN_SIDE, MAX_SIDE = 64, 2048


def option_overrides(values: dict) -> dict:
    """Partial run config from the CLI options that were given (None = not given)."""
    out: dict = {}
    for name, value in values.items():
        if value is None:
            continue
        section, key = OPTION_KEYS[name]
        if section is None:
            out[key] = value
        else:
            out.setdefault(section, {})[key] = value
    return out


def terrain_override(dem: Path | None, map_: Path | None, terrain: str | None) -> dict | None:
    """The ``[terrain]`` table that ``--dem``/``--map``/``--terrain`` put in place of the file's."""
    given = [(k, v) for k, v in (("dem", dem), ("map", map_), ("builtin", terrain)) if v is not None]
    if len(given) > 1:
        raise FedmapError("give at most one of --dem, --map and --terrain")
    if not given:
        return None
    kind, value = given[0]
    return {"kind": kind, "terrain": value} if kind == "builtin" else {"kind": kind, "path": str(Path(value).resolve())}


def prepare(config: Path | None, *, overrides: list[dict], terrain: dict | None, pixel_size: float | None = None):
    """Resolve the config and load the truth: ``(resolved dict, TerrainSource, truth, PipelineConfig)``."""
    from fedmap.config import resolve, terrain_source, to_pipeline_config
    from fedmap.sources import load_truth

    if pixel_size is not None:
        overrides = [*overrides, {"terrain": {"options": {"pixel_size": pixel_size}}}]
    resolved = resolve(config, overrides, terrain=terrain)
    source = terrain_source(resolved)
    resolved["terrain"] = {k: v for k, v in source.to_dict().items() if k != "thresholds"}
    truth = load_truth(source, seed=resolved["seed"])
    h, w = truth.shape
    if h != w or not MIN_SIDE <= h <= MAX_SIDE:
        raise FedmapError(f"the terrain map is {h}x{w} cells; the pipeline needs a square map of {MIN_SIDE}..{MAX_SIDE} "
                          f"cells: set [terrain] size (or --size)")
    return resolved, source, truth, to_pipeline_config(resolved, size=h, label=source.label)


def run_command(
    config: Optional[Path] = typer.Argument(None, help="Run config (TOML); options below override it."),
    dem: Optional[Path] = typer.Option(None, "--dem", help="DEM file (.tif, .asc, .img/.raw, .png heightmap, .npy)."),
    map_: Optional[Path] = typer.Option(None, "--map", help="Traversability class map (.png or .npy)."),
    terrain: Optional[str] = typer.Option(None, "--terrain", help="Built-in terrain: mars, moon or ice."),
    pixel_size: Optional[float] = typer.Option(None, "--pixel-size", help="Metres per cell of the file (overrides it)."),
    crop: Optional[int] = typer.Option(None, help="Centred square crop of the terrain, in cells, before resampling."),
    size: Optional[int] = typer.Option(None, help="Resample the terrain to size x size cells (64..2048)."),
    max_slope: Optional[float] = typer.Option(None, "--max-slope", help="Traversability: max slope in degrees."),
    max_step: Optional[float] = typer.Option(None, "--max-step", help="Traversability: max step height in metres."),
    max_roughness: Optional[float] = typer.Option(None, "--max-roughness", help="Traversability: max roughness (m)."),
    method: Optional[str] = typer.Option(None, help="Preset: paper or fedmap (defaults below it)."),
    agents: Optional[int] = typer.Option(None, help="Number of rovers."),
    explore: Optional[str] = typer.Option(None, help="Exploration: quadrants, strips, grid or traverse."),
    overlap: Optional[int] = typer.Option(None, help="Cells of overlap between neighbouring rovers' blocks."),
    net: Optional[str] = typer.Option(None, help="Network: paper, small or grid."),
    init: Optional[str] = typer.Option(None, help="Initial weights: random or empty (empty-map prior)."),
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
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Any config key: section.key=value (TOML value), repeatable."),
    out: Path = typer.Option(Path("fedmap-out/run"), "--out", "-o", help="Output folder (replaced atomically)."),
) -> None:
    """Map any terrain (DEM, class map, tiles or built-in) with a federated team; config from TOML + options."""
    from fedmap.cli import _progress, _scores_table, _stage_callbacks, console
    from fedmap.config import dumps_toml, parse_set
    from fedmap.pipeline import run_pipeline, write_outputs
    from fedmap.report import to_json

    t0 = time.perf_counter()
    values = dict(method=method, seed=seed, size=size, crop=crop, max_slope=max_slope, max_step=max_step,
                  max_roughness=max_roughness, agents=agents, explore=explore, overlap=overlap, net=net, init=init,
                  local_epochs=local_epochs, lr=lr, masked=masked, rounds=rounds, aggregator=aggregator, eta=eta,
                  beta1=beta1, beta2=beta2, tau=tau, uplink=uplink, downlink=downlink, min_size=min_size,
                  pairs=pairs, central=central)
    overrides = [parse_set(s) for s in set_ or []] + [option_overrides(values)]
    table = terrain_override(dem, map_, terrain)
    with _progress() as progress:
        on_stage, on_step = _stage_callbacks(progress)
        on_stage("load terrain", 0)
        resolved, source, truth, pconfig = prepare(config, overrides=overrides, terrain=table, pixel_size=pixel_size)
        result = run_pipeline(pconfig, truth=truth, on_stage=on_stage, on_step=on_step)
        on_stage("write outputs", 0)
        write_outputs(result, out, extra={"config.toml": dumps_toml(resolved), "run_config.json": to_json(resolved)})
        on_stage(None, 0)
    m = result.metrics
    f = truth.fractions()
    console.print(f"terrain: {source.label}, {truth.shape[0]}x{truth.shape[1]} cells of {truth.pixel_size:.3g} m; "
                  f"{f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown")
    console.print(_scores_table(m))
    b = m["bytes"]
    console.print(f"link: {b['uplink']:,} B uplink, {b['downlink']:,} B downlink in total")
    console.print(f"outputs: {out}/  (config.toml, metrics.json, figure.png, global_model.safetensors, maps)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")
