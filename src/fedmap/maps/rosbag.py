"""Class maps in ROS 2 bags, without ROS: ``nav_msgs/msg/OccupancyGrid`` in and out
through `rosbags <https://gitlab.com/ternaris/rosbags>`_.

Reading (:func:`read_bag_map`, :func:`bag_map_feed`; :func:`fedmap.maps.io.load_map` and
``--map`` take a bag too). The path is the bag folder (``metadata.yaml`` plus its storage
files), or one ``.db3`` (sqlite3) or ``.mcap`` storage file. The topic is ``topic=``,
by default the bag's only OccupancyGrid topic; the message is ``index=`` (default -1, the
last). Each cell's value ``v`` follows map_server's reading of a raw map
(:mod:`fedmap.maps.ros`, the same thresholds): ``p = v / 100`` is IMPASSABLE above
``occupied_thresh`` (0.65), FREE below ``free_thresh`` (0.196) and UNKNOWN between;
-1 (and any value outside 0..100) is UNKNOWN. So 0..19 is free, 20..65 unknown and
66..100 impassable.

A ROS grid's row 0 is at the bottom (``origin.y``), fedmap's at the top, so the rows are
flipped; the map's transform puts the grid's lower-left corner at ``info.origin`` with
``info.resolution`` metres per cell (the pixel size), no CRS, as a map_server YAML does.
A rotated origin (non-zero yaw) leaves the transform unset, noted in ``meta["yaw"]``.

Writing (:func:`write_map_bag`, :func:`write_bag`; ``fedmap export MAP --format
rosbag2``) gives the same message back: values 0 (free), 100 (impassable) and -1
(unknown), frame ``map``, origin the lower-left corner of the map's transform when its CRS
is metric (else 0, 0), offered with map_server's QoS (reliable, transient local, keep last
1) so that RViz and Nav2 receive it from ``ros2 bag play``. Bags are written in rosbag2
format version 8 with sqlite3 storage by default: version 9 stores QoS profiles as a YAML
list, which Humble's reader (it reads them as a string) refuses. ``storage="mcap"`` writes
MCAP (Humble reads it with ``rosbag2_storage_mcap`` installed).

Every problem (not a bag, a missing topic, a topic of another type, a truncated or corrupt
file) is a one-line :class:`~fedmap.errors.FedmapError` naming the bag.

``grid_map_msgs/msg/GridMap`` (elevation) is not read: its column-major, circular-buffer
layout needs its own reader and a reference bag to test it against.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import numpy as np
from affine import Affine

from fedmap._util import check_writable, one_line
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.ros import FREE_THRESH, OCCUPIED_THRESH, classes_from_occupancy, lower_left_origin

#: The message type read and written.
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
#: Suffixes of the storage files a bag holds (sqlite3, MCAP).
BAG_SUFFIXES: tuple[str, ...] = (".db3", ".mcap")
#: The storages :func:`write_bag` writes.
STORAGES: tuple[str, ...] = ("sqlite3", "mcap")
#: rosbag2 format version written: the newest Humble reads (QoS profiles as a string).
BAG_VERSION: Literal[8] = 8
#: OccupancyGrid value of each class when written.
OCCUPANCY_VALUES: dict[int, int] = {FREE: 0, IMPASSABLE: 100, UNKNOWN: -1}


# --------------------------------------------------------------------------- values


def occupancy_from_classes(classes: np.ndarray) -> np.ndarray:
    """OccupancyGrid values (int8: 0 free, 100 impassable, -1 unknown) of a class map, same layout."""
    lut = np.zeros(3, dtype=np.int8)
    for c, v in OCCUPANCY_VALUES.items():
        lut[c] = v
    return lut[np.asarray(classes, dtype=np.uint8)]


def _yaw(q) -> float:
    """Yaw (rotation about z) of a quaternion, radians."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


# --------------------------------------------------------------------------- reading


