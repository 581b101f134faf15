"""What a mission is: :class:`MissionConfig` (team, time, sensing, planning, strategies) and
:class:`LinkConfig` (the seeded radio link), and the TOML file that sets them.

TOML layout (every key optional)::

    seed = 0
    [terrain]      # exactly as `fedmap run` (builtin | dem | map | tiles), see fedmap.config
    [thresholds]   # exactly as `fedmap run`
    [mission]      # MissionConfig: rovers, steps, sync_every, speed, sensor_radius, ...
    [link]         # LinkConfig: uplink_bytes, downlink_bytes, loss, latency, max_range, seed
    [prior]        # PriorConfig: kind (none | orbital), factor
    [helicopter]   # HelicopterConfig: speed, sensor_radius, resolution, flight_budget, recharge
    [frames]       # FramesConfig: unknown start poses and odometry drift (fedmap.mission.world.frames)
    [strategies.fedmap]   # method_config keywords for a model strategy, e.g. epochs = 30
    [strategies.paper]
    [strategies.predictive]  # the coder's parts (PREDICTIVE_OPTIONS), e.g. prior = "none"

The terrain sections go through :mod:`fedmap.config` (the one builder), so a mission
reads the same terrain sources, with the same checks, as ``fedmap run``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

from fedmap import _schema
from fedmap._schema import setting, wiring
from fedmap._util import check_keys, suggest
from fedmap.config import (
    KEYWORDS,
    base_defaults,
    dumps_toml,
    merge,
    parse_set,
    read_toml,
    terrain_source,
    used_thresholds,
    validate,
    with_rover_profile,
)
from fedmap.errors import FedmapError
from fedmap.maps.grid import LAYERS, check_layers
from fedmap.maps.sources import TerrainSource, needs_dem
from fedmap.maps.traversability import ROVER_NAMES
from fedmap.mission.ends.registry import REGISTRY
from fedmap.mission.network.topology import TOPOLOGIES as TOPOLOGY_CLASSES

#: Every sharing strategy, from the lower bound to the upper bound (:data:`~fedmap.mission.ends.registry.REGISTRY`).
STRATEGIES: tuple[str, ...] = tuple(REGISTRY)
#: The strategies a mission runs unless told otherwise (``paper`` is slow: an option).
DEFAULT_STRATEGIES: tuple[str, ...] = tuple(n for n, s in REGISTRY.items() if s.default)
#: The strategies that run on every topology (``[link] topology``); the others need the
#: base station of the ``star`` topology.
PEER_STRATEGIES: tuple[str, ...] = tuple(n for n, s in REGISTRY.items() if s.peer is not None)
#: The strategies a peer topology runs unless told otherwise (``admm`` is an option).
PEER_DEFAULTS: tuple[str, ...] = tuple(n for n, s in REGISTRY.items() if s.peer_default)
#: A rover's own traversability profile: the shared ``[thresholds]`` (``team``) or a named rover.
PROFILES: tuple[str, ...] = ("team", *ROVER_NAMES)
#: Who talks to whom (:mod:`fedmap.mission.network.topology`).
TOPOLOGIES: tuple[str, ...] = tuple(TOPOLOGY_CLASSES)
MODES: tuple[str, ...] = ("frontier", "waypoints")
#: What a model strategy's rover trains on at a sync (``[mission] train_on``).
TRAIN_ON: tuple[str, ...] = ("map", "changed")
#: What rovers plan with beside their maps (``[mission] predictor``): nothing, or the shipped
#: map predictor's guesses (:mod:`fedmap.nets.predictor`).
PREDICTORS: tuple[str, ...] = ("none", "learned")
def check_strategies(names) -> tuple[str, ...]:
    """``names`` as a tuple of known strategies (one-line error with a suggestion otherwise)."""
    names = tuple(names)
    if not names:
        raise FedmapError("a mission needs at least one strategy")
    for s in names:
        if s not in STRATEGIES:
            raise FedmapError(f"unknown strategy {s!r}{suggest(s, STRATEGIES)}")
    if len(set(names)) != len(names):
        raise FedmapError(f"a strategy is listed twice: {', '.join(names)}")
    return names


def check_strategy_options(name: str, options: dict) -> None:
    """Check ``[strategies.<name>]``: the registry says what a strategy takes (its options
    dataclass, or :func:`fedmap.config.method_config` keywords for one that trains)."""
    spec = REGISTRY.get(name)
    where = f"[strategies.{name}]"
    if spec is not None and spec.options is not None:
        _schema.check_table(spec.options, options, "the mission settings", section=f"strategies.{name}")
        spec.options(**options)  # its own checks of the values
    elif spec is not None and spec.trains:
        check_keys(options, KEYWORDS, where)
    else:
        takes = [*(n for n, s in REGISTRY.items() if s.trains), *(n for n, s in REGISTRY.items() if s.options)]
        raise FedmapError(f"{where}: only {', '.join(takes)} take settings")


def _cell(value, what: str) -> tuple[int, int]:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        raise FedmapError(f"{what} must be a [row, col] pair of integers, got {value!r}")
    return int(value[0]), int(value[1])


@dataclass(frozen=True)
class LinkConfig:
    """The radio link between each rover and the base station, seeded.

    Parameters
    ----------
    uplink_bytes, downlink_bytes : int or None
        Budget per rover per sync round (None: unlimited). A payload over budget is not
        sent (see :mod:`fedmap.mission.ends.registry` and each strategy's ends for what it does instead).
    loss : float
        Probability that a message is lost, drawn independently per (round, rover,
        direction) from ``seed`` (:meth:`fedmap.mission.network.link.Link.lost`).
    latency : int
        Steps between sending and arrival, both ways.
    max_range : float or None
        Cells (Euclidean) from the base station beyond which a rover has no link.
    seed : int or None
        The link's own seed (the loss draws); None: the mission's ``seed``, so that
        ``--seed`` changes the losses too.
    """

    uplink_bytes: int | None = setting(None, help="Uplink budget per rover per sync round, bytes (unset: unlimited)")
    downlink_bytes: int | None = setting(None, help="Downlink budget per rover per sync round, bytes (unset: "
                                         "unlimited)")
    loss: float = setting(0.1, help="Probability that a message is lost")
    latency: int = setting(0, help="Steps a message takes, each way")
    max_range: float | None = setting(None, help="Link range from the base station, cells (unset: unlimited)")
    seed: int | None = setting(None, help="The link's own seed (its loss draws; unset: the mission's seed)",
                               cli="--link-seed")
    topology: str = setting("star", help="star: every rover talks to the base; mesh: agents within peer_range talk "
                            "peer to peer; leader: each connected group elects a leader that plays the base",
                            choices=TOPOLOGIES, cli="--topology")
    peer_range: float | None = setting(None, help="mesh, leader: range of a peer link, cells (unset: unlimited)")
    peer_bytes: int | None = setting(None, help="mesh: budget per link per direction per round, bytes (unset: "
                                     "unlimited)")
    drop: float = setting(0.0, help="Probability that a link is down for a whole round, drawn per link and round",
                          cli="--drop")
    lander_cut: tuple[int, int] | None = setting(None, help="[from, to): steps during which every link of the "
                                                 "lander (base station) is down (unset: none)")
    lander_agent: bool = setting(True, help="mesh, leader: the lander takes part as an agent that never moves "
                                 "(false: a team without a base station)", cli="--lander-agent/--no-lander-agent")

    def __post_init__(self) -> None:
        if self.topology not in TOPOLOGIES:
            raise FedmapError(f"unknown topology {self.topology!r}{suggest(self.topology, TOPOLOGIES)}")
        if not (isinstance(self.drop, (int, float)) and not isinstance(self.drop, bool) and 0.0 <= self.drop < 1.0):
            raise FedmapError(f"link drop must be a probability in [0, 1), got {self.drop!r}")
        if self.peer_range is not None and not (math.isfinite(self.peer_range) and self.peer_range > 0):
            raise FedmapError(f"link peer_range must be a positive number of cells (or unset), got {self.peer_range!r}")
        if self.lander_cut is not None:
            cut = self.lander_cut
            if (not isinstance(cut, (list, tuple)) or len(cut) != 2
                    or not all(isinstance(v, int) and not isinstance(v, bool) for v in cut) or not 0 <= cut[0] < cut[1]):
                raise FedmapError(f"link lander_cut must be [from, to) steps with 0 <= from < to, got {cut!r}")
            object.__setattr__(self, "lander_cut", (int(cut[0]), int(cut[1])))
        for name in ("uplink_bytes", "downlink_bytes", "peer_bytes"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
                raise FedmapError(f"link {name} must be a non-negative number of bytes (or unset), got {v!r}")
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise FedmapError(f"link seed must be a whole number (or unset: the mission's seed), got {self.seed!r}")
        if not (isinstance(self.loss, (int, float)) and 0.0 <= self.loss <= 1.0):
            raise FedmapError(f"link loss must be a probability in [0, 1], got {self.loss!r}")
        if isinstance(self.latency, bool) or not isinstance(self.latency, int) or self.latency < 0:
            raise FedmapError(f"link latency must be a non-negative number of steps, got {self.latency!r}")
        if self.max_range is not None and not (math.isfinite(self.max_range) and self.max_range > 0):
            raise FedmapError(f"link max_range must be a positive number of cells (or unset), got {self.max_range!r}")

    def to_dict(self) -> dict:
        return asdict(self)


PRIOR_KINDS: tuple[str, ...] = ("none", "orbital")


@dataclass(frozen=True)
class PriorConfig:
    """What every agent and the base know before the mission (``[prior]``).

    ``orbital``: the site's DEM block-averaged ``factor`` times and classified at that
    resolution (:func:`fedmap.maps.orbital.orbital_prior`), as an orbiter would map it.
    Every rover and the base hold it before the mission starts; it is never sent, so it
    costs no bytes on the link. Rovers plan their paths on it where they have no
    observation (a prior IMPASSABLE cell is avoided, unless no path exists otherwise); it
    is never an observation: beliefs, coverage, sharing and target choice ignore it.
    """

    kind: str = setting("none", help="none, or orbital: the DEM block-averaged factor times, for planning",
                        choices=PRIOR_KINDS, cli="--prior")
    factor: int = setting(8, help="How many times coarser the orbital prior is than the map", cli="--prior-factor")

    def __post_init__(self) -> None:
        if self.kind not in PRIOR_KINDS:
            raise FedmapError(f"unknown prior kind {self.kind!r}{suggest(self.kind, PRIOR_KINDS)}")
        if isinstance(self.factor, bool) or not isinstance(self.factor, int) or self.factor < 2:
            raise FedmapError(f"prior factor must be an integer >= 2, got {self.factor!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class HelicopterConfig:
    """The helicopters of a team (``[helicopter]``; how many: ``[mission] helicopters``).

    A helicopter starts at the lander and flies over any terrain, ``speed`` cells a step
    (8-connected moves). From every cell it enters it sees the blocks of ``resolution`` x
    ``resolution`` cells whose centre is within ``sensor_radius`` cells, coarsely: a block
    whose cells are all of one class is observed as that class, a mixed block stays unknown
    (its coarse camera cannot resolve it); the cells it observes are marked as coarse. A
    sortie lasts at most ``flight_budget`` steps in the air; it then must be on a landing
    site (the lander, or a cell it observed free), where it stays ``recharge`` steps.
    """

    speed: int = setting(6, help="Cells flown per step", cli="--heli-speed")
    sensor_radius: float = setting(16.0, help="Footprint radius, cells", cli="--heli-radius")
    resolution: int = setting(4, help="How many times coarser than the map it sees (block side, cells)",
                              cli="--heli-resolution")
    flight_budget: int = setting(30, help="Steps in the air per sortie", cli="--heli-flight-budget")
    recharge: int = setting(20, help="Steps on the ground between sorties", cli="--heli-recharge")

    def __post_init__(self) -> None:
        for name, low in (("speed", 1), ("resolution", 1), ("flight_budget", 2), ("recharge", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise FedmapError(f"helicopter {name} must be an integer >= {low}, got {v!r}")
        if not (math.isfinite(self.sensor_radius) and self.sensor_radius >= 1.5):
            raise FedmapError(f"helicopter sensor_radius must be >= 1.5 cells, got {self.sensor_radius!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FramesConfig:
    """Rovers that do not know their poses exactly (``[frames]``; :mod:`fedmap.mission.world.frames`).

    Each rover's start pose is off by a seeded draw (an offset of ``start_offset`` cells std
    per axis, a heading of ``start_heading`` degrees std), and its odometry drifts as it
    drives: a scale error of ``drift`` std (0.02: 2 % of the distance) and a heading drift
    of ``heading_drift`` degrees std per metre, each drawn once per rover. A rover maps in
    the frame its estimated pose implies; ``raw`` and ``predictive`` on the star, and ``raw``
    gossip on the mesh, then merge through registration (:mod:`fedmap.maps.registration`).
    ``lander_view``: the lander imaged the ground within this many cells of itself at
    landing, in its own (the true) frame; the base (on the mesh, the lander) registers rovers
    on that image too, but never merges or shares it. All zero (the
    default): known poses, the mission as without this table.
    """

    start_offset: float = setting(0.0, help="Std of each rover's start offset per axis, cells (0: known)",
                                  cli="--frames-offset")
    start_heading: float = setting(0.0, help="Std of each rover's start heading error, degrees (0: known)",
                                   cli="--frames-heading")
    drift: float = setting(0.0, help="Std of each rover's odometry scale error (0.02: 2 percent of the distance driven)",
                           cli="--frames-drift")
    heading_drift: float = setting(0.0, help="Std of each rover's heading drift, degrees per metre driven",
                                   cli="--frames-heading-drift")
    lander_view: float = setting(0.0, help="Radius the lander imaged around itself at landing, cells: the base "
                                 "registers on it, never merges it (0: the first rover's frame is the team's)",
                                 cli="--frames-lander-view")
    window: int = setting(5, help="Sync rounds of a rover's cells the base re-registers (loop closure)",
                          cli="--frames-window")
    gate: float = setting(0.5, help="Registration gate: the kappa a placement must reach to be merged",
                          cli="--frames-gate")

    def __post_init__(self) -> None:
        for name in ("start_offset", "start_heading", "drift", "heading_drift"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
                raise FedmapError(f"frames {name} must be a number >= 0, got {v!r}")
        lv = self.lander_view
        if isinstance(lv, bool) or not isinstance(lv, (int, float)) or not (math.isfinite(lv) and lv >= 0):
            raise FedmapError(f"frames lander_view must be a number >= 0, got {lv!r}")
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise FedmapError(f"frames window must be an integer >= 1, got {self.window!r}")
        if not (isinstance(self.gate, (int, float)) and -1.0 <= self.gate <= 1.0):
            raise FedmapError(f"frames gate must be a kappa in [-1, 1], got {self.gate!r}")

    @property
    def enabled(self) -> bool:
        """True when any pose is unknown or any odometry drifts."""
        return any(v > 0 for v in (self.start_offset, self.start_heading, self.drift, self.heading_drift))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class MissionConfig:
    """One mission: the team, the clock, sensing, planning, the link and the strategies.

    Parameters
    ----------
    rovers : int
        Team size.
    steps : int
        Mission length in steps; every rover moves and senses once per step.
    sync_every : int
        A sync round at every step that is a multiple of it (not step 0).
    speed : int
        Cells driven per step (each cell entered is sensed from).
    sensor_radius : float
        Cells (Euclidean, centre to centre) a rover observes around itself.
    line_of_sight : bool
        Observe only cells visible over the DEM from ``sensor_height_m`` above the ground.
    lander : [row, col] or None
        Where the team starts: every rover starts on the free cell nearest to it (default:
        the map centre). ``starts`` overrides it with one cell per rover.
    start_spread : int
        0: the rovers start on the free cells nearest to the lander. More: on distinct free
        cells drawn, seeded by ``seed``, within this many cells (Euclidean) of the lander:
        the start area, so that repeats of a mission start differently.
    base : [row, col] or None
        The base station (default: the lander).
    mode : str
        ``frontier`` (coordinated frontier exploration) or ``waypoints`` (a fixed traverse:
        ``waypoints`` per rover, or seeded random ones).
    stay_in_range : bool
        Pick only targets within the link's ``max_range`` of the base.
    unknown_cost : float
        Cost of one unknown cell relative to a known free one when rating targets.
    predictor : str
        ``none``, or ``learned``: every rover runs the shipped map predictor on the map it
        holds and plans with its guesses (:mod:`fedmap.mission.world.frontiers`); the guesses
        cost no bytes and are never shared, scored or counted as observed.
    strategies : tuple of str
        Which of :data:`STRATEGIES` to run, on the same terrain, starts, seeds and link.
    eval_pairs : int
        Start/goal pairs of the path F1 (scored at step 0, every sync and the last step).
    methods : dict
        Per model strategy, :func:`fedmap.config.method_config` keywords laid over its
        preset (e.g. ``{"fedmap": {"epochs": 30}}``).
    """

    rovers: int = setting(4, help="Number of rovers")
    helicopters: int = setting(0, help="Number of helicopters, after the rovers in the team ([helicopter] sets them)")
    profiles: tuple[str, ...] = setting(
        (), help="One traversability profile per rover, comma-separated, or one for all (team: the shared "
        "thresholds; or a rover: cadre, mer, msl); each plans on its own (unset: all follow the shared "
        "thresholds)", choices=PROFILES)
    steps: int = setting(150, help="Mission steps")
    stop_coverage: float | None = setting(None, help="Stop rule: a strategy's run ends at the first step its team has "
                                          "observed this share of the cells a rover can reach (e.g. 0.99; unset: "
                                          "every run takes all steps). In process only: it reads the truth")
    sync_every: int = setting(10, help="Steps between sync rounds")
    speed: int = setting(2, help="Cells driven per step")
    sensor_radius: float = setting(8.0, help="Sensor range, cells")
    line_of_sight: bool = setting(False, help="Observe only cells in line of sight over the DEM")
    layers: tuple[str, ...] = setting(("classes",), help="Map layers the rovers observe and raw shares, "
                                      "comma-separated: classes, or classes,elevation", choices=LAYERS)
    elevation_noise_m: float = setting(0.0, help="elevation layer: std of the rovers' height noise, metres (seeded)")
    elevation_q_m: float = setting(0.01, help="elevation layer: the step raw quantises shared heights to, metres")
    sensor_height_m: float = setting(1.5, help="Sensor height above the ground for line of sight, metres")
    lander: tuple[int, int] | None = setting(None, help="[row, col] the team starts from (unset: the map centre)")
    starts: tuple[tuple[int, int], ...] | None = setting(None, help="One [row, col] start per rover (overrides "
                                                         "lander)")
    start_spread: int = setting(0, help="0: rovers start on the free cells nearest the lander; N: on free cells drawn "
                                "(seeded) within N cells of it")
    base: tuple[int, int] | None = setting(None, help="[row, col] of the base station (unset: the lander)")
    mode: str = setting("frontier", help="frontier: coordinated frontier exploration; waypoints: a fixed traverse",
                        choices=MODES)
    waypoints: tuple[tuple[tuple[int, int], ...], ...] | None = setting(
        None, help="waypoints: one list of [row, col] per rover (unset: seeded random ones)")
    n_waypoints: int = setting(6, help="waypoints: seeded random waypoints per rover")
    stay_in_range: bool = setting(False, help="Pick only targets within the link's range of the base",
                                  cli="--stay-in-range/--roam")
    unknown_cost: float = setting(1.5, help="Cost of an unknown cell relative to a known free one when rating targets")
    predictor: str = setting("none", help="learned: every rover runs the shipped map predictor on its map; an unknown "
                             "cell costs more the likelier it is impassable and a frontier's gain counts the guesses' "
                             "uncertainty (no bytes; guesses are never shared or counted as observed)",
                             choices=PREDICTORS)
    predictor_check: bool = setting(True, help="learned: every 10 steps each rover hides patches of its own map's "
                                    "known cells from the predictor and plans with the guesses only while they beat "
                                    "all free there by 3 points (it steps aside where they cannot help)",
                                    cli="--predictor-check/--predictor-always")
    predictor_adapt: bool = setting(False, help="learned: every 10 steps each rover fine-tunes its own copy of the "
                                    "predictor on its own map (hides known cells and learns to guess them); for "
                                    "planning only: the coder keeps the shipped weights",
                                    cli="--predictor-adapt/--predictor-fixed")
    strategies: tuple[str, ...] = setting(DEFAULT_STRATEGIES, help="Ways of sharing to run side by side, "
                                          "comma-separated", choices=STRATEGIES)
    train_on: str = setting("map", help="Model strategies: what a rover trains on at a sync: map (its whole map) or "
                            "changed (the cells it observed since its last sync, and a replay sample of the rest)",
                            choices=TRAIN_ON)
    replay: float = setting(1.0, help="train_on = changed: the replay sample's size, as a multiple of the changed "
                            "cells")
    eval_pairs: int = setting(40, help="Start/goal pairs of the path F1 (scored at step 0, every sync and the end)")
    link: LinkConfig = wiring(default_factory=LinkConfig)
    prior: PriorConfig = wiring(default_factory=PriorConfig)
    helicopter: HelicopterConfig = wiring(default_factory=HelicopterConfig)
    frames: FramesConfig = wiring(default_factory=FramesConfig)
    methods: dict = wiring(default_factory=dict)
    seed: int = wiring(0)

    def __post_init__(self) -> None:
        def whole(name: str, low: int) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise FedmapError(f"{name} must be an integer >= {low}, got {v!r}")

        whole("rovers", 1)
        whole("helicopters", 0)
        whole("steps", 1)
        whole("sync_every", 1)
        whole("speed", 1)
        whole("eval_pairs", 1)
        stop = self.stop_coverage
        if stop is not None and (isinstance(stop, bool) or not isinstance(stop, (int, float))
                                 or not 0.0 < stop <= 1.0):
            raise FedmapError(f"stop_coverage must be a share in (0, 1] (e.g. 0.99), got {stop!r}")
        whole("n_waypoints", 1)
        if not (math.isfinite(self.sensor_radius) and self.sensor_radius >= 1.5):
            raise FedmapError(f"sensor_radius must be >= 1.5 cells (a rover must see its neighbours), "
                              f"got {self.sensor_radius!r}")
        if not (math.isfinite(self.unknown_cost) and self.unknown_cost >= 1):
            raise FedmapError(f"unknown_cost must be >= 1, got {self.unknown_cost!r}")
        if self.predictor not in PREDICTORS:
            raise FedmapError(f"unknown predictor {self.predictor!r}{suggest(self.predictor, PREDICTORS)}")
        if self.predictor_adapt and self.predictor == "none":
            raise FedmapError("predictor_adapt needs predictor = \"learned\" (there is no predictor to adapt)")
        if self.train_on not in TRAIN_ON:
            raise FedmapError(f"unknown train_on {self.train_on!r}{suggest(self.train_on, TRAIN_ON)}")
        if not (math.isfinite(self.replay) and self.replay >= 0):
            raise FedmapError(f"replay must be >= 0, got {self.replay!r}")
        if self.mode not in MODES:
            raise FedmapError(f"unknown mode {self.mode!r}{suggest(self.mode, MODES)}")
        object.__setattr__(self, "strategies", check_strategies(self.strategies))
        if not TOPOLOGY_CLASSES[self.link.topology].has_base:
            if self.strategies == DEFAULT_STRATEGIES:  # the defaults that run on a peer topology
                object.__setattr__(self, "strategies", PEER_DEFAULTS)
            for s in self.strategies:
                if s not in PEER_STRATEGIES:
                    raise FedmapError(f"strategy {s!r} needs the star topology's base station; on a "
                                      f"{self.link.topology} topology run {', '.join(PEER_STRATEGIES)}")
        link = self.link
        if TOPOLOGY_CLASSES[link.topology].has_base:  # a budget below the headers can never carry a message
            for i, (what, budget) in enumerate((("uplink", link.uplink_bytes), ("downlink", link.downlink_bytes))):
                short = [s for s in self.strategies if REGISTRY[s].on_link and budget is not None
                         and budget < REGISTRY[s].least[i]]
                if short:
                    head = max(REGISTRY[s].least[i] for s in short)
                    raise FedmapError(f"the {what} budget of {budget} B is below the {head}-byte header every "
                                      f"{what} message of {', '.join(short)} carries: nothing could ever be sent "
                                      f"(raise link.{what}_bytes to at least {head})")
        if not (isinstance(self.start_spread, int) and not isinstance(self.start_spread, bool)
                and self.start_spread >= 0):
            raise FedmapError(f"start_spread must be a whole number of cells >= 0, got {self.start_spread!r}")
        if self.lander is not None:
            object.__setattr__(self, "lander", _cell(self.lander, "lander"))
        if self.base is not None:
            object.__setattr__(self, "base", _cell(self.base, "base"))
        if self.starts is not None:
            starts = tuple(_cell(s, f"start {i}") for i, s in enumerate(self.starts))
            if len(starts) != self.rovers:
                raise FedmapError(f"starts gives {len(starts)} cells for {self.rovers} rovers")
            object.__setattr__(self, "starts", starts)
        layers = check_layers(self.layers)
        # classes are always a layer (GridMap's canonical one): "elevation" alone means both
        layers = tuple(n for n in LAYERS if n in layers)
        object.__setattr__(self, "layers", layers)
        if not (math.isfinite(self.elevation_noise_m) and self.elevation_noise_m >= 0):
            raise FedmapError(f"elevation_noise_m must be >= 0, got {self.elevation_noise_m!r}")
        if not (math.isfinite(self.elevation_q_m) and self.elevation_q_m >= 0):
            raise FedmapError(f"elevation_q_m must be >= 0 (0: exact float32), got {self.elevation_q_m!r}")
        if self.profiles:
            profiles = tuple(self.profiles)
            if len(profiles) not in (1, self.rovers):  # one per rover, or one for all
                raise FedmapError(f"profiles gives {len(profiles)} profiles for {self.rovers} rovers")
            for name in profiles:
                if name not in PROFILES:
                    raise FedmapError(f"unknown rover profile {name!r}{suggest(name, PROFILES)}")
            object.__setattr__(self, "profiles", profiles)
        if self.waypoints is not None:
            wps = tuple(tuple(_cell(c, f"waypoint of rover {k}") for c in w) for k, w in enumerate(self.waypoints))
            if len(wps) != self.rovers:
                raise FedmapError(f"waypoints gives {len(wps)} lists for {self.rovers} rovers")
            object.__setattr__(self, "waypoints", wps)
        for name, kw in self.methods.items():
            check_strategy_options(name, kw)

    @property
    def rover_profiles(self) -> tuple[str, ...]:
        """Every rover's profile (``profiles`` given once applies to all; unset: ``team``)."""
        p = self.profiles or ("team",)
        return p * self.rovers if len(p) == 1 else p

    @property
    def sync_steps(self) -> range:
        """Every step with a sync round (``sync_every``, ``2 * sync_every``, ... up to ``steps``):
        a range, so a mission of a billion steps does not hold a list of them."""
        return range(self.sync_every, self.steps + 1, self.sync_every)

    def sync_round(self, t: int) -> int | None:
        """The sync round at step ``t`` (1, 2, ...), or None when ``t`` has none."""
        return t // self.sync_every if 0 < t <= self.steps and t % self.sync_every == 0 else None

    def stops(self, t: int, coverage_reachable: float) -> bool:
        """Whether the stop rule ends a run at step ``t``, before its last, its team having
        observed ``coverage_reachable`` of the cells it can reach (never without ``stop_coverage``)."""
        return (self.stop_coverage is not None and t < self.steps
                and coverage_reachable >= self.stop_coverage - 1e-12)

    def evaluated(self, t: int) -> bool:
        """Whether step ``t`` is scored in full (maps and paths): step 0, every sync and the last."""
        return t in (0, self.steps) or self.sync_round(t) is not None

    @property
    def link_seed(self) -> int:
        """The seed the link draws from: ``[link] seed``, or the mission's ``seed`` when unset."""
        return self.seed if self.link.seed is None else self.link.seed

    def to_dict(self) -> dict:
        out = _without_unset_options(asdict(self))
        if not self.frames.enabled:  # known poses: the settings (and metrics.json) as before [frames] existed
            out.pop("frames", None)
        return out


