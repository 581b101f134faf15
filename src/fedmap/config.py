"""The one way to build a run's configuration: presets, a TOML file, options -> PipelineConfig.

A run config has a top-level ``method`` (a preset, ``src/fedmap/presets/<name>.toml``)
and ``seed``, and one table per section of :class:`~fedmap.pipeline.PipelineConfig`::

    method = "paper"
    seed = 0
    [terrain]        # fedmap.maps.sources.TerrainSource (relative paths: relative to the TOML file)
    [terrain.options]  # reader options, e.g. pixel_size, nodata, shape, byteorder
    [thresholds]     # fedmap.maps.traversability.TraversabilityThresholds
    [explore]        # fedmap.explore.ExploreConfig
    [model]          # fedmap.nets.init.ModelConfig
    [train]          # fedmap.nets.training.TrainConfig
    [federation]     # fedmap.federation.runner.FederationConfig
    [refine]         # fedmap.refine.RefineConfig
    [evaluate]       # fedmap.evaluation.scores.EvaluateConfig

Each key of a table is a field of its class, declared once there with its type, default
and help (:mod:`fedmap._schema`); this module derives the checks, the defaults, the
``--set`` keys and the :func:`method_config` keywords from those fields and knows no
setting by name.

Resolution: library defaults < method preset < TOML file < options (:func:`resolve`). An
unknown section or key, or a value of the wrong type, is a
:class:`~fedmap.errors.FedmapError` naming the key and the file. :func:`to_pipeline_config`
builds the :class:`~fedmap.pipeline.PipelineConfig` (whose classes do the value checks)
and :func:`terrain_source` the :class:`~fedmap.maps.sources.TerrainSource`.
:func:`method_config` is the same path for Python callers: a method plus overrides.
Every command (``demo``, ``run``, ``mission``, ``reproduce``, ``bandwidth``,
``base-station``) builds its configuration here.
"""

from __future__ import annotations

import copy
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from fedmap import _schema
from fedmap._util import check_keys, suggest
from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.sources import READER_OPTIONS, TerrainSource, load_truth
from fedmap.maps.traversability import rover_profile
from fedmap.pipeline import MAX_SIDE, MIN_SIDE, PipelineConfig, preset_names

#: Section name -> its configuration class (derived from :class:`PipelineConfig`'s fields).
SECTIONS: dict[str, type] = _schema.sections(PipelineConfig)


def validate(data: dict, where: str) -> None:
    """Check sections, keys and value types of a (partial) run config (one-line errors
    naming the key and ``where``, with a suggestion for a typo)."""
    _schema.validate(PipelineConfig, data, where)
    options = data.get("terrain", {}).get("options", {})
    check_keys(options, READER_OPTIONS, f"[terrain.options] of {where}")
    for k, v in options.items():
        _schema.check_type(v, READER_OPTIONS[k], f"[terrain.options] {k} in {where}")


def path_settings() -> list[_schema.Setting]:
    """The settings that are file paths (relative ones are resolved against their TOML file)."""
    return [s for s in _schema.walk(PipelineConfig) if s.path]


#: Suffixes of the terrain files a command takes with --dem or --map, not as its TOML config.
TERRAIN_SUFFIXES = (".tif", ".tiff", ".png", ".npy", ".asc", ".img", ".cub", ".lbl", ".xml", ".jp2", ".nc", ".yaml",
                    ".yml", ".pgm", ".vrt")


