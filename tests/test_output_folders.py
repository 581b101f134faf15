"""A run's output folder is replaced as a whole at its end: only a new or empty folder, or one
fedmap wrote, may be; anything else, and a place that cannot be written, is one line before
any work, and nothing that was there is lost."""

from __future__ import annotations

import os
import stat

import pytest

from fedmap._util import OUTPUT_MARKER, AtomicDir, check_output_dir
from fedmap.cli import main
from fedmap.errors import FedmapError

TINY = ["--size", "64", "--steps", "4", "--sync-every", "2", "--rovers", "2", "--sensor-radius", "3",
        "--strategies", "none,raw", "--no-animation"]


def _mission(args, capsys):
    rc = main(["mission", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _tree(path):
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_a_folder_of_ones_own_files_is_refused_before_the_run_and_kept(tmp_path, capsys, monkeypatch):
    mine = tmp_path / "data"
    (mine / "sub").mkdir(parents=True)
    (mine / "notes.txt").write_text("mine")
    (mine / "sub" / "more.bin").write_bytes(b"\x00\x01")
    before = _tree(mine)
    loads = []
    import fedmap.cli.mission as cli_mission
    monkeypatch.setattr(cli_mission, "mission_terrain", lambda *a, **k: loads.append(1))  # must not be reached
    rc, _, err = _mission([*TINY, "-o", mine], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "not a fedmap output folder" in err and str(mine) in " ".join(err.split())
    assert _tree(mine) == before and not loads
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no temporary folder left beside it


@pytest.mark.parametrize("case", ["file", "unwritable", "cwd", "parent of cwd"])
def test_an_output_that_cannot_be_a_folder_is_one_line_before_the_run(case, tmp_path, capsys, monkeypatch):
    import fedmap.cli.mission as cli_mission
    loads = []
    monkeypatch.setattr(cli_mission, "mission_terrain", lambda *a, **k: loads.append(1))
    work = tmp_path / "work"
    work.mkdir()
    (work / "own.txt").write_text("x")
    monkeypatch.chdir(work)
    if case == "file":
        out = tmp_path / "afile"
        out.write_text("keep me")
        expect = "exists and is not a folder"
    elif case == "unwritable":
        out = "/proc/fedmap-out"
        expect = "cannot write /proc/fedmap-out"
    elif case == "cwd":
        out, expect = ".", "current folder"
    else:
        out, expect = "..", "current folder"
    rc, _, err = _mission([*TINY, "-o", out], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and expect in err, err
    assert not loads and (work / "own.txt").read_text() == "x"
    if case == "file":
        assert (tmp_path / "afile").read_text() == "keep me"


def test_an_earlier_output_is_replaced_with_its_permissions_and_an_empty_folder_is_used(tmp_path, capsys):
    out = tmp_path / "m"
    rc, _, err = _mission([*TINY, "-o", out], capsys)
    assert rc == 0, err
    assert (out / OUTPUT_MARKER).is_file() and (out / "metrics.json").is_file()
    os.chmod(out, 0o750)
    (out / "stale.txt").write_text("from before")
    rc, _, err = _mission([*TINY, "-o", out, "--set", "seed=3"], capsys)
    assert rc == 0, err
    assert not (out / "stale.txt").exists() and (out / "metrics.json").is_file()
    assert stat.S_IMODE(out.stat().st_mode) == 0o750
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no old or temporary folder left
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check_output_dir(empty) == empty.resolve()


def test_a_recording_or_bag_inside_the_output_folder_or_a_bag_over_a_file_is_refused_first(tmp_path, capsys):
    out = tmp_path / "m"
    rc, _, err = _mission([*TINY, "-o", out], capsys)
    assert rc == 0, err
    before = _tree(out)
    for extra, expect in ((["--record", out / "rec.mcap"], "--record"), (["--rosbag", out / "bag"], "--rosbag")):
        rc, _, err = _mission([*TINY, "-o", out, "--set", "seed=5", *extra], capsys)
        assert rc == 2 and len(err.strip().splitlines()) == 1 and expect in err and "inside the output folder" in err
    afile = tmp_path / "rb"
    afile.write_text("not a bag")
    rc, _, err = _mission([*TINY, "-o", out, "--set", "seed=5", "--rosbag", afile], capsys)
    assert rc == 2 and "exists and is not a ROS 2 bag" in err and len(err.strip().splitlines()) == 1
    rc, _, err = _mission([*TINY, "-o", out, "--set", "seed=5", "--record", "/proc/x.mcap"], capsys)
    assert rc == 2 and "cannot record to /proc/x.mcap" in err and len(err.strip().splitlines()) == 1
    notes = tmp_path / "notes.txt"  # a file of the user's own is never turned into a recording
    notes.write_text("my notes")
    rc, _, err = _mission([*TINY, "-o", out, "--set", "seed=5", "--record", notes], capsys)
    assert rc == 2 and "exists and is not an MCAP recording" in err and len(err.strip().splitlines()) == 1
    assert _tree(out) == before and afile.read_text() == "not a bag"  # the earlier result is whole
    assert notes.read_text() == "my notes"


def test_atomic_dir_puts_the_old_folder_back_if_the_swap_fails(tmp_path, monkeypatch):
    out = tmp_path / "r"
    with AtomicDir(out) as tmp:
        (tmp / "a.txt").write_text("first")
    real = os.replace
    calls = []

    def failing(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the new folder into place
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(FedmapError, match="cannot write .*No space left.*this run's result is in") as e:
        with AtomicDir(out) as tmp:
            (tmp / "a.txt").write_text("second")
    monkeypatch.setattr(os, "replace", real)
    assert (out / "a.txt").read_text() == "first" and (out / OUTPUT_MARKER).is_file()
    assert str(tmp) in str(e.value) and (tmp / "a.txt").read_text() == "second"  # the new result kept, named
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["r", tmp.name])  # no old folder left


def test_an_output_of_an_earlier_fedmap_without_the_marker_is_still_replaced_and_a_look_alike_is_not(tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    (old / "metrics.json").write_text('{"timings": {"total_s": 1.0}, "global": {}}')
    assert check_output_dir(old) == old.resolve()
    mine = tmp_path / "ml"
    mine.mkdir()
    (mine / "metrics.json").write_text('{"accuracy": 0.9}')  # somebody else's metrics.json
    with pytest.raises(FedmapError, match="is not a fedmap output folder"):
        check_output_dir(mine)


def test_a_recording_replaces_only_an_earlier_recording(tmp_path):
    from fedmap.mission.outputs.recording import MCAP_MAGIC, check_recording_path

    earlier = tmp_path / "run.mcap"
    earlier.write_bytes(MCAP_MAGIC + b"\x00" * 8)
    assert check_recording_path(earlier) == earlier  # an earlier recording: replaced at the end
    assert check_recording_path(tmp_path / "new.mcap") == tmp_path / "new.mcap"
    other = tmp_path / "data.mcap"
    other.write_bytes(b"PK\x03\x04 a zip named .mcap")
    with pytest.raises(FedmapError, match="exists and is not an MCAP recording"):
        check_recording_path(other)