def _without_unset_options(mission: dict) -> dict:
    """``mission`` without ``predictor`` (and ``predictor_check``) when it is ``none``, without ``predictor_adapt``
    when it is off, and without ``stop_coverage``
    when it is unset: missions that use neither keep the settings (and the ``metrics.json``)
    they had before they existed."""
    none = mission.get("predictor") == "none"
    return {k: v for k, v in mission.items() if not ((k in ("predictor", "predictor_check") and none)
                                                     or (k == "predictor_adapt" and not v)
                                                     or (k == "stop_coverage" and v is None))}


#: The tables of a mission file besides the run config's ``seed``, ``[terrain]`` and ``[thresholds]``.
MISSION_SECTIONS: dict[str, type] = {"mission": MissionConfig, "link": LinkConfig, "prior": PriorConfig,
                                     "helicopter": HelicopterConfig, "frames": FramesConfig}
_RUN_PART = ("seed", "terrain", "thresholds")


def preset_names() -> tuple[str, ...]:
    """Mission presets shipped in ``fedmap/mission/presets/<name>.toml`` (e.g. ``cadre``)."""
    files = resources.files("fedmap.mission").joinpath("presets").iterdir()
    return tuple(sorted(f.name.removesuffix(".toml") for f in files if f.name.endswith(".toml")))


