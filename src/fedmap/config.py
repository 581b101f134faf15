"""The one way to build a run's configuration: presets, a TOML file, options -> PipelineConfig.

Layout (every key optional; defaults come from the ``method`` preset and the library's
config classes)::

    method = "paper"          # preset (src/fedmap/presets/<name>.toml): paper or fedmap
    seed = 0

    [terrain]                 # fedmap.maps.sources.TerrainSource
    kind = "dem"              # builtin | dem | map | tiles
    path = "gale.tif"         # relative paths are relative to the TOML file
    crop = 320                # centred square side, or [row0, row1, col0, col1]
    size = 128                # resample to size x size cells
    [terrain.options]         # reader options, e.g. pixel_size, nodata, shape, byteorder
    [thresholds]              # TraversabilityThresholds: max_slope_deg, max_step_m, ..., rover (a profile)
    [explore]                 # agents, mode, overlap, sensor_radius
    [model]                   # net, init (random | empty | meta), init_weights, prior_steps
    [train]                   # epochs, lr, masked, batch (cells per batch; 0 = full grid), precision
    [federation]              # rounds, aggregator, eta, beta1, beta2, tau, uplink, downlink
    [refine]                  # window, min_votes, iterations, min_size
    [evaluate]                # pairs, unknown_passable, central

Resolution: library defaults < method preset < TOML file < options (:func:`resolve`). An
unknown section or key, or a value of the wrong type, is a
:class:`~fedmap.errors.FedmapError` naming the key and the file. :func:`to_pipeline_config`
maps the result onto :class:`~fedmap.pipeline.PipelineConfig` (whose classes do the
value checks) and :func:`terrain_source` onto :class:`~fedmap.maps.sources.TerrainSource`.
:func:`method_config` is the same path for Python callers: a method plus overrides.
Every command (``demo``, ``run``, ``reproduce``, ``bandwidth``, ``base-station``) builds
its configuration here.
"""

from __future__ import annotations

import copy
import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from fedmap._util import check_keys, suggest
from fedmap.errors import FedmapError
from fedmap.federation.runner import FederationConfig
from fedmap.maps.grid import GridMap
from fedmap.maps.sources import DEFAULT_BUILTIN_SIZE, READER_OPTIONS, TerrainSource, load_truth
from fedmap.maps.traversability import TraversabilityThresholds, rover_profile
from fedmap.nets.training import TrainConfig
from fedmap.pipeline import PipelineConfig
from fedmap.refine import RefineConfig

_NUM = (int, float)

#: Section -> key -> accepted Python types (as tomllib returns them).
SCHEMA: dict[str, dict[str, tuple[type, ...]]] = {
    "terrain": {"kind": (str,), "path": (str,), "terrain": (str,), "lon": (int,), "lat": (int,), "tiles": (int,),
                "crop": (int, list), "size": (int,), "resample": (str,), "options": (dict,)},
    "thresholds": {"max_slope_deg": _NUM, "max_step_m": _NUM, "max_roughness_m": _NUM, "rover_scale_max_px": _NUM,
                   "step_window_m": _NUM, "footprint_m": _NUM, "max_slope_percentile": _NUM, "rover": (str,)},
    "explore": {"agents": (int,), "mode": (str,), "overlap": (int,), "sensor_radius": _NUM},
    "model": {"net": (str,), "init": (str,), "init_weights": (str,), "prior_steps": (int,)},
    "train": {"epochs": (int,), "lr": _NUM, "masked": (bool,), "batch": (int,), "precision": (str,)},
    "federation": {"rounds": (int,), "aggregator": (str,), "eta": _NUM, "beta1": _NUM, "beta2": _NUM, "tau": _NUM,
                   "uplink": (str,), "downlink": (str,)},
    "refine": {"window": (int,), "min_votes": (int,), "iterations": (int,), "min_size": (int,)},
    "evaluate": {"pairs": (int,), "unknown_passable": (bool,), "central": (bool,)},
}
TOP_LEVEL: dict[str, tuple[type, ...]] = {"method": (str,), "seed": (int,)}

_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", list: "a list",
               dict: "a table"}


def _check_type(value, types: tuple[type, ...], what: str) -> None:
    # bool is an int in Python, but `epochs = true` is a mistake.
    ok = isinstance(value, types) and not (isinstance(value, bool) and bool not in types)
    if isinstance(value, float) and not math.isfinite(value):
        ok = False
    if not ok:
        want = " or ".join(dict.fromkeys(_TYPE_NAMES[t] for t in types))
        raise FedmapError(f"{what} must be {want}, got {value!r}")


