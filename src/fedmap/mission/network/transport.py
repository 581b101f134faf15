"""The transport seam: what carries frames between a team's nodes.

A :class:`Transport` takes a node's :class:`~fedmap.mission.network.wire.Frame`, decides
its fate, hands it to the node it is for (``take``: the receiver answers whether it could
use it) and gives the sender the acknowledgement (``acked``) at arrival time. It tells the
time of its clock and delivers what is due by a step.

* :class:`Exchange` is the in-process transport: the seeded
  :class:`~fedmap.mission.network.link.Link` (budget, loss, latency, range, links down),
  the queue of frames in flight and the mission clock's sync rounds, run by the topology
  (:meth:`~fedmap.mission.network.topology.Topology.sync`). ``fedmap mission`` runs every
  strategy and topology through it.
* On processes (:mod:`fedmap.mission.network.remote`), the base station's side is the same
  :class:`Exchange` whose rover nodes are far away (:class:`~fedmap.mission.network.remote.FarRover`:
  what the base heard of a rover, in its frames), and a rover's side is the order it
  answers; Flower carries both (:mod:`fedmap.flower.mission`).
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from fedmap.mission.ends.protocol import side_by_side
from fedmap.mission.network.link import BASE, DOWN, UP, Link, Message
from fedmap.mission.network.wire import Frame

Cell = tuple[int, int]


class Transport(Protocol):
    """What every transport offers the nodes of a team."""

    def now(self) -> int:
        """The step of its clock."""
        ...

    def send(self, frame: Frame, role: str, path: Sequence[int] | None = None) -> int | None:
        """Offer ``frame`` (``role``: up, down or peer; ``path``: a peer frame's relays, its
        sender first); its arrival step, or None when it will not arrive (its sender is
        acknowledged "not delivered" at once)."""
        ...

    def deliver(self, until: int) -> None:
        """Hand every frame due by step ``until`` to its node, and its acknowledgement to its sender."""
        ...


def _call(fn: Callable[..., None], *args: Any) -> Callable[[int], None]:
    """An event that calls ``fn(*args, due)`` when it is due (the arguments bound now)."""
    return lambda due: fn(*args, due)


class Exchange:
    """The in-process transport of one strategy's run over its nodes: ``rovers`` (rover
    nodes, team order) and ``base`` on the star, ``peers`` (by agent) on peers; the link and
    the queue of frames in flight. ``positions()`` gives every rover's cell now;
    ``replan(k)`` tells rover ``k`` (None: every member) its belief changed; ``on_sync``
    is called at every sync before the nodes' own (a record the run keeps); ``on_link``:
    whether the strategy sends anything at all."""

    def __init__(self, topology: Any, link: Link, *, rovers: Sequence[Any] = (), base: Any = None,
                 peers: dict[int, Any] | None = None, positions: Callable[[], list[Cell]],
                 replan: Callable[[int | None], None], on_sync: Callable[[int], None] | None = None,
                 on_link: bool = True) -> None:
        self.topology, self.link = topology, link
        self.rovers, self.base, self.peers = list(rovers), base, peers
        self.nodes: dict[int, Any] = dict(peers) if peers is not None else {n.address: n for n in self.rovers}
        if base is not None:
            self.nodes[BASE] = base
        self.positions, self.replan, self.on_sync, self.on_link = positions, replan, on_sync, on_link
        self.latency = link.config.latency
        self.queue: list = []
        self.seq = 0
        self.clock = 0
        self.links: tuple[tuple[int, int], ...] = ()  #: peer topologies: the links up at the last sync
        self.leaders: tuple[int, ...] = ()  #: leader topology: the agents leading at the last sync
        #: per rover far away, the downlinks it was handed but has not answered yet (frame, ledger entry)
        self.pending: dict[int, list[tuple[Frame, Message]]] = {}
        #: what the transport carried: every frame packed (:meth:`Frame.pack`), its bytes counted
        #: once per hop the link spent bytes on (the ledger counts the payload's)
        self.wire = {"frames": 0, "bytes": 0}

    # -- the seam
    def now(self) -> int:
        return self.clock

    def send(self, frame: Frame, role: str, path: Sequence[int] | None = None) -> int | None:
        link, sent = self.link, len(self.link.ledger)
        budget = self.topology.budget(frame.sender, frame.to, role)
        if path is None:  # the star: between a rover and the base station
            k, direction = (frame.sender, UP) if frame.to == BASE else (frame.to, DOWN)
            msg = link.send(frame.payload, round_no=frame.round, step=frame.step, rover=k, direction=direction,
                            kind=frame.kind, positions=self.positions(), budget=budget)
            arrival = msg.arrival
        else:
            msg = link.send_route(frame.payload, path, round_no=frame.round, step=frame.step, kind=frame.kind,
                                  budget=budget)
            arrival = msg.arrival if msg.to == frame.to else None
        raw = self._carry(frame, sent)
        if arrival is None:
            self.nodes[frame.sender].acked(frame, False)
            return None
        self.at(arrival, _call(self._arrive, raw, msg, path is not None))
        return arrival

    def deliver(self, until: int) -> None:
        """Everything due by step ``until``, in order."""
        while self.queue and self.queue[0][0] <= until:
            due, _, event = heapq.heappop(self.queue)
            event(due)
        self.clock = max(self.clock, until)

    def _carry(self, frame: Frame, sent: int) -> bytes:
        """``frame`` on the wire, counted as wire bytes for every ledger entry from ``sent`` on
        that spent bytes (one per hop; none: nothing was sent, e.g. nothing fit the budget)."""
        raw = frame.pack()
        hops = sum(1 for m in self.link.ledger[sent:] if m.bytes)
        self.wire["frames"] += hops
        self.wire["bytes"] += hops * len(raw)
        return raw

    def _arrive(self, raw: bytes, msg: Message, peer: bool, due: int) -> None:
        frame = Frame.unpack(raw)
        ok = self.nodes[frame.to].take(frame, due)
        if ok is None:  # a rover far away: its answer comes with its next report
            self.pending.setdefault(frame.to, []).append((frame, msg))
            return
        self.answered(frame, msg, ok, peer)

    def answered(self, frame: Frame, msg: Message, ok: bool, peer: bool = False) -> None:
        """The receiver's answer to ``frame`` (ledger entry ``msg``): the sender's
        acknowledgement, and a frame it could not use marked stale (an uplink on the star stays
        delivered: the base's answer to it says only whether its rover may forget its cells)."""
        self.nodes[frame.sender].acked(frame, ok)
        if not ok and (peer or frame.to != BASE):
            msg.status = "stale"

    def answers(self, k: int, oks: Sequence[bool]) -> None:
        """Rover ``k``'s answers to its downlinks still pending, in the order they arrived."""
        waiting = self.pending.get(k, [])
        if len(oks) != len(waiting):
            raise ValueError(f"rover {k} answered {len(oks)} downlink(s), {len(waiting)} were pending")
        for (frame, msg), ok in zip(waiting, oks):
            self.answered(frame, msg, ok)
        self.pending[k] = []

    def at(self, due: int, event: Callable[[int], None]) -> None:
        """Run ``event(due)`` when the clock reaches ``due``."""
        heapq.heappush(self.queue, (due, self.seq, event))
        self.seq += 1

    # -- the mission clock's sync rounds (the topology runs them)
    def sync(self, t: int, round_no: int) -> None:
        if not self.on_link:
            return
        if self.on_sync is not None:
            self.on_sync(round_no)
        for node in (self.peers.values() if self.peers is not None else self.rovers):  # before any message
            node.at_sync(round_no)
        self.topology.sync(self, t, round_no)

    def star_round(self, t: int, round_no: int) -> None:
        """Every rover in range sends its uplink; ``latency`` steps later the base closes its round and answers."""
        positions = self.positions()
        reachable = self.topology.reachable(positions)
        side_by_side([c for k, node in enumerate(self.rovers) if reachable[k] and (c := node.prepare(round_no))])
        for k, node in enumerate(self.rovers):
            if not reachable[k]:  # recorded as out of range
                self.link.send(None, round_no=round_no, step=t, rover=k, direction=UP, kind="-", positions=positions)
                continue
            frame = node.uplink(round_no, t)
            if frame is None:  # its end made none (a rover far away: or it has not synced since its last report)
                self.link.ledger.append(Message(round_no, t, k, UP, "update", 0, node.silence))
                continue
            self.send(frame, UP)
        self.at(t + self.latency, _call(self._base_round, round_no))

    def _base_round(self, round_no: int, due: int) -> None:
        for frame in self.base.downlinks(round_no, due):
            self.send(frame, DOWN)

    def peer_links(self, round_no: int, pairs: Sequence[tuple[int, int]]) -> None:
        """Tell every agent how many agents it exchanges with this round."""
        degree: dict[int, int] = {}
        for a, b in pairs:
            degree[a] = degree.get(a, 0) + 1
            degree[b] = degree.get(b, 0) + 1
        assert self.peers is not None
        for agent, node in self.peers.items():
            node.links(round_no, degree.get(agent, 0))

    def offer(self, path: list[int], t: int, round_no: int, role: str) -> None:
        """Agent ``path[0]``'s message to ``path[-1]``, along ``path``."""
        a, b = path[0], path[-1]
        self.send(self.nodes[a].message(b, round_no, t, self.topology.budget(a, b, role)), role, path)

    def close(self, round_no: int, agents: Sequence[int] | None) -> None:
        """The ``agents`` (None: every agent) close round ``round_no``."""
        assert self.peers is not None
        for agent, node in self.peers.items():
            if agents is None or agent in agents:
                node.close(round_no)

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


__all__ = ["Exchange", "Transport"]
