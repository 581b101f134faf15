"""A peer mission whose agents run elsewhere: one node per agent (each rover, and the lander
when it is an agent) on a machine of its own, in lockstep, and only messages between them.

There is no base station giving orders. Every agent holds the mission (the same config
and seed), drives its own rover, and at each sync step runs the round of its topology
(:meth:`~fedmap.mission.network.topology.Topology.sync`) over :class:`PeerRound`: the
in-process :class:`~fedmap.mission.network.transport.Exchange` with only its own node at
home. Every agent runs the same round, so they agree on who talks to whom without a word
about it:

1. **Positions.** Each rover posts its cell to the team's table keeper (the lander's desk on
   Zenoh) and gets back the table of the round: every rover's cell, and the agents that left.
   The topology's range, the links that are up (the seeded drops, and none to an agent that
   left), the connected groups and their leaders
   (:func:`~fedmap.mission.network.topology.elect_leaders`) are functions of the table, the
   round and the seed, so every agent computes the same: a leader that leaves is replaced at
   the next round by the same rule, with no election messages.
2. **Messages.** The topology offers its messages in the same order on every agent (an
   *offer number* per message). The sender applies the link model (budget, the seeded
   loss of each hop, relays: :meth:`~fedmap.mission.network.link.Link.send_route`) on its
   own :class:`~fedmap.mission.network.link.Link`, keeps the ledger entries of what it
   sent, and posts the frame to its receiver, or a word that nothing comes. The receiver
   takes it at its place in the round and answers whether it could use it; the sender
   gets that answer where the in-process transport would acknowledge it. Each agent
   handles its events in the round's one order, so the result is the in-process round's,
   message for message (the offer numbers order the merged ledger).
3. **Closing.** Every agent closes its round as the topology says.

What the agents post is :class:`Mail` (one message frame, with its check) through a
:class:`Post`: Zenoh on real machines (:mod:`fedmap.zenohnet.peer`), threads in one process
for tests (:class:`LocalPost`). Each agent logs what an observer reads of its rover
(:class:`~fedmap.mission.network.nodelog.RoverEntry`, as a star rover does) and its own part
of the link (:class:`~fedmap.mission.network.nodelog.PeerRecord`); the mission is scored
from the logs afterwards (:func:`merge_records`, then
:func:`~fedmap.mission.scoring.score_strategy`).

An agent that leaves mid-round (its process killed) costs the others only what it would have
sent them: a frame that does not come is not delivered, an answer that does not come is "not
used". From the next round it has no links; its log ends where it left, and its last record
stands for the rest of the mission (:func:`~fedmap.mission.scoring.score_strategy`).

Limits: lockstep, ``latency = 0``, and the strategies whose peer ends hold only their own
agent (``peer_deployable``). A relayed message's hops are drawn and counted by its sender
(the relays' radios are modelled, not run). An agent that left does not come back.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import UNKNOWN
from fedmap.mission.ends.registry import Setup, build, names_that
from fedmap.mission.ends.sharing import agreed
from fedmap.mission.network.link import BASE, Link, Message
from fedmap.mission.network.nodelog import BaseRecord, PeerRecord, RoverEntry, StepState
from fedmap.mission.network.nodes import PeerNode
from fedmap.mission.network.remote import check_process_limits
from fedmap.mission.network.topology import make_topology
from fedmap.mission.network.transport import Exchange
from fedmap.mission.network.wire import MAIL, Frame, Head, Writer, pack_message, unpack_message
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import Mission

Cell = tuple[int, int]
#: What a :class:`Mail` carries: a rover's position at a sync, a frame, a word that a frame
#: will not come (lost, over budget: its sender was told so at once), a receiver's answer.
POS, FRAME, NOTHING, ANSWER = 0, 1, 2, 3
#: Seconds an agent waits for one mail from another before the mission fails (lockstep: a
#: mail that never comes is an agent that stopped).
MAIL_WAIT = 300.0


@dataclass(frozen=True)
class Mail:
    """One message between two agents of strategy ``strategy``'s run: ``what`` (:data:`POS`,
    :data:`FRAME`, :data:`NOTHING`, :data:`ANSWER`) from ``sender`` to ``to`` at ``step``
    (round ``round``), for the round's offer ``offer`` (0 for a position), with ``body``
    (a position: its cell, :func:`pos_body`; a frame: the packed frame; an answer: one byte)."""

    what: int
    sender: int
    to: int
    round: int
    step: int
    offer: int
    strategy: str
    body: bytes = b""

    @property
    def key(self) -> tuple[int, int, int, int]:
        """What a receiver waits for: (kind, sender, step, offer); a frame and a "nothing" are one kind."""
        return (FRAME if self.what == NOTHING else self.what, self.sender, self.step, self.offer)

    def to_bytes(self) -> bytes:
        w = Writer().put("hBI", self.to, self.what, self.offer).text(self.strategy).blob(self.body)
        return pack_message(Head(MAIL, self.sender, self.round, self.step), w.done())

    @classmethod
    def from_bytes(cls, raw: bytes) -> Mail:
        """The mail in ``raw``; :class:`~fedmap.mission.network.wire.CorruptMessage` for anything that is not one."""
        head, r = unpack_message(raw, MAIL)
        to, what, offer = r.get("hBI")
        strategy, body = r.text(), r.blob()
        r.end()
        return cls(what, head.sender, to, head.round, head.step, offer, strategy, body)


def pos_body(pos: Cell) -> bytes:
    """A rover's cell, as a :data:`POS` mail carries it."""
    return Writer().put("hh", *pos).done()


