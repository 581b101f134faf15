"""A team over Zenoh (:mod:`fedmap.zenohnet`): one process per rover, the base station's
clock, mutual TLS and access control, on loopback. It records what the in-process mission
records, message for message, and carries on through faults."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.flower.launch import free_port, make_certs  # noqa: E402
from fedmap.mission import load_mission, mission_terrain, run_mission  # noqa: E402
from fedmap.mission.ends.registry import names_that  # noqa: E402
from fedmap.mission.outputs.report import metrics, without_timings  # noqa: E402
from fedmap.mission.settings import mission_toml  # noqa: E402
from fedmap.zenohnet.deploy import deploy_zenoh  # noqa: E402
from fedmap.zenohnet.session import Certs, acl, check_listen, endpoint, node_config, open_session, order_key  # noqa: E402

pytestmark = pytest.mark.slow


def _in_process(text: str):
    config, source, _ = load_mission(None, overrides=[__import__("tomllib").loads(text)])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    return run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                       thresholds=source.thresholds, frames=1, workers=1)


def _same(here, apart, names):
    a, b = without_timings(metrics(here)), without_timings(metrics(apart))
    for name in names:
        assert [(m.bytes, m.status, m.kind) for m in here.runs[name].ledger] == \
               [(m.bytes, m.status, m.kind) for m in apart.runs[name].ledger], name
        assert json.dumps(a["strategies"][name], sort_keys=True) == json.dumps(b["strategies"][name], sort_keys=True), name
        assert here.runs[name].trails == apart.runs[name].trails
        for va, vb in zip(here.runs[name].views, apart.runs[name].views):
            np.testing.assert_array_equal(va, vb)


def _mission(steps: int, strategies, **link) -> str:
    _, _, resolved = load_mission(overrides=[{"mission": {"steps": steps, "strategies": list(strategies)},
                                              "link": link}])
    return mission_toml(resolved)


@pytest.mark.xdist_group("loopback-c")
def test_every_star_strategy_over_zenoh_equals_the_mission_in_process(tmp_path):
    names = names_that("deployable")
    assert {"none", "raw", "predictive", "fedmap", "paper", "rosgrid"} <= set(names)
    text = _mission(30, names)
    started: list[float] = []
    apart = deploy_zenoh(text, members=4, out=tmp_path / "out", strategies=names, frames=1,
                         on_started=started.append)
    assert started and apart.faults == ()
    here = _in_process(text)
    _same(here, apart, names)
    for name in ("raw", "predictive", "fedmap", "paper", "rosgrid"):  # every one of them sent something
        assert sum(m.bytes for m in apart.runs[name].ledger) > 0, name
    work = tmp_path / "out.run"
    assert not (work / "certs").exists()  # no private key outlives the run
    assert {f"rover{k}.log" for k in range(4)} | {"rover-host.log"} <= {p.name for p in work.glob("*.log")}


@pytest.mark.xdist_group("loopback-c")
def test_a_mission_over_zenoh_loses_nothing_to_faults(tmp_path):
    """Rover 1 damages its report of the order to step 30 (its check fails: the order goes
    again); rover 2's process is killed at step 40 (everything it held in memory is gone) and
    started again (it refuses the next order as a rover that lost its state; the base sends
    it with every earlier order and the rover rebuilds itself from them); the lander's link
    is down for steps 20-40. The result equals the uninterrupted in-process mission's."""
    text = _mission(60, ["predictive"], loss=0.0, lander_cut=[20, 40])
    work = tmp_path / "out.run"
    killed: list[int] = []

    def on_step(name: str, step: int) -> None:
        if step >= 40 and not killed:
            pid = int((work / "rover2.pid").read_text())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    apart = deploy_zenoh(text, members=4, out=tmp_path / "out", strategies=("predictive",), frames=1,
                         faults={1: "corrupt@30"}, on_step=on_step)
    assert killed and int((work / "rover2.pid").read_text()) != killed[0]  # started again
    here = _in_process(text)
    _same(here, apart, ("predictive",))
    what = [(f["rover"], f["fault"]) for f in apart.faults]
    assert any(k == 1 and "report damaged" in w for k, w in what), what
    assert any(k == 2 and "rover process exited" in w for k, w in what), what
    assert any(k == 2 and "lost its state" in w for k, w in what), what
    assert any(k == 2 and "rebuilt from its orders" in w for k, w in what), what
    ledger = apart.runs["predictive"].ledger
    assert any(m.status == "out of range" or m.bytes == 0 for m in ledger if 20 <= m.step <= 40)


# -- peer missions: an agent per process, no base station giving orders ----------------------------


