"""Flower apps without processes: the real ClientApp and Strategy code on in-memory messages.

A fake grid stands in for the SuperLink (as Flower's own strategy tests do with mock
replies); the global model must equal :func:`run_federation` for the same settings.
"""

import subprocess
import sys
import time
import tomllib

import numpy as np
import pytest

pytest.importorskip("flwr")

from flwr.app import ConfigRecord, Context, Error, Message, RecordDict  # noqa: E402
from flwr.server.superlink.linkstate.utils import create_message_error_unavailable_res_message  # noqa: E402
from flwr.supercore.task_identity import TaskIdentity  # noqa: E402

from fedmap.errors import FedmapError, RejectedUpdate  # noqa: E402
from fedmap.explore import explore  # noqa: E402
from fedmap.federation.aggregate import weighted_average  # noqa: E402
from fedmap.federation.codecs import Encoder  # noqa: E402
from fedmap.federation.runner import agent_seed, run_federation  # noqa: E402
from fedmap.flower.launch import key_values, make_certs  # noqa: E402
from fedmap.flower.polling import REPLY_LOST  # noqa: E402
from fedmap.flower.records import check_flower_count, flower_overhead, from_record, to_record  # noqa: E402
from fedmap.flower.rover import rover_node_config  # noqa: E402
from fedmap.flower.settings import RunSettings  # noqa: E402
from fedmap.flower.snapshot import client as client_app  # noqa: E402
from fedmap.flower.snapshot.server import NO_REPLY, NOT_CONNECTED, FedmapStrategy  # noqa: E402
from fedmap.flower.task import load_local_map  # noqa: E402
from fedmap.maps.io import save_map  # noqa: E402
from fedmap.nets.model import build_model, get_weights, preset, set_weights  # noqa: E402
from fedmap.nets.training import fit  # noqa: E402


@pytest.fixture(autouse=True)
def task_identity():
    """Messages need a run id; in a real run the ServerApp/ClientApp process sets it."""
    old = (TaskIdentity._run_id, TaskIdentity._node_id, TaskIdentity._task_id)
    TaskIdentity.run_id, TaskIdentity.node_id, TaskIdentity.task_id = 1, 0, 1
    yield
    TaskIdentity._run_id, TaskIdentity._node_id, TaskIdentity._task_id = old


class FakeGrid:
    def __init__(self, node_ids):
        self.node_ids = list(node_ids)

    def get_node_ids(self):
        return list(self.node_ids)


def _team(tmp_path, blob_map, n=4):
    """Local maps saved as files, one node config per rover (node id = 100 + k)."""
    maps = explore(blob_map, n, "quadrants")
    nodes = {}
    for k, m in enumerate(maps):
        path = tmp_path / f"local{k}.npy"
        save_map(m, path)
        nodes[100 + k] = {"partition-id": k, "map": str(path)}
    return maps, nodes


RUN = {"net": "small", "init": "random", "epochs": 3, "lr": 1e-2, "seed": 4, "rovers": 4, "min-rovers": 2}


def _round(strategy, grid, contexts, arrays, server_round, *, skip=(), fail=(), twice=False):
    """One round through the real ClientApp ``train`` and the strategy. ``twice``: each
    message also arrives as a copy (``polling.copy_of``, as the base sends one when a reply
    is long overdue), whose reply must be the first's."""
    from fedmap.flower.polling import copy_of

    msgs = strategy.configure_train(server_round, arrays, ConfigRecord(), grid)
    replies = []
    for m in msgs:
        m.metadata.__dict__["_message_id"] = m.object_id  # what Flower's grid does when it pushes
        node = m.metadata.dst_node_id
        if node in skip:
            continue
        if node in fail:  # the SuperLink's own error reply for a node that stopped heartbeating
            replies.append(create_message_error_unavailable_res_message(m.metadata, "node unavailable"))
            continue
        replies.append(client_app.train(m, contexts[node]))
        if twice:
            again = copy_of(m)
            again.metadata.__dict__["_message_id"] = again.object_id
            second = client_app.train(again, contexts[node])
            assert second.metadata.reply_to_message_id == again.object_id != m.object_id
            assert from_record(second.content["uplink"]) == from_record(replies[-1].content["uplink"])
            assert dict(second.content["metrics"]) == dict(replies[-1].content["metrics"])
    return strategy.aggregate_train(server_round, replies)


def _contexts(nodes, run):
    return {n: Context(run_id=1, node_id=n, node_config=cfg, state=RecordDict(), run_config=run)
            for n, cfg in nodes.items()}