def _reader_errors() -> tuple[type[BaseException], ...]:
    """What rosbags and its storages raise on a bad bag (sqlite3 through apsw)."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag2 import ReaderError
    from rosbags.serde import SerdeError

    errors: list[type[BaseException]] = [AnyReaderError, ReaderError, SerdeError, OSError, ValueError, KeyError,
                                         IndexError, EOFError, AssertionError]
    try:
        import apsw

        errors.append(apsw.Error)
    except ImportError:  # pragma: no cover  (rosbags' sqlite3 storage needs it)
        pass
    return tuple(errors)


def bag_storage(path) -> Path:
    """The path rosbags opens for ``path``: a bag folder with ``metadata.yaml``, a folder
    holding exactly one ``.db3``/``.mcap`` file (that file), a storage file, or the folder
    of a ``metadata.yaml``. Anything else is a one-line error."""
    path = Path(path)
    if not path.exists():
        raise FedmapError(f"no such ROS 2 bag: {path}")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in BAG_SUFFIXES)
        if len(files) == 1:
            return files[0]
        why = "no" if not files else f"{len(files)}"
        raise FedmapError(f"{path} is a folder that is not a ROS 2 bag: no metadata.yaml, and {why} storage files "
                          f"({', '.join(BAG_SUFFIXES)}) where one is needed")
    if path.name == "metadata.yaml":
        return path.parent
    if path.suffix.lower() in BAG_SUFFIXES:
        return path
    raise FedmapError(f"{path} is not a ROS 2 bag: give the bag folder, or a {' or '.join(BAG_SUFFIXES)} file")


def is_bag(path) -> bool:
    """True when ``path`` looks like a ROS 2 bag (see :func:`bag_storage`); nothing is read."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            p.suffix.lower() in BAG_SUFFIXES for p in path.iterdir() if p.is_file())
    return path.suffix.lower() in BAG_SUFFIXES or (path.name == "metadata.yaml" and path.is_file())


