"""``fedmap mission`` end to end on a tiny map, its outputs, presets and its bad-input contract."""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fedmap.cli import main
from fedmap.mission import load_mission
from fedmap.mission.outputs.report import LABEL_BAND

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = ["--size", "64", "--steps", "12", "--sync-every", "4", "--rovers", "2", "--sensor-radius", "4"]


def _run(args, capsys):
    rc = main(["mission", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_mission_cli_writes_every_output(tmp_path, capsys):
    out = tmp_path / "m"
    rc, stdout, err = _run([*TINY, "--strategies", "none,raw,central", "--loss", "0.5", "-o", out], capsys)
    assert rc == 0, err
    assert "wall time" in stdout and "raw" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert list(metrics["strategies"]) == ["none", "raw", "central"]
    _report_links_only_files_that_exist(out)
    assert "mission_raw.gif" in (out / "report.md").read_text()
    raw = metrics["strategies"]["raw"]
    assert len(raw["series"]["step"]) == 13 and raw["series"]["eval"]["step"] == [0, 4, 8, 12]
    # the ledger and the cumulative bytes agree
    up = [0, 0]
    for m in raw["ledger"]:
        if m["direction"] == "up":
            up[m["rover"]] += m["bytes"]
    assert raw["series"]["bytes_up_per_rover"][-1] == up and sum(up) == raw["summary"]["bytes_up"]
    report = (out / "report.md").read_text()
    for name in ("none", "raw", "central"):
        assert f"| {name} |" in report
    for png in ("coverage.png", "f1.png", "accuracy_bytes.png", "knowing.png"):
        with Image.open(out / png) as im:
            assert im.size[0] > 100
    with Image.open(out / "mission_raw.gif") as gif:
        assert gif.n_frames == 13  # one frame per step (12 steps + the start)
        # truth | 2 beliefs | global, each 64 wide, 2-cell gaps, upscaled x2; a title band and a footer
        assert gif.size == (2 * (4 * 64 + 3 * 2), 2 * 64 + 2 * LABEL_BAND)
        first = np.asarray(gif.convert("RGB"))
        gif.seek(12)
        last = np.asarray(gif.convert("RGB"))
    # the title band is written (black text on white), the same on every frame; the footer
    # (step, bytes so far) changes from the first frame to the last
    assert (first[:LABEL_BAND] < 100).any() and np.array_equal(first[:LABEL_BAND], last[:LABEL_BAND])
    assert not np.array_equal(first[-LABEL_BAND:], last[-LABEL_BAND:])
    resolved = tomllib.loads((out / "mission.toml").read_text())
    assert resolved["mission"]["steps"] == 12 and resolved["link"]["loss"] == 0.5


def test_mission_without_animation_and_with_a_class_map(tmp_path, capsys):
    from fedmap.maps.grid import FREE, IMPASSABLE, GridMap
    from fedmap.maps.io import save_map

    c = np.full((64, 64), FREE, dtype=np.uint8)
    c[20:24, 10:50] = IMPASSABLE
    save_map(GridMap(c), tmp_path / "map.png")
    out = tmp_path / "m"
    rc, _, err = _run([*TINY, "--map", tmp_path / "map.png", "--strategies", "raw", "--no-animation", "-o", out],
                      capsys)
    assert rc == 0, err
    assert not list(out.glob("*.gif"))
    rc, _, err = _run([*TINY, "--map", tmp_path / "map.png", "--line-of-sight", "-o", out], capsys)
    assert rc == 2 and "line of sight needs the terrain's elevation" in err


@pytest.mark.parametrize("args, message", [
    (["--strategies", "raw,centrl"], "unknown strategy 'centrl' (did you mean 'central'?)"),
    (["--sync-every", "0"], "sync_every must be an integer >= 1"),
    (["--uplink-bytes", "-3"], "uplink_bytes must be a non-negative number of bytes"),
    (["--loss", "1.5"], "loss must be a probability"),
    (["--rovers", "5000"], "5000 rovers but only"),
    (["--preset", "cadr"], "unknown mission preset 'cadr' (did you mean 'cadre'?)"),
    # no close name: the known strategies are listed once
    (["--strategies", "raw,federated"],
     "unknown strategy 'federated'; known: none, raw, predictive, rosgrid, rosgrid-zlib, paper, fedmap, gossip, admm, "
     "central\n"),
])
def test_mission_cli_bad_input_is_one_line(args, message, tmp_path, capsys):
    rc, stdout, err = _run([*TINY, *args, "-o", tmp_path / "x"], capsys)
    assert rc == 2
    assert err.strip().startswith("error: ") and message in err and err.strip().count("\n") == 0
    assert not (tmp_path / "x").exists()


def test_cadre_preset_and_examples_resolve():
    cfg, source, _ = load_mission(preset="cadre")
    assert cfg.rovers == 3 and cfg.sensor_radius <= 5 and cfg.sync_every <= 5 and cfg.stay_in_range
    assert cfg.link.uplink_bytes is not None and cfg.link.uplink_bytes <= 2000 and cfg.link.max_range is not None
    assert source.terrain == "moon"
    # a file laid over the preset wins
    cfg2, src2, _ = load_mission(preset="cadre", mission={"steps": 7}, size=64)
    assert cfg2.steps == 7 and cfg2.rovers == 3 and src2.terrain == "moon" and src2.size == 64
    for name in ("gale", "hadley", "glacier"):
        cfg, source, _ = load_mission(EXAMPLES / f"mission_{name}.toml", size=96)  # --size keeps the file's source
        assert source.size == 96
        assert source.kind in ("dem", "tiles") and Path(source.path).name in (
            "missionDEM_gale_1m.tif", "gld100_256p", "test-files_columbia_dem_Columbia.tif")


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg is not on the PATH")
def test_mp4_when_ffmpeg_is_present(tmp_path):
    from fedmap.mission.outputs.report import mp4_bytes

    frames = [np.full((16, 20, 3), 40 * i, dtype=np.uint8) for i in range(5)]
    data = mp4_bytes(frames)
    assert data is not None and b"ftyp" in data[:64]


def test_mission_takes_runs_terrain_and_threshold_options(tmp_path, capsys):
    """The line from the schema issue: a DEM, a percentile slope limit, a rover profile and
    a --set of a [mission] key, exactly as `fedmap run` takes the first three."""
    from fedmap.config import load_run
    from fedmap.maps.terrain import generate_dem

    dem = tmp_path / "site.npy"
    np.save(dem, generate_dem("moon", 64, seed=1).elevation)
    out = tmp_path / "m"
    rc, stdout, err = _run(["--dem", dem, "--pixel-size", "2", "--max-slope", "p75", "--rover", "cadre",
                            "--set", "mission.rovers=3", "--steps", "6", "--sync-every", "3", "--strategies", "none,raw",
                            "--no-animation", "-o", out], capsys)
    assert rc == 0, err
    saved = tomllib.loads((out / "mission.toml").read_text())
    assert saved["mission"]["rovers"] == 3
    assert saved["thresholds"]["rover"] == "cadre" and saved["thresholds"]["max_slope_percentile"] == 75.0
    assert saved["terrain"]["kind"] == "dem" and saved["terrain"]["options"] == {"pixel_size": 2.0}
    # the same options give `fedmap run` the same thresholds (one set of declarations)
    run_resolved = load_run(None, [{"thresholds": {"rover": "cadre", "max_slope_percentile": 75.0},
                                    "terrain": {"options": {"pixel_size": 2.0}}}],
                            terrain={"kind": "dem", "path": str(dem)})[0]
    assert run_resolved["thresholds"] == saved["thresholds"]
    ledger = json.loads((out / "metrics.json").read_text())["strategies"]["raw"]["ledger"]
    assert {m["rover"] for m in ledger if m["direction"] == "up"} == {0, 1, 2}  # three rovers sent
    _report_links_only_files_that_exist(out)
    assert "animations: none" in (out / "report.md").read_text()  # --no-animation wrote none


def _report_links_only_files_that_exist(out: Path) -> None:
    import re

    named = re.findall(r"`([\w.-]+\.(?:png|gif|mp4|json|toml|md))`", (out / "report.md").read_text())
    assert named and all((out / n).is_file() for n in named), [n for n in named if not (out / n).is_file()]


def test_report_flags_undelivered_messages_and_names_the_best_map(tmp_path, capsys):
    """report.md says which messages did not arrive and why (counted here from the ledger),
    each strategy's belief accuracy at step 0, and one computed line naming the best map and
    the best map per byte (recomputed here from metrics.json)."""
    out = tmp_path / "m"
    rc, stdout, err = _run([*TINY, "--strategies", "none,raw", "--uplink-bytes", "40", "--loss", "0.3",
                            "--no-animation", "-o", out], capsys)
    assert rc == 0, err
    metrics = json.loads((out / "metrics.json").read_text())["strategies"]
    report = (out / "report.md").read_text()
    raw_row = next(line for line in report.splitlines() if line.startswith("| raw |")).split(" | ")
    header = next(line for line in report.splitlines() if line.startswith("| strategy |")).split(" | ")
    cell = dict(zip(header, raw_row))
    for direction, col in (("up", "uplinks not delivered"), ("down", "downlinks not delivered |")):
        counts: dict = {}
        for m in metrics["raw"]["ledger"]:
            if m["direction"] == direction and m["status"] != "delivered":
                counts[m["status"]] = counts.get(m["status"], 0) + 1
        want = ", ".join(f"{counts[s]} {s}" for s in ("over budget", "lost", "stale", "out of range", "rejected")
                         if s in counts) or "-"
        assert cell[col].rstrip(" |") == want
    assert "over budget" in cell["uplinks not delivered"]  # 40 B is tight: the test exercises the flag
    acc0 = sum(metrics["raw"]["series"]["accuracy"][0]) / 2
    assert cell["belief acc. at step 0"] == f"{acc0:.3f}"
    acc = {n: metrics[n]["summary"]["final_belief_accuracy_mean"] for n in ("none", "raw")}
    if round(acc["raw"], 3) == round(acc["none"], 3):  # equal as printed: a tie, none spent fewer bytes
        assert f"Best map: a tie between none and raw (belief accuracy {acc['none']:.3f}); **none** spent" in report
        best = "a tie between none and raw"
    else:
        best = "raw" if acc["raw"] > acc["none"] else "none"
        assert f"Best map: **{best}**" in report
    spent = metrics["raw"]["summary"]["bytes_up"] + metrics["raw"]["summary"]["bytes_down"]
    if acc["raw"] > acc["none"] and spent:
        assert f"Best map per byte: **raw** (+{(acc['raw'] - acc['none']) * 100:.2f} accuracy points" in report
    assert f"Best map: {best}" in " ".join(stdout.split())  # the console says it too


def test_a_strategy_that_got_nothing_through_is_not_the_best_map(tmp_path, capsys):
    """The newcomer's case: a model strategy whose every uplink is over budget (20 B: above the
    header, far below any model) keeps its initial model's rendering; the verdict says so
    instead of naming it the best map."""
    out = tmp_path / "m"
    rc, stdout, err = _run([*TINY, "--strategies", "none,fedmap", "--uplink-bytes", "20", "--no-animation",
                            "-o", out], capsys)
    assert rc == 0, err
    report = (out / "report.md").read_text()
    fedmap = json.loads((out / "metrics.json").read_text())["strategies"]["fedmap"]["summary"]
    assert fedmap["bytes_up"] + fedmap["bytes_down"] == 0 and fedmap["messages"]["up_over budget"] > 0
    assert "Best map: **none**" in report
    assert f"fedmap got nothing through the link (uplinks: {fedmap['messages']['up_over budget']} over budget)" in report


def test_a_start_in_a_small_pocket_is_flagged(tmp_path, capsys):
    """Built-in mars at 512² puts the lander in a free pocket of 101 cells: the rovers could
    only explore that. Here the same by hand: a free 5x5 pocket walled off at the centre."""
    from fedmap.maps.grid import FREE, IMPASSABLE, GridMap
    from fedmap.mission.sim import start_pocket_warning

    classes = np.full((64, 64), FREE, np.uint8)
    classes[28:37, 28:37] = IMPASSABLE
    classes[30:35, 30:35] = FREE  # the pocket around the centre (32, 32)
    cfg, _, _ = load_mission(mission={"rovers": 2})
    warning = start_pocket_warning(GridMap(classes, 1.0, "pocket"), cfg)
    assert warning is not None and "free ground of 25 cells" in warning
    open_map = np.full((64, 64), FREE, np.uint8)
    assert start_pocket_warning(GridMap(open_map, 1.0, "open"), cfg) is None
    np.save(tmp_path / "pocket.npy", classes)
    rc, stdout, err = _run(["--map", tmp_path / "pocket.npy", "--steps", "3", "--strategies", "none",
                            "--no-animation", "-o", tmp_path / "m"], capsys)
    assert rc == 0, err
    assert "warning: the rovers start on free ground of 25 cells" in " ".join(stdout.split())


@pytest.mark.parametrize("preset", ["ramen", "cadre-mesh", "scout"])
def test_peer_and_helicopter_presets_run_and_report(preset, tmp_path, capsys):
    out = tmp_path / preset
    rc, stdout, err = _run(["--preset", preset, *TINY, "--strategies", "none,raw", "-o", out], capsys)
    assert rc == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    raw = metrics["strategies"]["raw"]
    report = (out / "report.md").read_text()
    cfg, _, _ = load_mission(preset=preset)
    if cfg.link.topology != "star":
        assert "B/link/rnd" in stdout and "Topology: **" in report
        peer = [m for m in raw["ledger"] if m["direction"] == "peer"]
        assert peer and len(peer) == len(raw["ledger"])
        offered = [m for m in peer if m["status"] not in ("link down",)]
        # bytes per link per round: the ledger's bytes over the messages offered on links that were up
        assert raw["summary"]["bytes_per_link_round"] == pytest.approx(sum(m["bytes"] for m in peer) / len(offered))
    else:
        assert "Helicopters: 1" in report
        with Image.open(out / "mission_raw.gif") as gif:  # truth | 2 rovers + 1 helicopter | global
            assert gif.size[0] == 2 * (5 * 64 + 4 * 2)


def test_a_tie_at_the_top_is_named_as_a_tie_and_bytes_buy_over_sharing_nothing_only(tmp_path, capsys):
    """raw and predictive share every cell losslessly: on a perfect link their rovers end with
    the same beliefs, so the verdict calls it a tie (naming the one that spent fewer bytes)
    instead of a winner. Without `none`, the per-byte line names its missing baseline instead
    of switching to another one."""
    out = tmp_path / "m"
    rc, _, err = _run([*TINY, "--strategies", "raw,predictive", "--loss", "0", "--no-animation", "-o", out], capsys)
    assert rc == 0, err
    s = json.loads((out / "metrics.json").read_text())["strategies"]
    acc = {n: round(s[n]["summary"]["final_belief_accuracy_mean"], 3) for n in ("raw", "predictive")}
    assert acc["raw"] == acc["predictive"]  # the premise: lossless sharing on a perfect link
    spent = {n: s[n]["summary"]["bytes_up"] + s[n]["summary"]["bytes_down"] for n in acc}
    fewer = min(spent, key=spent.get)
    report = " ".join((out / "report.md").read_text().split())
    assert f"Best map: a tie between raw and predictive (belief accuracy {acc['raw']:.3f}); **{fewer}** spent" in report
    assert "Best map per byte: needs none (sharing nothing) among the strategies" in report
    assert "over step 0" not in report


def test_the_wall_time_under_repeats_is_the_whole_run(tmp_path, capsys):
    """report.md's wall time with --repeats is every repeat's, not the first's."""
    out = tmp_path / "m"
    rc, _, err = _run([*TINY, "--strategies", "none,raw", "--repeats", "3", "--no-animation", "-o", out], capsys)
    assert rc == 0, err
    runs = json.loads((out / "metrics.json").read_text())["repeats"]["runs"]
    total = sum(r["seconds"] for r in runs)
    assert len(runs) == 3 and total > runs[0]["seconds"]
    report = (out / "report.md").read_text()
    assert f"Wall time: {total:.1f} s over 3 repeats (" in report
    pairs = json.loads((out / "metrics.json").read_text())["settings"]["mission"]["eval_pairs"]
    assert f"Path F1 is strict (A*, {pairs} seeded start/goal pairs" in report  # (a literal {c.eval_pairs} was printed)


def test_the_knowing_plot_titles_do_not_overlap(monkeypatch):
    """knowing.png's four panel titles ran into each other: each title's box, drawn, stays
    clear of its neighbours'."""
    from fedmap.maps.grid import FREE, GridMap
    from fedmap.mission import MissionConfig, run_mission
    from fedmap.mission.outputs import report as rep

    c = np.full((24, 24), FREE, np.uint8)
    result = run_mission(MissionConfig(rovers=2, steps=6, sync_every=3, sensor_radius=3.0, eval_pairs=4,
                                       strategies=("none", "raw")), GridMap(c))
    figs = []
    monkeypatch.setattr(rep, "_png", lambda fig: figs.append(fig) or b"")
    rep.plot_knowing([result])
    fig = figs[0]
    fig.canvas.draw()
    boxes = [ax.title.get_window_extent() for ax in fig.axes if ax.get_title()]
    assert len(boxes) == 4
    for a, b in zip(boxes, boxes[1:]):
        assert a.x1 < b.x0, (a, b)
