"""ROS 2 messages on the DDS wire, with types built from ROS 2's message definitions.

A ROS 2 graph is a DDS domain (ROS 2 design article "Topic and Service name mapping to
DDS"; ``rmw_cyclonedds`` and ``rmw_fastrtps`` both follow it):

- the ROS 2 topic ``/map`` is the DDS topic ``rt/map`` (:func:`dds_topic`);
- the message type ``nav_msgs/msg/OccupancyGrid`` is the DDS type
  ``nav_msgs::msg::dds_::OccupancyGrid_`` (:func:`dds_name`), sent as plain CDR.

:func:`dds_type` builds the Cyclone DDS IDL class (``cyclonedds.idl.IdlStruct``) of any
message type that rosbags' typestore knows (ROS 2 Humble's definitions), field by field
and nested types first. So no message type is copied here by hand, and a sample's CDR bytes
equal rosbags' ``serialize_cdr`` of the same message (tests check OccupancyGrid,
PoseStamped, Odometry and TFMessage). :func:`to_dds` and :func:`from_dds` carry a message
between rosbags' classes (what :func:`fedmap.maps.rosbag.grid_from_message` and
:func:`fedmap.maps.rosbag.occupancy_message` read and build) and the DDS samples.

Needs the ``ros2`` extra (``pip install 'fedmap[ros2]'``: Cyclone DDS's Python binding, a
self-contained wheel); without it, :func:`dds_type` says so in one line.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.rosbag import check_topic

#: rosbags' typestore the types come from: ROS 2 Humble's message definitions.
STORE = "ros2_humble"


@functools.cache
def typestore() -> Any:
    """rosbags' typestore of :data:`STORE`."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores(STORE))


def _split(msgtype: str) -> tuple[str, str, str]:
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise FedmapError(f"a ROS 2 message type is package/msg/Name, got {msgtype!r}")
    return parts[0], parts[1], parts[2]


def dds_name(msgtype: str) -> str:
    """The DDS type name of a ROS 2 message type: ``nav_msgs/msg/OccupancyGrid`` ->
    ``nav_msgs::msg::dds_::OccupancyGrid_``."""
    package, kind, name = _split(msgtype)
    return f"{package}::{kind}::dds_::{name}_"


def dds_topic(topic: str) -> str:
    """The DDS topic of an absolute ROS 2 topic: ``/map`` -> ``rt/map``."""
    return "rt" + check_topic(topic)


def _idl() -> Any:
    try:
        import cyclonedds.idl as idl
    except ImportError as e:  # the ros2 extra is not installed
        raise FedmapError("ROS 2 over DDS needs Cyclone DDS's Python binding: pip install 'fedmap[ros2]' "
                          f"({e})") from None
    return idl


def _base(name: str, bound: int) -> Any:
    t = _idl().types
    if name == "string":
        return t.bounded_str[bound] if bound else str
    if name == "bool":
        return bool
    if name in ("byte", "char"):  # one unsigned byte on the wire in ROS 2
        return t.uint8
    if name in ("int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32", "float64"):
        return getattr(t, name)
    raise FedmapError(f"no DDS type for the ROS 2 base type {name!r}")


def _field_type(node: tuple) -> Any:
    from rosbags.typesys.base import Nodetype

    kind, spec = node
    t = _idl().types
    if kind == Nodetype.BASE:
        return _base(*spec)
    if kind == Nodetype.NAME:
        return dds_type(spec)
    if kind == Nodetype.ARRAY:
        sub, length = spec
        return t.array[_field_type(sub), length]
    if kind == Nodetype.SEQUENCE:
        sub, bound = spec
        return t.sequence[_field_type(sub), bound] if bound else t.sequence[_field_type(sub)]
    raise FedmapError(f"no DDS type for the ROS 2 field kind {kind!r}")


@functools.cache
def dds_type(msgtype: str) -> Any:
    """The Cyclone DDS IDL class of ROS 2 message type ``msgtype`` (``nav_msgs/msg/OccupancyGrid``),
    built from rosbags' typestore with the type name :func:`dds_name` gives. One class per type
    and process (a DDS participant matches types by name and layout)."""
    _split(msgtype)
    defs = typestore().fielddefs
    if msgtype not in defs:
        raise FedmapError(f"unknown ROS 2 message type {msgtype!r} (ROS 2 Humble's definitions)")
    _, fields = defs[msgtype]
    return _idl().make_idl_struct(msgtype.replace("/", "_"), dds_name(msgtype),
                                  {name: _field_type(node) for name, node in fields})


def _fields(msgtype: str) -> list[tuple[str, tuple]]:
    return typestore().fielddefs[msgtype][1]


