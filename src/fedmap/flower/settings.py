"""Run config (base station, ``[tool.flwr.app.config]``) and node config (one rover).

Flower passes both as flat ``{key: scalar}`` dicts. The run config holds two kinds of key,
both derived from dataclass fields (:mod:`fedmap._schema`), never listed by hand:

- **run settings**: every one-value setting of :class:`~fedmap.pipeline.PipelineConfig`'s
  sections except ``[terrain]`` (the base station names its ground truth with its own
  keys), under its name with hyphens (``rounds``, ``lr``, ``prior-steps``, ``max-slope-deg``)
  and ``seed``. A setting that may be unset is ``""`` when unset (Flower has no null).
  They go through the one configuration builder (:mod:`fedmap.config`), so a Flower run
  and ``fedmap run`` with the same settings build the same
  :class:`~fedmap.pipeline.PipelineConfig`.
- **the base station's own keys**: the fields of :class:`BaseStation`, the same way.

:data:`RUN_DEFAULTS` is the ``paper`` preset in that flat form plus the base station's
defaults; the app's ``pyproject.toml`` declares the same table (a test checks it).
This module does not import ``flwr``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from fedmap import _schema
from fedmap.config import SECTIONS, defaults, resolve, to_pipeline_config, toml_value
from fedmap.errors import FedmapError
from fedmap.federation.runner import FederationConfig
from fedmap.maps.sources import DEFAULT_BUILTIN_SIZE
from fedmap.pipeline import PipelineConfig


@dataclass(frozen=True)
class BaseStation:
    """The base station's own settings (not part of a run config)."""

    rovers: int = _schema.setting(4, help="Rovers in the team (partition ids 0..rovers-1)")
    min_rovers: int = _schema.setting(1, help="Fewest rovers a round may aggregate; fewer ends the run")
    deadline: float = _schema.setting(600.0, help="Seconds a round waits for replies; late rovers are recorded as "
                                      "missing")
    first_deadline: float = _schema.setting(0.0, help="Seconds the first round this base station runs waits for "
                                            "replies: it also covers each rover's start-up (its SuperExec, the "
                                            "app's install, a ClientApp process), so it may be longer than a later "
                                            "round's (0: the deadline)")
    connect_timeout: float = _schema.setting(120.0, help="Seconds to wait for rovers to connect")
    out: str = _schema.setting("fedmap-out/flower", help="Output folder (replaced atomically)")
    truth: str = _schema.setting("", help="Ground-truth map file (.png or .npy) to evaluate against ('': none)",
                                 path=True)
    terrain: str = _schema.setting("", help="Ground truth from the built-in generator: mars, moon or ice ('': none)")
    size: int = _schema.setting(DEFAULT_BUILTIN_SIZE, help="Side of the generated ground truth, cells")
    resume: str = _schema.setting("", help="A checkpoint folder this run continues from ('': none)")
    keep_checkpoints: int = _schema.setting(3, help="Per-round checkpoints kept in OUT.run/")
    rover_nodes: str = _schema.setting("", help="Each registered key's node and its rover, 'node=rover,...' (set by "
                                       "the launcher: a node claiming another rover's number is refused; '': none)")

    def __post_init__(self) -> None:
        if self.keep_checkpoints < 1:
            raise FedmapError(f"keep-checkpoints must be >= 1, got {self.keep_checkpoints}")
        if self.rovers < 1:
            raise FedmapError(f"rovers must be >= 1 (the team is partition ids 0..rovers-1), got {self.rovers}")
        if not 1 <= self.min_rovers <= self.rovers:
            raise FedmapError(f"need 1 <= min-rovers <= rovers, got min-rovers={self.min_rovers}, rovers={self.rovers}")
        if not self.first_deadline >= 0:
            raise FedmapError(f"first-deadline must be >= 0 (0: the deadline), got {self.first_deadline}")
        if not (self.deadline > 0 and self.connect_timeout > 0):
            raise FedmapError(f"deadline and connect-timeout must be positive, got {self.deadline}, "
                              f"{self.connect_timeout}")
        if self.truth and self.terrain:
            raise FedmapError("give either truth (a map file) or terrain (a built-in generator), not both")


def flower_key(name: str) -> str:
    """A setting's run-config key: its name with hyphens (``prior_steps`` -> ``prior-steps``)."""
    return name.replace("_", "-")


def _run_settings() -> dict[str, _schema.Setting]:
    out = {flower_key(s.name): s for s in _schema.settings(PipelineConfig) if s.name == "seed"}
    for name, cls in SECTIONS.items():
        if name != "terrain":
            out.update({flower_key(s.name): s for s in _schema.settings(cls, name) if s.scalar})
    return out


