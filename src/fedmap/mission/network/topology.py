"""Who talks to whom, and how one sync round goes over a strategy's ends.

A topology is a class with a complete protocol (:class:`Topology`): who reaches whom from
the rovers' positions, the budget of each link, and :meth:`~Topology.sync`, which runs one
sync round over the ends through an :class:`Exchange` (the in-process transport: the
seeded :class:`~fedmap.mission.network.link.Link` and the messages in flight). :func:`make_topology`
builds one from ``[link]``; :data:`TOPOLOGIES` is the registry of them.

* :class:`StarTopology`: every rover talks only to the base station, within ``max_range``.
  A star round: every rover in range offers its uplink; ``latency`` steps later the base,
  holding what arrived, runs its round and offers a downlink per rover. A peer strategy on
  the star exchanges both ways between each rover and the base (an agent).
* :class:`MeshTopology`: agents within ``peer_range`` of each other; every link that is up
  exchanges both ways, and every agent closes its round ``latency`` steps later.
* :class:`LeaderTopology`: the links that are up split the agents into connected groups;
  each elects a leader (:func:`elect_leaders`) that plays the base for its group: members
  reach it over relays (:func:`route`), leaders close their round when their members'
  messages are in and answer, and members close theirs when the answers are.

Every message goes sender end -> bytes -> receiver end; the receiver answers whether it
could use it, and the sender's ``delivered`` hook gets that answer at arrival time (the
link-level acknowledgement). A message that does not arrive is acknowledged as not
delivered when it is sent.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from fedmap.mission.ends.protocol import Outgoing, side_by_side
from fedmap.mission.network.link import BASE, DOWN, UP, Link, Message
from fedmap.mission.network.wire import pack_payload, unpack_payload

Cell = tuple[int, int]
#: Slack on ``max_range`` (cells), so a rover exactly at the range is in range despite rounding.
RANGE_SLACK = 1e-9


def _call(fn: Callable[..., None], *args: Any) -> Callable[[int], None]:
    """An event that calls ``fn(*args)`` whenever it is due (the arguments bound now)."""
    return lambda due: fn(*args)


class Exchange:
    """The in-process transport of one strategy's run: the link, the ends (a
    :class:`~fedmap.mission.ends.registry.Sharing`) and the queue of messages in flight.
    ``positions()`` gives every rover's cell now; ``replan(k)`` tells rover ``k`` its belief
    changed."""

    def __init__(self, topology: Topology, link: Link, sharing: Any, positions: Callable[[], list[Cell]],
                 replan: Callable[[int | None], None]) -> None:
        self.topology, self.link, self.sharing = topology, link, sharing
        self.positions, self.replan = positions, replan
        self.latency = link.config.latency
        self.queue: list = []
        self.seq = 0
        self.links: tuple[tuple[int, int], ...] = ()  #: peer topologies: the links up at the last sync
        self.leaders: tuple[int, ...] = ()  #: leader topology: the agents leading at the last sync
        #: star: per rover, the downlinks it was handed but has not answered yet (round, ledger entry)
        self.pending: dict[int, list[tuple[int, Message]]] = {}
        #: what the transport carried: every message as a frame (:func:`~fedmap.mission.network.wire.pack_payload`),
        #: its bytes counted once per hop the link spent bytes on (the ledger counts the payload's)
        self.wire = {"frames": 0, "bytes": 0}

    def carry(self, sender: int, to: int, round_no: int, step: int, out: Outgoing, sent: int) -> bytes:
        """The frame that carries ``out`` from ``sender`` to ``to``, counted as wire bytes for
        every ledger entry from ``sent`` on that spent bytes (one per hop; none: nothing was
        sent, e.g. nothing fit the budget, and nothing is counted)."""
        raw = pack_payload(sender, to, round_no, step, out.kind, out.payload or b"")
        hops = sum(1 for m in self.link.ledger[sent:] if m.bytes)
        self.wire["frames"] += hops
        self.wire["bytes"] += hops * len(raw)
        return raw

    def at(self, due: int, event: Callable[[int], None]) -> None:
        """Run ``event(due)`` when the clock reaches ``due``."""
        heapq.heappush(self.queue, (due, self.seq, event))
        self.seq += 1

    def sync(self, t: int, round_no: int) -> None:
        if self.sharing.on_link:
            self.sharing.at_sync(round_no)  # every topology: before any message of the round
            self.topology.sync(self, t, round_no)

    def deliver(self, t: int) -> None:
        """Everything due by step ``t``, in order."""
        while self.queue and self.queue[0][0] <= t:
            due, _, event = heapq.heappop(self.queue)
            event(due)

    # -- the star's messages
    def star_round(self, t: int, round_no: int) -> None:
        s, link = self.sharing, self.link
        positions = self.positions()
        reachable = self.topology.reachable(positions)
        side_by_side([c for k, rover in enumerate(s.rovers) if reachable[k] and (c := rover.prepare(round_no))])
        for k, rover in enumerate(s.rovers):
            if not reachable[k]:  # recorded as out of range
                link.send(None, round_no=round_no, step=t, rover=k, direction=UP, kind="-", positions=positions)
                continue
            out = rover.uplink(round_no)
            if out is None:
                link.ledger.append(Message(round_no, t, k, UP, "update", 0, "rejected"))
                continue
            sent = len(link.ledger)
            msg = link.send(out.payload, round_no=round_no, step=t, rover=k, direction=UP, kind=out.kind,
                            positions=positions, budget=self.topology.budget(k, BASE, UP))
            raw = self.carry(k, BASE, round_no, t, out, sent)
            if msg.arrival is None:
                rover.delivered(round_no, False)
                continue
            self.at(msg.arrival, _call(self._up, k, raw))
        self.at(t + self.latency, lambda due: self._base(due, round_no))

    def _up(self, k: int, raw: bytes) -> None:
        head, _, _, payload = unpack_payload(raw)
        ok = self.sharing.base.receive(k, payload, head.round)
        self.sharing.rovers[k].delivered(head.round, ok)

    def _base(self, due: int, round_no: int) -> None:
        base = self.sharing.base
        for k, out in base.downlinks(round_no).items():
            sent = len(self.link.ledger)
            msg = self.link.send(out.payload, round_no=round_no, step=due, rover=k, direction=DOWN, kind=out.kind,
                                 positions=self.positions(), budget=self.topology.budget(BASE, k, DOWN))
            raw = self.carry(BASE, k, round_no, due, out, sent)
            if msg.arrival is None:
                base.delivered(k, round_no, False)
                continue
            self.at(msg.arrival, _call(self._down, k, raw, msg))

    def _down(self, k: int, raw: bytes, msg: Message) -> None:
        head, _, _, payload = unpack_payload(raw)
        round_no = head.round
        ok = self.sharing.rovers[k].receive(payload)
        if ok is None:  # a rover on another machine: its answer comes with its next report
            self.pending.setdefault(k, []).append((round_no, msg))
            return
        self.answered(k, round_no, msg, ok)

    def answered(self, k: int, round_no: int, msg: Message, ok: bool) -> None:
        """Rover ``k``'s answer to the downlink ``msg`` of round ``round_no``: the base's
        acknowledgement, and a stale downlink marked as such."""
        self.sharing.base.delivered(k, round_no, ok)
        if ok:
            self.replan(k)
        else:
            msg.status = "stale"

    def answers(self, k: int, oks: Sequence[bool]) -> None:
        """Rover ``k``'s answers to its downlinks still pending, in the order they arrived."""
        waiting = self.pending.get(k, [])
        if len(oks) != len(waiting):
            raise ValueError(f"rover {k} answered {len(oks)} downlink(s), {len(waiting)} were pending")
        for (round_no, msg), ok in zip(waiting, oks):
            self.answered(k, round_no, msg, ok)
        self.pending[k] = []

    # -- peer messages
    def peer_links(self, round_no: int, pairs: Sequence[tuple[int, int]]) -> None:
        """Tell every agent how many agents it exchanges with this round."""
        degree: dict[int, int] = {}
        for a, b in pairs:
            degree[a] = degree.get(a, 0) + 1
            degree[b] = degree.get(b, 0) + 1
        for agent, end in self.sharing.peers.items():
            end.links(round_no, degree.get(agent, 0))

    def offer(self, path: list[int], t: int, round_no: int, role: str) -> int:
        """Offer agent ``path[0]``'s message to ``path[-1]`` along ``path``; its arrival step (or t)."""
        a, b = path[0], path[-1]
        budget = self.topology.budget(a, b, role)
        sender = self.sharing.peers[a]
        out = sender.message(b, round_no, t, budget)
        sent = len(self.link.ledger)
        msg = self.link.send_route(out.payload, path, round_no=round_no, step=t, kind=out.kind, budget=budget)
        raw = self.carry(a, b, round_no, t, out, sent)
        if msg.arrival is not None and msg.to == b:
            self.at(msg.arrival, lambda due: self._peer(raw, due, msg))
            return msg.arrival
        sender.delivered(b, round_no, False)
        return t

    def _peer(self, raw: bytes, due: int, msg: Message) -> None:
        head, b, _, payload = unpack_payload(raw)
        a, round_no = head.sender, head.round
        ok = self.sharing.peers[b].receive(a, payload, round_no, due)
        self.sharing.peers[a].delivered(b, round_no, ok)
        if not ok:
            msg.status = "stale"
        elif b != BASE:
            self.replan(b)

    def close(self, round_no: int, agents: Sequence[int] | None) -> None:
        """The ``agents`` (None: every agent) close round ``round_no``."""
        for agent, end in self.sharing.peers.items():
            if agents is None or agent in agents:
                end.close_round(round_no)

    def exchange_round(self, t: int, round_no: int, pairs: list[tuple[int, int]]) -> None:
        """Every pair exchanges both ways; every agent closes its round ``latency`` steps later."""
        self.links, self.leaders = tuple(pairs), ()
        self.peer_links(round_no, pairs)
        for a, b in pairs:
            self.offer([a, b], t, round_no, "peer")
            self.offer([b, a], t, round_no, "peer")

        def closing(due: int) -> None:
            self.close(round_no, None)
            self.replan(None)

        self.at(t + self.latency, closing)


