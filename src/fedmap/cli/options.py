"""Command-line options derived from the settings' dataclass fields (:mod:`fedmap._schema`).

A command declares which configuration classes it exposes; :func:`with_settings` adds one
typer option per one-value setting (``--lr``, ``--masked/--no-masked``, ``--strategies``
as a comma-separated list), with the setting's help (escaped for rich, so a ``[section]`` in
it is shown as written), allowed values and default, and
hands the command a partial config ``{section: {key: value}}`` of the options given.
Nothing here names a setting: a new field appears on the command line by itself.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Optional

import typer
from rich.markup import escape

from fedmap import _schema
from fedmap.config import defaults, merge, preset_names, terrain_table
from fedmap.maps.traversability import parse_slope_limit

_PREFIX = "setting__"  # parameter names of generated options: setting__<section>__<name>


def _kind(s: _schema.Setting) -> type | None:
    """The option's Python type, or None when the setting takes no single option value."""
    if s.scalar:
        for t in (bool, str, float, int):
            if t in s.types:
                return t
    if s.types == (list,) and s.choices:  # a list of names: comma-separated
        return str
    return None


def _decls(s: _schema.Setting, kind: type) -> list[str]:
    flag = s.cli or f"--{s.name.replace('_', '-')}"
    if kind is bool and "/" not in flag:
        flag = f"{flag}/--no-{flag.removeprefix('--')}"
    return [flag]


def _preset_default(s: _schema.Setting, presets: dict[str, dict]) -> Any:
    """The default a run sees: the library's, or ``paper: x; fedmap: y`` when the
    ``presets`` (name -> resolved defaults) differ."""
    if not s.section:
        return s.default
    by = {m: table.get(s.section, {}).get(s.name, s.default) for m, table in presets.items()}
    if len({repr(v) for v in by.values()}) == 1:
        return next(iter(by.values()))
    return "; ".join(f"{m}: {_schema.shown(v)}" for m, v in by.items())


def _option(name: str, kind: type, decl: str, help_: str) -> inspect.Parameter:
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=typer.Option(None, decl, help=escape(help_)),
                             annotation=Optional[kind])  # noqa: UP045  (typer reads Optional)


#: Terrain and threshold shortcuts shared by ``run`` and ``mission`` (beside the generated
#: ``[terrain]`` and ``[thresholds]`` options; an option here wins a generated one's name).
TERRAIN_SHORTCUTS: list[inspect.Parameter] = [
    _option("dem", Path, "--dem", "A DEM file instead of the config's terrain: any raster GDAL reads (GeoTIFF, ISIS3 "
            ".cub, PDS3 .lbl, PDS4 .xml, .asc, ...), a .png heightmap or .npy."),
    _option("map_path", Path, "--map", "A traversability class map instead of the config's terrain (.png, .npy, .tif "
            "GeoTIFF or ROS .yaml)."),
    _option("builtin", str, "--terrain", "A built-in terrain instead of the config's: mars, moon or ice."),
    _option("pixel_size", float, "--pixel-size", "Metres per cell of the file (overrides the file's)."),
    _option("crop", int, "--crop", "Centred square crop of the terrain, in cells, before resampling."),
    _option("max_slope", str, "--max-slope", "Traversability: max slope in degrees (e.g. 20), or a percentile of the "
            "map's own slopes (e.g. p75) for coarse DEMs."),
]
#: The flags of :data:`TERRAIN_SHORTCUTS`.
SHORTCUT_FLAGS = frozenset(p.default.param_decls[0] for p in TERRAIN_SHORTCUTS)


def _panel(s: _schema.Setting) -> str:
    return f"Settings of \\[{s.section}]" if s.section else "Settings"


#: Generated options whose setting is a list: their comma-separated value is split.
_LISTS: set[str] = set()


def parameters(settings: Iterable[_schema.Setting], *, presets: bool = False,
               skip: Iterable[str] = ()) -> list[inspect.Parameter]:
    """One keyword parameter (a typer option) per setting that takes one value, but for
    those whose flag is in ``skip`` (e.g. :data:`SHORTCUT_FLAGS`, which a shortcut has)."""
    skip = set(skip)
    preset_defaults = {m: defaults(m) for m in preset_names()} if presets else {}  # once, not per option
    out = []
    for s in settings:
        kind = _kind(s)
        if kind is None or _decls(s, kind)[0].split("/")[0] in skip:
            continue
        default = _preset_default(s, preset_defaults) if presets else s.default
        help_ = _schema.help_text(s, default)
        if s.path:
            kind = Path
        # typer reads help as rich markup: escaped, a "[helicopter]" in it is shown, not eaten as a style
        option = typer.Option(None, *_decls(s, kind), help=escape(help_ + "."), rich_help_panel=_panel(s))
        name = f"{_PREFIX}{s.section}__{s.name}"
        if s.types == (list,):
            _LISTS.add(name)
        out.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option,
                                     annotation=Optional[kind]))  # noqa: UP045  (typer reads Optional)
    return out


def shortcut_settings(dem: Path | None = None, map_path: Path | None = None, builtin: str | None = None,
                      pixel_size: float | None = None, crop: int | None = None,
                      max_slope: str | None = None) -> tuple[dict | None, dict]:
    """The :data:`TERRAIN_SHORTCUTS` as ``(terrain table replacing the config's or None,
    partial config)``."""
    partial: dict[str, Any] = {}
    if max_slope is not None:
        partial["thresholds"] = parse_slope_limit(max_slope)
    if pixel_size is not None:
        partial["terrain"] = {"options": {"pixel_size": pixel_size}}
    if crop is not None:
        partial = merge(partial, {"terrain": {"crop": crop}})
    return terrain_table(dem=dem, map_path=map_path, builtin=builtin), partial


def with_settings(params: list[inspect.Parameter], *, terrain: bool = False
                  ) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Add the generated ``params`` to a command; it receives ``settings``: the partial
    config of the options given (``{"train": {"lr": 0.01}, "seed": 3}``). With
    ``terrain``, the command also has the :data:`TERRAIN_SHORTCUTS` and receives
    ``terrain``: the terrain table they put in place of the config's (or None)."""
    params = [*(TERRAIN_SHORTCUTS if terrain else []), *params]

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        sig = inspect.signature(func, eval_str=True)
        own = [p for n, p in sig.parameters.items() if n not in ("settings", "terrain")]

        @functools.wraps(func)
        def command(**kwargs: Any) -> Any:
            settings: dict[str, Any] = {}
            if terrain:
                table, settings = shortcut_settings(**{p.name: kwargs.pop(p.name) for p in TERRAIN_SHORTCUTS})
                kwargs["terrain"] = table
            for p in params:
                if not p.name.startswith(_PREFIX):
                    continue
                value = kwargs.pop(p.name)
                if value is None:
                    continue
                section, name = p.name.removeprefix(_PREFIX).split("__", 1)
                if isinstance(value, Path):
                    value = str(value.resolve())
                if p.name in _LISTS and isinstance(value, str):  # "classes,elevation"
                    value = [v.strip() for v in value.split(",") if v.strip()]
                settings = merge(settings, {section: {name: value}} if section else {name: value})
            return func(**kwargs, settings=settings)

        command.__signature__ = sig.replace(parameters=[*own, *params])  # type: ignore[attr-defined]
        command.__annotations__ = {p.name: p.annotation for p in [*own, *params]}
        return command

    return deco
