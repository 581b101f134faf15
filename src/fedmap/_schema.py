"""Settings declared once: a typed dataclass field is a setting's only description.

A configuration class is a dataclass; each of its settings is a field made with
:func:`setting`, which records, beside the default, a one-line help and (optionally) the
allowed values and a command-line spelling. Everything else about a setting is derived
from the field, by the functions here and by their callers:

- its TOML key is the field's name in its section (``[train] lr``), its ``--set`` key
  the dotted path (``train.lr``), its Flower run-config key the same dotted path;
- its accepted TOML types come from the field's annotation (:func:`toml_types`);
- its default is the field's default (:func:`defaults`), and the command-line help
  shows it.

Fields made with :func:`wiring` are not settings: the code that assembles a run fills
them (for example the seed a federation inherits from the run's top-level ``seed``).
A nested configuration (a field whose type is itself a configuration class) is a
section. Adding a setting is adding one :func:`setting` field; see the docs' "How to add
a setting".
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import types
import typing
from collections.abc import Callable, Iterator, Sequence
from dataclasses import MISSING, dataclass
from typing import Any

from fedmap._util import suggest
from fedmap.errors import FedmapError

_META = "fedmap"


def setting(default: Any = MISSING, *, help: str, choices: Sequence[str] | Callable[[], Sequence[str]] | None = None,
            cli: str | None = None, default_factory: Callable[[], Any] | Any = MISSING, path: bool = False) -> Any:
    """A dataclass field that is a user-facing setting.

    Parameters
    ----------
    default, default_factory
        As :func:`dataclasses.field`.
    help : str
        One line, without the default (it is added where the help is shown).
    choices : sequence of str, or a callable returning one, optional
        The allowed values of a string setting (shown in help; the class checks them).
    cli : str, optional
        The command-line spelling when it is not ``--<name-with-hyphens>`` (e.g.
        ``"--local-epochs"``, or ``"--stay-in-range/--roam"`` for a flag pair).
    path : bool
        The value is a file path: relative paths are resolved against the TOML file's
        folder (or the working directory, on the command line).
    """
    meta = {_META: {"help": help, "choices": choices, "cli": cli, "path": path}}
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def wiring(default: Any = MISSING, *, default_factory: Callable[[], Any] | Any = MISSING) -> Any:
    """A dataclass field that is not a setting: the run assembly fills it."""
    meta = {_META: None}
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


@dataclass(frozen=True)
class Setting:
    """One setting, as derived from its field."""

    section: str  # "" for a top-level setting
    name: str
    annotation: Any  # the resolved type hint
    default: Any
    help: str
    choices: tuple[str, ...] | None
    cli: str | None
    path: bool

    @property
    def key(self) -> str:
        """The dotted key (``train.lr``; ``seed`` at the top level)."""
        return f"{self.section}.{self.name}" if self.section else self.name

    @property
    def types(self) -> tuple[type, ...]:
        return toml_types(self.annotation)

    @property
    def optional(self) -> bool:
        """True when None (unset) is a valid value."""
        return type(None) in _union_args(self.annotation)

    @property
    def scalar(self) -> bool:
        """True for a bool, int, float or str setting (one command-line value)."""
        return all(t in (bool, int, float, str) for t in self.types)


def is_config(tp: Any) -> bool:
    """True when ``tp`` is a configuration class (a dataclass with at least one setting)."""
    return dataclasses.is_dataclass(tp) and isinstance(tp, type) and any(
        f.metadata.get(_META) for f in dataclasses.fields(tp))


def _union_args(tp: Any) -> tuple[Any, ...]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return typing.get_args(tp)
    return (tp,)


def toml_types(tp: Any) -> tuple[type, ...]:
    """The Python types (as :mod:`tomllib` returns them) a setting of type ``tp`` accepts."""
    out: list[type] = []
    for arg in _union_args(tp):
        origin = typing.get_origin(arg) or arg
        if arg is type(None):
            continue
        if origin is float:
            out += [int, float]
        elif origin in (tuple, list, Sequence):
            out.append(list)
        elif origin is dict:
            out.append(dict)
        elif origin in (int, str, bool):
            out.append(origin)
        else:
            raise TypeError(f"a setting cannot have type {arg!r}")
    return tuple(dict.fromkeys(out))


def _choices(meta: dict) -> tuple[str, ...] | None:
    c = meta["choices"]
    if c is None:
        return None
    return tuple(c() if callable(c) else c)


@functools.cache
def settings(cls: type, section: str = "") -> tuple[Setting, ...]:
    """The settings of one configuration class (its sections not included), in field order.
    Derived once per class (the CLI builds its options from them at every start-up)."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata.get(_META)
        if not meta or is_config(hints[f.name]):
            continue
        if f.default is not MISSING:
            default = f.default
        elif f.default_factory is not MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"setting {cls.__name__}.{f.name} has no default")
        out.append(Setting(section, f.name, hints[f.name], default, meta["help"], _choices(meta), meta["cli"],
                           meta["path"]))
    return tuple(out)


