"""A mission on real processes (``fedmap mission --deploy local``): a SuperLink with TLS and
SuperNode authentication, one rover process per rover, the mission's ServerApp, all on
loopback. It records what the in-process mission records, message for message, and
carries on through faults: a damaged report, a rover process killed mid-mission and
started again, the link down for several syncs."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("flwr")

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.flower.launch import OWNER_FILE  # noqa: E402
from fedmap.flower.mission.deploy import deploy_mission  # noqa: E402
from fedmap.flower.mission.task import MISSION_RUN_DEFAULTS  # noqa: E402
from fedmap.maps.grid import UNKNOWN  # noqa: E402
from fedmap.mission import load_mission, mission_terrain, run_mission  # noqa: E402
from fedmap.mission.outputs.report import metrics, without_timings  # noqa: E402
from fedmap.mission.settings import mission_toml  # noqa: E402

pytestmark = pytest.mark.slow


def _in_process(mission_toml):
    config, source, _ = load_mission(mission_toml)
    truth, elevation, prior, profiles = mission_terrain(config, source)
    return run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                       thresholds=source.thresholds, frames=1)


def _same(here, apart, names):
    a, b = without_timings(metrics(here)), without_timings(metrics(apart))
    for name in names:
        assert [(m.bytes, m.status) for m in here.runs[name].ledger] == \
               [(m.bytes, m.status) for m in apart.runs[name].ledger], name
        assert json.dumps(a["strategies"][name], sort_keys=True) == json.dumps(b["strategies"][name], sort_keys=True), name
        assert here.runs[name].trails == apart.runs[name].trails
        for va, vb in zip(here.runs[name].views, apart.runs[name].views):
            np.testing.assert_array_equal(va, vb)


@pytest.mark.xdist_group("loopback-b")  # a long loopback run: see addopts in pyproject.toml
def test_the_default_mission_on_processes_equals_the_mission_in_process(tmp_path):
    out = tmp_path / "out"
    names = ("raw", "predictive", "fedmap")
    r = subprocess.run([sys.executable, "-m", "fedmap", "mission", "--deploy", "local", "--strategies", ",".join(names),
                        "--set", "mission.steps=30", "--no-animation", "-o", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    deployed = json.loads((out / "metrics.json").read_text())
    assert set(deployed["strategies"]) == set(names)
    assert "faults" not in deployed  # nothing went wrong
    here = _in_process(out / "mission.toml")  # the mission as deployed, resolved
    assert without_timings(deployed["strategies"]) == without_timings(metrics(here)["strategies"])
    for name in names:
        assert sum(m["bytes"] for m in deployed["strategies"][name]["ledger"]) > 0
    logs = {p.name for p in (out / "logs").iterdir()}
    assert {"superlink.log", "rover-host.log", *(f"rover{k}.log" for k in range(4)),
            *(f"rover{k}.supernode.log" for k in range(4))} <= logs
    assert "TLS" not in r.stderr and "insecure" not in (out / "logs" / "rover0.log").read_text().lower()
    # no private key outlives the run: no CA key ever written, the run's server and rover keys and the
    # control secret gone (certificates may stay: they are public)
    left = [p for d in (out, out.with_name("out.run")) for p in d.rglob("*")
            if p.suffix in (".key", ".secret", ".pem") and p.name != "server.pem" or re.fullmatch(r"rover\d+", p.name)]
    assert left == []


@pytest.mark.xdist_group("loopback-b")
def test_a_mission_on_processes_loses_nothing_to_faults(tmp_path):
    """Rover 1 damages its report of the order to step 30 (its check fails: the order goes
    again); rover 2's process is killed at step 40 and its state folder deleted, then it is
    started again (it refuses the next order, the base sends it with every earlier order,
    and the rover rebuilds itself from them); the lander's link is down for steps 20-40. The
    result equals the uninterrupted in-process mission's, and every cell observed reached the base."""
    config, source, resolved = load_mission(overrides=[{"mission": {"steps": 60, "strategies": ["predictive"]},
                                                        "link": {"loss": 0.0, "lander_cut": [20, 40]}}])
    text = mission_toml(resolved)
    (tmp_path / "mission.toml").write_text(text)
    work = tmp_path / "out.run"
    killed: list[int] = []
    left: list[Path] = []
    hosts: list[bool] = []  # whether the rover killed was forked by the deploy's host of rovers

    def on_status(st: dict) -> None:
        if st.get("step", 0) >= 40 and not killed:  # the rover's own process (its SuperNode dies with it)
            pid = int((work / "rover2.pid").read_text())
            parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
            hosts.append(b"fedmap.cli.rover_host" in Path(f"/proc/{parent}/cmdline").read_bytes())
            left.extend(_temp_dirs_of(pid))  # its temporary folders, which a SIGKILL leaves behind
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            shutil.rmtree(work / "rover2.state", ignore_errors=True)  # everything it held is gone

    apart = deploy_mission(text, members=config.rovers, out=tmp_path / "out", strategies=("predictive",), frames=1,
                           rounds=len(config.sync_steps) + 1, faults={1: "corrupt@30"}, on_status=on_status)
    assert killed and hosts == [True]
    restarted = int((work / "rover2.pid").read_text())
    assert restarted != killed[0]  # started again, and its PID recorded
    assert len(left) == 2 and not [d for d in left if d.exists()]  # the restarted rover removed the killed one's
    here = _in_process(tmp_path / "mission.toml")
    _same(here, apart, ("predictive",))
    what = [f["fault"] for f in apart.faults]
    assert any("report damaged" in w for w in what) and any(f["rover"] == 1 for f in apart.faults)
    assert any("rover process exited" in w for w in what) and any(f["rover"] == 2 for f in apart.faults)
    assert [f["rover"] for f in apart.faults if "lost its state" in f["fault"]] == [2]
    assert any(f["rover"] == 2 and "rebuilt from its orders" in f["fault"] for f in apart.faults)
    ledger = apart.runs["predictive"].ledger
    assert any(m.status == "link down" for m in ledger)
    # nothing observed is lost: the base holds every cell any rover observed by the last sync
    run = apart.runs["predictive"]
    last = run.series.coverage[-1]
    held = run.frames[-1].global_map != UNKNOWN
    assert abs(held.mean() - last) < 1e-12


