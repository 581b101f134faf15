"""A mission whose rovers run elsewhere: each rover's world and end on a machine of its
own, the base station's end and the radio on another, and only messages between them.

The mission clock belongs to the base station. At every sync it sends each rover an
**order** (:class:`Order`): the events the radio delivered to it since the last order
(acknowledgements of its uplinks, downlinks), in the order they happened, and the step to
drive to. The rover (:class:`RoverNode`) applies the events, drives, senses and plans up to
that step, runs its end's sync (``at_sync``, then ``uplink`` when it is in range) and
answers with a **report** (:class:`Report`): its uplink (the strategy's own message, the
bytes the ledger counts), whether it could use each downlink it was handed, and what an
observer reads of it at every step since the last report (belief, view, cells observed,
position, target, distance: what the simulator's record reads; not counted, a real
rover's software need not send it). The base (:class:`BaseNode`) runs the same
:class:`~fedmap.mission.topology.Exchange` and :class:`~fedmap.mission.link.Link` as the
simulator over the rovers' reports, so with the same seed and config it records the same
mission as :func:`~fedmap.mission.sim.run_mission`. After the last sync a final order
(``finish``) delivers what is left and drives the rovers to the last step.

Orders and reports are bytes (:func:`pack_frame`): a version byte, a CRC-32 check of the
rest, a JSON header and length-prefixed blobs. A frame that fails its check is refused with
one line (:class:`CorruptMessage`); the transport sends it again.

A rover that lost its state (its process started again without its state folder) refuses
the order with :class:`LostState`. The base keeps every order it sent each rover, and sends
them all again with the order (:func:`pack_history`): the rover answers each again, as it
did the first time (its world is seeded and its end is a function of what it was told,
so it ends where it was, coder state and all, bit for bit; :meth:`RoverNode.rebuild`),
then answers the order. That replay is the rover's keyframe: it is sent whenever the base
cannot know what the rover holds, and its bytes are a line of the run's faults.

Limits: the star topology with ``latency = 0`` (on real processes the link's own delay is
the latency), and strategies whose rover ends hold only their own rover (their spec's ``deployable``).
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zstandard

from fedmap._util import inflate_zstd
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, MAX_WIRE_SIDE, UNKNOWN
from fedmap.maps.planning import astar
from fedmap.mission.feed import FeedWorld, MapFeed
from fedmap.mission.frontiers import choose_target, travel_costs
from fedmap.mission.protocol import DroppedUpdate, Outgoing
from fedmap.mission.registry import Setup, Sharing, build, names_that
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import Mission, StrategyRun, TeamState
from fedmap.mission.topology import make_topology

Cell = tuple[int, int]
#: The wire format's version (the first byte of every frame).
WIRE_VERSION = 1
_HEAD = struct.Struct("<BII")  # version, crc32 of what follows, header length
_BLOB = struct.Struct("<I")


#: The most bytes a report's maps may decode to (their sides: at most :data:`MAX_WIRE_SIDE`; a
#: receiver that knows its mission's map checks the shape too).
MAX_REPORT_MAPS = 256 << 20


class CorruptMessage(FedmapError):
    """A frame whose check failed or whose layout is wrong."""


class LostState(FedmapError):
    """A rover asked to carry on from a step it holds no state for: it needs its orders again."""


def pack_frame(header: dict, blobs: list[bytes] = ()) -> bytes:  # type: ignore[assignment]
    """``header`` (JSON) and ``blobs`` as one checked frame."""
    head = json.dumps(header, separators=(",", ":")).encode()
    body = head + b"".join(_BLOB.pack(len(b)) + bytes(b) for b in blobs)
    return _HEAD.pack(WIRE_VERSION, zlib.crc32(body), len(head)) + body


def unpack_frame(raw: bytes) -> tuple[dict, list[bytes]]:
    """The header and blobs of a frame; :class:`CorruptMessage` when its check or layout fails."""
    if len(raw) < _HEAD.size:
        raise CorruptMessage(f"corrupted message: {len(raw)} bytes, shorter than a header")
    version, crc, n = _HEAD.unpack_from(raw)
    if version != WIRE_VERSION:
        raise CorruptMessage(f"message of wire version {version}, this end speaks {WIRE_VERSION}: update fedmap on "
                             "both ends")
    body = raw[_HEAD.size:]
    if zlib.crc32(body) != crc:
        raise CorruptMessage("corrupted message: its check failed")
    try:
        header = json.loads(body[:n])
        blobs, off = [], n
        while off < len(body):
            (size,) = _BLOB.unpack_from(body, off)
            blobs.append(body[off + _BLOB.size: off + _BLOB.size + size])
            off += _BLOB.size + size
    except (ValueError, struct.error) as e:
        raise CorruptMessage(f"corrupted message: {e}") from None
    if off != len(body):
        raise CorruptMessage("corrupted message: its last blob is cut short")
    return header, blobs


# -- what crosses ---------------------------------------------------------------------------


@dataclass
class Order:
    """The base's message to one rover at a sync: the events delivered to it since the last
    order, then drive to ``step`` (``finish``: the last step, no sync there)."""

    strategy: str
    rover: int
    round_no: int  #: the sync round at ``step`` (0 with ``finish``)
    step: int
    finish: bool = False
    #: ``("ack", round, ok)`` for its uplink of ``round``, ``("down", round, payload)`` for a downlink
    events: list[tuple] = field(default_factory=list)
    mission: str = ""  #: the mission's id (a rover keeps one state per mission and strategy)
    since: int = 0  #: the step the base holds the rover at (the step of its last order)

    def to_bytes(self) -> bytes:
        heads: list[list] = []
        blobs: list[bytes] = []
        for ev in self.events:
            if ev[0] == "down":
                heads.append(["down", ev[1], len(blobs)])
                blobs.append(ev[2])
            else:
                heads.append(list(ev))
        return pack_frame({"kind": "order", "strategy": self.strategy, "rover": self.rover, "round": self.round_no,
                           "step": self.step, "finish": self.finish, "events": heads, "mission": self.mission,
                           "since": self.since}, blobs)

    @classmethod
    def from_bytes(cls, raw: bytes) -> Order:
        h, blobs = unpack_frame(raw)
        if h.get("kind") != "order":
            raise CorruptMessage(f"expected an order, got a {h.get('kind')!r} message")
        try:
            events = [("down", e[1], blobs[e[2]]) if e[0] == "down" else ("ack", e[1], bool(e[2]))
                      for e in h["events"]]
            return cls(h["strategy"], h["rover"], h["round"], h["step"], h["finish"], events, h.get("mission", ""),
                       h.get("since", 0))
        except (KeyError, TypeError, IndexError, ValueError) as e:  # a header of the wrong layout
            raise CorruptMessage(f"corrupted message: its header is not an order's ({type(e).__name__}: {e})") from None


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


@dataclass
class Report:
    """A rover's answer to an order."""

    strategy: str
    rover: int
    step: int  #: the step it drove to
    pos: Cell  #: where it is at ``step``
    target: Cell | None
    reached: bool  #: it was in range of the base at the sync (it made an uplink, or tried)
    uplink: Outgoing | None  #: its uplink (None: none, e.g. its update was rejected)
    answers: list[bool]  #: whether it could use each downlink of the order, in order
    version: str | None  #: the model version it holds before the sync (model strategies)
    journal: dict  #: its journal's new entries (dropped updates, losses, cells trained on)
    states: list[StepState]  #: the observer's view of every step since its last report
    trail: list[Cell]  #: the cells it entered since its last report

    def to_bytes(self) -> bytes:
        up = self.uplink
        head = {"kind": "report", "strategy": self.strategy, "rover": self.rover, "step": self.step,
                "pos": list(self.pos), "target": None if self.target is None else list(self.target),
                "reached": self.reached, "uplink": None if up is None else (up.kind, up.payload is not None),
                "answers": self.answers, "version": self.version, "journal": self.journal,
                "trail": [list(c) for c in self.trail],
                "states": [[s.step, list(s.pos), None if s.target is None else list(s.target), s.distance,
                            s.trail_len] for s in self.states]}
        payload = up.payload if up is not None and up.payload is not None else b""
        return pack_frame(head, [payload, _pack_maps(self.states)])

    @classmethod
    def from_bytes(cls, raw: bytes, *, shape: tuple[int, int] | None = None) -> Report:
        """The report in ``raw``; :class:`CorruptMessage` for anything that is not one, or
        whose maps are not of ``shape`` (the mission's, where the receiver knows it)."""
        h, blobs = unpack_frame(raw)
        if h.get("kind") != "report" or len(blobs) != 2:
            raise CorruptMessage(f"expected a report, got a {h.get('kind')!r} message")
        try:
            up = None if h["uplink"] is None else Outgoing(blobs[0] if h["uplink"][1] else None, h["uplink"][0])
            maps = _unpack_maps(blobs[1], len(h["states"]), shape)
            states = [StepState(s[0], b, v, o, _cell(s[1]), _cell(s[2]), s[3], s[4])  # type: ignore[arg-type]
                      for s, (b, v, o) in zip(h["states"], maps)]
            return cls(h["strategy"], h["rover"], h["step"], _cell(h["pos"]), _cell(h["target"]),  # type: ignore[arg-type]
                       h["reached"], up, [bool(a) for a in h["answers"]], h["version"], h["journal"], states,
                       [(int(c[0]), int(c[1])) for c in h["trail"]])
        except (KeyError, TypeError, IndexError, ValueError) as e:  # a header of the wrong layout
            raise CorruptMessage(f"corrupted message: its header is not a report's ({type(e).__name__}: {e})") from None


