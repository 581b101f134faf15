"""Real processes on loopback: a SuperLink, four SuperNodes (``fedmap rover``), ``flwr run``.

Each test has its own ``FLWR_HOME`` in a temporary folder, update checks and telemetry
off, free ports picked at run time, and stops every process it started by its PID
(process group) in a ``finally`` (``Processes.__exit__``), also when it fails.
"""

import json
import signal
import sys

import numpy as np
import pytest

pytest.importorskip("flwr")

from fedmap.explore import explore  # noqa: E402
from fedmap.federation.codecs import Encoder  # noqa: E402
from fedmap.federation.runner import run_federation  # noqa: E402
from fedmap.flower.launch import Processes, flower_env, free_port, run_base_station, socket_dir  # noqa: E402
from fedmap.flower.mission.deploy import ROVER_HOST_SOCKET, RoverHost  # noqa: E402
from fedmap.flower.settings import RunSettings  # noqa: E402
from fedmap.maps.io import save_map  # noqa: E402
from fedmap.maps.sources import TerrainSource, load_truth  # noqa: E402
from fedmap.nets.model import build_model, get_weights, load_model, preset  # noqa: E402
from fedmap.pipeline import PipelineConfig  # noqa: E402

pytestmark = pytest.mark.slow

SEED = 1
RUN = {"net": "small", "init": "random", "epochs": 5, "lr": 1e-2, "seed": SEED, "rovers": 4,
       "min-rovers": 3, "connect-timeout": 120.0, "pairs": 10}


@pytest.fixture
def flower_home(tmp_path, monkeypatch):
    monkeypatch.setenv("FLWR_HOME", str(tmp_path / "flwr-home"))
    monkeypatch.setenv("FLWR_DISABLE_UPDATE_CHECK", "1")
    monkeypatch.setenv("FLWR_TELEMETRY_ENABLED", "0")
    return tmp_path


def _team(tmp_path):
    """Ground truth and the four rovers' local maps (as the demo explores them), saved as files."""
    truth = load_truth(TerrainSource(terrain="mars", size=64), seed=SEED)
    maps = explore(truth, 4, "quadrants", seed=SEED, sensor_radius=PipelineConfig().explore.sensor_radius)
    save_map(truth, tmp_path / "truth.npy")
    for k, m in enumerate(maps):
        save_map(m, tmp_path / f"local{k}.npy")
    return maps


#: The kill tests' rovers beat every 10 s (Flower's least): the base takes a killed rover for
#: gone after 20 s, not 60 s.
HEARTBEAT = ["--heartbeat", "10"]


def _start_rovers(procs: Processes, port: int, tmp_path, rovers=range(4), extra=(), host: RoverHost | None = None):
    """Each `fedmap rover` in its own process group, stopped by its PID: forked by ``host`` (a host
    of rovers, as ``fedmap mission --deploy local`` starts them), or as a process of its own."""
    for k in rovers:
        argv = [sys.executable, "-m", "fedmap", "rover", "--superlink", f"127.0.0.1:{port}", "--partition-id", str(k),
                "--map", str(tmp_path / f"local{k}.npy"), "--port", str(free_port()), *extra]
        env, log = flower_env(tmp_path / f"rover{k}-home"), tmp_path / f"rover{k}.log"
        if host is not None:
            host.start(f"rover{k}", argv, env=env, log=log)
        else:
            procs.start(f"rover{k}", argv, env=env, log=log)


def _reference(maps):
    """The in-process runner on the same maps, seed and settings."""
    return _reference_with(maps, RUN)


def _reference_with(maps, run, **participation):
    net = preset("small", 64)
    init = get_weights(build_model(net, seed=SEED))
    return init, run_federation(init, net, maps, RunSettings.from_run_config(run).federation, **participation)


def _run(tmp_path, run: dict, on_status=None, extra=(), forked=True):
    """The base station and four rovers; ``forked``: the rovers are forked from one host of rovers
    that imported fedmap, torch and Flower once (5 s of CPU less per rover; ``on_status(status, rovers, port,
    host)`` gets it), else each is a fresh Python, as on a robot of its own."""
    port, out = free_port(), tmp_path / "out"
    maps = _team(tmp_path)
    with socket_dir("fedmap-rovers-", ROVER_HOST_SOCKET) as socks, Processes() as rovers:
        host = RoverHost(rovers, socks, env=flower_env(tmp_path / "host-home"), log=tmp_path / "rover-host.log") \
            if forked else None
        status = run_base_station({**run, "out": str(out), "truth": str(tmp_path / "truth.npy")}, host="127.0.0.1",
                                  port=port,
                                  on_ready=lambda: _start_rovers(rovers, port, tmp_path, extra=extra, host=host),
                                  on_status=(lambda st: on_status(st, rovers, port, host)) if on_status else None)
    assert status["state"] == "done"
    return maps, out, json.loads((out / "metrics.json").read_text())