def validate(data: dict, where: str) -> None:
    """Check sections, keys and value types of a (partial) run config."""
    for key, value in data.items():
        if key in TOP_LEVEL:
            _check_type(value, TOP_LEVEL[key], f"{key!r} in {where}")
        elif key in SCHEMA:
            if not isinstance(value, dict):
                raise FedmapError(f"[{key}] in {where} must be a table, got {value!r}")
            check_keys(value, SCHEMA[key], f"[{key}] of {where}")
            for k, v in value.items():
                _check_type(v, SCHEMA[key][k], f"[{key}] {k} in {where}")
        else:
            raise FedmapError(f"unknown key {key!r} in {where}{suggest(key, [*TOP_LEVEL, *SCHEMA])}")
    options = data.get("terrain", {}).get("options", {})
    check_keys(options, READER_OPTIONS, f"[terrain.options] of {where}")
    for k, v in options.items():
        _check_type(v, READER_OPTIONS[k], f"[terrain.options] {k} in {where}")


def load_toml(path) -> dict:
    """Read and validate a run config; relative terrain paths become relative to its folder."""
    path = Path(path)
    if not path.is_file():
        raise FedmapError(f"no such config file: {path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FedmapError(f"cannot read config {path}: {' '.join(str(exc).split())}") from exc
    validate(data, path.name)
    for section, key in (("terrain", "path"), ("model", "init_weights")):
        table = data.get(section, {})
        if key in table and not Path(table[key]).is_absolute():
            table[key] = str((path.parent / table[key]).resolve())
    return data


def preset_names() -> tuple[str, ...]:
    """The presets shipped in ``fedmap/presets/``: ``("fedmap", "paper")``."""
    files = resources.files("fedmap.presets").iterdir()
    return tuple(sorted(f.name.removesuffix(".toml") for f in files if f.name.endswith(".toml")))


def load_preset(method: str) -> dict:
    """A preset's settings as a partial run config (validated like any TOML file)."""
    names = preset_names()
    if method not in names:
        raise FedmapError(f"unknown method {method!r}; choose one of {', '.join(names)}")
    text = resources.files("fedmap.presets").joinpath(f"{method}.toml").read_text(encoding="utf-8")
    data = tomllib.loads(text)
    validate(data, f"preset {method}")
    return data


def base_defaults() -> dict:
    """The library's defaults (its config classes) as a full run config, before any preset."""
    p, f, r = PipelineConfig(), FederationConfig(), RefineConfig()
    return {
        "method": "paper", "seed": 0,
        "terrain": {},  # TerrainSource's defaults: built-in mars, 128 cells
        "thresholds": TraversabilityThresholds().to_dict(),
        "explore": {"agents": p.agents, "mode": p.explore, "overlap": p.overlap, "sensor_radius": p.sensor_radius},
        "model": {"net": p.net, "init": p.init, "prior_steps": p.prior_steps},
        # precision stays "auto" here (portable config.toml); PipelineConfig holds the resolved value
        "train": {"epochs": f.local.epochs, "lr": f.local.lr, "masked": f.local.masked, "batch": 0, "precision": "auto"},
        "federation": {"rounds": f.rounds, "aggregator": f.aggregator, "eta": f.eta, "beta1": f.beta1,
                       "beta2": f.beta2, "tau": f.tau, "uplink": f.uplink, "downlink": f.downlink},
        "refine": r.to_dict(),
        "evaluate": {"pairs": p.eval_pairs, "unknown_passable": p.unknown_passable, "central": p.central},
    }


def defaults(method: str = "paper") -> dict:
    """The full run config of a method preset before any file or option."""
    return {**merge(base_defaults(), load_preset(method)), "method": method}


def merge(base: dict, update: dict) -> dict:
    """``base`` with ``update`` laid over it, tables merged key by key (a new dict)."""
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_set(assignment: str) -> dict:
    """``"train.lr=0.01"`` -> ``{"train": {"lr": 0.01}}`` (the value is read as TOML;
    a bare word is taken as a string)."""
    if "=" not in assignment:
        raise FedmapError(f"--set needs section.key=value, got {assignment!r}")
    dotted, raw = (s.strip() for s in assignment.split("=", 1))
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    keys = dotted.split(".")
    out: dict = {}
    node = out
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return out


#: [terrain] keys that describe the grid rather than the file; they survive a new source.
GRID_KEYS = ("crop", "size", "resample")


def with_rover_profile(thresholds: dict, layers: list[dict]) -> dict:
    """Resolved ``[thresholds]`` with its ``rover`` profile applied: the profile replaces the
    default limits, and limits set explicitly in any of ``layers`` (partial configs) win."""
    rover = thresholds.get("rover")
    if not rover:
        return thresholds
    explicit: dict = {}
    for layer in layers:
        explicit.update(layer.get("thresholds", {}))
    return {**rover_profile(rover).to_dict(), **explicit}


def resolve(config_path=None, overrides: list[dict] | None = None, *, terrain: dict | None = None) -> dict:
    """Preset defaults < TOML file < ``overrides`` (each a partial config, applied in order).

    When the file and the options say nothing of the init, ``init_weights`` means a
    meta-init from that file; otherwise the preset's ``init`` goes with the preset's
    ``net``, and a network swapped in starts from random weights.

    ``terrain`` (e.g. ``{"kind": "dem", "path": ...}`` from ``--dem``) replaces the file's
    terrain source: its keys except ``crop``, ``size`` and ``resample`` are dropped.
    """
    file_data = load_toml(config_path) if config_path is not None else {}
    overrides = list(overrides or [])
    if terrain is not None:
        kept = {k: v for k, v in file_data.get("terrain", {}).items() if k in GRID_KEYS}
        file_data["terrain"] = {**kept, **terrain}
    for o in overrides:
        validate(o, "the command-line options")
    method = file_data.get("method", "paper")
    for o in overrides:
        method = o.get("method", method)
    resolved = merge(defaults(method), file_data)
    for o in overrides:
        resolved = merge(resolved, o)
    resolved["method"] = method
    resolved["thresholds"] = with_rover_profile(resolved["thresholds"], [load_preset(method), file_data, *overrides])
    model = resolved["model"]
    if not any("init" in layer.get("model", {}) for layer in (file_data, *overrides)):
        # a weights file given without an init is a meta-init from that file; otherwise the
        # preset's init belongs to the preset's network: a network swapped in starts from
        # its seeded weights
        if model.get("init_weights"):
            model["init"] = "meta"
        elif model["net"] != load_preset(method).get("model", {}).get("net", model["net"]):
            model["init"] = "random"
    return resolved


def terrain_source(resolved: dict) -> TerrainSource:
    """The :class:`~fedmap.maps.sources.TerrainSource` of a resolved config."""
    return TerrainSource.from_dict({**resolved["terrain"], "thresholds": resolved["thresholds"]},
                                   where="[terrain]")


def to_pipeline_config(resolved: dict, *, size: int | None = None, label: str = "") -> PipelineConfig:
    """The :class:`~fedmap.pipeline.PipelineConfig` of a resolved config.

    ``size`` is the side of the map the run trains on (a loaded terrain's; default: the
    built-in terrain's ``[terrain] size``). ``label`` names a file source in titles.
    """
    e, m, t, f, ev = (resolved[k] for k in ("explore", "model", "train", "federation", "evaluate"))
    seed = resolved["seed"]
    local = TrainConfig(epochs=t["epochs"], lr=float(t["lr"]), masked=t["masked"], batch_pixels=t["batch"] or None,
                        precision=t["precision"])
    fed = FederationConfig(rounds=f["rounds"], aggregator=f["aggregator"], eta=float(f["eta"]), beta1=float(f["beta1"]),
                           beta2=float(f["beta2"]), tau=float(f["tau"]), local=local, seed=seed, uplink=f["uplink"],
                           downlink=f["downlink"])
    terrain = resolved["terrain"]
    builtin = terrain.get("kind", "builtin") == "builtin"
    if size is None:
        size = int(terrain.get("size", DEFAULT_BUILTIN_SIZE))
    return PipelineConfig(
        terrain=terrain.get("terrain", "mars") if builtin else "mars", label="" if builtin else label, size=size,
        agents=e["agents"], explore=e["mode"], overlap=e["overlap"], sensor_radius=float(e["sensor_radius"]),
        net=m["net"], init=m["init"], init_weights=m.get("init_weights"), prior_steps=m["prior_steps"],
        central=ev["central"], federation=fed, refine=RefineConfig(**resolved["refine"]),
        thresholds=TraversabilityThresholds(**resolved["thresholds"]), eval_pairs=ev["pairs"],
        unknown_passable=ev["unknown_passable"], seed=seed,
    )


#: ``method_config`` keyword -> (section, key) of the run config (None: top level).
KEYWORDS: dict[str, tuple[str | None, str]] = {
    "method": (None, "method"), "seed": (None, "seed"),
    "terrain": ("terrain", "terrain"), "size": ("terrain", "size"),
    "max_slope_deg": ("thresholds", "max_slope_deg"), "max_step_m": ("thresholds", "max_step_m"),
    "max_roughness_m": ("thresholds", "max_roughness_m"),
    "max_slope_percentile": ("thresholds", "max_slope_percentile"), "rover": ("thresholds", "rover"),
    "agents": ("explore", "agents"), "explore": ("explore", "mode"), "overlap": ("explore", "overlap"),
    "sensor_radius": ("explore", "sensor_radius"),
    "net": ("model", "net"), "init": ("model", "init"), "init_weights": ("model", "init_weights"),
    "prior_steps": ("model", "prior_steps"),
    "epochs": ("train", "epochs"), "lr": ("train", "lr"), "masked": ("train", "masked"), "batch": ("train", "batch"),
    "precision": ("train", "precision"),
    "rounds": ("federation", "rounds"), "aggregator": ("federation", "aggregator"), "eta": ("federation", "eta"),
    "beta1": ("federation", "beta1"), "beta2": ("federation", "beta2"), "tau": ("federation", "tau"),
    "uplink": ("federation", "uplink"), "downlink": ("federation", "downlink"),
    "min_size": ("refine", "min_size"), "eval_pairs": ("evaluate", "pairs"), "pairs": ("evaluate", "pairs"),
    "unknown_passable": ("evaluate", "unknown_passable"), "central": ("evaluate", "central"),
}


def overrides_from(values: dict[str, Any], keys: dict[str, tuple[str | None, str]] = KEYWORDS) -> dict:
    """A partial run config from flat ``{keyword: value}`` (None values are left out)."""
    out: dict = {}
    for name, value in values.items():
        if value is None:
            continue
        if name not in keys:
            raise FedmapError(f"unknown setting {name!r}{suggest(name, keys)}")
        section, key = keys[name]
        if section is None:
            out[key] = value
        else:
            out.setdefault(section, {})[key] = value
    return out


def method_config(method: str = "paper", **settings: Any) -> PipelineConfig:
    """The :class:`~fedmap.pipeline.PipelineConfig` of a preset with ``settings`` laid over it.

    ``settings`` are keywords of :data:`KEYWORDS` (``rounds``, ``epochs``, ``lr``, ``init``,
    ``aggregator``, ``uplink``, ``size``, ``seed``, ...); None means "the preset's value".
    This is :func:`resolve` + :func:`to_pipeline_config` for Python callers, so
    ``method_config("paper")`` is exactly what ``fedmap demo`` and ``fedmap run`` run.
    """
    if settings.get("init_weights") is not None:
        settings["init_weights"] = str(settings["init_weights"])
    return to_pipeline_config(resolve(None, [{"method": method}, overrides_from(settings)]))


#: Side limits of the map the pipeline trains on.
MIN_SIDE, MAX_SIDE = 64, 2048


def terrain_table(*, dem: str | Path | None = None, map_path: str | Path | None = None,
                  builtin: str | None = None) -> dict | None:
    """The ``[terrain]`` table that a DEM file, a class map or a built-in terrain put in
    place of a config file's (None when none is given; at most one may be)."""
    given = [(k, v) for k, v in (("dem", dem), ("map", map_path), ("builtin", builtin)) if v is not None]
    if len(given) > 1:
        raise FedmapError("give at most one of --dem, --map and --terrain")
    if not given:
        return None
    kind, value = given[0]
    return {"kind": kind, "terrain": value} if kind == "builtin" else {"kind": kind, "path": str(Path(value).resolve())}


def load_run(config_path: str | Path | None = None, overrides: list[dict] | None = None, *,
             terrain: dict | None = None) -> tuple[dict, TerrainSource, GridMap, PipelineConfig]:
    """Resolve a run and load its ground truth: ``(resolved, source, truth, pipeline config)``.

    The map must be square with a side in ``[MIN_SIDE, MAX_SIDE]`` (set ``[terrain] size``).
    """
    resolved = resolve(config_path, overrides, terrain=terrain)
    source = terrain_source(resolved)
    resolved["terrain"] = {k: v for k, v in source.to_dict().items() if k != "thresholds"}
    truth = load_truth(source, seed=resolved["seed"])
    h, w = truth.shape
    if h != w or not MIN_SIDE <= h <= MAX_SIDE:
        raise FedmapError(f"the terrain map is {h}x{w} cells; the pipeline needs a square map of {MIN_SIDE}..{MAX_SIDE} "
                          f"cells: set [terrain] size (or --size)")
    return resolved, source, truth, to_pipeline_config(resolved, size=h, label=source.label)


# --------------------------------------------------------------------------- writing TOML


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def dumps_toml(data: dict) -> str:
    """TOML text of a config dict: scalars, lists and nested tables (no None values)."""
    lines: list[str] = []

    def table(d: dict, name: str) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and v is not None}
        if name:
            lines.append(f"\n[{name}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in scalars.items())
        for k, v in d.items():
            if isinstance(v, dict):
                table(v, f"{name}.{k}" if name else k)

    table(data, "")
    return "\n".join(lines).lstrip("\n") + "\n"
