"""``rosgrid``: every rover's whole map as a ROS 2 ``nav_msgs/msg/OccupancyGrid``, merged at the base.

The expected messages are built here, independently of :mod:`fedmap.mission.ends.rosgrid`, with
rosbags' own message classes and CDR codec (map_server's values: 0 free, 100 occupied, -1
unknown; rows from the bottom up, as map_server loads an image).
"""

from __future__ import annotations

import zlib
from types import SimpleNamespace

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from conftest import maze
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.ends.protocol import UP_HEADER, unpack_down, unpack_up
from fedmap.mission.ends.rosgrid import GridCodec, RosgridBase, RosgridRover
from fedmap.mission.settings import DEFAULT_STRATEGIES

TS = get_typestore(Stores.ROS2_HUMBLE)
OCC = "nav_msgs/msg/OccupancyGrid"


def _expected_grid(classes: np.ndarray, resolution: float, stamp: int):
    """The OccupancyGrid a ROS node would publish for ``classes``, written out by hand."""
    T = TS.types
    h, w = classes.shape
    values = np.empty((h, w), dtype=np.int8)
    for r in range(h):
        for c in range(w):  # data row 0 is the map's bottom row (fedmap's last)
            values[h - 1 - r, c] = {FREE: 0, IMPASSABLE: 100, UNKNOWN: -1}[int(classes[r, c])]
    t = T["builtin_interfaces/msg/Time"](sec=stamp, nanosec=0)
    origin = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = T["nav_msgs/msg/MapMetaData"](map_load_time=t, resolution=resolution, width=w, height=h, origin=origin)
    return T[OCC](header=T["std_msgs/msg/Header"](stamp=t, frame_id="map"), info=info, data=values.ravel())


def _rover_end(level: int | None = None, budget: int | None = None):
    """A rover end on a 12x9 map of 0.5 m cells with a few cells of each class observed."""
    local = np.full((12, 9), UNKNOWN, dtype=np.uint8)
    local[2:6, 1:4] = FREE
    local[3, 2] = IMPASSABLE
    local[10, 8] = IMPASSABLE
    rover = SimpleNamespace(local=local, pos=(3, 1), target=(10, 7))
    codec = GridCodec(local.shape, resolution=0.5, origin=(0.0, 0.0), sync_every=6, level=level)
    return RosgridRover(0, rover, [(3, 1)], grids=codec, budget=budget), local


def test_uplink_is_the_cdr_of_the_rovers_occupancy_grid_after_the_uplink_header():
    end, local = _rover_end()
    out = end.uplink(round_no=2)  # stamped at the round's sync step: 2 * 6 s
    assert out is not None and out.payload is not None and out.kind == "grid"
    expected = bytes(TS.serialize_cdr(_expected_grid(local, 0.5, 12), OCC))
    assert len(out.payload) == UP_HEADER + len(expected)
    version, pos, target, body = unpack_up(out.payload)
    assert (version, pos, target) == ("", (3, 1), (10, 7))
    assert body == expected


def test_uplink_decodes_with_rosbags_as_the_rovers_map():
    end, local = _rover_end()
    out = end.uplink(round_no=1)
    assert out is not None and out.payload is not None
    msg = TS.deserialize_cdr(unpack_up(out.payload)[3], OCC)
    assert (msg.info.width, msg.info.height, msg.info.resolution) == (9, 12, 0.5)
    assert msg.header.frame_id == "map" and msg.header.stamp.sec == 6
    data = np.flipud(np.asarray(msg.data).reshape(12, 9))
    assert np.array_equal(data == 0, local == FREE)
    assert np.array_equal(data == 100, local == IMPASSABLE)
    assert np.array_equal(data == -1, local == UNKNOWN)


def test_zlib_variant_is_zlib_level_9_of_the_serialised_grid():
    end, local = _rover_end(level=9)
    out = end.uplink(round_no=1)
    assert out is not None and out.payload is not None
    cdr = bytes(TS.serialize_cdr(_expected_grid(local, 0.5, 6), OCC))
    assert unpack_up(out.payload)[3] == zlib.compress(cdr, 9)
    assert len(out.payload) == UP_HEADER + len(zlib.compress(cdr, 9))


