"""Run config (base station, ``[tool.flwr.app.config]``) and node config (one rover).

Flower passes both as flat ``{key: scalar}`` dicts with hyphenated keys; this module
turns them into fedmap objects with one-line errors. It does not import ``flwr``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fedmap.errors import FedmapError
from fedmap.federation.runner import FederationConfig
from fedmap.maps.grid import GridMap
from fedmap.training import TrainConfig

#: Every run-config key with its default; the app's pyproject declares the same table.
RUN_DEFAULTS: dict[str, object] = {
    "rounds": 1, "aggregator": "fedavg", "eta": 1e-2, "epochs": 100, "lr": 1e-3, "masked": False,
    "uplink": "fp32", "downlink": "fp32", "seed": 0, "net": "paper", "init": "random", "prior-steps": 150,
    "rovers": 4, "min-rovers": 1, "deadline": 600.0, "connect-timeout": 120.0,
    "out": "fedmap-out/flower", "truth": "", "terrain": "", "size": 128, "pairs": 75, "min-size": 0,
}


def _typed(cfg: dict, key: str, kind: type):
    value = cfg.get(key, RUN_DEFAULTS.get(key))
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if kind is bool and isinstance(value, str) and value.lower() in ("true", "false"):
        value = value.lower() == "true"
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise FedmapError(f"config value {key}={value!r} must be {kind.__name__}")
    return value


@dataclass(frozen=True)
class RunSettings:
    """The base station's settings (from Flower's run config)."""

    federation: FederationConfig
    net: str
    init: str
    prior_steps: int
    rovers: int
    min_rovers: int
    deadline: float
    connect_timeout: float
    out: Path
    truth: str
    terrain: str
    size: int
    pairs: int
    min_size: int

    @classmethod
    def from_run_config(cls, cfg: dict) -> "RunSettings":
        unknown = sorted(set(cfg) - set(RUN_DEFAULTS))
        if unknown:
            raise FedmapError(f"unknown run-config keys {unknown}; known: {', '.join(RUN_DEFAULTS)}")
        local = TrainConfig(epochs=_typed(cfg, "epochs", int), lr=_typed(cfg, "lr", float), masked=_typed(cfg, "masked", bool))
        fed = FederationConfig(rounds=_typed(cfg, "rounds", int), aggregator=_typed(cfg, "aggregator", str),
                               eta=_typed(cfg, "eta", float), local=local, seed=_typed(cfg, "seed", int),
                               uplink=_typed(cfg, "uplink", str), downlink=_typed(cfg, "downlink", str))
        s = cls(fed, _typed(cfg, "net", str), _typed(cfg, "init", str), _typed(cfg, "prior-steps", int),
                _typed(cfg, "rovers", int), _typed(cfg, "min-rovers", int), _typed(cfg, "deadline", float),
                _typed(cfg, "connect-timeout", float), Path(_typed(cfg, "out", str)), _typed(cfg, "truth", str),
                _typed(cfg, "terrain", str), _typed(cfg, "size", int), _typed(cfg, "pairs", int), _typed(cfg, "min-size", int))
        if not 1 <= s.min_rovers <= s.rovers:
            raise FedmapError(f"need 1 <= min-rovers <= rovers, got min-rovers={s.min_rovers}, rovers={s.rovers}")
        if not (s.deadline > 0 and s.connect_timeout > 0):
            raise FedmapError(f"deadline and connect-timeout must be positive, got {s.deadline}, {s.connect_timeout}")
        return s


def load_truth(settings: RunSettings) -> GridMap | None:
    """The ground truth the base evaluates against: a map file, a built-in terrain, or None."""
    if settings.truth and settings.terrain:
        raise FedmapError("give either truth (a map file) or terrain (a built-in generator), not both")
    if settings.truth:
        from fedmap.maps.io import load_map

        return load_map(settings.truth)
    if settings.terrain:
        from fedmap.pipeline import PipelineConfig, load_truth as generated

        return generated(PipelineConfig(terrain=settings.terrain, size=settings.size, seed=settings.federation.seed))
    return None


def load_local_map(node_config: dict) -> tuple[int, GridMap]:
    """``(partition_id, local map)`` of one rover from its node config.

    ``partition-id`` is required. The map is ``map=<path to a PNG/npy map>``, or the
    built-in generator: ``terrain``, ``size``, ``agents``, ``explore``, ``seed`` give the
    same local maps as ``fedmap demo`` (rover ``partition-id`` takes the k-th of them).
    """
    if "partition-id" not in node_config:
        raise FedmapError("node config needs partition-id=<rover index>")
    pid = node_config["partition-id"]
    if isinstance(pid, bool) or not isinstance(pid, int) or pid < 0:
        raise FedmapError(f"partition-id must be an integer >= 0, got {pid!r}")
    if "map" in node_config:
        from fedmap.maps.io import load_map

        return pid, load_map(str(node_config["map"]))
    if "terrain" not in node_config:
        raise FedmapError("node config needs map=<path> or terrain=<mars|moon|ice> (with size, agents, explore, seed)")
    from fedmap.explore import explore
    from fedmap.pipeline import PipelineConfig, load_truth as generated

    agents = int(node_config.get("agents", 4))
    if pid >= agents:
        raise FedmapError(f"partition-id {pid} is not below agents={agents}")
    cfg = PipelineConfig(terrain=str(node_config["terrain"]), size=int(node_config.get("size", 128)),
                         agents=agents, explore=str(node_config.get("explore", "quadrants")),
                         seed=int(node_config.get("seed", 0)))
    truth = generated(cfg)
    maps = explore(truth, cfg.agents, cfg.explore, seed=cfg.seed, overlap=cfg.overlap, sensor_radius=cfg.sensor_radius)
    return pid, maps[pid]


def run_dir(out: Path) -> Path:
    """``<out>.run/``: the base station's status and per-round checkpoints while a run goes."""
    out = Path(out)
    return out.with_name(out.name + ".run")


def run_status_path(out: Path) -> Path:
    """``<out>.run/status.json``: ``{"state": "running" | "done" | "failed", ...}``."""
    return run_dir(out) / "status.json"