def _who(agent: int) -> str:
    return "the lander" if agent == BASE else f"rover {agent}"


class AgentGone(FedmapError):
    """The agent whose mail was awaited left the team."""

    def __init__(self, agent: int, what: str) -> None:
        self.agent = agent
        super().__init__(f"{_who(agent)} left the team: {what}")


#: A round's table: every rover's cell (team order) and the agents that left.
Table = tuple[list[Cell], frozenset[int]]


class Post(Protocol):
    """How an agent's mail travels: ``send`` hands one on (it arrives, in order per receiver,
    or the mission fails), ``wait`` blocks until the mail with ``key`` (:attr:`Mail.key`)
    reached this agent, and returns it (:class:`AgentGone`: its sender left), ``table``
    posts this rover's cell at sync step ``step`` (None: the lander, which does not move) and
    returns the round's :data:`Table`, the same for every agent."""

    def send(self, mail: Mail) -> None: ...

    def wait(self, key: tuple[int, int, int, int]) -> Mail: ...

    def table(self, strategy: str, step: int, agent: int, pos: Cell | None) -> Table: ...


class Inbox:
    """What reached one agent, by :attr:`Mail.key`, until it is read (thread-safe; a
    transport's receiving side puts, the agent waits). ``alive(agent)`` says whether an agent
    is still there (a wait for a gone agent's mail fails at once, not at the timeout);
    ``failed()`` an error of the agent's own transport, raised by a wait."""

    def __init__(self, alive: Callable[[int], bool] = lambda a: True, timeout: float = MAIL_WAIT,
                 failed: Callable[[], FedmapError | None] = lambda: None) -> None:
        self.held: dict[tuple[int, int, int, int], Mail] = {}
        self.cond = threading.Condition()
        self.alive, self.timeout, self.failed = alive, timeout, failed

    def put(self, mail: Mail) -> None:
        with self.cond:
            self.held[mail.key] = mail
            self.cond.notify_all()

    def wait(self, key: tuple[int, int, int, int]) -> Mail:
        t_end = time.monotonic() + self.timeout
        with self.cond:
            while key not in self.held:
                error = self.failed()
                if error is not None:  # its own sending failed (the transport's)
                    raise error
                left = t_end - time.monotonic()
                if not self.alive(key[1]):
                    raise AgentGone(key[1], f"waiting for its {_WHAT[key[0]]} of step {key[2]}")
                if left <= 0:
                    raise FedmapError(f"{_who(key[1])} sent nothing for {self.timeout:g} s: waiting for its {_WHAT[key[0]]} "
                                      f"of step {key[2]}")
                self.cond.wait(min(left, 0.5))
            return self.held.pop(key)


