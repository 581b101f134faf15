"""Scoring off the link: a mission's record from what its nodes wrote to their own logs.

Every rover node logs what an observer reads of it at every step
(:class:`~fedmap.mission.network.nodelog.RoverEntry`), and the base station logs what it held and
sent (:class:`~fedmap.mission.network.nodelog.BaseRecord`). :func:`score_strategy` merges them
against the truth, step by step, through the same :class:`~fedmap.mission.sim.Scoring` an
in-process run records with: so a mission on processes is scored as the simulator scores
it, and nothing of the scoring crossed the link. :func:`score_folder` scores a run folder
(``fedmap score RUN_FOLDER``): the base's records, the mission they ran, and the rovers'
logs copied anywhere under it.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.mission.network.nodelog import (
    BaseRecord,
    RoverEntry,
    StepState,
    base_name,
    read_base_record,
    read_peer_records,
    read_rover_log,
)
from fedmap.mission.network.peers import merge_records
from fedmap.mission.network.topology import make_topology
from fedmap.mission.results import MissionResult, StrategyRun
from fedmap.mission.settings import load_mission
from fedmap.mission.sim import Mission, Scoring, TeamState, mission_terrain, prepare_mission

#: The file of a run folder that holds the mission its nodes ran (the resolved TOML).
MISSION_FILE = "mission.toml"
#: The file of a run folder that holds what the run says of itself (its id, its strategies).
RUN_FILE = "run.json"


class MissingLog(FedmapError):
    """A rover's log is not in the run folder (it is still on the rover)."""


def score_strategy(mission: Mission, record: BaseRecord, logs: Sequence[Sequence[RoverEntry]], *,
                   on_step: Callable[[str, int, float], None] | None = None) -> StrategyRun:
    """Strategy ``record.strategy``'s run, scored from the base's ``record`` and every rover's
    log (``logs[k]``: rover ``k``'s entries, in order). One line when a log misses a step; a
    rover that left a peer mission (``record.left``) stays as its last record says."""
    c, name = mission.config, record.strategy
    world = mission.world(make_topology(c.link, mission.base))
    n = len(world.team)
    if len(logs) != n:
        raise FedmapError(f"{name}: logs of {len(logs)} rovers, the team has {n}")
    steps: list[dict[int, StepState]] = [{s.step: s for e in log for s in e.states} for log in logs]
    for k in (record.left or {}):  # a rover that left the team: it stays where it was, as it was
        held = steps[k]
        if held:
            last = held[max(held)]
            held.update({t: replace(last, step=t) for t in range(max(held) + 1, c.steps + 1)})
    for k, held in enumerate(steps):
        if not held:
            raise MissingLog(f"{name}: no log of rover {k} in the run folder: a rover keeps its own log (log/ in its "
                              "--state folder); copy it into the run folder, then run fedmap score RUN_FOLDER")
        missing = [t for t in range(c.steps + 1) if t not in held]
        if missing:
            raise FedmapError(f"{name}: rover {k}'s log has no record of step {missing[0]} ({len(missing)} step(s) "
                              "missing): copy its whole log folder into the run folder")
    scoring = Scoring(name, mission, world)
    for t in range(c.steps + 1):
        states = [held[t] for held in steps]
        team = TeamState(beliefs=[s.belief for s in states], views=[s.view for s in states],
                         observed=np.stack([s.observed for s in states]), positions=[s.pos for s in states],
                         targets=[s.target for s in states], distances=[s.distance for s in states],
                         trail_len=[s.trail_len for s in states])
        scoring.record(t, c.evaluated(t), team, record.held_at(t), record.ledger)
        if on_step is not None:
            on_step(name, t, scoring.rows[-1].coverage)
    trails = [[cell for e in log for cell in e.trail] for log in logs]
    return scoring.result(record.seconds, trails, record.ledger, record.slots, final_heights=record.final_heights,
                          dropped=record.dropped, lags=record.lags,
                          registrations=None if record.registrations is None else tuple(record.registrations),
                          wire=record.wire)


def mission_from_text(text: str, *, frames: int = 60) -> Mission:
    """The mission of a resolved mission TOML: its terrain loaded, starts placed."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise FedmapError(f"the mission is not valid TOML: {e}") from None
    config, source, _ = load_mission(None, overrides=[data])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    return prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                           thresholds=source.thresholds, frames=frames)


def write_run(folder: Path, mission_text: str, strategies: Sequence[str], seconds: float,
              faults: Sequence[dict] = (), *, mission_id: str = "") -> None:
    """What a run says of itself, for :func:`score_folder`: the mission its nodes ran (the
    resolved TOML) and its id (the nodes' logs are named by it), its strategies, its wall
    time and what went wrong on the way."""
    atomic_write_bytes(Path(folder) / MISSION_FILE, mission_text.encode())
    atomic_write_bytes(Path(folder) / RUN_FILE, json.dumps({"mission": mission_id, "strategies": list(strategies),
                                                            "seconds": seconds, "faults": list(faults)},
                                                           indent=1).encode())


def score_folder(folder: Path, *, frames: int = 60,
                 on_step: Callable[[str, int, float], None] | None = None) -> MissionResult:
    """The mission of the run folder ``folder`` scored from its nodes' logs: the base's
    records (``*.base.log``), the mission they ran (``mission.toml``) and every rover's log
    (``*-rover<k>-*.log``, anywhere under ``folder``); a peer mission's from every agent's
record (``*.peer.log``) instead of the base's. One line for what is missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FedmapError(f"no run folder {folder}")
    try:
        text = (folder / MISSION_FILE).read_text()
        meta = json.loads((folder / RUN_FILE).read_text())
        mission_id = str(meta.get("mission", ""))
        seconds = float(meta.get("seconds", 0.0))
        strategies = [str(s) for s in meta["strategies"]]
        faults = tuple(dict(f) for f in meta.get("faults", ()))
    except FileNotFoundError as e:
        raise FedmapError(f"{folder} is not a mission's run folder: no {Path(str(e.filename)).name}") from None
    except (ValueError, KeyError, TypeError) as e:
        raise FedmapError(f"{folder / RUN_FILE} is damaged ({type(e).__name__}: {e})") from None
    mission = mission_from_text(text, frames=frames)
    shape: tuple[int, int] = tuple(mission.truth.shape)  # type: ignore[assignment]
    n = mission.config.rovers + mission.config.helicopters
    runs = {}
    for name in strategies:
        record = read_base_record(folder, mission_id, name, shape=shape)
        logs = [read_rover_log(folder, mission_id, name, k, shape=shape) for k in range(n)]
        if record is None and mission.config.link.topology != "star":  # a peer mission: every agent's own record
            peers = read_peer_records(folder, mission_id, name, shape=shape)
            record = merge_records(mission, peers, logs) if peers else None
        if record is None:
            raise FedmapError(f"{folder}: no base station record of {name} ({base_name(mission_id, name)}): the base "
                              "did not finish it")
        runs[name] = score_strategy(mission, record, logs, on_step=on_step)
    return MissionResult(mission.config, mission.truth, mission.starts, mission.base, runs, seconds,
                         faults=faults)


__all__ = ["MISSION_FILE", "RUN_FILE", "MissingLog", "mission_from_text", "score_folder", "score_strategy",
           "write_run"]
