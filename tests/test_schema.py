"""One schema: every setting is one dataclass field, reachable the same way from TOML,
``--set``, Python keywords, the command line and the Flower run config, with one default.

The values tried are derived from each field's type, default and allowed values (no
setting is named here), so a new field is walked without editing this file.
"""

from __future__ import annotations

import dataclasses

import click
import pytest
import typer

from fedmap import _schema
from fedmap.cli import app
from fedmap.config import KEYWORDS, base_defaults, defaults, method_config, parse_set, resolve, to_pipeline_config
from fedmap.errors import FedmapError
from fedmap.flower.settings import BASE_KEYS, RUN_DEFAULTS, RUN_KEYS, RunSettings, flower_key
from fedmap.mission.settings import MISSION_SECTIONS, load_mission
from fedmap.pipeline import PipelineConfig

RUN_SETTINGS = list(_schema.walk(PipelineConfig))


def _candidates(s: _schema.Setting) -> list:
    """Values other than the default, by type; the first the classes accept is used."""
    d, types = s.default, s.types
    if s.choices and str in types:
        return [c for c in s.choices if c != d]
    if s.choices and list in types:
        return [[c] for c in s.choices if [c] != list(d)]
    if bool in types:
        return [not d]
    if int in types and float not in types:
        base = [d + 1, d + 2, d + 40] if isinstance(d, int) else []
        return [*base, 2, 3, 64]
    if float in types:
        base = [d * 0.5, d * 2, d + 1.0] if isinstance(d, (int, float)) and not isinstance(d, bool) else []
        return [*base, 0.5, 2.0, 75.0]
    if str in types:
        return ["fp16", "w.safetensors", "x"]
    return []


#: Settings that only build beside another one (their prerequisite, laid under the value tried).
NEEDS = {"mission.predictor_adapt": {"mission": {"predictor": "learned"}}}


def _table(s: _schema.Setting, value) -> dict:
    return {s.section: {s.name: value}} if s.section else {s.name: value}


def _read(cfg, s: _schema.Setting, *, section: bool = True):
    obj = getattr(cfg, s.section) if s.section and section else cfg
    value = getattr(obj, s.name)
    return list(value) if isinstance(value, tuple) else value


def _accepted(s: _schema.Setting):
    """The first candidate that builds through TOML, with the config it built."""
    for value in _candidates(s):
        try:
            return value, to_pipeline_config(resolve(None, [_table(s, value)]))
        except FedmapError:
            continue
    pytest.fail(f"no value tried for setting {s.key} builds; extend _candidates for its type")


def test_sections_and_settings_are_found():
    sections = {s.section for s in RUN_SETTINGS}
    assert {"terrain", "thresholds", "explore", "model", "train", "federation", "refine", "evaluate"} <= sections
    assert all(s.help and "\n" not in s.help for s in RUN_SETTINGS)


@pytest.mark.parametrize("s", RUN_SETTINGS, ids=lambda s: s.key)
def test_every_run_setting_is_reachable_with_one_default(s):
    # one default: the field's, in the library defaults the presets are laid over
    table = base_defaults() if not s.section else base_defaults().get(s.section, {})
    if s.section != "terrain":  # TerrainSource's defaults depend on its kind (left to the class)
        assert table.get(s.name) == _schema.to_toml(s.default)
    if s.name == "method":
        return  # the preset, applied by the builder (tested in test_config)
    if s.section == "terrain" and s.name != "size":
        return  # the terrain source: its keys depend on its kind (tested in test_config / test_terrain)
    value, built = _accepted(s)
    assert _read(built, s) == (value if not isinstance(value, str) or not s.path else _read(built, s))
    # --set: the same value by its dotted key
    text = repr(value).replace("'", '"').replace("True", "true").replace("False", "false")
    assert to_pipeline_config(resolve(None, [parse_set(f"{s.key}={text}")])) == built
    # Python keywords: the dotted key, and the bare name where it is unique
    assert method_config("paper", **{s.key: value}) == built
    if s.name in KEYWORDS:
        assert method_config("paper", **{s.name: value}) == built
    # the Flower run config: every one-value setting but the terrain's (the base names its truth)
    if s.scalar and s.section != "terrain":
        key = flower_key(s.name)
        assert key in RUN_KEYS and key not in BASE_KEYS
        paper = defaults("paper") if not s.section else defaults("paper").get(s.section, {})
        assert RUN_DEFAULTS[key] == ("" if paper.get(s.name) is None else paper[s.name])
        assert RunSettings.from_run_config({key: value}).pipeline == built