def _walk(node: tuple, value: Any, message: Any, numbers: Any) -> Any:
    """A field's value carried across: nested messages by ``message(value, msgtype)``, arrays
    and sequences of numbers by ``numbers(value, base type)``, the rest as it is."""
    from rosbags.typesys.base import Nodetype

    kind, spec = node
    if kind == Nodetype.BASE:
        return value
    if kind == Nodetype.NAME:
        return message(value, spec)
    sub = spec[0]
    if sub[0] == Nodetype.BASE and sub[1][0] != "string":
        return numbers(value, sub[1][0])
    return [_walk(sub, v, message, numbers) for v in value]


def to_dds(msg: Any, msgtype: str) -> Any:
    """A rosbags message of type ``msgtype`` as a sample of :func:`dds_type` (numbers that
    rosbags holds as numpy arrays become lists)."""
    cls = dds_type(msgtype)
    return cls(**{name: _walk(node, getattr(msg, name), to_dds, lambda v, _: np.asarray(v).tolist())
                  for name, node in _fields(msgtype)})


_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8, "int16": np.int16,
          "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
          "float32": np.float32, "float64": np.float64}


def from_dds(sample: Any, msgtype: str) -> Any:
    """A sample of :func:`dds_type` as rosbags' message of type ``msgtype`` (numbers as
    numpy arrays, as rosbags deserialises them)."""
    cls = typestore().types[msgtype]
    return cls(**{name: _walk(node, getattr(sample, name), from_dds, lambda v, t: np.asarray(v, dtype=_NUMPY[t]))
                  for name, node in _fields(msgtype)})


# --------------------------------------------------------------------------- the live graph

#: Cyclone DDS's configuration of a domain confined to this machine: the loopback interface,
#: no multicast, discovery by unicast to localhost (tests, and a rehearsal on one computer).
LOOPBACK = ('<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
            '<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>'
            '<Peers><Peer address="localhost"/></Peers></Discovery></Domain></CycloneDDS>')


def check_domain(domain: int) -> int:
    """``domain`` when it is a ROS_DOMAIN_ID DDS accepts (0-232), else a one-line error."""
    if isinstance(domain, bool) or not isinstance(domain, int) or not 0 <= domain <= 232:
        raise FedmapError(f"a ROS 2 domain id is a whole number in [0, 232], got {domain!r}")
    return domain


def participant(domain: int = 0, *, loopback: bool = False) -> Any:
    """A DDS participant in ROS 2 domain ``domain`` (ROS_DOMAIN_ID), with Cyclone DDS's own
    configuration (``CYCLONEDDS_URI``), or confined to this machine with ``loopback``
    (:data:`LOOPBACK`; set before the process's first participant in that domain)."""
    _idl()
    from cyclonedds.domain import Domain, DomainParticipant

    check_domain(domain)
    if loopback and domain not in _CONFIGURED:  # (once: a domain is configured before its first participant)
        _CONFIGURED[domain] = Domain(domain, LOOPBACK)
    return DomainParticipant(domain)


#: Domains this process confined to the loopback interface (:func:`participant`).
_CONFIGURED: dict[int, Any] = {}


def map_qos(*, latched: bool = True) -> Any:
    """The QoS of a map topic: reliable, the last sample kept, and with ``latched`` transient
    local, as map_server and slam_toolbox publish ``/map`` and Nav2's static layer reads it
    (a reader that joins late still gets the last map); volatile otherwise."""
    _idl()
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    durability = Policy.Durability.TransientLocal if latched else Policy.Durability.Volatile
    return Qos(Policy.Reliability.Reliable(duration(seconds=1)), durability, Policy.History.KeepLast(1))


def writer(dp: Any, topic: str, msgtype: str, *, latched: bool = True) -> Any:
    """A DDS writer of ROS 2 topic ``topic`` (absolute) with messages of ``msgtype``."""
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic

    return DataWriter(dp, Topic(dp, dds_topic(topic), dds_type(msgtype)), qos=map_qos(latched=latched))


def reader(dp: Any, topic: str, msgtype: str, *, latched: bool = True) -> Any:
    """A DDS reader of ROS 2 topic ``topic`` (absolute) with messages of ``msgtype``. A
    transient-local reader (``latched``) matches writers of either durability; a volatile
    one does not get what a latched writer published before it joined."""
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    return DataReader(dp, Topic(dp, dds_topic(topic), dds_type(msgtype)), qos=map_qos(latched=latched))


def samples(reader: Any, n: int = 64) -> list:
    """Up to ``n`` samples taken from ``reader`` that hold data: the notifications DDS also
    delivers (a writer that left, an instance disposed: Cyclone's ``InvalidSample``) are dropped."""
    from cyclonedds.sub import InvalidSample

    return [s for s in reader.take(N=n) if not isinstance(s, InvalidSample)]


#: The ROS 2 type of every map in and out.
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"


