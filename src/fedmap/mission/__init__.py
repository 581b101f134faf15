"""Missions: rovers explore over time, share maps over a constrained link, and the ways of
sharing are compared on the same mission.

* :mod:`~fedmap.mission.settings`: :class:`MissionConfig`, :class:`LinkConfig`, the TOML loader;
* :mod:`~fedmap.mission.sensing`: the sensor footprint (disk, optional line of sight over the DEM);
* :mod:`~fedmap.mission.frontiers`: frontier cells and coordinated target choice on a belief map;
* :mod:`~fedmap.mission.world`: the rovers' world: drive, fly, sense, plan on a belief;
* :mod:`~fedmap.mission.protocol`: the ends of a strategy (rover, base, peer), its headers;
* :mod:`~fedmap.mission.raw`, :mod:`~fedmap.mission.predictive`, :mod:`~fedmap.mission.model`,
  :mod:`~fedmap.mission.gossip`: the strategies' ends (none, raw, central; predictive;
  paper, fedmap; gossip, admm), which talk to each other only in bytes;
* :mod:`~fedmap.mission.rosgrid`: the ROS 2 baseline's ends (rosgrid, rosgrid-zlib): whole
  ``nav_msgs/msg/OccupancyGrid`` messages both ways, merged at the base as map_merge does;
* :mod:`~fedmap.mission.registry`: the one registry of strategies (:data:`REGISTRY`);
* :mod:`~fedmap.mission.link`: the seeded link (budgets, loss, latency, drops) and its ledger;
* :mod:`~fedmap.mission.topology`: who talks to whom (:class:`StarTopology`,
  :class:`MeshTopology`, :class:`LeaderTopology`) and one sync round over the ends;
* :mod:`~fedmap.mission.sim`: :func:`run_mission`, the step loop; its typed results
  (:class:`StrategyRun`: a :class:`TimeSeries` and a :class:`MissionSummary` per strategy)
  are in :mod:`~fedmap.mission.results`;
* :mod:`~fedmap.mission.scoring`: a mission scored from what its nodes logged (``fedmap score``);
* :mod:`~fedmap.mission.report`: ``metrics.json``, ``report.md``, plots and the animation;
* :mod:`~fedmap.mission.maps_out`: the final global maps and beliefs as GridMaps and files
  (:func:`mission_maps`, :func:`write_mission_maps`).
"""

from fedmap.mission.maps_out import mission_maps, write_mission_maps
from fedmap.mission.registry import REGISTRY
from fedmap.mission.results import MissionResult, MissionSummary, StrategyRun, TimeSeries
from fedmap.mission.settings import STRATEGIES, LinkConfig, MissionConfig, load_mission
from fedmap.mission.sim import mission_terrain, run_mission
from fedmap.mission.topology import LeaderTopology, MeshTopology, StarTopology, Topology

__all__ = ["REGISTRY", "STRATEGIES", "LeaderTopology", "LinkConfig", "MeshTopology", "MissionConfig", "MissionResult",
           "MissionSummary", "StarTopology", "StrategyRun", "TimeSeries", "Topology", "load_mission",
           "mission_maps", "mission_terrain", "run_mission", "write_mission_maps"]