def _cell(c: list | None) -> Cell | None:
    return None if c is None else (int(c[0]), int(c[1]))


def _pack_maps(states: list[StepState]) -> bytes:
    """Every step's belief, view and observed cells: each step XOR the one before, zstd."""
    if not states:
        return b""
    h, w = states[0].belief.shape
    stack = np.stack([np.stack([s.belief, s.view, s.observed.astype(np.uint8)]) for s in states])
    delta = stack.copy()
    delta[1:] ^= stack[:-1]
    return struct.pack("<II", h, w) + zstandard.ZstdCompressor(level=3).compress(delta.tobytes())


def _unpack_maps(raw: bytes, n: int, shape: tuple[int, int] | None = None) -> list[tuple[np.ndarray, np.ndarray,
                                                                                           np.ndarray]]:
    """The maps of :func:`_pack_maps`: ``n`` steps of ``shape`` (when the receiver knows its
    mission's; else any side up to :data:`MAX_WIRE_SIDE`), at most :data:`MAX_REPORT_MAPS` bytes,
    checked before anything is decoded and while it is."""
    if n == 0:
        return []
    try:
        h, w = struct.unpack_from("<II", raw)
    except struct.error as e:
        raise CorruptMessage(f"corrupted message: its maps do not decode ({e})") from None
    if shape is not None and (h, w) != tuple(shape):
        raise CorruptMessage(f"corrupted message: its maps are {h}x{w}, the mission's are {shape[0]}x{shape[1]}")
    size = n * 3 * h * w
    if not (0 < h <= MAX_WIRE_SIDE and 0 < w <= MAX_WIRE_SIDE) or size > MAX_REPORT_MAPS:
        raise CorruptMessage(f"refused message: it announces {n} steps of {h}x{w} maps ({size} bytes), more than "
                             f"a report may carry ({MAX_REPORT_MAPS} bytes, sides up to {MAX_WIRE_SIDE})")
    try:
        delta = np.frombuffer(inflate_zstd(raw[8:], size), dtype=np.uint8).reshape(n, 3, h, w)
    except ValueError as e:
        raise CorruptMessage(f"corrupted message: its maps do not decode ({e})") from None
    stack = np.bitwise_xor.accumulate(delta, axis=0)
    return [(s[0], s[1], s[2].astype(bool)) for s in stack]


