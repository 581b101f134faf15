"""A rover node in the robot's ROS 2 graph (``fedmap node rover --ros2``), over DDS.

The rover's map comes live from its mapping stack: the latest ``nav_msgs/OccupancyGrid`` on
``--map-topic`` (default ``/map``; latched or volatile publishers both reach it), read with
map_server's thresholds (:class:`~fedmap.maps.ros2dds.MapSubscriber`,
:class:`~fedmap.mission.world.feed.LiveFeed`). After every order the node publishes what
it plans on, the team's map as it knows it, on ``--team-map-topic`` (default
``/fedmap/team_map``; reliable, transient local: Nav2's static layer and RViz get the last one
when they join late), and its status as JSON in a ``std_msgs/String`` on ``/fedmap/status``
(the step, orders answered, bytes in and out on the team link, maps received and dropped).

Bad input on the ROS side costs one line on the node's output and nothing else: a map that
cannot be read (a non-finite origin, a size that does not match its data) is dropped and the
one before kept; a map of another size than the mission's grid is not used; a message of
another type on the topic does not match the node's reader (DDS matches by type) and never
reaches it. The team link is any transport behind the seam; here Zenoh
(:mod:`fedmap.zenohnet.rover`).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps import ros2dds
from fedmap.maps.georef import cell_of
from fedmap.mission.sim import Mission
from fedmap.mission.world.feed import LiveFeed

#: The ROS 2 type of the node's status.
STATUS_TYPE = "std_msgs/msg/String"


#: The ROS 2 types a rover's pose may come in.
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")


class Ros2Bridge:
    """Rover ``k``'s maps in and out of ROS 2 domain ``domain`` (``loopback``: DDS confined
    to this machine). ``say`` gets each line about bad input."""

    def __init__(self, k: int, *, domain: int = 0, map_topic: str = "/map", team_topic: str = "/fedmap/team_map",
                 status_topic: str = "/fedmap/status", pose_topic: str | None = None,
                 pose_type: str = POSE_TYPES[0], loopback: bool = False,
                 say: Callable[[str], None] = print) -> None:
        self.k, self.say = k, say
        self.dp = ros2dds.participant(domain, loopback=loopback)
        self.sub = ros2dds.MapSubscriber(self.dp, map_topic)
        self.poses = None if pose_topic is None else PoseSubscriber(self.dp, pose_topic, pose_type)
        self.feed = LiveFeed(self.sub, poses=self.poses)
        self.team_topic = team_topic
        self.pub: ros2dds.MapPublisher | None = None
        self.status = ros2dds.writer(self.dp, status_topic, STATUS_TYPE, latched=False)
        self.traffic = {"orders": 0, "bytes_in": 0, "bytes_out": 0}
        self._told = {"rejected": 0, "off_grid": 0, "unplaced": 0}
        self.step = 0

    def wait_first(self, timeout: float) -> None:
        """Until the first map (and, with a pose topic, the first pose) has come; one line
        after ``timeout`` seconds."""
        self.sub.wait(timeout)
        t_end = time.monotonic() + timeout
        while self.poses is not None and self.poses.poll() is None:
            if time.monotonic() > t_end:
                raise FedmapError(f"no pose arrived on {self.poses.topic} within {timeout:g} s")
            time.sleep(0.02)

    def on_mission(self, mission: Mission) -> None:
        """The mission's grid: the team map is published on it (its cell size)."""
        if self.pub is None:
            self.pub = ros2dds.MapPublisher(self.dp, self.team_topic, resolution=mission.truth.pixel_size)

    def on_belief(self, step: int, belief: np.ndarray) -> None:
        """After an order: the team map out, and a line per new bad input."""
        if self.pub is not None:
            self.pub.publish(belief, time.time_ns())
        for why in self.sub.rejected[self._told["rejected"]:]:
            self.say(f"rover {self.k}: a map on {self.sub.topic} was dropped: {why}")
        self._told["rejected"] = len(self.sub.rejected)
        if self.feed.off_grid > self._told["off_grid"]:
            h, w = self.feed.off_shape or (0, 0)
            self.say(f"rover {self.k}: the latest map on {self.sub.topic} is {h}x{w} cells, not the mission's "
                     f"{self.feed.shape[0]}x{self.feed.shape[1]} grid; not used" if self.feed.shape else
                     f"rover {self.k}: the latest map on {self.sub.topic} is off the mission's grid; not used")
            self._told["off_grid"] = self.feed.off_grid
        if self.poses is not None and self.poses.unplaced > self._told["unplaced"]:
            self.say(f"rover {self.k}: a pose on {self.poses.topic} came before any map (or off it): not used until "
                     "a map places it")
            self._told["unplaced"] = self.poses.unplaced
        self.step = step

    def on_traffic(self, order: int, report: int) -> None:
        """An order of ``order`` bytes answered with a report of ``report`` bytes: the status out."""
        self.traffic["orders"] += 1
        self.traffic["bytes_in"] += order
        self.traffic["bytes_out"] += report
        status = {"rover": self.k, "step": self.step, **self.traffic, "maps_received": self.sub.received,
                  "maps_dropped": len(self.sub.rejected), "off_grid_steps": self.feed.off_grid}
        self.status.write(ros2dds.to_dds(_string(json.dumps(status)), STATUS_TYPE))


