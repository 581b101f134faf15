"""What each node of a mission writes to its own log, and nothing else: the record a
mission is scored from, off the link (:func:`fedmap.mission.scoring.score_strategy`).

* A **rover node** writes one :class:`RoverEntry` each time it answers an order: every
  step it recorded since the last one (its belief, its view, the cells it observed, where
  it is, its target, how far it has come: :class:`StepState`) and the cells it entered.
  On a robot this is the rover's own disk; nothing of it crosses the link.
* The **base station** writes one :class:`BaseRecord` per strategy: the global map it held
  after each of its rounds, its ledger (every message and its fate), what its journal
  says of the models, and its wall time.

Each is one frame (:mod:`fedmap.mission.network.wire`), so a damaged or cut log is refused with one
line naming the file, and every size in it is checked before anything is decoded (a log
from another machine is input like any other).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zstandard

from fedmap._util import atomic_write_bytes, inflate_zstd
from fedmap.errors import FedmapError
from fedmap.maps.grid import MAX_WIRE_SIDE
from fedmap.mission.ends.protocol import DroppedUpdate
from fedmap.mission.network.link import Message
from fedmap.mission.network.wire import CorruptMessage, pack_frame, unpack_frame

Cell = tuple[int, int]
#: The most bytes one log entry's maps may decode to (sides at most :data:`MAX_WIRE_SIDE`; a
#: reader that knows its mission's map checks the shape too).
MAX_ENTRY_MAPS = 256 << 20


@dataclass
class StepState:
    """What an observer reads of one rover at one step (the simulator's record)."""

    step: int
    belief: np.ndarray
    view: np.ndarray
    observed: np.ndarray
    pos: Cell
    target: Cell | None
    distance: float
    trail_len: int


def _cell(c: list | None) -> Cell | None:
    return None if c is None else (int(c[0]), int(c[1]))


def pack_stack(stack: np.ndarray) -> bytes:
    """Maps of ``uint8`` cells, ``(n, layers, h, w)``: each of the ``n`` XOR the one before, zstd."""
    if not len(stack):
        return b""
    h, w = stack.shape[-2:]
    delta = stack.astype(np.uint8, copy=True)
    delta[1:] ^= stack[:-1]
    return struct.pack("<II", h, w) + zstandard.ZstdCompressor(level=3).compress(delta.tobytes())


def unpack_stack(raw: bytes, n: int, layers: int, shape: tuple[int, int] | None = None) -> np.ndarray:
    """The maps of :func:`pack_stack`: ``n`` of ``layers`` maps of ``shape`` (when the reader
    knows its mission's; else any side up to :data:`MAX_WIRE_SIDE`), at most
    :data:`MAX_ENTRY_MAPS` bytes, checked before anything is decoded and while it is."""
    if n == 0:
        return np.zeros((0, layers, *(shape or (0, 0))), dtype=np.uint8)
    try:
        h, w = struct.unpack_from("<II", raw)
    except struct.error as e:
        raise CorruptMessage(f"corrupted log: its maps do not decode ({e})") from None
    if shape is not None and (h, w) != tuple(shape):
        raise CorruptMessage(f"corrupted log: its maps are {h}x{w}, the mission's are {shape[0]}x{shape[1]}")
    size = n * layers * h * w
    if not (0 < h <= MAX_WIRE_SIDE and 0 < w <= MAX_WIRE_SIDE) or size > MAX_ENTRY_MAPS:
        raise CorruptMessage(f"refused log: it announces {n} steps of {h}x{w} maps ({size} bytes), more than an "
                             f"entry may hold ({MAX_ENTRY_MAPS} bytes, sides up to {MAX_WIRE_SIDE})")
    try:
        delta = np.frombuffer(inflate_zstd(raw[8:], size), dtype=np.uint8).reshape(n, layers, h, w)
    except ValueError as e:
        raise CorruptMessage(f"corrupted log: its maps do not decode ({e})") from None
    return np.bitwise_xor.accumulate(delta, axis=0)


@dataclass
class RoverEntry:
    """What a rover node writes to its own log when it answers the order to ``step``:
    every step it recorded since its last entry, and the cells it entered since."""

    strategy: str
    rover: int
    mission: str  #: the mission's id ("" in process)
    step: int
    states: list[StepState]
    trail: list[Cell]

    @property
    def name(self) -> str:
        """Its file's name in a log folder: by the first step it records (the entries of one
        rover's run record every step once, in turn; the orders' steps need not be distinct:
        a sync at the last step, then the order that finishes)."""
        return entry_name(self.mission, self.strategy, self.rover, self.states[0].step if self.states else self.step)

    def to_bytes(self) -> bytes:
        head = {"kind": "rover-log", "strategy": self.strategy, "rover": self.rover, "mission": self.mission,
                "step": self.step, "trail": [list(c) for c in self.trail],
                "states": [[s.step, list(s.pos), None if s.target is None else list(s.target), s.distance,
                            s.trail_len] for s in self.states]}
        maps = np.stack([np.stack([s.belief, s.view, s.observed.astype(np.uint8)]) for s in self.states]) \
            if self.states else np.zeros((0, 3, 0, 0), dtype=np.uint8)
        return pack_frame(head, [pack_stack(maps)])

    @classmethod
    def from_bytes(cls, raw: bytes, *, shape: tuple[int, int] | None = None) -> RoverEntry:
        """The entry in ``raw``; :class:`CorruptMessage` for anything that is not one, or whose
        maps are not of ``shape`` (the mission's, where the reader knows it)."""
        h, blobs = unpack_frame(raw)
        if h.get("kind") != "rover-log" or len(blobs) != 1:
            raise CorruptMessage(f"expected a rover's log entry, got a {h.get('kind')!r} record")
        try:
            maps = unpack_stack(blobs[0], len(h["states"]), 3, shape)
            states = [StepState(int(s[0]), m[0], m[1], m[2].astype(bool), _cell(s[1]), _cell(s[2]),  # type: ignore[arg-type]
                                float(s[3]), int(s[4])) for s, m in zip(h["states"], maps)]
            return cls(str(h["strategy"]), int(h["rover"]), str(h["mission"]), int(h["step"]), states,
                       [(int(c[0]), int(c[1])) for c in h["trail"]])
        except (KeyError, TypeError, IndexError, ValueError) as e:  # a header of the wrong layout
            raise CorruptMessage(f"corrupted log: its header is not a rover entry's ({type(e).__name__}: {e})") from None


def entry_name(mission: str, strategy: str, rover: int, step: int) -> str:
    return f"{mission or 'mission'}-{strategy}-rover{rover}-{step:06d}.log"


def base_name(mission: str, strategy: str) -> str:
    return f"{mission or 'mission'}-{strategy}.base.log"


@dataclass
class BaseRecord:
    """What the base station of one strategy's run writes to its own log."""

    strategy: str
    mission: str  #: the mission's id ("" in process)
    seconds: float  #: the strategy's wall time
    #: the global map it held after each of its rounds (and before the first: step 0), by step
    held: dict[int, np.ndarray]
    ledger: list[Message]
    slots: int  #: the link's message slots (the ledger's denominator)
    final_heights: np.ndarray | None = None  #: its global heights at the end (elevation strategies)
    dropped: list[DroppedUpdate] | None = None  #: its journal's dropped model updates
    lags: list[dict] | None = None  #: its journal's model lags
    registrations: list[dict] | None = None
    #: the frames its transport carried: ``orders``, ``reports`` (bytes) and ``messages`` (pairs)
    wire: dict | None = None
    #: a peer mission's rovers that left the team, and the step it was noticed at (their last record stands)
    left: dict[int, int] | None = None

    @property
    def name(self) -> str:
        """Its file's name in a log folder."""
        return base_name(self.mission, self.strategy)

    def held_at(self, t: int) -> np.ndarray:
        """The global map the base held at step ``t`` (after that step's deliveries)."""
        return self.held[max(s for s in self.held if s <= t)]

    def to_bytes(self) -> bytes:
        steps = sorted(self.held)
        head = {"kind": "base-log", "strategy": self.strategy, "mission": self.mission, "seconds": self.seconds,
                "held": steps, "ledger": [m.to_dict() for m in self.ledger], "slots": self.slots,
                "heights": self.final_heights is not None,
                "dropped": None if self.dropped is None else [d.to_dict() for d in self.dropped],
                "lags": self.lags, "registrations": self.registrations,
                "wire": self.wire, "left": None if self.left is None else {str(a): t for a, t in self.left.items()}}
        maps = np.stack([self.held[s][None] for s in steps]) if steps else np.zeros((0, 1, 0, 0), dtype=np.uint8)
        z = b"" if self.final_heights is None else zstandard.ZstdCompressor(level=3).compress(
            np.ascontiguousarray(self.final_heights, dtype="<f4").tobytes())
        return pack_frame(head, [pack_stack(maps), z])

    @classmethod
    def from_bytes(cls, raw: bytes, *, shape: tuple[int, int] | None = None) -> BaseRecord:
        h, blobs = unpack_frame(raw)
        if h.get("kind") != "base-log" or len(blobs) != 2:
            raise CorruptMessage(f"expected a base station's log, got a {h.get('kind')!r} record")
        try:
            steps = [int(s) for s in h["held"]]
            maps = unpack_stack(blobs[0], len(steps), 1, shape)
            held = {s: m[0] for s, m in zip(steps, maps)}
            heights = None
            if h["heights"]:
                sides = maps.shape[-2:] if len(maps) else shape
                if sides is None:
                    raise CorruptMessage("corrupted log: heights without a map")
                size = 4 * sides[0] * sides[1]
                heights = np.frombuffer(inflate_zstd(blobs[1], size), dtype="<f4").reshape(sides).astype(np.float32)
            return cls(str(h["strategy"]), str(h["mission"]), float(h["seconds"]), held,
                       [Message(**m) for m in h["ledger"]], int(h["slots"]), heights,
                       None if h["dropped"] is None else [DroppedUpdate(**d) for d in h["dropped"]],
                       h["lags"], h["registrations"], h.get("wire"),
                       None if h.get("left") is None else {int(a): int(t) for a, t in h["left"].items()})
        except (KeyError, TypeError, IndexError, ValueError) as e:
            raise CorruptMessage(f"corrupted log: its header is not a base station's ({type(e).__name__}: {e})") \
                from None


def peer_name(mission: str, strategy: str, agent: int) -> str:
    return f"{mission or 'mission'}-{strategy}-agent{agent}.peer.log"


@dataclass
class PeerRecord:
    """What one agent of a peer mission writes to its own log once its run is over: its side
    of the link (the ledger entries of what it sent, each with its place in the round's order:
    ``(step, offer, hop)``), its slots and wire bytes, and, for the lander, the map it held
    after each sync (by step). Merged with the others' by
    :func:`~fedmap.mission.network.peers.merge_records`."""

    strategy: str
    mission: str
    agent: int  #: a rover, or the lander (-1)
    seconds: float
    ledger: list[Message]
    order: list[tuple[int, int, int]]
    slots: int
    wire: dict
    held: dict[int, np.ndarray]
    #: per sync, the wall seconds since the last one ended (its driving, its round and the
    #: wait for the slowest agent: a lockstep round's cadence)
    rounds: list[float] = field(default_factory=list)
    #: the agents that left the team, and the sync step it noticed it at
    left: dict[int, int] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return peer_name(self.mission, self.strategy, self.agent)

    def to_bytes(self) -> bytes:
        steps = sorted(self.held)
        head = {"kind": "peer-log", "strategy": self.strategy, "mission": self.mission, "agent": self.agent,
                "seconds": self.seconds, "ledger": [m.to_dict() for m in self.ledger],
                "order": [list(o) for o in self.order], "slots": self.slots, "wire": self.wire, "held": steps,
                "rounds": self.rounds, "left": {str(a): t for a, t in self.left.items()}}
        maps = np.stack([self.held[s][None] for s in steps]) if steps else np.zeros((0, 1, 0, 0), dtype=np.uint8)
        return pack_frame(head, [pack_stack(maps)])

    @classmethod
    def from_bytes(cls, raw: bytes, *, shape: tuple[int, int] | None = None) -> PeerRecord:
        h, blobs = unpack_frame(raw)
        if h.get("kind") != "peer-log" or len(blobs) != 1:
            raise CorruptMessage(f"expected an agent's peer log, got a {h.get('kind')!r} record")
        try:
            steps = [int(s) for s in h["held"]]
            maps = unpack_stack(blobs[0], len(steps), 1, shape)
            ledger = [Message(**m) for m in h["ledger"]]
            order = [(int(o[0]), int(o[1]), int(o[2])) for o in h["order"]]
            if len(order) != len(ledger):
                raise ValueError(f"{len(order)} places for {len(ledger)} ledger entries")
            return cls(str(h["strategy"]), str(h["mission"]), int(h["agent"]), float(h["seconds"]), ledger, order,
                       int(h["slots"]), dict(h["wire"]), {s: m[0] for s, m in zip(steps, maps)},
                       [float(x) for x in h.get("rounds", [])], {int(a): int(t) for a, t in h.get("left", {}).items()})
        except (KeyError, TypeError, IndexError, ValueError) as e:
            raise CorruptMessage(f"corrupted log: its header is not a peer log's ({type(e).__name__}: {e})") from None


def read_peer_records(folder: Path, mission: str, strategy: str, *,
                      shape: tuple[int, int] | None = None) -> list[PeerRecord]:
    """Every agent's :class:`PeerRecord` of ``strategy`` in mission ``mission`` under ``folder`` (one per agent)."""
    found: dict[str, Path] = {}
    for p in sorted(Path(folder).rglob(peer_name(mission, strategy, 0).replace("agent0", "agent*"))):
        found.setdefault(p.name, p)
    return [_read(p, PeerRecord, shape) for _, p in sorted(found.items())]


def write_log(folder: Path, record: RoverEntry | BaseRecord | PeerRecord) -> Path:
    """``record`` into ``folder`` (made if need be), atomically: written again, it replaces itself."""
    path = Path(folder) / record.name
    atomic_write_bytes(path, record.to_bytes())
    return path


def _read(path: Path, kind, shape: tuple[int, int] | None):
    try:
        return kind.from_bytes(path.read_bytes(), shape=shape)
    except CorruptMessage as e:
        raise FedmapError(f"{path}: {e}") from None


def read_rover_log(folder: Path, mission: str, strategy: str, rover: int, *,
                   shape: tuple[int, int] | None = None) -> list[RoverEntry]:
    """Rover ``rover``'s entries of ``strategy`` in mission ``mission``, found anywhere under
    ``folder``, in the order of their steps (one per step: a copy of the same entry, e.g.
    from a rover rebuilt from its orders, is the same entry)."""
    found: dict[int, Path] = {}
    pattern = entry_name(mission, strategy, rover, 0).rsplit("-", 1)[0] + "-*.log"
    for p in sorted(Path(folder).rglob(pattern)):
        step = p.stem.rsplit("-", 1)[1]
        if step.isdigit():
            found.setdefault(int(step), p)
    return [_read(found[s], RoverEntry, shape) for s in sorted(found)]


def read_base_record(folder: Path, mission: str, strategy: str, *,
                     shape: tuple[int, int] | None = None) -> BaseRecord | None:
    """The base station's record of ``strategy`` in mission ``mission``, found anywhere under
    ``folder`` (None: there is none; another mission's records there are not read)."""
    found = sorted(Path(folder).rglob(base_name(mission, strategy)))
    return _read(found[0], BaseRecord, shape) if found else None


__all__ = ["MAX_ENTRY_MAPS", "BaseRecord", "PeerRecord", "RoverEntry", "StepState", "base_name", "entry_name", "pack_stack",
           "peer_name", "read_base_record", "read_peer_records", "read_rover_log", "unpack_stack", "write_log"]
