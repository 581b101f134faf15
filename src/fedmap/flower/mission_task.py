"""What the mission apps do, Flower-free: the mission from the run config, a rover's node
kept between messages, faults a test can inject, and the base station's result file.

A mission's run config carries the whole resolved mission as TOML text (``mission``: the
``mission.toml`` an in-process run writes), so the base station and every rover build the
same mission (:func:`fedmap.mission.load_mission`, then the same terrain, starts and seeds).
The base station writes the finished :class:`~fedmap.mission.results.MissionResult` to
``<out>.run/result.pickle`` for the command that started it (its own process, on its own
machine: a file of this run, read once), next to ``status.json``.
"""

from __future__ import annotations

import pickle
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.remote import DEPLOYABLE, CorruptMessage, RoverNode
from fedmap.mission.results import MissionResult
from fedmap.mission.sim import Mission, prepare_mission

#: The mission app's run-config keys and their defaults (``mission_app/pyproject.toml`` holds the same).
MISSION_RUN_DEFAULTS: dict[str, Any] = {
    "mission": "",  # the resolved mission, TOML text
    "strategies": "",  # comma-separated; "" = the mission's own
    "out": "fedmap-out/mission",
    "frames": 60,  # the animation's frames per strategy (1: none kept)
    "connect-timeout": 120.0,  # seconds to wait for every rover to connect
    "deadline": 600.0,  # seconds a sync round may take
}


@dataclass(frozen=True)
class MissionRun:
    """The mission app's run config, checked."""

    mission: str
    strategies: tuple[str, ...]
    out: Path
    frames: int
    connect_timeout: float
    deadline: float

    @classmethod
    def from_run_config(cls, cfg: dict) -> MissionRun:
        unknown = set(cfg) - set(MISSION_RUN_DEFAULTS)
        if unknown:
            raise FedmapError(f"unknown mission run-config key(s): {', '.join(sorted(unknown))}")
        c = {**MISSION_RUN_DEFAULTS, **cfg}
        if not str(c["mission"]).strip():
            raise FedmapError("the mission run config has no mission (the resolved mission TOML)")
        names = tuple(s.strip() for s in str(c["strategies"]).split(",") if s.strip())
        return cls(str(c["mission"]), names, Path(str(c["out"])), int(c["frames"]), float(c["connect-timeout"]),
                   float(c["deadline"]))


def mission_from_text(text: str, *, frames: int = 60) -> Mission:
    """The mission of a resolved mission TOML: its terrain loaded, starts placed."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise FedmapError(f"the mission run config is not valid TOML: {e}") from None
    config, source, _ = load_mission(None, overrides=[data])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    return prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                           thresholds=source.thresholds, frames=frames)


def strategies_of(run: MissionRun, mission: Mission) -> tuple[str, ...]:
    """The strategies the run deploys: the run config's, else the mission's own that can run on processes."""
    return run.strategies or tuple(s for s in mission.config.strategies if s in DEPLOYABLE)


# -- a rover between messages ----------------------------------------------------------------


def rover_answer(blob: bytes | None, mission_text: str, strategy: str, k: int, order: bytes) -> tuple[bytes, bytes]:
    """Rover ``k``'s report to ``order`` and its node to keep until the next message
    (``blob``: the node it kept, None before its first order of ``strategy``). Both are
    this rover's own state, written by this rover. :class:`CorruptMessage` for a damaged order."""
    node = pickle.loads(blob) if blob is not None else RoverNode(mission_from_text(mission_text, frames=1), strategy, k)
    report = node.answer(order)
    return report, pickle.dumps(node, protocol=pickle.HIGHEST_PROTOCOL)


def parse_mission_fault(text: str) -> tuple[str, int]:
    """A test's fault: ``corrupt@STEP`` damages this rover's report of the order to STEP, once."""
    kind, _, at = text.partition("@")
    if kind != "corrupt" or not at.isdigit():
        raise FedmapError(f"unknown mission fault {text!r}: use corrupt@STEP")
    return kind, int(at)


def damaged(report: bytes) -> bytes:
    """``report`` with one byte of its body flipped (a damaged message on the link)."""
    b = bytearray(report)
    b[len(b) // 2] ^= 0x5A
    return bytes(b)


# -- the base station's result ----------------------------------------------------------------


def result_path(out: Path) -> Path:
    return run_dir(out) / "result.pickle"


def write_result(out: Path, result: MissionResult) -> None:
    """The finished mission for the command that started the base station (ends dropped:
    their state is not part of the outputs)."""
    runs = {name: replace(run, sharing=None) for name, run in result.runs.items()}
    atomic_write_bytes(result_path(out), pickle.dumps(replace(result, runs=runs), protocol=pickle.HIGHEST_PROTOCOL))


def read_result(out: Path) -> MissionResult:
    """The result the base station of this run wrote (:func:`write_result`)."""
    p = result_path(out)
    try:
        result = pickle.loads(p.read_bytes())
    except FileNotFoundError:
        raise FedmapError(f"the base station wrote no result ({p})") from None
    if not isinstance(result, MissionResult):
        raise FedmapError(f"{p} is not a mission result")
    return result


__all__ = ["MISSION_RUN_DEFAULTS", "CorruptMessage", "MissionRun", "damaged", "mission_from_text",
           "parse_mission_fault", "read_result", "result_path", "rover_answer", "strategies_of", "write_result"]
