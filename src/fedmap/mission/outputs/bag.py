"""A mission as a ROS 2 bag: every strategy's global map and every rover's belief at every
kept frame, as ``nav_msgs/OccupancyGrid`` messages that ``ros2 bag play`` publishes
(written by :func:`fedmap.maps.rosbag.write_bag`: sqlite3 storage, rosbag2 version 8).

Topics: ``/<strategy>/global_map`` (the base station's map) and ``/<strategy>/belief_<k>``
(rover ``k``'s belief, k from 0 in team order), frame ``map``, each map in the truth's
frame (origin the truth's lower-left corner, resolution its pixel size). Time is the
mission clock: step ``t`` is stamped ``t * step_seconds`` seconds (default
:data:`STEP_SECONDS`, one second a step) from the epoch, the same for every strategy, so
the strategies can be played side by side.

The frames are the run's kept frames (``result.runs[s].frames``, which ``run_mission``'s
``frames`` bounds; the last step is always kept). A global map that holds nothing yet (all
UNKNOWN, e.g. ``none``'s) is still written: a viewer sees it grow.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.rosbag import write_bag
from fedmap.mission.results import MissionResult, Snapshot
from fedmap.mission.settings import MissionConfig

#: Seconds of mission clock per step in a mission's bag.
STEP_SECONDS = 1.0


#: One strategy's maps at one step: ``(strategy, step, global map, beliefs)``.
Maps = tuple[str, int, np.ndarray, list[np.ndarray]]


def _messages(truth: GridMap, maps: Iterable[Maps], step_seconds: float) -> Iterator[tuple[str, int, GridMap]]:
    for name, step, global_map, beliefs in maps:
        t = int(round(step * step_seconds * 1e9))
        yield f"/{name}/global_map", t, truth.with_classes(global_map, f"mission {name}: global map")
        for k, belief in enumerate(beliefs):
            yield f"/{name}/belief_{k}", t, truth.with_classes(belief, f"mission {name}: rover {k}'s belief")


class SyncMaps:
    """A ``run_mission`` ``on_snapshot`` that keeps every strategy's global map and every
    member's belief at step 0, at every sync and at the last step, for :meth:`write` to put
    in a bag (the run's kept frames are fewer: an animation's, or only the last)."""

    def __init__(self, config: MissionConfig, truth: GridMap) -> None:
        self.truth, self.config = truth, config
        self.maps: list[Maps] = []

    def __call__(self, snap: Snapshot) -> None:
        if snap.eval is not None:  # scored in full: step 0, every sync and the last (or where the stop rule ended it)
            self.maps.append((snap.strategy, snap.step, snap.global_map.copy(), [b.copy() for b in snap.beliefs]))

    def write(self, path, *, step_seconds: float = STEP_SECONDS, storage: str = "sqlite3") -> Path:
        """The kept maps as a new ROS 2 bag folder ``path`` (see :func:`write_mission_bag`)."""
        if not step_seconds > 0:
            raise FedmapError(f"step_seconds must be positive, got {step_seconds!r}")
        if not self.maps:
            raise FedmapError("the mission recorded no step: nothing to write into a bag")
        return write_bag(_messages(self.truth, self.maps, float(step_seconds)), path, storage=storage)


def write_mission_bag(result: MissionResult, path, *, step_seconds: float = STEP_SECONDS,
                      storage: str = "sqlite3") -> Path:
    """Write a mission's maps at every kept frame into a new ROS 2 bag folder ``path``.

    Parameters
    ----------
    result : MissionResult
        A mission's result (:func:`~fedmap.mission.sim.run_mission`).
    path : str or Path
        The bag folder (written whole or not at all; an existing bag there is replaced).
    step_seconds : float
        Mission-clock seconds per step: step ``t`` is stamped ``t * step_seconds``.
    storage : str
        ``sqlite3`` (the default, what ROS 2 Humble reads out of the box) or ``mcap``.

    Returns
    -------
    Path
        The bag folder.
    """
    if not step_seconds > 0:
        raise FedmapError(f"step_seconds must be positive, got {step_seconds!r}")
    if not any(run.frames for run in result.runs.values()):
        raise FedmapError("the mission recorded no frame: nothing to write into a bag")
    maps = [(name, f.step, f.global_map, f.beliefs) for name, run in result.runs.items() for f in run.frames]
    return write_bag(_messages(result.truth, maps, float(step_seconds)), path, storage=storage)


__all__ = ["STEP_SECONDS", "SyncMaps", "write_mission_bag"]
