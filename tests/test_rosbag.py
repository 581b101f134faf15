"""ROS 2 bags in and out (``fedmap.maps.rosbag``, ``fedmap.mission.outputs.bag``, ``fedmap export
--format rosbag2``): bags written by rosbags' own Writer read as terrain, fedmap's bags read
back with rosbags' AnyReader, and every bad input is one line."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine
from PIL import Image
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from conftest import maze
from fedmap.cli import main
from fedmap.errors import FedmapError
from fedmap.maps.export import export_map
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.io import load_map
from fedmap.maps.ros import read_ros_map
from fedmap.maps.rosbag import bag_map_feed, read_bag_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.outputs.bag import write_mission_bag
from fedmap.mission.outputs.maps_out import write_mission_maps

TS = get_typestore(Stores.ROS2_HUMBLE)
OG = "nav_msgs/msg/OccupancyGrid"
RES, X0, Y0 = 0.5, 12.25, -3.5

# ROS rows, bottom row first, as a mapper publishes them; map_server's thresholds on v / 100:
# free below 0.196 (v <= 19), impassable above 0.65 (v >= 66), unknown between and at -1.
VALUES = np.array([[0, 100, -1, 19, 20],
                   [65, 66, 50, 0, 0],
                   [-1, -1, 100, 100, 10],
                   [0, 0, 0, 0, 99]], dtype=np.int8)
F, X, U = FREE, IMPASSABLE, UNKNOWN
EXPECTED_ROS_ROWS = np.array([[F, X, U, F, U],
                              [U, X, U, F, F],
                              [U, U, X, X, F],
                              [F, F, F, F, X]], dtype=np.uint8)
EXPECTED = EXPECTED_ROS_ROWS[::-1]  # fedmap's row 0 is the top


def _msg(values: np.ndarray, sec: int = 7, frame: str = "map"):
    t = TS.types
    h, w = values.shape
    stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=0)
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=X0, y=Y0, z=0.0),
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = t["nav_msgs/msg/MapMetaData"](map_load_time=stamp, resolution=RES, width=w, height=h, origin=pose)
    return t[OG](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame), info=info,
                 data=np.ascontiguousarray(values).reshape(-1))


def _ros_bag(path, grids=(VALUES,), *, storage=StoragePlugin.SQLITE3, extra=()):
    """A bag written by rosbags' own Writer: OccupancyGrids on /map (one per second) and
    ``extra`` (topic, msgtype, message) of other types."""
    with Writer(path, version=8, storage_plugin=storage) as w:
        c = w.add_connection("/map", OG, typestore=TS)
        for k, values in enumerate(grids):
            w.write(c, (k + 1) * 1_000_000_000, TS.serialize_cdr(_msg(values, sec=k + 1), OG))
        for topic, msgtype, msg in extra:
            c2 = w.add_connection(topic, msgtype, typestore=TS)
            w.write(c2, 5, TS.serialize_cdr(msg, msgtype))
    return path


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_a_rosbags_bag_is_a_terrain_with_the_classes_of_the_same_png_and_ros_yaml(tmp_path, storage):
    bag = _ros_bag(tmp_path / "bag", storage=storage)
    grid = load_map(bag)
    np.testing.assert_array_equal(grid.classes, EXPECTED)
    assert grid.pixel_size == RES and grid.meta["frame_id"] == "map"
    assert grid.transform == Affine(RES, 0.0, X0, 0.0, -RES, Y0 + 4 * RES)  # lower-left corner at the origin
    # the storage file alone, and the bag as a terrain source
    suffix = ".db3" if storage == StoragePlugin.SQLITE3 else ".mcap"
    (storage_file,) = bag.glob(f"*{suffix}")
    np.testing.assert_array_equal(load_map(storage_file).classes, EXPECTED)
    truth = load_truth(TerrainSource(kind="map", path=str(bag)))  # a terrain is cut square (centred)
    np.testing.assert_array_equal(truth.classes, EXPECTED[:, :4])
    assert truth.transform == grid.transform
    # map_server's own raw mode on the same values (an independent reader: PGM, -1 stored as 255)
    Image.fromarray(VALUES[::-1].astype(np.int16).astype(np.uint8), mode="L").save(tmp_path / "raw.pgm")
    (tmp_path / "raw.yaml").write_text(f"image: raw.pgm\nmode: raw\nresolution: {RES}\norigin: [{X0}, {Y0}, 0.0]\n"
                                       "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
    raw = read_ros_map(tmp_path / "raw.yaml")
    np.testing.assert_array_equal(raw.classes, grid.classes)
    assert raw.transform == grid.transform
    # the same grid written through fedmap.maps.export as PNG and ROS YAML loads back the same
    for fmt in ("png", "ros"):
        (written, *_) = export_map(grid, tmp_path / f"same_{fmt}", fmt)
        back = load_map(written)
        np.testing.assert_array_equal(back.classes, grid.classes)
        assert back.transform == grid.transform and back.pixel_size == RES


def test_the_feed_gives_every_message_and_the_default_is_the_last(tmp_path):
    second = np.full_like(VALUES, 100)
    bag = _ros_bag(tmp_path / "bag", grids=(VALUES, second, VALUES))
    feed = list(bag_map_feed(bag))
    assert [t for t, _ in feed] == [1.0, 2.0, 3.0]
    assert (feed[1][1].classes == IMPASSABLE).all() and feed[1][1].meta["stamp_ns"] == 2_000_000_000
    np.testing.assert_array_equal(read_bag_map(bag).classes, EXPECTED)
    assert (read_bag_map(bag, index=1).classes == IMPASSABLE).all()
    assert (read_bag_map(bag, index=-2).classes == IMPASSABLE).all()
    with pytest.raises(FedmapError, match="has 3 map message"):
        read_bag_map(bag, index=3)


def _read_back(bag):
    """Every message of a bag by rosbags' AnyReader: [(topic, time ns, message)]."""
    with AnyReader([bag]) as r:
        return [(c.topic, t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages()], \
            {c.topic: c.msgtype for c in r.connections}


def test_a_fedmap_bag_reads_back_with_anyreader(tmp_path):
    grid = GridMap(EXPECTED.copy(), RES, "m", transform=Affine(RES, 0.0, X0, 0.0, -RES, Y0 + 4 * RES))
    (bag,) = export_map(grid, tmp_path / "out", "rosbag2")
    msgs, types = _read_back(bag)
    assert types == {"/map": OG} and len(msgs) == 1
    msg = msgs[0][2]
    assert msg.header.frame_id == "map" and msg.info.resolution == RES
    assert (msg.info.width, msg.info.height) == (5, 4)
    assert (msg.info.origin.position.x, msg.info.origin.position.y) == (X0, Y0)
    want = np.select([EXPECTED_ROS_ROWS == FREE, EXPECTED_ROS_ROWS == IMPASSABLE], [0, 100], -1)
    np.testing.assert_array_equal(np.asarray(msg.data).reshape(4, 5), want)
    qos = (bag / "metadata.yaml").read_text()
    assert "version: 8" in qos and "storage_identifier: sqlite3" in qos and "durability: 1" in qos


@pytest.fixture(scope="module")
def small_mission():
    cfg = MissionConfig(rovers=2, steps=8, sync_every=4, speed=2, sensor_radius=3.0, eval_pairs=4,
                        strategies=("none", "raw"), link=LinkConfig(seed=1))
    return run_mission(cfg, maze(20, seed=1, blocks=3), frames=4)


def test_write_mission_bag_has_every_frame_on_the_mission_clock(tmp_path, small_mission):
    result = small_mission
    bag = write_mission_bag(result, tmp_path / "mission_bag", step_seconds=0.5)
    msgs, types = _read_back(bag)
    want_topics = {f"/{s}/{m}" for s in ("none", "raw") for m in ("global_map", "belief_0", "belief_1")}
    assert set(types) == want_topics and set(types.values()) == {OG}
    for s, run in result.runs.items():
        steps = [f.step for f in run.frames]
        assert steps[-1] == result.config.steps and len(steps) > 1
        for m in ("global_map", "belief_0", "belief_1"):
            mine = [(t, msg) for topic, t, msg in msgs if topic == f"/{s}/{m}"]
            assert [t for t, _ in mine] == [int(k * 0.5e9) for k in steps]
        last = read_bag_map(bag, topic=f"/{s}/global_map")
        np.testing.assert_array_equal(last.classes, run.frames[-1].global_map)
        np.testing.assert_array_equal(read_bag_map(bag, topic=f"/{s}/belief_1", index=0).classes,
                                      run.frames[0].beliefs[1])
        assert last.pixel_size == result.truth.pixel_size


def test_export_cli_writes_a_bag_for_a_map_and_for_a_mission_folder(tmp_path, capsys, small_mission):
    grid = GridMap(EXPECTED.copy(), RES, "m")
    export_map(grid, tmp_path / "m.png", "png")
    assert main(["export", str(tmp_path / "m.png"), "--format", "rosbag2"]) == 0
    assert "/map: 4x5 cells of 0.5 m" in " ".join(capsys.readouterr().out.split())
    np.testing.assert_array_equal(load_map(tmp_path / "m").classes, EXPECTED)
    # and back out of the bag (a bag folder is a map, not a mission folder)
    assert main(["export", str(tmp_path / "m"), "-f", "png", "-o", str(tmp_path / "again.png")]) == 0
    np.testing.assert_array_equal(load_map(tmp_path / "again.png").classes, EXPECTED)
    # a mission folder: every map of maps/ in one bag, a topic per map
    write_mission_maps(small_mission, tmp_path / "mission", beliefs=True, formats=("geotiff",))
    names = sorted(p.stem for p in (tmp_path / "mission" / "maps").glob("*.tif"))
    assert main(["export", str(tmp_path / "mission"), "--format", "rosbag2"]) == 0, capsys.readouterr().err
    msgs, types = _read_back(tmp_path / "mission" / "maps" / "maps_bag")
    assert sorted(types) == [f"/{n}" for n in names] and len(msgs) == len(names)
    np.testing.assert_array_equal(read_bag_map(tmp_path / "mission" / "maps" / "maps_bag", topic="/raw_global").classes,
                                  small_mission.runs["raw"].frames[-1].global_map)


def _one_line_error(capsys, args, *phrases):
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err, err
    for p in phrases:
        assert p in err, err


def test_bad_bags_are_one_line_errors(tmp_path, capsys):
    string = TS.types["std_msgs/msg/String"](data="hello")
    bag = _ros_bag(tmp_path / "bag", extra=[("/chatter", "std_msgs/msg/String", string)])
    with pytest.raises(FedmapError, match="has no topic '/nope'; its nav_msgs/msg/OccupancyGrid topics: /map"):
        read_bag_map(bag, topic="/nope")
    with pytest.raises(FedmapError, match="topic /chatter of .* holds std_msgs/msg/String, not nav_msgs"):
        read_bag_map(bag, topic="/chatter")
    only_string = tmp_path / "strings"
    with Writer(only_string, version=8) as w:
        w.write(w.add_connection("/chatter", "std_msgs/msg/String", typestore=TS), 1,
                TS.serialize_cdr(string, "std_msgs/msg/String"))
    _one_line_error(capsys, ["export", str(only_string), "-f", "png", "-o", str(tmp_path / "x.png")],
                    "has no nav_msgs/msg/OccupancyGrid topic", "/chatter (std_msgs/msg/String)")
    two = tmp_path / "two"
    with Writer(two, version=8) as w:
        for topic in ("/map", "/costmap"):
            w.write(w.add_connection(topic, OG, typestore=TS), 1, TS.serialize_cdr(_msg(VALUES), OG))
    with pytest.raises(FedmapError, match=r"has 2 nav_msgs/msg/OccupancyGrid topics \(/map, /costmap\)"):
        load_map(two)
    np.testing.assert_array_equal(load_map(two, topic="/costmap").classes, EXPECTED)
    # not a bag: an empty folder (given as a map), a text file named .mcap
    (tmp_path / "empty").mkdir()
    with pytest.raises(FedmapError, match="is not a ROS 2 bag: no metadata.yaml"):
        load_map(tmp_path / "empty")
    _one_line_error(capsys, ["run", "--map", str(tmp_path / "empty")], "is not a ROS 2 bag")
    (tmp_path / "notes.mcap").write_text("not a bag\n")
    _one_line_error(capsys, ["export", str(tmp_path / "notes.mcap"), "-f", "png"], "cannot read ROS 2 bag")
    # truncated storage files, sqlite3 and MCAP, read through the folder and alone
    for storage, suffix in ((StoragePlugin.SQLITE3, ".db3"), (StoragePlugin.MCAP, ".mcap")):
        cut = _ros_bag(tmp_path / f"cut{suffix[1:]}", storage=storage)
        (f,) = cut.glob(f"*{suffix}")
        f.write_bytes(f.read_bytes()[: f.stat().st_size * 9 // 10])
        for target in (cut, f):
            with pytest.raises(FedmapError, match="cannot read ROS 2 bag") as info:
                load_map(target)
            assert "\n" not in str(info.value)
        _one_line_error(capsys, ["export", str(cut), "-f", "png", "-o", str(tmp_path / "y.png")], "cannot read ROS 2 bag")
    # writing over a folder that is not a bag is refused; a bag is replaced whole
    grid = GridMap(EXPECTED.copy(), RES, "m")
    with pytest.raises(FedmapError, match="exists and is not a ROS 2 bag"):
        export_map(grid, tmp_path / "empty", "rosbag2")
    export_map(GridMap(np.zeros((3, 3), np.uint8), 1.0, "z"), bag, "rosbag2")
    assert load_map(bag).shape == (3, 3)


def test_mission_rosbag_holds_every_sync_of_every_strategy(tmp_path, capsys):
    """``fedmap mission --rosbag``: step 0, every sync and the last step, for every strategy's
    global map and every rover's belief; the last global map is the one the mission wrote."""
    out, bag = tmp_path / "m", tmp_path / "bag"
    rc = main(["mission", "--size", "64", "--steps", "10", "--sync-every", "4", "--rovers", "2", "--sensor-radius",
               "4", "--strategies", "none,raw", "--no-animation", "--rosbag", str(bag), "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    steps: dict[str, list[int]] = {}
    last = None
    with AnyReader([bag]) as reader:
        for conn, t, raw in reader.messages():
            steps.setdefault(conn.topic, []).append(t // 1_000_000_000)
            if conn.topic == "/raw/global_map":
                last = reader.deserialize(raw, conn.msgtype)
    assert set(steps) == {f"/{s}/{m}" for s in ("none", "raw") for m in ("global_map", "belief_0", "belief_1")}
    assert all(v == [0, 4, 8, 10] for v in steps.values())
    written = load_map(out / "maps" / "raw_global.tif").classes
    assert last is not None and np.array_equal(read_bag_map(bag, topic="/raw/global_map").classes, written)
