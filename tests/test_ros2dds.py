"""ROS 2 messages on DDS: the types built from rosbags' typestore give rosbags' CDR bytes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cyclonedds")  # the ros2 extra (in the test extra: CI always has it)

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.maps.ros2dds import dds_name, dds_topic, dds_type, from_dds, to_dds, typestore  # noqa: E402

TS = typestore()


def rosbags_make(name: str, **fields):
    """A message built with rosbags' own class (numeric sequences as numpy arrays)."""
    return TS.types[name](**fields)


def dds_make(name: str, **fields):
    """A sample built with the DDS class (numeric sequences as lists)."""
    return dds_type(name)(**{k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in fields.items()})


def header(make, rng, frame: str):
    return make("std_msgs/msg/Header",
                stamp=make("builtin_interfaces/msg/Time", sec=int(rng.integers(0, 2**31)),
                           nanosec=int(rng.integers(0, 10**9))), frame_id=frame)


def point(make, rng, name="geometry_msgs/msg/Point"):
    x, y, z = (float(v) for v in rng.normal(size=3))
    return make(name, x=x, y=y, z=z)


def quaternion(make, rng):
    x, y, z, w = (float(v) for v in rng.normal(size=4))
    return make("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)


def pose(make, rng):
    return make("geometry_msgs/msg/Pose", position=point(make, rng), orientation=quaternion(make, rng))


def occupancy_grid(make, rng):
    h, w = (int(v) for v in rng.integers(1, 40, size=2))
    info = make("nav_msgs/msg/MapMetaData", map_load_time=make("builtin_interfaces/msg/Time", sec=3, nanosec=7),
                resolution=float(np.float32(rng.uniform(0.05, 2))), width=w, height=h, origin=pose(make, rng))
    data = rng.choice(np.array([-1, 0, 100], np.int8), size=h * w)
    return make("nav_msgs/msg/OccupancyGrid", header=header(make, rng, "map"), info=info, data=data)


def pose_stamped(make, rng):
    return make("geometry_msgs/msg/PoseStamped", header=header(make, rng, "odom"), pose=pose(make, rng))


def odometry(make, rng):
    cov = rng.normal(size=36)
    twist = make("geometry_msgs/msg/Twist", linear=point(make, rng, "geometry_msgs/msg/Vector3"),
                 angular=point(make, rng, "geometry_msgs/msg/Vector3"))
    return make("nav_msgs/msg/Odometry", header=header(make, rng, "odom"),
                child_frame_id="base_link" * int(rng.integers(1, 4)),
                pose=make("geometry_msgs/msg/PoseWithCovariance", pose=pose(make, rng), covariance=cov),
                twist=make("geometry_msgs/msg/TwistWithCovariance", twist=twist, covariance=cov[::-1].copy()))


def tf_message(make, rng):
    def one(child):
        return make("geometry_msgs/msg/TransformStamped", header=header(make, rng, "map"), child_frame_id=child,
                    transform=make("geometry_msgs/msg/Transform", translation=point(make, rng, "geometry_msgs/msg/Vector3"),
                                   rotation=quaternion(make, rng)))
    return make("tf2_msgs/msg/TFMessage", transforms=[one("odom"), one("base_link"), one("rover_7")])


CASES = {"nav_msgs/msg/OccupancyGrid": occupancy_grid, "geometry_msgs/msg/PoseStamped": pose_stamped,
         "nav_msgs/msg/Odometry": odometry, "tf2_msgs/msg/TFMessage": tf_message}


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("msgtype", list(CASES))
def test_a_sample_built_with_the_dds_type_has_rosbags_cdr_bytes(msgtype, seed):
    """The same values built twice, with rosbags' class and with the DDS class (every field
    written out above, odd lengths so alignment matters): byte-equal CDR, header included."""
    build = CASES[msgtype]
    msg = build(rosbags_make, np.random.default_rng(seed))
    sample = build(dds_make, np.random.default_rng(seed))
    expected = bytes(TS.serialize_cdr(msg, msgtype))
    assert sample.serialize() == expected
    assert to_dds(msg, msgtype).serialize() == expected  # the converter gives the same sample
    back = from_dds(type(sample).deserialize(expected), msgtype)  # and back to rosbags' class
    assert bytes(TS.serialize_cdr(back, msgtype)) == expected


def test_the_names_follow_ros2s_mapping_to_dds():
    assert dds_name("nav_msgs/msg/OccupancyGrid") == "nav_msgs::msg::dds_::OccupancyGrid_"
    assert dds_type("nav_msgs/msg/OccupancyGrid").__idl_typename__ == "nav_msgs::msg::dds_::OccupancyGrid_"
    assert dds_type("std_msgs/msg/Header").__idl_typename__ == "std_msgs::msg::dds_::Header_"
    assert dds_topic("/map") == "rt/map" and dds_topic("/fedmap/team_map") == "rt/fedmap/team_map"
    for bad in ("map", "/", "/map/", "//map", "/2map"):
        with pytest.raises(FedmapError, match="not a ROS topic name"):
            dds_topic(bad)
    with pytest.raises(FedmapError, match="unknown ROS 2 message type 'nav_msgs/msg/Nope'"):
        dds_type("nav_msgs/msg/Nope")
    with pytest.raises(FedmapError, match="package/msg/Name"):
        dds_type("OccupancyGrid")


PLAYER = """
import sys, time
import numpy as np
from fedmap.maps import ros2dds
from fedmap.maps.rosbag import occupancy_message

dp = ros2dds.participant(int(sys.argv[1]), loopback=True)
w = ros2dds.writer(dp, "/map", "nav_msgs/msg/OccupancyGrid", latched=sys.argv[2] == "latched")
rng = np.random.default_rng(int(sys.argv[3]))
for k in range(3):  # three maps, as a mapping stack publishes them; only the last is kept
    classes = rng.integers(0, 3, size=(6, 9)).astype(np.uint8)
    msg = occupancy_message(ros2dds.typestore(), classes, resolution=0.25, origin=(1.5, -2.0), time_ns=k)
    w.write(ros2dds.to_dds(msg, "nav_msgs/msg/OccupancyGrid"))
np.save(sys.argv[4], classes)
print("published", flush=True)
time.sleep(30)
"""


@pytest.mark.parametrize("latched", [True, False])
def test_a_reader_that_joins_late_gets_the_last_map_of_a_latched_writer_only(tmp_path, latched):
    """Another process plays map_server (its own DDS participant, loopback only) and publishes
    three maps on /map; this process joins after they were written and reads /map as Nav2's
    static layer does (transient local). From a latched writer it gets the last map, and
    fedmap reads it as that map's classes; from a volatile one it gets nothing."""
    import subprocess
    import sys
    import time

    from fedmap.maps import ros2dds
    from fedmap.maps.rosbag import grid_from_message

    domain = 100 + (2 if latched else 3)  # a domain of this test's own
    script = tmp_path / "player.py"
    script.write_text(PLAYER)
    last = tmp_path / "last.npy"
    with subprocess.Popen([sys.executable, str(script), str(domain), "latched" if latched else "volatile", "5",
                           str(last)], stdout=subprocess.PIPE, text=True) as player:
        try:
            assert player.stdout is not None and player.stdout.readline().strip() == "published"
            dp = ros2dds.participant(domain, loopback=True)
            r = ros2dds.reader(dp, "/map", "nav_msgs/msg/OccupancyGrid")
            got: list = []
            deadline = time.monotonic() + (10 if latched else 3)
            while time.monotonic() < deadline and not got:
                got = ros2dds.samples(r, 10)
                time.sleep(0.05)
        finally:
            player.kill()
    if not latched:
        assert got == []
        return
    assert len(got) == 1  # keep last 1: the last of the three
    grid = grid_from_message(ros2dds.from_dds(got[0], "nav_msgs/msg/OccupancyGrid"), "/map")
    np.testing.assert_array_equal(grid.classes, np.load(last))
    assert grid.pixel_size == 0.25 and grid.meta["stamp_ns"] == 2


LATE_READER = """
import sys, time
import numpy as np
from fedmap.maps import ros2dds

dp = ros2dds.participant(int(sys.argv[1]), loopback=True)
sub = ros2dds.MapSubscriber(dp, "/fedmap/team_map")
grid = sub.wait(10)
np.save(sys.argv[2], grid.classes)
print(sub.received, grid.meta["stamp_ns"], flush=True)
"""


def test_a_rover_fed_live_over_dds_publishes_its_team_map_to_a_late_subscriber(tmp_path):
    """Another process plays the rover's mapping stack: it publishes the rover's map, latched,
    on /map. Rover 0 of a raw mission (base and rovers over bytes) takes it live and publishes
    its belief on /fedmap/team_map after every order. A third process joins after the mission
    ended, as Nav2's static layer does, and gets the last team map. It equals rover 0's final
    belief in the same mission fed the same map from a file, in process."""
    import subprocess
    import sys

    from fedmap.maps import ros2dds
    from fedmap.maps.grid import UNKNOWN
    from fedmap.mission.network.remote import ProcessBase, loopback, rounds
    from fedmap.mission.settings import load_mission
    from fedmap.mission.sim import mission_terrain, prepare_mission
    from fedmap.mission.world.feed import LiveFeed, MapFeed

    config, source, _ = load_mission(overrides=[{"mission": {"steps": 40, "strategies": ["raw"]},
                                                 "terrain": {"size": 64}, "link": {"loss": 0.0}}])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    rows, cols = np.indices(truth.shape)
    snap = np.where((rows - 20) ** 2 + (cols - 40) ** 2 <= 144, truth.classes, UNKNOWN).astype(np.uint8)
    np.save(tmp_path / "snap.npy", snap)
    (tmp_path / "stack.py").write_text(
        "import sys, time\nimport numpy as np\nfrom fedmap.maps import ros2dds\n"
        "dp = ros2dds.participant(int(sys.argv[1]), loopback=True)\n"
        "pub = ros2dds.MapPublisher(dp, '/map', resolution=1.0)\n"
        "pub.publish(np.load(sys.argv[2]), 7)\nprint('published', flush=True)\ntime.sleep(60)\n")
    (tmp_path / "late.py").write_text(LATE_READER)
    domain = 104

    def run(feed, on_belief=None):
        m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                            thresholds=source.thresholds, frames=1)
        base = ProcessBase(m, "raw")
        rovers = loopback(m, "raw", feeds={0: feed}, on_beliefs={0: on_belief} if on_belief else None)
        for _ in rounds(base, rovers):
            pass
        return rovers.nodes[0].node.belief()

    with subprocess.Popen([sys.executable, str(tmp_path / "stack.py"), str(domain), str(tmp_path / "snap.npy")],
                          stdout=subprocess.PIPE, text=True) as stack:
        try:
            assert stack.stdout is not None and stack.stdout.readline().strip() == "published"
            dp = ros2dds.participant(domain, loopback=True)
            sub = ros2dds.MapSubscriber(dp, "/map")
            np.testing.assert_array_equal(sub.wait(10).classes, snap)
            out = ros2dds.MapPublisher(dp, "/fedmap/team_map", resolution=truth.pixel_size)
            live = run(LiveFeed(sub), lambda step, belief: out.publish(belief, step))
            late = subprocess.run([sys.executable, str(tmp_path / "late.py"), str(domain), str(tmp_path / "team.npy")],
                                  capture_output=True, text=True, timeout=60)
        finally:
            stack.kill()
    assert late.returncode == 0, late.stderr[-2000:]
    received, stamp = (int(v) for v in late.stdout.split())
    assert received == 1 and stamp == config.steps and out.sent > 1  # the last of the team maps, only
    filed = run(MapFeed([(0, snap)], "file"))
    np.testing.assert_array_equal(live, filed)
    np.testing.assert_array_equal(np.load(tmp_path / "team.npy"), live)
    assert ((live != UNKNOWN) >= (snap != UNKNOWN)).all()  # the rover's map is in the team map it plans on