def _temp_dirs_of(pid: int) -> list[Path]:
    """The temporary folders whose owner file names the running process ``pid`` (its PID and
    start time: a folder left by an earlier process with the same PID is not its)."""
    started = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    found = []
    for parent in {Path(tempfile.gettempdir()), Path("/tmp")}:
        for d in parent.glob("fedmap-*"):
            try:
                if (d / OWNER_FILE).read_text().split()[:2] == [str(pid), started]:
                    found.append(d)
            except OSError:
                continue
    return found


def _kill_everything_of(tmp_path) -> int:
    """SIGKILL every process started for this test (its environment names ``tmp_path``): the
    base station's machine crashing, with every rover on it."""
    killed = 0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if str(tmp_path).encode() in (d / "environ").read_bytes() or \
                    str(tmp_path).encode() in (d / "cmdline").read_bytes():
                os.kill(int(d.name), signal.SIGKILL)
                killed += 1
        except (OSError, ProcessLookupError):
            continue
    return killed


@pytest.mark.xdist_group("loopback-a")
def test_a_base_station_killed_mid_mission_resumes_bit_for_bit(tmp_path):
    """Everything is killed at once at step >= 20 of the second strategy (SIGKILL: no clean-up); the same command
    with --resume replays the base's journal, the rovers carry on from their state folders,
    and the result equals the uninterrupted in-process mission's."""
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "fedmap", "mission", "--deploy", "local", "--strategies", "raw,predictive",
            "--set", "mission.steps=30", "--no-animation", "-o", str(out)]
    env = {**os.environ, "FEDMAP_TEST_RUN": str(tmp_path)}
    first = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                             start_new_session=True)
    status = tmp_path / "out.run" / "status.json"
    t_end = time.monotonic() + 600
    try:
        while time.monotonic() < t_end:
            st = json.loads(status.read_text()) if status.is_file() else {}
            if st.get("strategy") == "predictive" and st.get("step", 0) >= 20:
                break
            assert first.poll() is None, "the first run ended before it could be killed"
            time.sleep(0.2)
        assert _kill_everything_of(tmp_path) > 0
    finally:
        first.kill()
        first.wait()
    time.sleep(1.0)
    r = subprocess.run([*argv, "--resume"], capture_output=True, text=True, timeout=900, env=env)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    deployed = json.loads((out / "metrics.json").read_text())
    assert any("base station resumed" in f["fault"] for f in deployed["faults"])
    here = _in_process(out / "mission.toml")
    assert without_timings(deployed["strategies"]) == without_timings(metrics(here)["strategies"])


def test_resuming_without_a_journal_or_with_another_mission_is_refused(tmp_path):
    from fedmap.flower.mission.task import BaseJournal

    with pytest.raises(FedmapError, match="nothing to resume"):
        BaseJournal(tmp_path / "out", "[mission]\nsteps = 10\n", resume=True)
    j = BaseJournal(tmp_path / "out", "[mission]\nsteps = 10\n", resume=False)
    j.save("raw", 0, {0: b"a", 1: b"bc"}, [{"rover": 1, "fault": "x"}])
    again = BaseJournal(tmp_path / "out", "[mission]\nsteps = 10\n", resume=True)
    assert again.mission_id == j.mission_id and again.saved("raw") == 1 and again.saved("fedmap") == 0
    assert again.load("raw", 0) == ({0: b"a", 1: b"bc"}, [{"rover": 1, "fault": "x"}])
    with pytest.raises(FedmapError, match="another mission"):
        BaseJournal(tmp_path / "out", "[mission]\nsteps = 20\n", resume=True)


