"""``fedmap mission --deploy``: a mission on real processes, started and waited for.

``local``: on this machine, a SuperLink with TLS and SuperNode authentication (a fresh CA,
server certificate and one key pair per rover, :func:`~fedmap.flower.launch.make_certs`),
one rover process per member of the team (``fedmap rover --mission``: its SuperNode, kept
connected), and the mission's ServerApp (:mod:`fedmap.flower.mission.server`), all on
127.0.0.1. ``base``: only the base station, for rovers on other machines (``--certs`` and
``--auth-keys`` unless it listens on loopback or ``--insecure``). Either way the command
returns the finished :class:`~fedmap.mission.results.MissionResult`, scored from the
nodes' own logs (:func:`fedmap.mission.scoring.score_folder`), and every process's log is
in ``<out>.run/`` (kept beside the outputs as ``logs/``).

Nothing here imports ``flwr``.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.launch import (
    SUPERLINK_EXES,
    Proc,
    Processes,
    Tls,
    check_exposure,
    flower_env,
    free_port,
    make_certs,
    read_status,
    require_executables,
    sigterm_as_interrupt,
    socket_dir,
    start_superlink,
    submit_run,
    wait_for_result,
)
from fedmap.flower.mission.task import MissionRun, base_dir, base_log
from fedmap.flower.rover import WarmChild
from fedmap.flower.task import rover_nodes_text, run_status_path, write_status
from fedmap.flower.warm import ROVER
from fedmap.mission.results import MissionResult
from fedmap.mission.scoring import RUN_FILE, score_folder

#: Seconds between a local rover's polls of its SuperLink, and its SuperExec's for a task. Polls
#: are not free on two cores: with three loopback missions side by side (tests/, the suite's lanes)
#: rovers polling every 0.05 s (the base every 0.02 s) took a quarter of the CPU and made each
#: mission 190 s against 147 s at 0.25 s (the base 0.05 s, :data:`fedmap.flower.polling.POLL`);
#: alone, 0.25 s cost a round nothing measurable (docs/processes.md).
LOCAL_POLL = 0.25
#: Seconds between a local rover's heartbeats; None: Flower's own (30 s in 1.41), no
#: ``--heartbeat`` passed. The base station takes a rover for gone after two missed ones.
#: 10 s (gone after 20 s) was tried: a killed rover started again (its key, so its node id,
#: unchanged) took about 20 s to come back, and activated just as its old node lapsed; the
#: base never saw the node offline, so the order its old process had taken was neither
#: answered nor reported lost, and the mission waited out the round's whole deadline (600 s).
#: With 30 s the rover started again is refused until the old node lapses, and each retry
#: leaves the base seconds to see it offline.
LOCAL_HEARTBEAT: float | None = None
#: ``--deploy local``: rover processes started again after they died, in all, before the mission fails.
ROVER_PROCESS_RESTARTS = 20
#: ``--deploy local``: the process the rovers are forked from (:func:`fedmap.flower.warm.serve_rovers`),
#: its module and its socket's name. It imports fedmap, torch and Flower's runtime once for the team:
#: a rover started as a fresh Python imports them for itself, about 5 s of CPU each.
ROVER_HOST, ROVER_HOST_MODULE, ROVER_HOST_SOCKET = "rover-host", "fedmap.cli.rover_host", "rovers.sock"
#: Where ``fedmap mission --deploy`` runs.
DEPLOY_MODES = ("local", "base")


def mission_app_dir() -> Path:
    """The mission's Flower App (its ``pyproject.toml``) that ``flwr run`` submits."""
    return Path(__file__).resolve().parent / "app"


def rover_argv(k: int, *, superlink: str, root_cert: Path | None, auth_key: Path | None, log: Path, state: Path,
               poll: float = LOCAL_POLL, heartbeat: float | None = LOCAL_HEARTBEAT,
               fault: str | None = None) -> list[str]:
    """``fedmap rover --mission`` for member ``k`` (what each rover machine runs)."""
    argv = [sys.executable, "-m", "fedmap", "rover", "--mission", "--partition-id", str(k), "--superlink", superlink,
            "--log", str(log), "--max-wait", "120", "--poll", str(poll), "--state", str(state)]
    if heartbeat is not None:
        argv += ["--heartbeat", f"{heartbeat:g}"]
    if root_cert is not None:
        argv += ["--root-cert", str(root_cert)]
    if auth_key is not None:
        argv += ["--auth-key", str(auth_key)]
    if fault:
        argv += ["--fault", fault]
    return argv