def _peer_mission(steps: int, strategies, **link) -> str:
    _, _, resolved = load_mission(overrides=[{"mission": {"steps": steps, "strategies": list(strategies)},
                                              "link": {"latency": 0, **link}}])
    return mission_toml(resolved)


PEER_CASES = [
    # the lander an agent and leader of its group, its link cut for a while; a damaged mail
    ("leader", ("raw", "gossip"), {"loss": 0.1, "drop": 0.1, "lander_cut": [10, 25], "uplink_bytes": 1500}),
    # no lander: a mesh of rovers alone
    ("mesh", ("raw", "admm"), {"loss": 0.1, "drop": 0.1, "lander_agent": False, "peer_range": 60.0}),
    # rovers alone on a short range: the team splits into groups, each electing its leader, and heals
    ("leader", ("raw",), {"lander_agent": False, "peer_range": 40.0, "steps": 90}),
]


@pytest.mark.xdist_group("loopback-c")
@pytest.mark.parametrize("topology,names,link", PEER_CASES)
def test_a_peer_mission_over_zenoh_equals_the_mission_in_process(tmp_path, topology, names, link):
    """One process per rover (``fedmap node peer``) and the lander in this process, over
    Zenoh with mutual TLS and access control: every agent runs its side of the rounds, and
    the mission scored from their logs equals the in-process one, message for message.
    Rover 1 damages one mail (its check fails at the receiver, which refuses it; it is sent again)."""
    link = dict(link)
    text = _peer_mission(link.pop("steps", 40), names, topology=topology, **link)
    apart = deploy_zenoh(text, members=4, out=tmp_path / "out", strategies=names, frames=1,
                         faults={1: "corrupt@10"})
    here = _in_process(text)
    _same(here, apart, names)
    for name in names:
        assert sum(m.bytes for m in apart.runs[name].ledger) > 0, name
    if "loss" in link:
        assert all({m.status for m in apart.runs[n].ledger} - {"delivered"} for n in names)  # losses and drops drawn
    else:  # the team split into groups with leaders of their own, and healed (the in-process run's frames say so)
        config, source, _ = load_mission(None, overrides=[__import__("tomllib").loads(text)])
        truth, *_ = mission_terrain(config, source)
        groups = [len(set(f.leaders)) for f in run_mission(config, truth, frames=90).runs["raw"].frames if f.leaders]
        whole = [i for i, g in enumerate(groups) if g == 1]
        assert whole and any(g > 1 for g in groups[whole[0]:whole[-1]])
    assert [f["rover"] for f in apart.faults] == [1], apart.faults
    assert "damaged on the way" in apart.faults[0]["fault"] and "its check failed" in apart.faults[0]["fault"]
    assert not (tmp_path / "out.run" / "certs").exists()


@pytest.mark.xdist_group("loopback-c")
def test_a_leader_killed_mid_mission_is_replaced_and_the_team_goes_on(tmp_path):
    """No lander agent: rover 0, the lowest-numbered, leads its group. Its process is killed
    (SIGKILL) after the sync of step 30. At the next sync the lander's table says it left;
    every agent drops its links and the group elects rover 1, by the same rule and with no
    message about it. The mission finishes and is scored: rover 0's last record stands."""
    text = _peer_mission(60, ["raw"], topology="leader", lander_agent=False)
    apart = deploy_zenoh(text, members=4, out=tmp_path / "out", strategies=("raw",), frames=1,
                         faults={0: "die@30"})
    ledger = apart.runs["raw"].ledger
    assert [(f["rover"], f["fault"].split(";")[0]) for f in apart.faults] == \
        [(0, "left the team before the sync of step 40")]
    assert any(m.to == 0 for m in ledger if m.step <= 30)  # it led: its members sent to it
    assert not any(0 in (m.rover, m.to) for m in ledger if m.step > 30)  # then nobody reached it
    assert any(m.to == 1 and m.status == "delivered" for m in ledger if m.step > 30)  # rover 1 leads
    here = _in_process(text).runs["raw"]
    gone = apart.runs["raw"].trails[0]
    assert 0 < len(gone) < len(here.trails[0]) and here.trails[0][:len(gone)] == gone  # its log up to its last sync
    assert [m for m in here.ledger if m.step <= 30] != [] and \
        [(m.step, m.rover, m.to, m.bytes) for m in here.ledger if m.step <= 30] == \
        [(m.step, m.rover, m.to, m.bytes) for m in ledger if m.step <= 30]  # until then, the in-process mission


def test_a_peer_node_without_its_lander_is_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fedmap", "node", "peer", "--rover", "0", "--connect",
                        f"127.0.0.1:{free_port()}", "--connect-timeout", "1", "--state", str(tmp_path / "r0")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: zenoh: Unable to connect"), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and ".rs:" not in r.stderr  # (not zenoh's source line)


