"""``fedmap`` command line: wires the library's boxes together, nothing more.

User mistakes (bad files, bad options) print one line ``error: ...`` and exit 2.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import click
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from fedmap.errors import FedmapError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Federated multi-agent mapping for planetary exploration.",
)
console = Console()


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description:<26}"), BarColumn(bar_width=24), MofNCompleteColumn(), TextColumn("{task.fields[loss]}"),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True,
    )


def _stage_callbacks(progress: Progress):
    """``on_stage(name, total)`` closes the running bar and opens the next (``name=None``
    only closes); ``on_step(step, loss)`` advances the current bar."""
    current: dict = {"task": None}

    def on_stage(name: str | None, total: int) -> None:
        if current["task"] is not None:
            progress.update(current["task"], total=1, completed=1)
        current["task"] = progress.add_task(name, total=total or None, loss="") if name is not None else None

    def on_step(step: int, loss: float) -> None:
        progress.update(current["task"], advance=1, loss=f"loss {loss:.4f}")

    return on_stage, on_step


def _fmt(x, nd=2) -> str:
    if x is None:
        return "-"
    if isinstance(x, float) and x == float("inf"):
        return "inf"
    return f"{x:.{nd}f}"


def _scores_table(metrics: dict) -> Table:
    t = Table(title="maps vs ground truth", header_style="bold")
    for col in ("map", "PSNR", "SSIM", "acc.", "P", "R", "F1", "tol.F1"):
        t.add_column(col, justify="right" if col != "map" else "left", no_wrap=True)
    rows = [("federated", metrics["global"]), ("fed.+refined", metrics["refined"])]
    if "central" in metrics:
        rows.append(("central (bound)", metrics["central"]))
    rows += [(f"rover {a['agent'] + 1} alone", a) for a in metrics["agents"]]
    for name, m in rows:
        p = m["path"]
        t.add_row(name, _fmt(m["psnr"]), _fmt(m["ssim"], 3), _fmt(m["accuracy"], 3), _fmt(p["precision"]),
                  _fmt(p["recall"]), _fmt(p["f1"]), _fmt(p["tolerant"]["f1"]))
    return t


@app.command()
def demo(
    terrain: str = typer.Option("mars", help="Built-in terrain: mars, moon or ice."),
    size: int = typer.Option(128, help="Map side in cells (64..2048)."),
    agents: int = typer.Option(4, help="Number of rovers."),
    explore: str = typer.Option("quadrants", help="Exploration: quadrants, strips, grid or traverse."),
    method: str = typer.Option("paper", help="Preset: paper (Fourier MLP, FedAvg, fp32) or fedmap (feature grids, "
                               "coverage-aware FedAvg, masked loss, int4/int8 update payloads). Options below override it."),
    rounds: int = typer.Option(1, help="Communication rounds R."),
    local_epochs: int = typer.Option(100, "--local-epochs", help="Local epochs per round E."),
    lr: Optional[float] = typer.Option(None, help="Local Adam learning rate [paper 1e-3, fedmap 0.05]."),
    aggregator: Optional[str] = typer.Option(None, help="fedavg, fedadam, fedyogi or coverage (coverage-aware FedAvg)."),
    net: Optional[str] = typer.Option(None, help="Network: paper (Fourier MLP, 199,683 params), small, or grid (feature grids)."),
    central: bool = typer.Option(True, help="Also fit one network to the union of the local maps (the upper bound)."),
    uplink: Optional[str] = typer.Option(None, help="Rover -> base codec: fp32, fp16, bf16, int8, int4, topk:0.01, update-int4, ... (+zstd)."),
    downlink: Optional[str] = typer.Option(None, help="Base -> rover codec (same grammar)."),
    eta: float = typer.Option(1e-2, help="Server learning rate for fedadam/fedyogi."),
    init: Optional[str] = typer.Option(None, help="Initial weights: random, empty (empty-map prior) or meta "
                                       "(shipped meta-init) [paper net: meta; grid: random = zero grids]."),
    init_weights: Optional[Path] = typer.Option(None, "--init-weights", help="With --init meta: a weights file "
                                                "from fedmap meta-train instead of the shipped one."),
    masked: Optional[bool] = typer.Option(None, help="Loss on known cells only [paper: off, unknown is trained as grey; fedmap: on]."),
    min_size: int = typer.Option(0, "--min-size", help="Refinement: remove impassable blobs smaller than this many cells (paper: 200; 0 = off)."),
    pairs: int = typer.Option(75, help="Random start/goal pairs for the path F1."),
    seed: int = typer.Option(0, help="Seed for terrain, exploration, initialisation, training and evaluation."),
    out: Path = typer.Option(Path("fedmap-out/demo"), "--out", "-o", help="Output folder (replaced atomically)."),
) -> None:
    """Built-in terrain -> 4 rovers explore -> fit -> federate -> refine -> evaluate."""
    from fedmap.federation.runner import FederationConfig
    from fedmap.pipeline import PipelineConfig, run_pipeline, write_outputs
    from fedmap.refine import RefineConfig
    from fedmap.training import TrainConfig

    from fedmap.presets import method_settings

    chosen = method_settings(method, lr=lr, aggregator=aggregator, net=net, uplink=uplink, downlink=downlink,
                             masked=masked)
    lr, aggregator, net, uplink, downlink, masked = (chosen[k] for k in ("lr", "aggregator", "net", "uplink", "downlink", "masked"))
    if init is None:
        init = "meta" if net in ("paper",) or init_weights is not None else "random"
    t0 = time.perf_counter()
    config = PipelineConfig(
        terrain=terrain, size=size, agents=agents, explore=explore, init=init, seed=seed, eval_pairs=pairs,
        init_weights=str(init_weights) if init_weights is not None else None,
        net=net, central=central,
        federation=FederationConfig(rounds=rounds, aggregator=aggregator, eta=eta, seed=seed, uplink=uplink,
                                    downlink=downlink,
                                    local=TrainConfig(epochs=local_epochs, lr=lr, masked=masked)),
        refine=RefineConfig(min_size=min_size),
    )
    with _progress() as progress:
        on_stage, on_step = _stage_callbacks(progress)
        result = run_pipeline(config, on_stage=on_stage, on_step=on_step)
        on_stage("write outputs", 0)
        write_outputs(result, out)
        on_stage(None, 0)
    m = result.metrics
    console.print(_scores_table(m))
    console.print("PSNR in dB on RGB renderings; P/R/F1: A* path planning over "
                  f"{pairs} start/goal pairs (identical path = TP); tol.F1: paths within 5% of the true length")
    b = m["bytes"]
    console.print(f"link: {b['uplink']:,} B uplink ({uplink}), {b['downlink']:,} B downlink ({downlink}) in total; "
                  f"{b['uplink_per_agent_round']:,.0f} B per rover per round uplink")
    console.print(f"outputs: {out}/  (metrics.json, figure.png, global_model.safetensors, maps)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


@app.command()
def bandwidth(
    terrain: str = typer.Option("mars", help="Built-in terrain: mars, moon or ice."),
    size: int = typer.Option(128, help="Map side for the rate-distortion comparison (64..2048)."),
    pairs: int = typer.Option(75, help="Random start/goal pairs for the path F1."),
    seed: int = typer.Option(0),
    federated: bool = typer.Option(True, help="Also run fedmap's federated configurations on the same map."),
    out: Path = typer.Option(Path("fedmap-out/bandwidth"), "--out", "-o", help="Output folder (replaced atomically)."),
) -> None:
    """Table III with real bytes: model codecs vs raw, JPEG, WebP, PNG and zstd of the map."""
    from fedmap.bandwidth_report import bandwidth_report
    from fedmap.pipeline import PipelineConfig

    PipelineConfig(terrain=terrain, size=size, eval_pairs=pairs)  # validates before any work
    t0 = time.perf_counter()
    with _progress() as progress:
        on_stage, on_step = _stage_callbacks(progress)
        res = bandwidth_report(out, terrain=terrain, size=size, pairs=pairs, seed=seed, federated=federated,
                               on_stage=on_stage, on_step=on_step)
    t = Table(title=f"bytes vs quality, {terrain} {size}x{size}", header_style="bold")
    for col in ("payload", "bytes", "PSNR", "F1"):
        t.add_column(col, justify="left" if col == "payload" else "right", no_wrap=True)
    for r in res["image_codecs"]:
        t.add_row(r["codec"], f"{r['bytes']:,}", _fmt(r["psnr"]), _fmt(r["f1"]))
    for p in res["federated"]:
        t.add_row(f"fedmap: {p['label']}", f"{p['bytes']:,}", _fmt(p["psnr"]), _fmt(p["f1"]))
    console.print(t)
    fp16 = next(r for r in res["model_payloads"] if r["codec"] == "fp16")
    console.print(f"paper network in fp16: {fp16['bytes']:,} B (199,683 x 2 = 399,366 B of values + "
                  f"{fp16['bytes'] - 399_366} B header)")
    console.print(f"outputs: {out}/  (report.md, bandwidth.json, rd.png); wall time {time.perf_counter() - t0:.1f} s")


@app.command()
def reproduce(
    data: Optional[Path] = typer.Option(None, help="Real terrain folder (e.g. ../shared/data); default: built-in terrains."),
    quick: bool = typer.Option(False, help="Smoke run: 64x64 maps, 40 local epochs, 30 routes, curve to R=3, no central bound or Table III."),
    size: Optional[int] = typer.Option(None, help="Map side in cells [128; quick: 64]."),
    pairs: Optional[int] = typer.Option(None, help="A* start/goal pairs per map [75; quick: 30]."),
    eta: float = typer.Option(1e-2, help="Server learning rate for FedAdam/FedYogi."),
    curve_epochs: Optional[int] = typer.Option(None, "--curve-epochs", help="Local epochs per round in the rounds curve [10]."),
    random_baseline: bool = typer.Option(False, "--random-baseline", help="Table II: also the paper's FedAvg from a random start."),
    seed: int = typer.Option(0),
    out: Path = typer.Option(Path("fedmap-out/reproduce"), "--out", "-o", help="Report folder (replaced atomically)."),
) -> None:
    """The paper's experiments: Table II (+ fedmap), Fig. 4 panels, rounds curve, Tables I and III."""
    from fedmap.reproduce import ReproduceConfig, reproduce as run_reproduce

    kw = {k: v for k, v in {"data": data, "size": size, "pairs": pairs, "eta": eta, "seed": seed,
                            "curve_epochs": curve_epochs, "random_baseline": random_baseline}.items() if v is not None}
    config = ReproduceConfig.quick(**kw) if quick else ReproduceConfig(**kw)
    t0 = time.perf_counter()
    with _progress() as progress:
        on_stage, on_step = _stage_callbacks(progress)
        res = run_reproduce(out, config, on_stage=on_stage, on_step=on_step)
        on_stage(None, 0)
    for name, t in res["terrains"].items():
        table = Table(title=f"Table II — {name}", header_style="bold")
        table.add_column("configuration", overflow="fold")
        for col in ("PSNR", "SSIM", "P", "R", "F1", "B/rover/round"):
            table.add_column(col, justify="right", no_wrap=True)
        for r in t["table2"]:
            b = r["uplink_bytes_per_rover_round"]
            table.add_row(r["label"], _fmt(r["psnr"]), _fmt(r["ssim"], 3), _fmt(r["precision"]), _fmt(r["recall"]),
                          _fmt(r["f1"]), "-" if b is None else f"{b:,.0f}")
        console.print(table)
    console.print(f"outputs: {out}/  (report.md, reproduce.json, figures); wall time {time.perf_counter() - t0:.1f} s")