def read_toml(path: str | Path, what: str = "config") -> dict:
    """A TOML file's tables; a missing, binary or unparsable file is a one-line error, and a
    terrain file given in its place (a common slip) says to pass it with --dem or --map."""
    path = Path(path)
    if not path.is_file():
        raise FedmapError(f"no such {what} file: {path}")
    looks_like_terrain = path.suffix.lower() in TERRAIN_SUFFIXES
    try:
        return tomllib.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark (Windows' Notepad) is not TOML
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        if looks_like_terrain or isinstance(exc, UnicodeDecodeError):
            raise FedmapError(f"{path} is not a TOML {what} (it looks like a terrain file): pass it with --dem "
                              "(a DEM) or --map (a class map)") from exc
        raise FedmapError(f"cannot read {what} {path}: {' '.join(str(exc).split())}") from exc


def load_toml(path) -> dict:
    """Read and validate a run config; relative terrain paths become relative to its folder."""
    path = Path(path)
    data = read_toml(path)
    if "mission" in data and "mission" not in SECTIONS:  # a mission file given to run
        raise FedmapError(f"{path.name} is a mission file ([mission]); run it with: fedmap mission {path}")
    validate(data, path.name)
    for s in path_settings():
        table = data.get(s.section, {})
        if s.name in table and not Path(table[s.name]).is_absolute():
            table[s.name] = str((path.parent / table[s.name]).resolve())
    return data


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
    """The library's defaults (the fields of :class:`PipelineConfig`'s sections) as a full
    run config, before any preset. ``[train] precision`` stays ``"auto"`` (a portable
    ``config.toml``); the built config holds the resolved value."""
    out = _schema.defaults(PipelineConfig)
    out["terrain"] = {}  # TerrainSource's own defaults apply: which keys it uses depends on its kind
    return out


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


def to_pipeline_config(resolved: dict, *, label: str = "") -> PipelineConfig:
    """The :class:`~fedmap.pipeline.PipelineConfig` of a resolved config (the sections'
    classes do the value checks). ``label`` names a file source in titles."""
    thresholds = _schema.build(SECTIONS["thresholds"], resolved["thresholds"])
    built = {name: _schema.build(cls, resolved[name]) for name, cls in SECTIONS.items()
             if name not in ("terrain", "thresholds")}
    terrain = _schema.build(SECTIONS["terrain"], resolved["terrain"], thresholds=thresholds)
    top = {s.name: resolved[s.name] for s in _schema.settings(PipelineConfig) if s.name in resolved}
    builtin = terrain.kind == "builtin"
    return PipelineConfig(**top, terrain=terrain, thresholds=thresholds, label="" if builtin else label, **built)


def keywords() -> dict[str, tuple[str | None, str]]:
    """:func:`method_config` keywords -> ``(section, key)`` (None: top level): every
    setting by its dotted key (``"train.lr"``) and, where no other section has a setting
    of that name, by its bare name (``lr``)."""
    every = list(_schema.walk(PipelineConfig))
    out: dict[str, tuple[str | None, str]] = {s.key: (s.section or None, s.name) for s in every}
    names = [s.name for s in every]
    for s in every:
        if names.count(s.name) == 1:
            out[s.name] = (s.section or None, s.name)
    return out


#: Every keyword of :func:`method_config` (see :func:`keywords`).
KEYWORDS: dict[str, tuple[str | None, str]] = keywords()


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

    ``settings`` are keywords of :data:`KEYWORDS`: any setting's name (``rounds``,
    ``epochs``, ``lr``, ``init``, ``aggregator``, ``uplink``, ``size``, ``seed``, ...) or
    dotted key (``**{"explore.mode": "strips"}``); None means "the preset's value". This
    is :func:`resolve` + :func:`to_pipeline_config` for Python callers, so
    ``method_config("paper")`` is exactly what ``fedmap demo`` and ``fedmap run`` run.
    """
    for s in path_settings():
        for k in (s.name, s.key):
            if settings.get(k) is not None:
                settings[k] = str(settings[k])
    return to_pipeline_config(resolve(None, [{"method": method}, overrides_from(settings)]))


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
    config = to_pipeline_config(resolved, label=source.label)  # a bad setting stops the run before any terrain work
    truth = load_truth(source, seed=resolved["seed"], elevation="elevation" in config.explore.layers)
    h, w = truth.shape
    if h != w or not MIN_SIDE <= h <= MAX_SIDE:
        raise FedmapError(f"the terrain map is {h}x{w} cells; the pipeline needs a square map of {MIN_SIDE}..{MAX_SIDE} "
                          f"cells: set [terrain] size (or --size)")
    resolved["thresholds"] = used_thresholds(resolved["thresholds"])
    return resolved, source, truth, config


def used_thresholds(thresholds: dict) -> dict:
    """``[thresholds]`` as written to ``config.toml``: a slope limit given as a percentile
    replaces the one in degrees, so only the setting that was used is kept."""
    if thresholds.get("max_slope_percentile") is not None:
        return {k: v for k, v in thresholds.items() if k != "max_slope_deg"}
    return thresholds


# --------------------------------------------------------------------------- writing TOML


def toml_value(v: Any) -> str:
    """One TOML value: a scalar, or a list of them."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def dumps_toml(data: dict) -> str:
    """TOML text of a config dict: scalars, lists and nested tables (no None values)."""
    lines: list[str] = []

    def table(d: dict, name: str) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and v is not None}
        if name:
            lines.append(f"\n[{name}]")
        lines.extend(f"{k} = {toml_value(v)}" for k, v in scalars.items())
        for k, v in d.items():
            if isinstance(v, dict):
                table(v, f"{name}.{k}" if name else k)

    table(data, "")
    return "\n".join(lines).lstrip("\n") + "\n"
