"""Missions: rovers explore over time, share maps over a constrained link, and the ways of
sharing are compared on the same mission.

* :mod:`~fedmap.mission.settings`: :class:`MissionConfig`, :class:`LinkConfig`, the TOML loader;
* :mod:`~fedmap.mission.sensing`: the sensor footprint (disk, optional line of sight over the DEM);
* :mod:`~fedmap.mission.frontiers`: frontier cells and coordinated target choice on a belief map;
* :mod:`~fedmap.mission.link`: the seeded link (budgets, loss, latency), its :class:`Topology`
  (who reaches the base: :class:`StarTopology`, within range) and its ledger;
* :mod:`~fedmap.mission.strategies`: none, raw, predictive, paper, fedmap, central;
* :mod:`~fedmap.mission.sim`: :func:`run_mission`, the step loop and its typed results
  (:class:`StrategyRun`: a :class:`TimeSeries` and a :class:`MissionSummary` per strategy);
* :mod:`~fedmap.mission.report`: ``metrics.json``, ``report.md``, plots and the animation.
"""

from fedmap.mission.link import StarTopology, Topology
from fedmap.mission.settings import STRATEGIES, LinkConfig, MissionConfig, load_mission
from fedmap.mission.sim import MissionResult, MissionSummary, StrategyRun, TimeSeries, mission_terrain, run_mission

__all__ = ["STRATEGIES", "LinkConfig", "MissionConfig", "MissionResult", "MissionSummary", "StarTopology",
           "StrategyRun", "TimeSeries", "Topology", "load_mission", "mission_terrain", "run_mission"]