class Topology:
    """Who can talk to whom from the rovers' positions (cells, team order), each link's
    budget, and one sync round over a strategy's ends (:meth:`sync`)."""

    name: ClassVar[str]
    #: whether there is a base station (a strategy's ``star`` ends run on it)
    has_base: ClassVar[bool] = False

    def neighbours(self, agent: int, positions: Sequence[Cell]) -> tuple[int, ...]:
        """The agents ``agent`` talks to directly this step (rover indices, or :data:`BASE`)."""
        raise NotImplementedError

    def reachable(self, positions: Sequence[Cell]) -> tuple[bool, ...]:
        """For every rover (team order): can its messages reach the base this step?"""
        raise NotImplementedError

    def region(self, shape: tuple[int, int]) -> np.ndarray | None:
        """The cells from which a rover reaches the base whatever the others do (boolean map
        of ``shape``), or None where there is no such limit."""
        return None

    def peer_agents(self, n_rovers: int) -> tuple[int, ...]:
        """The agents of a peer strategy, the lander (:data:`BASE`) first when it is one."""
        raise NotImplementedError

    def up_pairs(self, link: Link, round_no: int, step: int, positions: Sequence[Cell]) -> list[tuple[int, int]]:
        """The links up this round (pairs of agents), less the links down."""
        raise NotImplementedError

    def budget(self, a: int, b: int, role: str) -> int | None:
        """The budget of a message from ``a`` to ``b`` (``role``: up, down or peer)."""
        raise NotImplementedError

    @classmethod
    def describe(cls, lc: Any) -> str:
        """One sentence of ``report.md`` on who talks to whom under ``[link]`` ``lc``."""
        return "every rover talks to the base station"

    def sync(self, x: Exchange, t: int, round_no: int) -> None:
        """Round ``round_no`` at step ``t`` over the ends of ``x.sharing``."""
        x.exchange_round(t, round_no, self.up_pairs(x.link, round_no, t, x.positions()))