class PoseSubscriber:
    """The latest pose on ROS 2 topic ``topic`` (``PoseStamped`` or ``Odometry``), as a cell
    of a map: :meth:`cell` places it on the map's grid through its origin and resolution
    (None, and counted in :attr:`unplaced`, before any map or off it)."""

    def __init__(self, dp: Any, topic: str, msgtype: str = POSE_TYPES[0]) -> None:
        if msgtype not in POSE_TYPES:
            raise FedmapError(f"a pose is one of {', '.join(POSE_TYPES)}, not {msgtype!r}")
        self.reader, self.topic, self.msgtype = ros2dds.reader(dp, topic, msgtype, latched=False), topic, msgtype
        self.xy: tuple[float, float] | None = None
        self.unplaced = 0

    def poll(self) -> tuple[float, float] | None:
        for sample in ros2dds.samples(self.reader):
            msg = ros2dds.from_dds(sample, self.msgtype)
            p = (msg.pose.pose if self.msgtype.endswith("Odometry") else msg.pose).position
            if math.isfinite(p.x) and math.isfinite(p.y):
                self.xy = (float(p.x), float(p.y))
        return self.xy

    def cell(self, grid: Any) -> tuple[int, int] | None:
        """The latest pose's cell of ``grid`` (a :class:`~fedmap.maps.grid.GridMap` read from
        an OccupancyGrid), or None."""
        xy = self.poll()
        if xy is None:
            return None
        if grid is None or grid.transform is None:  # no map yet, or one turned in its frame
            self.unplaced += 1
            return None
        (row, col), (h, w) = cell_of(grid.transform, *xy), grid.shape
        if not (0 <= row < h and 0 <= col < w):
            self.unplaced += 1
            return None
        return row, col


def play_in_background(bag: Any, domain: int, topics: list[str], *, loopback: bool = False,
                       say: Callable[[str], None] = print) -> threading.Thread:
    """Play ``bag``'s ``topics`` (its map, and its poses) into domain ``domain`` at the bag's
    timing from a participant of its own, once every topic has a reader, in a daemon thread
    (``--bag``: a rover rehearsed from its logs). Keep the thread object: its participant, and
    with it the last map played (latched), lives as long as it does. The bag is checked first (one line for a
    bag without one of the topics)."""
    from fedmap.maps.rosbag import bag_topics, wanted_topics

    wanted_topics(bag_topics(bag), topics, str(bag))
    dp = ros2dds.participant(domain, loopback=loopback)

    def play() -> None:
        n = ros2dds.play_bag(bag, dp, topics=topics, readers=1)
        say(f"played {n} message(s) of {', '.join(topics)} from {bag}")

    t = threading.Thread(target=play, name="bag", daemon=True)
    t.participant = dp  # type: ignore[attr-defined]  # its writers (the latched map) live as long as the thread object
    t.start()
    return t


def _string(text: str) -> Any:
    return ros2dds.typestore().types[STATUS_TYPE](data=text)


__all__ = ["POSE_TYPES", "STATUS_TYPE", "PoseSubscriber", "Ros2Bridge", "play_in_background"]