def deploy_mission(mission_toml: str, *, members: int, out: Path, mode: str = "local", strategies: tuple[str, ...] = (),
                   frames: int = 60, host: str = "127.0.0.1", port: int = 0, certs: Path | None = None,
                   auth_keys: Path | None = None, insecure: bool = False, deadline: float = 600.0,
                   connect_timeout: float = 120.0, rounds: int = 1, resume: bool = False, poll: float = LOCAL_POLL,
                   step_seconds: float = 0.0,
                   faults: dict[int, str] | None = None,
                   on_status: Callable[[dict], None] | None = None,
                   on_ready: Callable[[str], None] | None = None) -> MissionResult:
    """Run the mission ``mission_toml`` (resolved TOML) on real processes; its result.

    ``members``: rovers and helicopters (one process each with ``local``). ``out``: where
    the outputs will go; the run's files (certificates, Flower's home, logs, status,
    result) are in ``<out>.run/``. ``on_ready(address)`` is called once the SuperLink
    listens (``base``: start the rovers then). ``rounds``: the orders of one strategy's
    mission (its syncs and the last), which bound the wait with ``deadline``. ``step_seconds`` > 0:
    every node runs on its own clock, a step every that many seconds (0: lockstep). ``faults``: per rover, a fault it injects
    (tests only, :func:`fedmap.flower.mission.task.parse_mission_fault`).
    """
    if mode not in DEPLOY_MODES:
        raise FedmapError(f"unknown --deploy {mode!r}: choose one of {', '.join(DEPLOY_MODES)}")
    out = Path(out).resolve()
    work = run_dir(out)
    work.mkdir(parents=True, exist_ok=True)
    require_executables(SUPERLINK_EXES)
    if mode == "local" and not resume:  # a rover's state from an earlier run is not this run's
        for old in work.glob("rover*.state"):
            shutil.rmtree(old, ignore_errors=True)
    if mode == "local":
        if host != "127.0.0.1" or certs is not None or auth_keys is not None:
            raise FedmapError("--deploy local makes its own certificates on 127.0.0.1; --host, --certs and --auth-keys "
                              "are for --deploy base")
        # a throw-away CA (its key never written) and rover keys that go with the run (removed when it ends)
        make_certs(work / "certs", hosts=["127.0.0.1", "localhost"], rovers=members, overwrite=True, keep_ca_key=False)
        certs = auth_keys = work / "certs"
    check_exposure(host, tls=certs is not None, auth=auth_keys is not None, insecure=insecure)
    tls = Tls.from_dir(certs) if certs is not None else None
    keys = sorted(Path(auth_keys).resolve().glob("*.pub")) if auth_keys is not None else []
    if auth_keys is not None and not keys:
        raise FedmapError(f"no rover public keys (*.pub) in {auth_keys}; make them with: fedmap certs DIR --rovers N")
    env = flower_env(work / "flwr-home")
    run_config = {"mission": mission_toml, "strategies": ",".join(strategies), "out": str(out), "frames": frames,
                  "connect-timeout": connect_timeout, "deadline": deadline, "resume": resume,
                  "step-seconds": step_seconds}
    MissionRun.from_run_config(run_config)  # a bad run config fails here, before any process starts
    run_status_path(out).unlink(missing_ok=True)
    (work / RUN_FILE).unlink(missing_ok=True)
    if not resume:  # the base's records of an earlier run are not this run's
        shutil.rmtree(base_dir(out), ignore_errors=True)
    port = port or free_port(host if host not in ("0.0.0.0", "::", "") else "127.0.0.1")
    try:
        with contextlib.ExitStack() as stack:
            socks = stack.enter_context(socket_dir("fedmap-rovers-", ROVER_HOST_SOCKET)) if mode == "local" else None
            procs = stack.enter_context(Processes())
            stack.enter_context(sigterm_as_interrupt())
            # the rovers are forked from it; it imports while the SuperLink starts
            rover_host = RoverHost(procs, socks, env=env, log=work / f"{ROVER_HOST}.log") if socks is not None else None
            address, nodes = start_superlink(procs, host=host, port=port, tls=tls, auth=auth_keys is not None,
                                             env=env, work=work, keys=keys)
            run_config["rover-nodes"] = rover_nodes_text(nodes)
            rovers: list[str] = []
            argvs: dict[str, list[str]] = {}
            restarted: list[dict] = []

            def start_rover(name: str, argv: list[str]) -> None:  # its PID recorded for whoever runs the machine
                assert rover_host is not None  # only --deploy local starts rovers
                p = rover_host.start(name, argv, env=env, log=work / f"{name}.log")
                atomic_write_bytes(work / f"{name}.pid", f"{p.pid}\n".encode())
            if rover_host is not None:
                for k in range(members):
                    name = f"rover{k}"
                    argvs[name] = rover_argv(k, superlink=f"127.0.0.1:{port}", root_cert=work / "certs" / "ca.crt",
                                             auth_key=work / "certs" / name, log=work / f"{name}.supernode.log",
                                             state=work / f"{name}.state", poll=poll, fault=(faults or {}).get(k))
                    start_rover(name, argvs[name])
                    rovers.append(name)
            since = time.time() - 1
            submit_run(Path(env["FLWR_HOME"]), run_config, env=env, app=mission_app_dir())
            if on_ready is not None:
                on_ready(address)

            def alive() -> None:
                procs.check_alive("superlink")
                for k, name in enumerate(rovers):
                    code = procs.procs[name].poll()
                    if code in (None, 0):
                        continue
                    if len(restarted) >= ROVER_PROCESS_RESTARTS:
                        procs.check_alive(name)
                    st = read_status(out) or {}
                    restarted.append({"strategy": st.get("strategy", ""), "rover": k,
                                      "fault": f"rover process exited (code {code}) near step {st.get('step', 0)}; "
                                               "started again"})
                    # the same record in the base's log as in metrics.json
                    base_log(out, "WARNING", f"{restarted[-1]['strategy']} rover {k}: {restarted[-1]['fault']}")
                    start_rover(name, [*argvs[name], "--rejoin"])

            budget = connect_timeout + 600 + max(len(strategies), 1) * rounds * deadline
            wait_for_result(out, since=since, timeout=budget, alive=alive,
                            on_status=on_status)
            for name in rovers:  # each stops once the base said the mission is over
                try:
                    procs.procs[name].wait(timeout=30)
                except Exception:  # noqa: BLE001 - a rover that lingers is stopped with the rest
                    pass
    except KeyboardInterrupt:
        st = read_status(out) or {}
        write_status(out, "interrupted", message="interrupted")
        raise FedmapError(f"mission interrupted ({st.get('strategy', 'before the first strategy')}, step "
                          f"{st.get('step', 0)}); its processes are stopped; logs in {work}") from None
    finally:  # no private key outlives the run: the run's own certificates (the control secret goes with procs)
        if mode == "local":
            shutil.rmtree(work / "certs", ignore_errors=True)
    result = score_folder(work, frames=frames)
    return replace(result, faults=(*result.faults, *restarted))