def test_a_rover_cannot_post_mail_as_another_rover(tmp_path):
    """Access control on a peer mission: rover 1 may post mail to rover 0, and tell the
    lander it finished, as itself, not as rover 2."""
    from fedmap.zenohnet.peer import finished_key, mail_key

    make_certs(tmp_path, hosts=["127.0.0.1"], rovers=3)
    port = free_port()

    def client(who: str):
        return open_session(node_config(connect=[f"tls/127.0.0.1:{port}"], certs=Certs.for_node(tmp_path, who),
                                        mode="client"))

    for guarded in (True, False):
        lander = open_session(node_config(listen=[f"tls/127.0.0.1:{port}"], certs=Certs.for_node(tmp_path, "base"),
                                          access=acl("t", 3) if guarded else None, mode="router"))
        with lander, client("rover0") as r0, client("rover1") as r1:
            inbox = _answer(r0, mail_key("t", "raw", 0, "*"), b"taken")
            desk = _answer(lander, finished_key("t", "*"), b"noted")
            time.sleep(0.5)
            assert _ask(r1, mail_key("t", "raw", 0, 1)) == [b"taken"]  # as itself
            forged = _ask(r1, mail_key("t", "raw", 0, 2))  # as rover 2
            assert forged == ([] if guarded else [b"taken"])  # (without the rules it gets through)
            assert _ask(r1, finished_key("t", 1)) == [b"noted"]
            assert _ask(r1, finished_key("t", 2)) == ([] if guarded else [b"noted"])
            inbox.undeclare()
            desk.undeclare()
        port = free_port()


# -- security -------------------------------------------------------------------------------------


def _base(certs: Path, port: int, team: str, rovers: int):
    return open_session(node_config(listen=[f"tls/127.0.0.1:{port}"], certs=Certs.for_node(certs, "base"),
                                    access=acl(team, rovers)))


def _rover(certs: Path, port: int, who: str):
    return open_session(node_config(connect=[f"tls/127.0.0.1:{port}"], certs=Certs.for_node(certs, who)))


def _ask(session, key: str) -> list[bytes]:
    """The payloads of the replies to a query on ``key``."""
    return [r.ok.payload.to_bytes() for r in session.get(key, payload=b"order", timeout=3.0) if r.ok is not None]


def _answer(session, key: str, what: bytes):
    def reply(q):
        q.reply(q.key_expr, what)
        q.drop()
    return session.declare_queryable(key, reply)


def test_a_rover_cannot_answer_as_another_rover(tmp_path):
    """Access control: rover 1's certificate may answer rover 1's orders, not rover 0's."""
    make_certs(tmp_path, hosts=["127.0.0.1"], rovers=2)
    port = free_port()
    with _base(tmp_path, port, "t", 2) as base, _rover(tmp_path, port, "rover1") as impostor:
        own = _answer(impostor, order_key("t", 1), b"report of rover 1")
        other = _answer(impostor, order_key("t", 0), b"forged report of rover 0")
        time.sleep(1.0)
        assert _ask(base, order_key("t", 1)) == [b"report of rover 1"]  # (the link works)
        assert _ask(base, order_key("t", 0)) == []  # the forged one never reaches the base
        own.undeclare()
        other.undeclare()


def test_a_certificate_from_another_ca_is_refused(tmp_path):
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    make_certs(ours, hosts=["127.0.0.1"], rovers=1)
    make_certs(theirs, hosts=["127.0.0.1"], rovers=1)
    port = free_port()
    with _base(ours, port, "t", 1) as base:
        # a rover with another CA's certificate (and that CA's root): the base's TLS refuses it
        with _rover(theirs, port, "rover0") as stranger:
            q = _answer(stranger, order_key("t", 0), b"stranger")
            time.sleep(1.5)
            assert _ask(base, order_key("t", 0)) == []
            q.undeclare()
        with _rover(ours, port, "rover0") as friend:  # the same, with our CA's: it gets through
            q = _answer(friend, order_key("t", 0), b"friend")
            time.sleep(1.5)
            assert _ask(base, order_key("t", 0)) == [b"friend"]
            q.undeclare()


def _listening_ports() -> set[int]:
    """The TCP ports this process listens on (Linux: its sockets in /proc/net/tcp*, state LISTEN)."""
    inodes = set()
    for fd in Path("/proc/self/fd").iterdir():
        try:
            link = os.readlink(fd)
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    ports = set()
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:
                ports.add(int(f[1].rsplit(":", 1)[1], 16))
    return ports


