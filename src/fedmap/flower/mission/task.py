"""What the mission apps do, Flower-free: the mission from the run config, a rover's node
kept between messages, faults a test can inject, and the base station's result file.

A mission's run config carries the whole resolved mission as TOML text (``mission``: the
``mission.toml`` an in-process run writes), so the base station and every rover build the
same mission (:func:`fedmap.mission.load_mission`, then the same terrain, starts and seeds).
Every node writes its own log: a rover in ``log/`` of its state folder, the base station in
``<out>.run/base/``, beside the mission and what the run says of itself (``mission.toml``,
``run.json``); the command that started the base scores the run from them
(:func:`fedmap.mission.scoring.score_folder`, as ``fedmap score`` does).
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.mission.ends.registry import REGISTRY
from fedmap.mission.network.nodelog import write_log
from fedmap.mission.network.remote import (
    CorruptMessage,
    LostState,
    Order,
    ProcessRover,
    pack_frame,
    pack_history,
    unpack_frame,
    unpack_history,
)
from fedmap.mission.scoring import mission_from_text
from fedmap.mission.sim import Mission
from fedmap.mission.world.feed import MapFeed

#: The mission app's run-config keys and their defaults (``app/pyproject.toml`` holds the same).
MISSION_RUN_DEFAULTS: dict[str, Any] = {
    "mission": "",  # the resolved mission, TOML text
    "strategies": "",  # comma-separated; "" = the mission's own
    "out": "fedmap-out/mission",
    "frames": 60,  # the animation's frames per strategy (1: none kept)
    "connect-timeout": 120.0,  # seconds to wait for every rover to connect
    "deadline": 600.0,  # seconds a sync round may take
    "rejoin": 300.0,  # seconds a rover that stopped answering may take to come back
    "resume": False,  # carry on from the base station's journal (a base that was killed)
    "step-seconds": 0.0,  # a step of every node's own clock (0: lockstep, the base orders every step)
    "rover-nodes": "",  # each registered key's node and its rover, "node=rover,..." (the launcher's)
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
    rejoin: float
    resume: bool
    rover_nodes: str = ""
    step_seconds: float = 0.0

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
                   float(c["deadline"]), float(c["rejoin"]), bool(c["resume"]), str(c["rover-nodes"]),
                   float(c["step-seconds"]))


def strategies_of(run: MissionRun, mission: Mission) -> tuple[str, ...]:
    """The strategies the run deploys: the run config's, else the mission's own that can run on processes."""
    return run.strategies or tuple(s for s in mission.config.strategies if REGISTRY[s].deployable)


# -- a rover between messages ----------------------------------------------------------------


def base_log(out: Path, level: str, line: str) -> None:
    """One line in the base station's own log, ``<out>.run/base.log`` (``level``: INFO, WARNING)."""
    with open(run_dir(out) / "base.log", "a") as fh:
        fh.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {level} {line}\n")


def log_dir(state_dir: Path) -> Path:
    """Where a rover keeps its own log (:class:`~fedmap.mission.network.nodelog.RoverEntry` files):
    ``log/`` in its state folder. It stays when the mission is over: the mission is scored
    from it (``fedmap score``)."""
    return Path(state_dir) / "log"


def state_file(state_dir: Path, order: Order, k: int) -> Path:
    """Where rover ``k`` keeps its node of ``order``'s mission and strategy between messages
    (rovers sharing a state folder each keep their own file)."""
    return Path(state_dir) / f"{order.mission or 'mission'}-{order.strategy}-rover{k}.pickle"


def hold_state(state_dir: Path, k: int) -> int:
    """Hold rover ``k``'s state in ``state_dir`` for as long as this process (and what it
    forks) lives: an exclusive lock on ``rover{k}.lock`` there; returns its file descriptor.
    A second process of rover ``k`` on the same folder would overwrite its state: refused
    in one line."""
    import fcntl

    state_dir = Path(state_dir)
    state_dir.mkdir(parents=True, exist_ok=True)
    lock = state_dir / f"rover{k}.lock"
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        held = lock.read_text().strip() or "?"
        raise FedmapError(f"rover {k}: another rover {k} process (PID {held}) keeps its state in {state_dir}: "
                          "stop it first, or give this one its own --state") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def rover_answer(state_dir: Path, mission_text: str, k: int, raw: bytes, *, feed: MapFeed | None = None,
                 history: bytes | None = None) -> bytes:
    """Rover ``k``'s report to the order ``raw``. Its node (its world, end and clock) lives in
    ``state_dir`` between messages (its own state, written by itself, atomically with each
    report: a rover process killed and started again carries on where it was; the file goes
    when the mission's last order is answered). A rover whose state is gone refuses an order
    that carries on from a later step (:class:`LostState`); the base sends it again with
    ``history``, every order it sent this rover before (:func:`~fedmap.mission.network.remote.pack_history`),
    and the node is rebuilt from them (:meth:`ProcessRover.rebuild`). ``feed``: its observations
    come from its own mapping software (:mod:`fedmap.mission.world.feed`). :class:`CorruptMessage`
    for a damaged order."""
    order = Order.from_bytes(raw)
    path = state_file(state_dir, order, k)
    if history is not None:
        node = ProcessRover.rebuild(mission_from_text(mission_text, frames=1), order.strategy, k,
                                 unpack_history(history), feed=feed)
    elif path.is_file():
        try:
            node = pickle.loads(path.read_bytes())
        except Exception:  # a state file cut short or damaged: as good as lost (the base rebuilds it)
            raise LostState(f"rover {k}'s state file {path} does not load") from None
    else:
        node = ProcessRover(mission_from_text(mission_text, frames=1), order.strategy, k, feed=feed)
    report = node.answer(raw)
    for entry in node.log:  # its own log, beside its state (written first: a state never runs ahead of its log)
        write_log(log_dir(state_dir), entry)
    node.log = []
    if order.finish:
        path.unlink(missing_ok=True)
    else:
        atomic_write_bytes(path, pickle.dumps(node, protocol=pickle.HIGHEST_PROTOCOL))
    return report


