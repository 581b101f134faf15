"""``fedmap mission --deploy zenoh``: a whole team on this machine, over Zenoh.

The base station runs in this process (:func:`~fedmap.zenohnet.base.run_base`), listening
on a free port of 127.0.0.1; each rover is a process of its own (``fedmap node rover``,
forked from a host that imported fedmap and torch once, as ``--deploy local``'s rovers are:
:class:`~fedmap.flower.mission.deploy.RoverHost`; its PID in ``<out>.run/rover<k>.pid``) that
connects to it. By default every link is TLS with mutual authentication, from a throw-away
CA made for the run (its key never written; the certificates go when the run ends), and the
base enforces access control (rover ``k`` answers only under its own keys). A rover process
that exits is started again (it rebuilds itself from the base's orders). The run's files and
every process's log are in ``<out>.run/``; the result is scored from the nodes' logs
(:func:`~fedmap.mission.scoring.score_folder`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
import tomllib
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.launch import Processes, free_port, make_certs, sigterm_as_interrupt, socket_dir
from fedmap.flower.mission.deploy import ROVER_HOST, ROVER_HOST_SOCKET, RoverHost
from fedmap.flower.mission.task import base_dir, base_log
from fedmap.mission.results import MissionResult
from fedmap.mission.scoring import RUN_FILE, score_folder
from fedmap.zenohnet.base import ZenohTeam, run_base
from fedmap.zenohnet.peer import run_lander
from fedmap.zenohnet.session import Certs, acl, node_config, open_session

#: Rover processes started again after they exited, in all, before the mission fails.
ROVER_PROCESS_RESTARTS = 20


def rover_argv(k: int, *, connect: str, team: str, state: Path, certs: Path | None = None,
               fault: str | None = None, command: str = "rover") -> list[str]:
    """``fedmap node rover`` for member ``k`` (what each rover's computer runs; ``command``
    ``peer``: ``fedmap node peer``, a rover of a peer mission)."""
    argv = [sys.executable, "-m", "fedmap", "node", command, "--rover", str(k), "--connect", connect, "--team", team,
            "--state", str(state)]
    if certs is not None:
        argv += ["--certs", str(certs)]
    if fault:
        argv += ["--fault", fault]
    return argv


def _prepare(out: Path, members: int, *, tls: bool, resume: bool) -> tuple[Path, Path | None, str]:
    """A run's folder (the logs and records of an earlier run into it gone, unless
    ``resume``), its certificates (``tls``: a throw-away CA whose key is never written) and
    the address its base or lander listens on (a free port of 127.0.0.1)."""
    work = run_dir(out)
    work.mkdir(parents=True, exist_ok=True)
    if not resume:  # a rover's log and the base's records of an earlier run are not this run's
        for old in work.glob("rover*.state"):
            shutil.rmtree(old, ignore_errors=True)
        shutil.rmtree(base_dir(out), ignore_errors=True)
    (work / RUN_FILE).unlink(missing_ok=True)
    certs = work / "certs" if tls else None
    if certs is not None:  # the certificates go with the run
        make_certs(certs, hosts=["127.0.0.1", "localhost"], rovers=members, overwrite=True, keep_ca_key=False)
    return work, certs, f"{'tls' if tls else 'tcp'}/127.0.0.1:{free_port('127.0.0.1')}"


def _open(stack: contextlib.ExitStack, work: Path, certs: Path | None, address: str, team: str, members: int,
          env: dict, *, mode: str) -> tuple[Processes, RoverHost, Any]:
    """The processes of a run on this machine, within ``stack``: the host the rovers are forked
    from (fedmap and torch imported once, their pages shared) and the base's (or lander's)
    Zenoh session listening on ``address``, with TLS and access control when ``certs``."""
    socks = stack.enter_context(socket_dir("fedmap-rovers-", ROVER_HOST_SOCKET))
    procs = stack.enter_context(Processes())
    stack.enter_context(sigterm_as_interrupt())
    host = RoverHost(procs, socks, env=env, log=work / f"{ROVER_HOST}.log")
    session = open_session(node_config(listen=[address], certs=None if certs is None else Certs.for_node(certs, "base"),
                                       access=None if certs is None else acl(team, members), mode=mode))
    stack.callback(session.close)
    return procs, host, session


def _start(host: RoverHost, work: Path, k: int, argv: list[str], env: dict) -> None:
    """Rover ``k``'s process, forked from ``host``; its PID recorded for whoever runs the machine."""
    p = host.start(f"rover{k}", argv, env=env, log=work / f"rover{k}.log")
    atomic_write_bytes(work / f"rover{k}.pid", f"{p.pid}\n".encode())


