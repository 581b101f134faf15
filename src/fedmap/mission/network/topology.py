"""Who talks to whom, and how one sync round goes over a strategy's ends.

A topology is a class with a complete protocol (:class:`Topology`): who reaches whom from
the rovers' positions, the budget of each link, and :meth:`~Topology.sync`, which runs one
sync round over the team's nodes through an
:class:`~fedmap.mission.network.transport.Exchange` (the in-process transport: the seeded
:class:`~fedmap.mission.network.link.Link` and the messages in flight). :func:`make_topology`
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

Every message goes sender node -> frame -> receiver node; the receiver answers whether it
could use it, and the sender gets that answer at arrival time (``acked``: the link-level
acknowledgement). A message that does not arrive is acknowledged as not
delivered when it is sent.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from fedmap.mission.network.link import BASE, Link

Cell = tuple[int, int]
#: Slack on ``max_range`` (cells), so a rover exactly at the range is in range despite rounding.
RANGE_SLACK = 1e-9


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

    def sync(self, x: Any, t: int, round_no: int) -> None:
        """Round ``round_no`` at step ``t`` over the nodes of ``x``
        (an :class:`~fedmap.mission.network.transport.Exchange`)."""
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

    def sync(self, x: Any, t: int, round_no: int) -> None:
        if x.base is not None:
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

    def sync(self, x: Any, t: int, round_no: int) -> None:
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
            members = tuple(a for a in x.peers if a not in leaders)

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
