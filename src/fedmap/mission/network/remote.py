"""A mission whose rovers run elsewhere: each rover's world and end on a machine of its
own, the base station's end and the radio on another, and only messages between them.

At every sync the base station sends each rover an **order** (:class:`Order`): the frames
the radio delivered to it since the last order (acknowledgements of its uplinks,
downlinks), in the order they happened, and the step to drive to. The rover
(:class:`ProcessRover`, around its :class:`~fedmap.mission.network.nodes.RoverNode`) hands
them to its node, drives, senses and plans up to that step, syncing at each of its sync
steps on the way (``at_sync``, then ``uplink`` when it is in range), and answers with a
**report** (:class:`Report`): its uplink (the strategy's own message, the bytes the ledger
counts), whether it could use each downlink it was handed, and where it is (its cell and
target: what the base's side of the link needs). In lockstep (the default) the base's clock
is the mission's; with a ``pace`` every node runs on its own clock (:class:`Order`). What
an observer reads of a rover at every step (belief, view, cells observed, distance) stays
on it: it goes to its own log (:class:`~fedmap.mission.network.nodelog.RoverEntry`,
:attr:`ProcessRover.log`). The base (:class:`ProcessBase`) runs its node, the same
:class:`~fedmap.mission.network.transport.Exchange` and
:class:`~fedmap.mission.network.link.Link` as the simulator over what the rovers reported
(:class:`FarRover`) and logs what it holds (:meth:`ProcessBase.record`); the mission is
scored from the logs afterwards (:func:`~fedmap.mission.scoring.score_strategy`), so with
the same seed and config it records the same mission as
:func:`~fedmap.mission.sim.run_mission`. After the last sync a final order (``finish``)
delivers what is left and drives the rovers to the last step.

Orders and reports are fedmap's binary message frames (:mod:`fedmap.mission.network.wire`):
a head, the kind's fields and a CRC-32. A frame that fails its check is refused with one
line (:class:`CorruptMessage`); the transport sends it again.

A rover that lost its state (its process started again without its state folder) refuses
the order with :class:`LostState`. The base keeps every order it sent each rover, and sends
them all again with the order (:func:`pack_history`): the rover answers each again, as it
did the first time (its world is seeded and its end is a function of what it was told,
so it ends where it was, coder state and all, bit for bit; :meth:`ProcessRover.rebuild`),
then answers the order. That replay is the rover's keyframe: it is sent whenever the base
cannot know what the rover holds, and its bytes are a line of the run's faults.

Limits: the star topology with ``latency = 0`` (on real processes the link's own delay is
the latency), and strategies whose rover ends hold only their own rover (their spec's ``deployable``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, UNKNOWN
from fedmap.maps.planning import astar
from fedmap.mission.ends.framed import registrations
from fedmap.mission.ends.protocol import DroppedUpdate, Outgoing
from fedmap.mission.ends.registry import Setup, build, names_that
from fedmap.mission.network.link import BASE, Link
from fedmap.mission.network.nodelog import BaseRecord, RoverEntry, StepState
from fedmap.mission.network.nodes import BaseNode, RoverNode
from fedmap.mission.network.topology import make_topology
from fedmap.mission.network.transport import Exchange
from fedmap.mission.network.wire import (
    HISTORY,
    ORDER,
    REPORT,
    WIRE_VERSION,
    CorruptMessage,
    Frame,
    Head,
    Writer,
    pack_frame,
    pack_message,
    unpack_frame,
    unpack_message,
)
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import Mission
from fedmap.mission.world.feed import Feed, FeedWorld
from fedmap.mission.world.frontiers import choose_target, travel_costs
from fedmap.mission.world.world import start_team

Cell = tuple[int, int]
_ACK, _DOWN = 0, 1  # an order's events
class LostState(FedmapError):
    """A rover asked to carry on from a step it holds no state for: it needs its orders again."""


# -- what crosses ---------------------------------------------------------------------------


@dataclass
class Order:
    """The base's message to one rover at a sync: the events delivered to it since the last
    order, then drive to ``step`` (``finish``: the last step, no sync there). With ``pace``
    (milliseconds a step, > 0) the rover runs on its own clock instead: it drives as far as
    its clock says, syncing at its own sync steps on the way (:class:`ProcessRover`)."""

    strategy: str
    rover: int
    round_no: int  #: the sync round at ``step`` (0 with ``finish``)
    step: int
    finish: bool = False
    #: ``("ack", round, ok)`` for its uplink of ``round``, ``("down", round, payload)`` for a downlink
    events: list[tuple] = field(default_factory=list)
    mission: str = ""  #: the mission's id (a rover keeps one state per mission and strategy)
    since: int = 0  #: the step the base holds the rover at (the step of its last report)
    pace: int = 0  #: milliseconds a step of the rover's own clock (0: lockstep, drive to ``step``)

    def to_bytes(self) -> bytes:
        w = Writer().put("hIBI", self.rover, self.since, self.finish, self.pace).text(self.mission)
        w.text(self.strategy)
        w.put("H", len(self.events))
        for ev in self.events:
            if ev[0] == "down":
                w.put("BI", _DOWN, ev[1]).blob(ev[2])
            else:
                w.put("BIB", _ACK, ev[1], bool(ev[2]))
        return pack_message(Head(ORDER, BASE, self.round_no, self.step), w.done())

    @classmethod
    def from_bytes(cls, raw: bytes) -> Order:
        head, r = unpack_message(raw, ORDER)
        rover, since, finish, pace = r.get("hIBI")
        mission, strategy = r.text(), r.text()
        events: list[tuple] = []
        for _ in range(r.one("H")):
            kind, round_no = r.get("BI")
            if kind == _DOWN:
                events.append(("down", round_no, r.blob()))
            elif kind == _ACK:
                events.append(("ack", round_no, bool(r.one("B"))))
            else:
                raise CorruptMessage(f"corrupted message: an order's event of kind {kind}")
        r.end()
        return cls(strategy, rover, head.round, head.step, bool(finish), events, mission, since, pace)


@dataclass
class Report:
    """A rover's answer to an order: what the base's side of the link needs, no more."""

    strategy: str
    rover: int
    step: int  #: the step it drove to
    pos: Cell  #: where it is at ``step``
    target: Cell | None
    reached: bool  #: it was in range of the base at its last sync (it made an uplink, or tried)
    uplink: Outgoing | None  #: its uplink (None: none, e.g. its update was rejected)
    answers: list[bool]  #: whether it could use each downlink of the order, in order
    version: str | None  #: the model version it holds before the sync (model strategies)
    journal: dict  #: its journal's new entries (dropped updates, losses, cells trained on)
    round_no: int = 0  #: the round of its uplink (its own sync's)
    sent: int = 0  #: the step it made its uplink at (its last sync)
    synced: bool = True  #: it passed a sync step of its clock since its last report (always, in lockstep)

    def to_bytes(self) -> bytes:
        up = self.uplink
        flags = (self.reached | (up is not None) << 1 | (up is not None and up.payload is not None) << 2
                 | (self.version is not None) << 3 | (not self.synced) << 4)
        target = (-1, -1) if self.target is None else self.target
        w = Writer().text(self.strategy).put("hhhhB", *self.pos, *target, flags)
        if up is not None:
            w.put("I", self.sent).text(up.kind).blob(up.payload or b"")
        w.put("H", len(self.answers)).put(f"{len(self.answers)}B", *self.answers)
        if self.version is not None:
            w.text(self.version)
        # what its end journaled (most rounds: nothing, and no bytes)
        w.blob(json.dumps(self.journal, separators=(",", ":")).encode() if self.journal else b"")
        return pack_message(Head(REPORT, self.rover, self.round_no, self.step), w.done())

    @classmethod
    def from_bytes(cls, raw: bytes) -> Report:
        """The report in ``raw``; :class:`CorruptMessage` for anything that is not one."""
        head, r = unpack_message(raw, REPORT)
        strategy = r.text()
        pr, pc, tr, tc, flags = r.get("hhhhB")
        up, sent = None, 0
        if flags & 2:
            sent, kind, payload = r.one("I"), r.text(), r.blob()
            up = Outgoing(payload if flags & 4 else None, kind)
        answers = [bool(a) for a in r.get(f"{r.one('H')}B")]
        version = r.text() if flags & 8 else None
        text = r.blob()
        r.end()
        try:
            journal = json.loads(text) if text else {}
            if not isinstance(journal, dict):
                raise ValueError("not an object")
        except ValueError as e:
            raise CorruptMessage(f"corrupted message: a report's journal does not decode ({e})") from None
        return cls(strategy, head.sender, head.step, (pr, pc), None if (tr, tc) == (-1, -1) else (tr, tc),
                   bool(flags & 1), up, answers, version, journal, head.round, sent, not flags & 16)


def _cell(c: list | None) -> Cell | None:
    return None if c is None else (int(c[0]), int(c[1]))


def pack_history(orders: list[bytes]) -> bytes:
    """Every order a rover was sent, in order, as one frame (a rover that lost its state is rebuilt from it)."""
    w = Writer().put("I", len(orders))
    for o in orders:
        w.blob(o)
    return pack_message(Head(HISTORY, BASE, 0, 0), w.done())


def unpack_history(raw: bytes) -> list[bytes]:
    _, r = unpack_message(raw, HISTORY)
    n = r.one("I")
    orders = [r.blob() for _ in range(min(n, len(raw)))]  # (a count beyond its bytes is cut short on the way)
    r.end()
    return orders


# -- the rover's side -----------------------------------------------------------------------


def check_process_limits(c: MissionConfig) -> None:
    """One line when the mission ``c`` asks for what no mission on processes (star or peers) does."""
    if c.frames.enabled:
        raise FedmapError("a mission on processes runs with known poses: [frames] (unknown poses, drift) runs "
                          "in process only")
    if c.link.latency != 0:
        raise FedmapError(f"a mission on processes needs [link] latency = 0 (got {c.link.latency}): the real "
                          "link's delay is its latency: add --set link.latency=0")
    if c.stop_coverage is not None:
        raise FedmapError("a mission on processes takes every step: stop_coverage reads the truth (the share of the "
                          "reachable cells observed), which no node holds")


def check_deployable(c: MissionConfig, strategies: list[str] | tuple[str, ...]) -> None:
    """One line when the mission ``c`` or a strategy cannot run on processes (see the module's limits)."""
    if c.link.topology != "star":
        raise FedmapError(f"a mission on Flower's processes runs the star topology only, not {c.link.topology!r}: "
                          "rovers have no links of their own there (Flower routes every message through the base's "
                          "SuperLink); run mesh and leader teams with --deploy zenoh (fedmap node base and fedmap node "
                          "peer)")
    check_process_limits(c)
    deployable = names_that("deployable")
    bad = [s for s in strategies if s not in deployable]
    if bad:
        raise FedmapError(f"strategy {', '.join(bad)} cannot run on processes (its ends are not one per machine); "
                          f"these can: {', '.join(deployable)}")


def deployable_strategies(c: MissionConfig) -> tuple[tuple[str, ...], list[str]]:
    """The mission's strategies that run on processes and those left out, checked before any
    process starts: one line when none of them does, or when the mission cannot
    (:func:`check_deployable`)."""
    deployable = names_that("deployable")
    names = tuple(n for n in c.strategies if n in deployable)
    if not names:
        raise FedmapError(f"none of the strategies {', '.join(c.strategies)} runs on processes; these do: "
                          f"{', '.join(deployable)}")
    check_deployable(c, names)  # the topology and latency
    return names, [n for n in c.strategies if n not in deployable]


class ProcessRover:
    """Rover ``k`` of strategy ``name`` on a machine of its own, in lockstep with the base or
    on its own clock (the order says which): its node
    (:class:`~fedmap.mission.network.nodes.RoverNode`: its end and its robot, the mission's
    terrain seeded as the simulator's; or with ``feed`` the maps its own software writes,
    :class:`~fedmap.mission.world.feed.FeedWorld`), its clock and its own log. :meth:`answer`
    takes an order, returns the report: the order is its transport (the frames that reached
    it, and the step to drive to), the report carries its frame back."""

    #: called after every order it answered with its step and its belief (what it plans on:
    #: the team's map as it knows it), e.g. to publish it to the robot's ROS 2 graph. A class
    #: default, so a state file written before it existed still loads and answers.
    on_belief: Callable[[int, np.ndarray], None] | None = None

    def __init__(self, mission: Mission, name: str, k: int, *, feed: Feed | None = None) -> None:
        check_deployable(mission.config, [name])
        self.name, self.k, self.config = name, k, mission.config
        topology = make_topology(mission.config.link, mission.base)
        world = mission.world(topology)
        if not 0 <= k < len(world.team):
            raise FedmapError(f"rover {k} is not in the team of {len(world.team)}")
        if feed is not None:  # its observations come from its own mapping software (fedmap.mission.world.feed)
            world = FeedWorld(world, k, feed)
        sharing = build(name, Setup(mission.config, mission.truth, world.team, topology))
        world.ends = sharing.rovers  # only its own end is ever asked
        self.node = RoverNode(k, sharing.rovers[k], world, topology)
        self.journal = sharing.journal
        self.step = 0
        self._told = 0  # trail cells already logged
        self.mission_id = ""  # the mission's id, from its first order
        #: its own log: one entry per order answered (what it recorded; never sent), taken by its keeper
        self.log: list[RoverEntry] = []
        self._last: tuple[bytes, bytes] | None = None  # the last order it answered, and its report
        self._seen = {"dropped": 0, "losses": 0, "trained_cells": 0}
        self.unsent: Frame | None = None  # its last uplink, until the radio takes it (the next report)
        self.reached = False  # in range of the base at its last sync of this order
        self.synced = False  # it passed a sync step while answering this order
        self.t0: float | None = None  # on its own clock: when its step 0 was (seconds, ``now``'s)
        self.now = time.time
        self.node.sense(0)
        self._states = [self._state(0)]  # recorded, not yet logged (the record of a step follows its deliveries)

    def _state(self, t: int) -> StepState:
        node = self.node
        r, belief = node.rover, node.belief()
        return StepState(t, belief, node.world.own_view(self.k, belief), r.local != UNKNOWN, r.pos, r.target,
                         r.distance, len(r.trail))

    def _journal(self) -> dict:
        out: dict[str, list] = {}
        for key, seen in self._seen.items():
            entries = getattr(self.journal, key)
            if entries is None:
                continue
            new = entries[seen:]
            self._seen[key] = len(entries)
            if new:
                out[key] = [e.to_dict() if isinstance(e, DroppedUpdate) else e for e in new]
        return out

    @classmethod
    def rebuild(cls, mission: Mission, name: str, k: int, history: list[bytes], *,
                feed: Feed | None = None) -> ProcessRover:
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
        """Hand its node the order's frames, drive (to the order's step, or as far as its own
        clock says), syncing at each of its sync steps on the way, and report."""
        if order.strategy != self.name or order.rover != self.k:
            raise FedmapError(f"an order for {order.strategy} rover {order.rover} reached {self.name} rover {self.k}")
        lockstep = order.pace == 0
        if lockstep and (order.step < self.step or (order.step == self.step and not order.finish)):
            raise FedmapError(f"rover {self.k} is at step {self.step}: an order to drive to step {order.step} is stale")
        if order.since > self.step:
            raise LostState(f"rover {self.k} is at step {self.step}, the base holds it at step {order.since}: it lost "
                            "its state")
        if order.since != self.step:
            raise FedmapError(f"rover {self.k} is at step {self.step}, ahead of the base's step {order.since}: the "
                              "base station's journal is older than this rover's state")
        node, answers = self.node, []
        for ev in order.events:
            if ev[0] == "ack":
                node.acked(Frame(self.k, BASE, ev[1], self.step, "", None), ev[2])
            else:
                answers.append(node.take(Frame(BASE, self.k, ev[1], self.step, "", ev[2]), self.step))
        states = self._states
        if not states or states[-1].step != self.step:
            states.append(self._state(self.step))  # the last step's record, now that its deliveries are in
        version, self.reached, self.synced = getattr(node.end, "version", None), False, False
        target = order.step if lockstep else self._clock(order)
        for t in range(self.step + 1, target + 1):
            node.drive(t)
            self.step = t
            round_no = self.config.sync_round(t)
            if round_no is not None and not order.finish:
                self._sync(t, round_no)
            if t < target or order.finish:
                states.append(self._state(t))
        r, up = node.rover, self.unsent
        self.unsent = None  # handed to the radio
        self.mission_id = order.mission
        self.log.append(RoverEntry(self.name, self.k, order.mission, self.step, states, list(r.trail[self._told:])))
        self._told = len(r.trail)
        self._states = []
        if self.on_belief is not None:
            self.on_belief(self.step, node.belief())
        return Report(self.name, self.k, self.step, r.pos, r.target, self.reached,
                      None if up is None else Outgoing(up.payload, up.kind), answers, version, self._journal(),
                      0 if up is None else up.round, 0 if up is None else up.step, self.synced)

    def _clock(self, order: Order) -> int:
        """The step its own clock is at (``order.pace`` ms a step; the mission's last with
        ``finish``), never behind the step it is at. Its clock starts at its first order, set
        to the step that order was sent at (the mission started that long ago), and runs on
        its own from then on."""
        if order.finish:
            return max(self.config.steps, self.step)
        if self.t0 is None:
            self.t0 = self.now() - order.step * order.pace / 1000
        return max(self.step, min(self.config.steps, int((self.now() - self.t0) * 1000 / order.pace)))

    def _sync(self, t: int, round_no: int) -> None:
        """Its sync (round ``round_no``) at step ``t`` of its clock: an uplink made earlier that
        never left (no message came since) is not delivered, and the new one waits for the radio."""
        node = self.node
        self.synced = True
        if self.unsent is not None:
            node.acked(self.unsent, False)
            self.unsent = None
        node.at_sync(round_no)
        self.reached = node.in_range()
        if self.reached:
            self.unsent = node.uplink(round_no, t)


# -- the base's side ------------------------------------------------------------------------


class FarRover:
    """Rover ``k`` as the base station's transport reaches it on processes: what its last
    report said (its uplink frame, where it is, the model it holds), and the frames and
    acknowledgements the link delivered to it, kept for its next order. It holds no end:
    its answers to downlinks come with its next report."""

    def __init__(self, k: int) -> None:
        self.k = self.address = k
        self.report: Report | None = None
        self.events: list[tuple] = []

    @property
    def version(self) -> str | None:
        return None if self.report is None else self.report.version

    @property
    def silence(self) -> str:
        """Why it sent no uplink: its end made none, or (on its own clock) it had not reached a sync step."""
        return "rejected" if self.report is None or self.report.synced else "no sync"

    def at_sync(self, round_no: int) -> None:
        """Its sync ran on the rover, before its report."""

    def prepare(self, round_no: int) -> None:
        """Its training ran on the rover, before its report."""
        return None

    def uplink(self, round_no: int, step: int) -> Frame | None:
        rep = self.report
        assert rep is not None
        up = rep.uplink  # made at its own sync (lockstep: this round's, at this step)
        return None if up is None else Frame(self.k, BASE, rep.round_no, rep.sent, up.kind, up.payload)

    def acked(self, frame: Frame, ok: bool) -> None:
        self.events.append(("ack", frame.round, ok))

    def take(self, frame: Frame, due: int) -> None:
        self.events.append(("down", frame.round, frame.payload or b""))
        return None  # its answer comes with its next report


class ProcessBase:
    """The base station of strategy ``name`` on processes, the mission's clock: its node
    (:class:`~fedmap.mission.network.nodes.BaseNode`, its end alone: no world, no rover's
    end), the link and the in-process transport's rounds over the rovers far away
    (:class:`FarRover`), and its own log. :meth:`first_orders` starts the mission;
    :meth:`take` takes every rover's report and gives the next orders (none: the mission is
    over, :meth:`record`)."""

    def __init__(self, mission: Mission, name: str, *, mission_id: str = "", pace: int = 0) -> None:
        check_deployable(mission.config, [name])
        c = mission.config
        self.name, self.config, self.mission_id, self.pace = name, c, mission_id, pace
        topology = make_topology(c.link, mission.base)
        team = start_team(c, mission.truth.shape, mission.starts, mission.base, mission.waypoints)
        self.sharing = sharing = build(name, Setup(c, mission.truth, team, topology))  # (it keeps the base's end)
        assert sharing.base is not None, f"{name} has no base station's end"
        self.node = BaseNode(sharing.base)
        self.far = sharing.rovers = [FarRover(k) for k in range(len(team))]  # what the journal reads of the rovers
        self.positions = [r.pos for r in team]  # every rover's cell, as its last report said
        self.since = [0] * len(team)  # every rover's step, as its last report said
        self.link = Link(replace(c.link, seed=c.link_seed), topology)
        self.exchange = Exchange(topology, self.link, rovers=self.far, base=self.node,
                                 positions=lambda: list(self.positions), replan=lambda k: None,
                                 on_sync=sharing.on_sync, on_link=sharing.on_link)
        #: the global map it held after each of its rounds, by step (its log)
        self.held: dict[int, np.ndarray] = {0: self.node.global_map().copy()}
        #: the frames it sent and took: how many, their bytes (framing included), and of them the orders' and reports'
        self.wire = {"frames": 0, "bytes": 0, "orders": 0, "reports": 0}
        self.done = False

    @property
    def n(self) -> int:
        return len(self.far)

    def _orders(self, after: int) -> dict[int, Order]:
        """Every rover's next order after step ``after``: to the next sync, or to the end."""
        c = self.config
        nxt = (after // c.sync_every + 1) * c.sync_every  # the next sync step
        step, finish = (nxt, False) if nxt <= c.steps else (c.steps, True)
        orders = {}
        for s in self.far:
            orders[s.k] = Order(self.name, s.k, 0 if finish else step // c.sync_every, step, finish, s.events,
                                self.mission_id, self.since[s.k], self.pace)
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
            step_ok = rep.step == o.step if not self.pace else (rep.step >= o.since or o.finish)
            if (rep.strategy, rep.rover) != (self.name, k) or not step_ok:
                raise FedmapError(f"rover {k}'s report is for {rep.strategy} step {rep.step}, its order was "
                                  f"{self.name} step {o.step}")
            self.since[k] = rep.step
            self.exchange.answers(k, rep.answers)
        step = next(iter(orders.values())).step
        if next(iter(orders.values())).finish:
            self.done = True
            return {}
        journal = self.sharing.journal
        for s in self.far:
            rep = s.report = reports[s.k]
            self.positions[s.k] = rep.pos
            for key, entries in rep.journal.items():  # what its end journaled making its uplink
                held = getattr(journal, key)
                if held is not None:
                    held.extend(DroppedUpdate(**e) if key == "dropped" else e for e in entries)
        round_no = self.config.sync_round(step)
        assert round_no is not None  # (orders go to sync steps, but the last)
        self.exchange.sync(step, round_no)
        self.exchange.deliver(step)
        self.held[step] = self.node.global_map().copy()
        return self._orders(step)

    def record(self, seconds: float) -> BaseRecord:
        """What the base logged of its run (the mission is over): what it held after each
        round, its ledger and its journal's models; scored with the rovers' logs by
        :func:`~fedmap.mission.scoring.score_strategy`."""
        if not self.done:
            raise FedmapError(f"{self.name}: the mission is not over")
        s, journal = self.sharing, self.sharing.journal
        regs = registrations(s)
        return BaseRecord(self.name, self.mission_id, seconds, dict(self.held), self.link.ledger,
                          self.link.slots, self.node.global_heights(),
                          None if journal.dropped is None else list(journal.dropped),
                          None if journal.lags is None else list(journal.lags),
                          None if regs is None else list(regs), dict(self.wire))


def warm_up() -> None:
    """Load the compiled planners (numba, cached on disk) into this process. A process that
    forks one process per message (Flower's ClientApps, :mod:`fedmap.flower.warm`) calls it
    once before forking, so no message pays the load (about 0.5 s each, measured)."""
    belief = np.full((8, 8), FREE, dtype=np.uint8)
    belief[0] = UNKNOWN
    choose_target(belief, (4, 4), radius=1.5, unknown_cost=1.5, others=[])
    travel_costs(belief, (4, 4), 1.5)  # the cheapest path's search (a rover with a predictor)
    astar(np.ones((4, 4), dtype=bool), (0, 0), (3, 3))


#: Flower's side of the lockstep seam: every rover's order as bytes -> its report as bytes.
Exchanger = Callable[[dict[int, bytes]], dict[int, bytes]]


def rounds(base: ProcessBase, send: Exchanger, *, clock: Callable[[], float] = time.monotonic,
           sleep: Callable[[float], None] = time.sleep) -> Iterator[int]:
    """Run ``base``'s mission over ``send`` (every rover's order as bytes -> its report as
    bytes); yields each step an order drove to. On its own clock (``base.pace`` ms a step;
    ``clock`` in seconds, ``sleep`` waits), the base sends the orders of step ``t`` when its
    clock reaches ``t``."""
    orders = base.first_orders()
    t0 = clock()
    while orders:
        step = next(iter(orders.values())).step
        if base.pace and not next(iter(orders.values())).finish:
            sleep(max(0.0, t0 + step * base.pace / 1000 - clock()))
        sent = {k: o.to_bytes() for k, o in orders.items()}
        raw = send(sent)
        reports = {k: Report.from_bytes(r) for k, r in raw.items()}
        w = base.wire
        w["orders"] += sum(map(len, sent.values()))
        w["reports"] += sum(map(len, raw.values()))
        w["frames"] += len(sent) + len(raw)
        w["bytes"] = w["orders"] + w["reports"]
        orders = base.take(reports, orders)
        yield step


class Loopback:
    """Every rover of strategy ``name`` in this process, reached only through bytes (tests,
    and the reference a mission on processes is checked against); ``feeds``: rovers whose
    observations come from a map feed. Call it with the orders; :attr:`logs` holds each
    rover's own log."""

    def __init__(self, mission: Mission, name: str, *, feeds: dict[int, Feed] | None = None,
                 clocks: dict[int, Callable[[], float]] | None = None,
                 on_beliefs: dict[int, Callable[[int, np.ndarray], None]] | None = None) -> None:
        self.mission, self.name, self.feeds, self.clocks = mission, name, feeds or {}, clocks or {}
        self.on_beliefs = on_beliefs or {}
        self.nodes: dict[int, ProcessRover] = {}

    def __call__(self, orders: dict[int, bytes]) -> dict[int, bytes]:
        out = {}
        for k, raw in orders.items():
            if k not in self.nodes:
                self.nodes[k] = ProcessRover(self.mission, self.name, k, feed=self.feeds.get(k))
                if k in self.clocks:  # its own clock (seconds), for a rover on its own clock
                    self.nodes[k].now = self.clocks[k]
                self.nodes[k].on_belief = self.on_beliefs.get(k)
            out[k] = self.nodes[k].answer(raw)
        return out

    @property
    def logs(self) -> list[list[RoverEntry]]:
        """Every rover's log, in team order."""
        return [self.nodes[k].log for k in sorted(self.nodes)]


def loopback(mission: Mission, name: str, *, feeds: dict[int, Feed] | None = None,
             clocks: dict[int, Callable[[], float]] | None = None,
             on_beliefs: dict[int, Callable[[int, np.ndarray], None]] | None = None) -> Loopback:
    """:class:`Loopback`: every rover of ``name`` in this process, behind bytes (``clocks``:
    a rover's own clock, in seconds, instead of the machine's; ``on_beliefs``: a rover's
    :attr:`ProcessRover.on_belief`)."""
    return Loopback(mission, name, feeds=feeds, clocks=clocks, on_beliefs=on_beliefs)


__all__ = ["WIRE_VERSION", "CorruptMessage", "FarRover", "ProcessBase", "ProcessRover", "Loopback", "LostState",
           "Order", "Report", "StepState", "check_deployable", "check_process_limits", "deployable_strategies",
           "loopback", "pack_frame", "pack_history", "rounds", "unpack_frame", "unpack_history", "warm_up"]