def _rehearsal_bag(path):
    """A bag as a rover records it: maps on /map, poses on /pose, interleaved in time."""
    from rosbags.rosbag2 import Writer

    from fedmap.maps.rosbag import BAG_VERSION, occupancy_message

    rng = np.random.default_rng(9)
    maps = [(0, rng.integers(0, 3, (5, 7)).astype(np.uint8)), (500_000_000, rng.integers(0, 3, (5, 7)).astype(np.uint8)),
            (1_500_000_000, rng.integers(0, 3, (5, 7)).astype(np.uint8))]
    poses = [(t, pose_stamped(rosbags_make, np.random.default_rng(t))) for t in (250_000_000, 1_000_000_000)]
    with Writer(path, version=BAG_VERSION) as w:
        cm = w.add_connection("/map", "nav_msgs/msg/OccupancyGrid", typestore=TS)
        cp = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=TS)
        for t, m in sorted([*((t, ("map", c)) for t, c in maps), *((t, ("pose", p)) for t, p in poses)],
                           key=lambda x: x[0]):
            if m[0] == "map":
                msg = occupancy_message(TS, m[1], resolution=0.5, origin=(0.0, 0.0), time_ns=t)
                w.write(cm, t, TS.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))
            else:
                w.write(cp, t, TS.serialize_cdr(m[1], "geometry_msgs/msg/PoseStamped"))
    return maps, poses