class RoverHost:
    """A host of rovers (:data:`ROVER_HOST`, :func:`fedmap.flower.warm.serve_rovers`) started
    under ``procs``, its socket in ``socks`` (a short folder: :func:`~fedmap.flower.launch.socket_dir`),
    its output in ``log``. It imports while the caller goes on; :meth:`start` forks a rover from it."""

    def __init__(self, procs: Processes, socks: Path, *, env: dict, log: Path) -> None:
        self.procs, self.sock = procs, str(socks / ROVER_HOST_SOCKET)
        self.proc = procs.start(ROVER_HOST, [sys.executable, "-m", ROVER_HOST_MODULE, self.sock], env=env, log=log,
                                die_with_parent=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def start(self, name: str, argv: list[str], *, env: dict, log: Path) -> Proc:
        """Rover ``name``: ``argv`` (``[python, -m, fedmap, rover, ...]``) forked by the host,
        watched by ``procs`` as ``name``, its output in ``log``; once the host is gone, started
        as a process of its own in ``env`` instead. It dies with the host, or with us."""
        if self.alive():
            try:
                return self.procs.adopt(name, WarmChild(self.sock, argv[3:], log=log, alive=self.alive, program=ROVER),
                                        log=log)
            except FedmapError:  # the host died meanwhile: this rover and the next start cold
                pass
        return self.procs.start(name, argv, env=env, log=log, die_with_parent=True)


def deploy_logs(out: Path) -> dict[str, str]:
    """Every process's log of the mission run for ``out`` (``logs/<name>.log`` -> text), for its outputs."""
    work = run_dir(Path(out).resolve())
    return {f"logs/{p.name}": p.read_text(errors="replace") for p in sorted(work.glob("*.log"))}


__all__ = ["DEPLOY_MODES", "RoverHost", "deploy_logs", "deploy_mission", "mission_app_dir", "rover_argv"]