@app.command()
def terrain(
    kind: str = typer.Argument(..., help="mars, moon or ice."),
    out: Path = typer.Argument(..., help="Output map (.png or .npy)."),
    size: int = typer.Option(256, help="Map side in cells (64..2048)."),
    seed: int = typer.Option(0),
    dem_out: Optional[Path] = typer.Option(None, "--dem", help="Also save the DEM as .npy."),
) -> None:
    """Generate a built-in terrain's traversability map."""
    import numpy as np

    from fedmap.maps.io import atomic_write_bytes, save_map
    from fedmap.maps.terrain import generate_dem
    from fedmap.maps.traversability import dem_to_traversability

    dem = generate_dem(kind, size, seed=seed)
    grid = dem_to_traversability(dem)
    save_map(grid, out)
    if dem_out is not None:
        import io

        buf = io.BytesIO()
        np.save(buf, dem.elevation)
        atomic_write_bytes(dem_out, buf.getvalue())
    f = grid.fractions()
    console.print(f"{out}: {size}x{size} {kind}, {f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown")


@app.command()
def evaluate(
    learned: Path = typer.Argument(..., help="Learned map (.png or .npy)."),
    truth: Path = typer.Argument(..., help="Ground-truth map (.png or .npy)."),
    pairs: int = typer.Option(75, help="Random start/goal pairs."),
    seed: int = typer.Option(0),
    unknown_passable: bool = typer.Option(False, help="Let the planner cross UNKNOWN cells."),
) -> None:
    """PSNR, SSIM and A* path F1 of a map against ground truth."""
    import json

    from fedmap.evaluation.metrics import image_scores
    from fedmap.evaluation.planning import path_f1
    from fedmap.maps.io import load_map
    from fedmap.report import _clean

    a, b = load_map(learned), load_map(truth)
    if a.shape != b.shape:
        raise FedmapError(f"{learned} is {a.shape[0]}x{a.shape[1]} but {truth} is {b.shape[0]}x{b.shape[1]}")
    scores = image_scores(b.classes, a.classes)
    scores["path"] = path_f1(b.classes, a.classes, n_pairs=pairs, seed=seed, unknown_passable=unknown_passable)
    console.print_json(json.dumps(_clean(scores)))


# `fedmap run` lives in its own module (imported here, after the helpers it uses).
from fedmap.run_cli import run_command  # noqa: E402

app.command("run")(run_command)

# Real federation with Flower (optional extra): base-station, rover, certs.
from fedmap.federation.flower_cli import register as _register_flower  # noqa: E402

_register_flower(app, console, _progress)

# -- meta-initialisation (bodies in fedmap.meta_cli) --------------------------------------
from fedmap.meta_cli import ablate_init as _ablate_init, meta_train as _meta_train  # noqa: E402

app.command("meta-train")(_meta_train)
app.command("ablate-init")(_ablate_init)


def main(argv: list[str] | None = None) -> int:
    """Entry point: one-line errors, no tracebacks for user mistakes."""
    try:
        app(args=argv, standalone_mode=False)
    except FedmapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except click.UsageError as e:
        if isinstance(e, getattr(click.exceptions, "NoArgsIsHelpError", ())):
            return 0  # help was printed
        print(f"error: {e.format_message()}", file=sys.stderr)
        return 2
    except click.exceptions.Abort:
        print("error: aborted", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("error: interrupted; no partial output was written", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
