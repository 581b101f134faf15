"""Missions: sensing, frontiers, planning contract, coverage, raw merging, link, seeds, errors."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from conftest import maze
from fedmap.coding.mapcodec import decode_map
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.ends.protocol import unpack_up
from fedmap.mission.network.link import Link
from fedmap.mission.network.topology import StarTopology
from fedmap.mission.settings import load_mission
from fedmap.mission.world.frontiers import DETOUR, choose_target, frontier_mask, gain_at, plan_path, travel_costs
from fedmap.mission.world.sensing import disk_offsets, footprint


def _maze(n: int = 40, seed: int = 3) -> GridMap:
    return maze(n, seed)


# ---------------------------------------------------------------- sensing


def test_footprint_is_the_disk_by_brute_force():
    shape, pos, radius = (20, 23), (3, 18), 4.5
    got = footprint(pos, shape, radius)
    want = np.zeros(shape, dtype=bool)
    for r in range(shape[0]):
        for c in range(shape[1]):
            want[r, c] = (r - pos[0]) ** 2 + (c - pos[1]) ** 2 <= radius**2
    assert np.array_equal(got, want)


def test_line_of_sight_stops_at_a_constructed_wall():
    z = np.zeros((21, 21))
    z[:, 12] = 10.0  # a 10 m wall along column 12
    pos, radius = (10, 8), 8.0
    seen = footprint(pos, z.shape, radius, elevation=z, height_m=1.5)
    flat = footprint(pos, z.shape, radius)
    assert seen[9:12, 12].all()  # the face of the wall in front of the rover is seen
    assert not seen[10, 13:].any() and not seen[7:14, 14:].any()  # nothing behind it
    assert np.array_equal(seen[:, :12], flat[:, :12])  # in front of it: the whole disk
    # without the wall, line of sight over flat ground is the disk
    assert np.array_equal(footprint(pos, z.shape, radius, elevation=np.zeros_like(z)), flat)
    # a rover on top of the wall sees over it
    assert footprint((10, 12), z.shape, radius, elevation=z)[10, 18]


# ---------------------------------------------------------------- frontiers


def test_frontier_on_a_constructed_map():
    b = np.full((6, 7), UNKNOWN, dtype=np.uint8)
    b[1:4, 1:4] = FREE
    b[2, 2] = IMPASSABLE
    b[3, 3] = FREE
    got = frontier_mask(b)
    want = np.zeros_like(got)
    for r in range(6):
        for c in range(7):
            if b[r, c] != FREE:
                continue
            nbrs = [(r + dr, c + dc) for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1))]
            want[r, c] = any(0 <= i < 6 and 0 <= j < 7 and b[i, j] == UNKNOWN for i, j in nbrs)
    assert np.array_equal(got, want)
    assert not got[2, 2] and got[1, 1]  # the obstacle is no frontier; corners of the free block are
    # gain = unknown cells within the radius, counted by hand for one cell
    r, c = 1, 1
    assert gain_at(b, np.array([r * 7 + c]), 1.5)[0] == sum(b[i, j] == UNKNOWN for i in range(0, 3) for j in range(0, 3))
    # and at every cell, the convolution of the unknown cells with the sensor's disk
    every = np.arange(b.size)
    assert np.array_equal(gain_at(b, every, 1.5).reshape(b.shape), gain_map(b, 1.5))
    assert np.array_equal(gain_at(b, every, 3.0).reshape(b.shape), gain_map(b, 3.0))


def _random_belief(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A belief with blobs of known ground in unknown terrain, and scattered obstacles."""
    b = np.full(shape, UNKNOWN, dtype=np.uint8)
    for _ in range(rng.integers(3, 9)):
        r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        s = rng.integers(3, 14)
        b[max(r - s, 0):r + s, max(c - s, 0):c + s] = FREE
    b[(rng.random(shape) < 0.15) & (b == FREE)] = IMPASSABLE
    return b


def _disk_sum(values: np.ndarray, radius: float) -> np.ndarray:
    """The sum of ``values`` within ``radius`` of every cell, by convolution with the
    sensor's disk (outside the map counts 0)."""
    off = disk_offsets(radius)
    r = int(np.abs(off).max())
    kernel = np.zeros((2 * r + 1, 2 * r + 1))
    kernel[off[:, 0] + r, off[:, 1] + r] = 1.0
    return ndimage.convolve(values, kernel, mode="constant", cval=0.0)


def gain_map(belief: np.ndarray, radius: float) -> np.ndarray:
    """The reference gain: UNKNOWN cells within ``radius`` of every cell (outside the map
    counts 0)."""
    return np.rint(_disk_sum((np.asarray(belief) == UNKNOWN).astype(np.float64), radius)).astype(np.int64)


