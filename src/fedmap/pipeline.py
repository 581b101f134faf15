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
from importlib import resources

import numpy as np

from fedmap._schema import setting, wiring
from fedmap.errors import FedmapError
from fedmap.evaluation.scores import EvaluateConfig, MapScores
from fedmap.explore import ExploreConfig
from fedmap.federation.heightfed import HEIGHT_CODEC, federate_heights
from fedmap.federation.runner import FederationConfig, FederationResult, RoundRecord, run_federation, total_local_steps
from fedmap.maps.dem import Dem
from fedmap.maps.grid import GridMap, check_same_frame, classes_from_rgb
from fedmap.maps.sources import TerrainSource, load_truth, needs_dem
from fedmap.maps.terrain import TERRAIN_KINDS
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, resolved_slope
from fedmap.nets.init import ModelConfig
from fedmap.nets.init import initial_model as build_initial_model
from fedmap.nets.model import CoordNet, GridNet, Weights, build_model, get_weights, render, set_weights
from fedmap.nets.training import TrainConfig, fit, release_freed_memory, steps_per_epoch
from fedmap.refine import RefineConfig
from fedmap.stages import global_map, truth_summary, union_map


def preset_names() -> tuple[str, ...]:
    """The presets shipped in ``fedmap/presets/`` (the values of ``method``): ``("fedmap", "paper")``."""
    files = resources.files("fedmap.presets").iterdir()
    return tuple(sorted(f.name.removesuffix(".toml") for f in files if f.name.endswith(".toml")))


@dataclass(frozen=True)
class PipelineConfig:
    """Everything one run needs, one section per step: terrain, traversability, exploration,
    network, local training, federation, refinement, scoring. Its settings are the run
    config's (TOML, ``--set``, the command-line options and the Flower run config are
    derived from these fields, :mod:`fedmap._schema`). Build it for a named method with
    :func:`fedmap.config.method_config`, or from a TOML file with :func:`fedmap.config.load_run`.
    """

    method: str = setting("paper", help="Preset (paper: the source paper's network and FedAvg from its meta-init; "
                          "fedmap: feature grids, coverage-aware FedAvg, int4/int8 update payloads); everything else "
                          "is laid over it", choices=preset_names)
    seed: int = setting(0, help="Seed of the terrain, exploration, initialisation, training and evaluation")
    terrain: TerrainSource = setting(default_factory=TerrainSource, help="What terrain is mapped")
    thresholds: TraversabilityThresholds = setting(default_factory=TraversabilityThresholds,
                                                   help="Rover limits: DEM -> traversability")
    explore: ExploreConfig = setting(default_factory=ExploreConfig, help="Who observes what")
    model: ModelConfig = setting(default_factory=ModelConfig, help="The network and its start")
    train: TrainConfig = setting(default_factory=TrainConfig, help="Local training")
    federation: FederationConfig = setting(default_factory=FederationConfig, help="Rounds, aggregation, payloads")
    refine: RefineConfig = setting(default_factory=RefineConfig, help="Gap filling and blob removal")
    evaluate: EvaluateConfig = setting(default_factory=EvaluateConfig, help="Scoring against the truth")
    label: str = wiring("")  # the terrain's name in titles (a DEM file...); default: the built-in terrain

    def __post_init__(self) -> None:
        # one source of truth: the federation trains with [train] and the run's seed, and the
        # terrain is classified with [thresholds]
        if self.federation.local != self.train or self.federation.seed != self.seed:
            object.__setattr__(self, "federation", replace(self.federation, local=self.train, seed=self.seed))
        if self.terrain.thresholds != self.thresholds:
            object.__setattr__(self, "terrain", replace(self.terrain, thresholds=self.thresholds))
        if self.terrain.kind == "builtin":
            if self.terrain.terrain not in TERRAIN_KINDS:
                raise FedmapError(f"unknown terrain kind {self.terrain.terrain!r}; choose one of {', '.join(TERRAIN_KINDS)}")
            size = self.terrain.size
            if isinstance(size, bool) or not isinstance(size, int) or not MIN_SIDE <= size <= MAX_SIDE:
                raise FedmapError(f"terrain size must be an integer in [{MIN_SIDE}, {MAX_SIDE}], got {size}")

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def title(self) -> str:
        """The terrain's name in titles."""
        return self.label or self.terrain.terrain

    def score(self, truth: GridMap, classes: np.ndarray) -> MapScores:
        """``classes`` scored against ``truth`` with this run's pairs, seed and planner."""
        return self.evaluate.score(truth.classes, classes, seed=self.seed)


#: Side limits of the map the pipeline trains on.
MIN_SIDE, MAX_SIDE = 64, 4096


# --------------------------------------------------------------------------- the run assembly


def build_local_maps(config: PipelineConfig, truth: GridMap) -> list[GridMap]:
    """The rovers' local maps of a one-shot run: the one place they are built (the
    pipeline and the Flower rovers call it)."""
    return config.explore.local_maps(truth, seed=config.seed)


def initial_model(config: PipelineConfig, side: int) -> CoordNet | GridNet:
    """The model every rover starts round 1 from, for a ``side x side`` map: the one place
    it is built (the pipeline, the Flower apps and the mission strategies call it)."""
    m = config.model
    return build_initial_model(m.network(side), init=m.init, seed=config.seed, prior_steps=m.prior_steps,
                               init_weights=m.init_weights, precision=config.train.precision)


def initial_weights(config: PipelineConfig, side: int) -> Weights:
    """The weights of :func:`initial_model`."""
    return get_weights(initial_model(config, side))