_WHAT = {POS: "position", FRAME: "message", NOTHING: "message", ANSWER: "answer"}


class Tables:
    """The keeper of a peer mission's tables (the lander's, or a process's for its threads):
    a round's table is made once every rover of ``rovers`` posted its cell or left
    (``alive(k)`` says), and is the same for everyone who asks. ``on_table(strategy, step,
    gone)``: a table was made (who had left by then)."""

    def __init__(self, rovers: int, alive: Callable[[int], bool] = lambda a: True, timeout: float = MAIL_WAIT,
                 on_table: Callable[[str, int, frozenset[int]], None] | None = None) -> None:
        self.rovers, self.alive, self.timeout, self.on_table = rovers, alive, timeout, on_table
        self.cond = threading.Condition()
        self.cells: dict[tuple[str, int], dict[int, Cell]] = {}
        self.made: dict[tuple[str, int], Table] = {}
        self.last: dict[str, list[Cell]] = {}  # every rover's last cell posted, per strategy
        self.gone: set[int] = set()  # (an agent that left does not come back)

    def post(self, strategy: str, step: int, agent: int, pos: Cell | None) -> None:
        with self.cond:
            if pos is not None:
                self.cells.setdefault((strategy, step), {})[agent] = pos
            self.cond.notify_all()

    def ready(self, strategy: str, step: int) -> Table | None:
        """The table of ``step``, made now if every rover posted or left (under the lock)."""
        key = (strategy, step)
        if key in self.made:
            return self.made[key]
        posted = self.cells.get(key, {})
        self.gone |= {k for k in range(self.rovers) if k not in posted and not self.alive(k)}
        if any(k not in posted and k not in self.gone for k in range(self.rovers)):
            return None
        last = self.last.setdefault(strategy, [(0, 0)] * self.rovers)
        cells = [posted.get(k, last[k]) for k in range(self.rovers)]
        self.last[strategy] = cells
        self.made[key] = table = (cells, frozenset(self.gone))
        self.cells.pop(key, None)
        if self.on_table is not None:
            self.on_table(strategy, step, table[1])
        return table

    def table(self, strategy: str, step: int, agent: int, pos: Cell | None) -> Table:
        self.post(strategy, step, agent, pos)
        t_end = time.monotonic() + self.timeout
        with self.cond:
            while (table := self.ready(strategy, step)) is None:
                if time.monotonic() > t_end:
                    raise FedmapError(f"no table of step {step} within {self.timeout:g} s: a rover neither posted "
                                      "its cell nor left")
                self.cond.wait(0.2)
            self.cond.notify_all()
            return table

    def settle(self) -> None:
        """Someone left: wake whoever waits for a table."""
        with self.cond:
            self.cond.notify_all()


class LocalPost:
    """Every agent's post in one process (tests, and the reference the real one is checked
    against): ``post(agent)`` is agent ``agent``'s :class:`Post`."""

    def __init__(self, rovers: int) -> None:
        self.inboxes: dict[int, Inbox] = {}
        self.lock = threading.Lock()
        self.tables = Tables(rovers, timeout=120.0)

    def inbox(self, agent: int) -> Inbox:
        with self.lock:
            return self.inboxes.setdefault(agent, Inbox(timeout=120.0))

    def post(self, agent: int) -> Post:
        me = self

        class _Agent:
            def send(self, mail: Mail) -> None:
                me.inbox(mail.to).put(Mail.from_bytes(mail.to_bytes()))  # through bytes, as on a wire

            def wait(self, key: tuple[int, int, int, int]) -> Mail:
                return me.inbox(agent).wait(key)

            def table(self, strategy: str, step: int, who: int, pos: Cell | None) -> Table:
                return me.tables.table(strategy, step, who, pos)

        return _Agent()