def test_base_merges_as_map_merge_and_sends_the_whole_merged_grid():
    shape = (6, 5)
    codec = GridCodec(shape, resolution=2.0, origin=(0.0, 0.0), sync_every=1, level=None)
    base = RosgridBase(shape, [(0, 0), (5, 4)], grids=codec, budget=None)
    a = np.full(shape, UNKNOWN, dtype=np.uint8)
    b = a.copy()
    a[0:3, :] = FREE
    b[2:6, :] = FREE
    b[2, 2] = IMPASSABLE  # a disagrees (free): occupied wins, as cv::max of map_merge's GridCompositor
    for k, m in enumerate((a, b)):
        end = RosgridRover(k, SimpleNamespace(local=m, pos=(k, k), target=None), [(0, 0), (5, 4)], grids=codec,
                           budget=None)
        out = end.uplink(1)
        assert out is not None and out.payload is not None
        assert base.receive(k, out.payload, 1)
    want = np.where(b != UNKNOWN, b, a)
    assert np.array_equal(base.global_map(), want)
    downs = base.downlinks(1)
    assert set(downs) == {0, 1}
    for out in downs.values():
        assert out.payload is not None
        _, _, reports, body = unpack_down(out.payload)
        assert reports == {0: ((0, 0), None), 1: ((1, 1), None)}
        assert body == bytes(TS.serialize_cdr(_expected_grid(want, 2.0, 1), OCC))


def _small(**kw) -> MissionConfig:  # as tests/test_mission.py
    base = dict(rovers=3, steps=36, sync_every=6, speed=2, sensor_radius=4.0, eval_pairs=12,
                strategies=("raw", "rosgrid", "rosgrid-zlib"), link=LinkConfig(loss=0.0, seed=5))
    base.update(kw)
    return MissionConfig(**base)


@pytest.fixture(scope="module")
def perfect() -> tuple[GridMap, object]:
    truth = maze()
    return truth, run_mission(_small(), truth)


def test_over_a_perfect_link_the_merged_map_is_the_union_of_the_observations(perfect):
    truth, result = perfect
    for name in ("rosgrid", "rosgrid-zlib"):
        run = result.runs[name]
        union = np.full(truth.shape, UNKNOWN, dtype=np.uint8)
        for r in run.sharing.team:  # the last sync is the last step: every observation was sent
            union = np.where(r.local != UNKNOWN, r.local, union)
        assert np.array_equal(run.sharing.global_map(), union)
        # the same knowledge as raw at every sync, so the same mission and the same global map
        assert np.array_equal(run.sharing.global_map(), result.runs["raw"].sharing.global_map())
        assert run.trails == result.runs["raw"].trails
        for end in run.sharing.rovers:  # every rover holds the last merged grid
            assert np.array_equal(end.held(), union)
        assert {m.status for m in run.ledger} == {"delivered"}


def test_bytes_are_whole_grids_every_sync(perfect):
    truth, result = perfect
    cfg = result.config
    h, w = truth.shape
    grid = 104 + h * w  # CDR of an OccupancyGrid with frame "map": 104 bytes around the cells (docs/protocol.md)
    up = [m.bytes for m in result.runs["rosgrid"].ledger if m.direction == "up"]
    down = [m.bytes for m in result.runs["rosgrid"].ledger if m.direction == "down"]
    assert len(up) == len(down) == cfg.rovers * len(cfg.sync_steps)
    assert set(up) == {UP_HEADER + grid}
    assert set(down) == {10 + 9 * cfg.rovers + grid}
    assert sum(m.bytes for m in result.runs["rosgrid-zlib"].ledger) < sum(up) + sum(down)


def test_a_budget_below_one_grid_sends_nothing_and_says_so():
    truth = maze()
    cfg = _small(strategies=("rosgrid",), steps=12, link=LinkConfig(uplink_bytes=1000, downlink_bytes=1000, seed=5))
    run = run_mission(cfg, truth).runs["rosgrid"]
    assert run.ledger and {m.status for m in run.ledger} == {"over budget"}
    assert all(m.bytes == 0 for m in run.ledger)
    assert (run.sharing.global_map() == UNKNOWN).all()


def test_a_lost_grid_goes_again_at_the_next_sync():
    truth = maze()
    run = run_mission(_small(strategies=("rosgrid",), link=LinkConfig(loss=0.4, seed=5)), truth).runs["rosgrid"]
    assert "lost" in {m.status for m in run.ledger}
    base = run.sharing.base
    for k, r in enumerate(run.sharing.team):  # each rover's latest delivered grid is all the base holds from it
        last = max(m.round for m in run.ledger if m.direction == "up" and m.rover == k and m.status == "delivered")
        assert base.latest[k][1] == last * 6
        assert np.all((base.global_map() != UNKNOWN) | (r.local == UNKNOWN) | (r.obs_step > last * 6))


def test_rosgrid_is_selectable_but_not_a_default():
    assert "rosgrid" not in DEFAULT_STRATEGIES and "rosgrid-zlib" not in DEFAULT_STRATEGIES
    assert MissionConfig(strategies=("rosgrid", "rosgrid-zlib")).strategies == ("rosgrid", "rosgrid-zlib")