@pytest.mark.parametrize("downlink,twice", [("fp16", False), ("update-int8", True)])
def test_two_rounds_equal_run_federation(tmp_path, blob_map, downlink, twice):
    """Rover state (held model, error-feedback residual) survives between rounds in context.state.
    ``twice``: every message also arrives as a copy; the rover answers it with the reply it
    gave, neither training again (its residual would move) nor decoding the broadcast again
    (an update relative to a model it no longer holds), so nothing changes."""
    run = {**RUN, "rounds": 2, "uplink": "update-int8", "downlink": downlink}
    maps, nodes = _team(tmp_path, blob_map)
    settings = RunSettings.from_run_config(run)
    strategy = FedmapStrategy(settings)
    grid, contexts = FakeGrid(nodes), _contexts(nodes, run)
    arrays = to_record(b"")
    for r in (1, 2):
        arrays, _ = _round(strategy, grid, contexts, arrays, r, twice=twice)
    net = preset("small", blob_map.shape[0])
    ref = run_federation(get_weights(build_model(net, seed=4)), net, maps, settings.federation)
    for k in ref.weights:
        np.testing.assert_allclose(strategy.held[k], ref.weights[k], atol=1e-6)
    for got, want in zip(strategy.history, ref.history):
        assert got.uplink_bytes == want.uplink_bytes
        assert got.aggregation_counts == {k: float(v) for k, v in want.aggregation_counts.items()}
    # round 1's broadcast went out with round 2's messages, to every rover
    assert strategy.history[0].downlink_bytes == ref.history[0].downlink_bytes
    # the payload Flower carried is exactly what the runner counted, plus the .npy header and key
    n = ref.history[0].uplink_bytes[0]
    assert strategy.history[0].flower.uplink_bytes[0] == n + 128 + len("payload")


def test_missing_and_failed_rovers_are_recorded(tmp_path, blob_map):
    run = {**RUN, "rounds": 1}
    maps, nodes = _team(tmp_path, blob_map)
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    arrays, metrics = _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1, skip={103})
    rec = strategy.history[0]
    assert rec.missing == [3] and sorted(rec.aggregation_counts) == [0, 1, 2]
    assert metrics["rovers-used"] == 3
    # independent reference: train the three survivors by hand and FedAvg them
    net = preset("small", blob_map.shape[0])
    init = get_weights(build_model(net, seed=4))
    ws = []
    for k in range(3):
        model = build_model(net)
        set_weights(model, init)
        fit(model, maps[k], strategy.settings.federation.local, seed=agent_seed(4, 0, k))
        ws.append(get_weights(model))
    ref = weighted_average(ws, [m.n_known for m in maps[:3]])
    for k in ref:
        np.testing.assert_allclose(strategy.held[k], ref[k], atol=1e-6)
    # the broadcast is fedmap's fp32 payload of that model
    assert from_record(arrays) == Encoder("fp32").encode(strategy.held)


def test_rover_lost_in_a_later_round_is_missing_by_name(tmp_path, blob_map):
    """A rover that delivers nothing is *missing* (with Flower's reason) whether it stayed
    silent or Flower reported its node gone; *dropped* is for replies that were not used."""
    run = {**RUN, "rounds": 2}
    _, nodes = _team(tmp_path, blob_map)
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    grid, contexts = FakeGrid(nodes), _contexts(nodes, run)
    arrays, _ = _round(strategy, grid, contexts, to_record(b""), 1)
    _round(strategy, grid, contexts, arrays, 2, fail={101})
    rec = strategy.history[1]
    assert rec.missing == [1] and "Node Unavailable" in rec.flower.missing_why[1]
    assert rec.dropped == {} and sorted(rec.aggregation_counts) == [0, 2, 3]


def test_a_rover_not_connected_when_a_round_begins_is_missing_as_not_connected(tmp_path, blob_map):
    """Rover 3's node is gone from the grid before round 2 (a restart still starting): it is
    missing because nothing was sent to it, not for want of a reply; rover 2, sent the round
    and silent, is missing for want of a reply."""
    run = {**RUN, "rounds": 2}
    _, nodes = _team(tmp_path, blob_map)
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    grid, contexts = FakeGrid(nodes), _contexts(nodes, run)
    arrays, _ = _round(strategy, grid, contexts, to_record(b""), 1)
    grid.node_ids.remove(103)
    _round(strategy, grid, contexts, arrays, 2, skip={102})
    rec = strategy.history[1]
    assert rec.missing == [2, 3] and sorted(rec.aggregation_counts) == [0, 1]
    assert rec.flower.missing_why == {2: NO_REPLY, 3: NOT_CONNECTED}
    # a silent node the base never heard from may be any rover: then none is said to be unconnected
    one = {**RUN, "rounds": 1}
    fresh = FedmapStrategy(RunSettings.from_run_config(one))
    _round(fresh, FakeGrid(nodes), _contexts(nodes, one), to_record(b""), 1, skip={102, 103})
    assert fresh.history[0].flower.missing_why == {2: NO_REPLY, 3: NO_REPLY}


def test_too_few_rovers_end_the_run(tmp_path, blob_map):
    run = {**RUN, "rounds": 1, "min-rovers": 3}
    _, nodes = _team(tmp_path, blob_map)
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    with pytest.raises(FedmapError, match=r"2 rover\(s\) delivered an update, fewer than min-rovers=3"):
        _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1, skip={101, 102})


