"""The one registry of sharing strategies: a name, its ends, the topologies it runs on and
its options.

Each :class:`StrategySpec` says how to build the strategy's ends for one run: ``star``
builds a rover end per rover and a base end (a topology with a base station), ``peer`` a
peer end per agent (any topology; on the star the base station is an agent). A strategy
with only ``peer`` runs as peers on the star too; one with only ``star`` needs the star.
``raw`` has both, so it is lossless merging at the base on the star and gossip of cells
on a mesh: that is decided here, in :func:`build`, and nowhere else.

Adding a strategy is writing its ends (:mod:`fedmap.mission.ends.protocol`) and one entry of
:data:`REGISTRY`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from fedmap.coding.streamcodec import LEAST_BYTES
from fedmap.config import method_config
from fedmap.federation.runner import init_held
from fedmap.maps.ros import lower_left_origin
from fedmap.mission.ends.framed import framed_predictive, framed_raw
from fedmap.mission.ends.gossip import AdmmPeer, GossipPeer
from fedmap.mission.ends.model import MISSION_DEFAULTS, ModelBase, ModelRover, Training, model_lags
from fedmap.mission.ends.predictive import PredictiveBase, PredictiveOptions, PredictiveRover
from fedmap.mission.ends.protocol import DOWN_HEADER, UP_HEADER, BaseEnd, Journal, PeerEnd, RoverEnd
from fedmap.mission.ends.raw import CentralBase, CentralRover, RawBase, RawPeer, RawRover
from fedmap.mission.ends.rosgrid import ZLIB_LEVEL, GridCodec, RosgridBase, RosgridRover
from fedmap.mission.ends.sharing import Factory, Setup, Sharing
from fedmap.mission.network.link import BASE
from fedmap.pipeline import initial_weights


@dataclass(frozen=True)
class StrategySpec:
    """A strategy of :data:`REGISTRY`."""

    name: str
    help: str
    star: Factory | None = None  #: its ends with a base station
    peer: Factory | None = None  #: its ends as peers
    options: type | None = None  #: the dataclass of ``[strategies.<name>]`` (declared through ``_schema``)
    trains: bool = False  #: ``[strategies.<name>]`` takes :func:`fedmap.config.method_config` keywords
    on_link: bool = True  #: it sends anything at all (``none`` and the ``central`` oracle do not)
    default: bool = False  #: run unless told otherwise, on the star
    peer_default: bool = False  #: run unless told otherwise, on a peer topology
    #: the bytes every uplink and every downlink of it carries at the least (its headers): a
    #: star budget below them can never carry a message (the mission config refuses it)
    least: tuple[int, int] = (UP_HEADER, DOWN_HEADER)
    #: its rover ends hold only their own rover, so each can run in a process of its own
    #: (``central`` pools every rover's observations at once: a reference, not a protocol)
    deployable: bool = False
    #: its peer ends hold only their own agent, so each agent of a peer mission can run in a
    #: process of its own (:mod:`fedmap.mission.network.peers`)
    peer_deployable: bool = False
    #: it runs with ``[frames]`` (rovers that do not know their poses, :mod:`fedmap.mission.world.frames`)
    framed: bool = False
    #: its ends with ``[frames]`` (None: its own ends, each rover keeping its own frame)
    framed_ends: Factory | None = None
    #: what the report makes of it: ``"protocol"`` (a way of sharing, a candidate of the verdict),
    #: ``"baseline"`` (sharing nothing: what the bytes of the others bought is measured above it)
    #: or ``"reference"`` (an oracle shown beside the others, never a candidate)
    role: str = "protocol"

    def factory(self, topology: Any) -> Factory | None:
        """Its factory on ``topology`` (:class:`~fedmap.mission.network.topology.Topology`): the
        star ends where there is a base station and it has them, else its peer ends."""
        return (self.star or self.peer) if topology.has_base else self.peer


def _journal_with_updates() -> Journal:
    return Journal(dropped=[], lags=[])


def _none(s: Setup) -> Sharing:
    rovers = [RoverEnd(k, r, s.starts) for k, r in enumerate(s.team)]
    return Sharing(s.name, s.team, rovers, BaseEnd(s.truth.shape, s.starts), journal=s.journal)


def _central(s: Setup) -> Sharing:
    rovers: list[RoverEnd] = [CentralRover(k, r, s.starts, team=s.team) for k, r in enumerate(s.team)]
    base = CentralBase(s.truth.shape, s.starts, team=s.team)
    return Sharing(s.name, s.team, rovers, base, journal=s.journal)


def _height_q(s: Setup) -> float | None:
    return s.config.elevation_q_m if "elevation" in s.config.layers else None


def _raw_star(s: Setup) -> Sharing:
    lc, q = s.config.link, _height_q(s)
    rovers = [RawRover(k, r, s.starts, budget=lc.uplink_bytes, height_q=q) for k, r in enumerate(s.team)]
    base = RawBase(s.truth.shape, s.starts, budget=lc.downlink_bytes, height_q=q, journal=s.journal)
    return Sharing(s.name, s.team, rovers, base, journal=s.journal)


def _peers(s: Setup, make: Callable[[int, Any, tuple[int, ...]], PeerEnd]) -> Sharing:
    agents = s.topology.peer_agents(len(s.team))
    peers = {a: make(a, None if a == BASE else s.team[a], agents) for a in agents}
    return Sharing(s.name, s.team, [peers[k] for k in range(len(s.team))], peers=peers, journal=s.journal)


def _raw_peer(s: Setup) -> Sharing:
    return _peers(s, lambda a, r, agents: RawPeer(a, r, s.truth.shape, s.starts, agents=agents, journal=s.journal))


def _predictive(s: Setup) -> Sharing:
    lc, radius = s.config.link, s.config.sensor_radius
    opts = PredictiveOptions(**s.options)
    rovers = [PredictiveRover(k, r, s.starts, budget=lc.uplink_bytes, radius=radius, options=opts)
              for k, r in enumerate(s.team)]
    base = PredictiveBase(s.truth.shape, s.starts, budget=lc.downlink_bytes, radius=radius, options=opts)
    return Sharing(s.name, s.team, rovers, base, journal=s.journal)


def _rosgrid(level: int | None) -> Factory:
    def build(s: Setup) -> Sharing:
        lc = s.config.link
        grids = GridCodec(s.truth.shape, resolution=s.truth.pixel_size, origin=lower_left_origin(s.truth),
                          sync_every=s.config.sync_every, level=level)
        rovers = [RosgridRover(k, r, s.starts, grids=grids, budget=lc.uplink_bytes) for k, r in enumerate(s.team)]
        base = RosgridBase(s.truth.shape, s.starts, grids=grids, budget=lc.downlink_bytes, journal=s.journal)
        return Sharing(s.name, s.team, rovers, base, journal=s.journal)
    return build


def _preset(s: Setup, method: str):
    pc = method_config(method, **{**MISSION_DEFAULTS.get(method, {}), **s.options, "seed": s.config.seed})
    return pc, init_held(initial_weights(pc, s.truth.shape[0]))


def _model(s: Setup) -> Sharing:
    c, lc = s.config, s.config.link
    s.journal = _journal_with_updates()
    pc, init = _preset(s, s.name)
    training = Training(c.train_on, c.replay, c.seed)
    rovers = [ModelRover(k, r, s.starts, truth=s.truth, pc=pc, init=init, budget=lc.uplink_bytes,
                         training=training, journal=s.journal) for k, r in enumerate(s.team)]
    base = ModelBase(s.truth.shape, s.starts, pc=pc, init=init, budget=lc.downlink_bytes, journal=s.journal)
    lags = s.journal.lags
    assert lags is not None
    sharing = Sharing(s.name, s.team, rovers, base, journal=s.journal)

    def on_sync(round_no: int) -> None:  # the rover ends the run holds (stand-ins for rovers elsewhere)
        lags.append({"round": round_no, "lag": model_lags(base, sharing.rovers)})

    sharing.on_sync = on_sync
    return sharing


def _gossip(cls: type[GossipPeer]) -> Factory:
    def build(s: Setup) -> Sharing:
        pc, init = _preset(s, "fedmap")  # the fedmap preset's network, trained as [strategies.<name>] says
        return _peers(s, lambda a, r, agents: cls(a, r, s.truth.shape, s.starts, truth=s.truth, pc=pc, init=init,
                                                  agents=agents, journal=s.journal))
    return build


#: Every sharing strategy, from the lower bound to the upper bound.
REGISTRY: dict[str, StrategySpec] = {spec.name: spec for spec in (
    StrategySpec("none", "nothing is sent: a rover's belief is its own observations", star=_none, peer=_none,
                 on_link=False, default=True, peer_default=True, deployable=True, framed=True, role="baseline"),
    StrategySpec("raw", "observed cells, lossless (context codec): merged at the base on the star, gossiped on "
                 "peers", star=_raw_star, peer=_raw_peer, default=True, peer_default=True, deployable=True,
                 peer_deployable=True,
                 framed=True, framed_ends=framed_raw),
    StrategySpec("predictive", "new cells, lossless, with a learned probability model both ends keep",
                 star=_predictive, options=PredictiveOptions, default=True,
                 least=(LEAST_BYTES, LEAST_BYTES), deployable=True, framed=True, framed_ends=framed_predictive),
    StrategySpec("rosgrid", "what a ROS 2 team sends: every rover's whole map as a nav_msgs/OccupancyGrid (CDR), "
                 "merged as map_merge does, the whole merged grid back", star=_rosgrid(None), deployable=True),
    StrategySpec("rosgrid-zlib", f"rosgrid with every serialised grid compressed by zlib (level {ZLIB_LEVEL})",
                 star=_rosgrid(ZLIB_LEVEL), deployable=True),
    StrategySpec("paper", "the source paper's Fourier MLP, FedAvg", star=_model, trains=True, deployable=True),
    StrategySpec("fedmap", "fedmap's feature grids, coverage-aware FedAvg", star=_model, trains=True, default=True,
                 deployable=True),
    StrategySpec("gossip", "fedmap's network averaged peer to peer (Metropolis weights)", peer=_gossip(GossipPeer),
                 trains=True, peer_default=True, peer_deployable=True),
    StrategySpec("admm", "fedmap's network by DiNNO's decentralised C-ADMM", peer=_gossip(AdmmPeer), trains=True,
                 peer_deployable=True),
    StrategySpec("central", "every observation pooled at once, free (a reference, not a bound)", star=_central,
                 peer=_central, on_link=False, default=True, peer_default=True, role="reference"),
)}


def role_of(name: str) -> str:
    """``name``'s :attr:`StrategySpec.role` (a name the registry does not hold is a protocol)."""
    spec = REGISTRY.get(name)
    return spec.role if spec is not None else "protocol"


def names_that(capability: str) -> tuple[str, ...]:
    """The strategies whose spec has ``capability`` (``"deployable"``, ``"framed"``, ``"trains"``), in registry order."""
    return tuple(n for n, s in REGISTRY.items() if getattr(s, capability))


def build(name: str, setup: Setup) -> Sharing:
    """The ends of strategy ``name`` for one run on ``setup``'s topology."""
    spec = REGISTRY[name]
    make = spec.factory(setup.topology)
    if setup.config.frames.enabled and spec.framed_ends is not None:
        make = spec.framed_ends
    assert make is not None, f"{name} does not run on this topology (the config check refuses it)"
    sharing = make(replace(setup, name=name))
    sharing.on_link = spec.on_link
    return sharing


__all__ = ["REGISTRY", "Factory", "Setup", "Sharing", "StrategySpec", "build", "names_that", "role_of"]