def _graph_costs(b: np.ndarray, start: tuple[int, int], unknown_cost, p_impassable=None) -> np.ndarray:
    """The reference travel costs: SciPy's Dijkstra on the explicit graph. Every pair of
    8-neighbours that are both crossable is an edge of weight ``(a + b) / 2`` times its
    length (scikit-image's ``MCP_Geometric`` cost model), a diagonal one only if both cells
    it passes are crossable (the path planner's rule). With ``p_impassable``, an unknown
    cell costs its expected cost, by hand: a free one ``unknown_cost``, a blocked one DETOUR."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    if p_impassable is not None:
        unknown_cost = (1 - p_impassable) * unknown_cost + p_impassable * max(DETOUR, unknown_cost)
    costs = np.where(b == FREE, 1.0, unknown_cost)
    costs[b == IMPASSABLE] = -1.0
    h, w = b.shape
    rows, cols, weights = [], [], []
    for r in range(h):
        for c in range(w):
            if costs[r, c] < 0:
                continue
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    rr, cc = r + dr, c + dc
                    if not (dr or dc) or not (0 <= rr < h and 0 <= cc < w) or costs[rr, cc] < 0:
                        continue
                    if dr and dc and (costs[rr, c] < 0 or costs[r, cc] < 0):
                        continue
                    rows.append(r * w + c)
                    cols.append(rr * w + cc)
                    weights.append((np.sqrt(2.0) if dr and dc else 1.0) * 0.5 * (costs[r, c] + costs[rr, cc]))
    graph = coo_matrix((weights, (rows, cols)), shape=(h * w, h * w)).tocsr()
    cum = dijkstra(graph, indices=start[0] * w + start[1]).reshape(h, w)
    return np.where(np.isfinite(cum) & (costs >= 0), cum, np.inf)


def _whole_map_target(b, pos, *, radius, unknown_cost, others, allowed=None, excluded=(), heading=None,
                      p_impassable=None):
    """The reference target choice: every cell rated over the whole map (gain by convolution,
    costs by SciPy), the lowest score, ties to the lowest flat index. With ``p_impassable``
    the gain counts each unknown cell by the binary entropy of its prediction, by hand."""
    front = frontier_mask(b)
    if allowed is not None:
        front &= allowed
    for cell in excluded:
        front[cell] = False
    gain = gain_map(b, radius)
    cost = _graph_costs(b, pos, unknown_cost, p_impassable)
    front &= (gain > 0) & np.isfinite(cost)
    if p_impassable is not None:
        q = p_impassable
        bits = -(q * np.log2(q) + (1 - q) * np.log2(1 - q))  # q is in (0, 1) here
        gain = _disk_sum(np.where(b == UNKNOWN, bits, 0.0), radius)
    if not front.any():
        return None
    score = cost - 2 * radius * gain / len(disk_offsets(radius))
    rows, cols = np.indices(b.shape)
    if heading is not None:
        r0, c0, angle = heading
        dr, dc = rows - r0, cols - c0
        score = score - radius * (dr * np.sin(angle) + dc * np.cos(angle)) / np.maximum(np.hypot(dr, dc), 1e-9)
    for r, c in others:
        score = score + 4 * radius * ((rows - r) ** 2 + (cols - c) ** 2 <= (2 * radius) ** 2)
    score = np.where(front, score, np.inf)
    return divmod(int(np.argmin(score)), b.shape[1])


def test_travel_costs_equal_scipy_dijkstra_without_corner_cutting():
    rng = np.random.default_rng(11)
    for trial in range(20):
        b = _random_belief(rng, (int(rng.integers(5, 60)), int(rng.integers(5, 60))))
        free = np.argwhere(b != IMPASSABLE)
        pos = tuple(int(v) for v in free[rng.integers(len(free))])
        uc = float(rng.choice([1.0, 1.5, 3.0]))
        want = _graph_costs(b, pos, uc)
        got = travel_costs(b, pos, uc)
        assert np.array_equal(np.isfinite(got), np.isfinite(want)), trial
        assert np.allclose(got[np.isfinite(got)], want[np.isfinite(want)], rtol=0, atol=1e-9), trial
        # bounded: every settled cell has its whole-map cost, and every cell within the slack is settled
        targets = frontier_mask(b)
        part = travel_costs(b, pos, uc, targets=targets, slack=5.0)
        fin = np.isfinite(part)
        assert np.array_equal(part[fin], got[fin]), trial
        if (targets & np.isfinite(got)).any():
            c0 = got[targets & np.isfinite(got)].min()
            assert fin[np.isfinite(got) & (got <= c0 + 5.0)].all(), trial


def test_the_bounded_target_choice_is_the_whole_map_choice():
    rng = np.random.default_rng(5)
    for trial in range(120):
        shape = (int(rng.integers(8, 70)), int(rng.integers(8, 70)))
        b = _random_belief(rng, shape)
        free = np.argwhere(b == FREE)
        if not len(free):
            continue
        pos = tuple(int(v) for v in free[rng.integers(len(free))])
        kw = dict(radius=float(rng.choice([1.5, 3.0, 4.0, 6.5])), unknown_cost=float(rng.choice([1.0, 1.5, 2.5])),
                  others=[tuple(int(v) for v in rng.integers(0, shape)) for _ in range(rng.integers(0, 4))])
        if rng.random() < 0.5:
            kw["heading"] = (shape[0] / 2, shape[1] / 2, float(rng.uniform(0, 2 * np.pi)))
        if rng.random() < 0.3:
            kw["allowed"] = rng.random(shape) < 0.7
        if rng.random() < 0.3 and len(free) > 1:
            kw["excluded"] = {tuple(int(v) for v in free[i]) for i in rng.integers(0, len(free), 3)}
        assert choose_target(b, pos, **kw) == _whole_map_target(b, pos, **kw), (trial, kw)


def test_a_chosen_target_is_one_the_path_planner_reaches():
    """The pick's search and the path planner agree on what is reachable: every target
    chosen has an A* path on the same belief (unknown passable), and a rover shut in by
    diagonal gaps (crossable only by cutting a corner) gets no target at all."""
    rng = np.random.default_rng(21)
    for trial in range(80):
        b = _random_belief(rng, (int(rng.integers(8, 50)), int(rng.integers(8, 50))))
        b[(rng.random(b.shape) < 0.2)] = IMPASSABLE  # many diagonal gaps
        free = np.argwhere(b == FREE)
        if not len(free):
            continue
        pos = tuple(int(v) for v in free[rng.integers(len(free))])
        target = choose_target(b, pos, radius=3.0, unknown_cost=1.5, others=[])
        if target is not None:
            assert plan_path(b, pos, target) is not None, trial
    shut = np.full((12, 12), UNKNOWN, dtype=np.uint8)
    shut[:2] = FREE  # known ground, frontier cells along its edge
    shut[5, 5] = FREE  # the rover, its four orthogonal neighbours impassable: only corners lead out
    for cell in ((4, 5), (6, 5), (5, 4), (5, 6)):
        shut[cell] = IMPASSABLE
    assert choose_target(shut, (5, 5), radius=2.0, unknown_cost=1.5, others=[]) is None
    shut[4, 5] = UNKNOWN  # a way out
    target = choose_target(shut, (5, 5), radius=2.0, unknown_cost=1.5, others=[])
    assert target is not None and plan_path(shut, (5, 5), target) is not None


def test_a_pick_with_a_layer_of_another_shape_or_a_rover_off_the_map_is_one_line():
    """The compiled search reads its layers unchecked, so a wrong shape never reaches it."""
    b = np.full((6, 7), FREE, dtype=np.uint8)
    b[0] = UNKNOWN
    kw = dict(radius=2.0, unknown_cost=1.5, others=[])
    with pytest.raises(FedmapError, match="allowed is 6x6, the map is 6x7"):
        choose_target(b, (3, 3), allowed=np.ones((6, 6), bool), **kw)
    with pytest.raises(FedmapError, match="p_impassable is 42, the map is 6x7"):
        choose_target(b, (3, 3), p_impassable=np.zeros(42), **kw)
    with pytest.raises(FedmapError, match=r"rover position \(6, 0\) is outside the 6x7 map"):
        choose_target(b, (6, 0), **kw)
    assert choose_target(b, (3, 3), allowed=np.ones((6, 7), bool), **kw) == choose_target(b, (3, 3), **kw)


def test_the_target_choice_with_a_prediction_is_the_whole_map_choice():
    """The same with a predictor's P(impassable): unknown cells cost their expected cost and
    count their entropy in the gain. Every map has one shape, so each pick starts from the
    buffers the last one left (they must be as made)."""
    rng = np.random.default_rng(9)
    shape = (37, 53)
    for trial in range(60):
        b = _random_belief(rng, shape)
        free = np.argwhere(b == FREE)
        if not len(free):
            continue
        pos = tuple(int(v) for v in free[rng.integers(len(free))])
        p = rng.uniform(0.01, 0.99, shape)
        kw = dict(radius=float(rng.choice([1.5, 3.0, 4.0])), unknown_cost=float(rng.choice([1.0, 1.5])),
                  others=[tuple(int(v) for v in rng.integers(0, shape)) for _ in range(rng.integers(0, 3))],
                  p_impassable=p)
        if rng.random() < 0.5:
            kw["heading"] = (shape[0] / 2, shape[1] / 2, float(rng.uniform(0, 2 * np.pi)))
        if trial % 2:  # a pick that finds nothing (no cell allowed) searches everything it reaches first
            assert choose_target(b, pos, allowed=np.zeros(shape, bool), **kw) is None
        assert choose_target(b, pos, **kw) == _whole_map_target(b, pos, **kw), trial


# ---------------------------------------------------------------- missions


def _small(**kw) -> MissionConfig:
    base = dict(rovers=3, steps=36, sync_every=6, speed=2, sensor_radius=4.0, eval_pairs=12,
                strategies=("none", "raw", "central"), link=LinkConfig(loss=0.3, seed=5))
    base.update(kw)
    return MissionConfig(**base)


@pytest.fixture(scope="module")
def mission():
    truth = _maze()
    return truth, run_mission(_small(), truth)


def test_rovers_never_enter_impassable_cells_and_move_legally(mission):
    truth, result = mission
    for run in result.runs.values():
        for trail in run.trails:
            assert len(trail) > 5  # they do drive
            for (r0, c0), (r1, c1) in zip(trail, trail[1:]):
                assert max(abs(r1 - r0), abs(c1 - c0)) == 1
            assert all(truth.classes[cell] != IMPASSABLE for cell in trail)


def test_coverage_equals_a_brute_force_count(mission):
    truth, result = mission
    c = result.config
    run = result.runs["none"]
    # replay each rover's trail: every cell within the radius of a visited cell is observed
    seen = np.zeros(truth.shape, dtype=bool)
    for trail in run.trails:
        for pr, pc in trail:
            for r in range(truth.shape[0]):
                for col in range(truth.shape[1]):
                    if (r - pr) ** 2 + (col - pc) ** 2 <= c.sensor_radius**2:
                        seen[r, col] = True
    assert run.series.coverage[-1] == pytest.approx(seen.mean())
    assert 0 < run.series.coverage[-1] <= 1


def test_raw_global_map_is_exactly_the_union_of_delivered_observations(mission):
    truth, result = mission
    run = result.runs["raw"]
    union = np.full(truth.shape, UNKNOWN, dtype=np.uint8)
    delivered = [m for m in run.ledger if m.direction == "up" and m.status == "delivered"]
    assert delivered and any(m.status == "lost" for m in run.ledger)
    # the global map is the union of what the delivered uplinks carried: decode them again
    received = run.sharing.journal.received  # (round, rover, payload) as the base got them
    assert len(received) == len(delivered)
    for _, _, payload in received:
        cells = decode_map(unpack_up(payload)[3], expected_shape=truth.shape)
        assert np.all((cells == UNKNOWN) | (cells == truth.classes))  # observations are truth
        union = np.where(cells != UNKNOWN, cells, union)
    assert np.array_equal(run.frames[-1].global_map, union)
    # and it is strictly less than what the rovers observed (messages were lost) or equal
    assert (union != UNKNOWN).mean() <= run.series.coverage[-1]


def test_link_drops_exactly_the_seeded_messages(mission):
    _, result = mission
    run = result.runs["raw"]
    for m in run.ledger:
        d = 0 if m.direction == "up" else 1
        rng = np.random.default_rng(np.random.SeedSequence([5, m.round, m.rover, d]))
        assert (m.status == "lost") == (rng.random() < 0.3)
    # every strategy sees the same link: lost (round, rover, direction) are a property of the seed
    link = Link(LinkConfig(loss=0.3, seed=5), StarTopology((0, 0)))
    draws = [link.lost(r, k, "up") for r in range(1, 200) for k in range(3)]
    assert 0.2 < np.mean(draws) < 0.4
    assert not any(Link(LinkConfig(loss=0.0), StarTopology((0, 0))).lost(r, 0, "up") for r in range(50))
    assert all(Link(LinkConfig(loss=1.0), StarTopology((0, 0))).lost(r, 0, "down") for r in range(50))


def test_same_seed_same_series_and_bytes(mission):
    truth, result = mission
    again = run_mission(_small(strategies=("raw",)), truth)
    a, b = result.runs["raw"], again.runs["raw"]
    assert a.series == b.series and a.summary == b.summary
    assert [m.to_dict() for m in a.ledger] == [m.to_dict() for m in b.ledger]
    assert a.sharing.journal.received == b.sharing.journal.received


def test_strategies_side_by_side_in_processes_are_the_runs_one_after_another(mission):
    """workers=2 forks a process per strategy (two at a time): every run equals the serial
    run's (series, summary, ledger, frames, trails, last views), in the serial order, and the
    progress callbacks still see every strategy start and every step."""
    from fedmap.mission.sim import can_fork

    if not can_fork():
        pytest.skip("no fork on this OS")
    truth, _ = mission
    config = _small(strategies=("none", "raw", "fedmap"))  # fedmap: its ends hold a model
    serial = run_mission(config, truth)
    started, steps = [], {}
    forked = run_mission(config, truth, workers=2, on_strategy=started.append,
                         on_step=lambda name, t, cov: steps.setdefault(name, []).append(t))
    assert list(forked.runs) == list(serial.runs) and sorted(started) == sorted(serial.runs)
    assert all(steps[n] == list(range(1, 37)) for n in serial.runs), steps
    for name, a in serial.runs.items():
        b = forked.runs[name]
        assert a.series == b.series and a.summary == b.summary and a.trails == b.trails
        assert [m.to_dict() for m in a.ledger] == [m.to_dict() for m in b.ledger]
        assert len(a.frames) == len(b.frames) and all(
            np.array_equal(x, y) for fa, fb in zip(a.frames, b.frames) for x, y in zip(fa.beliefs, fb.beliefs))
        assert all(np.array_equal(x, y) for x, y in zip(a.views, b.views))
        assert b.sharing is None  # the ends' state stays in its process


def test_budget_and_range_are_enforced():
    truth = _maze()
    cfg = _small(strategies=("raw",), steps=24, link=LinkConfig(uplink_bytes=60, downlink_bytes=80, max_range=8.0))
    run = run_mission(cfg, truth).runs["raw"]
    statuses = {m.status for m in run.ledger}
    assert "out of range" in statuses or "over budget" in statuses
    for m in run.ledger:
        assert m.bytes <= (60 if m.direction == "up" else 80)
        if m.status in ("out of range", "over budget"):
            assert m.bytes == 0


def test_central_covers_at_least_as_fast_as_none(mission):
    _, result = mission
    assert result.runs["central"].series.redundant[-1] <= result.runs["none"].series.redundant[-1]
    assert result.runs["central"].summary.final_belief_accuracy_mean >= \
        result.runs["none"].summary.final_belief_accuracy_mean


# ---------------------------------------------------------------- errors


@pytest.mark.parametrize("kw, message", [
    ({"strategies": ("none", "fedmapp")}, "unknown strategy 'fedmapp' (did you mean 'fedmap'?)"),
    ({"sync_every": 0}, "sync_every must be an integer >= 1"),
    ({"link": {"uplink_bytes": -1}}, "uplink_bytes must be a non-negative"),
])
def test_bad_settings_are_one_line_errors(kw, message):
    with pytest.raises(FedmapError, match=re.escape(message)) as e:
        link = kw.pop("link", None)
        MissionConfig(**kw, link=LinkConfig(**link) if link else LinkConfig())
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("kw, message", [
    ({"starts": ((0, 0), (0, 1), (-1, 5))}, r"start of rover 2 \[-1, 5\] is outside the 40x40 map"),
    ({"starts": ((0, 0), (0, 1), (5, 5))}, r"start of rover 2 \[5, 5\] is impassable"),
    ({"lander": (99, 0)}, "lander"),
])
def test_bad_starts_are_one_line_errors(kw, message):
    truth = _maze()
    truth.classes[5, 5] = IMPASSABLE
    truth.classes[0, :2] = FREE
    with pytest.raises(FedmapError, match=message) as e:
        run_mission(_small(**kw), truth)
    assert "\n" not in str(e.value)


def test_more_rovers_than_free_start_cells():
    c = np.full((12, 12), IMPASSABLE, dtype=np.uint8)
    c[5:7, 5] = FREE
    with pytest.raises(FedmapError, match="3 rovers but only 2 free start cells"):
        run_mission(_small(), GridMap(c))


def test_mission_toml_errors(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text('[mission]\nstrategies = ["raw", "centrl"]\n')
    with pytest.raises(FedmapError, match="did you mean 'central'"):
        load_mission(p)
    p.write_text("[mission]\nsync_every = -2\n")
    with pytest.raises(FedmapError, match="sync_every"):
        load_mission(p)
    p.write_text("[link]\ndownlink_bytes = -5\n")
    with pytest.raises(FedmapError, match="downlink_bytes must be a non-negative"):
        load_mission(p)
    p.write_text("[mision]\nsteps = 3\n")
    with pytest.raises(FedmapError, match="did you mean 'mission'"):
        load_mission(p)


# ---------------------------------------------------------------- one implementation of the math


def test_fedmap_strategy_is_one_round_of_fedmap_run():
    """One sync with a perfect link: the base's model equals run_federation (the rover and
    base steps of `fedmap run`) on the rovers' local maps at that sync."""
    from fedmap.config import method_config
    from fedmap.federation.runner import run_federation
    from fedmap.mission.ends.model import COUNT_BYTES
    from fedmap.mission.ends.protocol import UP_HEADER, torch_threads
    from fedmap.pipeline import initial_weights

    truth = _maze(32)
    cfg = _small(rovers=2, steps=6, sync_every=6, strategies=("fedmap",), link=LinkConfig(loss=0.0),
                 methods={"fedmap": {"epochs": 15}})
    run = run_mission(cfg, truth).runs["fedmap"]
    strat = run.sharing
    assert strat.base.rounds_aggregated == 1
    pc = method_config("fedmap", epochs=15, seed=cfg.seed)
    init = initial_weights(pc, 32)
    locals_ = [truth.with_classes(r.local, f"rover {k}") for k, r in enumerate(strat.team)]
    with torch_threads():  # the mission's thread setting: the same float order
        fed = run_federation(init, pc.model.network(32), locals_, pc.federation)
    for name, w in fed.weights.items():
        np.testing.assert_array_equal(strat.base.held_w[name], w)
        for k in range(2):  # and every rover decoded the same broadcast
            np.testing.assert_array_equal(strat.rovers[k].held_w[name], w)
    up = [m.bytes for m in run.ledger if m.direction == "up"]
    assert sorted(up) == sorted(b + UP_HEADER + COUNT_BYTES for b in fed.history[0].uplink_bytes.values())


