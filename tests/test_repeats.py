"""Repeats of a mission with 95 % intervals, the verdict that names a winner only where the
intervals separate, when a team first has a plannable map, and the checks that refuse or
flag a mission before (or after) it runs: a budget below the header, a start area too
small, a DEM resampled, a member that hardly moved."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats

from conftest import maze
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, GridMap
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.outputs.report import plannable, verdict, write_mission
from fedmap.mission.repeats import Interval, interval, intervals, repeat_configs, run_repeats
from fedmap.mission.results import F1_GOAL, READY_COVERAGE, UNWRITTEN_WHEN_NONE, movement_warnings
from fedmap.mission.world.world import place_starts
from test_mission import _small


def test_interval_is_students_t_as_scipy_computes_it():
    values = [0.61, 0.55, 0.72, 0.58, 0.66]
    iv = interval(values)
    lo, hi = stats.t.interval(0.95, len(values) - 1, loc=np.mean(values), scale=stats.sem(values))
    assert iv is not None and iv.mean == pytest.approx(np.mean(values))
    assert (iv.lo, iv.hi) == (pytest.approx(lo), pytest.approx(hi))
    # by hand for two values: mean +- t(0.975, 1) * |a - b| / 2, t(0.975, 1) = 12.7062
    two = interval([1.0, 3.0])
    assert two is not None and two.hi - two.mean == pytest.approx(12.7062 * 1.0, rel=1e-4)
    # a value never reached is counted as missing, not as a number; a share is clipped to [0, 1]
    some = interval([10, None, 14])
    assert some is not None and (some.n, some.missing, some.mean) == (2, 1, 12.0)
    assert interval([None, None]) is None
    clipped = interval([0.0, 0.02, 0.0], bounds=(0.0, 1.0))
    assert clipped is not None and clipped.lo == 0.0
    one = interval([0.4])
    assert one is not None and (one.lo, one.hi) == (0.4, 0.4)


def _cfg(**kw) -> MissionConfig:
    """test_mission's small mission, 30 steps, with predictive beside raw."""
    return _small(**{"steps": 30, "strategies": ("none", "raw", "predictive"), **kw})


@pytest.fixture(scope="module")
def repeated():
    truth = maze(40, seed=3)
    cfg = _cfg(start_spread=6)
    return truth, cfg, run_repeats(cfg, truth, 3, frames=1)


def test_repeats_vary_the_seeds_the_link_and_the_starts(repeated):
    truth, cfg, results = repeated
    assert [r.config.seed for r in results] == [cfg.seed, cfg.seed + 1, cfg.seed + 2]
    assert [r.config.link_seed for r in results] == [5, 6, 7]
    unset = repeat_configs(_cfg(link=LinkConfig(loss=0.3), seed=3), 2)  # an unset link seed follows the mission's
    assert [c.link.seed for c in unset] == [None, None] and [c.link_seed for c in unset] == [3, 4]
    starts = [tuple(r.starts) for r in results]
    assert len(set(starts)) == 3  # each repeat draws its own starts ...
    for s in starts:  # ... on free cells of the start area
        for cell in s:
            assert truth.classes[cell] == FREE
            assert math.dist(cell, (20, 20)) <= 6
        assert len(set(s)) == len(s)


def test_three_repeats_give_intervals_that_contain_each_single_run(repeated):
    truth, cfg, results = repeated
    singles = [run_mission(c, truth, frames=1) for c in repeat_configs(cfg, 3)]
    ivs = intervals(results)
    for name in cfg.strategies:
        for value in ("coverage", "belief accuracy", "belief F1", "team bytes"):
            iv = ivs[name][value]
            assert iv is not None
            got = [{"coverage": s.runs[name].summary.final_coverage,
                    "belief accuracy": s.runs[name].summary.final_belief_accuracy_mean,
                    "belief F1": s.runs[name].summary.final_belief_f1_mean,
                    "team bytes": s.runs[name].summary.bytes_up + s.runs[name].summary.bytes_down}[value]
                   for s in singles]
            assert list(iv.values) == pytest.approx(got)  # a repeat is that single run, bit for bit
            for v in got:
                assert iv.lo - 1e-12 <= v <= iv.hi + 1e-12
    # the losses did differ between repeats: some strategy's bytes are not the same in all three
    assert len(set(ivs["raw"]["team bytes"].values)) > 1  # type: ignore[union-attr]


