"""The end-to-end job: terrain -> local maps -> federation -> global map -> refine -> evaluate.

:func:`run_pipeline` computes everything in memory and returns a :class:`PipelineResult`;
:func:`write_outputs` writes it as one atomic folder. The CLI's ``demo`` only wires these.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import image_scores
from fedmap.evaluation.planning import path_f1
from fedmap.explore import explore
from fedmap.federation.runner import FederationConfig, FederationResult, run_federation, total_local_steps
from fedmap.maps.grid import UNKNOWN, GridMap, check_same_frame, classes_from_rgb
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability
from fedmap.meta.prior import empty_prior
from fedmap.meta.shipped import load_init_weights
from fedmap.model import NetConfig, build_model, get_weights, preset, render, set_weights
from fedmap.refine import RefineConfig, refine
from fedmap.training import TrainConfig, fit, steps_per_epoch

INITS = ("random", "empty", "meta")


@dataclass(frozen=True)
class PipelineConfig:
    terrain: str = "mars"
    size: int = 128
    agents: int = 4
    explore: str = "quadrants"
    overlap: int = 0
    sensor_radius: float = 12.0
    net: str = "paper"
    init: str = "random"
    init_weights: str | None = None  # init="meta": a weights file (default: the shipped meta-init)
    prior_steps: int = 150
    central: bool = True  # also fit one network to the union of the local maps (upper bound)
    federation: FederationConfig = field(default_factory=FederationConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    thresholds: TraversabilityThresholds = field(default_factory=TraversabilityThresholds)
    eval_pairs: int = 75
    unknown_passable: bool = False
    seed: int = 0
    label: str = ""  # the terrain's name in titles (a DEM file...); default: terrain

    def __post_init__(self) -> None:
        if self.init not in INITS:
            raise FedmapError(f"unknown init {self.init!r}; choose one of {', '.join(INITS)}")
        from fedmap.maps.terrain import TERRAIN_KINDS

        if self.terrain not in TERRAIN_KINDS:
            raise FedmapError(f"unknown terrain {self.terrain!r}; choose one of {', '.join(TERRAIN_KINDS)}")
        if isinstance(self.size, bool) or not isinstance(self.size, int) or not 64 <= self.size <= 2048:
            raise FedmapError(f"size must be an integer number of cells in [64, 2048], got {self.size}")
        if self.eval_pairs <= 0:
            raise FedmapError(f"eval pairs must be positive, got {self.eval_pairs}")
        preset(self.net)
        if self.init == "meta" and self.net == "grid":
            raise FedmapError("init 'meta' is for the Fourier networks (paper, small); a grid network starts at zero")
        if self.init_weights is not None and self.init != "meta":
            raise FedmapError(f"init weights are only used with init 'meta', not {self.init!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class PipelineResult:
    config: PipelineConfig
    truth: GridMap
    local_maps: list[GridMap]
    model: torch.nn.Module  # CoordNet or GridNet
    global_rgb: np.ndarray
    global_classes: np.ndarray
    refined: np.ndarray
    federation: FederationResult
    metrics: dict
    timings: dict


def initial_model(net_config: NetConfig, *, init: str, seed: int, prior_steps: int,
                  init_weights: str | Path | None = None) -> torch.nn.Module:
    """The model every rover starts round 1 from: seeded random weights, the empty-map
    prior, or meta-initialised weights (``init_weights``, default: the shipped ones).

    Deterministic, so rovers and the base station rebuild it alone and it never travels.
    """
    if init not in INITS:
        raise FedmapError(f"unknown init {init!r}; choose one of {', '.join(INITS)}")
    if init == "empty":
        return empty_prior(net_config, steps=prior_steps, seed=seed)
    model = build_model(net_config, seed=seed)
    if init == "meta":
        set_weights(model, load_init_weights(net_config, init_weights))
    return model


def global_map(net_config: NetConfig, weights: dict, shape: tuple[int, int],
               refine_config: RefineConfig) -> tuple[torch.nn.Module, np.ndarray, np.ndarray, np.ndarray]:
    """What every rover makes of the global weights: the model, its (H, W, 3) rendering,
    the rendering snapped to classes, and the refined classes."""
    model = build_model(net_config)
    set_weights(model, weights)
    rgb = render(model, *shape)
    classes = classes_from_rgb(rgb)
    return model, rgb, classes, refine(classes, refine_config)


def truth_summary(truth: GridMap) -> dict:
    """The ground truth as ``metrics.json`` describes it."""
    h, w = truth.shape
    return {"shape": [h, w], "pixel_size_m": truth.pixel_size, "source": truth.source, **truth.fractions()}


def union_map(local_maps: list[GridMap]) -> GridMap:
    """All agents' observations in one map: what the base would hold with raw maps."""
    out = np.full(local_maps[0].shape, UNKNOWN, dtype=np.uint8)
    for m in local_maps:
        out = np.where(m.known, m.classes, out)
    return local_maps[0].with_classes(out, "union of local maps")


def load_truth(config: PipelineConfig) -> GridMap:
    from fedmap.maps.terrain import generate_dem

    dem = generate_dem(config.terrain, config.size, seed=config.seed)
    return dem_to_traversability(dem, config.thresholds)


def evaluate(truth: GridMap, classes: np.ndarray, config: PipelineConfig) -> dict:
    scores = image_scores(truth.classes, classes)
    scores["path"] = path_f1(truth.classes, classes, n_pairs=config.eval_pairs, seed=config.seed,
                             unknown_passable=config.unknown_passable)
    return scores