def test_a_bag_is_played_at_its_own_timing(tmp_path):
    """The pauses between messages are the bag's gaps over the speed (a clock that moves only
    when the player sleeps: by hand, 0.25, 0.25, 0.5 and 0.5 s of bag time)."""
    from fedmap.maps import ros2dds

    _rehearsal_bag(tmp_path / "bag")
    now, slept = [0.0], []

    def sleep(d):
        slept.append(d)
        now[0] += d

    dp = ros2dds.participant(105, loopback=True)
    sent = ros2dds.play_bag(tmp_path / "bag", dp, speed=2.0, clock=lambda: now[0], sleep=sleep)
    assert sent == 5 and slept == pytest.approx([0.125, 0.125, 0.25, 0.25])
    with pytest.raises(FedmapError, match="has no topic /scan"):
        ros2dds.play_bag(tmp_path / "bag", dp, topics=["/scan"])
    with pytest.raises(FedmapError, match="speed must be a positive number"):
        ros2dds.play_bag(tmp_path / "bag", dp, speed=0)


def test_a_played_bag_reaches_readers_in_another_process_message_for_message(tmp_path):
    """Another process plays a rover's recorded bag into the graph (waiting for this
    process's readers first): every pose arrives, in order and byte-equal to the bag's, and
    the latest map read is the bag's last."""
    import subprocess
    import sys
    import time

    from fedmap.maps import ros2dds

    maps, poses = _rehearsal_bag(tmp_path / "bag")
    domain = 106
    dp = ros2dds.participant(domain, loopback=True)
    sub = ros2dds.MapSubscriber(dp, "/map")
    pose_reader = ros2dds.reader(dp, "/pose", "geometry_msgs/msg/PoseStamped", latched=False)
    code = ("import sys\nfrom fedmap.maps import ros2dds\n"
            f"dp = ros2dds.participant({domain}, loopback=True)\n"
            "print(ros2dds.play_bag(sys.argv[1], dp, speed=4.0, readers=1), flush=True)\n"
            "import time; time.sleep(1)\n")
    got: list = []
    with subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "bag")], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as player:
        try:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and (len(got) < len(poses) or sub.received < 1
                                                   or not np.array_equal(sub.poll().classes, maps[-1][1])):
                got += ros2dds.samples(pose_reader, 10)
                sub.poll()
                time.sleep(0.02)
            out, err = player.communicate(timeout=20)
        finally:
            player.kill()
    assert player.returncode == 0, err[-2000:]
    assert out.strip() == "5"
    assert [g.serialize() for g in got] == [bytes(TS.serialize_cdr(p, "geometry_msgs/msg/PoseStamped"))
                                            for _, p in poses]
    np.testing.assert_array_equal(sub.poll().classes, maps[-1][1])