@dataclass
class PipelineResult:
    """Everything a run computed; :attr:`metrics` is its ``metrics.json`` (without timings).

    ``result.global_scores.path.f1`` is the federated map's strict path F1,
    ``result.federation.total_bytes().uplink`` the bytes every rover sent in all rounds.
    """

    config: PipelineConfig  #: the run's settings
    truth: GridMap  #: the ground truth
    local_maps: list[GridMap]  #: rover k's observations (UNKNOWN elsewhere), in the truth's frame
    model: CoordNet | GridNet  #: the final global model, as the rovers decoded it
    global_rgb: np.ndarray  #: (H, W, 3) in [0, 1]: the global model's rendering
    global_classes: np.ndarray  #: (H, W) classes of the rendering (nearest colour)
    refined: np.ndarray  #: (H, W) classes after gap filling and blob removal
    federation: FederationResult  #: rounds (typed records), the byte ledger, the aggregator
    global_scores: MapScores  #: the federated map against the truth
    refined_scores: MapScores  #: the refined map against the truth
    agent_scores: list[MapScores]  #: each rover's own map against the truth
    central_scores: MapScores | None = None  #: one network fitted to all the observations (the upper bound)
    central_steps: int | None = None  #: its training steps (rounds x local epochs)
    timings: dict = field(default_factory=dict)  #: stage -> seconds
    central_classes: np.ndarray | None = None  #: the centralised bound's class map
    #: with ``[explore] layers`` holding elevation: the federated heights' scores and bytes
    #: (:func:`fedmap.federation.heightfed.federate_heights`), else None
    elevation: dict | None = None

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
        if self.elevation is not None:
            out["elevation"] = self.elevation
        return out


def run_pipeline(
    config: PipelineConfig,
    *,
    truth: GridMap | None = None,
    local_maps: list[GridMap] | None = None,
    on_stage: Callable[[str | None, int], None] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    on_round: Callable[[RoundRecord, Weights], None] | None = None,
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
    heights = "elevation" in config.explore.layers
    if truth is None:
        truth = load_truth(config.terrain, seed=config.seed, elevation=heights)
    if heights and "elevation" not in truth.layers:
        raise needs_dem("an elevation layer")
    if local_maps is None:
        local_maps = build_local_maps(config, truth)
    elif check_same_frame(local_maps) != truth.shape:
        raise FedmapError(f"local maps are {local_maps[0].shape}, the ground truth is {truth.shape}")
    timings["terrain_and_explore_s"] = time.perf_counter() - t

    net_config = config.model.network(truth.shape[0])
    t = time.perf_counter()
    if config.model.init == "empty":
        stage("empty-map prior", config.model.prior_steps)
    elif config.model.init == "meta":
        stage("meta-init weights", 0)
    init_weights = initial_weights(config, truth.shape[0])
    timings["init_s"] = time.perf_counter() - t

    t = time.perf_counter()
    stage("federated training", total_local_steps(local_maps, config.federation))
    fed = run_federation(init_weights, net_config, local_maps, config.federation, on_step=on_step,
                         on_round=on_round, one_shot_cache=one_shot_cache)
    release_freed_memory()  # each stage's peak, not their sum (see release_freed_memory)
    timings["federation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    stage("render, refine, evaluate", 0)
    h, w = truth.shape
    model, global_rgb, global_classes, refined = global_map(net_config, fed.weights, (h, w), config.refine)

    global_scores, refined_scores = config.score(truth, global_classes), config.score(truth, refined)
    agent_scores = [config.score(truth, m.classes) for m in local_maps]
    release_freed_memory()
    timings["evaluate_s"] = time.perf_counter() - t
    central_scores, steps, central_classes = None, None, None
    if config.evaluate.central:
        t = time.perf_counter()
        steps = config.federation.rounds * config.train.epochs
        stage("centralised upper bound", steps * steps_per_epoch(truth.classes.size, config.train))
        central = build_model(net_config)
        set_weights(central, init_weights)
        fit(central, union_map(local_maps), replace(config.train, epochs=steps), seed=config.seed,
            on_step=on_step)
        central_classes = classes_from_rgb(render(central, h, w))
        del central
        central_scores = config.score(truth, central_classes)
        release_freed_memory()
        timings["central_s"] = time.perf_counter() - t
    elevation = None
    if "elevation" in config.explore.layers:
        t = time.perf_counter()
        stage("elevation: height grids", 0)
        elevation = _elevation(config, truth, local_maps)
        timings["elevation_s"] = time.perf_counter() - t
    return PipelineResult(config, truth, local_maps, model, global_rgb, global_classes, refined, fed, global_scores,
                          refined_scores, agent_scores, central_scores, steps, timings, central_classes, elevation)


def _elevation(config: PipelineConfig, truth: GridMap, local_maps: list[GridMap]) -> dict:
    """Federate the rovers' heights and score them: RMSE and max error, the bytes both ways
    (and a lossless 1 cm share's, for comparison), and the path F1 of the classes re-derived
    from the federated heights with the run's thresholds."""
    hf = federate_heights(local_maps, seed=config.seed)
    z = truth.layer("elevation").astype(np.float64)  # run_pipeline checked it is there before any work
    observed = np.any([m.known for m in local_maps], axis=0)
    # a percentile slope limit is the truth's, in degrees: not re-taken on the federated heights
    limits = resolved_slope(config.thresholds, truth)
    derived = dem_to_traversability(Dem(hf.heights.astype(np.float32), truth.pixel_size), limits).classes
    return {"method": "height grid", "resolutions": list(hf.resolutions), "codec": HEIGHT_CODEC,
            **hf.scores(z, observed), "bytes": {"uplink": hf.uplink_bytes, "downlink": hf.downlink_bytes,
                                                "lossless_1cm_uplink": hf.reference_bytes},
            "rederived_classes": config.score(truth, derived).to_dict()}