def pack_history(orders: list[bytes]) -> bytes:
    """Every order a rover was sent, in order, as one frame (a rover that lost its state is rebuilt from it)."""
    return pack_frame({"kind": "history", "orders": len(orders)}, orders)


def unpack_history(raw: bytes) -> list[bytes]:
    h, blobs = unpack_frame(raw)
    if h.get("kind") != "history" or h.get("orders") != len(blobs):
        raise CorruptMessage(f"expected a rover's order history, got a {h.get('kind')!r} message")
    return blobs


# -- the rover's side -----------------------------------------------------------------------


def check_deployable(c: MissionConfig, strategies: list[str] | tuple[str, ...]) -> None:
    """One line when the mission ``c`` or a strategy cannot run on processes (see the module's limits)."""
    if c.link.topology != "star":
        raise FedmapError(f"a mission on processes runs the star topology only, not {c.link.topology!r}: Flower routes "
                          "every message through the base's SuperLink, so rovers have no links of their own "
                          "(mesh, leader, gossip and admm run in process)")
    if c.frames.enabled:
        raise FedmapError("a mission on processes runs with known poses: [frames] (unknown poses, drift) runs "
                          "in process only")
    if c.link.latency != 0:
        raise FedmapError(f"a mission on processes needs [link] latency = 0 (got {c.link.latency}): the real "
                          "link's delay is its latency")
    deployable = names_that("deployable")
    bad = [s for s in strategies if s not in deployable]
    if bad:
        raise FedmapError(f"strategy {', '.join(bad)} cannot run on processes (its ends are not one per machine); "
                          f"these can: {', '.join(deployable)}")