@dataclass(frozen=True)
class StarTopology(Topology):
    """Every rover talks only to the base station at ``base``, when it is within
    ``max_range`` cells of it (Euclidean, in cells; None: no limit). Rovers never talk to
    each other."""

    base: Cell
    max_range: float | None = None
    uplink_bytes: int | None = None
    downlink_bytes: int | None = None
    name: ClassVar[str] = "star"
    has_base: ClassVar[bool] = True

    @classmethod
    def from_config(cls, lc: Any, base: Cell) -> StarTopology:
        return cls(base, lc.max_range, lc.uplink_bytes, lc.downlink_bytes)

    def _in_range(self, pos: Cell) -> bool:
        r = self.max_range
        return r is None or math.hypot(pos[0] - self.base[0], pos[1] - self.base[1]) <= r + RANGE_SLACK

    def neighbours(self, agent: int, positions: Sequence[Cell]) -> tuple[int, ...]:
        if agent == BASE:
            return tuple(k for k, p in enumerate(positions) if self._in_range(p))
        return (BASE,) if self._in_range(positions[agent]) else ()

    def reachable(self, positions: Sequence[Cell]) -> tuple[bool, ...]:
        return tuple(self._in_range(p) for p in positions)

    def region(self, shape: tuple[int, int]) -> np.ndarray | None:
        if self.max_range is None:
            return None
        rows, cols = np.indices(shape)
        return np.hypot(rows - self.base[0], cols - self.base[1]) <= self.max_range + RANGE_SLACK

    def peer_agents(self, n_rovers: int) -> tuple[int, ...]:
        return (BASE, *range(n_rovers))

    def up_pairs(self, link: Link, round_no: int, step: int, positions: Sequence[Cell]) -> list[tuple[int, int]]:
        reach = self.reachable(positions)
        return [(BASE, k) for k in range(len(positions)) if reach[k] and not link.down(round_no, k, BASE, step)]

    def budget(self, a: int, b: int, role: str) -> int | None:
        return self.uplink_bytes if b == BASE else self.downlink_bytes

    def sync(self, x: Exchange, t: int, round_no: int) -> None:
        if x.sharing.base is not None:
            x.star_round(t, round_no)
        else:  # a peer strategy: the base station is an agent
            super().sync(x, t, round_no)


