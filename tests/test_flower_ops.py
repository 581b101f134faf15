"""What a field operator gets wrong, and what a killed process leaves behind: one-line errors,
bounded waits, no orphans. Fast checks first; the few real Flower processes are marked slow."""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("flwr")

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.flower import launch  # noqa: E402
from fedmap.flower.launch import (  # noqa: E402
    Processes,
    flower_env,
    free_port,
    require_executables,
    rover_failure,
    rover_node_config,
    run_base_station,
)
from fedmap.flower.settings import RunSettings  # noqa: E402
from fedmap.maps.grid import GridMap  # noqa: E402
from fedmap.maps.io import save_map  # noqa: E402


def test_flower_helpers_resolve_from_this_interpreter_without_path(monkeypatch, tmp_path):
    """Flower starts flower-superexec / flwr-clientapp by name: with the venv's bin/ off PATH
    they must still resolve to this environment's."""
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    env = flower_env(tmp_path)
    here = str(Path(sys.executable).parent)
    assert env["PATH"].split(os.pathsep)[0] == here
    for exe in launch.SUPERLINK_EXES + launch.SUPERNODE_EXES:
        assert shutil.which(exe, path=env["PATH"]) == os.path.join(here, exe)
    require_executables(launch.SUPERLINK_EXES)  # all present here
    monkeypatch.setattr(launch.sys, "executable", str(tmp_path / "python"))
    with pytest.raises(FedmapError, match=r"^Flower executable\(s\) flower-superexec, flwr-clientapp not found"):
        require_executables(("flower-superexec", "flwr-clientapp"))


