"""What a field operator gets wrong, and what a killed process leaves behind: one-line errors,
bounded waits, no orphans. Fast checks first; the few real Flower processes are marked slow."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("flwr")

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.flower import launch, rover  # noqa: E402
from fedmap.flower.launch import (  # noqa: E402
    Processes,
    flower_env,
    free_port,
    require_executables,
    run_base_station,
)
from fedmap.flower.rover import rover_failure, rover_node_config, superlink_answers  # noqa: E402
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

    assert RunSettings.from_run_config({}).pipeline.model.init == method_config("paper").model.init == "meta"
    help_text = CliRunner().invoke(app, ["base-station", "--help"], env={"COLUMNS": "200"}).output
    assert all(word in help_text for word in ("random", "empty", "meta"))


FAKE_SUPERNODE = """
import os, pathlib, sys, time
count, done, script = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), sys.argv[3].split(";")
n = int(count.read_text()) if count.exists() else 0
count.write_text(str(n + 1))
step = script[min(n, len(script) - 1)]
if step == "env":  # what the rover set for its SuperNode, then the final model
    (count.parent / "heartbeat").write_text(os.environ.get("FEDMAP_SUPERNODE_HEARTBEAT", "unset"))
    done.write_text("1")
    sys.exit(0)
if step == "served":  # the final model, its reply sent a second later; then it serves on, as Flower's does
    print("INFO :      Receiving: evaluate message (ID: 6e2a)\\nINFO :      Received successfully", flush=True)
    done.write_text("1")
    time.sleep(1)
    print("INFO :      Sending: evaluate message (ID: a78f)\\nINFO :      Sent successfully", flush=True)
    time.sleep(600)
if step == "unconfirmed":  # as seen through a link that failed after round 2: a train message and its
    # reply, then the final model, whose ClientApp ran while the SuperNode still retried confirming it
    print(LOGS["round"], flush=True)
    print("INFO :      Receiving: evaluate message (ID: 6e2a)\\nINFO :      Start `flwr-clientapp` process", flush=True)
    done.write_text("1")
    for _ in range(4):
        time.sleep(0.5)
        print("WARNING :   Connection attempt failed, retrying in 0.37 seconds", flush=True)
    print("INFO :      Received successfully\\nINFO :      Sending: evaluate message (ID: a78f)", flush=True)
    (count.parent / "sent").write_text("1")  # sent, then logged (the other order raced the rover's kill)
    print("INFO :      Sent successfully", flush=True)
    time.sleep(600)
if step == "bind":  # Flower's SuperNode starts its local API on its port first
    import socket
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn does
        try:
            s.bind(("127.0.0.1", int(sys.argv[4])))
        except OSError:
            print("ERROR:    [Errno 98] error while attempting to bind on address ('127.0.0.1', " + sys.argv[4]
                  + "): address already in use\\nRuntimeError: SuperNode Runtime HTTP API failed to start.",
                  flush=True)
            sys.exit(1)
    done.write_text("1")
    sys.exit(0)
if step == "done":  # the ClientApp received the final model
    done.write_text("1")
    sys.exit(0)
print(LOGS[step], flush=True)
if step.startswith("hang"):  # what Flower 1.41's SuperNode can do after it logged its own end
    time.sleep(600)
if step == "busy":  # exchanges with a SuperLink too busy to answer a probe in time, then the final model
    for _ in range(12):
        time.sleep(0.5)
        print("INFO :      Received successfully", flush=True)
    done.write_text("1")
    sys.exit(0)