@dataclass(frozen=True)
class MeshTopology(Topology):
    """Every agent talks directly to every agent within ``peer_range`` cells of it
    (Euclidean; None: no limit). The agents are the rovers (0, 1, ...) and, when
    ``lander_agent``, the lander at ``base`` as :data:`BASE`."""

    base: Cell
    peer_range: float | None = None
    lander_agent: bool = True
    peer_bytes: int | None = None
    name: ClassVar[str] = "mesh"

    @classmethod
    def from_config(cls, lc: Any, base: Cell) -> MeshTopology:
        return cls(base, lc.peer_range, lc.lander_agent, lc.peer_bytes)

    def agents(self, n_rovers: int) -> tuple[int, ...]:
        """Every agent, the lander (:data:`BASE`) first when it is one."""
        return ((BASE,) if self.lander_agent else ()) + tuple(range(n_rovers))

    peer_agents = agents

    def position(self, agent: int, positions: Sequence[Cell]) -> Cell:
        return self.base if agent == BASE else positions[agent]

    def in_range(self, a: int, b: int, positions: Sequence[Cell]) -> bool:
        if self.peer_range is None:
            return True
        pa, pb = self.position(a, positions), self.position(b, positions)
        return math.hypot(pa[0] - pb[0], pa[1] - pb[1]) <= self.peer_range + RANGE_SLACK

    def neighbours(self, agent: int, positions: Sequence[Cell]) -> tuple[int, ...]:
        return tuple(b for b in self.agents(len(positions)) if b != agent and self.in_range(agent, b, positions))

    def pairs(self, positions: Sequence[Cell]) -> list[tuple[int, int]]:
        """Every pair of agents in range of each other, ``(a, b)`` with ``a < b``, in order."""
        ags = self.agents(len(positions))
        return [(a, b) for i, a in enumerate(ags) for b in ags[i + 1:] if self.in_range(a, b, positions)]

    def reachable(self, positions: Sequence[Cell]) -> tuple[bool, ...]:
        """For every rover: is it connected to the lander, over any number of hops?"""
        if not self.lander_agent:
            return tuple(False for _ in positions)
        group = next(g for g in components(self.agents(len(positions)), self.pairs(positions)) if BASE in g)
        return tuple(k in group for k in range(len(positions)))

    def up_pairs(self, link: Link, round_no: int, step: int, positions: Sequence[Cell]) -> list[tuple[int, int]]:
        return [(a, b) for a, b in self.pairs(positions) if not link.down(round_no, a, b, step)]

    def budget(self, a: int, b: int, role: str) -> int | None:
        return self.peer_bytes

    @classmethod
    def describe(cls, lc: Any) -> str:
        budget = "unlimited" if lc.peer_bytes is None else f"{lc.peer_bytes:,} B"
        return (cls._within(lc) + "; every link that is up exchanges both ways at every sync; budget per link per "
                f"direction per round {budget}")

    @staticmethod
    def _within(lc: Any) -> str:
        return (f"agents within {'any distance' if lc.peer_range is None else f'{lc.peer_range:g} cells'} of each "
                "other talk directly")