@pytest.mark.parametrize("kept, catch_up", [(0, "keyframe"), (8, "chain")])
def test_lost_broadcasts_cost_keyframes_or_chains_and_rovers_stay_in_step_with_the_base(kept, catch_up):
    """Without a window a rover that missed a broadcast gets a keyframe; with one, the chain
    of broadcasts it missed (smaller than the keyframe here)."""
    truth = _maze(32)
    cfg = _small(rovers=2, steps=16, sync_every=2, strategies=("fedmap",), link=LinkConfig(loss=0.4, seed=1),
                 methods={"fedmap": {"epochs": 5, "versions_kept": kept}})
    run = run_mission(cfg, truth).runs["fedmap"]
    strat = run.sharing
    kinds = {(m.kind, m.status) for m in run.ledger if m.direction == "down"}
    assert (catch_up, "delivered") in kinds and ("broadcast", "lost") in kinds
    for k in range(2):
        if strat.rovers[k].version == strat.base.bc.version:  # the same version is the same weights
            for name, w in strat.base.held_w.items():
                np.testing.assert_array_equal(strat.rovers[k].held_w[name], w)
    assert strat.base.rounds_aggregated >= 1


def test_latency_delays_every_delivery_and_waypoints_are_followed():
    truth = _maze()
    wps = (((5, 5), (30, 30)), ((34, 4), (4, 34)), ((20, 35), (20, 4)))
    for r, c in (w for ws in wps for w in ws):
        truth.classes[r, c] = FREE
    cfg = _small(strategies=("raw",), link=LinkConfig(loss=0.0, latency=3), mode="waypoints", waypoints=wps)
    run = run_mission(cfg, truth).runs["raw"]
    delivered = [m for m in run.ledger if m.status == "delivered"]
    assert delivered and all(m.arrival == m.step + 3 for m in delivered)
    # downlinks leave when the uplinks of their round arrive: latency after the sync
    assert all(m.step % cfg.sync_every == 3 for m in delivered if m.direction == "down")
    # each rover heads for its first waypoint: its trail gets closer to it than it started
    for k, trail in enumerate(run.trails):
        goal = np.array(wps[k][0])
        d = [np.hypot(*(np.array(p) - goal)) for p in trail]
        assert min(d) < d[0]