sys.exit(1)
"""

#: What flower-supernode 1.41 logs, by case (the fake prints one per start, in order).
FAKE_LOGS = {
    # a new SuperLink (a resumed base station) does not know this node
    "kicked": "httpx.HTTPStatusError: Client error '401 Unauthorized' for url '.../send-node-heartbeat'",
    # nobody answers at the address
    "gone": "WARNING :   Giving up reconnection after 5.00 seconds and 5 tries.\nERROR :     Exit Code: 305",
    # the link dropped during a TLS handshake: Flower takes it for a certificate problem, gives up and hangs
    "hang-eof": ("SuperNode ID: 42\nERROR :     SSL/TLS handshake error detected.\nWARNING :   Giving up reconnection "
                 "after 0.94 seconds and 3 tries.\nERROR :     [SSL: UNEXPECTED_EOF_WHILE_READING] EOF occurred in "
                 "violation of protocol (_ssl.c:1006)\nINFO :      SuperNode terminated gracefully."),
    # reached its SuperLink, then keeps exchanging messages (the fake logs one every 0.5 s)
    "busy": "INFO :      SuperNode ID: 42",
    # one round: the message taken, confirmed, answered
    "round": ("INFO :      [RUN 1515]\nINFO :      Receiving: train message (ID: 2a0b)\nINFO :      Received "
              "successfully\nINFO :      Start `flwr-clientapp` process\nINFO :      [RUN 1515]\nINFO :      Sending: "
              "train message (ID: c184)\nINFO :      Sent successfully"),
    # silent: e.g. polling a SuperLink whose port went away
    "hang-silent": "INFO :      Starting Flower SuperNode",
    # a self-registering SuperNode's RegisterNode answered but the answer lost (a link reset): re-sent, refused
    "in-use": ("WARNING :   Giving up reconnection after 0.39 seconds and 2 tries.\nERROR :     Exit Code: 305\n"
               "Failed to initialize the connection to the SuperLink.\n[code: 23] Public key already in use."),
    # ActivateNode answered but the answer lost, sent again: the node is already online
    "refused-resent": ("WARNING :   Connection attempt failed, retrying in 0.70 seconds\nWARNING :   Giving up "
                       "reconnection after 0.74 seconds and 2 tries.\nERROR :     Exit Code: 305\n[code: 2004] Failed "
                       "to activate SuperNode."),
    "refused": ("ERROR :     Exit Code: 305\nFailed to initialize the connection to the SuperLink.\n[code: 2004] Failed "
                "to activate SuperNode."),
    "bad-ca": ("ERROR :     SSL/TLS handshake error detected.\nERROR :     Exit Code: 305\nFailed to initialize the "
               "connection to the SuperLink.\n[SSL: CERTIFICATE_VERIFY_FAILED] certificate verify failed: "
               "certificate signature failure (_ssl.c:1006)"),
}


def _fake_rover(tmp_path, monkeypatch, script: str, *, auth: bool = True, **kw):
    """run_rover against the fake SuperNode (``script``: its behaviour at each start, ';'-separated)."""
    (tmp_path / "fake.py").write_text(f"LOGS = {FAKE_LOGS!r}\n" + FAKE_SUPERNODE)
    count = tmp_path / "count"

    def fake_argv(**a):
        return [sys.executable, str(tmp_path / "fake.py"), str(count), a["node_config"]["done-file"], script,
                str(a["port"])]

    monkeypatch.setattr(rover, "supernode_argv", fake_argv)
    monkeypatch.setattr(rover, "PROBE_EVERY", 0.5)
    key = tmp_path / "rover1"  # SuperNode auth (a registered key); without: the SuperNode registers its own
    key.write_text("unused")
    t0 = time.monotonic()
    try:
        return rover.run_rover({"partition-id": 1, "map": "unused"}, superlink="127.0.0.1:1", warm=False,
                               log=tmp_path / "supernode.log", auth_key=key if auth else None,
                               **kw), int(count.read_text()), time.monotonic() - t0
    except FedmapError as e:
        return str(e), int(count.read_text()), time.monotonic() - t0


def test_a_rover_reconnects_when_the_base_station_restarts(tmp_path, monkeypatch):
    """A resumed base station is a new SuperLink: the rover's SuperNode is refused (401) and
    the rover starts a new one."""
    assert _fake_rover(tmp_path, monkeypatch, "kicked;kicked;done", max_wait=30)[:2] == (0, 3)


def test_a_rover_replaces_a_supernode_that_hangs_after_a_dropped_link(tmp_path, monkeypatch, capfd):
    """Flower's SuperNode gives up on an EOF in the TLS handshake (a link cut) and then hangs:
    the rover stops it within END_GRACE s of its last line and starts a new one."""
    code, starts, took = _fake_rover(tmp_path, monkeypatch, "hang-eof;hang-eof;done", max_wait=30)
    assert (code, starts) == (0, 3) and took < 2 * (rover.END_GRACE + 1) + 3
    err = capfd.readouterr().err
    assert err.count("rover 1: the link to 127.0.0.1:1 dropped or its SuperLink restarted; starting a new "
                     "SuperNode") == 2, err


@pytest.mark.parametrize("script", ["gone", "hang-silent", "kicked"])
def test_a_rover_gives_up_after_max_wait_without_an_answer(tmp_path, monkeypatch, script):
    """Nobody answers at the address (127.0.0.1:1): however the SuperNode behaves (gives up,
    hangs silently, is refused over and over), the rover ends in one line after ~max_wait s."""
    line, starts, took = _fake_rover(tmp_path, monkeypatch, script, max_wait=3)
    assert line.startswith("rover 1: no SuperLink answered at 127.0.0.1:1 for 3 s; gave up"), line
    assert 3 <= took < 3 + rover.PROBE_EVERY + rover.END_GRACE + 4
    assert starts == 1 if script == "hang-silent" else starts >= 2


def test_a_supernode_that_keeps_exchanging_is_not_taken_for_a_silent_superlink(tmp_path, monkeypatch):
    """The probe (127.0.0.1:1) never answers, as a SuperLink too busy to answer within the
    probe's timeout on a loaded machine; the SuperNode logs an exchange every 0.5 s for 6 s,
    twice max_wait. Each exchange is an answer: the rover keeps its SuperNode (one start) and
    ends with the final model. Counting only the first exchange stopped it after max_wait."""
    assert _fake_rover(tmp_path, monkeypatch, "busy", max_wait=3)[:2] == (0, 1)


def test_a_supernode_whose_port_was_taken_gets_a_new_one(tmp_path, monkeypatch):
    """Another process holds the port the rover picked for its SuperNode's local API (an
    outgoing connection can take a port between its pick and the SuperNode's bind): the
    SuperNode cannot start, and the rover starts the next one on a new port, not the same
    one again (which failed for two minutes in a CI run)."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        taken = held.getsockname()[1]
        picks = iter([taken])
        monkeypatch.setattr(rover, "free_port", lambda: next(picks, None) or free_port())
        assert _fake_rover(tmp_path, monkeypatch, "bind", max_wait=30)[:2] == (0, 2)