def _options(command: str) -> dict[str, click.Option]:
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    return {o: p for p in cmd.params for o in p.opts if isinstance(p, click.Option)}


@pytest.mark.parametrize("command", ["run", "demo"])
def test_every_one_value_run_setting_is_a_command_line_option(command):
    options = _options(command)
    for s in RUN_SETTINGS:
        if not s.scalar or (command == "demo" and s.section == "thresholds"):
            continue
        flag = (s.cli or f"--{s.name.replace('_', '-')}").split("/")[0]
        if s.section == "terrain" and flag in ("--terrain",) and command == "run":
            continue  # run's --terrain is the shortcut that replaces the source (a built-in terrain)
        assert flag in options, f"{command} has no option {flag} for {s.key}"
        opt = options[flag]
        assert opt.default is None  # None: the file's or the preset's value
        assert "default:" in (opt.help or "") or "unset" in (opt.help or "")


def test_command_line_help_shows_the_fields_default():
    """The help's default comes from the field (it was once written by hand and wrong)."""
    options = _options("run")
    slope = next(s for s in RUN_SETTINGS if s.section == "thresholds" and s.cli is None and s.default is not None
                 and isinstance(s.default, float))
    flag = f"--{slope.name.replace('_', '-')}"
    assert f"(default: {slope.default})" in options[flag].help


MISSION_SETTINGS = [s for name, cls in MISSION_SECTIONS.items() for s in _schema.settings(cls, name)]


@pytest.mark.parametrize("s", MISSION_SETTINGS, ids=lambda s: s.key)
def test_every_mission_setting_is_reachable(s):
    default_cfg, _, _ = load_mission()
    part = lambda cfg: cfg if s.section == "mission" else getattr(cfg, s.section)  # noqa: E731
    assert _read(part(default_cfg), s, section=False) == _schema.to_toml(s.default)
    for value in _candidates(s):
        try:
            cfg, _, _ = load_mission(overrides=[NEEDS.get(s.key, {}), _table(s, value)])
        except FedmapError:
            continue
        break
    else:
        if not _candidates(s):
            return  # a list of cells: reachable from TOML, tested in test_mission
        pytest.fail(f"no value tried for {s.key} builds")
    got = _read(part(cfg), s, section=False)
    assert got == value
    text = repr(value).replace("'", '"').replace("True", "true").replace("False", "false")
    cfg2, _, _ = load_mission(overrides=[NEEDS.get(s.key, {}), parse_set(f"{s.key}={text}")])
    assert cfg2 == cfg
    if s.scalar or s.choices:
        flag = (s.cli or f"--{s.name.replace('_', '-')}").split("/")[0]
        assert flag in _options("mission"), f"mission has no option {flag} for {s.key}"


def test_mission_file_mistakes_are_named():
    with pytest.raises(FedmapError, match="unknown key 'rovrs' in \\[mission\\] of the command-line options "
                                          "\\(did you mean 'rovers'\\?\\)"):
        load_mission(overrides=[parse_set("mission.rovrs=3")])
    with pytest.raises(FedmapError, match="\\[link\\] loss in the command-line options must be"):
        load_mission(overrides=[parse_set("link.loss=\"high\"")])


def test_wiring_fields_are_not_settings():
    """A section's wiring (filled by the run assembly) is no setting: not in TOML, not on the link."""
    for cls in _schema.sections(PipelineConfig).values():
        names = {s.name for s in _schema.settings(cls)}
        for f in dataclasses.fields(cls):
            meta = f.metadata.get("fedmap", "absent")
            assert meta is not None or f.name not in names


def test_unknown_toml_type_is_refused():
    with pytest.raises(TypeError, match="cannot have type"):
        _schema.toml_types(complex)