def test_a_rover_profile_applies_in_a_mission_as_in_a_run(tmp_path):
    """`[thresholds] rover = "mer"` gives a mission the same limits it gives `fedmap run`
    (the profile's, with a limit set beside it winning), not the defaults."""
    from fedmap.config import resolve
    from fedmap.maps.traversability import rover_profile
    from fedmap.mission.settings import load_mission

    toml = tmp_path / "m.toml"
    toml.write_text('[thresholds]\nrover = "mer"\nmax_slope_deg = 12.0\n')
    _, _, out = load_mission(toml)
    run = resolve(None, [{"thresholds": {"rover": "mer", "max_slope_deg": 12.0}}])["thresholds"]
    assert out["thresholds"] == run
    mer = rover_profile("mer").to_dict()
    assert out["thresholds"]["max_step_m"] == mer["max_step_m"] and out["thresholds"]["max_slope_deg"] == 12.0


# ---------------------------------------------------------------- knowing vs guessing


def _executed_by_hand(truth: np.ndarray, pred: np.ndarray, n_pairs: int, seed: int) -> float:
    """Executed path success, step by step: drive the path planned on ``pred`` on ``truth``."""
    from fedmap.maps.planning import astar, sample_pairs
    pt, pp = truth == FREE, pred == FREE
    ok = total = 0
    for s, g in sample_pairs(pt, n_pairs, seed=seed):
        if astar(pt, s, g) is None:
            continue
        total += 1
        path = astar(pp, s, g)
        if path is None or path[-1] != g:
            continue
        cells_ok = all(pt[c] for c in path)
        steps_ok = all(max(abs(b[0] - a[0]), abs(b[1] - a[1])) == 1 and
                       (a[0] == b[0] or a[1] == b[1] or (pt[b[0], a[1]] and pt[a[0], b[1]]))
                       for a, b in zip(path, path[1:]))
        ok += cells_ok and steps_ok
    return ok / total if total else 1.0