def test_a_rover_given_a_port_in_use_says_so_in_one_line(tmp_path, monkeypatch):
    """``--port`` names a port in use: not retried, one line naming it."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        taken = held.getsockname()[1]
        line, starts, _ = _fake_rover(tmp_path, monkeypatch, "bind", max_wait=30, port=taken)
    assert (line, starts) == (f"rover 1: port {taken} (--port, the SuperNode's local API) is in use on this "
                              "machine: give another, or 0 for any free port", 1)


def test_free_ports_are_outside_the_range_of_outgoing_connections():
    """What free_port gives can be bound, and no outgoing connection can have it as its source port."""
    from fedmap.flower.launch import ephemeral_ports

    low, high = ephemeral_ports()
    for _ in range(20):
        port = free_port()
        assert not low <= port <= high and port >= 1024
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))


def test_a_self_registered_key_already_in_use_is_retried(tmp_path, monkeypatch):
    """Without SuperNode auth each SuperNode registers a fresh key; "already in use" means its
    own registration went through and the answer was lost: a new SuperNode fixes it."""
    assert _fake_rover(tmp_path, monkeypatch, "in-use;done", max_wait=30)[:2] == (0, 2)


def test_a_certificate_problem_is_not_retried(tmp_path, monkeypatch):
    line, starts, _ = _fake_rover(tmp_path, monkeypatch, "bad-ca", max_wait=30)
    assert starts == 1 and line.startswith("rover 1: TLS certificate problem with 127.0.0.1:1 (wrong --root-cert?): "
                                           "[SSL: CERTIFICATE_VERIFY_FAILED]"), line


def test_a_refused_key_is_final_unless_it_may_be_a_second_activation(tmp_path, monkeypatch):
    """Flower answers 2004 both to an unregistered key and to a second SuperNode for a key
    whose first SuperNode is still listed online (until its heartbeat lapses, ~60 s): a
    rover whose key was accepted earlier retries; a rover refused from the start stops."""
    line, starts, _ = _fake_rover(tmp_path, monkeypatch, "refused", max_wait=30)
    assert starts == 1 and "refused this rover's key" in line, line
    for script, auth, starts in (("hang-eof;refused;refused;done", True, 4),  # accepted before
                                 ("refused-resent;done", True, 2),  # its activation was sent twice
                                 ("refused;done", False, 2)):  # no --auth-key: a new SuperNode, a new key
        (tmp_path / "count").unlink()
        assert _fake_rover(tmp_path, monkeypatch, script, auth=auth, max_wait=30)[:2] == (0, starts), script


def test_a_finished_rover_stops_its_supernode_once_the_last_reply_is_sent(tmp_path, monkeypatch):
    """Flower's SuperNode serves on after its run: the rover stops it as soon as it has
    answered every message it received, not after the longest grace it allows."""
    monkeypatch.setattr(rover, "DONE_GRACE", 60.0)
    code, starts, took = _fake_rover(tmp_path, monkeypatch, "served")
    assert (code, starts) == (0, 1) and took < 30, took


def test_a_finished_rover_waits_for_the_reply_to_a_message_not_yet_confirmed(tmp_path, monkeypatch):
    """The SuperNode logs "Received successfully" only once the SuperLink confirmed a message,
    and its ClientApp may have answered by then: counted by that line, the final model's
    reply looked sent when the ClientApp finished, and the rover killed its SuperNode before
    it went out (the base then lacked that rover's acknowledgement). Each message taken is
    counted by its ID instead."""
    code, starts, took = _fake_rover(tmp_path, monkeypatch, "unconfirmed")
    assert (code, starts) == (0, 1) and (tmp_path / "sent").exists() and took < 30, took
    log = FAKE_LOGS["round"] + "\nINFO :      Receiving: evaluate message (ID: 6e2a)"
    assert rover.replies_owed(log) == (2, 1)
    assert rover.replies_owed(log + "\nINFO :      Received successfully") == (2, 1)
    assert rover.replies_owed(log + "\nINFO :      Sending: evaluate message (ID: a78f)\nINFO :      Sent "
                              "successfully") == (2, 0)
    # a message it failed to take wants no reply
    assert rover.replies_owed(log + "\nERROR :     Failed to receive message 6e2a: gone") == (1, 0)


def test_a_rovers_heartbeat_reaches_flowers_supernode(tmp_path, monkeypatch):
    """``fedmap rover --heartbeat`` sets the interval the SuperNode activates with, sends with
    each heartbeat and waits by; an interval the SuperLink would refuse is one line, before
    anything starts."""
    import flwr.common.constant as flower_constants
    import flwr.supercore.heartbeat as beat
    import flwr.supernode.fleet_http_connection as fleet

    from fedmap.flower import HEARTBEAT_ENV, HEARTBEAT_RANGE, supernode

    assert HEARTBEAT_RANGE == (flower_constants.HEARTBEAT_MIN_INTERVAL, flower_constants.HEARTBEAT_MAX_INTERVAL)
    assert _fake_rover(tmp_path, monkeypatch, "env", heartbeat=12.5)[0] == 0
    assert (tmp_path / "heartbeat").read_text() == "12.5"
    (tmp_path / "x").mkdir()
    assert _fake_rover(tmp_path / "x", monkeypatch, "env")[0] == 0
    assert (tmp_path / "x" / "heartbeat").read_text() == "unset"  # Flower's own
    for bad in (5.0, 3600.0):
        with pytest.raises(FedmapError, match=r"^rover 1: --heartbeat must be in \[10, 1800\] s .*got "):
            rover.run_rover({"partition-id": 1}, superlink="127.0.0.1:1", heartbeat=bad)
    # the SuperNode process: Flower's constants, as its connection and heartbeat sender read them
    for module in (fleet, beat):
        monkeypatch.setattr(module, "HEARTBEAT_DEFAULT_INTERVAL", module.HEARTBEAT_DEFAULT_INTERVAL)
    monkeypatch.setattr(fleet, "make_simple_http_retry_invoker", fleet.make_simple_http_retry_invoker)
    seen = []
    monkeypatch.setattr(supernode, "flower_supernode",
                        lambda: seen.append((fleet.HEARTBEAT_DEFAULT_INTERVAL, beat.HEARTBEAT_DEFAULT_INTERVAL)))
    monkeypatch.setenv(HEARTBEAT_ENV, "12.5")
    monkeypatch.setattr(sys, "argv", sys.argv)
    assert supernode.main([]) == 0 and seen == [(12.5, 12.5)]


def test_the_supernode_retries_a_tls_handshake_cut_short_but_not_a_bad_certificate():
    """Flower 1.41 gives up at once on any error mentioning SSL; fedmap's SuperNode retries
    an EOF in the handshake (a dropped link) and still gives up on a certificate problem."""
    import httpx
    from flwr.supercore.retry import make_simple_http_retry_invoker

    from fedmap.flower.supernode import retry_invoker

    eof = httpx.ConnectError("[SSL: UNEXPECTED_EOF_WHILE_READING] EOF occurred in violation of protocol (_ssl.c:1006)")
    bad = httpx.ConnectError("[SSL: CERTIFICATE_VERIFY_FAILED] certificate verify failed: self-signed certificate")
    refused = httpx.ConnectError("[Errno 111] Connection refused")
    flower, ours = make_simple_http_retry_invoker().should_giveup, retry_invoker().should_giveup
    assert flower is not None and ours is not None
    assert [flower(e) for e in (eof, bad, refused)] == [True, True, False]  # the bug, in the pinned Flower
    assert [ours(e) for e in (eof, bad, refused)] == [False, True, False]


def test_restarts_are_bounded_in_count(tmp_path, monkeypatch):
    monkeypatch.setattr(rover, "ROVER_RESTARTS", 2)
    monkeypatch.setattr(rover, "superlink_answers", lambda *a, **k: True)  # the SuperLink answers, the node fails
    line, starts, _ = _fake_rover(tmp_path, monkeypatch, "kicked", max_wait=30)
    assert starts == 3 and line.endswith("(after 2 new SuperNodes, 2 in a row)"), line


def test_the_probe_needs_an_http_answer_not_just_an_open_port(tmp_path):
    """A relay whose far end is gone accepts and closes: that is not a SuperLink answering."""
    import http.server
    import threading

    class Quiet(http.server.BaseHTTPRequestHandler):
        def log_message(self, *a):
            pass

    web = http.server.HTTPServer(("127.0.0.1", 0), Quiet)
    threading.Thread(target=web.serve_forever, daemon=True).start()
    relay = socket.create_server(("127.0.0.1", 0))

    def accept_and_close():
        while True:
            try:
                relay.accept()[0].close()
            except OSError:
                return

    threading.Thread(target=accept_and_close, daemon=True).start()
    try:
        assert superlink_answers(f"127.0.0.1:{web.server_address[1]}", tls=False)
        assert not superlink_answers(f"127.0.0.1:{relay.getsockname()[1]}", tls=False)
        assert not superlink_answers(f"127.0.0.1:{relay.getsockname()[1]}", tls=True)
        assert not superlink_answers(f"127.0.0.1:{free_port()}", tls=False)
    finally:
        web.shutdown()
        web.server_close()
        relay.close()


@pytest.mark.parametrize("host, tls, auth, insecure, refused", [
    ("0.0.0.0", False, False, False, "TLS \\(--certs\\) and rover authentication"),
    ("192.0.2.7", True, False, False, "without rover authentication"),
    ("::", False, True, False, "without TLS \\(--certs\\):"),
    ("base.example", True, True, False, None),  # TLS and authentication: fine anywhere
    ("0.0.0.0", False, False, True, None),  # the user said the network is trusted
    ("127.0.0.1", False, False, False, None), ("127.8.9.10", False, False, False, None),
    ("::1", False, False, False, None), ("[::1]", False, False, False, None), ("localhost", False, False, False, None),
])
def test_the_base_station_refuses_to_listen_beyond_loopback_unprotected(host, tls, auth, insecure, refused):
    from fedmap.flower.launch import check_exposure

    if refused is None:
        check_exposure(host, tls=tls, auth=auth, insecure=insecure)
    else:
        with pytest.raises(FedmapError, match=refused):
            check_exposure(host, tls=tls, auth=auth, insecure=insecure)


def test_base_station_cli_without_protection_is_one_line_and_starts_nothing(tmp_path):
    """The default address (0.0.0.0) without --certs/--auth-keys is refused before any
    SuperLink starts; --insecure is the way to say the network is trusted."""
    r = subprocess.run([sys.executable, "-m", "fedmap", "base-station", "--rovers", "2", "-o", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    errors = [ln for ln in r.stderr.splitlines() + r.stdout.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "refusing to listen on 0.0.0.0" in errors[0] and "--insecure" in errors[0]
    assert "Traceback" not in r.stderr and not (tmp_path / "out.run" / "superlink.log").exists()


@pytest.mark.parametrize("mission", [True, False])
def test_a_warm_servers_child_builds_its_optimiser_without_importing(tmp_path, mission):
    """Whatever a rover's ClientApp child would import when it trains is imported once by the
    warm server before it forks: building the first optimiser imports torch's compiler
    (1.3 s, once per child and message before this was preloaded)."""
    save_map(GridMap(np.zeros((8, 8), dtype=np.uint8)), tmp_path / "m.npy")
    config = {"partition-id": 0, "mission": True} if mission else {"partition-id": 0, "map": str(tmp_path / "m.npy")}
    code = ("import sys, json, torch\n"
            "from fedmap.flower.warm import preload\n"
            f"preload(json.loads({json.dumps(json.dumps(config))}))\n"
            "before = set(sys.modules)\n"
            "torch.optim.Adam([torch.zeros(2, requires_grad=True)])\n"
            "print(sorted(set(sys.modules) - before))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[]", r.stdout[-2000:]


def test_a_warm_stand_in_does_not_outlive_its_server_or_its_supernode(tmp_path):
    """The stand-ins a SuperNode starts for ``flower-superexec`` and ``flwr-clientapp`` wait
    for the rover's warm server to listen, but give up at once when its folder is gone (the
    rover ended) or the SuperNode that started them died, not after their 300 s."""
    import subprocess
    import time

    from fedmap.flower.rover import write_shim
    from fedmap.flower.warm import PROGRAMS

    folder = tmp_path / "server"
    folder.mkdir()
    write_shim(tmp_path / "bin", str(folder / "clientapp.sock"))
    assert sorted(p.name for p in (tmp_path / "bin").iterdir()) == sorted(PROGRAMS)
    shim = subprocess.Popen([str(tmp_path / "bin" / "flower-superexec"), "--parent-pid", "1"], stderr=subprocess.PIPE,
                            text=True)
    time.sleep(1.0)
    assert shim.poll() is None  # the server may still be starting
    folder.rmdir()
    assert shim.wait(timeout=10) == 1 and "did not answer" in shim.communicate()[1]
    folder.mkdir()
    parent = subprocess.run(["bash", "-c", f"{tmp_path}/bin/flwr-clientapp --x >/dev/null 2>&1 & echo $!; sleep 0.5"],
                            capture_output=True, text=True, timeout=10)  # the SuperNode, gone after 0.5 s
    stat = Path(f"/proc/{int(parent.stdout.split()[0])}/stat")

    t_end = time.monotonic() + 10
    while _running(int(stat.parent.name)) and time.monotonic() < t_end:  # neither gone nor a zombie
        time.sleep(0.1)
    assert not _running(int(stat.parent.name))


def _warm_server(tmp_path) -> tuple[str, subprocess.Popen]:
    """A warm server started as its own process (as a predictor's site starts one): its socket and process."""
    sock = str(tmp_path / "s.sock")
    with open(tmp_path / "server.log", "wb") as log:
        server = subprocess.Popen([sys.executable, "-m", "fedmap.flower.warm", sock,
                                   json.dumps({"partition-id": 0, "samples": "unused"})], stdout=log,
                                  stderr=subprocess.STDOUT)
    return sock, server


def _running(pid: int) -> bool:
    """Whether process ``pid`` runs: neither gone nor a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
def test_a_supernode_forked_by_the_warm_server_is_watched_and_stopped_like_a_process(tmp_path):
    """A rover's SuperNode is forked by its warm server, not started as a fresh Python: it runs
    in a process group of its own (the rover stops it, and what it started, as one group), the rover
    sees its exit code as it would a process's, stops it through :class:`Processes`, and it
    does not outlive the server."""
    from fedmap.flower.warm import SUPERNODE

    sock, server = _warm_server(tmp_path)

    def alive() -> bool:
        return server.poll() is None

    try:
        log = tmp_path / "supernode.log"
        bad = rover.WarmChild(sock, ["--no-such-option"], log=log, alive=alive)  # Flower's own argument parser: exit 2
        assert bad.args[0] == SUPERNODE and bad.wait(timeout=60) == 2 and bad.poll() == 2
        assert "--no-such-option" in log.read_text()  # its output, in the log it was given

        argv = rover.supernode_argv(superlink=f"127.0.0.1:{free_port()}", port=free_port(),  # nobody listens there
                                    node_config={"partition-id": 0}, root_cert=None, auth_key=None, max_wait=300)
        assert argv[1:3] == ["-m", rover.SUPERNODE_MODULE]
        child = rover.WarmChild(sock, argv[3:], log=log, alive=alive)
        fields = Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()
        assert int(fields[1]) == server.pid  # forked by the server ...
        assert int(fields[2]) == child.pid  # ... in a process group of its own, from the start
        assert child.poll() is None
        with pytest.raises(subprocess.TimeoutExpired):
            child.wait(timeout=0.5)
        procs = Processes()
        procs.adopt("supernode", child, log=log)
        procs.stop("supernode", grace=20.0)
        assert child.returncode is not None and not _running(child.pid)

        last = rover.WarmChild(sock, argv[3:], log=log, alive=alive)
        assert _running(last.pid)
        server.kill()
        server.wait(timeout=10)
        assert last.wait(timeout=10) == -9  # the server's end of the line closed without an exit code
        t_end = time.monotonic() + 10
        while _running(last.pid) and time.monotonic() < t_end:
            time.sleep(0.1)
        assert not _running(last.pid)  # gone with the server
    finally:
        server.kill()
        server.wait(timeout=10)


@pytest.mark.slow
def test_a_killed_warm_server_leaves_no_clientapp_running_and_no_requester_waiting(tmp_path):
    """A rover killed mid-mission once left its warm server's ClientApp running for hours (it
    retried its dead SuperNode's address forever) and its SuperExec's stand-in waiting on a
    connection that ClientApp had inherited. Every child of the server dies with it, and holds
    no other request's connection: each requester sees the end of its line at once."""
    from fedmap.flower.warm import SUPERNODE

    sock, server = _warm_server(tmp_path)

    def alive() -> bool:
        return server.poll() is None

    def children() -> set[int]:  # the server's, from every process's parent PID
        found: set[int] = set()
        for d in Path("/proc").iterdir():
            try:
                if d.name.isdigit() and int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == server.pid:
                    found.add(int(d.name))
            except (OSError, ValueError, IndexError):
                continue
        return found

    conn, left = None, []
    try:
        argv = rover.supernode_argv(superlink=f"127.0.0.1:{free_port()}", port=free_port(),  # nobody listens there
                                    node_config={"partition-id": 0}, root_cert=None, auth_key=None, max_wait=300)
        node = rover.WarmChild(sock, argv[3:], log=tmp_path / "supernode.log", alive=alive)
        left.append(node.pid)
        assert node.args[0] == SUPERNODE
        # then a ClientApp, as the SuperExec's stand-in asks for one: its SuperNode's address is dead,
        # so Flower's ClientApp retries it for as long as it runs
        conn = socket.socket(socket.AF_UNIX)
        conn.connect(sock)
        conn.sendall(json.dumps(["flwr-clientapp", "--insecure", "--runtime-api-address",
                                 f"127.0.0.1:{free_port()}", "--token", "1"]).encode() + b"\n")
        t_end = time.monotonic() + 60
        while not children() - {node.pid} and time.monotonic() < t_end:
            time.sleep(0.05)
        (app,) = children() - {node.pid}
        left.append(app)
        time.sleep(1.0)
        assert _running(app)  # retrying its SuperNode

        server.kill()
        server.wait(timeout=10)
        assert node.wait(timeout=10) == -9  # the end of the SuperNode's line: the ClientApp does not hold it
        conn.settimeout(10)
        assert conn.recv(16) == b""  # nor the ClientApp's own
        t_end = time.monotonic() + 10
        while (_running(app) or _running(node.pid)) and time.monotonic() < t_end:
            time.sleep(0.1)
        assert not _running(app) and not _running(node.pid)  # both gone with the server
    finally:
        server.kill()
        server.wait(timeout=10)
        if conn is not None:
            conn.close()
        for pid in left:  # what a regression would leave running
            if _running(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.slow
def test_a_local_deploys_rovers_are_forked_by_one_host_and_watched_like_processes(tmp_path):
    """``--deploy local`` forks its rovers from one host process (``fedmap.cli.rover_host``) that
    imported everything once: a rover's arguments reach ``fedmap rover`` (a bad one is its
    one-line error and exit code 2, in the rover's log), it runs in a process group of its own,
    its SuperNode and the rest are its own children as with a rover started cold, it ends with
    ``fedmap rover``'s own exit code, and it does not outlive the host."""
    from fedmap.flower.mission.deploy import ROVER_HOST_MODULE
    from fedmap.flower.warm import ROVER

    sock = str(tmp_path / "h.sock")
    with open(tmp_path / "host.log", "wb") as log:
        host = subprocess.Popen([sys.executable, "-m", ROVER_HOST_MODULE, sock], stdout=log, stderr=subprocess.STDOUT)

    def alive() -> bool:
        return host.poll() is None

    def stat(pid: int) -> list[str]:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()

    def rover_args(k: int, max_wait: float) -> list[str]:  # nobody listens at the SuperLink's address
        return ["rover", "--mission", "--partition-id", str(k), "--superlink", f"127.0.0.1:{free_port()}",
                "--max-wait", f"{max_wait:g}"]

    try:
        log = tmp_path / "rover.log"
        bad = rover.WarmChild(sock, ["rover", "--no-such-option"], log=log, alive=alive, program=ROVER)
        assert bad.args[0] == ROVER and bad.wait(timeout=120) == 2
        assert log.read_text().strip().splitlines() == ["error: No such option '--no-such-option'."]  # one line

        gives_up = rover.WarmChild(sock, rover_args(0, 3), log=log, alive=alive, program=ROVER)
        fields = stat(gives_up.pid)
        assert int(fields[1]) == host.pid and int(fields[2]) == gives_up.pid  # forked, in a group of its own
        assert gives_up.wait(timeout=120) == 2  # fedmap rover's own exit code: it gave up on the SuperLink
        assert "rover 0: connecting to" in log.read_text() and "error: rover 0" in log.read_text()

        last = rover.WarmChild(sock, rover_args(1, 300), log=tmp_path / "last.log", alive=alive, program=ROVER)
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and not ((tmp_path / "last.log").exists()  # the rover opens it
                                                and "connecting to" in (tmp_path / "last.log").read_text()):
            time.sleep(0.1)
        host.kill()
        host.wait(timeout=10)
        assert last.wait(timeout=10) == -9  # the host's end of the line closed without an exit code
        t_end = time.monotonic() + 10
        while Path(f"/proc/{last.pid}").exists() and stat(last.pid)[0] != "Z" and time.monotonic() < t_end:
            time.sleep(0.1)
        assert not Path(f"/proc/{last.pid}").exists() or stat(last.pid)[0] == "Z"  # gone with the host
    finally:
        host.kill()
        host.wait(timeout=10)


def test_a_socket_folder_fits_a_unix_socket_however_long_tmpdir_is(tmp_path, monkeypatch):
    """A rover's warm server listens on a Unix socket, whose path Linux caps at 107 bytes: under a
    long TMPDIR (pytest's own is close) its folder moves to /tmp, and either way it is removed."""
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    deep.mkdir(parents=True)
    monkeypatch.setattr(launch.tempfile, "tempdir", str(deep))
    with launch.socket_dir("fedmap-x-", "clientapp.sock") as d:
        assert d.parent == Path("/tmp") and len(os.fsencode(d / "clientapp.sock")) <= launch.UNIX_SOCKET_PATH_MAX
        with socket.socket(socket.AF_UNIX) as s:
            s.bind(str(d / "clientapp.sock"))
    assert not d.exists()
    monkeypatch.setattr(launch.tempfile, "tempdir", str(tmp_path.parent.parent))  # short enough: stays there
    with launch.socket_dir("fedmap-x-", "clientapp.sock") as d:
        assert d.parent == tmp_path.parent.parent
    assert not d.exists()
    assert not list(deep.iterdir())  # nothing left where the first was tried


def test_a_killed_processes_temporary_folder_is_removed_by_the_next_one_and_no_other_is(tmp_path):
    """A rover killed with SIGKILL cannot remove its temporary folders; the next process to make
    one of that kind does. Folders of live processes, folders without an owner file and a folder
    whose PID now belongs to another process (a different start time) are told apart."""
    code = ("import sys, time\nfrom fedmap.flower.launch import owned_temp_dir\n"
            "cm = owned_temp_dir('fedmap-t-', parent=sys.argv[1])\nprint(cm.__enter__(), flush=True)\ntime.sleep(120)\n")
    p = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        killed = Path(p.stdout.readline().strip())
        assert killed.parent == tmp_path and (killed / launch.OWNER_FILE).read_text().split()[0] == str(p.pid)
    finally:
        p.kill()
        p.wait(timeout=30)
        p.stdout.close()
    assert killed.is_dir()  # SIGKILL: no clean-up of its own
    sleeper = subprocess.Popen(["sleep", "120"])
    try:
        started = Path(f"/proc/{sleeper.pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
        live = tmp_path / "fedmap-t-live"
        live.mkdir()
        (live / launch.OWNER_FILE).write_text(f"{sleeper.pid} {started}\n")
        reused = tmp_path / "fedmap-t-reused"  # the sleeper's PID, but another start: its owner is gone
        reused.mkdir()
        (reused / launch.OWNER_FILE).write_text(f"{sleeper.pid} {int(started) - 1}\n")
        unowned = tmp_path / "fedmap-t-unowned"
        unowned.mkdir()
        other = tmp_path / "fedmap-u-other"  # another prefix: not this kind's to remove
        other.mkdir()
        (other / launch.OWNER_FILE).write_text(f"{p.pid} 1\n")
        elsewhere = tmp_path / "fedmap-t-elsewhere"  # a dead PID here, but made on another host or container
        elsewhere.mkdir()
        (elsewhere / launch.OWNER_FILE).write_text(f"{p.pid} 1 not-{socket.gethostname()}\n")
        with launch.owned_temp_dir("fedmap-t-", parent=tmp_path) as mine:
            assert mine.is_dir() and (mine / launch.OWNER_FILE).read_text().split()[0] == str(os.getpid())
            assert not killed.exists() and not reused.exists()
            assert live.is_dir() and unowned.is_dir() and other.is_dir() and elsewhere.is_dir()
            assert launch.sweep_stale_dirs(tmp_path, "fedmap-t-") == []  # its own, live, is kept
        assert not mine.exists()
    finally:
        sleeper.kill()
        sleeper.wait(timeout=30)
    assert launch.sweep_stale_dirs(tmp_path, "fedmap-t-") == [live]  # once the sleeper is gone


def test_without_proc_a_live_owner_is_told_by_its_pid_and_its_folder_kept(tmp_path, monkeypatch):
    """Where there is no /proc (macOS) start times are unknown: a folder is removed only when
    no process has its owner's PID."""
    monkeypatch.setattr(launch, "PROC_SELF_STAT", tmp_path / "no-proc")
    sleeper = subprocess.Popen(["sleep", "120"])
    try:
        live, gone = tmp_path / "fedmap-t-live", tmp_path / "fedmap-t-gone"
        for d in (live, gone):
            d.mkdir()
        (live / launch.OWNER_FILE).write_text(f"{sleeper.pid} -\n")
        dead = subprocess.Popen(["true"])
        dead.wait(timeout=30)
        (gone / launch.OWNER_FILE).write_text(f"{dead.pid} -\n")
        assert launch.sweep_stale_dirs(tmp_path, "fedmap-t-") == [gone]
        assert live.is_dir()
    finally:
        sleeper.kill()
        sleeper.wait(timeout=30)


def test_certs_forced_over_an_old_ca_leave_no_rover_key_of_it(tmp_path):
    launch.make_certs(tmp_path, hosts=["127.0.0.1"], rovers=3)
    (tmp_path / "notes.txt").write_text("mine")
    launch.make_certs(tmp_path, hosts=["127.0.0.1"], rovers=1, overwrite=True)
    assert sorted(p.name for p in tmp_path.glob("rover*")) == ["rover0", "rover0.crt", "rover0.key", "rover0.pub"]
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_rover_keys_are_registered_in_one_process_and_a_bad_one_is_named_in_one_line(tmp_path):
    """All of a mission's keys go through one Flower CLI process (fedmap.flower.control); a
    key that is not one is a one-line error naming it."""
    env = flower_env(tmp_path / "home")
    launch.write_connection(tmp_path / "home", address=f"127.0.0.1:{free_port()}", root_cert=None)
    (tmp_path / "bad.pub").write_text("not a key")
    with pytest.raises(FedmapError) as err:
        launch.register_keys([tmp_path / "bad.pub"], env=env)
    message = str(err.value)
    assert "\n" not in message and "bad.pub" in message and message.startswith("flwr supernode register failed")
    launch.register_keys([], env=env)  # nothing to register: no process at all
