"""Missions: rovers explore over time, share maps over a constrained link, and the ways of
sharing are compared on the same mission.

* :mod:`~fedmap.mission.settings`: :class:`MissionConfig`, :class:`LinkConfig`, the TOML loader;
* :mod:`~fedmap.mission.world.sensing`: the sensor footprint (disk, optional line of sight over the DEM);
* :mod:`~fedmap.mission.world.frontiers`: frontier cells and coordinated target choice on a belief map;
* :mod:`~fedmap.mission.world.world`: the rovers' world: drive, fly, sense, plan on a belief;
* :mod:`~fedmap.mission.ends.protocol`: the ends of a strategy (rover, base, peer), its headers;
* :mod:`~fedmap.mission.ends.raw`, :mod:`~fedmap.mission.ends.predictive`, :mod:`~fedmap.mission.ends.model`,
  :mod:`~fedmap.mission.ends.gossip`: the strategies' ends (none, raw, central; predictive;
  paper, fedmap; gossip, admm), which talk to each other only in bytes;
* :mod:`~fedmap.mission.ends.rosgrid`: the ROS 2 baseline's ends (rosgrid, rosgrid-zlib): whole
  ``nav_msgs/msg/OccupancyGrid`` messages both ways, merged at the base as map_merge does;
* :mod:`~fedmap.mission.ends.registry`: the one registry of strategies (:data:`REGISTRY`);
* :mod:`~fedmap.mission.network.link`: the seeded link (budgets, loss, latency, drops) and its ledger;
* :mod:`~fedmap.mission.network.topology`: who talks to whom (:class:`StarTopology`,
  :class:`MeshTopology`, :class:`LeaderTopology`) and one sync round over the ends;
* :mod:`~fedmap.mission.sim`: :func:`run_mission`, the step loop; its typed results
  (:class:`StrategyRun`: a :class:`TimeSeries` and a :class:`MissionSummary` per strategy)
  are in :mod:`~fedmap.mission.results`;
* :mod:`~fedmap.mission.scoring`: a mission scored from what its nodes logged (``fedmap score``);
* :mod:`~fedmap.mission.outputs.report`: ``metrics.json``, ``report.md``, plots and the animation;
* :mod:`~fedmap.mission.outputs.maps_out`: the final global maps and beliefs as GridMaps and files
  (:func:`mission_maps`, :func:`write_mission_maps`).
"""

from fedmap.mission.ends.registry import REGISTRY
from fedmap.mission.network.topology import LeaderTopology, MeshTopology, StarTopology, Topology
from fedmap.mission.outputs.maps_out import mission_maps, write_mission_maps
from fedmap.mission.results import MissionResult, MissionSummary, StrategyRun, TimeSeries
from fedmap.mission.settings import STRATEGIES, LinkConfig, MissionConfig, load_mission
from fedmap.mission.sim import mission_terrain, run_mission

__all__ = ["REGISTRY", "STRATEGIES", "LeaderTopology", "LinkConfig", "MeshTopology", "MissionConfig", "MissionResult",
           "MissionSummary", "StarTopology", "StrategyRun", "TimeSeries", "Topology", "load_mission",
           "mission_maps", "mission_terrain", "run_mission", "write_mission_maps"]