def node_feed(node_config: dict) -> MapFeed | None:
    """A mission rover's map feed from its node config (``feed``, ``feed-topic``), or None."""
    path = node_config.get("feed")
    if not path:
        return None
    return MapFeed.open(Path(str(path)), topic=str(node_config.get("feed-topic") or "") or None)


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


# -- the base station's journal ----------------------------------------------------------------


class BaseJournal:
    """The base station's mission so far, in ``<out>.run/mission-journal/``: the mission's id
    and digest, and every round's reports (and faults), written atomically as each round's
    reports are in. The base's state is a function of the mission and those reports, so a
    base that was killed rebuilds it bit for bit by replaying them (``resume``), then
    carries on; a rover asked again for an order it already answered sends the same report."""

    def __init__(self, out: Path, mission_text: str, *, resume: bool) -> None:
        self.dir = run_dir(out) / "mission-journal"
        digest = hashlib.sha256(mission_text.encode()).hexdigest()[:16]
        meta = self.dir / "meta.json"
        if resume:
            try:
                saved = json.loads(meta.read_text())
            except (FileNotFoundError, ValueError):
                raise FedmapError(f"nothing to resume: no base station journal in {self.dir}") from None
            if saved.get("mission") != digest:
                raise FedmapError(f"the journal in {self.dir} is of another mission (its settings differ): run the "
                                  "same mission to resume it, or start again without --resume")
            self.mission_id = str(saved["id"])
        else:
            shutil.rmtree(self.dir, ignore_errors=True)
            self.mission_id = uuid.uuid4().hex[:12]
            atomic_write_bytes(meta, json.dumps({"id": self.mission_id, "mission": digest}).encode())

    def _path(self, strategy: str, i: int) -> Path:
        return self.dir / f"{strategy}-{i:05d}.frame"

    def saved(self, strategy: str) -> int:
        """How many rounds of ``strategy`` are in the journal (its first rounds, in order)."""
        n = 0
        while self._path(strategy, n).is_file():
            n += 1
        return n

    def load(self, strategy: str, i: int) -> tuple[dict[int, bytes], list[dict]]:
        header, blobs = unpack_frame(self._path(strategy, i).read_bytes())
        return dict(zip(header["rovers"], blobs)), list(header["faults"])

    def save(self, strategy: str, i: int, reports: dict[int, bytes], faults: list[dict]) -> None:
        ks = sorted(reports)
        atomic_write_bytes(self._path(strategy, i), pack_frame({"rovers": ks, "faults": faults},
                                                               [reports[k] for k in ks]))


# -- the base station's record ----------------------------------------------------------------


def lost_state(history: list[bytes], why: str) -> tuple[bytes, str]:
    """A rover that lost its state (``why``) and was sent ``history`` (every earlier order):
    the frame to rebuild it from, and the fault's line."""
    packed = pack_history(history)
    return packed, (f"lost its state ({why}); its {len(history)} earlier order(s) sent again with this one "
                    f"({len(packed) / 1e3:.1f} kB) to rebuild it")


class JournaledSend:
    """The base's ``send`` of one strategy's rounds (:func:`~fedmap.mission.network.remote.rounds`)
    over ``team`` (its ``faults``, ``send(strategy, orders, history)`` and ``note(strategy,
    what)``), through ``journal``: rounds already in it are replayed from it (a base that
    was resumed), every new round's reports are saved to it; every order each rover was sent
    is kept (to rebuild a rover that lost its state). ``say`` logs a line per round."""

    def __init__(self, journal: BaseJournal, name: str, team: Any, say: Callable[[str], None]) -> None:
        self.journal, self.name, self.team, self.say = journal, name, team, say
        self.saved, self.done = journal.saved(name), 0
        self.history: dict[int, list[bytes]] = {}

    def __call__(self, orders: dict[int, bytes]) -> dict[int, bytes]:
        name, team = self.name, self.team
        if self.done < self.saved:  # replayed: the base's state is rebuilt from what the rovers reported
            reports, faults = self.journal.load(name, self.done)
            team.faults += faults
        else:
            if self.done == self.saved and self.saved:
                team.note(name, f"base station resumed: {self.saved} round(s) replayed from its journal")
            before, t_round = len(team.faults), time.perf_counter()
            reports = team.send(name, orders, self.history)
            self.journal.save(name, self.done, reports, team.faults[before:])
            self.say(f"{name} order {self.done + 1}: {len(reports)} rovers answered in "
                     f"{time.perf_counter() - t_round:.3f} s")
        self.done += 1
        for k, raw in orders.items():
            self.history.setdefault(k, []).append(raw)
        return reports


def base_dir(out: Path) -> Path:
    """Where the base station keeps its own log (:class:`~fedmap.mission.network.nodelog.BaseRecord` files)."""
    return run_dir(out) / "base"


__all__ = ["MISSION_RUN_DEFAULTS", "BaseJournal", "CorruptMessage", "JournaledSend", "LostState", "MissionRun", "base_dir",
           "damaged",
           "log_dir", "lost_state", "mission_from_text", "node_feed", "parse_mission_fault", "rover_answer", "state_file",
           "strategies_of"]
