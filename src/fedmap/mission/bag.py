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

from collections.abc import Iterator
from pathlib import Path

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.rosbag import write_bag
from fedmap.mission.results import MissionResult

#: Seconds of mission clock per step in a mission's bag.
STEP_SECONDS = 1.0


def _messages(result: MissionResult, step_seconds: float) -> Iterator[tuple[str, int, GridMap]]:
    truth = result.truth
    for name, run in result.runs.items():
        for frame in run.frames:
            t = int(round(frame.step * step_seconds * 1e9))
            yield f"/{name}/global_map", t, truth.with_classes(frame.global_map, f"mission {name}: global map")
            for k, belief in enumerate(frame.beliefs):
                yield f"/{name}/belief_{k}", t, truth.with_classes(belief, f"mission {name}: rover {k}'s belief")


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
    return write_bag(_messages(result, float(step_seconds)), path, storage=storage)


__all__ = ["STEP_SECONDS", "write_mission_bag"]