#: Run-config key -> the run setting it sets.
RUN_KEYS: dict[str, _schema.Setting] = _run_settings()
#: Run-config key -> the base station's setting it sets.
BASE_KEYS: dict[str, _schema.Setting] = {flower_key(s.name): s for s in _schema.settings(BaseStation)}
if set(RUN_KEYS) & set(BASE_KEYS):  # a new setting must not take a base-station key's name
    raise RuntimeError(f"run-config keys used twice: {sorted(set(RUN_KEYS) & set(BASE_KEYS))}")


def flat_run_config(resolved: dict) -> dict[str, Any]:
    """The run settings of a resolved fedmap run config, as Flower's flat run config."""
    out: dict[str, Any] = {}
    for key, s in RUN_KEYS.items():
        value = (resolved if not s.section else resolved.get(s.section, {})).get(s.name)
        out[key] = "" if value is None else value
    return out


#: Every run-config key with its default: the ``paper`` preset, flattened, then the base station's.
RUN_DEFAULTS: dict[str, Any] = {**flat_run_config(defaults("paper")),
                                **{k: s.default for k, s in BASE_KEYS.items()}}


def _typed(key: str, s: _schema.Setting, value: Any) -> Any:
    """A run-config value as the setting's type (TOML ints for floats and CLI strings for
    bools are fine; ``""`` unsets an optional setting). None: unset."""
    if s.optional and value == "":
        return None
    if bool in s.types and isinstance(value, str) and value.lower() in ("true", "false"):
        value = value.lower() == "true"
    _schema.check_type(value, s.types, f"config value {key}")
    if float in s.types and int not in s.types and not isinstance(value, bool):
        value = float(value)
    return value


@dataclass(frozen=True)
class RunSettings:
    """The base station's settings (from Flower's run config)."""

    pipeline: PipelineConfig  # built by fedmap.config, like every command's
    base: BaseStation

    @property
    def federation(self) -> FederationConfig:
        return self.pipeline.federation

    @property
    def out(self) -> Path:
        return Path(self.base.out)

    @classmethod
    def from_run_config(cls, cfg: dict) -> RunSettings:
        unknown = sorted(set(cfg) - set(RUN_DEFAULTS))
        if unknown:
            known = sorted(RUN_DEFAULTS)
            raise FedmapError(f"unknown run-config key {unknown[0]!r}{_schema.suggest(unknown[0], known)}")
        values = {k: _typed(k, s, cfg.get(k, RUN_DEFAULTS[k])) for k, s in {**RUN_KEYS, **BASE_KEYS}.items()}
        base = BaseStation(**{s.name: values[k] for k, s in BASE_KEYS.items()})
        run: dict = {}
        for key, s in RUN_KEYS.items():
            # Flower passes every key; one at its default counts as unset, so that, as in
            # `fedmap run`, a rover profile's limits apply unless a limit is set beside it
            if values[key] is not None and values[key] != _typed(key, s, RUN_DEFAULTS[key]):
                if s.section:
                    run.setdefault(s.section, {})[s.name] = values[key]
                else:
                    run[s.name] = values[key]
        run["terrain"] = {"size": base.size, **({"terrain": base.terrain} if base.terrain else {})}
        label = Path(base.truth).name if base.truth else ""
        return cls(to_pipeline_config(resolve(None, [run]), label=label), base)

    def record(self) -> dict[str, Any]:
        """The base station's settings as ``metrics.json`` records them."""
        return asdict(self.base)


def run_config_from(resolved: dict, **base: Any) -> dict[str, Any]:
    """The full flat run config of a resolved fedmap run config plus base-station keys
    (``rovers``, ``min_rovers``, ``deadline``, ...; None = default)."""
    extra = {flower_key(k): v for k, v in base.items() if v is not None}
    unknown = sorted(set(extra) - set(BASE_KEYS))
    if unknown:
        raise FedmapError(f"unknown base-station settings {unknown}; known: {', '.join(BASE_KEYS)}")
    return {**flat_run_config(resolved), **{k: s.default for k, s in BASE_KEYS.items()}, **extra}


def app_config_toml() -> str:
    """The ``[tool.flwr.app.config]`` table the Flower app's ``pyproject.toml`` must declare
    (``flwr run`` accepts overrides of declared keys only): :data:`RUN_DEFAULTS`."""
    lines = ["[tool.flwr.app.config]", *(f"{k} = {toml_value(v)}" for k, v in RUN_DEFAULTS.items())]
    return "\n".join(lines) + "\n"


def write_app_config(path: Path) -> None:
    """Replace the ``[tool.flwr.app.config]`` table (the file's last) of the app's ``pyproject.toml``."""
    text = Path(path).read_text(encoding="utf-8")
    head = text[:text.index("[tool.flwr.app.config]")]
    Path(path).write_text(head + app_config_toml(), encoding="utf-8")


if __name__ == "__main__":  # python -m fedmap.flower.settings: regenerate the app's run-config table
    write_app_config(Path(__file__).resolve().parent / "snapshot" / "app" / "pyproject.toml")