@dataclass(frozen=True)
class LeaderTopology(MeshTopology):
    """The mesh, with a leader elected per connected group at every sync (module docstring).
    Members' messages to their leader have the uplink budget, its answers the downlink's."""

    uplink_bytes: int | None = None
    downlink_bytes: int | None = None
    name: ClassVar[str] = "leader"

    @classmethod
    def from_config(cls, lc: Any, base: Cell) -> LeaderTopology:
        return cls(base, lc.peer_range, lc.lander_agent, lc.peer_bytes, lc.uplink_bytes, lc.downlink_bytes)

    def budget(self, a: int, b: int, role: str) -> int | None:
        return self.uplink_bytes if role == "up" else self.downlink_bytes

    @classmethod
    def describe(cls, lc: Any) -> str:
        return (cls._within(lc) + "; at every sync each connected group elects a leader (the lander if in the group, "
                "else its lowest-numbered rover) that plays the base for the group, members reaching it over relays")

    def sync(self, x: Exchange, t: int, round_no: int) -> None:
        positions = x.positions()
        pairs = self.up_pairs(x.link, round_no, t, positions)
        x.links = tuple(pairs)
        leader = elect_leaders(components(self.agents(len(positions)), pairs))
        leaders = x.leaders = tuple(sorted(set(leader.values())))
        routes = {m: route(m, ld, pairs) for m, ld in leader.items() if m != ld}
        x.peer_links(round_no, [(m, leader[m]) for m in routes])
        hops = max((len(r) - 1 for r in routes.values() if r), default=0)
        for r in routes.values():
            assert r is not None
            x.offer(r, t, round_no, "up")

        def lead(due: int) -> None:  # leaders have what their members sent: they mix, and answer
            x.close(round_no, leaders)
            for r in routes.values():
                assert r is not None
                x.offer(r[::-1], due, round_no, "down")
            members = tuple(a for a in x.sharing.peers if a not in leaders)

            def members_close(due: int) -> None:
                x.close(round_no, members)
                x.replan(None)

            x.at(due + x.latency * hops, members_close)

        x.at(t + x.latency * hops, lead)


#: Every topology by its ``[link] topology`` name.
TOPOLOGIES: dict[str, type[StarTopology] | type[MeshTopology]] = {
    c.name: c for c in (StarTopology, MeshTopology, LeaderTopology)}


def make_topology(lc: Any, base: Cell) -> Topology:
    """The topology ``[link]`` (a :class:`~fedmap.mission.settings.LinkConfig`) asks for, the base station at ``base``."""
    return TOPOLOGIES[lc.topology].from_config(lc, base)


def components(agents: Sequence[int], pairs: Sequence[tuple[int, int]]) -> list[tuple[int, ...]]:
    """The connected groups of ``agents`` over the undirected ``pairs``, each sorted, in the
    order of their lowest agent (:data:`BASE` sorts first)."""
    parent = {a: a for a in agents}

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in pairs:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for a in sorted(agents):
        groups.setdefault(root(a), []).append(a)
    return [tuple(g) for _, g in sorted(groups.items())]


def elect_leaders(groups: Sequence[tuple[int, ...]]) -> dict[int, int]:
    """Every agent's leader: in each group, the lander (:data:`BASE`) when it is in the
    group, else the lowest-numbered rover. Deterministic: it depends only on who is in the
    group, never on order, time or the strategy."""
    out = {}
    for g in groups:
        leader = BASE if BASE in g else min(g)
        out.update({a: leader for a in g})
    return out


def route(a: int, b: int, pairs: Sequence[tuple[int, int]]) -> list[int] | None:
    """The shortest route from ``a`` to ``b`` over the undirected ``pairs`` (``[a, ..., b]``;
    breadth first, lower-numbered neighbours first, so it is deterministic), or None."""
    nbrs: dict[int, list[int]] = {}
    for x, y in pairs:
        nbrs.setdefault(x, []).append(y)
        nbrs.setdefault(y, []).append(x)
    prev: dict[int, int | None] = {a: None}
    frontier = [a]
    while frontier and b not in prev:
        nxt = []
        for x in frontier:
            for y in sorted(nbrs.get(x, ())):
                if y not in prev:
                    prev[y] = x
                    nxt.append(y)
        frontier = nxt
    if b not in prev:
        return None
    out = [b]
    while out[-1] != a:
        p = prev[out[-1]]
        assert p is not None
        out.append(p)
    return out[::-1]