def test_a_node_that_connects_listens_nowhere(tmp_path):
    """A Zenoh peer listens on every interface by default (plain TCP, a random port): past
    the base's TLS and access control. A rover's node listens only where it is told: nowhere."""
    make_certs(tmp_path, hosts=["127.0.0.1"], rovers=1)
    port = free_port()
    before = _listening_ports()
    with _base(tmp_path, port, "t", 1):
        assert _listening_ports() - before == {port}
        with _rover(tmp_path, port, "rover0"):
            time.sleep(0.3)
            assert _listening_ports() - before == {port}  # the base's port only
    bare = zenoh.Config()  # (the default it guards against: a peer listens anyway)
    bare.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(bare):
        assert _listening_ports() - before


def test_a_node_sends_every_byte_over_the_network():
    """Zenoh hands messages above 3 kB to another process of the same machine through shared
    memory, around the network: a team rehearsed on one machine behind a thin link would not
    feel the link. Every node's config turns that off."""
    assert zenoh.Config().get_json("transport/shared_memory/enabled") == "true"  # (the default it guards against)
    assert node_config(connect=["tcp/127.0.0.1:7447"]).get_json("transport/shared_memory/enabled") == "false"


def test_listening_beyond_loopback_without_certificates_is_refused():
    check_listen([endpoint("127.0.0.1:7447", tls=False)], secure=False, insecure=False)  # loopback: fine
    with pytest.raises(FedmapError, match="refusing to listen on tcp/0.0.0.0:7447 without TLS"):
        check_listen([endpoint("0.0.0.0:7447", tls=False)], secure=False, insecure=False)
    check_listen([endpoint("0.0.0.0:7447", tls=True)], secure=True, insecure=False)
    check_listen([endpoint("0.0.0.0:7447", tls=False)], secure=False, insecure=True)
    r = subprocess.run([sys.executable, "-m", "fedmap", "node", "base", "--listen", "0.0.0.0:17447"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: refusing to listen on tcp/0.0.0.0:17447")
    assert len(r.stderr.strip().splitlines()) == 1


# -- nodes started on their own: fedmap node base / rover -------------------------------------------


@pytest.mark.xdist_group("loopback-c")
def test_a_base_station_killed_and_resumed_loses_nothing(tmp_path):
    """``fedmap node base`` and four ``fedmap node rover`` processes, each started on its own.
    The base is killed (SIGKILL) once it has journaled 3 rounds and started again with
    ``--resume``: it replays its journal and carries on, the rovers (still running) answer
    the order it sends again with the same report. Scored from the nodes' logs, the mission
    equals the in-process one."""
    text = _mission(60, ["predictive"])
    (tmp_path / "mission.toml").write_text(text)
    out = tmp_path / "out"
    work = tmp_path / "out.run"
    port = free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    base_argv = [sys.executable, "-m", "fedmap", "--quiet", "node", "base", str(tmp_path / "mission.toml"),
                 "--listen", f"127.0.0.1:{port}", "--out", str(out), "--team", "kill"]
    logs = {name: open(tmp_path / f"{name}.log", "ab") for name in ("base", "base2", *(f"rover{k}" for k in range(4)))}
    rovers = [subprocess.Popen([sys.executable, "-m", "fedmap", "node", "rover", "--rover", str(k), "--connect",
                                f"127.0.0.1:{port}", "--team", "kill", "--state", str(work / f"rover{k}.state")],
                               env=env, stdout=logs[f"rover{k}"], stderr=subprocess.STDOUT) for k in range(4)]
    try:
        base = subprocess.Popen(base_argv, env=env, stdout=logs["base"], stderr=subprocess.STDOUT)
        journal = work / "mission-journal"
        t_end = time.monotonic() + 300
        while len(list(journal.glob("predictive-*.frame"))) < 3:
            assert base.poll() is None and time.monotonic() < t_end, (tmp_path / "base.log").read_text()[-2000:]
            time.sleep(0.01)
        base.kill()
        base.wait(timeout=30)
        assert all(r.poll() is None for r in rovers)  # the rovers carry on waiting
        again = subprocess.run([*base_argv, "--resume"], env=env, stdout=logs["base2"], stderr=subprocess.STDOUT,
                               timeout=600)
        assert again.returncode == 0, (tmp_path / "base2.log").read_text()[-2000:]
        for r in rovers:  # each stops once told the mission is over
            assert r.wait(timeout=60) == 0
    finally:
        for p in rovers:
            if p.poll() is None:
                p.kill()
        for fh in logs.values():
            fh.close()
    from fedmap.mission.scoring import score_folder

    apart = score_folder(work, frames=1)
    _same(_in_process(text), apart, ("predictive",))
    resumed = [f["fault"] for f in apart.faults if f["rover"] == -1]
    assert len(resumed) == 1 and resumed[0].startswith("base station resumed: "), apart.faults
    assert int(resumed[0].split(": ")[1].split(" ")[0]) >= 3  # at least the rounds journaled before the kill