class MapPublisher:
    """Publishes class maps as ``nav_msgs/OccupancyGrid`` on ROS 2 topic ``topic``,
    latched (reliable, transient local, the last kept): Nav2's static layer and RViz get the
    last map when they join late. ``resolution`` (m per cell) and ``origin`` (the lower-left
    corner in ``frame_id``) place every map."""

    def __init__(self, dp: Any, topic: str, *, resolution: float, origin: tuple[float, float] = (0.0, 0.0),
                 frame_id: str = "map") -> None:
        self.writer = writer(dp, topic, OCCUPANCY_GRID)
        self.resolution, self.origin, self.frame_id = float(resolution), origin, frame_id
        self.sent = 0  #: maps published

    def publish(self, classes: np.ndarray, time_ns: int) -> None:
        """Publish the class map ``classes`` (H, W), stamped ``time_ns``."""
        from fedmap.maps.rosbag import occupancy_message

        msg = occupancy_message(typestore(), classes, resolution=self.resolution, origin=self.origin,
                                time_ns=time_ns, frame_id=self.frame_id)
        self.writer.write(to_dds(msg, OCCUPANCY_GRID))
        self.sent += 1


class MapSubscriber:
    """The latest ``nav_msgs/OccupancyGrid`` on ROS 2 topic ``topic``, read with map_server's
    thresholds (:func:`fedmap.maps.rosbag.grid_from_message`). The reader is transient local,
    so it gets the last map of a latched publisher (map_server, slam_toolbox) that published
    before it joined, and every later one of a volatile publisher too."""

    def __init__(self, dp: Any, topic: str) -> None:
        self.reader, self.topic = reader(dp, topic, OCCUPANCY_GRID), topic
        self.latest: GridMap | None = None
        self.received = 0  #: maps received
        self.rejected: list[str] = []  #: why each map that could not be read was dropped, in order

    def poll(self) -> GridMap | None:
        """The latest map received by now (None before the first); a damaged one (a size
        that does not match its grid, a non-finite origin) is dropped, the one before kept and
        why noted in :attr:`rejected`."""
        from fedmap.maps.rosbag import grid_from_message

        for sample in samples(self.reader):
            try:
                self.latest = grid_from_message(from_dds(sample, OCCUPANCY_GRID), self.topic)
            except FedmapError as e:
                self.rejected.append(str(e))
                continue
            self.received += 1
        return self.latest

    def wait(self, timeout: float) -> GridMap:
        """The first map, waiting at most ``timeout`` seconds for it (a one-line error when none came)."""
        import time

        deadline = time.monotonic() + timeout
        while self.poll() is None:
            if time.monotonic() > deadline:
                if self.rejected:
                    raise FedmapError(f"no map on {self.topic} could be read within {timeout:g} s: "
                                      f"{len(self.rejected)} dropped, the last because {self.rejected[-1]}")
                raise FedmapError(f"no map arrived on {self.topic} within {timeout:g} s (is the mapping stack "
                                  "running, in this ROS_DOMAIN_ID?)")
            time.sleep(0.02)
        assert self.latest is not None
        return self.latest


def play_bag(path, dp: Any, *, topics: list[str] | None = None, speed: float = 1.0, readers: int = 0,
             wait: float = 10.0, clock: Any = None, sleep: Any = None) -> int:
    """Publish the messages of a ROS 2 bag on their topics at the bag's timing, as the robot
    that recorded it did (a mapping stack rehearsed from its logs). Returns how many.

    ``topics``: the bag's topics to play (all when None). Maps (OccupancyGrid) go out latched,
    as map_server and slam_toolbox publish them; every other type reliable and volatile.
    ``speed``: 2 plays twice as fast. ``readers``: before the first message, wait (at most
    ``wait`` seconds) until every topic has that many readers, so none misses the start.
    ``clock`` and ``sleep`` (default: the monotonic clock) pace it."""
    import time

    from fedmap.maps.rosbag import bag_messages, bag_topics, wanted_topics

    if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
        raise FedmapError(f"speed must be a positive number, got {speed!r}")
    clock, sleep = clock or time.monotonic, sleep or time.sleep
    kinds = bag_topics(path)
    chosen = wanted_topics(kinds, topics, f"ROS 2 bag {path}")  # before waiting for readers
    writers = {t: writer(dp, t, kinds[t], latched=kinds[t] == OCCUPANCY_GRID) for t in chosen}
    deadline = clock() + wait
    while readers and any(len(w.get_matched_subscriptions()) < readers for w in writers.values()):
        if clock() > deadline:
            raise FedmapError(f"no {readers} reader(s) on every topic of {', '.join(writers)} within {wait:g} s")
        sleep(0.02)
    start, first, sent = clock(), None, 0
    for topic, msgtype, t, msg in bag_messages(path, chosen):
        first = t if first is None else first
        ahead = start + (t - first) / 1e9 / speed - clock()
        if ahead > 0:
            sleep(ahead)
        writers[topic].write(to_dds(msg, msgtype))
        sent += 1
    return sent


__all__ = ["LOOPBACK", "OCCUPANCY_GRID", "STORE", "MapPublisher", "MapSubscriber", "play_bag", "check_domain", "dds_name",
           "dds_topic", "dds_type", "from_dds", "map_qos", "participant", "reader", "samples", "to_dds", "typestore",
           "writer"]
