"""What the commands print when nobody's terminal is there (a log file, a pipe), and their help."""

from __future__ import annotations

import re

import click
import pytest
import typer
from typer.testing import CliRunner

from fedmap.cli import app, main, ui
from fedmap.cli.options import _PREFIX

TINY_MISSION = ["mission", "--size", "64", "--steps", "8", "--sync-every", "4", "--rovers", "2", "--sensor-radius",
                "4", "--strategies", "none,raw", "--no-animation"]


def test_a_piped_mission_table_is_printed_whole(tmp_path, capsys, monkeypatch):
    """``fedmap mission > log.txt``: the table's headers and numbers are whole, not cut to 80
    columns with ``…``, even with a narrow ``$COLUMNS``; each line of text is one line."""
    monkeypatch.setenv("COLUMNS", "60")
    assert main([*TINY_MISSION, "-o", str(tmp_path / "m")]) == 0
    out = capsys.readouterr().out
    assert "…" not in out
    header = next(line for line in out.splitlines() if "strategy" in line and "┃" in line)
    for name in ("50 %", "F1>=.9", "glob.F1", "team up B", "team down B", "up lost/over"):
        assert name in header
    assert max(len(line) for line in out.splitlines()) > 80  # the table and the legend are wider than rich's default
    assert any(line.startswith("50/80/95 %") and line.rstrip().endswith("All columns: report.md.")
               for line in out.splitlines())  # the legend is one line


def test_the_console_is_wide_without_a_terminal_and_the_terminals_width_in_one(monkeypatch):
    monkeypatch.setenv("COLUMNS", "70")
    assert not ui.console.is_terminal  # pytest captures stdout
    assert ui.console.width == ui.LOG_WIDTH
    monkeypatch.setenv("TTY_COMPATIBLE", "1")  # rich: treat the output as a terminal
    monkeypatch.setenv("TERM", "xterm-256color")  # and not a dumb one (rich gives a dumb terminal 80 columns)
    assert ui.console.is_terminal and ui.console.width == 70


def _help(command: str) -> str:
    result = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "3000"})
    assert result.exit_code == 0, result.output
    return " ".join(result.output.split())


def test_mission_help_shows_the_section_in_the_helicopters_help():
    """rich read ``[helicopter]`` as a style and showed "( sets them)"."""
    assert "Number of helicopters, after the rovers in the team ([helicopter] sets them)" in _help("mission")


def test_no_generated_option_loses_a_bracketed_word_of_its_help():
    """For every command and every generated option whose setting's help has a ``[word]``,
    the rendered ``--help`` shows it. (An option's help is its setting's, escaped for rich:
    ``\\[`` stands for ``[``.)"""
    group = typer.main.get_command(app)
    assert isinstance(group, click.Group)
    checked = set()
    for name, command in group.commands.items():
        bracketed = {word for p in command.params if p.name and p.name.startswith(_PREFIX)
                     for word in re.findall(r"\[[^\[\]]+\]", (p.help or "").replace("\\[", "["))}
        if not bracketed:
            continue
        shown = _help(name)
        for word in bracketed:
            assert word in shown, (name, word)
            checked.add((name, word))
    assert ("mission", "[helicopter]") in checked  # the test saw the generated options


@pytest.mark.parametrize("command", ["demo", "mission"])
def test_generated_help_is_escaped_once(command):
    """The escape is rich's: no backslash is left in the rendered help."""
    assert "\\[" not in _help(command)
