"""``fedmap federate-predictor --deploy local``: the predictor's federated fine-tuning on real
processes, started and waited for.

On this machine: a SuperLink on 127.0.0.1, one SuperNode per site (each given only its own
samples file, node config ``samples``), and the predictor's ServerApp
(:mod:`fedmap.flower.predictor.server`) submitted with ``flwr run``. The command returns the
global weights of every round; every process's log is in ``<out>.run/``. Nothing here
imports ``flwr``.

Each site's SuperNode runs its messages' ClientApps warm, as a rover's does
(:mod:`fedmap.flower.warm`): one server process per site imports Flower's ClientApp
runtime, torch and fedmap once and forks a ClientApp per message, instead of Flower's fresh
``flwr-clientapp`` process per message that imports them all again.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from fedmap.errors import FedmapError
from fedmap.flower import POLL_ENV, SUPEREXEC_POLL_ENV
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.launch import (
    SUPERLINK_EXES,
    SUPERNODE_EXES,
    Proc,
    Processes,
    flower_env,
    free_port,
    read_status,
    require_executables,
    sigterm_as_interrupt,
    socket_dir,
    start_superlink,
    submit_run,
    wait_for_result,
)
from fedmap.flower.mission.deploy import LOCAL_POLL
from fedmap.flower.predictor.task import PredictorRun, read_rounds
from fedmap.flower.rover import WarmChild, supernode_argv, write_shim
from fedmap.flower.task import run_status_path, write_status
from fedmap.nets.model import Weights


def _server_alive(server: Proc) -> Callable[[], bool]:
    """Whether a site's warm server is still running."""
    return lambda: server.poll() is None


def predictor_app_dir() -> Path:
    """The predictor's Flower App (its ``pyproject.toml``) that ``flwr run`` submits."""
    return Path(__file__).resolve().parent / "app"


def deploy_predictor(samples: Sequence[Path], *, out: Path, rounds: int, run_config: dict | None = None,
                     on_status: Callable[[dict], None] | None = None) -> list[Weights]:
    """Federated fine-tuning over one SuperNode per file of ``samples`` (site ``k`` reads
    ``samples[k]`` only) for ``rounds`` rounds; the global weights after every round.
    ``run_config``: the other keys of :data:`~fedmap.flower.predictor.task.PREDICTOR_RUN_DEFAULTS`."""
    out = Path(out).resolve()
    config = {**(run_config or {}), "sites": len(samples), "rounds": rounds, "out": str(out)}
    run = PredictorRun.from_run_config(config)  # a bad run config fails here, before any process starts
    files = [Path(s).resolve() for s in samples]
    for f in files:
        if not f.is_file():
            raise FedmapError(f"no such site samples file: {f}")
    require_executables(SUPERLINK_EXES)
    require_executables(SUPERNODE_EXES)
    work = run_dir(out)
    work.mkdir(parents=True, exist_ok=True)
    env = flower_env(work / "flwr-home")
    run_status_path(out).unlink(missing_ok=True)
    port = free_port()
    try:
        with socket_dir("fedmap-sites-", "site999.sock") as socks, Processes() as procs, sigterm_as_interrupt():
            start_superlink(procs, host="127.0.0.1", port=port, tls=None, auth=False, env=env, work=work)
            site_env = {**env, POLL_ENV: str(LOCAL_POLL), SUPEREXEC_POLL_ENV: str(LOCAL_POLL)}
            nodes = []
            for k, f in enumerate(files):
                node = {"partition-id": k, "samples": str(f), "done-file": str(work / f"site{k}.done")}
                sock, shim = str(socks / f"site{k}.sock"), socks / f"site{k}-bin"
                write_shim(shim, sock)  # the SuperNode's flwr-clientapp: hands each message to the warm server
                node_env = {**site_env, "FLWR_HOME": str(work / f"site{k}-home"),
                            "PATH": os.pathsep.join([str(shim), site_env["PATH"]])}
                procs.start(f"site{k}-clientapps", [sys.executable, "-m", "fedmap.flower.warm", sock, json.dumps(node)],
                            env=node_env, log=work / f"site{k}.clientapps.log", die_with_parent=True)
                nodes.append((node, sock))
            for k, (node, sock) in enumerate(nodes):  # each site's SuperNode, forked by its server
                argv = supernode_argv(superlink=f"127.0.0.1:{port}", port=free_port(), node_config=node,
                                      root_cert=None, auth_key=None, max_wait=120)
                server = procs.procs[f"site{k}-clientapps"]
                node_log = work / f"site{k}.log"
                procs.adopt(f"site{k}", WarmChild(sock, argv[3:], log=node_log, alive=_server_alive(server)),
                            log=node_log)
            since = time.time() - 1
            submit_run(work / "flwr-home", {k: v for k, v in config.items()}, env=env, app=predictor_app_dir())

            def alive() -> None:
                procs.check_alive("superlink")
                for k in range(len(files)):
                    procs.check_alive(f"site{k}")
                    procs.check_alive(f"site{k}-clientapps")

            budget = run.connect_timeout + rounds * run.deadline + 120
            wait_for_result(out, since=since, timeout=budget, alive=alive, on_status=on_status)
    except KeyboardInterrupt:
        st = read_status(out) or {}
        write_status(out, "interrupted", message="interrupted")
        raise FedmapError(f"federated fine-tuning interrupted (round {st.get('round', 0)}); its processes are "
                          f"stopped; logs in {work}") from None
    return read_rounds(out, rounds)


__all__ = ["LOCAL_POLL", "deploy_predictor", "predictor_app_dir"]
