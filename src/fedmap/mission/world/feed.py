"""A rover's world from its own mapping software: a **map feed**.

By default a rover of a mission on processes simulates its own rover on the mission's
terrain (:class:`~fedmap.mission.world.world.World`). With a feed, what it has observed comes
from the maps its own software writes instead:

- a **folder of map snapshots** (PNG with a world file, GeoTIFF, ``.npy``, ROS map YAML:
  whatever :func:`fedmap.maps.io.load_map` reads), each named with the mission step it was
  taken at as the last number of its name (``map_0040.png``);
- a **ROS 2 bag** of ``nav_msgs/OccupancyGrid`` (:func:`fedmap.maps.rosbag.bag_map_feed`,
  no ROS needed), message time ``t`` at step ``round((t - t0) / step_seconds)``;
- a **live ROS 2 topic** (:class:`LiveFeed`: the latest map the robot's mapping stack
  published, over DDS, :class:`fedmap.maps.ros2dds.MapSubscriber`), whatever step the
  rover's clock is at.

Every snapshot must be on the mission's grid (its shape). At every step the rover takes
the latest snapshot at or before that step: its known cells the rover has not observed yet
become its observations of that step. Its software drives it, so it plans nothing; its
position (which the strategies' messages carry) is the known free cell nearest the centre
of what it observed last.
"""

from __future__ import annotations

import math
import re
from bisect import bisect_right
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, UNKNOWN, GridMap
from fedmap.maps.io import load_map
from fedmap.maps.rosbag import bag_map_feed, is_bag
from fedmap.mission.world.world import World

#: What a folder feed reads (the suffixes of map files).
FEED_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".yaml", ".yml")
_NUMBER = re.compile(r"(\d+)(?!.*\d)")


class MapFeed:
    """A rover's maps by mission step (:meth:`at`). ``maps`` are ``(step, classes)``."""

    def __init__(self, maps: list[tuple[int, np.ndarray]], source: str) -> None:
        if not maps:
            raise FedmapError(f"map feed {source} holds no maps")
        maps = sorted(maps, key=lambda m: m[0])
        self.steps = [s for s, _ in maps]
        self.maps = [m for _, m in maps]
        self.source = source

    @classmethod
    def open(cls, path, *, topic: str | None = None, step_seconds: float = 1.0) -> MapFeed:
        """A folder of snapshots or a ROS 2 bag (see the module docstring)."""
        path = Path(path)
        if not path.exists():
            raise FedmapError(f"map feed {path} does not exist")
        if is_bag(path):
            timed = list(bag_map_feed(path, topic=topic))
            if not timed:
                raise FedmapError(f"map feed {path}: the bag holds no OccupancyGrid message")
            t0 = timed[0][0]
            return cls([(int(round((t - t0) / step_seconds)), g.classes) for t, g in timed], str(path))
        if not path.is_dir():
            raise FedmapError(f"map feed {path} is neither a folder of map snapshots nor a ROS 2 bag")
        maps = []
        for f in sorted(path.iterdir()):
            if f.suffix.lower() not in FEED_SUFFIXES or f.name.startswith("."):
                continue
            m = _NUMBER.search(f.stem)
            if m is None:
                raise FedmapError(f"map feed snapshot {f.name} has no step number in its name (e.g. map_0040.png)")
            maps.append((int(m.group(1)), load_map(f).classes))
        return cls(maps, str(path))

    def at(self, step: int) -> np.ndarray | None:
        """The latest map at or before ``step`` (None before the first)."""
        i = bisect_right(self.steps, step)
        return self.maps[i - 1] if i else None

    def check(self, truth: GridMap) -> None:
        """One line when a snapshot is not on the mission's grid."""
        for s, m in zip(self.steps, self.maps):
            if m.shape != truth.shape:
                raise FedmapError(f"map feed {self.source}: the map of step {s} is {m.shape[0]}x{m.shape[1]}, the "
                                  f"mission's grid is {truth.shape[0]}x{truth.shape[1]}")