class PeerRound(Exchange):
    """One agent's side of its topology's rounds: the in-process transport with only its
    own node (``node``, agent ``me``) at home; every other agent's part reaches it as mail
    (module docstring). ``positions()``: every rover's cell as the round's table said."""

    def __init__(self, topology, link: Link, me: int, node: PeerNode, post: Post, strategy: str, *,
                 positions: Callable[[], list[Cell]], replan: Callable[[int | None], None]) -> None:
        super().__init__(topology, link, peers={me: node}, positions=positions, replan=replan)
        self.me, self.node, self.post, self.strategy = me, node, post, strategy
        self.offers = 0  # the round's offers so far (every agent counts the same)
        #: per ledger entry of this agent's: (step, offer, hop), the merged ledger's order
        self.order: list[tuple[int, int, int]] = []

    def sync(self, t: int, round_no: int) -> None:
        self.offers = 0
        super().sync(t, round_no)

    def _mail(self, what: int, to: int, round_no: int, step: int, offer: int, body: bytes = b"") -> None:
        self.post.send(Mail(what, self.me, to, round_no, step, offer, self.strategy, body))

    def offer(self, path: list[int], t: int, round_no: int, role: str) -> None:
        n = self.offers
        self.offers += 1
        a, b = path[0], path[-1]
        if a == self.me:
            budget = self.topology.budget(a, b, role)
            frame = self.node.message(b, round_no, t, budget)
            ledger, sent = self.link.ledger, len(self.link.ledger)
            msg = self.link.send_route(frame.payload, path, round_no=round_no, step=frame.step, kind=frame.kind,
                                       budget=budget)
            self.order += [(t, n, i) for i in range(len(ledger) - sent)]
            raw = self._carry(frame, sent)
            if msg.to != b or msg.arrival is None:  # lost on the way, or nothing fit: told at once
                self.node.acked(frame, False)
                self._mail(NOTHING, b, round_no, t, n)
                return
            self._mail(FRAME, b, round_no, t, n, raw)

            def acked(due: int) -> None:  # where the in-process transport acknowledges it
                try:
                    ok = self.post.wait((ANSWER, b, t, n)).body == b"\x01"
                except AgentGone:  # it left before it answered: as good as not used
                    ok = False
                self.answered(frame, msg, ok, peer=True)
            self.at(msg.arrival, acked)
        elif b == self.me:
            def take(due: int) -> None:  # where it would arrive (latency 0: this step)
                try:
                    mail = self.post.wait((FRAME, a, t, n))
                except AgentGone:  # it left before it sent it
                    return
                if mail.what == NOTHING:
                    return
                frame = Frame.unpack(mail.body)
                ok = self.node.take(frame, due)
                self._mail(ANSWER, a, round_no, t, n, b"\x01" if ok else b"\x00")
            self.at(t + self.latency * (len(path) - 1), take)


class TeamLink(Link):
    """The link model of one agent on processes: the mission's, and no link to an agent that left (``gone``)."""

    def __init__(self, config, topology) -> None:
        super().__init__(config, topology)
        self.gone: frozenset[int] = frozenset()

    def down(self, round_no: int, a: int, b: int, step: int | None = None) -> bool:
        return a in self.gone or b in self.gone or super().down(round_no, a, b, step)


def peer_deployable(c: MissionConfig, strategies: list[str] | tuple[str, ...]) -> None:
    """One line when the peer mission ``c`` or a strategy cannot run with an agent per process."""
    if c.link.topology == "star":
        raise FedmapError("a peer mission on processes needs a peer topology (mesh or leader); the star runs "
                          "with a base station (fedmap node base)")
    check_process_limits(c)
    if c.helicopters:
        raise FedmapError("a peer mission on processes runs rovers only: helicopters fly in process")
    ok = names_that("peer_deployable")
    bad = [s for s in strategies if s not in ok]
    if bad:
        raise FedmapError(f"strategy {', '.join(bad)} cannot run as peers on processes; these can: {', '.join(ok)}")


def peer_strategies(c: MissionConfig) -> tuple[tuple[str, ...], list[str]]:
    """The strategies of the peer mission ``c`` that run with an agent per process, and those left out."""
    ok = names_that("peer_deployable")
    names = tuple(n for n in c.strategies if n in ok)
    if not names:
        raise FedmapError(f"none of the strategies {', '.join(c.strategies)} runs as peers on processes; these do: "
                          f"{', '.join(ok)}")
    peer_deployable(c, names)
    return names, [n for n in c.strategies if n not in ok]


