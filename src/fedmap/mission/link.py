"""The seeded radio link between the rovers and the base station, and its ledger.

Every message is a real payload (``bytes``); the ledger records its length. What happens
to a message, in this order:

1. **Range.** A rover farther than ``max_range`` cells from the base has no link: nothing
   is sent (``out of range``, 0 bytes).
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
from dataclasses import dataclass

import numpy as np

from fedmap.mission.settings import LinkConfig

UP, DOWN = "up", "down"


@dataclass
class Message:
    """One entry of the ledger."""

    round: int
    step: int  # when it was sent (or would have been)
    rover: int
    direction: str  # "up" or "down"
    kind: str  # what the payload is (e.g. "cells", "update", "keyframe")
    bytes: int  # bytes spent on the link (0 when not sent)
    status: str  # delivered | lost | over budget | out of range | stale
    arrival: int | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class Link:
    """The link of one strategy's run: decides each message's fate and keeps the ledger."""

    def __init__(self, config: LinkConfig, base: tuple[int, int]) -> None:
        self.config = config
        self.base = base
        self.ledger: list[Message] = []

    def lost(self, round_no: int, rover: int, direction: str) -> bool:
        """The seeded loss draw of one message (see the module docstring)."""
        if self.config.loss <= 0:
            return False
        d = 0 if direction == UP else 1
        rng = np.random.default_rng(np.random.SeedSequence([self.config.seed, round_no, rover, d]))
        return bool(rng.random() < self.config.loss)

    def in_range(self, pos: tuple[int, int]) -> bool:
        r = self.config.max_range
        return r is None or math.hypot(pos[0] - self.base[0], pos[1] - self.base[1]) <= r + 1e-9

    def budget(self, direction: str) -> int | None:
        return self.config.uplink_bytes if direction == UP else self.config.downlink_bytes

    def fits(self, n_bytes: int, direction: str) -> bool:
        b = self.budget(direction)
        return b is None or n_bytes <= b

    def send(self, payload: bytes | None, *, round_no: int, step: int, rover: int, direction: str, kind: str,
             pos: tuple[int, int]) -> Message:
        """Offer one message to the link; returns its ledger entry (``status`` says its fate).

        ``payload=None`` records a message the strategy could not fit into the budget.
        """
        if not self.in_range(pos):
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
