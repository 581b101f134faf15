"""``fedmap meta-train``, ``fedmap ablate-init`` and ``fedmap meta-coder``: meta-initialisation
(:mod:`fedmap.meta`)."""

from __future__ import annotations

import shlex
import time
from pathlib import Path
from typing import Optional

import click
import torch
import typer
from rich.table import Table

from fedmap import __version__
from fedmap._util import check_output_dir, check_output_file
from fedmap.cli.ui import console, progress_bar
from fedmap.errors import FedmapError
from fedmap.maps.traversability import TraversabilityThresholds
from fedmap.meta.ablation import AblationConfig, make_inits, pick_maps, run_ablation, write_ablation
from fedmap.meta.collections import BUILTIN_CATEGORIES, LAYOUTS, MapCollection, earth_like, load_collection
from fedmap.meta.reptile import MetaConfig
from fedmap.meta.reptile import meta_train as run_meta_train
from fedmap.nets.model import NetConfig, preset
from fedmap.nets.predictor import SHIPPED_PREDICTOR, PredictorTraining, count_parameters, train_predictor
from fedmap.training.coderprior import learn_coder_prior, prior_path, save_coder_prior
from fedmap.training.predictorprior import check_every, exploration_samples, save_shipped_predictor


def _collection(source: str, *, layout: str, size: int, per_category: int, categories: Optional[str],
                max_slope: Optional[float], seed: int) -> MapCollection:
    names = tuple(c.strip() for c in categories.split(",") if c.strip()) if categories else None
    if layout not in LAYOUTS:
        raise FedmapError(f"unknown collection layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    if source == "builtin" and layout != "maps":
        raise FedmapError(f"--layout {layout} is for a collection folder; the built-in collection has no layout")
    if source == "builtin":
        return earth_like(size=size, per_category=per_category, seed=seed, categories=names or BUILTIN_CATEGORIES)
    th = TraversabilityThresholds(max_slope_deg=max_slope) if max_slope is not None else None
    coll = load_collection(source, layout=layout, size=size, max_per_category=per_category, thresholds=th, seed=seed)
    return coll.subset(names) if names else coll


def _command_line() -> str:
    """The running command with every option spelled out (works under ``main(argv)`` too)."""
    ctx = click.get_current_context()
    parts = ["fedmap", ctx.info_name or ""]
    for p in ctx.command.params:
        v = ctx.params.get(p.name)
        if v is None:
            continue
        if isinstance(v, bool):
            flag = p.opts[0] if v else (p.secondary_opts[0] if p.secondary_opts else None)
            parts += [flag] if flag else []
        else:
            parts += [p.opts[0], str(v)]
    return shlex.join(parts)


def _threads(threads: int) -> None:
    if threads < 1:
        raise FedmapError(f"threads must be at least 1, got {threads}")
    torch.set_num_threads(threads)


def meta_train(
    collection: str = typer.Option("builtin", help="'builtin' (Earth-like generator) or a folder of maps."),
    layout: str = typer.Option("maps", help="Folder layout: maps, kitti, domars or dem (see fedmap.meta.collections)."),
    categories: Optional[str] = typer.Option(None, help="Comma-separated categories to use (default: all)."),
    per_category: int = typer.Option(32, "--per-category", help="Maps per category (generated, or a seeded subset)."),
    max_slope: Optional[float] = typer.Option(None, "--max-slope", help="dem layout: slope limit in degrees [15]."),
    size: int = typer.Option(64, help="Map side in cells for meta-training."),
    net: str = typer.Option("paper", help="Network preset: paper or small."),
    iterations: int = typer.Option(300, help="Reptile meta-iterations."),
    inner_steps: int = typer.Option(5, "--inner-steps", help="Adam steps per task (k)."),
    inner_lr: float = typer.Option(1e-3, "--inner-lr", help="Inner Adam learning rate."),
    meta_batch: int = typer.Option(4, "--meta-batch", help="Tasks per meta-iteration."),
    eps_start: float = typer.Option(1.0, "--eps-start", help="Meta step size at the first iteration."),
    eps_end: float = typer.Option(0.0, "--eps-end", help="Meta step size at the last iteration (linear)."),
    prior_steps: int = typer.Option(150, "--prior-steps", help="Adam steps of the empty-map prior theta_0."),
    holdout: int = typer.Option(2, help="Maps per category held out for validation."),
    val_every: int = typer.Option(25, "--val-every", help="Validation PSNR every this many iterations."),
    seed: int = typer.Option(0, min=0),
    precision: str = typer.Option("auto", help="Training arithmetic: auto (bf16 where the CPU has native bf16, else fp32), bf16 or fp32."),
    threads: int = typer.Option(2, help="torch CPU threads (with bf16, 2 threads are 1.6x faster than 1 on an idle 2-core CPU; use 1 on a busy one)."),
    out: Path = typer.Option(Path("fedmap-out/meta/meta_init.safetensors"), "--out", "-o",
                             help="Weights file; also the checkpoint (rewritten atomically)."),
    resume: bool = typer.Option(False, help="Continue from --out (same options)."),
) -> None:
    """Empty-map prior -> Reptile over a map collection (each category a task) -> meta-init weights."""
    _threads(threads)
    config = MetaConfig(iterations=iterations, inner_steps=inner_steps, inner_lr=inner_lr, meta_batch=meta_batch,
                        eps_start=eps_start, eps_end=eps_end, prior_steps=prior_steps, val_every=val_every, seed=seed,
                        precision=precision)
    net_config = preset(net)
    if net_config.encoding != "fourier":
        raise FedmapError("meta-training is for the Fourier networks (paper, small)")
    coll = _collection(collection, layout=layout, size=size, per_category=per_category, categories=categories,
                       max_slope=max_slope, seed=seed)
    train, val = coll.split(holdout=holdout, seed=seed)
    extra = {"command": _command_line(), "fedmap_version": __version__, "seed": seed,
             "collection": coll.summary(), "size": size, "validation_maps": len(val)}
    t0 = time.perf_counter()
    with progress_bar() as progress:
        task = progress.add_task("Reptile", total=iterations, loss="")
        last = {"val": None}

        def on_step(it: int, info: dict) -> None:
            if "val_psnr" in info:
                last["val"] = info["val_psnr"]
            val_txt = f"val {last['val']:.2f} dB" if last["val"] is not None else ""
            progress.update(task, completed=it, loss=f"eps {info['epsilon']:.3f} {val_txt}")

        result = run_meta_train(train, net_config, config, val_maps=val, checkpoint=out, resume=resume, extra=extra,
                     on_step=on_step)
    for h in result.history:
        if h["iteration"] in (0, result.iteration) or h is result.history[-1]:
            console.print(f"iteration {h['iteration']:>5}: validation PSNR after {config.val_steps} steps "
                          f"(lr {config.val_lr:g}) {h['val_psnr']:.2f} dB")
    console.print(f"{coll.name}: {coll.n_maps} maps in {len(coll.categories)} categories "
                  f"({', '.join(coll.categories)}); {len(val)} held out")
    console.print(f"weights: {out}  wall time {time.perf_counter() - t0:.1f} s")


def ablate_init(
    collection: str = typer.Option("builtin", help="Test maps: 'builtin' or a folder."),
    layout: str = typer.Option("maps", help="Folder layout: maps, kitti, domars or dem."),
    categories: Optional[str] = typer.Option(None, help="Comma-separated categories (default: all)."),
    maps: int = typer.Option(16, help="Number of test maps (seeded random choice)."),
    max_slope: Optional[float] = typer.Option(None, "--max-slope", help="dem layout: slope limit in degrees [15]."),
    size: int = typer.Option(64, help="Map side in cells."),
    steps: int = typer.Option(2, help="N: optimisation steps for the PSNR/SSIM columns."),
    lr: float = typer.Option(1e-4, help="Adam learning rate (paper: 1e-4)."),
    max_steps: int = typer.Option(150, "--max-steps", help="Cap for the steps-to-reach count."),
    init_weights: Optional[Path] = typer.Option(None, "--init-weights", help="Meta weights (default: the shipped ones)."),
    prior_steps: int = typer.Option(150, "--prior-steps", help="Adam steps of the empty-map prior."),
    seed: int = typer.Option(1, min=0, help="Seed for the test maps (builtin), the random init and the prior."),
    precision: str = typer.Option("auto", help="Training arithmetic: auto (bf16 where the CPU has native bf16, else fp32), bf16 or fp32."),
    threads: int = typer.Option(2, help="torch CPU threads."),
    out: Path = typer.Option(Path("fedmap-out/ablate-init"), "--out", "-o", help="Output folder (replaced atomically)."),
) -> None:
    """Table I: PSNR/SSIM after N steps from random, empty-map and meta inits, and steps to reach meta."""
    _threads(threads)
    config = AblationConfig(n_steps=steps, lr=lr, max_steps=max_steps, seed=seed, precision=precision)
    if maps < 1:
        raise FedmapError(f"need at least one test map, got {maps}")
    check_output_dir(out)
    coll = _collection(collection, layout=layout, size=size, per_category=maps, categories=categories,
                       max_slope=max_slope, seed=seed)
    test = pick_maps(coll.maps(), maps, seed=seed)
    t0 = time.perf_counter()
    with progress_bar() as progress:
        task = progress.add_task("empty-map prior", total=0, loss="")
        inits = make_inits(init_weights=init_weights, prior_steps=prior_steps, seed=seed, precision=config.precision)
        progress.update(task, description="fit test maps", total=len(test) * len(inits), completed=0)
        result = run_ablation(test, inits, _net(), config,
                              on_map=lambda i, name: progress.update(task, advance=1, loss=f"map {i + 1} {name}"))
        result["collection"] = coll.summary()
        result["init_weights"] = str(init_weights) if init_weights else "shipped"
        write_ablation(result, test[0], inits, config, out, title=f"{coll.name}, {len(test)} maps {size}x{size}")
    console.print(table_of(result))
    console.print(f"random needs {result['random_over_meta_steps']:.1f}x the steps of meta to reach meta's "
                  f"{steps}-step PSNR (capped runs count as {max_steps})")
    console.print(f"outputs: {out}/  (ablation.json, fig3.png, psnr_curve.png); wall time {time.perf_counter() - t0:.1f} s")


def _net() -> NetConfig:
    return preset("paper")


def table_of(result: dict) -> Table:
    n = result["config"]["n_steps"]
    t = Table(title=f"Table I: {result['n_maps']} maps, Adam lr {result['config']['lr']:g}", header_style="bold")
    for col in ("init", f"PSNR @{n}", f"SSIM @{n}", "PSNR @0", "steps to meta's PSNR", "capped"):
        t.add_column(col, justify="left" if col == "init" else "right", no_wrap=True)
    for name, r in result["table"].items():
        s = r["steps_to_meta"]
        t.add_row(name, f"{r['psnr']['mean']:.2f} ± {r['psnr']['std']:.2f}", f"{r['ssim']['mean']:.3f}",
                  f"{r['psnr_step0']['mean']:.2f}", f"{s['mean']:.2f} ± {s['std']:.2f}", f"{s['capped']}/{s['n']}")
    return t


#: The options of the offline learners (meta-coder, meta-predictor) that pick their maps.
_OFFLINE_COLLECTION = typer.Option("builtin", help="'builtin' (Earth-like generator) or a folder of maps; never a "
                                   "test site.")
_LAYOUT = typer.Option("maps", help="Folder layout: maps, kitti, domars or dem (see fedmap.meta.collections).")
_CATEGORIES = typer.Option(None, help="Comma-separated categories to use (default: all).")
_MAX_SLOPE = typer.Option(None, "--max-slope", help="dem layout: slope limit in degrees [15].")


def meta_coder(
    collection: str = _OFFLINE_COLLECTION,
    layout: str = _LAYOUT,
    categories: Optional[str] = _CATEGORIES,
    per_category: int = typer.Option(4, "--per-category", help="Maps per category (generated, or a seeded subset)."),
    max_slope: Optional[float] = _MAX_SLOPE,
    size: int = typer.Option(128, help="Map side in cells."),
    steps: int = typer.Option(150, help="Steps of the predictive mission run on every map."),
    seed: int = typer.Option(0, min=0),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Where to write the prior (default: the one "
                                       "the installed fedmap ships and reads)."),
) -> None:
    """Learn the predictive coder's initial state: a predictive mission on every map of a collection."""
    check_output_file(out if out is not None else prior_path())  # before the missions
    coll = _collection(collection, layout=layout, size=size, per_category=per_category, categories=categories,
                       max_slope=max_slope, seed=seed)
    t0 = time.perf_counter()
    with progress_bar() as progress:
        task = progress.add_task("missions", total=coll.n_maps, loss="")
        state = learn_coder_prior(coll, steps=steps, seed=seed,
                                  on_map=lambda done, total: progress.update(task, completed=done))
    path = save_coder_prior(state, out)
    console.print(f"{coll.name}: {coll.n_maps} maps in {len(coll.categories)} categories; "
                  f"{int(state.cells.sum()):,} cell counts, {int(state.moves.sum()):,} move counts")
    console.print(f"coder prior: {path}  wall time {time.perf_counter() - t0:.1f} s")


def meta_predictor(
    collection: str = _OFFLINE_COLLECTION,
    layout: str = _LAYOUT,
    categories: Optional[str] = _CATEGORIES,
    per_category: int = typer.Option(6, "--per-category", help="Maps per category (generated, or a seeded subset)."),
    max_slope: Optional[float] = _MAX_SLOPE,
    size: int = typer.Option(128, help="Map side in cells."),
    steps: int = typer.Option(150, help="Steps of the raw mission run on every map (its rovers' maps are the inputs)."),
    every: int = typer.Option(10, help="Keep every rover's map every this many steps."),
    train_steps: int = typer.Option(600, "--train-steps", help="Adam steps of the network."),
    batch: int = typer.Option(8, help="Maps per Adam step."),
    crop: int = typer.Option(96, help="Side of the random crop of every map, cells."),
    lr: float = typer.Option(2e-3, help="Adam learning rate (cosine-decayed to 5 %)."),
    seed: int = typer.Option(0, min=0),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Where to write the weights (default: the file "
                                       "the installed fedmap ships and reads)."),
) -> None:
    """Learn the map predictor: raw missions on a collection, then the network fitted to guess what the rovers' maps miss (one thread, deterministic: the same seed gives the same file)."""
    training = PredictorTraining(steps=train_steps, batch=batch, crop=crop, lr=lr, seed=seed)
    check_every(every, steps, ("--every", "--steps"))
    check_output_file(out if out is not None else SHIPPED_PREDICTOR)  # before the missions
    coll = _collection(collection, layout=layout, size=size, per_category=per_category, categories=categories,
                       max_slope=max_slope, seed=seed)
    t0 = time.perf_counter()
    with progress_bar() as progress:
        task = progress.add_task("missions", total=coll.n_maps, loss="")
        beliefs, truths = exploration_samples(coll, steps=steps, every=every, seed=seed,
                                              on_map=lambda done, total: progress.update(task, completed=done))
        progress.update(task, description="train", total=train_steps, completed=0)
        model = train_predictor(beliefs, truths, training=training,
                                on_step=lambda i, loss: progress.update(task, completed=i, loss=f"loss {loss:.3f}"))
    extra = {"command": _command_line(), "fedmap_version": __version__, "collection": coll.summary(),
             "samples": int(len(beliefs))}
    path = save_shipped_predictor(model, out, extra=extra)
    console.print(f"{coll.name}: {coll.n_maps} maps in {len(coll.categories)} categories; {len(beliefs):,} rover maps; "
                  f"{count_parameters(model):,} parameters")
    console.print(f"predictor: {path}  wall time {time.perf_counter() - t0:.1f} s")