def test_executed_path_success_counts_paths_that_drive_safely_to_the_goal():
    from fedmap.evaluation.paths import path_f1
    truth = _maze(40, 8).classes
    assert path_f1(truth, truth, n_pairs=30, seed=2).success == 1.0
    wrong = truth.copy()
    wrong[truth == IMPASSABLE] = FREE  # believes every hazard is free ground: paths cut through them
    unknown = np.where(np.arange(40)[None, :] < 20, truth, UNKNOWN).astype(np.uint8)  # half the map unknown
    for pred in (wrong, unknown):
        got = path_f1(truth, pred, n_pairs=30, seed=2).success
        assert got == pytest.approx(_executed_by_hand(truth, pred, 30, 2))
    assert path_f1(truth, wrong, n_pairs=30, seed=2).success < 1.0


def test_beliefs_are_scored_on_observed_and_unobserved_cells_apart():
    config = MissionConfig(rovers=2, steps=30, sync_every=5, sensor_radius=4.0, strategies=("none", "raw"),
                           eval_pairs=5, link=LinkConfig(loss=0.0))
    result = run_mission(config, _maze(40, 9), frames=1)
    truth = result.truth.classes
    for run in result.runs.values():
        s = run.sharing
        seen = np.stack([r.local != UNKNOWN for r in s.team]).any(axis=0)
        for k in range(config.rovers):
            b = s.belief(k)
            assert run.series.accuracy_observed[-1][k] == pytest.approx((b == truth)[seen].mean())
            assert run.series.accuracy_unobserved[-1][k] == 0.0  # sharing observations only: nothing guessed
        assert run.summary.final_path_success_mean == pytest.approx(np.mean(run.series.eval.belief_success[-1]))
    # raw shares every observation, so its rovers know what the team observed
    assert np.mean(result.runs["raw"].series.accuracy_observed[-1]) > np.mean(
        result.runs["none"].series.accuracy_observed[-1])