def test_children_die_with_a_killed_parent(tmp_path):
    """kill -9 of the base station must not leave its SuperLink behind (PR_SET_PDEATHSIG)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux-only")
    code = ("import sys, time\n"
            "from pathlib import Path\n"
            "from fedmap.flower.launch import Processes\n"
            "p = Processes().start('child', ['sleep', '60'], env={}, log=Path(sys.argv[1]), die_with_parent=True)\n"
            "print(p.pid, flush=True)\n"
            "time.sleep(60)\n")
    with subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "child.log")], stdout=subprocess.PIPE,
                          text=True) as parent:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        os.kill(child, 0)  # alive
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
    t_end = time.monotonic() + 10
    while time.monotonic() < t_end:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the child outlived its SIGKILLed parent")


def test_operator_mistakes_are_one_line_errors(tmp_path):
    with pytest.raises(FedmapError, match=r"^rovers must be >= 1 .*got 0$"):
        RunSettings.from_run_config({"rovers": 0})
    (tmp_path / "bad.png").write_bytes(b"not a png")
    for path, why in ((tmp_path / "bad.png", "not a valid PNG"), (tmp_path / "nope.npy", "no such file")):
        with pytest.raises(FedmapError, match=rf"^rover 2: .*{why}") as e:
            rover_node_config(partition_id=2, map_path=path, terrain=None, size=64, agents=4, explore="quadrants",
                              seed=0, out=None)
        assert "\n" not in str(e.value)
    # a typo in --truth fails before any process starts (it used to cost the whole run)
    started = []
    with pytest.raises(FedmapError, match="no such file"):
        run_base_station({"truth": str(tmp_path / "truht.png"), "out": str(tmp_path / "out")},
                         on_ready=lambda: started.append(1))
    assert not started and not (tmp_path / "out.run" / "superlink.log").exists()


def test_an_exact_map_prints_infinite_psnr():
    from fedmap.cli.flower import _db

    assert _db(None) == "inf dB (exact)" and _db(12.345) == "12.35 dB"


SUPERNODE_305 = """\x1b[93mWARNING \x1b[0m:   Giving up reconnection after 5.00 seconds and 5 tries.
\x1b[91mERROR \x1b[0m:     Exit Code: 305
Failed to initialize the connection to the SuperLink.
[Errno 111] Connection refused
"""


def test_rover_failures_name_the_rover_and_the_problem():
    line = rover_failure(3, "10.0.0.2:9092", SUPERNODE_305, max_wait=5, code=1)
    assert line.startswith("rover 3: no SuperLink answered at 10.0.0.2:9092 for 5 s; gave up")
    # what flower-supernode 1.41 logs for a CA that did not sign the SuperLink's certificate ...
    tls = ("\x1b[91mERROR \x1b[0m:     SSL/TLS handshake error detected.\n\x1b[91mERROR \x1b[0m:     Exit Code: 305\n"
           "Failed to initialize the connection to the SuperLink.\n[SSL: CERTIFICATE_VERIFY_FAILED] certificate "
           "verify failed: certificate signature failure (_ssl.c:1006)\n")
    assert rover_failure(1, "h:1", tls, max_wait=5, code=1) == (
        "rover 1: TLS certificate problem with h:1 (wrong --root-cert?): [SSL: CERTIFICATE_VERIFY_FAILED] "
        "certificate verify failed: certificate signature failure (_ssl.c:1006)")
    # ... and for a key the SuperLink has not registered
    refused = ("\x1b[91mERROR \x1b[0m:     Exit Code: 305\nFailed to initialize the connection to the SuperLink.\n"
               "[code: 2004] Failed to activate SuperNode.\nThe SuperNode could not establish a connection to the "
               "SuperLink.\n")
    assert rover_failure(4, "h:1", refused, max_wait=5, code=1).startswith("rover 4: the SuperLink at h:1 refused "
                                                                            "this rover's key")
    other = "INFO : starting\n\x1b[91mERROR \x1b[0m:     something odd\n"
    assert rover_failure(0, "h:1", other, max_wait=5, code=7) == ("rover 0: the Flower SuperNode exited with code 7: "
                                                                  "something odd")


@pytest.mark.slow
def test_a_rover_pointed_at_the_wrong_port_gives_up_in_one_line(tmp_path):
    """A real `fedmap rover` against a port nobody listens on: bounded wait, one line, exit 2,
    and no temporary folder left behind."""
    save_map(GridMap(np.zeros((64, 64), np.uint8), 1.0, "m"), tmp_path / "m.npy")
    env = {**os.environ, "TMPDIR": str(tmp_path), "FLWR_HOME": str(tmp_path / "home")}
    argv = [sys.executable, "-m", "fedmap", "rover", "--superlink", f"127.0.0.1:{free_port()}", "--partition-id", "2",
            "--map", str(tmp_path / "m.npy"), "--max-wait", "3"]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("error: rover 2: no SuperLink answered at 127.0.0.1:") and "for 3 s; gave up" in last
    assert not list(tmp_path.glob("fedmap-rover-flwr-*"))


def test_processes_sharing_our_group_are_stopped_alone(tmp_path):
    with Processes() as procs:
        p = procs.start("s", ["sleep", "30"], env={}, log=tmp_path / "s.log", new_session=False)
        assert os.getpgid(p.pid) == os.getpgid(0)
        procs.stop("s", grace=5)
        assert p.poll() is not None  # and we are still here: our own group was not signalled


@pytest.mark.slow
def test_sigterm_stops_the_base_station_in_one_line_and_records_it(tmp_path):
    """SIGTERM: the SuperLink is stopped (its port is free again), status.json says
    interrupted, and the command prints one line and exits 2."""
    import json
    import socket

    port, out = free_port(), tmp_path / "out"
    env = {**os.environ, "FLWR_HOME": str(tmp_path / "home")}
    argv = [sys.executable, "-m", "fedmap", "base-station", "--rovers", "2", "--port", str(port), "--host", "127.0.0.1",
            "--net", "small", "--init", "random", "--out", str(out), "--connect-timeout", "300"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) as base:
        try:
            t_end = time.monotonic() + 120
            assert base.stdout is not None
            while time.monotonic() < t_end and "ready" not in base.stdout.readline():
                pass
            base.send_signal(signal.SIGTERM)
            _, err = base.communicate(timeout=60)
        finally:
            if base.poll() is None:
                base.kill()
    assert base.returncode == 2, err
    assert err.strip().splitlines()[-1].startswith("error: base station interrupted ")
    assert json.loads((tmp_path / "out.run" / "status.json").read_text())["state"] == "interrupted"
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))  # nobody listens there any more


def test_base_station_starts_from_the_meta_init_like_the_demo():
    from typer.testing import CliRunner

    from fedmap.cli import app
    from fedmap.config import method_config

    assert RunSettings.from_run_config({}).pipeline.init == method_config("paper").init == "meta"
    help_text = CliRunner().invoke(app, ["base-station", "--help"], env={"COLUMNS": "200"}).output
    assert all(word in help_text for word in ("random", "empty", "meta"))


FAKE_SUPERNODE = """
import pathlib, sys
count, done, kicks = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), int(sys.argv[3])
n = int(count.read_text()) if count.exists() else 0
count.write_text(str(n + 1))
if n < kicks:  # what Flower's SuperNode logs when a new SuperLink does not know its node
    print("httpx.HTTPStatusError: Client error '401 Unauthorized' for url '.../send-node-heartbeat'")
    sys.exit(1)
if kicks < 0:
    print("ERROR : Exit Code: 305 ... Giving up reconnection after 5.00 seconds and 5 tries.")
    sys.exit(1)
done.write_text("1")  # the ClientApp received the final model
"""


@pytest.mark.parametrize("kicks", [2, -1])
def test_a_rover_reconnects_when_the_base_station_restarts(tmp_path, monkeypatch, kicks):
    """A resumed base station is a new SuperLink: the rover's SuperNode is refused (401) and
    the rover starts a new one, a bounded number of times; a real failure is not retried."""
    (tmp_path / "fake.py").write_text(FAKE_SUPERNODE)
    count = tmp_path / "count"

    def fake_argv(**kw):
        return [sys.executable, str(tmp_path / "fake.py"), str(count), kw["node_config"]["done-file"], str(kicks)]

    monkeypatch.setattr(launch, "supernode_argv", fake_argv)
    cfg = {"partition-id": 1, "map": "unused"}
    if kicks > 0:
        assert launch.run_rover(cfg, superlink="127.0.0.1:1", warm=False, max_wait=5) == 0
        assert count.read_text() == "3"
    else:
        with pytest.raises(FedmapError, match="^rover 1: no SuperLink answered at 127.0.0.1:1 for 5 s"):
            launch.run_rover(cfg, superlink="127.0.0.1:1", warm=False, max_wait=5)
        assert count.read_text() == "1"