@contextmanager
def _open_bag(path: Path) -> Iterator[Any]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    errors = _reader_errors()
    try:  # the Humble typestore decodes bags that embed no message definitions (older rosbag2)
        with AnyReader([bag_storage(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            yield reader
    except FedmapError:
        raise
    except errors as exc:
        raise FedmapError(f"cannot read ROS 2 bag {path}: {one_line(exc)} (truncated or not a bag?)") from exc


def bag_topics(path) -> dict[str, str]:
    """Every topic of a bag and its message type."""
    with _open_bag(Path(path)) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


def _pick_topic(topics: dict[str, str], topic: str | None, where: str) -> str:
    grids = [t for t, ty in topics.items() if ty == OCCUPANCY_GRID]
    if topic is None:
        if len(grids) == 1:
            return grids[0]
        if not grids:
            shown = ", ".join(f"{t} ({ty})" for t, ty in topics.items()) or "none"
            raise FedmapError(f"{where} has no {OCCUPANCY_GRID} topic (its topics: {shown})")
        raise FedmapError(f"{where} has {len(grids)} {OCCUPANCY_GRID} topics ({', '.join(grids)}); choose one "
                          f"with topic= ([terrain.options] topic)")
    if topic not in topics:
        raise FedmapError(f"{where} has no topic {topic!r}; its {OCCUPANCY_GRID} topics: {', '.join(grids) or 'none'}")
    if topics[topic] != OCCUPANCY_GRID:
        raise FedmapError(f"topic {topic} of {where} holds {topics[topic]}, not {OCCUPANCY_GRID}")
    return topic


def grid_from_message(msg, source: str, *, time_ns: int | None = None) -> GridMap:
    """A :class:`GridMap` of a deserialised OccupancyGrid message (see the module docstring)."""
    info = msg.info
    h, w, res = int(info.height), int(info.width), float(info.resolution)
    data = np.asarray(msg.data)
    if h <= 0 or w <= 0:
        raise FedmapError(f"{source}: an empty grid ({w}x{h} cells)")
    if data.size != h * w:
        raise FedmapError(f"{source}: {data.size} values for a {w}x{h} grid")
    if not (res > 0 and math.isfinite(res)):
        raise FedmapError(f"{source}: resolution must be positive, got {res}")
    classes = classes_from_occupancy(data.reshape(h, w)[::-1])  # ROS row 0 is the bottom
    pos, yaw = info.origin.position, _yaw(info.origin.orientation)
    x0, y0 = float(pos.x), float(pos.y)
    if not (math.isfinite(x0) and math.isfinite(y0) and math.isfinite(yaw)):
        raise FedmapError(f"{source}: the grid's origin is not finite (x {x0}, y {y0}, yaw {yaw})")
    transform = Affine(res, 0.0, x0, 0.0, -res, y0 + h * res) if abs(yaw) < 1e-12 else None
    stamp = msg.header.stamp
    meta: dict[str, Any] = {"format": "rosbag2", "frame_id": str(msg.header.frame_id), "origin": [x0, y0, yaw],
                            "stamp_ns": int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec), "pixel_size_from": "file",
                            "occupied_thresh": OCCUPIED_THRESH, "free_thresh": FREE_THRESH}
    if time_ns is not None:
        meta["time_ns"] = int(time_ns)
    if transform is None:
        meta["yaw"] = yaw
    return GridMap(np.ascontiguousarray(classes), res, source, meta, transform=transform)


def wanted_topics(known: Mapping[str, str], topics: Iterable[str] | None, where: str) -> list[str]:
    """``topics`` (every one of ``known`` when None), each checked against ``known`` (topic ->
    type): a topic not there is a one-line error naming ``where`` and what is."""
    wanted = list(known) if topics is None else list(topics)
    missing = [t for t in wanted if t not in known]
    if missing:
        raise FedmapError(f"{where} has no topic {', '.join(missing)} (it has {', '.join(sorted(known)) or 'none'})")
    return wanted


def _messages(path: Path, choose: Callable[[dict[str, str]], list[str]]
              ) -> Generator[tuple[str, str, int, Any], None, None]:
    """``(topic, type, bag time in ns, message)`` of the topics ``choose`` picks from the bag's
    (topic -> type), deserialised, in bag order; the bag is opened once."""
    errors = _reader_errors()
    with _open_bag(path) as reader:
        chosen = set(choose({c.topic: c.msgtype for c in reader.connections}))
        conns = [c for c in reader.connections if c.topic in chosen]
        try:
            for conn, t, raw in reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, int(t), reader.deserialize(raw, conn.msgtype)
        except FedmapError:
            raise
        except errors as exc:
            raise FedmapError(f"cannot read ROS 2 bag {path}: {one_line(exc)} (truncated or not a bag?)") from exc


def bag_messages(path, topics: Iterable[str] | None = None) -> Generator[tuple[str, str, int, Any], None, None]:
    """``(topic, message type, bag time in ns, message)`` of every message on ``topics`` (every
    topic when None), deserialised, in bag order. A topic the bag lacks is a one-line error."""
    path = Path(path)
    yield from _messages(path, lambda known: wanted_topics(known, topics, f"ROS 2 bag {path}"))


def _grid_messages(path: Path, topic: str | None) -> Generator[tuple[int, GridMap], None, None]:
    """(bag time in ns, map) of every message of the chosen topic, in bag order."""
    pick = lambda known: [_pick_topic(known, topic, f"ROS 2 bag {path}")]  # noqa: E731
    for n, (chosen, _, t, msg) in enumerate(_messages(path, pick)):
        yield t, grid_from_message(msg, f"{path} {chosen} #{n}", time_ns=t)


def bag_map_feed(path, *, topic: str | None = None) -> Iterator[tuple[float, GridMap]]:
    """A map feed: ``(time, map)`` of every OccupancyGrid message on ``topic``, in bag order.

    ``time`` is the bag's receive time in seconds (the header stamp is in
    ``map.meta["stamp_ns"]``, the bag time in ``map.meta["time_ns"]``).
    """
    for t, grid in _grid_messages(Path(path), topic):
        yield t / 1e9, grid


def read_bag_map(path, *, topic: str | None = None, index: int = -1) -> GridMap:
    """One OccupancyGrid message of a ROS 2 bag as a class map.

    Parameters
    ----------
    path : str or Path
        The bag folder, or its ``.db3`` / ``.mcap`` file.
    topic : str, optional
        The topic; by default the bag's only OccupancyGrid topic.
    index : int
        Which message of the topic, from 0 (negative: from the end; default the last).
    """
    path = Path(path)
    feed = _grid_messages(path, topic)
    count = 0
    try:
        if index >= 0:
            for _t, grid in feed:
                if count == index:
                    return grid
                count += 1
        else:
            last: deque[GridMap] = deque(maxlen=-index)
            for _t, grid in feed:
                last.append(grid)
                count += 1
            if count >= -index:
                return last[0]
    finally:
        feed.close()  # a message picked early closes the bag now
    raise FedmapError(f"ROS 2 bag {path} has {count} map message(s) on its topic; there is no message {index}")


# --------------------------------------------------------------------------- writing


def occupancy_message(typestore, classes: np.ndarray, *, resolution: float, origin: tuple[float, float],
                      time_ns: int, frame_id: str = "map"):
    """The ``nav_msgs/msg/OccupancyGrid`` of a class map (H, W): map_server's values, rows from
    the bottom up, ``origin`` its lower-left corner, stamped ``time_ns``."""
    t = typestore.types
    h, w = classes.shape
    stamp = t["builtin_interfaces/msg/Time"](sec=int(time_ns // 1_000_000_000), nanosec=int(time_ns % 1_000_000_000))
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=float(origin[0]), y=float(origin[1]),
                                                                             z=0.0),
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = t["nav_msgs/msg/MapMetaData"](map_load_time=stamp, resolution=float(resolution), width=w, height=h,
                                         origin=pose)
    data = np.ascontiguousarray(occupancy_from_classes(classes)[::-1]).reshape(-1)  # bottom row first
    return t[OCCUPANCY_GRID](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id), info=info, data=data)


def _message(typestore, grid: GridMap, time_ns: int, frame_id: str):
    """The OccupancyGrid message of ``grid`` stamped ``time_ns``."""
    return occupancy_message(typestore, grid.classes, resolution=grid.pixel_size, origin=lower_left_origin(grid),
                             time_ns=time_ns, frame_id=frame_id)


def _map_qos():
    """map_server's QoS: reliable, transient local, keep last 1 (a late subscriber still gets the map)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL, deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


def check_topic(topic: str) -> str:
    """``topic`` when it is an absolute ROS topic name (``/map``, ``/fedmap/team_map``), else a one-line error."""
    if not topic.startswith("/") or not all(part and (part[0].isalpha() or part[0] == "_") and all(
            c.isalnum() or c == "_" for c in part) for part in topic[1:].split("/")):
        raise FedmapError(f"not a ROS topic name: {topic!r} (e.g. /map, /raw/global_map)")
    return topic


def check_bag_path(path) -> Path:
    """Where a bag goes, checked before any work: a new folder, or an existing ROS 2 bag (which
    is replaced), in a folder that can be written; otherwise a one-line error."""
    path = Path(path)
    if path.exists() and not (path.is_dir() and (path / "metadata.yaml").is_file()):
        raise FedmapError(f"{path} exists and is not a ROS 2 bag; a bag is written to a new folder")
    check_writable(path, f"ROS 2 bag {path}")
    return path


def write_bag(messages: Iterable[tuple[str, int, GridMap]], path, *, frame_id: str = "map",
              storage: str = "sqlite3") -> Path:
    """Write ``(topic, time in ns, map)`` messages as OccupancyGrids into a new ROS 2 bag folder.

    The bag is written in a temporary sibling folder and moved into place, so ``path``
    holds a whole bag or nothing; an existing bag at ``path`` is replaced, any other
    existing path is a one-line error. Times must not be negative. Returns ``path``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
    from rosbags.typesys import Stores, get_typestore

    path = check_bag_path(path)
    if storage not in STORAGES:
        raise FedmapError(f"unknown bag storage {storage!r}; choose one of {', '.join(STORAGES)}")
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        with Writer(tmp / path.name, version=BAG_VERSION, storage_plugin=plugin) as writer:
            conns: dict[str, Any] = {}
            for topic, time_ns, grid in messages:
                if topic not in conns:
                    conns[topic] = writer.add_connection(check_topic(topic), OCCUPANCY_GRID, typestore=typestore,
                                                         offered_qos_profiles=[_map_qos()])
                if time_ns < 0:
                    raise FedmapError(f"bag time must not be negative, got {time_ns} ns")
                msg = _message(typestore, grid, int(time_ns), frame_id)
                writer.write(conns[topic], int(time_ns), typestore.serialize_cdr(msg, OCCUPANCY_GRID))
        if path.exists():  # an older bag: swap it out only once the new one is complete
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            shutil.rmtree(old, ignore_errors=True)
        os.replace(tmp / path.name, path)
    except (OSError, WriterError) as exc:
        raise FedmapError(f"cannot write ROS 2 bag {path}: {one_line(exc)}") from exc
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_map_bag(grid: GridMap, path, *, topic: str = "/map", frame_id: str = "map", time_ns: int = 0,
                  storage: str = "sqlite3") -> Path:
    """Write one map as a ROS 2 bag: one OccupancyGrid on ``topic`` (see :func:`write_bag`)."""
    return write_bag([(topic, time_ns, grid)], path, frame_id=frame_id, storage=storage)


def write_maps_bag(maps: Mapping[str, GridMap], path, *, frame_id: str = "map", time_ns: int = 0,
                   storage: str = "sqlite3") -> Path:
    """Write several maps into one bag, ``/<name>`` per map, all at ``time_ns``."""
    return write_bag(((f"/{name}", time_ns, grid) for name, grid in maps.items()), path, frame_id=frame_id,
                     storage=storage)


__all__ = ["BAG_SUFFIXES", "BAG_VERSION", "OCCUPANCY_GRID", "OCCUPANCY_VALUES", "STORAGES", "bag_map_feed",
           "bag_messages", "bag_storage", "bag_topics", "check_topic", "classes_from_occupancy", "grid_from_message",
           "is_bag", "occupancy_from_classes", "occupancy_message", "read_bag_map", "wanted_topics", "write_bag",
           "write_map_bag", "write_maps_bag"]