def agents_of(c: MissionConfig, base: Cell) -> tuple[int, ...]:
    """The agents of the peer mission ``c`` (the lander, :data:`BASE`, first when it is one)."""
    return make_topology(c.link, base).peer_agents(c.rovers)


class ProcessPeer:
    """Agent ``agent`` of strategy ``name``'s peer mission on a machine of its own: its node
    (its end, and its rover: the mission's terrain seeded as the simulator's), its side of
    the rounds (:class:`PeerRound`) over ``post``, and its own log. :meth:`run` runs the
    mission to its last step."""

    def __init__(self, mission: Mission, name: str, agent: int, post: Post, *, mission_id: str = "") -> None:
        c = mission.config
        peer_deployable(c, [name])
        self.name, self.agent, self.config, self.mission_id, self.post = name, agent, c, mission_id, post
        self.topology = topology = make_topology(c.link, mission.base)
        self.agents = topology.peer_agents(c.rovers)
        if agent not in self.agents:
            raise FedmapError(f"agent {agent} is not in the team {list(self.agents)} (-1: the lander)")
        self.world = world = mission.world(topology)
        sharing = build(name, Setup(c, mission.truth, world.team, topology))
        assert sharing.peers is not None
        world.ends = sharing.rovers  # only its own end is ever asked
        self.rover = None if agent == BASE else world.team[agent]
        self.node = PeerNode(agent, sharing.peers[agent], self.rover)
        self.positions: list[Cell] = world.positions()
        self.link = TeamLink(replace(c.link, seed=c.link_seed), topology)
        self.left: dict[int, int] = {}  #: the agents that left, and the sync step it was noticed at

        def replan(k: int | None) -> None:
            if self.rover is not None and k in (None, agent):
                self.rover.replan = True

        self.round = PeerRound(topology, self.link, agent, self.node, post, name,
                               positions=lambda: list(self.positions), replan=replan)
        #: its own log: rover entries (a rover agent), taken by its keeper as they come
        self.log: list[RoverEntry] = []
        self.held: dict[int, np.ndarray] = {}  #: the lander: its belief after every sync, by step

    def _state(self, t: int) -> StepState:
        r, belief = self.rover, self.node.belief()
        assert r is not None
        return StepState(t, belief, self.world.own_view(self.agent, belief), r.local != UNKNOWN, r.pos, r.target,
                         r.distance, len(r.trail))

    def _positions(self, t: int) -> None:
        """Every rover's cell at sync step ``t``, and who left: the round's table (its own cell posted)."""
        pos = None if self.rover is None else self.rover.pos
        cells, gone = self.post.table(self.name, t, self.agent, pos)
        self.positions = list(cells)
        for a in gone - set(self.left):
            self.left[a] = t
        self.link.gone = gone

    def run(self, on_step: Callable[[int], None] | None = None,
            keep: Callable[[RoverEntry | PeerRecord], object] | None = None) -> PeerRecord:
        """The whole mission, step by step, in lockstep with the other agents; its record.
        ``keep(entry)`` writes its log as it goes: each rover entry, and its record after every
        sync (a process killed mid-mission leaves its log up to its last sync)."""
        c, w, t0 = self.config, self.world, time.perf_counter()
        k, states, told = self.agent, [], 0
        rounds: list[float] = []
        last = t0
        if self.rover is not None:
            w.sense(k, 0)
            states.append(self._state(0))
        self.held[0] = self.node.belief().copy()
        for t in range(1, c.steps + 1):
            if self.rover is not None:
                w.drive(k, t)
            round_no = c.sync_round(t)
            if round_no is not None:
                self._positions(t)
                self.round.sync(t, round_no)
            self.round.deliver(t)
            if round_no is not None:
                now = time.perf_counter()
                rounds.append(now - last)
                last = now
                if self.rover is None:
                    self.held[t] = self.node.belief().copy()
            if self.rover is not None:
                states.append(self._state(t))
            if round_no is not None or t == c.steps:  # its log, a chunk per sync
                if self.rover is not None:
                    self.log.append(RoverEntry(self.name, k, self.mission_id, t, states,
                                               list(self.rover.trail[told:])))
                    told, states = len(self.rover.trail), []
                    if keep is not None:
                        keep(self.log[-1])
                if keep is not None:
                    keep(self._record(time.perf_counter() - t0, rounds))
            if on_step is not None:
                on_step(t)
        return self._record(time.perf_counter() - t0, rounds)

    def _record(self, seconds: float, rounds: list[float]) -> PeerRecord:
        return PeerRecord(self.name, self.mission_id, self.agent, seconds, list(self.link.ledger),
                          list(self.round.order), self.link.slots, dict(self.round.wire),
                          dict(self.held) if self.rover is None else {}, list(rounds), dict(self.left))