def test_a_tie_is_no_clear_difference_and_separated_intervals_name_a_winner(repeated):
    """raw and predictive deliver the same cells, so they end with the same map in every
    repeat: a tie on belief accuracy. Against sharing nothing, both are far ahead."""
    _, _, results = repeated
    acc = [r.runs["raw"].summary.final_belief_accuracy_mean for r in results]
    assert acc == [r.runs["predictive"].summary.final_belief_accuracy_mean for r in results]
    text = verdict(results[0], results)
    assert "Best map: no clear difference between raw" in text and "predictive" in text
    # constructed intervals: one wholly above the other is a winner, overlapping ones are not
    from fedmap.mission.outputs.report import _winner

    a, b, c = Interval(0.8, 0.75, 0.85, 5), Interval(0.6, 0.55, 0.65, 5), Interval(0.7, 0.62, 0.78, 5)
    assert _winner({"a": a, "b": b}, high=True) == ("a", [])
    assert _winner({"a": a, "c": c}, high=True) == (None, ["a", "c"])
    assert _winner({"a": a, "b": b}, high=False) == ("b", [])


def test_the_plannable_step_and_its_bytes_are_the_first_step_both_goals_hold():
    truth = maze(32, seed=1)
    res = run_mission(_cfg(steps=60, link=LinkConfig(loss=0.0, seed=1), strategies=("raw", "central")), truth)
    for run in res.runs.values():
        s, ser = run.summary, run.series
        at = {t: i for i, t in enumerate(ser.step)}
        by_hand = None
        for t, f in zip(ser.eval.step, ser.eval.belief_f1):
            if np.mean(f[:3]) >= F1_GOAL and ser.coverage[at[t]] >= READY_COVERAGE:
                by_hand = t
                break
        assert s.ready_step == by_hand
        if by_hand is not None:
            i = at[by_hand]
            assert s.ready_bytes == sum(ser.bytes_up[i]) + sum(ser.bytes_down[i])
    assert res.runs["raw"].summary.ready_step is not None  # this small maze is mapped in 60 steps
    line = plannable([res])
    assert f"raw at step {res.runs['raw'].summary.ready_step} for {res.runs['raw'].summary.ready_bytes:,} B" in line


def test_no_strategy_reaching_a_plannable_map_is_said_plainly():
    res = run_mission(_cfg(steps=4), maze(40, seed=3))
    assert plannable([res]).startswith("No strategy gave the team a plannable map")


def test_repeats_are_written_with_intervals(repeated, tmp_path):
    _, _, results = repeated
    out = write_mission(results[0], tmp_path / "m", title="maze", animation=False, repeats=results)
    data = json.loads((out / "metrics.json").read_text())
    rep = data["repeats"]
    assert rep["n"] == 3 and len(rep["runs"]) == 3
    iv = rep["intervals"]["raw"]["belief accuracy"]
    assert iv["lo"] <= iv["mean"] <= iv["hi"] and len(iv["values"]) == 3
    report = (out / "report.md").read_text()
    assert "**Repeats**: 3 repeats" in report and f"{iv['mean']:.3f} [{iv['lo']:.3f}, {iv['hi']:.3f}]" in report


def test_a_budget_below_the_header_is_refused_before_the_mission():
    with pytest.raises(FedmapError, match="uplink budget of 10 B is below the 16-byte header"):
        _cfg(link=LinkConfig(uplink_bytes=10))
    with pytest.raises(FedmapError, match="downlink budget of 4 B is below the 10-byte header"):
        _cfg(link=LinkConfig(downlink_bytes=4))  # kind 1 B + model version 8 B + rovers reported 1 B
    # predictive carries no mission header: its least message is its state byte and check byte
    _cfg(link=LinkConfig(uplink_bytes=6, downlink_bytes=6), strategies=("predictive",))
    with pytest.raises(FedmapError, match="uplink budget of 1 B is below the 2-byte header every uplink message "
                                          "of predictive carries"):
        _cfg(link=LinkConfig(uplink_bytes=1), strategies=("predictive",))
    _cfg(link=LinkConfig(uplink_bytes=10), strategies=("none", "central"))  # nothing on the link: nothing to refuse