def test_a_downlink_over_the_budget_arrives_in_chunks_over_the_rounds(monkeypatch):
    from fedmap.mission.ends.model import ModelRover
    completed: list[tuple[int, str]] = []
    real = ModelRover._receive_chunk

    def spy(self, reference, reports, body):
        before = self.version
        ok = real(self, reference, reports, body)
        if self.version != before:
            completed.append((self.k, self.version))
        return ok

    monkeypatch.setattr(ModelRover, "_receive_chunk", spy)
    truth = _maze(32)
    budget = 400
    cfg = _small(rovers=2, steps=24, sync_every=2, strategies=("fedmap",),
                 link=LinkConfig(loss=0.3, seed=2, downlink_bytes=budget),
                 methods={"fedmap": {"epochs": 5, "versions_kept": 8}})
    run = run_mission(cfg, truth).runs["fedmap"]
    strat = run.sharing
    down = [m for m in run.ledger if m.direction == "down"]
    assert all(m.bytes <= budget for m in down)
    assert any(m.kind.endswith(" chunk") and m.status == "delivered" for m in down)
    assert any(m.kind.endswith(" chunk") and m.status == "lost" for m in down)  # and a lost one was sent again
    for k in range(2):  # whatever a rover holds is a model the base held, bit for bit
        if strat.rovers[k].version == strat.base.bc.version:
            for name, w in strat.base.held_w.items():
                np.testing.assert_array_equal(strat.rovers[k].held_w[name], w)
    # rovers that missed a broadcast were resynchronised by downlinks put together from chunks
    assert completed
    assert strat.base.rounds_aggregated >= 1


def test_rate_control_sends_the_best_update_that_fits_rather_than_nothing():
    truth = _maze(32)
    cfg = _small(rovers=2, steps=12, sync_every=2, strategies=("fedmap",),
                 link=LinkConfig(loss=0.0, uplink_bytes=700, downlink_bytes=900), methods={"fedmap": {"epochs": 5}})
    run = run_mission(cfg, truth).runs["fedmap"]
    up = [m for m in run.ledger if m.direction == "up"]
    assert all(m.status == "delivered" and 0 < m.bytes <= 700 for m in up)  # none over budget
    assert any(m.kind.startswith("update top-k") for m in up)  # the codec's own update did not fit
    down = [m for m in run.ledger if m.direction == "down"]
    assert all(m.bytes <= 900 for m in down) and not any(m.status == "over budget" for m in down)
    s = run.sharing
    for k in range(2):  # on a perfect link every rover ends holding the base's model, bit for bit
        assert s.rovers[k].version == s.base.bc.version


def test_training_on_what_changed_selects_the_new_cells_and_a_seeded_replay_sample():
    from fedmap.mission.ends.model import MIN_REPLAY

    truth = maze(40, seed=2)
    base = dict(rovers=2, steps=30, sync_every=10, speed=2, sensor_radius=4.0, eval_pairs=8,
                strategies=("fedmap",), methods={"fedmap": {"epochs": 5}}, link=LinkConfig(loss=0.0))
    whole = run_mission(MissionConfig(**base), truth).runs["fedmap"].sharing
    changed = run_mission(MissionConfig(**base, train_on="changed", replay=0.5), truth).runs["fedmap"].sharing
    # the whole map: every known cell at every sync (fedmap's preset trains masked)
    for rec in whole.journal.trained_cells:
        assert rec["cells"] > 0
    # round 1 trains on the whole map; later rounds on the new cells and a replay sample
    first = [r for r in changed.journal.trained_cells if r["round"] == 1]
    assert first and all(r["cells"] > 0 for r in first)
    later = [r for r in changed.journal.trained_cells if r["round"] > 1]
    assert later
    for rec in later:
        k = rec["rover"]
        r = changed.team[k]
        # from the record of when each cell was first observed: the new cells are those observed
        # after the last cell it had at the previous sync, up to this sync; the rest replay
        prev, hi = (rec["round"] - 1) * 10, rec["round"] * 10
        seen = r.obs_step[(r.obs_step >= 0) & (r.obs_step <= prev)]
        since = int(seen.max())
        new = int(((r.obs_step > since) & (r.obs_step <= hi)).sum())
        old = int(((r.obs_step >= 0) & (r.obs_step <= since)).sum())
        assert rec["cells"] == new + min(old, max(int(np.ceil(0.5 * new)), MIN_REPLAY))
    with pytest.raises(FedmapError, match="did you mean 'changed'"):
        MissionConfig(train_on="chanegd")