def merge_records(mission: Mission, records: list[PeerRecord], logs: list[list[RoverEntry]]) -> BaseRecord:
    """The team's record of one strategy's peer run from every agent's own
    (:class:`~fedmap.mission.network.nodelog.PeerRecord`) and the rovers' logs: the ledger in
    the round's order, the slots and wire bytes summed, and the global map as the simulator
    keeps it (the lander's belief, or without a lander the cells every rover's belief holds
    alike)."""
    c = mission.config
    if not records:
        raise FedmapError("no agent's record of the peer run")
    name = records[0].strategy
    agents = agents_of(c, mission.base)
    have = sorted(r.agent for r in records)
    left: dict[int, int] = {}
    for r in records:
        for a, t in r.left.items():
            left[a] = min(t, left.get(a, t))
    if have != sorted(agents):
        raise FedmapError(f"{name}: records of agents {have}, the team's are {sorted(agents)} (-1: the lander)")
    keyed = sorted(((key, m) for r in records for key, m in zip(r.order, r.ledger)), key=lambda km: km[0])
    ledger: list[Message] = [m for _, m in keyed]
    wire = {key: sum(r.wire.get(key, 0) for r in records) for key in dict.fromkeys(k for r in records for k in r.wire)}
    lander = next((r for r in records if r.agent == BASE), None)
    if lander is not None:
        held = lander.held
    else:
        by_step: list[dict[int, np.ndarray]] = [{s.step: s.belief for e in log for s in e.states} for log in logs]
        ends = [max(b, default=-1) for b in by_step]  # each rover's last logged step
        held = {}
        for t in range(c.steps + 1):  # (a rover that left: its last belief)
            beliefs = [b[t] if t in b else b[ends[k]] for k, b in enumerate(by_step)
                       if t in b or (k in left and b and ends[k] < t)]
            if len(beliefs) != len(by_step):
                continue  # (score_strategy names the missing step)
            held[t] = agreed(beliefs)
    return BaseRecord(name, records[0].mission, max(r.seconds for r in records), held, ledger,
                      sum(r.slots for r in records), wire=wire, left=left or None)


def run_local(mission: Mission, name: str, *, mission_id: str = "") -> tuple[BaseRecord, list[list[RoverEntry]]]:
    """Strategy ``name``'s peer mission with every agent in a thread of this process, through
    :class:`LocalPost` (tests: the reference for a mission over a real network); the merged
    record and every rover's log."""
    post = LocalPost(mission.config.rovers)
    agents = agents_of(mission.config, mission.base)
    peers = {a: ProcessPeer(mission, name, a, post.post(a), mission_id=mission_id) for a in agents}
    records: dict[int, PeerRecord] = {}
    errors: list[BaseException] = []

    def go(a: int) -> None:
        try:
            records[a] = peers[a].run()
        except BaseException as e:  # noqa: BLE001  (raised below, in the caller's thread)
            errors.append(e)

    threads = [threading.Thread(target=go, args=(a,), daemon=True) for a in agents]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    if errors:
        raise errors[0]
    logs = [peers[k].log for k in range(mission.config.rovers)]
    return merge_records(mission, [records[a] for a in agents], logs), logs


__all__ = ["ANSWER", "FRAME", "MAIL_WAIT", "NOTHING", "POS", "AgentGone", "Inbox", "LocalPost", "Mail", "PeerRound",
           "Post", "ProcessPeer", "Table", "Tables", "TeamLink", "agents_of", "merge_records", "peer_deployable",
           "peer_strategies", "pos_body", "run_local"]