def test_a_start_area_too_small_is_one_line_and_a_draw_is_seeded():
    walls = np.full((20, 20), IMPASSABLE, np.uint8)
    walls[10, 10:12] = FREE  # two free cells by the lander ...
    walls[:, 18:] = FREE  # ... and plenty far away
    with pytest.raises(FedmapError, match=r"start area \(free cells within 3 cells .* holds 2 cells for 3 rovers"):
        place_starts(GridMap(walls, 1.0), _cfg(start_spread=3, lander=(10, 10)))
    truth = maze(40, seed=3)
    a, _ = place_starts(truth, _cfg(start_spread=6, seed=2))
    b, _ = place_starts(truth, _cfg(start_spread=6, seed=2))
    assert a == b
    with pytest.raises(FedmapError, match="start_spread"):
        _cfg(start_spread=-1)


def test_a_member_that_hardly_moved_is_flagged():
    truth = maze(40, seed=3)
    res = run_mission(_cfg(steps=20, strategies=("none",)), truth, frames=1)
    assert movement_warnings(res) == []  # every rover drove
    stuck = run_mission(_cfg(steps=20, strategies=("none",), mode="waypoints",
                             waypoints=(((20, 20),), ((20, 20),), ((20, 20),))), truth, frames=1)
    lines = movement_warnings(stuck)
    moved = [stuck.runs["none"].series.distance[-1][k] for k in range(3)]
    assert len(lines) == sum(d < 0.1 * 20 * 2 for d in moved) > 0
    assert all("moved only" in w and "40-cell range" in w for w in lines)


def test_the_cli_runs_repeats_and_writes_maps(tmp_path, capsys):
    from fedmap.cli import main

    out = tmp_path / "m"
    rc = main(["mission", "--size", "64", "--steps", "12", "--sync-every", "4", "--rovers", "2", "--sensor-radius",
               "4", "--strategies", "none,raw", "--repeats", "2", "--no-animation", "-o", str(out)])
    stdout = capsys.readouterr().out
    assert rc == 0
    assert "repeats: 2 repeats, seeds 0..1" in stdout and "of 2 repeats" in stdout
    data = json.loads((out / "metrics.json").read_text())
    assert data["repeats"]["n"] == 2 and [r["seed"] for r in data["repeats"]["runs"]] == [0, 1]
    assert (out / "maps" / "raw_global.tif").is_file() and (out / "maps" / "raw_global.yaml").is_file()


def test_a_resampled_dem_says_from_what_to_what_cell_size(tmp_path):
    import rasterio
    from affine import Affine

    from fedmap.maps.sources import TerrainSource, load_terrain

    z = np.random.default_rng(0).normal(0, 5, (100, 100)).cumsum(axis=0).astype(np.float32)
    path = tmp_path / "dem.tif"
    with rasterio.open(path, "w", driver="GTiff", height=100, width=100, count=1, dtype="float32",
                       crs="EPSG:32633", transform=Affine(30.0, 0, 500000.0, 0, -30.0, 4000000.0)) as dst:
        dst.write(z, 1)
    truth, _ = load_terrain(TerrainSource(kind="dem", path=str(path), size=64))
    note = truth.meta["resampled"]
    assert "from 100x100 cells of 30 m to 64x64 cells of 46.9 m" in note  # 30 m * 100 / 64
    kept, _ = load_terrain(TerrainSource(kind="dem", path=str(path), size=100))
    assert "resampled" not in kept.meta


def test_metrics_json_names_every_summary_value_as_python_does(repeated, tmp_path):
    from dataclasses import fields

    _, _, results = repeated
    out = write_mission(results[0], tmp_path / "one", title="maze", animation=False)
    data = json.loads((out / "metrics.json").read_text())["strategies"]
    for name, run in results[0].runs.items():
        got = data[name]["summary"]
        for f in fields(run.summary):
            value = getattr(run.summary, f.name)
            if f.name in UNWRITTEN_WHEN_NONE and value is None:  # no predictor, no stop rule: not written
                assert f.name not in got
            elif f.name in ("coverage_steps", "coverage_reachable_steps"):
                assert got[f.name] == {f"{int(lv * 100)}%": t for lv, t in value.items()}
            elif isinstance(value, tuple):
                assert got[f.name] == list(value)
            else:
                assert got[f.name] == value, f.name