@pytest.mark.parametrize("kind", ["rovers", "helicopter"])
def test_the_central_map_kept_between_writes_is_the_overlay_of_every_rover(kind, monkeypatch):
    """``central``'s base keeps the team's map until a rover's map is written: at every call
    it equals the overlay built anew from every rover's map (team order, a later known cell
    over an earlier one), with rovers and with a helicopter (coarse cells); and it cannot
    be written through."""
    from fedmap.mission.ends.raw import CentralBase
    from fedmap.mission.settings import HelicopterConfig

    kept = CentralBase.global_map
    calls = []

    def checked(self):
        got = kept(self)
        want = np.full(self.shape, UNKNOWN, dtype=np.uint8)
        for r in self.team:
            want = np.where(r.local != UNKNOWN, r.local, want)
        assert np.array_equal(got, want) and not got.flags.writeable
        calls.append(int((got != UNKNOWN).sum()))
        return got

    monkeypatch.setattr(CentralBase, "global_map", checked)
    heli = {"helicopters": 1, "helicopter": HelicopterConfig(sensor_radius=5.0, resolution=2)} \
        if kind == "helicopter" else {}
    run_mission(_small(steps=25, strategies=("central",), **heli), _maze())
    assert len(calls) > 25 and calls[-1] > calls[0]  # asked for at every step, and it grew


def test_rovers_training_side_by_side_send_what_they_send_one_after_another(monkeypatch):
    """A sync's rovers train on threads side by side (``protocol.side_by_side``), each on one
    torch thread: the same losses, bytes on the link and models as training them in turn
    (one core), including a rejected update's place in the journal."""
    from fedmap.mission.ends import protocol
    from fedmap.mission.network import transport

    truth = _maze(32)
    cfg = _small(rovers=3, steps=12, sync_every=4, strategies=("fedmap",), link=LinkConfig(loss=0.2, seed=2),
                 methods={"fedmap": {"epochs": 4}})
    pools = []

    class Counted(protocol.ThreadPoolExecutor):
        def __init__(self, n):
            pools.append(n)
            super().__init__(n)

    monkeypatch.setattr(protocol, "ThreadPoolExecutor", Counted)
    monkeypatch.setattr(protocol, "cpu_cores", lambda: 2)
    two = run_mission(cfg, truth).runs["fedmap"]
    assert pools and set(pools) == {2}  # 3 rovers per sync on 2 cores
    monkeypatch.setattr(transport, "side_by_side", lambda calls: None)  # each rover trains in its uplink, in turn
    one = run_mission(cfg, truth).runs["fedmap"]
    assert len(pools) == 3  # one pool per sync, none since
    assert one.ledger == two.ledger and sum(m.bytes for m in one.ledger) > 0
    losses = [r.sharing.rovers[0].journal.losses for r in (one, two)]
    assert losses[0] == losses[1] and len(losses[0]) >= 6
    for a, b in zip(one.sharing.rovers, two.sharing.rovers):
        for name, w in a.held_w.items():
            np.testing.assert_array_equal(b.held_w[name], w)


def test_a_raw_downlink_over_its_budget_sends_the_newest_cells_that_fit():
    """A downlink budget below what the base has for a rover cuts the message to the cells
    stamped latest (protocol.cut_to_budget) instead of sending nothing: a base that left
    nothing out (BaseEnd.withheld: None) once turned its candidate mask into integers, so
    the cut-offs were read at cells 0 and 1 and no cut fitted."""
    from fedmap.mission import load_mission, mission_terrain, run_mission

    def downlinks(budget):
        link = {"loss": 0.0} if budget is None else {"loss": 0.0, "downlink_bytes": budget}
        config, source, _ = load_mission(None, seed=0, mission={"strategies": ["raw"], "steps": 60},
                                         overrides=[{"link": link}])
        truth, *_ = mission_terrain(config, source)
        return {(m.round, m.rover): m.bytes for m in run_mission(config, truth).runs["raw"].ledger
                if m.direction == "down"}

    free = downlinks(None)
    budget = min(free.values()) * 7 // 8  # below every whole downlink: each must be cut to be sent
    cut = downlinks(budget)
    sent = {key: b for key, b in cut.items() if b > 0}
    assert sent, cut  # cut to the newest cells, not dropped
    assert all(b <= budget < free[key] for key, b in sent.items())


@pytest.mark.parametrize("shape", [(1, 50), (50, 1), (7, 64)])
def test_a_map_too_small_for_a_mission_says_so(shape):
    """A 1x50 class map said "only 1 free start cells": the map's size is the problem."""
    c = np.full(shape, FREE, dtype=np.uint8)
    with pytest.raises(FedmapError, match=rf"the map is {shape[0]}x{shape[1]} cells, too small for a mission") as e:
        run_mission(_small(), GridMap(c))
    assert "\n" not in str(e.value)


def _reach_by_hand(classes, starts, radius):
    """Brute force: flood the free cells 8-connected from the starts, then every known cell within ``radius``."""
    from collections import deque

    h, w = classes.shape
    seen = np.zeros((h, w), bool)
    q = deque(s for s in starts if classes[s] == FREE)
    for s in q:
        seen[s] = True
    while q:
        r, c = q.popleft()
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if 0 <= rr < h and 0 <= cc < w and not seen[rr, cc] and classes[rr, cc] == FREE:
                    seen[rr, cc] = True
                    q.append((rr, cc))
    out = np.zeros((h, w), bool)
    for r, c in zip(*np.nonzero(seen)):
        for rr in range(h):
            for cc in range(w):
                if (rr - r) ** 2 + (cc - c) ** 2 <= radius ** 2:
                    out[rr, cc] = True
    return out & (classes != UNKNOWN)


def test_the_cells_a_team_can_reach_match_a_flood_fill_by_hand():
    from fedmap.mission.world.world import reachable_cells

    rng = np.random.default_rng(4)
    c = np.where(rng.random((30, 30)) < 0.35, IMPASSABLE, FREE).astype(np.uint8)
    c[:, 14] = IMPASSABLE  # a wall with one gap
    c[20, 14] = FREE
    c[0:3, 0:3] = UNKNOWN
    starts = [(5, 5), (25, 25)]
    for s in starts:
        c[s] = FREE
    cfg = _small(sensor_radius=2.5)
    np.testing.assert_array_equal(reachable_cells(GridMap(c), starts, cfg), _reach_by_hand(c, starts, 2.5))