class RoverNode:
    """One rover of strategy ``name``: its world (the mission's terrain, seeded as the
    simulator's; or with ``feed`` the maps its own software writes), its end, and its
    clock. :meth:`handle` takes an order, returns the report."""

    def __init__(self, mission: Mission, name: str, k: int, *, feed: MapFeed | None = None) -> None:
        check_deployable(mission.config, [name])
        self.name, self.k, self.config = name, k, mission.config
        self.topology = make_topology(mission.config.link, mission.base)
        world = mission.world(self.topology)
        if not 0 <= k < len(world.team):
            raise FedmapError(f"rover {k} is not in the team of {len(world.team)}")
        if feed is not None:  # its observations come from its own mapping software (fedmap.mission.feed)
            world = FeedWorld(world, k, feed)
        self.world = world
        sharing = build(name, Setup(mission.config, mission.truth, world.team, self.topology))
        world.ends = sharing.rovers  # only its own end is ever asked
        self.end, self.journal = sharing.rovers[k], sharing.journal
        self.rover = world.team[k]
        self.step = 0
        self._told = 0  # trail cells already reported
        self._last: tuple[bytes, bytes] | None = None  # the last order it answered, and its report
        self._seen = {"dropped": 0, "losses": 0, "trained_cells": 0}
        world.sense(k, 0)
        self._states = [self._state(0)]  # recorded, not yet reported (the record of a step follows its deliveries)

    def _state(self, t: int) -> StepState:
        r, belief = self.rover, self.end.belief()
        return StepState(t, belief, self.world.own_view(self.k, belief), r.local != UNKNOWN, r.pos, r.target,
                         r.distance, len(r.trail))

    def _journal(self) -> dict:
        out: dict[str, list] = {}
        for key, seen in self._seen.items():
            entries = getattr(self.journal, key)
            if entries is None:
                continue
            new = entries[seen:]
            self._seen[key] = len(entries)
            out[key] = [e.to_dict() if isinstance(e, DroppedUpdate) else e for e in new]
        return out

    @classmethod
    def rebuild(cls, mission: Mission, name: str, k: int, history: list[bytes], *,
                feed: MapFeed | None = None) -> RoverNode:
        """Rover ``k`` as it was after answering ``history`` (every order the base sent it, in
        order): a new node answers each of them again. Its world is seeded and its end is a
        function of what it was told, so it is the node that lost its state, bit for bit."""
        node = cls(mission, name, k, feed=feed)
        for raw in history:
            node.answer(raw)
        return node

    def answer(self, raw: bytes) -> bytes:
        """The report (bytes) to an order (bytes). The same order again (its report was lost
        or damaged on the way) gets the same report again; a damaged order raises
        :class:`CorruptMessage` (the base sends it again)."""
        if self._last is not None and raw == self._last[0]:
            return self._last[1]
        report = self.handle(Order.from_bytes(raw)).to_bytes()
        self._last = (raw, report)
        return report

    def handle(self, order: Order) -> Report:
        """Apply the order's events, drive to its step, sync, and report."""
        if order.strategy != self.name or order.rover != self.k:
            raise FedmapError(f"an order for {order.strategy} rover {order.rover} reached {self.name} rover {self.k}")
        if order.step < self.step or (order.step == self.step and not order.finish):
            raise FedmapError(f"rover {self.k} is at step {self.step}: an order to drive to step {order.step} is stale")
        if order.since > self.step:
            raise LostState(f"rover {self.k} is at step {self.step}, the base holds it at step {order.since}: it lost "
                            "its state")
        if order.since != self.step:
            raise FedmapError(f"rover {self.k} is at step {self.step}, ahead of the base's step {order.since}: the "
                              "base station's journal is older than this rover's state")
        answers = []
        for ev in order.events:
            if ev[0] == "ack":
                self.end.delivered(ev[1], ev[2])
            else:
                ok = bool(self.end.receive(ev[2]))
                answers.append(ok)
                if ok:
                    self.rover.replan = True
        states = self._states
        if not states or states[-1].step != self.step:
            states.append(self._state(self.step))  # the last step's record, now that its deliveries are in
        for t in range(self.step + 1, order.step + 1):
            self.world.drive(self.k, t)
            self.step = t
            if t < order.step or order.finish:
                states.append(self._state(t))
        version, reached, uplink = getattr(self.end, "version", None), False, None
        if not order.finish:
            self.end.at_sync(order.round_no)
            reached = self.topology.reachable(self.world.positions())[self.k]
            if reached:
                uplink = self.end.uplink(order.round_no)
        r = self.rover
        trail = list(r.trail[self._told:])
        self._told = len(r.trail)
        self._states = []
        return Report(self.name, self.k, self.step, r.pos, r.target, reached, uplink, answers, version,
                      self._journal(), states, trail)


