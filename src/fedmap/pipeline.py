"""The end-to-end job: terrain -> local maps -> federation -> global map -> refine -> evaluate.

:func:`run_pipeline` computes everything in memory and returns a :class:`PipelineResult`;
:func:`fedmap.outputs.write_outputs` writes it as one atomic folder. Build the
:class:`PipelineConfig` of a named method with :func:`fedmap.config.method_config` (or
from a TOML file with :func:`fedmap.config.resolve`); the CLI only wires these.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from fedmap.errors import FedmapError
from fedmap.evaluation.scores import MapScores, score_map
from fedmap.explore import explore
from fedmap.federation.runner import FederationConfig, FederationResult, run_federation, total_local_steps
from fedmap.maps.grid import GridMap, check_same_frame, classes_from_rgb
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.maps.terrain import TERRAIN_KINDS
from fedmap.maps.traversability import TraversabilityThresholds
from fedmap.nets.init import check_init, initial_model
from fedmap.nets.model import CoordNet, GridNet, build_model, get_weights, preset, render, set_weights
from fedmap.nets.training import fit, steps_per_epoch
from fedmap.refine import RefineConfig
from fedmap.stages import global_map, truth_summary, union_map


@dataclass(frozen=True)
class PipelineConfig:
    """Everything one run needs: terrain, team, network and its start, federation, refinement,
    scoring. Build it for a named method with :func:`fedmap.config.method_config`."""

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
        if self.terrain not in TERRAIN_KINDS:
            raise FedmapError(f"unknown terrain {self.terrain!r}; choose one of {', '.join(TERRAIN_KINDS)}")
        if isinstance(self.size, bool) or not isinstance(self.size, int) or not 64 <= self.size <= 2048:
            raise FedmapError(f"size must be an integer number of cells in [64, 2048], got {self.size}")
        if self.eval_pairs <= 0:
            raise FedmapError(f"eval pairs must be positive, got {self.eval_pairs}")
        preset(self.net)
        check_init(self.init, self.net)
        if self.init_weights is not None and self.init != "meta":
            raise FedmapError(f"init weights are only used with init 'meta', not {self.init!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    def score(self, truth: GridMap, classes: np.ndarray) -> MapScores:
        """``classes`` scored against ``truth`` with this run's pairs, seed and planner."""
        return score_map(truth.classes, classes, pairs=self.eval_pairs, seed=self.seed,
                         unknown_passable=self.unknown_passable)

    def terrain_source(self) -> TerrainSource:
        """The built-in terrain this config maps when no ``truth`` is given."""
        return TerrainSource(kind="builtin", terrain=self.terrain, size=self.size, thresholds=self.thresholds)


@dataclass
class PipelineResult:
    """Everything a run computed; :attr:`metrics` is its ``metrics.json`` (without timings)."""

    config: PipelineConfig
    truth: GridMap
    local_maps: list[GridMap]
    model: CoordNet | GridNet
    global_rgb: np.ndarray
    global_classes: np.ndarray
    refined: np.ndarray
    federation: FederationResult
    global_scores: MapScores
    refined_scores: MapScores
    agent_scores: list[MapScores]
    central_scores: MapScores | None = None
    central_steps: int | None = None
    timings: dict = field(default_factory=dict)
    central_classes: np.ndarray | None = None  # the centralised bound's class map

    @property
    def metrics(self) -> dict:
        fed = self.federation
        out = {
            "global": self.global_scores.to_dict(),
            "refined": self.refined_scores.to_dict(),
            "agents": [{"agent": k, "known_cells": m.n_known, **s.to_dict()}
                       for k, (m, s) in enumerate(zip(self.local_maps, self.agent_scores))],
            "truth": truth_summary(self.truth),
            "aggregator": fed.aggregator,
            "bytes": fed.total_bytes(),
            "ledger": fed.ledger(),
            "rounds": fed.history,
        }
        if self.central_scores is not None:
            out["central"] = {"steps": self.central_steps, **self.central_scores.to_dict()}
        return out


def run_pipeline(
    config: PipelineConfig,
    *,
    truth: GridMap | None = None,
    local_maps: list[GridMap] | None = None,
    on_stage: Callable[[str | None, int], None] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    on_round: Callable[[dict, dict], None] | None = None,
    one_shot_cache: dict | None = None,
) -> PipelineResult:
    """Run the whole job. ``on_stage(name, total_steps)`` announces each stage;
    ``on_round(record, weights)`` and ``one_shot_cache`` are passed to
    :func:`~fedmap.federation.runner.run_federation`.

    ``truth`` replaces the built-in terrain (e.g. a DEM loaded with
    :func:`fedmap.maps.sources.load_truth`) and ``local_maps`` the exploration (e.g. a
    heterogeneous team made with :func:`fedmap.explore.explore`).
    """
    stage = on_stage or (lambda name, total: None)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    stage("terrain", 0)
    if truth is None:
        truth = load_truth(config.terrain_source(), seed=config.seed)
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
                               init_weights=config.init_weights, precision=config.federation.local.precision)
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

    global_scores, refined_scores = config.score(truth, global_classes), config.score(truth, refined)
    agent_scores = [config.score(truth, m.classes) for m in local_maps]
    timings["evaluate_s"] = time.perf_counter() - t
    central_scores, steps, central_classes = None, None, None
    if config.central:
        t = time.perf_counter()
        steps = config.federation.rounds * config.federation.local.epochs
        stage("centralised upper bound", steps * steps_per_epoch(truth.classes.size, config.federation.local))
        central = build_model(net_config)
        set_weights(central, get_weights(init_model))
        fit(central, union_map(local_maps), replace(config.federation.local, epochs=steps), seed=config.seed,
            on_step=on_step)
        central_classes = classes_from_rgb(render(central, h, w))
        central_scores = config.score(truth, central_classes)
        timings["central_s"] = time.perf_counter() - t
    return PipelineResult(config, truth, local_maps, model, global_rgb, global_classes, refined, fed, global_scores,
                          refined_scores, agent_scores, central_scores, steps, timings, central_classes)