def test_a_walled_off_map_is_plannable_on_the_cells_the_team_can_reach():
    """A mountain walls off 400 of 2,304 cells (more than the sensor radius from any free
    cell): 95 % of the whole map is out of reach, so "plannable" counted over the whole map
    never came. Over the cells the team can reach, raw's team gets there, and the verdict
    names it and says what share of the map those cells are."""
    from fedmap.mission.outputs.report import verdict

    c = np.full((48, 48), FREE, np.uint8)
    c[0:24, 0:24] = IMPASSABLE
    cfg = _small(rovers=3, steps=120, sync_every=10, sensor_radius=4.0, strategies=("none", "raw"),
                 link=LinkConfig(loss=0.0))
    result = run_mission(cfg, GridMap(c))
    raw = result.runs["raw"].summary
    assert raw.reachable_share == pytest.approx((2304 - 400) / 2304)  # rows and columns 0..19 are out of reach
    assert raw.final_coverage < 0.95 <= raw.final_coverage_reachable
    assert raw.ready_step is not None and raw.coverage_reachable_steps[0.95] is not None
    series = result.runs["raw"].series
    assert len(series.coverage_reachable) == len(series.coverage)
    assert all(a >= b - 1e-12 for a, b in zip(series.coverage_reachable, series.coverage))
    line = verdict(result)
    assert "95% coverage of the cells they can reach, 83% of the map" in line and "Soonest: **raw**" in line


def test_the_stop_rule_ends_each_run_at_the_first_step_its_team_knows_the_share_asked():
    """A mission kept stepping after every strategy had observed 99 % of what it could reach.
    With ``stop_coverage`` each run ends at the first step its reachable coverage reaches the
    share (read here from the same mission run without the rule, step for step), is scored in
    full there, and says so; without it (the default) the verdict names the step and the option."""
    from fedmap.mission.outputs.maps_out import mission_maps
    from fedmap.mission.outputs.report import verdict

    c = np.full((48, 48), FREE, np.uint8)
    c[0:24, 0:24] = IMPASSABLE
    cfg = _small(rovers=3, steps=200, sync_every=10, sensor_radius=4.0, strategies=("none", "raw"),
                 link=LinkConfig(loss=0.0))
    full = run_mission(cfg, GridMap(c))
    cut = run_mission(replace(cfg, stop_coverage=0.99), GridMap(c))
    for name in ("none", "raw"):
        whole = full.runs[name].series
        first = next(t for t, v in zip(whole.step, whole.coverage_reachable) if v >= 0.99)
        assert 0 < first < cfg.steps
        run = cut.runs[name]
        assert run.series.step[-1] == first and run.summary.stopped_step == first
        assert run.series.coverage_reachable == whole.coverage_reachable[:first + 1]  # the same run, cut short
        assert run.series.eval.step[-1] == first  # scored in full at its last step
        assert run.frames[-1].step == first
        assert "stopped_step" not in full.runs[name].summary.to_dict()  # no rule: metrics.json as before
        assert run.summary.to_dict()["stopped_step"] == first
    assert mission_maps(cut)["raw_global"].meta["step"] == cut.runs["raw"].summary.stopped_step
    assert "stop_coverage" not in cfg.to_dict() and cut.config.to_dict()["stop_coverage"] == 0.99
    firsts = [cut.runs[n].summary.stopped_step for n in ("none", "raw")]
    assert (f"Stop rule: a run ends once its team has observed 99% of the cells it can reach: none at step "
            f"{firsts[0]}; raw at step {firsts[1]}.") in verdict(cut)
    assert (f"No stop rule (the default: every run takes all 200 steps); every strategy's team had observed 99% "
            f"of the cells it can reach by step {max(firsts)}: --stop-coverage 0.99 ends each run there.") \
        in verdict(full)
    from fedmap.mission.outputs.report import report_md

    assert "a run ends once its team has observed 99% of the cells it can reach" in report_md(cut, title="t")
    assert "a run ends once" not in report_md(full, title="t")
    for bad in (0, 1.5, True, "0.9"):
        with pytest.raises(FedmapError, match="stop_coverage must be a share in"):
            replace(cfg, stop_coverage=bad)


def test_a_mission_whose_records_cannot_fit_is_refused_before_it_starts():
    """`--steps 1000000000` grew to 12 GB and on: what the per-step records need is weighed
    against the memory available before the first step, in one line."""
    from fedmap.mission.sim import STEP_RECORD_BYTES, check_memory

    cfg = _small(steps=1_000_000_000, strategies=("none", "raw"))
    need = (cfg.steps + 1) * (STEP_RECORD_BYTES[0] + STEP_RECORD_BYTES[1] * 3) * 2
    with pytest.raises(FedmapError, match=r"a mission of 1,000,000,000 steps keeps about .* GiB") as e:
        check_memory(cfg, available=need)  # (80 % of it may be used)
    assert "\n" not in str(e.value)
    check_memory(cfg, available=2 * need)  # fits
    assert len(cfg.sync_steps) == 1_000_000_000 // cfg.sync_every  # a range: nothing held per sync
    assert cfg.sync_round(cfg.sync_every * 7) == 7 and cfg.sync_round(cfg.sync_every * 7 + 1) is None


def test_memory_stays_flat_over_steps_within_the_records():
    """Beyond the per-step records (a few hundred bytes a member), a mission holds nothing per
    step: the Python-side growth from step 200 to 600 of raw is within those records."""
    import tracemalloc

    from fedmap.mission.sim import STEP_RECORD_BYTES, prepare_mission

    cfg = _small(steps=600, sync_every=10, strategies=("raw",), link=LinkConfig(loss=0.1, seed=1))
    m = prepare_mission(cfg, _maze(48), frames=1)
    run = m.new_run("raw")
    seen = {}

    def on_step(name, t, coverage):
        if t in (200, 600):
            seen[t] = tracemalloc.get_traced_memory()[0]

    tracemalloc.start()
    try:
        run.run(on_step)
    finally:
        tracemalloc.stop()
    per_step = (seen[600] - seen[200]) / 400
    assert per_step < STEP_RECORD_BYTES[0] + STEP_RECORD_BYTES[1] * cfg.rovers, per_step