def test_rejected_update_drops_a_rover_and_a_mistake_stops_the_run(tmp_path, blob_map, monkeypatch):
    """The ClientApp reports a RejectedUpdate (the base drops that rover) apart from any
    other error (fatal: the base stops the run with the rover's line)."""
    run = {**RUN, "rounds": 1}
    _, nodes = _team(tmp_path, blob_map)
    real = client_app.train_round

    def failing(error):
        def train_round(settings, local, pid, server_round, held, encoder):
            if pid == 1:
                raise error
            return real(settings, local, pid, server_round, held, encoder)
        return train_round

    monkeypatch.setattr(client_app, "train_round", failing(RejectedUpdate("update holds NaN or infinite weights")))
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1)
    rec = strategy.history[0]
    assert rec.dropped == {1: "update holds NaN or infinite weights"} and sorted(rec.aggregation_counts) == [0, 2, 3]

    monkeypatch.setattr(client_app, "train_round", failing(FedmapError("no such init weights file x.safetensors")))
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    with pytest.raises(FedmapError, match="^rover 1: no such init weights file x.safetensors$"):
        _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1)


def test_a_rover_with_a_bad_node_config_stops_the_run(tmp_path, blob_map):
    """A node config the rover cannot read is a mistake, not a dropout: the base stops."""
    run = {**RUN, "rounds": 1}
    _, nodes = _team(tmp_path, blob_map)
    nodes[103] = {"partition-id": 3, "map": str(tmp_path / "missing.npy")}
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    with pytest.raises(FedmapError, match=r"^a rover \(node 103\) failed before training: .*missing\.npy"):
        _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1)


def test_flower_settings_are_the_one_config_builder():
    """The base station's run config builds the same PipelineConfig as fedmap run / method_config."""
    from fedmap.config import method_config

    s = RunSettings.from_run_config({})
    assert s.pipeline == method_config("paper")
    s = RunSettings.from_run_config({"rounds": 3, "net": "small", "init": "random", "lr": 0.01, "min-size": 20})
    assert s.pipeline == method_config("paper", rounds=3, net="small", init="random", lr=0.01, min_size=20)


def test_waiting_for_rovers_has_a_deadline():
    run = {**RUN, "connect-timeout": 0.05}
    strategy = FedmapStrategy(RunSettings.from_run_config(run), sleep=lambda s: None)
    with pytest.raises(FedmapError, match=r"only 1 rover\(s\) connected after 0.05 s, fewer than min-rovers=2"):
        strategy.configure_train(1, to_record(b""), ConfigRecord(), FakeGrid([7]))
    # enough rovers: go on with those connected once the wait is over
    msgs = strategy.configure_train(1, to_record(b""), ConfigRecord(), FakeGrid([7, 8, 9]))
    assert sorted(m.metadata.dst_node_id for m in msgs) == [7, 8, 9]