STACK = """
import sys, time
import numpy as np
from fedmap.maps import ros2dds
dp = ros2dds.participant(int(sys.argv[1]), loopback=True)
pub = ros2dds.MapPublisher(dp, '/map', resolution=1.0)
pub.publish(np.load(sys.argv[2]), 7)
print('published', flush=True)
time.sleep(120)
"""


@pytest.mark.slow
@pytest.mark.xdist_group("loopback-c")
@pytest.mark.parametrize("mapper", ["stack", "bag"])
def test_a_ros2_rover_node_over_zenoh_publishes_the_team_map_a_late_nav2_gets(tmp_path, mapper):
    """Independent processes: one plays the rover's mapping stack (its map, latched, on /map;
    with ``bag`` the rover node plays it itself from a recorded bag, ``--bag``, a rehearsal);
    ``fedmap node base`` and four ``fedmap node rover`` processes run a raw mission over
    Zenoh, rover 0 with ``--ros2``: it takes its map from /map and publishes the team map on
    /fedmap/team_map after every order. A last process joins after the mission, as Nav2's
    static layer does, and gets the last team map. It equals rover 0's final belief in the same
    mission fed the same map from a file, in process; the mission scored from the nodes' logs
    equals it too."""
    import os
    import signal
    import subprocess
    import sys
    import time

    pytest.importorskip("zenoh")
    from fedmap.flower.launch import free_port
    from fedmap.maps.grid import UNKNOWN
    from fedmap.mission.network.remote import ProcessBase, loopback, rounds
    from fedmap.mission.scoring import score_folder
    from fedmap.mission.settings import load_mission, mission_toml
    from fedmap.mission.sim import mission_terrain, prepare_mission
    from fedmap.mission.world.feed import MapFeed

    config, source, resolved = load_mission(overrides=[{"mission": {"steps": 40, "strategies": ["raw"]},
                                                        "terrain": {"size": 64}, "link": {"loss": 0.0}}])
    (tmp_path / "mission.toml").write_text(mission_toml(resolved))
    truth, elevation, prior, profiles = mission_terrain(config, source)
    rows, cols = np.indices(truth.shape)
    snap = np.where((rows - 20) ** 2 + (cols - 40) ** 2 <= 144, truth.classes, UNKNOWN).astype(np.uint8)
    np.save(tmp_path / "snap.npy", snap)
    (tmp_path / "stack.py").write_text(STACK)
    (tmp_path / "late.py").write_text(LATE_READER)
    domain, port = (107 if mapper == "stack" else 109), free_port()
    ros = ["--ros2", "--domain", str(domain), "--ros2-loopback", "--first-map", "30"]
    if mapper == "bag":
        from rosbags.rosbag2 import Writer

        from fedmap.maps.rosbag import BAG_VERSION, occupancy_message

        with Writer(tmp_path / "rover0_bag", version=BAG_VERSION) as bw:  # its map, then its pose
            c = bw.add_connection("/map", "nav_msgs/msg/OccupancyGrid", typestore=TS)
            msg = occupancy_message(TS, snap, resolution=1.0, origin=(0.0, 0.0), time_ns=7)
            bw.write(c, 7, TS.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))
            cp = bw.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=TS)
            bw.write(cp, 8, TS.serialize_cdr(_pose_at(40.5, 43.5), "geometry_msgs/msg/PoseStamped"))
        ros += ["--bag", str(tmp_path / "rover0_bag"), "--pose-topic", "/pose"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    work = tmp_path / "out.run"
    node = [sys.executable, "-m", "fedmap", "node"]
    rovers: list = []
    stack_argv = [sys.executable, str(tmp_path / "stack.py"), str(domain), str(tmp_path / "snap.npy")]
    with subprocess.Popen(stack_argv if mapper == "stack" else [sys.executable, "-c", "print('published')"],
                          stdout=subprocess.PIPE, text=True) as stack:
        try:
            assert stack.stdout is not None and stack.stdout.readline().strip() == "published"
            rovers += [subprocess.Popen([*node, "rover", "--rover", str(k), "--connect", f"127.0.0.1:{port}", "--team",
                                        "ros", "--state", str(work / f"rover{k}.state"),
                                        *(ros if k == 0 else [])],
                                       env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                      for k in range(4)]
            base = subprocess.Popen([*node, "base", str(tmp_path / "mission.toml"), "--listen", f"127.0.0.1:{port}",
                                     "--team", "ros", "--out", str(tmp_path / "out"), "--connect-timeout", "60"],
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            t_end = time.monotonic() + 300
            while base.poll() is None:  # a rover that dies fails the test now, not at the base's rejoin timeout
                if any(r.poll() not in (None, 0) for r in rovers) or time.monotonic() > t_end:
                    base.kill()
                time.sleep(0.1)
            base_out, base_err = base.communicate()
            if base.returncode != 0:
                for r in rovers:
                    r.kill()
                raise AssertionError(base_out[-2000:] + base_err[-2000:] + "\n".join(
                    r.communicate()[0][-1000:] for r in rovers))
            said = [""] + [r.communicate(timeout=60)[0] for r in rovers[1:]]  # the others stop once it is over
            assert [r.returncode for r in rovers[1:]] == [0] * 3, said
            late = subprocess.run([sys.executable, str(tmp_path / "late.py"), str(domain), str(tmp_path / "team.npy")],
                                  capture_output=True, text=True, timeout=60)
            assert rovers[0].poll() is None  # the ROS 2 node stays in its graph until it is stopped
            rovers[0].send_signal(signal.SIGINT)
            said[0] = rovers[0].communicate(timeout=60)[0]
            assert rovers[0].returncode == 0, said[0]
        finally:
            stack.kill()
            for r in rovers:
                if r.poll() is None:
                    r.kill()
    assert late.returncode == 0, late.stderr[-2000:]
    assert int(late.stdout.split()[0]) == 1  # the last team map only
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                        thresholds=source.thresholds, frames=1)
    filed_feed = MapFeed([(0, snap)], "file")
    if mapper == "bag":  # the pose (40.5, 43.5) m is column 40, row 43 from the bottom: 63 - 43 = 20 from the top
        filed_feed.pose = lambda: (20, 40)  # type: ignore[attr-defined]
    here = loopback(m, "raw", feeds={0: filed_feed})
    for _ in rounds(ProcessBase(m, "raw"), here):
        pass
    filed = here.nodes[0].node.belief()
    team = np.load(tmp_path / "team.npy")
    np.testing.assert_array_equal(team, filed)
    assert ((team != UNKNOWN) >= (snap != UNKNOWN)).all()  # the rover's map is in the team map it plans on
    apart = score_folder(work, frames=1)  # what the nodes logged: rover 0's views are its live map's
    np.testing.assert_array_equal(apart.runs["raw"].views[0], filed)
    assert "ROS 2 map in /map" in said[0] and "stays on /fedmap/team_map" in said[0]
    if mapper == "bag":  # placed by its pose, in the live mission as in the reference
        assert here.nodes[0].node.rover.pos == (20, 40) and tuple(apart.runs["raw"].trails[0][-1]) == (20, 40)


def _pose_at(x: float, y: float):
    p = rosbags_make("geometry_msgs/msg/Pose", position=rosbags_make("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
                     orientation=rosbags_make("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
    return rosbags_make("geometry_msgs/msg/PoseStamped", header=pose_stamped(rosbags_make, np.random.default_rng(0)).header,
                        pose=p)


def test_bad_input_on_the_ros_side_costs_a_line_and_nothing_else(tmp_path):
    """A map with a non-finite origin is dropped (one line, the map before kept); a map of
    another size than the mission's grid is not used (one line); a message of another type on
    /map never reaches the node; after all that, a good map is taken."""
    import time

    from fedmap.maps import ros2dds
    from fedmap.maps.rosbag import occupancy_message
    from fedmap.mission.settings import load_mission
    from fedmap.mission.sim import mission_terrain, prepare_mission
    from fedmap.zenohnet.ros2 import Ros2Bridge

    config, source, _ = load_mission(overrides=[{"mission": {"steps": 10}, "terrain": {"size": 64}}])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    mission = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                              thresholds=source.thresholds, frames=1)
    domain = 108
    lines: list[str] = []
    bridge = Ros2Bridge(0, domain=domain, loopback=True, say=lines.append)
    bridge.on_mission(mission)
    bridge.feed.check(truth)
    dp = ros2dds.participant(domain, loopback=True)
    w = ros2dds.writer(dp, "/map", ros2dds.OCCUPANCY_GRID)
    rng = np.random.default_rng(3)
    good = rng.integers(0, 3, truth.shape).astype(np.uint8)

    def send(classes, origin=(0.0, 0.0)):
        msg = occupancy_message(ros2dds.typestore(), classes, resolution=1.0, origin=origin, time_ns=1)
        w.write(ros2dds.to_dds(msg, ros2dds.OCCUPANCY_GRID))

    def until(cond, what):
        t_end = time.monotonic() + 10
        while not cond():
            assert time.monotonic() < t_end, what
            time.sleep(0.02)

    send(good)  # (latched: the node's reader gets it whenever discovery matches them)
    until(lambda: bridge.feed.at(1) is not None, "the first good map")
    bridge.on_belief(1, good)
    assert lines == []
    send(good, origin=(float("nan"), 0.0))
    until(lambda: bridge.sub.poll() is not None and bridge.sub.rejected, "the damaged map")
    np.testing.assert_array_equal(bridge.feed.at(2), good)  # the map before is kept
    bridge.on_belief(2, good)
    assert len(lines) == 1 and "was dropped" in lines[0] and "origin is not finite" in lines[0]
    send(rng.integers(0, 3, (10, 12)).astype(np.uint8))
    until(lambda: bridge.feed.at(3) is None, "the map off the grid")
    bridge.on_belief(3, good)
    assert len(lines) == 2 and "is 10x12 cells, not the mission's 64x64 grid" in lines[1]
    other = ros2dds.participant(domain, loopback=True)  # a PoseStamped published on /map
    pw = ros2dds.writer(other, "/map", "geometry_msgs/msg/PoseStamped", latched=False)
    pw.write(ros2dds.to_dds(pose_stamped(rosbags_make, np.random.default_rng(1)), "geometry_msgs/msg/PoseStamped"))
    received = bridge.sub.received
    time.sleep(0.5)
    bridge.sub.poll()
    assert bridge.sub.received == received  # it never reached the node's reader
    later = rng.integers(0, 3, truth.shape).astype(np.uint8)
    send(later)
    until(lambda: bridge.feed.at(4) is not None, "a good map after the bad ones")
    np.testing.assert_array_equal(bridge.feed.at(4), later)


def test_a_pose_is_placed_on_the_latest_map_and_moves_the_rover(tmp_path):
    """The pose topic's (x, y) becomes the cell of the latest map that holds it (origin and
    resolution from the map; row 0 of the grid is the top, ROS's row 0 the bottom: a hand
    computation); a pose before any map is not placed (one line). A rover fed a map and a
    pose is where its pose says at the end of a mission, not where its map's cells are."""
    import time

    from fedmap.maps import ros2dds
    from fedmap.maps.grid import UNKNOWN
    from fedmap.maps.rosbag import occupancy_message
    from fedmap.mission.network.remote import ProcessBase, loopback, rounds
    from fedmap.mission.settings import load_mission
    from fedmap.mission.sim import mission_terrain, prepare_mission
    from fedmap.zenohnet.ros2 import Ros2Bridge

    domain = 110
    lines: list[str] = []
    bridge = Ros2Bridge(0, domain=domain, pose_topic="/pose", loopback=True, say=lines.append)
    dp = ros2dds.participant(domain, loopback=True)
    pw = ros2dds.writer(dp, "/pose", "geometry_msgs/msg/PoseStamped", latched=False)
    mw = ros2dds.writer(dp, "/map", ros2dds.OCCUPANCY_GRID)

    def send_pose(x, y):
        pw.write(ros2dds.to_dds(_pose_at(x, y), "geometry_msgs/msg/PoseStamped"))

    def until(cond, what):
        t_end = time.monotonic() + 10
        while not cond():
            assert time.monotonic() < t_end, what
            send_pose(*xy)  # (volatile: sent again until the reader has matched)
            time.sleep(0.05)

    xy = (3.0, 4.0)
    until(lambda: bridge.poses.poll() is not None, "the first pose")
    assert bridge.feed.pose() is None  # no map yet to place it on
    bridge.on_belief(0, np.zeros((4, 4), np.uint8))
    assert len(lines) == 1 and "came before any map" in lines[0]
    classes = np.full((64, 48), UNKNOWN, np.uint8)
    mw.write(ros2dds.to_dds(occupancy_message(ros2dds.typestore(), classes, resolution=0.5, origin=(1.0, 2.0),
                                              time_ns=1), ros2dds.OCCUPANCY_GRID))
    xy = (1.0 + 0.5 * 10.2, 2.0 + 0.5 * 5.7)  # column 10; row 5 from the bottom: 63 - 5 = 58 from the top
    until(lambda: bridge.sub.poll() is not None and bridge.feed.pose() == (58, 10), "the pose on the map")

    config, source, _ = load_mission(overrides=[{"mission": {"steps": 30, "strategies": ["raw"]},
                                                 "terrain": {"size": 64}, "link": {"loss": 0.0}}])
    truth, elevation, prior, profiles = mission_terrain(config, source)

    class Fed:  # a map that shows a disc, a pose somewhere else
        source = "test"

        def check(self, grid):
            pass

        def at(self, step):
            rows, cols = np.indices(truth.shape)
            return np.where((rows - 20) ** 2 + (cols - 40) ** 2 <= 64, truth.classes, UNKNOWN).astype(np.uint8)

        def pose(self):
            return (50, 7)

    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                        thresholds=source.thresholds, frames=1)
    rovers = loopback(m, "raw", feeds={0: Fed()})
    for _ in rounds(ProcessBase(m, "raw"), rovers):
        pass
    rover = rovers.nodes[0].node.rover
    assert rover.pos == (50, 7) and rover.trail[-1] == (50, 7)


def test_a_map_publisher_that_leaves_costs_nothing():
    """When a map's writer leaves the graph, DDS delivers a notification without data
    (Cyclone's InvalidSample) to the reader: the subscriber skips it and keeps the last map
    (it raised AttributeError, and the rover node died, when a bag's player finished)."""
    import gc
    import time

    from cyclonedds.sub import InvalidSample

    from fedmap.maps import ros2dds

    domain = 111
    dp = ros2dds.participant(domain, loopback=True)
    sub = ros2dds.MapSubscriber(dp, "/map")
    other = ros2dds.participant(domain, loopback=True)
    pub = ros2dds.MapPublisher(other, "/map", resolution=1.0)
    classes = np.random.default_rng(4).integers(0, 3, (4, 5)).astype(np.uint8)
    pub.publish(classes, 1)
    np.testing.assert_array_equal(sub.wait(10).classes, classes)
    del pub, other
    gc.collect()
    seen: list = []
    t_end = time.monotonic() + 10
    while not any(isinstance(s, InvalidSample) for s in seen):  # looked at, left in the reader's cache
        assert time.monotonic() < t_end, "no notification that the writer left"
        seen = sub.reader.read(N=10)
        time.sleep(0.02)
    np.testing.assert_array_equal(sub.poll().classes, classes)  # the notification skipped, the last map kept
    assert sub.received == 1 and sub.rejected == []
