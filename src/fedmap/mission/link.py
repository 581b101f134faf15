"""The seeded radio link between the rovers and the base station, its topology, and its ledger.

Every message is a real payload (``bytes``); the ledger records its length. What happens
to a message, in this order:

1. **Range.** A rover the :class:`Topology` says cannot reach the base this step has no
   link: nothing is sent (``out of range``, 0 bytes). The mission's topology is
   :class:`StarTopology`: every rover talks to the base directly, within ``max_range``
   cells of it.
2. **Budget.** A payload longer than the direction's per-round budget is not sent
   (``over budget``, 0 bytes); the strategy decides what to send instead, before asking.
3. **Loss.** A sent message is lost with probability ``loss``; the bytes are spent either
   way. The draw for (round, rover, direction) is the first ``random()`` of
   ``numpy.random.default_rng(SeedSequence([seed, round, rover, 0 or 1]))`` (0: uplink,
   1: downlink) compared ``< loss``: independent of every other message, of the strategy
   and of the payload, so every strategy sees the same link.
4. **Latency.** A message that is not lost arrives ``latency`` steps after it was sent.

The sender learns at arrival time whether its message got through (a link-level
acknowledgement, not counted in the bytes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from fedmap.mission.settings import LinkConfig

UP, DOWN = "up", "down"
Cell = tuple[int, int]
#: The base station's index among the agents of a :class:`Topology` (rovers are 0, 1, ...).
BASE = -1
#: Slack on ``max_range`` (cells), so a rover exactly at the range is in range despite rounding.
RANGE_SLACK = 1e-9


class Topology(Protocol):
    """Who can talk to whom this step, from the rovers' positions (cells, team order).

    The link asks it whether a rover's message can reach the base; the mission asks it
    where a rover may go and still reach the base (``stay_in_range``). :class:`StarTopology`
    (every rover talks only to the base, within range of it) is the mission's one
    implementation. A mesh topology (rovers relay for each other, peer to peer, within
    range of each other) or a leader topology (an elected rover relays the team's traffic)
    would be another implementation of this protocol: the link, strategies and mission
    loop only ask it, and compute no reachability themselves.
    """

    def neighbours(self, agent: int, positions: Sequence[Cell]) -> tuple[int, ...]:
        """The agents ``agent`` talks to directly this step (rover indices, or :data:`BASE`)."""
        ...

    def reachable(self, positions: Sequence[Cell]) -> tuple[bool, ...]:
        """For every rover (team order): can its messages reach the base this step?"""
        ...

    def region(self, shape: tuple[int, int]) -> np.ndarray | None:
        """The cells from which a rover reaches the base whatever the others do (boolean map
        of ``shape``), or None where there is no such limit."""
        ...


@dataclass(frozen=True)
class StarTopology:
    """Every rover talks only to the base station at ``base``, when it is within
    ``max_range`` cells of it (Euclidean, in cells; None: no limit). Rovers never talk to
    each other."""

    base: Cell
    max_range: float | None = None

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


@dataclass
class Message:
    """One entry of the ledger."""

    round: int
    step: int  # when it was sent (or would have been)
    rover: int
    direction: str  # "up" or "down"
    kind: str  # what the payload is (e.g. "cells", "update", "keyframe")
    bytes: int  # bytes spent on the link (0 when not sent)
    status: str  # delivered | lost | over budget | out of range | stale | rejected
    arrival: int | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class Link:
    """The link of one strategy's run: decides each message's fate and keeps the ledger.

    ``topology`` says who can reach the base (the mission's: :class:`StarTopology` at the
    base station, with the config's ``max_range``).
    """

    def __init__(self, config: LinkConfig, topology: Topology) -> None:
        self.config = config
        self.topology = topology
        self.ledger: list[Message] = []

    def lost(self, round_no: int, rover: int, direction: str) -> bool:
        """The seeded loss draw of one message (see the module docstring)."""
        if self.config.loss <= 0:
            return False
        d = 0 if direction == UP else 1
        rng = np.random.default_rng(np.random.SeedSequence([self.config.seed, round_no, rover, d]))
        return bool(rng.random() < self.config.loss)

    def budget(self, direction: str) -> int | None:
        return self.config.uplink_bytes if direction == UP else self.config.downlink_bytes

    def fits(self, n_bytes: int, direction: str) -> bool:
        b = self.budget(direction)
        return b is None or n_bytes <= b

    def send(self, payload: bytes | None, *, round_no: int, step: int, rover: int, direction: str, kind: str,
             positions: Sequence[Cell]) -> Message:
        """Offer one message to the link; returns its ledger entry (``status`` says its fate).

        ``positions`` are every rover's cells now (the topology decides the range from
        them); ``payload=None`` records a message the strategy could not fit into the budget.
        """
        if not self.topology.reachable(positions)[rover]:
            msg = Message(round_no, step, rover, direction, kind, 0, "out of range")
        elif payload is None or not self.fits(len(payload), direction):
            msg = Message(round_no, step, rover, direction, kind, 0, "over budget")
        elif self.lost(round_no, rover, direction):
            msg = Message(round_no, step, rover, direction, kind, len(payload), "lost")
        else:
            msg = Message(round_no, step, rover, direction, kind, len(payload), "delivered",
                          step + self.config.latency)
        self.ledger.append(msg)
        return msg
