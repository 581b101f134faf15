"""What a strategy's ends are built from (:class:`Setup`) and what one run holds of them
(:class:`Sharing`): the types every builder of ends speaks, the registry's
(:mod:`fedmap.mission.ends.registry`) and the framed ends."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.mission.ends.protocol import BaseEnd, Cell, Journal, PeerEnd
from fedmap.mission.network.link import BASE


@dataclass
class Setup:
    """What a strategy's ends are built from: the mission (``config``, a
    :class:`~fedmap.mission.settings.MissionConfig`), the truth's grid, the team (each
    rover end gets its own rover), every start, and the topology's agents and budgets."""

    config: Any
    truth: GridMap
    team: list
    topology: Any
    journal: Journal = field(default_factory=Journal)
    name: str = ""  #: the strategy being built (:func:`build` sets it)

    @property
    def starts(self) -> list[Cell]:
        return [r.pos for r in self.team]

    @property
    def options(self) -> dict:
        """The ``[strategies.<name>]`` settings of the strategy being built."""
        return dict(self.config.methods.get(self.name, {}))


@dataclass
class Sharing:
    """One strategy's ends in one run, as the simulator holds them.

    ``rovers`` are the ends the team's members plan with (rover ends, or the rovers' peer
    ends), ``base`` the base station's end (None on peers), ``peers`` every agent's peer end
    (None on the star), ``on_link`` whether it sends anything at all (``none`` and the
    ``central`` oracle do not).
    """

    name: str
    team: list
    rovers: list
    base: BaseEnd | None = None
    peers: dict[int, PeerEnd] | None = None
    on_link: bool = True
    journal: Journal = field(default_factory=Journal)
    #: called at every sync before the nodes' own (a record the run keeps, e.g. model lags)
    on_sync: Callable[[int], None] | None = None

    def belief(self, k: int) -> np.ndarray:
        return self.rovers[k].belief()

    def global_map(self) -> np.ndarray:
        """The base station's map; on peers the lander's, or without one the cells every
        rover's belief holds with the same class."""
        if self.base is not None:
            return self.base.global_map()
        assert self.peers is not None
        if BASE in self.peers:
            return self.peers[BASE].belief()
        return agreed([r.belief() for r in self.rovers])

    def global_heights(self) -> np.ndarray | None:
        return self.base.global_heights() if self.base is not None else None


Factory = Callable[[Setup], Sharing]


def agreed(beliefs: list[np.ndarray]) -> np.ndarray:
    """The cells every one of ``beliefs`` holds with the same class (the others UNKNOWN): a
    peer team's map without a lander."""
    agree = np.all([b == beliefs[0] for b in beliefs[1:]], axis=0) if len(beliefs) > 1 else \
        np.ones(beliefs[0].shape, bool)
    return np.where(agree, beliefs[0], UNKNOWN).astype(np.uint8)


__all__ = ["Factory", "Setup", "Sharing", "agreed"]
