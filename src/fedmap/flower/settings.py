"""Run config (base station, ``[tool.flwr.app.config]``) and node config (one rover).

Flower passes both as flat ``{key: scalar}`` dicts with hyphenated keys. The run
config's run keys (:data:`RUN_KEYS`) are the flat form of fedmap's run config and go
through the one configuration builder (:mod:`fedmap.config`), so a Flower run and
``fedmap run`` with the same settings build the same :class:`~fedmap.pipeline.PipelineConfig`.
:data:`RUN_DEFAULTS` is the ``paper`` preset in that flat form plus the base station's
own keys; the app's ``pyproject.toml`` declares the same table (a test checks it).
This module does not import ``flwr``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fedmap.config import defaults, overrides_from, resolve, to_pipeline_config
from fedmap.errors import FedmapError
from fedmap.federation.runner import FederationConfig
from fedmap.maps.sources import DEFAULT_BUILTIN_SIZE
from fedmap.pipeline import PipelineConfig

#: Run-config key -> (section, key) of fedmap's run config.
RUN_KEYS: dict[str, tuple[str | None, str]] = {
    "rounds": ("federation", "rounds"), "aggregator": ("federation", "aggregator"), "eta": ("federation", "eta"),
    "epochs": ("train", "epochs"), "lr": ("train", "lr"), "masked": ("train", "masked"),
    "uplink": ("federation", "uplink"), "downlink": ("federation", "downlink"), "seed": (None, "seed"),
    "net": ("model", "net"), "init": ("model", "init"), "prior-steps": ("model", "prior_steps"),
    "size": ("terrain", "size"), "pairs": ("evaluate", "pairs"), "min-size": ("refine", "min_size"),
}

#: The base station's own keys with their defaults (``terrain`` / ``truth``: "" = none;
#: ``resume``: a checkpoint folder to continue from; ``keep-checkpoints``: rounds kept).
BASE_DEFAULTS: dict[str, Any] = {
    "rovers": 4, "min-rovers": 1, "deadline": 600.0, "connect-timeout": 120.0, "out": "fedmap-out/flower",
    "truth": "", "terrain": "", "resume": "", "keep-checkpoints": 3,
}


def flat_run_config(resolved: dict) -> dict[str, Any]:
    """The run keys of a resolved fedmap run config, as Flower's flat run config (a built-in
    terrain's side, when no ``[terrain] size`` is set, is the built-in default)."""
    terrain = {"size": DEFAULT_BUILTIN_SIZE, **resolved["terrain"]}
    return {key: resolved[name] if section is None else (terrain if section == "terrain" else resolved[section])[name]
            for key, (section, name) in RUN_KEYS.items()}


#: Every run-config key with its default: the ``paper`` preset, flattened.
RUN_DEFAULTS: dict[str, Any] = {**flat_run_config(defaults("paper")), **BASE_DEFAULTS}

_TYPES = {"eta": float, "lr": float, "deadline": float, "connect-timeout": float, "masked": bool,
          "aggregator": str, "uplink": str, "downlink": str, "net": str, "init": str, "out": str, "truth": str,
          "terrain": str, "resume": str}


def _typed(cfg: dict, key: str) -> Any:
    kind = _TYPES.get(key, int)
    value = cfg.get(key, RUN_DEFAULTS[key])
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

    pipeline: PipelineConfig  # built by fedmap.config, like every command's
    rovers: int
    min_rovers: int
    deadline: float
    connect_timeout: float
    out: Path
    truth: str  # a ground-truth map file, or ""
    terrain: str  # a built-in terrain generated as ground truth, or ""
    resume: str = ""  # a checkpoint folder this run continues from, or ""
    keep_checkpoints: int = 3  # per-round checkpoints kept in <out>.run/

    @property
    def federation(self) -> FederationConfig:
        return self.pipeline.federation

    @classmethod
    def from_run_config(cls, cfg: dict) -> RunSettings:
        unknown = sorted(set(cfg) - set(RUN_DEFAULTS))
        if unknown:
            raise FedmapError(f"unknown run-config keys {unknown}; known: {', '.join(RUN_DEFAULTS)}")
        values = {k: _typed(cfg, k) for k in RUN_DEFAULTS}
        run = overrides_from({k: values[k] for k in RUN_KEYS}, RUN_KEYS)
        terrain = values["terrain"]
        if terrain:
            run["terrain"] = {**run.get("terrain", {}), "terrain": terrain}
        resolved = resolve(None, [run])
        label = Path(values["truth"]).name if values["truth"] else ""
        s = cls(to_pipeline_config(resolved, label=label), values["rovers"], values["min-rovers"], values["deadline"],
                values["connect-timeout"], Path(values["out"]), values["truth"], terrain, values["resume"],
                values["keep-checkpoints"])
        if s.keep_checkpoints < 1:
            raise FedmapError(f"keep-checkpoints must be >= 1, got {s.keep_checkpoints}")
        if s.rovers < 1:
            raise FedmapError(f"rovers must be >= 1 (the team is partition ids 0..rovers-1), got {s.rovers}")
        if not 1 <= s.min_rovers <= s.rovers:
            raise FedmapError(f"need 1 <= min-rovers <= rovers, got min-rovers={s.min_rovers}, rovers={s.rovers}")
        if not (s.deadline > 0 and s.connect_timeout > 0):
            raise FedmapError(f"deadline and connect-timeout must be positive, got {s.deadline}, {s.connect_timeout}")
        if s.truth and s.terrain:
            raise FedmapError("give either truth (a map file) or terrain (a built-in generator), not both")
        return s

    def record(self) -> dict[str, Any]:
        """The base station's settings as ``metrics.json`` records them."""
        return {"rovers": self.rovers, "min_rovers": self.min_rovers, "deadline": self.deadline,
                "connect_timeout": self.connect_timeout, "out": str(self.out), "truth": self.truth,
                "terrain": self.terrain, "resume": self.resume, "keep_checkpoints": self.keep_checkpoints}


def run_config_from(resolved: dict, **base: Any) -> dict[str, Any]:
    """The full flat run config of a resolved fedmap run config plus base-station keys
    (``rovers``, ``min_rovers``, ``deadline``, ...; None = default)."""
    extra = {k.replace("_", "-"): v for k, v in base.items() if v is not None}
    unknown = sorted(set(extra) - set(BASE_DEFAULTS))
    if unknown:
        raise FedmapError(f"unknown base-station settings {unknown}; known: {', '.join(BASE_DEFAULTS)}")
    return {**flat_run_config(resolved), **BASE_DEFAULTS, **extra}
