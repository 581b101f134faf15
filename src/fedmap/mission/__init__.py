"""Missions: rovers explore over time, share maps over a constrained link, and the ways of
sharing are compared on the same mission.

* :mod:`~fedmap.mission.settings`: :class:`MissionConfig`, :class:`LinkConfig`, the TOML loader;
* :mod:`~fedmap.mission.sensing`: the sensor footprint (disk, optional line of sight over the DEM);
* :mod:`~fedmap.mission.frontiers`: frontier cells and coordinated target choice on a belief map;
* :mod:`~fedmap.mission.link`: the seeded link (budgets, loss, latency, range) and its ledger;
* :mod:`~fedmap.mission.strategies`: none, raw, paper, fedmap, central;
* :mod:`~fedmap.mission.sim`: :func:`run_mission`, the step loop and its time series;
* :mod:`~fedmap.mission.report`: ``metrics.json``, ``report.md``, plots and the animation.
"""

from fedmap.mission.settings import STRATEGIES, LinkConfig, MissionConfig, load_mission
from fedmap.mission.sim import MissionResult, StrategyRun, run_mission

__all__ = ["STRATEGIES", "LinkConfig", "MissionConfig", "MissionResult", "StrategyRun", "load_mission",
           "run_mission"]