def test_the_mission_app_declares_every_run_config_key():
    import tomllib
    from pathlib import Path

    from fedmap.flower.mission.deploy import mission_app_dir

    app = tomllib.loads((Path(mission_app_dir()) / "pyproject.toml").read_text())
    assert app["tool"]["flwr"]["app"]["config"] == MISSION_RUN_DEFAULTS


def test_a_base_station_beyond_loopback_needs_tls_and_authentication(tmp_path):
    with pytest.raises(FedmapError, match="refusing to listen on 0.0.0.0 without TLS") as e:
        deploy_mission("[mission]\n", members=1, out=tmp_path / "out", mode="base", host="0.0.0.0", port=1)
    assert "\n" not in str(e.value)
    with pytest.raises(FedmapError, match="--deploy local makes its own certificates"):
        deploy_mission("[mission]\n", members=1, out=tmp_path / "out", mode="local", certs=tmp_path)
    with pytest.raises(FedmapError, match="unknown --deploy"):
        deploy_mission("[mission]\n", members=1, out=tmp_path / "out", mode="cloud")


@pytest.mark.parametrize("args, message", [
    (["--deploy", "cloud"], "error: unknown --deploy 'cloud': choose one of local, base, zenoh"),
    (["--deploy", "base", "--listen", "nope"], "error: --listen must be HOST:PORT, got 'nope'"),
    (["--deploy", "local", "--strategies", "central"], "error: none of the strategies central runs on processes"),
    (["--deploy", "local", "--topology", "mesh", "--strategies", "raw"],
     "error: a mission on Flower's processes runs the star topology only, not 'mesh': rovers have no links of their "
     "own there (Flower routes every message through the base's SuperLink); run mesh and leader teams with --deploy "
     "zenoh"),
    (["--step-seconds", "0.5"],
     "error: --step-seconds apply to a mission on processes only: add --deploy zenoh, local or base"),
    (["--deploy", "local", "--strategies", "raw", "--stop-coverage", "0.99"],
     "error: a mission on processes takes every step: stop_coverage reads the truth"),
])
def test_a_wrong_deploy_argument_is_one_line_before_the_terrain_loads(tmp_path, capsys, monkeypatch, args, message):
    import fedmap.cli.mission as cli_mission
    from fedmap.cli import main

    loaded: list[int] = []
    monkeypatch.setattr(cli_mission, "mission_terrain", lambda *a, **k: loaded.append(1))
    assert main(["mission", *args, "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and len(err.strip().splitlines()) == 1, err
    assert loaded == [] and not (tmp_path / "out").exists()


@pytest.mark.xdist_group("loopback-c")
def test_a_mission_base_refuses_an_unregistered_key_and_a_wrong_ca(tmp_path):
    """The mission's base station (``--deploy base``) with TLS and two registered rover keys:
    a rover with an unregistered key is refused, one that does not trust the base's CA
    fails, each with one line naming the problem."""
    from fedmap.flower.launch import flower_env, free_port, make_certs

    certs, other, keys = tmp_path / "certs", tmp_path / "other-ca", tmp_path / "registered"
    make_certs(certs, hosts=["127.0.0.1", "localhost"], rovers=3)
    make_certs(other, hosts=["127.0.0.1"], rovers=0)
    keys.mkdir()
    for k in range(2):  # rover2's key is never registered
        (keys / f"rover{k}.pub").write_bytes((certs / f"rover{k}.pub").read_bytes())
    port = free_port()
    base = subprocess.Popen([sys.executable, "-m", "fedmap", "mission", "--set", "mission.rovers=2", "--strategies", "raw",
                             "--deploy", "base", "--listen", f"127.0.0.1:{port}", "--certs", str(certs), "--auth-keys",
                             str(keys), "--no-animation", "-o", str(tmp_path / "out")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=flower_env(tmp_path / "home-base"), start_new_session=True)
    try:
        status = tmp_path / "out.run" / "superlink.log"
        t_end = time.monotonic() + 120
        while not status.is_file() and time.monotonic() < t_end:
            time.sleep(0.2)

        def rover(key, ca, name):  # each as its key's own number (a key given as another rover's is refused at once)
            return subprocess.run([sys.executable, "-m", "fedmap", "rover", "--mission", "--partition-id",
                                   key.name.removeprefix("rover"),
                                   "--superlink", f"127.0.0.1:{port}", "--root-cert", str(ca), "--auth-key", str(key),
                                   "--max-wait", "30", "--log", str(tmp_path / f"{name}.log")],
                                  capture_output=True, text=True, timeout=180, env=flower_env(tmp_path / f"home-{name}"))

        bad_key = rover(certs / "rover2", certs / "ca.crt", "unregistered")
        wrong_ca = rover(certs / "rover0", other / "ca.crt", "wrong-ca")
    finally:
        os.killpg(base.pid, signal.SIGTERM)
        base.communicate(timeout=60)
    assert bad_key.returncode != 0 and "refused this rover's key" in bad_key.stderr, bad_key.stderr[-1500:]
    assert wrong_ca.returncode != 0 and "TLS certificate problem" in wrong_ca.stderr, wrong_ca.stderr[-1500:]
    for r in (bad_key, wrong_ca):
        err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
        assert len(err) == 1 and "Traceback" not in r.stderr


@pytest.mark.xdist_group("loopback-b")  # a long loopback run: see addopts in pyproject.toml
def test_a_rover_restarted_across_machines_with_the_documented_command_rejoins(tmp_path):
    """``--deploy base`` on loopback with TLS and registered keys, its two rovers started as
    docs/processes.md shows (both with ``--state`` on one folder); rover 1 is killed
    (SIGKILL) mid-mission and started again with the very same command, no ``--rejoin``. The
    mission finishes and equals the mission in process; each rover kept its own state file."""
    from fedmap.flower.launch import flower_env, free_port, make_certs

    certs, state = tmp_path / "certs", tmp_path / "state"
    make_certs(certs, hosts=["127.0.0.1"], rovers=2)
    port, out = free_port(), tmp_path / "out"
    base = subprocess.Popen([sys.executable, "-m", "fedmap", "mission", "--set", "mission.rovers=2", "--set",
                             "mission.steps=40", "--strategies", "raw", "--deploy", "base", "--listen",
                             f"127.0.0.1:{port}", "--certs", str(certs), "--auth-keys", str(certs), "--no-animation",
                             "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=flower_env(tmp_path / "home-base"), start_new_session=True)

    def rover(k: int) -> subprocess.Popen:  # docs/processes.md's line
        with open(tmp_path / f"rover{k}.txt", "a") as fh:
            return subprocess.Popen([sys.executable, "-m", "fedmap", "rover", "--mission", "--partition-id", str(k),
                                     "--superlink", f"127.0.0.1:{port}", "--root-cert", str(certs / "ca.crt"),
                                     "--auth-key", str(certs / f"rover{k}"), "--state", str(state), "--poll", "0.5"],
                                    stdout=fh, stderr=subprocess.STDOUT, env=flower_env(tmp_path / f"home-{k}"),
                                    start_new_session=True)
    rovers, files = {}, set()
    try:
        rovers = {0: rover(0), 1: rover(1)}
        status, t_end, killed = out.with_name("out.run") / "status.json", time.monotonic() + 600, False
        while base.poll() is None and time.monotonic() < t_end:
            try:
                st = json.loads(status.read_text())
            except (OSError, ValueError):
                st = {}
            files |= {p.name for p in state.glob("*.pickle")}
            if not killed and st.get("step", 0) >= 16:
                os.killpg(rovers[1].pid, signal.SIGKILL)
                rovers[1].wait(timeout=30)
                rovers[1] = rover(1)  # the same command, as the docs give it
                killed = True
            time.sleep(0.2)
        text, _ = base.communicate(timeout=60)
        codes = {k: p.wait(timeout=120) for k, p in rovers.items()}
    finally:
        for p in (base, *rovers.values()):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
    assert killed and base.returncode == 0, text[-3000:]
    assert codes == {0: 0, 1: 0}, {k: (tmp_path / f"rover{k}.txt").read_text()[-1500:] for k in rovers}
    assert files == {f"{m}-raw-rover{k}.pickle" for m in {f.split("-raw-")[0] for f in files} for k in (0, 1)}
    # the base scored nothing: the rovers' logs are on their machines; copied in, fedmap score scores the run
    assert "fedmap score" in text and not out.exists(), text[-2000:]
    shutil.copytree(state / "log", out.with_name("out.run") / "from-the-rovers")
    scored = subprocess.run([sys.executable, "-m", "fedmap", "score", str(out.with_name("out.run")), "-o", str(out),
                             "--no-animation"], capture_output=True, text=True, timeout=300)
    assert scored.returncode == 0, scored.stderr[-2000:]
    deployed = json.loads((out / "metrics.json").read_text())
    here = _in_process(out / "mission.toml")
    assert without_timings(deployed["strategies"]) == without_timings(metrics(here)["strategies"])