def deploy_zenoh(mission_toml: str, *, members: int, out: Path, strategies: tuple[str, ...] = (), frames: int = 60,
                 resume: bool = False, step_seconds: float = 0.0, deadline: float = 600.0,
                 connect_timeout: float = 120.0, rejoin: float = 120.0, tls: bool = True, team: str = "fedmap",
                 faults: dict[int, str] | None = None,
                 on_step: Callable[[str, int], None] | None = None,
                 on_started: Callable[[float], None] | None = None) -> MissionResult:
    """Run the mission ``mission_toml`` (resolved TOML) with one process per rover over
    Zenoh on this machine; its result. ``tls``: mutual TLS and access control (the default).
    ``on_started(seconds)``: every rover is up (the start-up's wall time), the mission begins.
    ``faults``: per rover, a fault it injects (tests only: ``corrupt@STEP``). A mesh or
    leader mission runs as peers (:func:`deploy_peers`)."""
    if tomllib.loads(mission_toml).get("link", {}).get("topology", "star") != "star":
        if resume or step_seconds:
            raise FedmapError("a peer mission on processes runs in lockstep from its start: --resume and "
                              "--step-seconds are for the star")
        return deploy_peers(mission_toml, members=members, out=out, strategies=strategies, frames=frames,
                            connect_timeout=connect_timeout, tls=tls, team=team, faults=faults, on_step=on_step,
                            on_started=on_started)
    out = Path(out).resolve()
    work, certs, address = _prepare(out, members, tls=tls, resume=resume)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    restarted: list[dict] = []
    status = {"strategy": "", "step": 0}
    t0 = time.perf_counter()
    try:
        with contextlib.ExitStack() as stack:
            procs, host, session = _open(stack, work, certs, address, team, members, env, mode="peer")
            argvs = {k: rover_argv(k, connect=address, team=team, state=work / f"rover{k}.state", certs=certs,
                                   fault=(faults or {}).get(k)) for k in range(members)}

            def start(k: int) -> None:
                _start(host, work, k, argvs[k], env)

            def watch() -> None:  # a rover process that exited is started again (it rebuilds itself)
                for k in range(members):
                    code = procs.procs[f"rover{k}"].poll()
                    if code is None:
                        continue
                    if len(restarted) >= ROVER_PROCESS_RESTARTS:
                        raise FedmapError(f"rover {k}'s process exited (code {code}) after {len(restarted)} restarts; "
                                          f"its log: {work / f'rover{k}.log'}")
                    restarted.append({"strategy": status["strategy"], "rover": k,
                                      "fault": f"rover process exited (code {code}) near step {status['step']}; "
                                               "started again"})
                    base_log(out, "WARNING", f"{status['strategy']} rover {k}: {restarted[-1]['fault']}")
                    start(k)

            team_ = ZenohTeam(session, team, members, out, deadline=deadline, rejoin=rejoin, watch=watch)
            stack.callback(team_.close)
            for k in range(members):
                start(k)
            team_.wait_for_rovers(connect_timeout)
            if on_started is not None:
                on_started(time.perf_counter() - t0)

            def stepped(name: str, step: int) -> None:
                status.update(strategy=name, step=step)
                if on_step is not None:
                    on_step(name, step)

            run_base(team_, mission_toml, out=out, strategies=strategies, frames=frames, resume=resume,
                     step_seconds=step_seconds, connect_timeout=connect_timeout, on_step=stepped)
            team_.finish()
            for k in range(members):  # each stops once told the mission is over
                with contextlib.suppress(Exception):
                    procs.procs[f"rover{k}"].wait(timeout=30)
    except KeyboardInterrupt:
        raise FedmapError(f"mission interrupted ({status['strategy'] or 'before the first strategy'}, step "
                          f"{status['step']}); its processes are stopped; logs in {work}") from None
    finally:  # no private key outlives the run
        if certs is not None:
            shutil.rmtree(certs, ignore_errors=True)
    result = score_folder(work, frames=frames)
    return replace(result, faults=(*result.faults, *restarted))


def deploy_peers(mission_toml: str, *, members: int, out: Path, strategies: tuple[str, ...] = (), frames: int = 60,
                 connect_timeout: float = 120.0, tls: bool = True, team: str = "fedmap",
                 faults: dict[int, str] | None = None, on_step: Callable[[str, int], None] | None = None,
                 on_started: Callable[[float], None] | None = None) -> MissionResult:
    """Run the peer mission ``mission_toml`` (mesh or leader) with one process per rover
    over Zenoh on this machine, the lander in this process
    (:func:`~fedmap.zenohnet.peer.run_lander`: the team's router, and its own agent when it
    is one); its result, scored from every agent's log. ``tls`` and ``faults`` as
    :func:`deploy_zenoh`'s. A rover process that stops leaves the team: the others go on
    without it (a line of the run's faults; its last record stands)."""
    out = Path(out).resolve()
    work, certs, address = _prepare(out, members, tls=tls, resume=False)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    status = {"strategy": "", "step": 0}
    t0 = time.perf_counter()
    try:
        with contextlib.ExitStack() as stack:
            procs, host, session = _open(stack, work, certs, address, team, members, env, mode="router")
            for k in range(members):
                _start(host, work, k, rover_argv(k, connect=address, team=team, state=work / f"rover{k}.state",
                                                 certs=certs, fault=(faults or {}).get(k), command="peer"), env)

            exited: set[int] = set()

            def watch() -> None:  # a rover process that stopped: the team goes on without it (the lander notes it)
                for k in range(members):
                    code = procs.procs[f"rover{k}"].poll()
                    if code not in (None, 0) and k not in exited:
                        exited.add(k)
                        base_log(out, "WARNING", f"{status['strategy']} rover {k}: its process exited (code {code}) "
                                                 f"near step {status['step']}; its log: {work / f'rover{k}.log'}")

            def stepped(name: str, step: int) -> None:
                status.update(strategy=name, step=step)
                if on_step is not None:
                    on_step(name, step)

            def started() -> None:
                if on_started is not None:
                    on_started(time.perf_counter() - t0)

            run_lander(session, team, mission_toml, out=out, strategies=strategies, connect_timeout=connect_timeout,
                       frames=frames, on_step=stepped, watch=watch, on_started=started)
            for k in range(members):
                with contextlib.suppress(Exception):
                    procs.procs[f"rover{k}"].wait(timeout=30)
    except KeyboardInterrupt:
        raise FedmapError(f"mission interrupted ({status['strategy'] or 'before the first strategy'}, step "
                          f"{status['step']}); its processes are stopped; logs in {work}") from None
    finally:
        if certs is not None:
            shutil.rmtree(certs, ignore_errors=True)
    return score_folder(work, frames=frames)


__all__ = ["ROVER_PROCESS_RESTARTS", "deploy_peers", "deploy_zenoh", "rover_argv"]