@pytest.mark.xdist_group("loopback-b")  # a long loopback run: see addopts in pyproject.toml
def test_four_rovers_one_round_equal_the_in_process_runner(flower_home):
    """Four rovers started as a fresh Python each, as on robots of their own (the other loopback
    tests fork theirs from a host of rovers)."""
    maps, out, m = _run(flower_home, {**RUN, "deadline": 300.0}, forked=False)
    init, ref = _reference(maps)
    got = get_weights(load_model(out / "global_model.safetensors"))
    for k in ref.weights:
        np.testing.assert_allclose(got[k], ref.weights[k], atol=1e-5)
    ckpt = get_weights(load_model(out / "global_model_round1.safetensors"))
    assert all(np.array_equal(ckpt[k], got[k]) for k in got)
    n = len(Encoder("fp32").encode(init))  # fp32 payload of this network: the same size both ways
    rnd = m["rounds"][0]
    assert rnd["missing"] == [] and rnd["dropped"] == {} and sorted(rnd["aggregation_counts"]) == ["0", "1", "2", "3"]
    assert rnd["uplink_bytes"] == {str(k): n for k in range(4)} == rnd["downlink_bytes"]
    assert rnd["flower_uplink_bytes"] == {str(k): n + 135 for k in range(4)} == rnd["flower_downlink_bytes"]
    assert rnd["final_broadcast_received_by"] == [0, 1, 2, 3]
    assert m["bytes"] == {"uplink": 4 * n, "downlink": 4 * n, "uplink_per_agent_round": n}
    assert {"psnr", "ssim", "path"} <= set(m["global"]) and (out / "figure.png").is_file()


@pytest.mark.xdist_group("loopback-c")  # a long loopback run: see addopts in pyproject.toml
def test_a_rover_killed_mid_round_leaves_three(flower_home):
    killed = []

    def kill_rover3(st, rovers, port, host):
        if st["state"] == "running" and st.get("round") == 1 and not st.get("saved") and not killed:
            rovers.stop("rover3", sig=signal.SIGKILL)  # by its PID (process group), while the round runs
            killed.append(True)

    maps, out, m = _run(flower_home, {**RUN, "deadline": 120.0}, on_status=kill_rover3, extra=HEARTBEAT)
    assert killed
    rnd = m["rounds"][0]
    assert sorted(rnd["aggregation_counts"]) == ["0", "1", "2"]
    assert rnd["missing"] == [3] and rnd["dropped"] == {}  # no reply: missing, never "dropped"
    # its node's heartbeat lapsed before the deadline (a node that never replied is not yet known as rover 3)
    assert [why for why in rnd["node_errors"].values() if "Node Unavailable" in why]
    _, ref = _reference(maps[:3])
    got = get_weights(load_model(out / "global_model.safetensors"))
    for k in ref.weights:
        np.testing.assert_allclose(got[k], ref.weights[k], atol=1e-5)


@pytest.mark.xdist_group("loopback-a")  # a long loopback run: see addopts in pyproject.toml
def test_a_killed_rover_restarted_rejoins_with_an_update_codec(flower_home):
    """Real processes: rover 3 is killed (SIGKILL) as round 2 goes out and started again at
    once, with an ``update-int4+zstd`` downlink. Its state is gone: it misses round 2 (its
    old node never replies), joins round 3 as a new node, is sent a keyframe, and the
    final model equals the in-process runner with the same participation.

    Flower's own heartbeat (30 s) here, not ``HEARTBEAT``: round 2 ends when the killed node's
    heartbeat lapses (2 x its interval), and the restarted rover must be connected by then to
    be sent round 3. A restart took 30 s on a loaded 2-core machine, past the 20 s of a 10 s
    heartbeat (round 3 then went out without it: 'not connected when the round began')."""
    run = {**RUN, "rounds": 3, "downlink": "update-int4+zstd", "deadline": 120.0}
    events = []

    def kill_and_restart_rover3(st, rovers, port, host):
        if st["state"] == "running" and st.get("round") == 2 and not st.get("saved") and not events:
            rovers.stop("rover3", sig=signal.SIGKILL)
            _start_rovers(rovers, port, flower_home, rovers=[3], host=host)
            events.append("restarted")

    maps, out, m = _run(flower_home, run, on_status=kill_and_restart_rover3)
    assert events
    r1, r2, r3 = m["rounds"]
    assert sorted(r1["aggregation_counts"]) == sorted(r3["aggregation_counts"]) == ["0", "1", "2", "3"]
    assert sorted(r2["aggregation_counts"]) == ["0", "1", "2"] and r2["missing"] == [3]
    assert "Node Unavailable" in r2["missing_why"]["3"]  # its heartbeat lapsed before the deadline
    # the broadcast of round r's model is booked in round r's record: rovers 0-2 got round 2's
    # model as an update, the restarted rover (no model) got it as a keyframe
    assert not r1.get("keyframes") and r2["keyframes"] == [3] and not r3.get("keyframes")
    assert r2["downlink_bytes"]["3"] > 4 * max(r2["downlink_bytes"][str(k)] for k in range(3))
    init, ref = _reference_with(maps, run, absent={2: [3]}, restarted={3: [3]})
    got = get_weights(load_model(out / "global_model.safetensors"))
    for k in ref.weights:
        np.testing.assert_allclose(got[k], ref.weights[k], atol=1e-5)