def test_flower_byte_count_cross_check():
    """Flower counts ``np.save`` bytes + the key: a .npy v1 header of a 1-D uint8 array is 128 B."""
    for n in (0, 5, 202_940):
        payload = bytes(range(256)) * (n // 256) + bytes(n % 256)
        rec = to_record(payload)
        assert from_record(rec) == payload
        assert flower_overhead(n) == 128 + 7
        assert check_flower_count(rec, n) == rec.count_bytes() == n + 135
    with pytest.raises(FedmapError, match="byte accounting mismatch"):
        check_flower_count(to_record(b"abc"), 4)


def test_run_config_errors():
    with pytest.raises(FedmapError, match="unknown run-config key 'roundz' \\(did you mean 'rounds'\\?\\)"):
        RunSettings.from_run_config({"roundz": 2})
    with pytest.raises(FedmapError, match="config value rounds must be an integer, got 'two'"):
        RunSettings.from_run_config({"rounds": "two"})
    with pytest.raises(FedmapError, match="min-rovers"):
        RunSettings.from_run_config({"rovers": 2, "min-rovers": 3})
    with pytest.raises(FedmapError, match="unknown aggregator"):
        RunSettings.from_run_config({"aggregator": "fedprox"})
    s = RunSettings.from_run_config({"deadline": 30, "masked": "true"})  # TOML ints and CLI strings are fine
    assert s.base.deadline == 30.0 and s.pipeline.train.masked is True


def test_node_config_generator_matches_the_demo_exploration():
    from fedmap.maps.sources import TerrainSource, load_truth
    from fedmap.pipeline import PipelineConfig

    pid, m = load_local_map({"partition-id": 2, "terrain": "moon", "size": 64, "agents": 4, "seed": 3})
    cfg = PipelineConfig(terrain=TerrainSource(terrain="moon", size=64), seed=3)
    ref = explore(load_truth(TerrainSource(terrain="moon", size=64), seed=3), 4, "quadrants", seed=3,
                  sensor_radius=cfg.explore.sensor_radius)[2]
    assert pid == 2 and np.array_equal(m.classes, ref.classes)
    with pytest.raises(FedmapError, match="partition-id"):
        load_local_map({"terrain": "moon"})
    with pytest.raises(FedmapError, match="not below agents=4"):
        load_local_map({"partition-id": 4, "terrain": "moon", "size": 64})
    with pytest.raises(FedmapError, match="exactly one of --map"):
        rover_node_config(partition_id=0, map_path=None, terrain=None, size=64, agents=4, explore="quadrants",
                          seed=0, out=None)


def test_key_values_parse_back_with_flowers_parser():
    from flwr.common.config import parse_config_args

    d = {"partition-id": 3, "map": "/data/my maps/rover 3.png", "seed": 0, "masked": False, "lr": 0.001}
    assert parse_config_args([key_values(d)]) == d
    pairs = (kv.split("=", 1) for kv in key_values({"a": 1.5, "b": "x"}).split())
    assert tomllib.loads("\n".join(f"{k} = {v}" for k, v in pairs)) == {"a": 1.5, "b": "x"}


def test_certs_verify(tmp_path):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    make_certs(tmp_path, hosts=["base.local", "10.0.0.2"], rovers=2)
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.crt").read_bytes())
    srv = x509.load_pem_x509_certificate((tmp_path / "server.pem").read_bytes())
    srv.verify_directly_issued_by(ca)  # raises if the signature does not check out
    san = srv.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    # the rovers' names, and loopback, where the base's own processes reach its SuperLink
    assert san.get_values_for_type(x509.DNSName) == ["base.local", "localhost"]
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.2", "127.0.0.1"]
    key = serialization.load_ssh_private_key((tmp_path / "rover1").read_bytes(), None)
    pub = serialization.load_ssh_public_key((tmp_path / "rover1.pub").read_bytes())
    assert isinstance(key, ec.EllipticCurvePrivateKey) and key.curve.name == "secp384r1"
    assert key.public_key().public_numbers() == pub.public_numbers()
    assert (tmp_path / "rover1").stat().st_mode & 0o077 == 0
    client = x509.load_pem_x509_certificate((tmp_path / "rover1.crt").read_bytes())  # what the front asks of rover 1
    client.verify_directly_issued_by(ca)
    assert client.public_key().public_numbers() == pub.public_numbers()
    assert client.subject.rfc4514_string() == "CN=rover1"


@pytest.mark.slow
def test_fedmap_imports_and_runs_without_flwr(tmp_path):
    """Block flwr: the CLI loads, the demo's modules import, and rover/base-station say how to install."""
    code = (
        "import sys; sys.modules['flwr'] = None\n"
        "import fedmap.cli, fedmap.pipeline, fedmap.federation.runner\n"
        "from fedmap.cli import main\n"
        "sys.exit(main(['rover', '--superlink', '127.0.0.1:1', '--partition-id', '0', '--terrain', 'mars', "
        "'--size', '64']))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == "error: Flower is not installed; run: pip install 'fedmap[flower]'"


def test_app_pyproject_declares_every_run_config_key():
    """`flwr run` only accepts overrides of keys the app declares; they must match fedmap's defaults."""
    from fedmap.flower.launch import app_dir
    from fedmap.flower.settings import RUN_DEFAULTS

    app = tomllib.loads((app_dir() / "pyproject.toml").read_text())["tool"]["flwr"]["app"]
    assert app["config"] == RUN_DEFAULTS, "a setting changed: run `python -m fedmap.flower.settings` to regenerate it"
    assert app["components"] == {"serverapp": "fedmap.flower.snapshot.server:app",
                                 "clientapp": "fedmap.flower.snapshot.client:app"}


@pytest.mark.parametrize("event", ["missed", "restarted"])
def test_rejoin_with_an_update_downlink_equals_the_in_process_runner(tmp_path, blob_map, event):
    """update-int4+zstd downlink, 4 rounds. ``missed``: rover 1 misses round 2 (its node gets
    no message). ``restarted``: rover 1 comes back before round 3 as a new node with its state
    gone. Either way it gets a keyframe, the base uses every update, the ledger names it by
    partition id, and the global model equals run_federation with the same participation."""
    run = {**RUN, "rounds": 4, "uplink": "update-int8", "downlink": "update-int4+zstd"}
    maps, nodes = _team(tmp_path, blob_map)
    settings = RunSettings.from_run_config(run)
    strategy = FedmapStrategy(settings)
    grid, contexts = FakeGrid(nodes), _contexts(nodes, run)
    arrays = to_record(b"")
    for r in (1, 2, 3, 4):
        if event == "restarted" and r == 3:  # same rover, new SuperNode: new node id, empty state
            grid.node_ids = [100, 201, 102, 103]
            contexts[201] = _contexts({201: nodes[101]}, run)[201]
        skip = {101} if event == "missed" and r == 2 else set()
        arrays, _ = _round(strategy, grid, contexts, arrays, r, skip=skip)
    net = preset("small", blob_map.shape[0])
    kw = {"absent": {2: [1]}} if event == "missed" else {"restarted": {3: [1]}}
    ref = run_federation(get_weights(build_model(net, seed=4)), net, maps, settings.federation, **kw)
    for k in ref.weights:
        np.testing.assert_allclose(strategy.held[k], ref.weights[k], atol=1e-6)
    assert all(rec.dropped == {} for rec in strategy.history)
    # round 2's model reached rover 1 as a keyframe (it held round 0's or nothing)
    assert strategy.history[1].keyframes == [1] == ref.history[1].keyframes
    for got, want in zip(strategy.history[:3], ref.history[:3]):
        assert got.downlink_bytes == want.downlink_bytes  # keyed by partition id, never node-…
        assert got.missing == want.missing


def test_a_stale_rover_refuses_a_broadcast_it_cannot_decode(tmp_path, blob_map):
    """If the base believed a rover held the broadcast's reference but it does not (its state
    is gone under the same node id), the rover refuses instead of training on a wrong model."""
    run = {**RUN, "rounds": 2, "downlink": "update-int8"}
    _, nodes = _team(tmp_path, blob_map)
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    grid, contexts = FakeGrid(nodes), _contexts(nodes, run)
    arrays, _ = _round(strategy, grid, contexts, to_record(b""), 1)
    _round(strategy, grid, contexts, arrays, 2)  # round 2's broadcast is relative to round 1's model
    contexts[102] = _contexts({102: nodes[102]}, run)[102]  # rover 2 lost its state, same node
    strategy.settings = RunSettings.from_run_config({**run, "rounds": 3})
    _round(strategy, grid, contexts, arrays, 3)
    rec = strategy.history[2]
    assert "stale model" in rec.dropped[2] and sorted(rec.aggregation_counts) == [0, 1, 3]
    _round(strategy, grid, contexts, arrays, 4)  # it reported what it holds: now it gets a keyframe
    assert strategy.history[2].keyframes == [2] and sorted(strategy.history[3].aggregation_counts) == [0, 1, 2, 3]


def test_the_team_map_size_is_the_majority_not_the_first_reply(tmp_path, blob_map):
    from fedmap.maps.grid import GridMap

    run = {**RUN, "rounds": 1}
    _, nodes = _team(tmp_path, blob_map)
    big = GridMap(np.zeros((32, 32), np.uint8), 1.0, "other team")
    save_map(big, tmp_path / "big.npy")
    nodes[99] = {"partition-id": 0, "map": str(tmp_path / "big.npy")}  # replies first, wrong size
    del nodes[100]
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1)
    rec = strategy.history[0]
    assert rec.dropped == {0: "rover 0: its map is 32x32, the team's is 24x24"}
    assert sorted(rec.aggregation_counts) == [1, 2, 3] and strategy.shape == (24, 24)
    # with a ground truth the base knows the size before any reply: the 24x24 rovers are wrong
    save_map(big, tmp_path / "truth.npy")
    strategy = FedmapStrategy(RunSettings.from_run_config({**run, "truth": str(tmp_path / "truth.npy"),
                                                           "min-rovers": 1}))
    _round(strategy, FakeGrid(nodes), _contexts(nodes, run), to_record(b""), 1)
    assert sorted(strategy.history[0].dropped) == [1, 2, 3] and list(strategy.history[0].aggregation_counts) == [0]


def test_the_first_round_waits_its_own_deadline_and_the_later_ones_the_deadline(tmp_path, monkeypatch):
    """Flower's strategy takes one timeout for every round; the base station's grid gives the
    first exchange ``first-deadline`` (it also covers each rover's start-up) and every later
    one the timeout it is given. 0 (the default) is the deadline for every round."""
    from fedmap.flower.snapshot import server as server_app

    waits = []
    monkeypatch.setattr(server_app, "exchange", lambda grid, msgs, timeout, **kw: waits.append(timeout) or [])
    seen = {}

    def start(self, *, grid, timeout, **kw):  # what run_base_station hands Flower
        seen["grid"], seen["timeout"] = grid, timeout
        raise FedmapError("stop here")

    monkeypatch.setattr(server_app.FedmapStrategy, "start", start)
    for run, first, later in (({"deadline": 90.0, "first-deadline": 240.0}, 240.0, 90.0),
                              ({"deadline": 90.0}, 90.0, 90.0)):
        waits.clear()
        with pytest.raises(FedmapError, match="stop here"):
            server_app.run_base_station(FakeGrid([]), RunSettings.from_run_config({**RUN, "out": str(tmp_path), **run}))
        grid = seen["grid"]
        assert isinstance(grid, server_app.FirstRoundGrid) and seen["timeout"] == later
        for _ in range(3):
            grid.send_and_receive([], timeout=seen["timeout"])
        assert waits == [first, later, later]
        assert list(grid.get_node_ids()) == []  # everything else is the grid's own
    with pytest.raises(FedmapError, match="first-deadline"):
        RunSettings.from_run_config({**RUN, "first-deadline": -1.0})


def _with_id(msg):
    """``msg`` with its message ID set, as Flower sets it when a message is pushed."""
    msg.metadata.__dict__["_message_id"] = msg.object_id
    return msg


def _http_grid(monkeypatch, client, pushed):
    """Flower's real ``HttpGrid``, never connected: ``client`` stands in for the SuperLink and
    pushing returns the IDs of ``pushed``. Object pulls retry every 0.05-0.2 s."""
    from flwr.supercore.run import Run
    from flwr.superlink.grid import HttpGrid

    from fedmap.flower import polling

    grid = HttpGrid(insecure=True, token="t")
    grid.set_run(Run.create_empty(1))
    monkeypatch.setattr(HttpGrid, "_runtime_client", property(lambda self: client))
    monkeypatch.setattr(grid, "push_messages", lambda msgs: [m.object_id for m in pushed], raising=False)
    kw = polling.inflatable_utils.pull_objects.__kwdefaults__
    monkeypatch.setitem(kw, "initial_backoff", 0.05)
    monkeypatch.setitem(kw, "backoff_cap", 0.2)
    return grid


def test_a_reply_cut_on_the_link_costs_no_more_than_the_round_deadline(monkeypatch):
    """A reply whose message reached the SuperLink but whose body never did: Flower's own grid
    (``HttpGrid``) pulls the body with retries for up to 2 hours, until the SuperLink drops
    the upload (180 s). Every base station's exchange (``polling.exchange``) gives up at its
    deadline, with Flower's "objects unavailable" error for that reply."""
    from types import SimpleNamespace

    from flwr.app import Message, MessageType
    from flwr.common.serde import message_to_proto
    from flwr.proto.message_pb2 import ObjectTree
    from flwr.proto.runtime_pb2 import PullAppMessagesResponse

    from fedmap.flower import polling

    ins = _with_id(Message(RecordDict({"config": ConfigRecord({})}), dst_node_id=7, message_type=MessageType.TRAIN))
    reply = _with_id(Message(RecordDict({"config": ConfigRecord({"x": 1})}), reply_to=ins))
    tries = []

    class Client:  # the SuperLink: the reply's message is stored, its body never arrives
        def PullMessages(self, request):  # noqa: N802 (Flower's RPC names)
            return PullAppMessagesResponse(messages_list=[message_to_proto(reply)],
                                           message_object_trees=[ObjectTree(object_id=reply.object_id)])

        def PullObject(self, request):  # noqa: N802
            tries.append(request.object_id)
            if len(tries) > 50:  # Flower alone: retries far past the deadline (500 tries, 2 h)
                raise RuntimeError("still pulling a reply the deadline gave up on")
            return SimpleNamespace(object_found=True, object_available=False, object_content=b"")

    got = polling.exchange(_http_grid(monkeypatch, Client(), [ins]), [ins], 0.5)
    assert len(got) == 1 and got[0].has_error() and REPLY_LOST in got[0].error.reason
    assert got[0].metadata.reply_to_message_id == ins.object_id
    assert 2 <= len(tries) <= 12  # 0.5 s of retries 0.05-0.2 s apart
    assert polling.inflatable_utils.pull_objects.__kwdefaults__["max_time"] == 7200  # Flower's own, outside an exchange


def test_a_mission_bases_pull_of_a_cut_reply_gives_up_by_its_next_ask(monkeypatch):
    """A mission's base asks every OVERDUE s which process runs on a silent rover's node (a
    rover killed and started again is answered at once). A rover killed while uploading its
    report leaves a cut reply: a pull bounded only by the deadline held the exchange until
    the SuperLink dropped the upload (a loopback mission's order took 184.5 s). The pull now
    gives up after OVERDUE s, and the reply comes back as Flower's "objects unavailable"."""
    from types import SimpleNamespace

    from flwr.app import MessageType
    from flwr.common.serde import message_to_proto
    from flwr.proto.message_pb2 import ObjectTree
    from flwr.proto.runtime_pb2 import PullAppMessagesResponse

    from fedmap.flower import polling

    ins = _with_id(Message(RecordDict({"config": ConfigRecord({})}), dst_node_id=7, message_type=MessageType.TRAIN))
    reply = _with_id(Message(RecordDict({"config": ConfigRecord({"x": 1})}), reply_to=ins))

    class Client:  # the SuperLink: the reply's message is stored, its body never arrives
        def PullMessages(self, request):  # noqa: N802 (Flower's RPC names)
            return PullAppMessagesResponse(messages_list=[message_to_proto(reply)],
                                           message_object_trees=[ObjectTree(object_id=reply.object_id)])

        def PullObject(self, request):  # noqa: N802
            return SimpleNamespace(object_found=True, object_available=False, object_content=b"")

    monkeypatch.setattr(polling, "OVERDUE", 0.5)
    t0 = time.monotonic()
    got = polling.exchange(_http_grid(monkeypatch, Client(), [ins]), [ins], 30.0, overdue=lambda ids: set())
    assert time.monotonic() - t0 < 5.0
    assert len(got) == 1 and got[0].has_error() and REPLY_LOST in got[0].error.reason


def test_a_reply_that_arrives_whole_while_a_pull_waits_for_a_cut_one_is_not_lost(monkeypatch):
    """Two rovers: one reply is cut mid-upload (its message stored, its body never), the other
    arrives whole just after the first poll, which then waits for the cut body until the
    deadline. The exchange's last look takes the whole one (a loopback run that lost every
    reply of a round, the clean link's too, "0 rover(s) delivered", fits this mechanism)."""
    from types import SimpleNamespace

    from flwr.app import Message, MessageType
    from flwr.common.serde import message_to_proto
    from flwr.proto.runtime_pb2 import PullAppMessagesResponse
    from flwr.supercore.inflatable.inflatable_object import get_all_nested_objects, get_object_tree

    from fedmap.flower import polling

    ins = [_with_id(Message(RecordDict({"config": ConfigRecord({"k": k})}), dst_node_id=7 + k,
                            message_type=MessageType.TRAIN)) for k in range(2)]
    cut, whole = (_with_id(Message(RecordDict({"config": ConfigRecord({"x": k})}), reply_to=ins[k])) for k in range(2))
    bodies = {oid: obj.deflate() for oid, obj in get_all_nested_objects(whole).items()}
    polls = []

    class Client:  # the SuperLink: the cut reply is stored at once, the whole one from the second poll on
        def PullMessages(self, request):  # noqa: N802 (Flower's RPC names)
            polls.append(sorted(request.message_ids))
            ready = [m for m in (cut, whole)[:1 + (len(polls) > 1)]
                     if m.metadata.reply_to_message_id in request.message_ids]
            return PullAppMessagesResponse(messages_list=[message_to_proto(m) for m in ready],
                                           message_object_trees=[get_object_tree(m) for m in ready])

        def PullObject(self, request):  # noqa: N802
            body = bodies.get(request.object_id)
            return SimpleNamespace(object_found=True, object_available=body is not None, object_content=body or b"")

        def ConfirmMessageReceived(self, request):  # noqa: N802
            return None

    monkeypatch.setattr(polling, "LAST_LOOK", 0.3)
    got = {m.metadata.reply_to_message_id: m for m in polling.exchange(_http_grid(monkeypatch, Client(), ins), ins, 0.5)}
    assert got.keys() == {m.object_id for m in ins}, polls
    assert got[ins[0].object_id].has_error() and REPLY_LOST in got[ins[0].object_id].error.reason
    assert not got[ins[1].object_id].has_error()
    assert got[ins[1].object_id].content["config"]["x"] == 1
    assert len(polls) == 2 and polls[1] == [ins[1].object_id]  # the first poll ran to the deadline


def test_copies_sent_again_are_booked_to_their_rover(tmp_path, blob_map):
    """A copy sent again is counted in the round's record under its rover, and the
    SuperLink's error reply to a copy (its node gone) is put down to that rover."""
    from fedmap.flower.polling import copy_of

    run = {**RUN, "rounds": 1}
    maps, nodes = _team(tmp_path, blob_map)
    strategy = FedmapStrategy(RunSettings.from_run_config(run))
    msgs = strategy.configure_train(1, to_record(b""), ConfigRecord(), FakeGrid(nodes))
    by_node = {m.metadata.dst_node_id: m for m in msgs}
    copies = [copy_of(by_node[n]) for n in (101, 103, 103)]
    strategy.resent(copies)
    contexts = _contexts(nodes, run)
    replies = []
    for n in (100, 101, 102):
        m = by_node[n] if n != 101 else copies[0]
        m.metadata.__dict__["_message_id"] = m.object_id
        replies.append(client_app.train(m, contexts[n]))
    gone = copies[2]
    gone.metadata.__dict__["_message_id"] = gone.object_id
    replies.append(create_message_error_unavailable_res_message(gone.metadata, "node unavailable"))
    strategy.node_partition[103] = 3  # as after an earlier round
    strategy.aggregate_train(1, replies)
    rec = strategy.history[0]
    assert sorted(rec.aggregation_counts) == [0, 1, 2]
    assert rec.flower.resent == {1: 1, 3: 2}
    assert rec.flower.missing_why[3].startswith("Flower error") and not rec.flower.node_errors
    assert rec.to_dict()["resent"] == {1: 1, 3: 2}


class _LossyGrid:
    """A SuperLink behind a link that loses ``lost`` instructions to ``node`` (the rover's pull
    was cut: the SuperLink has it for delivered, the rover never saw it); every other message
    is answered ``delay`` s after it was pushed, once, and none to a node in ``busy`` before
    ``busy[node]`` s after the grid was made."""

    def __init__(self, node: int, lost: int, delay: float, busy: dict[int, float] | None = None,
                 cut: int = 0) -> None:
        self.node, self.lost, self.delay, self.busy, self.cut = node, lost, delay, busy or {}, cut
        self.t0 = time.monotonic()
        self.pushed: list[tuple[Message, float]] = []
        self.taken: set[str] = set()

    def push_messages(self, msgs):
        ids = []
        for m in msgs:
            m = _with_id(m)
            if m.metadata.dst_node_id == self.node and self.lost > 0:
                self.lost -= 1
                self.taken.add(m.object_id)  # never answered
            self.pushed.append((m, time.monotonic()))
            ids.append(m.object_id)
        return ids

    def pull_messages(self, ids):
        out, now = [], time.monotonic()
        for m, t in self.pushed:
            if m.object_id in ids and m.object_id not in self.taken and now - t >= self.delay \
                    and now - self.t0 >= self.busy.get(m.metadata.dst_node_id, 0.0):
                self.taken.add(m.object_id)
                if m.metadata.dst_node_id == self.node and self.cut > 0:  # its body never came: Flower's error
                    self.cut -= 1
                    out.append(_with_id(Message(Error(3, f"{REPLY_LOST}. The sender may not have completed "
                                                         "the upload."), reply_to=m)))
                    continue
                out.append(_with_id(Message(RecordDict({"config": ConfigRecord({"node": m.metadata.dst_node_id})}),
                                            reply_to=m)))
        return out


def _three():
    from flwr.app import MessageType

    return [Message(RecordDict({"config": ConfigRecord({"k": k})}), dst_node_id=7 + k, message_type=MessageType.TRAIN)
            for k in range(3)]


def test_an_instruction_lost_on_the_link_is_sent_again_not_waited_for(monkeypatch):
    """One of three rovers never receives its message (twice); the others answer after 0.2 s.
    With ``resend`` the exchange sends that message again once it has waited RESEND_FACTOR
    times as long as the slowest reply (at least RESEND_MIN), and the round ends with three
    replies, one per message, long before its deadline; without, it waits out the deadline
    with two."""
    from fedmap.flower import polling

    monkeypatch.setattr(polling, "RESEND_MIN", 0.5)
    copies: list[Message] = []
    t0 = time.monotonic()
    got = polling.exchange(_LossyGrid(9, lost=2, delay=0.2), _three(), 20.0, resend=True, on_resend=copies.extend)
    took = time.monotonic() - t0
    assert sorted(int(m.content["config"]["node"]) for m in got) == [7, 8, 9]
    assert [c.metadata.dst_node_id for c in copies] == [9, 9]  # lost twice: sent again twice
    assert dict(copies[0].content["config"]) == {"k": 2}
    assert took < 5.0  # 0.2 s, then 3 x 0.2 = 0.6 s, twice, then 0.2 s: not the 20 s deadline
    t0 = time.monotonic()
    got = polling.exchange(_LossyGrid(9, lost=1, delay=0.2), _three(), 1.5)
    assert sorted(int(m.content["config"]["node"]) for m in got) == [7, 8] and time.monotonic() - t0 >= 1.5


def test_a_message_never_answered_is_copied_at_most_resend_max_times(monkeypatch):
    """A node that is down (every instruction to it lost) gets RESEND_MAX copies of its
    message, no more, however long the deadline: it would run every one when it came back."""
    from fedmap.flower import polling

    monkeypatch.setattr(polling, "RESEND_MIN", 0.1)
    monkeypatch.setattr(polling, "RESEND_FACTOR", 0.5)
    copies: list[Message] = []
    got = polling.exchange(_LossyGrid(9, lost=1000, delay=0.05), _three(), 2.0, resend=True, on_resend=copies.extend)
    assert sorted(int(m.content["config"]["node"]) for m in got) == [7, 8]
    assert [c.metadata.dst_node_id for c in copies] == [9] * polling.RESEND_MAX


def test_replies_to_a_message_and_its_copies_are_taken_once(monkeypatch):
    """A rover that was only slow: its message is sent again (more than once), then the
    replies to the message and to every copy come back in one poll. The exchange returns
    one reply per message."""
    from fedmap.flower import polling

    monkeypatch.setattr(polling, "RESEND_MIN", 0.3)
    copies: list[Message] = []
    got = polling.exchange(_LossyGrid(0, lost=0, delay=0.1, busy={9: 1.2}), _three(), 10.0, resend=True,
                           on_resend=copies.extend)
    assert len(copies) >= 2 and {c.metadata.dst_node_id for c in copies} == {9}
    assert sorted(int(m.content["config"]["node"]) for m in got) == [7, 8, 9]


def test_a_reply_cut_on_its_way_up_has_its_message_sent_again(monkeypatch):
    """Rover 9's reply is cut mid-upload (Flower: "objects unavailable"): its message is sent
    again at once and the copy's reply taken, long before the deadline. When every reply it
    sends is cut, the round ends at its deadline with Flower's error as that rover's answer
    (recorded as a reply lost on the link), not with nothing."""
    from fedmap.flower import polling

    monkeypatch.setattr(polling, "RESEND_MIN", 0.5)
    copies: list[Message] = []
    t0 = time.monotonic()
    got = polling.exchange(_LossyGrid(9, lost=0, delay=0.2, cut=1), _three(), 20.0, resend=True,
                           on_resend=copies.extend)
    assert time.monotonic() - t0 < 3.0 and [c.metadata.dst_node_id for c in copies] == [9]
    assert not any(m.has_error() for m in got) and sorted(int(m.content["config"]["node"]) for m in got) == [7, 8, 9]
    got = polling.exchange(_LossyGrid(9, lost=0, delay=0.2, cut=1000), _three(), 2.0, resend=True)
    errors = [m for m in got if m.has_error()]
    assert len(got) == 3 and len(errors) == 1 and polling.REPLY_LOST in errors[0].error.reason
