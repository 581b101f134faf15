"""``rosgrid``: what a ROS 2 team shares without fedmap, as a strategy on the star.

Every sync each rover publishes its **whole** local map as a ``nav_msgs/msg/OccupancyGrid``
(map_server's values: 0 free, 100 occupied, -1 unknown), CDR-serialised by rosbags'
typestore for ROS 2 Humble. The base merges the latest grid of every rover as
``multirobot_map_merge`` does with known poses (its ``GridCompositor`` takes the cell-wise
maximum of the signed values: a known cell overwrites an unknown one, and where two rovers
disagree *occupied* wins over *free*; observations here are exact, so they never
disagree) and publishes the merged grid back to every rover, again whole.
``rosgrid-zlib`` compresses each serialised grid with zlib at level 9 (:data:`ZLIB_LEVEL`).

* **Frame.** Both directions use frame ``map``, the truth's pixel size as ``resolution``,
  the mission's whole grid (``width`` columns, ``height`` rows), and ``origin`` the
  lower-left corner of the grid as :mod:`fedmap.maps.ros` writes it (metric CRS: its
  coordinates; else (0, 0)), identity orientation. Rows run from the bottom (largest
  fedmap row) up, as map_server loads an image. ``header.stamp`` and
  ``info.map_load_time`` are the round's sync step in seconds (one step = 1 s): the
  mission has no clock of its own, and the stamp's 8 bytes are there whatever it says.
* **Positions and targets** go in fedmap's mission headers (:func:`~fedmap.mission.ends.protocol.pack_up`,
  16 bytes up; :func:`~fedmap.mission.ends.protocol.pack_down`, 10 + 9 per rover bytes down)
  in front of the grid, counted like every other strategy's. A ROS team would publish
  poses on topics of their own, which cost more (one ``geometry_msgs/msg/PoseStamped`` in
  frame ``map`` is 76 bytes of CDR).
* **The link.** A grid over the budget is not sent (``over budget``): a whole grid can't be
  cut. A lost grid is not sent again as such; the next sync sends the whole map anyway.
  The acknowledgement changes nothing (a grid is never relative to another). A grid that
  does not decode, is not in the mission's frame, or is older (by its stamp) than the one
  an end holds is refused (answered False: a downlink is recorded ``stale``).
* **Elevation.** An OccupancyGrid has no heights: with an elevation layer, ``rosgrid``
  shares classes only.
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from fedmap._util import inflate_zlib
from fedmap.maps.grid import UNKNOWN
from fedmap.maps.ros import classes_from_occupancy
from fedmap.maps.rosbag import OCCUPANCY_GRID, OCCUPANCY_VALUES, occupancy_message
from fedmap.mission.ends.protocol import (
    BaseEnd,
    Cell,
    Journal,
    Outgoing,
    RoverEnd,
    pack_down,
    pack_up,
    unpack_down,
    unpack_up,
)

MSGTYPE = OCCUPANCY_GRID
FRAME = "map"
#: Bytes of an OccupancyGrid's CDR besides its cells (header, frame id, info, lengths): a generous bound.
_CDR_HEAD = 1024
#: zlib's level in ``rosgrid-zlib`` (9: the smallest output zlib gives; level 6, its default,
#: gave 5-6 % more bytes on the default, Gale and Hadley missions).
ZLIB_LEVEL = 9
#: map_server's occupancy values (``nav_msgs/msg/OccupancyGrid.data``) of each fedmap class.
VALUES: dict[int, int] = OCCUPANCY_VALUES
_TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)


def typestore() -> Any:
    """rosbags' ROS 2 Humble typestore (its message classes and CDR codec)."""
    return _TYPESTORE


def grid_message(classes: np.ndarray, *, resolution: float, origin: tuple[float, float], stamp: int) -> Any:
    """The ``nav_msgs/msg/OccupancyGrid`` of a class map (H, W), stamped ``stamp`` seconds
    (:func:`fedmap.maps.rosbag.occupancy_message`, the one way fedmap builds the message)."""
    return occupancy_message(_TYPESTORE, classes, resolution=resolution, origin=origin,
                             time_ns=int(stamp) * 1_000_000_000, frame_id=FRAME)


def grid_classes(msg: Any) -> np.ndarray:
    """A decoded OccupancyGrid's classes (H, W), by map_server's trinary thresholds
    (:func:`fedmap.maps.ros.classes_from_occupancy`); rows from the top, as fedmap holds them."""
    v = np.asarray(msg.data, dtype=np.int16).reshape(int(msg.info.height), int(msg.info.width))
    return np.ascontiguousarray(classes_from_occupancy(v)[::-1])