def run_pipeline(
    config: PipelineConfig,
    *,
    truth: GridMap | None = None,
    local_maps: list[GridMap] | None = None,
    on_stage: Callable[[str, int], None] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    on_round: Callable[[dict, dict], None] | None = None,
    one_shot_cache: dict | None = None,
) -> PipelineResult:
    """Run the whole job. ``on_stage(name, total_steps)`` announces each stage;
    ``on_round(record, weights)`` and ``one_shot_cache`` are passed to
    :func:`~fedmap.federation.runner.run_federation`.

    ``truth`` replaces the built-in terrain and ``local_maps`` the exploration (e.g. a
    heterogeneous team made with :func:`fedmap.explore.explore`).
    """
    stage = on_stage or (lambda name, total: None)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    stage("terrain", 0)
    if truth is None:
        truth = load_truth(config)
    if local_maps is None:
        local_maps = explore(truth, config.agents, config.explore, seed=config.seed, overlap=config.overlap,
                             sensor_radius=config.sensor_radius)
    elif check_same_frame(local_maps) != truth.shape:
        raise FedmapError(f"local maps are {local_maps[0].shape}, the ground truth is {truth.shape}")
    timings["terrain_and_explore_s"] = time.perf_counter() - t

    net_config = preset(config.net, truth.shape[0])
    t = time.perf_counter()
    if config.init == "empty":
        stage("empty-map prior", config.prior_steps)
    elif config.init == "meta":
        stage("meta-init weights", 0)
    init_model = initial_model(net_config, init=config.init, seed=config.seed, prior_steps=config.prior_steps,
                               init_weights=config.init_weights)
    timings["init_s"] = time.perf_counter() - t

    t = time.perf_counter()
    stage("federated training", total_local_steps(local_maps, config.federation))
    fed = run_federation(get_weights(init_model), net_config, local_maps, config.federation, on_step=on_step,
                         on_round=on_round, one_shot_cache=one_shot_cache)
    timings["federation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    stage("render, refine, evaluate", 0)
    h, w = truth.shape
    model, global_rgb, global_classes, refined = global_map(net_config, fed.weights, (h, w), config.refine)
    metrics = {
        "global": evaluate(truth, global_classes, config),
        "refined": evaluate(truth, refined, config),
        "agents": [{"agent": k, "known_cells": m.n_known, **{kk: v for kk, v in evaluate(truth, m.classes, config).items()}}
                   for k, m in enumerate(local_maps)],
        "truth": truth_summary(truth),
        "aggregator": fed.aggregator,
        "bytes": fed.total_bytes(),
        "ledger": fed.ledger(),
        "rounds": fed.history,
    }
    timings["evaluate_s"] = time.perf_counter() - t
    if config.central:
        t = time.perf_counter()
        steps = config.federation.rounds * config.federation.local.epochs
        stage("centralised upper bound", steps * steps_per_epoch(truth.classes.size, config.federation.local))
        central = build_model(net_config)
        set_weights(central, get_weights(init_model))
        fit(central, union_map(local_maps), replace(config.federation.local, epochs=steps), seed=config.seed,
            on_step=on_step)
        central_classes = classes_from_rgb(render(central, h, w))
        metrics["central"] = {"steps": steps, **evaluate(truth, central_classes, config)}
        timings["central_s"] = time.perf_counter() - t
    return PipelineResult(config, truth, local_maps, model, global_rgb, global_classes, refined, fed, metrics, timings)


def write_outputs(result: PipelineResult, out_dir: str | Path, *, extra: dict[str, str] | None = None) -> Path:
    """Write metrics.json, config.json, the global model, maps and the Fig. 4 panel, atomically.

    ``extra`` maps further file names to text written into the same folder (e.g. the
    resolved run config).
    """
    from fedmap.maps.io import save_map
    from fedmap.model import save_model
    from fedmap.report import AtomicDir, fig4_panel, to_json

    out = Path(out_dir)
    with AtomicDir(out) as tmp:
        (tmp / "metrics.json").write_text(to_json({**result.metrics, "timings": result.timings}))
        (tmp / "config.json").write_text(to_json(result.config.to_dict()))
        for name, text in (extra or {}).items():
            (tmp / name).write_text(text)
        save_model(result.model, tmp / "global_model.safetensors", extra={"pipeline": result.config.to_dict()})
        save_map(result.truth, tmp / "truth.png")
        save_map(result.truth.with_classes(result.global_classes, "federated global map"), tmp / "global_map.png")
        save_map(result.truth.with_classes(result.refined, "refined global map"), tmp / "refined_map.png")
        for k, m in enumerate(result.local_maps):
            save_map(m, tmp / f"agent{k + 1}_local.png")
        m = result.metrics
        scores = {"federated global map": {"psnr": m["global"]["psnr"], "f1": m["global"]["path"]["f1"]},
                  "refined global map": {"psnr": m["refined"]["psnr"], "f1": m["refined"]["path"]["f1"]}}
        c = result.config
        init = "zero grids (empty-map prior)" if c.net == "grid" else f"init {c.init}"
        title = (f"{c.label or c.terrain} {c.size}x{c.size}, {c.agents} agents ({c.explore}), {c.net} net, {init}, "
                 f"{c.federation.aggregator} x {c.federation.rounds} round(s), {c.federation.local.epochs} local epochs")
        fig4_panel(result.local_maps, result.truth, result.global_classes, result.refined, tmp / "figure.png",
                   title=title, scores=scores)
    return out
