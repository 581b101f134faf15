"""The team's nodes: one per agent, each owning exactly one end of a strategy.

A node knows its own state and the frames that reach it, nothing else:

* :class:`RoverNode`: a rover's end and its robot (member ``k`` of a world that drives,
  senses and plans it in the simulator, or of a :class:`~fedmap.mission.world.feed.FeedWorld`
  whose map comes from the robot's own software);
* :class:`BaseNode`: the base station's end;
* :class:`PeerNode`: an agent's end on a peer topology (a rover's, or the lander's).

Every message between nodes is a :class:`~fedmap.mission.network.wire.Frame`. A node hands
the frames it sends to a transport (:class:`~fedmap.mission.network.transport.Transport`);
the transport hands it the frames that reach it (``take``: the node answers whether it
could use it) and the acknowledgement of each frame it sent (``acked``). The same node code
runs in the simulator (:class:`~fedmap.mission.network.transport.Exchange`) and on
processes (:mod:`fedmap.mission.network.remote`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from fedmap.mission.ends.protocol import BaseEnd, PeerEnd, RoverEnd
from fedmap.mission.network.link import BASE
from fedmap.mission.network.wire import Frame


class RoverNode:
    """Rover ``k``: its end (``end``) and its robot (member ``k`` of ``world``); ``topology``
    says whether it is in range of the base station from where it is."""

    #: why a sync of its ended with no uplink (its end made none: e.g. its update was rejected)
    silence = "rejected"

    def __init__(self, k: int, end: RoverEnd, world: Any, topology: Any) -> None:
        self.k = self.address = k
        self.end, self.world, self.topology = end, world, topology

    @property
    def rover(self) -> Any:
        """Its robot's state (position, target, trail, observations)."""
        return self.world.team[self.k]

    # -- the robot
    def sense(self, t: int) -> None:
        self.world.sense(self.k, t)

    def drive(self, t: int) -> None:
        """Drive (or fly) and sense for step ``t``."""
        self.world.drive(self.k, t)

    def in_range(self) -> bool:
        """Whether its messages reach the base station from where it is now."""
        return bool(self.topology.reachable(self.world.positions())[self.k])

    def belief(self) -> np.ndarray:
        return self.end.belief()

    # -- the link
    def at_sync(self, round_no: int) -> None:
        self.end.at_sync(round_no)

    def prepare(self, round_no: int) -> Callable[[], None] | None:
        """The heavy part of its uplink (a model's training), to run side by side with other rovers'."""
        return self.end.prepare(round_no)

    def uplink(self, round_no: int, step: int) -> Frame | None:
        """Its uplink of round ``round_no`` as a frame to the base (None: it has none; a
        frame without payload: nothing fit its budget)."""
        out = self.end.uplink(round_no)
        return None if out is None else Frame(self.k, BASE, round_no, step, out.kind, out.payload)

    def take(self, frame: Frame, due: int) -> bool:
        """A downlink reached it at step ``due``: whether it could use it (it replans if so)."""
        ok = bool(self.end.receive(frame.payload or b""))
        if ok:
            self.rover.replan = True
        return ok

    def acked(self, frame: Frame, ok: bool) -> None:
        """The acknowledgement of its uplink ``frame``: the base used it, or not (or it was lost)."""
        self.end.delivered(frame.round, ok)


class BaseNode:
    """The base station: its end of a star strategy."""

    address = BASE

    def __init__(self, end: BaseEnd) -> None:
        self.end = end

    def global_map(self) -> np.ndarray:
        return self.end.global_map()

    def global_heights(self) -> np.ndarray | None:
        return self.end.global_heights()

    def take(self, frame: Frame, due: int) -> bool:
        """Rover ``frame.sender``'s uplink reached it: whether it could use it."""
        return bool(self.end.receive(frame.sender, frame.payload or b"", frame.round))

    def downlinks(self, round_no: int, step: int) -> list[Frame]:
        """Its round ``round_no`` is closed (the uplinks that arrived are in): a frame per rover it answers."""
        return [Frame(BASE, k, round_no, step, out.kind, out.payload)
                for k, out in self.end.downlinks(round_no).items()]

    def acked(self, frame: Frame, ok: bool) -> None:
        """The acknowledgement of its downlink ``frame``: the rover used it, or not (or it was lost)."""
        self.end.delivered(frame.to, frame.round, ok)


class PeerNode:
    """Agent ``agent`` on a peer topology (a rover, or the lander as :data:`BASE`): its peer
    end, and its robot's state when it is a rover (``rover``: it replans when a message changes its belief)."""

    def __init__(self, agent: int, end: PeerEnd, rover: Any = None) -> None:
        self.agent = self.address = agent
        self.end, self.rover = end, rover

    def belief(self) -> np.ndarray:
        return self.end.belief()

    def at_sync(self, round_no: int) -> None:
        self.end.at_sync(round_no)

    def links(self, round_no: int, degree: int) -> None:
        """How many agents it exchanges with in round ``round_no``."""
        self.end.links(round_no, degree)

    def message(self, to: int, round_no: int, step: int, budget: int | None) -> Frame:
        """Its message to agent ``to`` this round, within ``budget`` bytes."""
        out = self.end.message(to, round_no, step, budget)
        return Frame(self.agent, to, round_no, step, out.kind, out.payload)

    def take(self, frame: Frame, due: int) -> bool:
        ok = bool(self.end.receive(frame.sender, frame.payload or b"", frame.round, due))
        if ok and self.rover is not None:  # (the lander's node has none)
            self.rover.replan = True
        return ok

    def acked(self, frame: Frame, ok: bool) -> None:
        self.end.delivered(frame.to, frame.round, ok)

    def close(self, round_no: int) -> None:
        """Its round ``round_no`` is over (what reached it is in)."""
        self.end.close_round(round_no)


def team_nodes(sharing: Any, world: Any, topology: Any) -> tuple[list[RoverNode], BaseNode | None,
                                                                  dict[int, PeerNode] | None]:
    """The nodes of one strategy's run in one process: a rover node per rover end (its
    robot in ``world``), the base's node on the star, a peer node per agent on peers."""
    peers = None
    if sharing.peers is not None:
        peers = {a: PeerNode(a, end, None if a == BASE else world.team[a]) for a, end in sharing.peers.items()}
    rovers = [] if sharing.peers is not None else [RoverNode(k, end, world, topology)
                                                   for k, end in enumerate(sharing.rovers)]
    base = None if sharing.base is None else BaseNode(sharing.base)
    return rovers, base, peers


__all__ = ["BaseNode", "PeerNode", "RoverNode", "team_nodes"]