class GridCodec:
    """The grid codec both ends of one run share: the mission's frame and the compression."""

    def __init__(self, shape: tuple[int, int], *, resolution: float, origin: tuple[float, float], sync_every: int,
                 level: int | None) -> None:
        self.shape, self.resolution, self.origin = shape, resolution, origin
        self.sync_every, self.level = sync_every, level

    def encode(self, classes: np.ndarray, round_no: int) -> bytes:
        msg = grid_message(classes, resolution=self.resolution, origin=self.origin, stamp=round_no * self.sync_every)
        cdr = bytes(_TYPESTORE.serialize_cdr(msg, MSGTYPE))
        return cdr if self.level is None else zlib.compress(cdr, self.level)

    def decode(self, body: bytes) -> tuple[np.ndarray, int] | None:
        """The classes and stamp of a grid, or None when it is not a grid of this mission's frame."""
        try:
            cdr = body if self.level is None else inflate_zlib(body, self.shape[0] * self.shape[1] + _CDR_HEAD)
            msg: Any = _TYPESTORE.deserialize_cdr(cdr, MSGTYPE)
        except Exception:  # a body that is not a grid: refused, whatever rosbags or zlib raised
            return None
        if ((int(msg.info.height), int(msg.info.width)) != self.shape or msg.header.frame_id != FRAME
                or not np.isclose(msg.info.resolution, self.resolution, rtol=1e-6)):
            return None
        return grid_classes(msg), int(msg.header.stamp.sec)


def _fits(payload: bytes, budget: int | None) -> bytes | None:
    return payload if budget is None or len(payload) <= budget else None


class RosgridRover(RoverEnd):
    """A rover's end of ``rosgrid``: it publishes its whole map, and holds the last merged grid."""

    def __init__(self, k: int, rover: Any, starts: list[Cell], *, grids: GridCodec, budget: int | None) -> None:
        super().__init__(k, rover, starts)
        self.grids, self.budget = grids, budget
        self._held = np.full(self.shape, UNKNOWN, dtype=np.uint8)
        self._stamp = -1  # the stamp of the merged grid it holds

    def held(self) -> np.ndarray:
        return self._held

    def uplink(self, round_no: int) -> Outgoing | None:
        r = self.rover
        payload = pack_up("", r.pos, r.target, self.grids.encode(r.local, round_no))
        return Outgoing(_fits(payload, self.budget), "grid")

    def receive(self, payload: bytes) -> bool:
        _, _, reports, body = unpack_down(payload)
        got = self.grids.decode(body)
        if got is None or got[1] < self._stamp:
            return False
        self._held, self._stamp = got
        self.reports.update(reports)
        return True


class RosgridBase(BaseEnd):
    """The base's end of ``rosgrid``: the latest grid of every rover, merged as map_merge does."""

    def __init__(self, shape: tuple[int, int], starts: list[Cell], *, grids: GridCodec, budget: int | None,
                 journal: Journal | None = None) -> None:
        super().__init__(shape, starts)
        self.grids, self.budget = grids, budget
        self.journal = journal if journal is not None else Journal()
        self.latest: dict[int, tuple[np.ndarray, int]] = {}  # rover -> its latest grid (classes) and stamp
        self.merged = np.full(shape, UNKNOWN, dtype=np.uint8)

    def global_map(self) -> np.ndarray:
        return self.merged

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        _, pos, target, body = unpack_up(payload)
        got = self.grids.decode(body)
        if got is None or (k in self.latest and got[1] < self.latest[k][1]):
            return False
        self.latest[k] = got
        self.journal.received.append((round_no, k, payload))
        self.merged = merge([g for g, _ in self.latest.values()], self.shape)
        self.reports[k] = (pos, target)
        return True

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        body = self.grids.encode(self.merged, round_no)  # one merged grid, published to every rover
        payload = _fits(pack_down("map", "", self.reports, body), self.budget)
        return {k: Outgoing(payload, "grid") for k in range(self.n)}


def merge(grids: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Class maps merged as map_merge's ``GridCompositor`` merges OccupancyGrids: the cell-wise
    maximum of their occupancy values (unknown -1 < free 0 < occupied 100)."""
    value = np.full(shape, VALUES[UNKNOWN], dtype=np.int8)
    for g in grids:
        v = np.full(shape, VALUES[UNKNOWN], dtype=np.int8)
        for c, x in VALUES.items():
            v[g == c] = x
        value = np.maximum(value, v)
    out = np.full(shape, UNKNOWN, dtype=np.uint8)
    for c, x in VALUES.items():
        out[value == x] = c
    return out