@functools.cache
def _sections(cls: type) -> tuple[tuple[str, type], ...]:
    hints = typing.get_type_hints(cls)
    return tuple((f.name, hints[f.name]) for f in dataclasses.fields(cls)
                 if f.metadata.get(_META) is not None and is_config(hints[f.name]))


def sections(cls: type) -> dict[str, type]:
    """``{section name: configuration class}`` of the fields of ``cls`` that are sections."""
    return dict(_sections(cls))


def walk(cls: type) -> Iterator[Setting]:
    """Every setting of a root configuration: its top-level settings, then each section's."""
    yield from settings(cls)
    for name, sub in sections(cls).items():
        yield from settings(sub, name)


def defaults(cls: type) -> dict[str, Any]:
    """The field defaults of a root configuration as a nested TOML-ready dict (unset
    optional settings left out; a new dict, the defaults' own objects not shared)."""
    out: dict[str, Any] = {s.name: s.default for s in settings(cls) if s.default is not None}
    for name, sub in sections(cls).items():
        out[name] = {s.name: to_toml(s.default) for s in settings(sub, name) if s.default is not None}
    return copy.deepcopy(out)


def to_toml(value: Any) -> Any:
    """A setting's value as TOML can hold it (tuples become lists)."""
    if isinstance(value, tuple):
        return [to_toml(v) for v in value]
    return value


_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", list: "a list",
               dict: "a table"}


def check_type(value: Any, types_: tuple[type, ...], what: str) -> None:
    """Raise a one-line :class:`FedmapError` unless ``value`` has one of ``types_``."""
    # bool is an int in Python, but `epochs = true` is a mistake.
    ok = isinstance(value, types_) and not (isinstance(value, bool) and bool not in types_)
    if isinstance(value, float) and not math.isfinite(value):
        if float in types_:
            raise FedmapError(f"{what} must be a finite number, got {value!r}")
        ok = False
    if not ok:
        want = " or ".join(dict.fromkeys(_TYPE_NAMES[t] for t in types_))
        raise FedmapError(f"{what} must be {want}, got {value!r}")


def check_table(cls: type, table: Any, where: str, *, section: str = "") -> None:
    """Check the keys and value types of one (partial) TOML table of ``cls``'s settings."""
    label = f"[{section}] of {where}" if section else where
    if not isinstance(table, dict):
        raise FedmapError(f"[{section}] in {where} must be a table, got {table!r}")
    known = {s.name: s for s in settings(cls, section)}
    for key, value in table.items():
        if key not in known:
            raise FedmapError(f"unknown key {key!r} in {label}{suggest(key, known)}")
        check_type(value, known[key].types, f"[{section}] {key} in {where}" if section else f"{key!r} in {where}")


def validate(cls: type, data: Any, where: str) -> None:
    """Check a (partial) nested config of the root class ``cls``: sections, keys, types."""
    if not isinstance(data, dict):
        raise FedmapError(f"{where} must be a table, got {data!r}")
    top = {s.name: s for s in settings(cls)}
    subs = sections(cls)
    for key, value in data.items():
        if key in top:
            check_type(value, top[key].types, f"{key!r} in {where}")
        elif key in subs:
            check_table(subs[key], value, where, section=key)
        else:
            raise FedmapError(f"unknown key {key!r} in {where}{suggest(key, [*top, *subs])}")


def build(cls: type, table: dict, **wired: Any) -> Any:
    """An instance of ``cls`` from a checked TOML table of its settings (lists become
    tuples where the field is a tuple) and ``wired`` non-setting or section fields.

    The class's own checks (``__post_init__``) then run on the values.
    """
    values: dict[str, Any] = {}
    for s in settings(cls):
        if s.name not in table:
            continue
        v = table[s.name]
        if isinstance(v, list) and any(typing.get_origin(a) is tuple for a in _union_args(s.annotation)):
            v = _to_tuple(v)
        if isinstance(v, int) and not isinstance(v, bool) and float in _union_args(s.annotation) \
                and int not in _union_args(s.annotation):
            v = float(v)
        values[s.name] = v
    return cls(**values, **wired)


def _to_tuple(v: Any) -> Any:
    return tuple(_to_tuple(x) for x in v) if isinstance(v, list) else v


def help_text(s: Setting, default: Any = MISSING) -> str:
    """The one-line help of a setting with its allowed values and default appended."""
    text = s.help.rstrip(".")
    if s.choices:
        text += f"; one of {', '.join(s.choices)}"
    d = s.default if default is MISSING else default
    if d in (None, "") and ("unset" in text or "'': none" in text):  # the help already says what unset means
        return text
    return f"{text} (default: {shown(d)})"


def shown(value: Any) -> str:
    """A setting's value as help text shows it (``on`` / ``off``, ``unset``, lists comma-separated)."""
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return ",".join(map(str, value))
    return str(value)