# -- the base's side ------------------------------------------------------------------------


class RemoteRover:
    """The base's stand-in for a rover end elsewhere: what its last report said, and the
    events the radio delivered to it, kept for its next order."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.report: Report | None = None
        self.state: StepState | None = None  #: the step being recorded
        self.events: list[tuple] = []
        self.journal: Any = None  # the run's journal (set by the base)

    @property
    def version(self) -> str | None:
        return None if self.report is None else self.report.version

    def belief(self) -> np.ndarray:
        assert self.state is not None
        return self.state.belief

    def at_sync(self, round_no: int) -> None:
        """Run on the rover, before its uplink."""

    def prepare(self, round_no: int) -> None:
        """Its training ran on the rover, before its report."""
        return None

    def uplink(self, round_no: int) -> Outgoing | None:
        assert self.report is not None
        for key, entries in self.report.journal.items():  # what its end journaled making the uplink
            held = getattr(self.journal, key)
            if held is not None:
                held.extend(DroppedUpdate(**e) if key == "dropped" else e for e in entries)
        return self.report.uplink

    def delivered(self, round_no: int, ok: bool) -> None:
        self.events.append(("ack", round_no, ok))

    def receive(self, payload: bytes) -> None:
        self.events.append(("down", 0, payload))
        return None  # its answer comes with its next report


class BaseNode:
    """The base station of strategy ``name``: its end, the radio (the simulator's link and
    exchange) and the record. :meth:`first_orders` starts the mission; :meth:`take` takes
    every rover's report and gives the next orders (none: the mission is over, :meth:`result`)."""

    def __init__(self, mission: Mission, name: str, *, on_step: Callable[[str, int, float], None] | None = None,
                 on_snapshot: Callable | None = None, mission_id: str = "") -> None:
        check_deployable(mission.config, [name])
        self.name, self.config, self.mission_id = name, mission.config, mission_id
        self.shape: tuple[int, int] = tuple(mission.truth.shape)  # type: ignore[assignment]  # the reports' maps
        self.stand_ins: list[RemoteRover] = []
        self.trails: list[list[Cell]] = []  # every member's cells driven, as reported (its start first)
        self.run = mission.new_run(name, ends=self._ends, on_snapshot=on_snapshot)
        self.syncs = {t: i + 1 for i, t in enumerate(self.config.sync_steps)}
        self.sync_at = sorted(self.syncs)
        self.on_step = on_step
        self.recorded = -1  # the last step recorded
        self.done = False

    def _ends(self, name: str, setup: Setup) -> Sharing:
        sharing = build(name, setup)
        self.stand_ins = [RemoteRover(k) for k in range(len(setup.team))]
        self.trails = [[] for _ in setup.team]
        for s in self.stand_ins:
            s.journal = sharing.journal
        sharing.rovers = self.stand_ins
        return sharing

    @property
    def n(self) -> int:
        return len(self.stand_ins)

    def _orders(self, after: int) -> dict[int, Order]:
        """Every rover's next order after step ``after``: to the next sync, or to the end."""
        nxt = [t for t in self.sync_at if t > after]
        step, finish = (nxt[0], False) if nxt else (self.config.steps, True)
        orders = {}
        for s in self.stand_ins:
            orders[s.k] = Order(self.name, s.k, 0 if finish else self.syncs[step], step, finish, s.events,
                                self.mission_id, after)
            s.events = []
        return orders

    def first_orders(self) -> dict[int, Order]:
        return self._orders(0)

    def take(self, reports: dict[int, Report], orders: dict[int, Order]) -> dict[int, Order]:
        """Every rover's report to ``orders``; the next orders (empty: the mission is over)."""
        if sorted(reports) != list(range(self.n)):
            raise FedmapError(f"reports from rovers {sorted(reports)}, expected 0..{self.n - 1}")
        for k, rep in reports.items():
            o = orders[k]
            if (rep.strategy, rep.rover, rep.step) != (self.name, k, o.step):
                raise FedmapError(f"rover {k}'s report is for {rep.strategy} step {rep.step}, its order was "
                                  f"{self.name} step {o.step}")
            self.run.exchange.answers(k, rep.answers)
            self.trails[k].extend(rep.trail)
        self._record(reports)
        step = next(iter(orders.values())).step
        if next(iter(orders.values())).finish:
            self.done = True
            return {}
        run = self.run
        for s in self.stand_ins:
            rep = reports[s.k]
            s.report = rep
            r = run.team[s.k]
            r.pos, r.target = rep.pos, rep.target
        run.exchange.sync(step, self.syncs[step])
        run.exchange.deliver(step)
        return self._orders(step)

    def _record(self, reports: dict[int, Report]) -> None:
        by_step: dict[int, list[StepState]] = {}
        for k in range(self.n):
            for st in reports[k].states:
                by_step.setdefault(st.step, []).append(st)
        run, c = self.run, self.config
        for t in sorted(by_step):
            states = by_step[t]
            if t != self.recorded + 1 or len(states) != self.n:
                raise FedmapError(f"step {t} reported by {len(states)} of {self.n} rovers after step {self.recorded}")
            for s, st in zip(self.stand_ins, states):
                s.state = st
                r = run.team[s.k]
                r.pos, r.target, r.distance = st.pos, st.target, st.distance
            team = TeamState(beliefs=[st.belief for st in states], views=[st.view for st in states],
                             observed=np.stack([st.observed for st in states]), positions=[st.pos for st in states],
                             targets=[st.target for st in states], distances=[st.distance for st in states],
                             trail_len=[st.trail_len for st in states])
            run.record(t, evaluate=t == 0 or t in self.syncs or t == c.steps, team=team)
            self.recorded = t
            if self.on_step is not None:
                self.on_step(self.name, t, run.rows[-1].coverage)

    def result(self, seconds: float) -> StrategyRun:
        if not self.done:
            raise FedmapError(f"{self.name}: the mission is not over (recorded to step {self.recorded})")
        return self.run.result(seconds, self.trails)


