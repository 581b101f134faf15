"""What the commands print when nobody's terminal is there (a log file, a pipe)."""

from __future__ import annotations

from fedmap.cli import main, ui

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
    assert ui.console.is_terminal and ui.console.width == 70
