"""``fedmap reproduce`` and ``fedmap bandwidth``: the paper's experiments (:mod:`fedmap.experiments`)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from fedmap._util import AtomicDir, check_output_dir
from fedmap.cli.ui import console, fit, fmt, progress_bar, stage_callbacks
from fedmap.config import method_config
from fedmap.errors import FedmapError
from fedmap.experiments.cellstreams import cell_stream_report, markdown
from fedmap.experiments.elevation import (
    DEFAULT_SIZE,
    FAMILIES,
    dem_source,
    elevation_markdown,
    elevation_rd,
    plot_rd,
    reach_rows,
    terrain_sources,
)
from fedmap.experiments.reproduce import F1_MEANINGS, PAPER_TABLE2, ReproduceConfig
from fedmap.experiments.reproduce import reproduce as run_reproduce
from fedmap.experiments.table3 import bandwidth_report
from fedmap.maps.traversability import TraversabilityThresholds, parse_slope_limit
from fedmap.mission import load_mission, mission_terrain


def bandwidth(
    terrain: str = typer.Option("mars", help="Built-in terrain: mars, moon or ice."),
    size: Optional[int] = typer.Option(None, help="Map side for the rate-distortion comparison (64..4096) [128]; "
                                       "--layer elevation: every terrain is resampled to it (--dem's: 3 or more)."),
    pairs: int = typer.Option(75, min=1, max=100_000, help="Random start/goal pairs for the path F1."),
    seed: int = typer.Option(0, min=0),
    federated: bool = typer.Option(True, help="Also run fedmap's federated configurations on the same map."),
    streams: Optional[str] = typer.Option(None, help="Instead: bits per new cell on a mission's uplink stream, "
                                          "for every cell coder ('default' or a mission TOML file)."),
    layer: str = typer.Option("classes", help="classes: Table III on the class map; elevation: the heights' rate-distortion (lossless, LERC, JPEG XL, JPEG 2000, neural) on the built-in terrains (and --data's)."),
    data: Optional[Path] = typer.Option(None, help="--layer elevation: a folder laid out like the project's shared/data, for the Gale, Hadley and Columbia Glacier DEMs."),
    dem: Optional[Path] = typer.Option(None, "--dem", help="--layer elevation: your own DEM (any raster GDAL reads, a .png heightmap or .npy) as the only terrain; its centred square, resampled to --size."),
    pixel_size: Optional[float] = typer.Option(None, "--pixel-size", help="--dem: metres per cell (overrides the file's)."),
    max_slope: Optional[str] = typer.Option(None, "--max-slope", help="--layer elevation: the slope limit of the re-derived classes, degrees (e.g. 20) or a percentile of the true heights' slopes (e.g. p75) [15]."),
    neural_steps: int = typer.Option(1500, "--neural-steps", help="--layer elevation: training steps of each neural height field."),
    out: Path = typer.Option(Path("fedmap-out/bandwidth"), "--out", "-o", help="Output folder (replaced atomically)."),
) -> None:
    """Table III with real bytes: model codecs vs raw, JPEG, WebP, PNG and zstd of the map."""
    check_output_dir(out)
    if streams is not None:
        _cell_streams(streams, out)
        return
    if layer not in ("classes", "elevation"):
        raise FedmapError(f"unknown layer {layer!r}; choose classes or elevation")
    if layer == "elevation":
        _elevation(data, dem, out, size=size, pixel_size=pixel_size, max_slope=max_slope, pairs=pairs, seed=seed,
                   neural_steps=neural_steps)
        return
    for flag, value in (("--dem", dem), ("--data", data), ("--pixel-size", pixel_size), ("--max-slope", max_slope)):
        if value is not None:
            raise FedmapError(f"{flag} applies to --layer elevation only")
    size = DEFAULT_SIZE if size is None else size
    method_config(terrain=terrain, size=size, pairs=pairs)  # validates before any work
    t0 = time.perf_counter()
    with progress_bar() as progress:
        on_stage, on_step = stage_callbacks(progress)
        res = bandwidth_report(out, terrain=terrain, size=size, pairs=pairs, seed=seed, federated=federated,
                               on_stage=on_stage, on_step=on_step)
    t = Table(title=f"bytes vs quality, {terrain} {size}x{size}", header_style="bold")
    for col in ("payload", "bytes", "PSNR", "F1"):
        t.add_column(col, justify="left" if col == "payload" else "right", no_wrap=True)
    for r in res["image_codecs"]:
        t.add_row(r["codec"], f"{r['bytes']:,}", fmt(r["psnr"]), fmt(r["f1"]))
    for p in res["federated"]:
        t.add_row(f"fedmap: {p['label']}", f"{p['bytes']:,}", fmt(p["psnr"]), fmt(p["f1"]))
    console.print(t)
    fp16 = next(r for r in res["model_payloads"] if r["codec"] == "fp16")
    console.print(f"paper network in fp16: {fp16['bytes']:,} B (199,683 x 2 = 399,366 B of values + "
                  f"{fp16['bytes'] - 399_366} B header)")
    console.print(f"outputs: {out}/  (report.md, bandwidth.json, rd.png); wall time {time.perf_counter() - t0:.1f} s")


def _elevation(data: Path | None, dem: Path | None, out: Path, *, size: int | None, pixel_size: float | None,
               max_slope: str | None, pairs: int, seed: int, neural_steps: int) -> None:
    t0 = time.perf_counter()
    if data is not None and not data.is_dir():
        raise FedmapError(f"--data {data} is not a folder")
    if dem is not None and data is not None:
        raise FedmapError("give --dem (your DEM alone) or --data (the benchmark's real terrains), not both")
    if pixel_size is not None and dem is None:
        raise FedmapError("--pixel-size applies to --dem only")
    if neural_steps < 1:
        raise FedmapError(f"--neural-steps must be at least 1, got {neural_steps}")
    thresholds = None if max_slope is None else TraversabilityThresholds(**parse_slope_limit(max_slope))
    if dem is not None:
        sources = dem_source(dem, size=DEFAULT_SIZE if size is None else size, pixel_size=pixel_size,
                             thresholds=thresholds)
    else:
        sources = terrain_sources(None if data is None else str(data), size=size, thresholds=thresholds)
    with progress_bar() as progress:
        task = progress.add_task("elevation: coding", total=None, loss="")
        report = elevation_rd(sources, pairs=pairs, seed=seed, neural_steps=neural_steps,
                              on_point=lambda what: progress.update(task, description=f"elevation: {what}"))
    target = next(iter(report["summary"].values()))["f1_target"]
    t = Table(title=f"bytes before the heights are good enough to plan on (path F1 >= {target:g} of the re-derived "
              "classes; smallest measured point)", header_style="bold")
    for col in ("terrain", *FAMILIES, "wins"):
        t.add_column(col, justify="left" if col in ("terrain", "wins") else "right")
    for row in reach_rows(report):
        t.add_row(*row)
    console.print(fit(t))
    t = Table(title="neural against JPEG XL (matched RMSE) and LERC (matched max error)", header_style="bold")
    for col in ("terrain", "best neural / JPEG XL bytes", "best neural+residual / LERC bytes", "its path F1"):
        t.add_column(col, justify="left" if col == "terrain" else "right")
    for name, sm in report["summary"].items():
        vs = sm["neural_residual_vs_lerc"]
        best = min(vs, key=lambda v: v["ratio"]) if vs else None
        t.add_row(name, fmt(sm["best_neural_vs_jxl"]), fmt(sm["best_neural_residual_vs_lerc"]),
                  fmt(None if best is None else best["path_f1"]))
    console.print(fit(t))
    console.print("below 1: the neural payload takes fewer bytes than the standard codec at the same error; its path "
                  "F1 says whether a planner could use those heights. All points: elevation.json, report.md, "
                  "rd_elevation.png", soft_wrap=True)
    with AtomicDir(out) as tmp:
        (tmp / "elevation.json").write_text(json.dumps(report, indent=1))
        (tmp / "rd_elevation.png").write_bytes(plot_rd(report))
        (tmp / "report.md").write_text(elevation_markdown(report))
    console.print(f"outputs: {out}/  (report.md, elevation.json, rd_elevation.png); wall time "
                  f"{time.perf_counter() - t0:.1f} s")


def _cell_streams(mission: str, out: Path) -> None:
    t0 = time.perf_counter()
    config, source, _ = load_mission(None if mission == "default" else mission)
    with progress_bar() as progress:
        task = progress.add_task("load terrain", total=None, loss="")
        truth, elevation, prior, _ = mission_terrain(config, source)
        report = cell_stream_report(config, truth, elevation=elevation, prior=prior,
                                    on_stage=lambda s: progress.update(task, description=f"mission: {s}"))
    t = Table(title=f"bits per new cell, uplink stream of the {mission} mission ({source.label})",
              header_style="bold")
    for col in ("coder", "messages", "cells", "bytes", "bits/cell", "bits/map cell"):
        t.add_column(col, justify="left" if col == "coder" else "right")
    for r in report["rows"]:
        t.add_row(r["coder"], str(r["messages"]), f"{r['cells']:,}", f"{r['bytes']:,}", f"{r['bits_per_cell']:.3f}",
                  f"{r['bits_per_map_cell']:.3f}")
    console.print(t)
    console.print("bits/cell: per cell the messages carried; bits/map cell: per cell of the base's final map "
                  "(predictive does not resend cells a rover received, so it carries fewer)", soft_wrap=True)
    with AtomicDir(out) as tmp:
        (tmp / "cell_streams.json").write_text(json.dumps(report, indent=1))
        (tmp / "cell_streams.md").write_text(markdown(report, f"{mission} ({source.label})"))
    console.print(f"outputs: {out}/  (cell_streams.json, cell_streams.md); wall time {time.perf_counter() - t0:.1f} s")


def reproduce(
    data: Optional[Path] = typer.Option(None, help="Real terrain folder (e.g. ../shared/data); default: built-in terrains."),
    quick: bool = typer.Option(False, help="Smoke run: 64x64 maps, 40 local epochs, 30 routes, curve to R=3, no central bound or Table III."),
    size: Optional[int] = typer.Option(None, help="Map side in cells [128; quick: 64]."),
    pairs: Optional[int] = typer.Option(None, help="A* start/goal pairs per map [75; quick: 30]."),
    eta: float = typer.Option(1e-2, help="Server learning rate for FedAdam/FedYogi."),
    curve_epochs: Optional[int] = typer.Option(None, "--curve-epochs", help="Local epochs per round in the rounds curve [10]."),
    random_baseline: bool = typer.Option(False, "--random-baseline", help="Table II: also the paper's FedAvg from a random start."),
    seed: int = typer.Option(0, min=0),
    precision: str = typer.Option("auto", help="Training arithmetic: auto (bf16 where the CPU has native bf16, else fp32), bf16 or fp32."),
    out: Path = typer.Option(Path("fedmap-out/reproduce"), "--out", "-o", help="Report folder (replaced atomically)."),
) -> None:
    """The paper's experiments: Table II (+ fedmap), Fig. 4 panels, rounds curve, Tables I and III."""
    kw: dict[str, Any] = {k: v for k, v in {"data": data, "size": size, "pairs": pairs, "eta": eta, "seed": seed,
                            "curve_epochs": curve_epochs, "random_baseline": random_baseline,
                            "precision": precision}.items() if v is not None}
    config = ReproduceConfig.quick(**kw) if quick else ReproduceConfig(**kw)
    check_output_dir(out)
    t0 = time.perf_counter()
    with progress_bar() as progress:
        on_stage, on_step = stage_callbacks(progress)
        res = run_reproduce(out, config, on_stage=on_stage, on_step=on_step)
        on_stage(None, 0)
    for name, t in res["terrains"].items():
        table = Table(title=f"Table II — {name}", header_style="bold")
        table.add_column("configuration", overflow="fold")
        for col in ("PSNR", "SSIM", "P", "R", "F1", "paperF1", "paperF1\nu.p.", "B/rover/round"):
            table.add_column(col, justify="right", no_wrap=True)
        for r in t["table2"]:
            b = r["uplink_bytes_per_rover_round"]
            table.add_row(r["label"], fmt(r["psnr"]), fmt(r["ssim"], 3), fmt(r["precision"]), fmt(r["recall"]),
                          fmt(r["f1"]), fmt(r["f1_paper"]), fmt(r["f1_paper_unknown_passable"]),
                          "-" if b is None else f"{b:,.0f}")
        console.print(fit(table))
    console.print(F1_MEANINGS)
    console.print("Paper (Table II, FedAvg): " + "; ".join(f"{k} PSNR {v['psnr']} / SSIM {v['ssim']} / F1 {v['f1']}"
                                                           for k, v in PAPER_TABLE2.items()))
    console.print(f"outputs: {out}/  (report.md, reproduce.json, figures); wall time {time.perf_counter() - t0:.1f} s")