def warm_up() -> None:
    """Load the compiled planners (numba, cached on disk) into this process. A process that
    forks one process per message (Flower's ClientApps, :mod:`fedmap.flower.warm`) calls it
    once before forking, so no message pays the load (about 0.5 s each, measured)."""
    belief = np.full((8, 8), FREE, dtype=np.uint8)
    belief[0] = UNKNOWN
    choose_target(belief, (4, 4), radius=1.5, unknown_cost=1.5, others=[])
    travel_costs(belief, (4, 4), 1.5)  # the cheapest path's search (a rover with a predictor)
    astar(np.ones((4, 4), dtype=bool), (0, 0), (3, 3))


Transport = Callable[[dict[int, bytes]], dict[int, bytes]]


def rounds(base: BaseNode, send: Transport) -> Iterator[int]:
    """Run ``base``'s mission over ``send`` (every rover's order as bytes -> its report as
    bytes); yields each step an order drove to."""
    orders = base.first_orders()
    while orders:
        raw = send({k: o.to_bytes() for k, o in orders.items()})
        reports = {k: Report.from_bytes(r, shape=base.shape) for k, r in raw.items()}
        step = next(iter(orders.values())).step
        orders = base.take(reports, orders)
        yield step


def loopback(mission: Mission, name: str, *, feeds: dict[int, MapFeed] | None = None) -> Transport:
    """Every rover of strategy ``name`` in this process, reached only through bytes (tests,
    and the reference a mission on processes is checked against); ``feeds``: rovers whose
    observations come from a map feed."""
    nodes: dict[int, RoverNode] = {}

    def send(orders: dict[int, bytes]) -> dict[int, bytes]:
        out = {}
        for k, raw in orders.items():
            if k not in nodes:
                nodes[k] = RoverNode(mission, name, k, feed=(feeds or {}).get(k))
            out[k] = nodes[k].answer(raw)
        return out

    return send


__all__ = ["WIRE_VERSION", "BaseNode", "CorruptMessage", "LostState", "Order", "Report", "RoverNode",
           "StepState", "check_deployable", "loopback", "pack_frame", "pack_history", "rounds", "unpack_frame",
           "unpack_history", "warm_up"]