def test_over_a_perfect_link_raw_and_predictive_give_the_same_maps_step_for_step():
    """The claim the README makes: with no loss and no budget, predictive delivers what raw
    delivers at the same syncs, so every rover holds the same belief at every step."""
    truth = maze(40, seed=3)
    res = run_mission(_cfg(steps=40, link=LinkConfig(loss=0.0), strategies=("raw", "predictive")), truth,
                      frames=1000)
    a, b = res.runs["raw"], res.runs["predictive"]
    assert len(a.frames) == 41
    for fa, fb in zip(a.frames, b.frames):
        assert fa.positions == fb.positions
        assert all(np.array_equal(x, y) for x, y in zip(fa.beliefs, fb.beliefs))
    assert b.summary.bytes_up + b.summary.bytes_down < a.summary.bytes_up + a.summary.bytes_down


def test_snapshots_follow_the_run_step_by_step():
    truth = maze(40, seed=3)
    got: list = []
    res = run_mission(_cfg(steps=12, strategies=("raw", "central")), truth, frames=1000, on_snapshot=got.append)
    for name, run in res.runs.items():
        snaps = [s for s in got if s.strategy == name]
        assert [s.step for s in snaps] == list(range(13))
        assert sum(len(s.messages) for s in snaps) == len(run.ledger)  # every ledger entry once, in order
        assert [m for s in snaps for m in s.messages] == run.ledger
        for s, f in zip(snaps, run.frames):
            assert s.positions == f.positions and np.array_equal(s.global_map, f.global_map)
        assert [s.eval is not None for s in snaps] == [t in (0, 6, 12) for t in range(13)]
        assert all(np.array_equal(a, b) for a, b in zip(snaps[-1].views, run.views))


def test_repeats_with_a_predictor_give_the_guessed_beliefs_step_an_interval():
    """With a predictor the repeats also give the first step the beliefs with the guesses
    filled in reached a mean F1 of 0.9 (Student's t over the repeats' summaries); without
    one the value is not there."""
    truth = maze(40, seed=3)
    results = run_repeats(_cfg(strategies=("raw",), predictor="learned", steps=40, start_spread=6), truth, 3, frames=1)
    steps = [r.runs["raw"].summary.to_dict()["predicted_belief"]["f1_step"] for r in results]
    iv = intervals(results)["raw"]["guessed F1≥0.9 at"]
    reached = [s for s in steps if s is not None]
    assert reached, "the test needs a repeat whose guessed beliefs reach 0.9"
    assert iv is not None and iv.mean == pytest.approx(np.mean(reached)) and iv.missing == len(steps) - len(reached)
    plain = run_repeats(_cfg(strategies=("raw",), steps=10), truth, 2, frames=1)
    assert "guessed F1≥0.9 at" not in intervals(plain)["raw"]


def test_repeats_that_the_stop_rule_ended_at_different_steps_are_drawn_over_the_steps_all_reached(tmp_path):
    """With the stop rule, repeats end at different steps (and their last evaluation is not a
    sync): a curve's mean is taken only at the steps every repeat reached, each value at its
    own step (by hand below), and a repeated mission with the rule writes every figure."""
    from fedmap.mission.outputs.report import _line

    class Ax:
        def plot(self, x, y, **kw):
            self.x, self.y = list(x), list(y)

        def fill_between(self, *a, **kw):
            pass

    ax = Ax()
    _line(ax, [0, 10, 20, 23], [[0.1, 0.5, 0.7, 0.9], [0.3, 0.6, 0.95]], xs=[[0, 10, 20, 23], [0, 10, 17]])
    assert ax.x == [0, 10] and ax.y == pytest.approx([0.2, 0.55])
    results = run_repeats(_cfg(steps=120, strategies=("none", "raw"), stop_coverage=0.9), maze(40, seed=3), 3)
    ends = [r.runs["raw"].series.step[-1] for r in results]
    assert all(e < 120 for e in ends) and len(set(ends)) > 1  # stopped, at different steps
    out = write_mission(results[0], tmp_path / "rep", title="maze", animation=False, repeats=results)
    for png in ("coverage.png", "f1.png", "accuracy_bytes.png", "knowing.png"):
        assert (out / png).stat().st_size > 10_000