class Feed(Protocol):
    """What :class:`FeedWorld` reads a rover's maps from: :class:`MapFeed` or :class:`LiveFeed`."""

    source: str

    def at(self, step: int) -> np.ndarray | None: ...

    def check(self, truth: GridMap) -> None: ...


class LiveFeed:
    """A rover's maps as its mapping stack publishes them: at every step, the latest map
    ``subscriber`` received by then (:class:`fedmap.maps.ros2dds.MapSubscriber`, or anything
    whose ``poll()`` gives the latest :class:`GridMap` or None). A map that is not on the
    mission's grid is not used (:attr:`off_grid` counts the steps it was the latest).
    ``poses``: where the rover is, from its pose topic (:meth:`pose`;
    :class:`fedmap.zenohnet.ros2.PoseSubscriber`)."""

    def __init__(self, subscriber: Any, *, poses: Any = None) -> None:
        self.subscriber, self.poses = subscriber, poses
        self.source = str(getattr(subscriber, "topic", "a live topic"))
        self.shape: tuple[int, int] | None = None
        self.off_grid = 0
        self.off_shape: tuple[int, int] | None = None  #: the shape of the last map off the grid

    def check(self, truth: GridMap) -> None:
        """Only the mission's grid is known before the maps arrive."""
        self.shape = truth.shape

    def at(self, step: int) -> np.ndarray | None:
        """The latest map received by now (None before the first, or when it is off the grid)."""
        grid = self.subscriber.poll()
        if grid is None:
            return None
        if self.shape is not None and grid.shape != self.shape:
            self.off_grid += 1
            self.off_shape = grid.shape
            return None
        return grid.classes

    def pose(self) -> tuple[int, int] | None:
        """The rover's cell from its pose topic, placed on the latest map (None: no pose
        topic, no pose yet, or no map to place it on)."""
        if self.poses is None:
            return None
        return self.poses.cell(getattr(self.subscriber, "latest", None))


class FeedWorld(World):
    """The team's world where member ``k`` observes through a :class:`MapFeed` (it plans
    nothing: its own software drives it). Only member ``k`` is ever driven."""

    def __init__(self, world: World, k: int, feed: Feed) -> None:
        feed.check(world.truth)
        self.__dict__.update(world.__dict__)
        self.k, self.feed = k, feed

    def sense(self, k: int, t: int) -> None:
        if k != self.k:
            super().sense(k, t)
            return
        r, snap = self.team[k], self.feed.at(t)
        cell = self.feed.pose() if hasattr(self.feed, "pose") else None
        if cell is not None and cell != r.pos:  # its pose topic says where it is
            r.distance += math.hypot(cell[0] - r.pos[0], cell[1] - r.pos[1])
            r.pos = cell
            r.trail.append(cell)
        if snap is None:
            return
        new = (snap != UNKNOWN) & (r.local == UNKNOWN)
        if not new.any():
            return
        r.local[new] = snap[new]
        r.obs_step[new] = t
        r.wrote()
        if cell is not None:  # placed by its pose: not guessed from what it saw
            return
        cells = np.argwhere(new)
        centre = cells.mean(axis=0)
        free = np.argwhere(r.local == FREE)
        if len(free):
            d = ((free - centre) ** 2).sum(axis=1)
            pos = (int(free[int(np.argmin(d))][0]), int(free[int(np.argmin(d))][1]))
            if pos != r.pos:
                r.distance += math.hypot(pos[0] - r.pos[0], pos[1] - r.pos[1])
                r.pos = pos
                r.trail.append(pos)

    def drive(self, k: int, t: int) -> None:
        if k != self.k:
            super().drive(k, t)
            return
        self.sense(k, t)


__all__ = ["FEED_SUFFIXES", "Feed", "FeedWorld", "LiveFeed", "MapFeed"]
