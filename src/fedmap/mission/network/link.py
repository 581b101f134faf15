"""The seeded radio link between the agents, and its ledger (who talks to whom:
:mod:`fedmap.mission.network.topology`).

Every message is a real payload (``bytes``); the ledger records its length. What happens
to a message, in this order:

1. **Range.** A rover the :class:`~fedmap.mission.network.topology.Topology` says cannot reach the base this step has no
   link: nothing is sent (``out of range``, 0 bytes). The mission's topology is
   :class:`~fedmap.mission.network.topology.StarTopology`: every rover talks to the base directly, within ``max_range``
   cells of it.
2. **Budget.** A payload longer than its budget (the topology's: per direction and round) is not sent
   (``over budget``, 0 bytes); the strategy decides what to send instead, before asking.
3. **Loss.** A sent message is lost with probability ``loss``; the bytes are spent either
   way. The draw for (round, rover, direction) is the first ``random()`` of
   ``numpy.random.default_rng(SeedSequence([seed, round, rover, 0 or 1]))`` (0: uplink,
   1: downlink) compared ``< loss``: independent of every other message, of the strategy
   and of the payload, so every strategy sees the same link.
4. **Latency.** A message that is not lost arrives ``latency`` steps after it was sent.

The sender learns at arrival time whether its message got through (a link-level
acknowledgement, not counted in the bytes).

**Peer topologies** (``[link] topology``). On ``mesh`` and ``leader`` every agent (the
rovers, and the lander as an agent that never moves unless ``lander_agent = false``) can
talk to every other agent within ``peer_range`` cells (:class:`~fedmap.mission.network.topology.MeshTopology`). A peer
message's ledger entry has ``direction = "peer"``, its sender in ``rover`` (:data:`BASE`
for the lander) and its receiver in ``to``; each hop of a relayed message is its own entry.

* **Drops.** Each link (star: rover-base; peer: each pair of agents) is *down* for a whole
  round with probability ``drop``: the first ``random()`` of
  ``default_rng(SeedSequence([seed, round, a + 1, b + 1, 3]))`` with ``a < b`` the two
  agents (:data:`BASE` is -1, so the lander is 0 there) compared ``< drop``. A message on a
  link that is down is not sent (``link down``, 0 bytes). RAMEN's protocol (every link
  dropped independently each round with probability p) is ``drop = p``.
* **Loss** of a peer message (one hop ``a -> b``) is drawn as above from
  ``SeedSequence([seed, round, a + 1, b + 1, 2])`` (directed: ``a`` is the sender).
* **Leaders** (``leader``): at every sync the links that are up split the agents into
  connected groups; each group's leader is the lander when it is in the group, else its
  lowest-numbered rover (:func:`~fedmap.mission.network.topology.elect_leaders`). Members reach their leader along the
  shortest route of links that are up (:func:`~fedmap.mission.network.topology.route`, ties to the lower-numbered agent),
  every hop relayed, costing its bytes, and drawn for loss on its own; latency is per hop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

UP, DOWN, PEER = "up", "down", "peer"
Cell = tuple[int, int]
#: The base station's index among the agents of a :class:`Topology` (rovers are 0, 1, ...).
BASE = -1


@dataclass
class Message:
    """One entry of the ledger."""

    round: int
    step: int  # when it was sent (or would have been)
    rover: int
    direction: str  # "up" or "down"
    kind: str  # what the payload is (e.g. "cells", "update", "keyframe")
    bytes: int  # bytes spent on the link (0 when not sent)
    status: str  # delivered | lost | over budget | out of range | link down | stale | rejected | no sync
    # ("no sync": a rover on its own clock had not reached a sync step since its last report)
    arrival: int | None = None
    to: int | None = None  # peer messages: the receiver (rover index, or BASE); None on the star

    @property
    def sender(self) -> int:
        """Who spent the bytes: the rover on a star uplink or any peer message it sends, else
        the base (:data:`BASE`)."""
        return self.rover if self.direction in (UP, PEER) else BASE

    @property
    def rover_side(self) -> int:
        """The rover whose account the bytes are charged to: the sender, or the receiving rover
        of a message the base (or lander) sent."""
        if self.direction == PEER:
            return self.rover if self.rover != BASE else (self.to if self.to is not None else BASE)
        return self.rover

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class Link:
    """The link of one strategy's run: decides each message's fate and keeps the ledger.

    ``config`` is the mission's :class:`~fedmap.mission.settings.LinkConfig`; ``topology``
    (a :class:`~fedmap.mission.network.topology.Topology`) says who can reach the base.
    """

    def __init__(self, config: Any, topology: Any) -> None:
        self.config = config
        self.topology = topology
        #: the seed of every draw (a link config outside a mission, whose seed is unset, draws from 0)
        self.seed: int = 0 if config.seed is None else int(config.seed)
        self.ledger: list[Message] = []
        #: messages offered on a link that was up (in range, not down), counting every hop:
        #: the denominator of "bytes per link per round"
        self.slots = 0

    def lost(self, round_no: int, rover: int, direction: str) -> bool:
        """The seeded loss draw of one message (see the module docstring)."""
        if self.config.loss <= 0:
            return False
        d = 0 if direction == UP else 1
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, round_no, rover, d]))
        return bool(rng.random() < self.config.loss)

    def down(self, round_no: int, a: int, b: int, step: int | None = None) -> bool:
        """Whether the link between agents ``a`` and ``b`` is down for this round: a link of the
        lander at a ``step`` inside ``lander_cut``, or the seeded draw (module docstring)."""
        cut = self.config.lander_cut
        if cut is not None and step is not None and BASE in (a, b) and cut[0] <= step < cut[1]:
            return True
        if self.config.drop <= 0:
            return False
        lo, hi = sorted((a, b))
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, round_no, lo + 1, hi + 1, 3]))
        return bool(rng.random() < self.config.drop)

    def lost_hop(self, round_no: int, a: int, b: int) -> bool:
        """The seeded loss draw of one peer message (one hop) from ``a`` to ``b``."""
        if self.config.loss <= 0:
            return False
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, round_no, a + 1, b + 1, 2]))
        return bool(rng.random() < self.config.loss)

    def send_route(self, payload: bytes | None, path: Sequence[int], *, round_no: int, step: int, kind: str,
                   budget: int | None) -> Message:
        """Offer a peer message along ``path`` (``[sender, relays..., receiver]``, over links
        that are up): one ledger entry per hop, each hop drawn for loss, ``latency`` steps per
        hop. Returns the last hop's entry (``arrival`` set when the receiver got it)."""
        if payload is None or (budget is not None and len(payload) > budget):
            msg = Message(round_no, step, path[0], PEER, kind, 0, "over budget", to=path[-1])
            self.ledger.append(msg)
            self.slots += 1
            return msg
        t = step
        for a, b in zip(path, path[1:]):
            self.slots += 1
            if self.lost_hop(round_no, a, b):
                msg = Message(round_no, t, a, PEER, kind, len(payload), "lost", to=b)
                self.ledger.append(msg)
                return msg
            msg = Message(round_no, t, a, PEER, kind, len(payload), "delivered", t + self.config.latency, to=b)
            self.ledger.append(msg)
            t += self.config.latency
        return msg

    def send(self, payload: bytes | None, *, round_no: int, step: int, rover: int, direction: str, kind: str,
             positions: Sequence[Cell], budget: int | None = None) -> Message:
        """Offer one message between rover ``rover`` and the base; returns its ledger entry
        (``status`` says its fate).

        ``positions`` are every rover's cells now (the topology decides the range from
        them); ``budget`` is the message's budget (the topology's, None: unlimited);
        ``payload=None`` records a message the strategy could not fit into the budget.
        """
        if not self.topology.reachable(positions)[rover]:
            msg = Message(round_no, step, rover, direction, kind, 0, "out of range")
        elif self.down(round_no, rover, BASE, step):
            msg = Message(round_no, step, rover, direction, kind, 0, "link down")
        elif payload is None or (budget is not None and len(payload) > budget):
            msg = Message(round_no, step, rover, direction, kind, 0, "over budget")
        elif self.lost(round_no, rover, direction):
            msg = Message(round_no, step, rover, direction, kind, len(payload), "lost")
        else:
            msg = Message(round_no, step, rover, direction, kind, len(payload), "delivered",
                          step + self.config.latency)
        if msg.status != "out of range" and msg.status != "link down":
            self.slots += 1
        self.ledger.append(msg)
        return msg