def _preset_data(name: str) -> dict:
    names = preset_names()
    if name not in names:
        raise FedmapError(f"unknown mission preset {name!r}{suggest(name, names)}")
    return tomllib.loads(resources.files("fedmap.mission").joinpath("presets", f"{name}.toml").read_text("utf-8"))


def mission_toml(resolved: dict) -> str:
    """The resolved mission (:func:`load_mission`'s third value) as the TOML text that runs
    it again (``mission.toml`` of the outputs; what a mission on processes sends its rovers)."""
    def ready(d):
        if isinstance(d, dict):
            return {k: ready(v) for k, v in d.items() if v is not None}  # TOML has no null
        if isinstance(d, (list, tuple)):
            return [ready(v) for v in d]
        return d

    return dumps_toml(ready(resolved))


def load_mission(path: str | Path | None = None, *, preset: str | None = None, mission: dict | None = None,
                 link: dict | None = None, terrain: dict | None = None, size: int | None = None,
                 seed: int | None = None, overrides: list[dict] | None = None) -> tuple[MissionConfig, TerrainSource, dict]:
    """Preset < TOML file < options -> ``(mission config, terrain source, resolved dict)``.

    ``overrides`` are partial mission files laid over the file in order (e.g. from
    ``--set mission.rovers=3`` or ``--set thresholds.rover=cadre``); ``mission`` and
    ``link`` are ``[mission]`` / ``[link]`` keys and ``seed`` the top-level seed (None
    values left out); ``terrain`` replaces the file's terrain source (like
    ``fedmap run --dem``), keeping its ``crop``, ``size`` and ``resample``; ``size`` then
    resamples the terrain.
    """
    data: dict = _preset_data(preset) if preset is not None else {}
    if path is not None:
        path = Path(path)
        file_data = read_toml(path, "mission")
        t = file_data.get("terrain", {})
        if isinstance(t, dict) and "path" in t and isinstance(t["path"], str) and not Path(t["path"]).is_absolute():
            t["path"] = str((path.parent / t["path"]).resolve())
        data = merge(data, file_data)
    where = Path(path).name if path is not None else "the mission settings"
    check_mission_file(data, where)
    if terrain is not None:
        kept = {k: v for k, v in data.get("terrain", {}).items() if k in ("crop", "size", "resample")}
        data["terrain"] = {**kept, **terrain}
    layers = [*(overrides or []),
              {"mission": {k: v for k, v in (mission or {}).items() if v is not None},
               "link": {k: v for k, v in (link or {}).items() if v is not None},
               **({"terrain": {"size": size}} if size is not None else {}),
               **({"seed": seed} if seed is not None else {})}]
    for layer in layers:
        m = layer.get("mission", {})
        for key in ("strategies", "profiles", "layers"):
            if isinstance(m.get(key), str):  # "none,raw" from the command line
                m[key] = [x.strip() for x in m[key].split(",") if x.strip()]
        check_mission_file(layer, "the command-line options")
        data = merge(data, layer)
    run_part = {k: data[k] for k in _RUN_PART if k in data}
    resolved = merge(base_defaults(), run_part)
    resolved["terrain"] = run_part.get("terrain", {})  # TerrainSource's own defaults (they depend on the kind)
    # a rover profile applies as in `fedmap run` (limits set beside it win)
    resolved["thresholds"] = with_rover_profile(resolved["thresholds"], [run_part])
    source = terrain_source(resolved)
    methods = data.get("strategies", {})
    try:
        config = _schema.build(MissionConfig, data.get("mission", {}), link=_schema.build(LinkConfig, data.get("link", {})),
                               prior=_schema.build(PriorConfig, data.get("prior", {})),
                               helicopter=_schema.build(HelicopterConfig, data.get("helicopter", {})),
                               frames=_schema.build(FramesConfig, data.get("frames", {})), methods=methods,
                               seed=resolved["seed"])
    except TypeError as exc:  # a wrong type reaching a comparison
        raise FedmapError(f"bad mission setting: {exc}") from exc
    if source.kind == "map":
        for asked, what in ((config.line_of_sight, "line of sight"), ("elevation" in config.layers, "an elevation layer"),
                            (bool(config.profiles), "rover profiles"),
                            (config.prior.kind == "orbital", "an orbital prior")):
            if asked:
                raise needs_dem(what)
    out = {"seed": resolved["seed"], "terrain": {k: v for k, v in source.to_dict().items() if k != "thresholds"},
           "thresholds": used_thresholds(resolved["thresholds"]),
           "mission": _without_unset_options({k: v for k, v in asdict(config).items()
                                                if k not in ("link", "prior", "helicopter", "frames", "methods",
                                                             "seed")}),
           "link": config.link.to_dict(), "prior": config.prior.to_dict(), "helicopter": config.helicopter.to_dict(),
           "strategies": methods}
    if config.frames.enabled:  # known poses: the resolved settings as before [frames] existed
        out["frames"] = config.frames.to_dict()
    return config, source, out


def check_mission_file(data: dict, where: str) -> None:
    """Check the tables, keys and value types of a (partial) mission file."""
    known = [*_RUN_PART, *MISSION_SECTIONS, "strategies"]
    for key in data:
        if key not in known:
            raise FedmapError(f"unknown key {key!r} in {where}{suggest(key, known)}")
    validate({k: data[k] for k in _RUN_PART if k in data}, where)
    for name, cls in MISSION_SECTIONS.items():
        if name in data:
            _schema.check_table(cls, data[name], where, section=name)
    methods = data.get("strategies", {})
    if not isinstance(methods, dict) or not all(isinstance(v, dict) for v in methods.values()):
        raise FedmapError(f"[strategies] of {where} must hold tables like [strategies.fedmap]")


def parse_sets(assignments: list[str] | None) -> list[dict]:
    """``--set section.key=value`` assignments as partial mission files."""
    return [parse_set(a) for a in assignments or []]


def with_settings(config: MissionConfig, **changes: Any) -> MissionConfig:
    """``config`` with some fields replaced (checked again)."""
    return replace(config, **changes)
