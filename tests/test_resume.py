"""Resume after a base-station crash: per-round checkpoints, atomic and verified, bounded.

The run itself goes through the real ClientApp and Strategy on in-memory messages (the fake
grid of ``test_flower.py``); the crash is the strategy object thrown away after round 2.
"""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("flwr")

from tests.test_flower import RUN, FakeGrid, _contexts, _round, _team, task_identity  # noqa: E402, F401

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.federation.codecs import Encoder  # noqa: E402
from fedmap.federation.runner import FlowerRound, RoundRecord  # noqa: E402
from fedmap.flower.checkpoint import (  # noqa: E402
    BaseState,
    checkpoints,
    latest_checkpoint,
    prune,
    read_checkpoint,
    resume_config,
    run_dir,
    write_checkpoint,
)
from fedmap.flower.records import to_record  # noqa: E402
from fedmap.flower.settings import RunSettings  # noqa: E402
from fedmap.flower.snapshot.server import FedmapStrategy  # noqa: E402


def _run(strategy, nodes, run, rounds, arrays=None):
    grid, contexts = FakeGrid(nodes), _contexts(nodes, run)
    arrays = arrays if arrays is not None else to_record(b"")
    for r in rounds:
        arrays, _ = _round(strategy, grid, contexts, arrays, r)
        strategy.checkpoint(r, arrays)
    return arrays


@pytest.mark.parametrize("aggregator", ["fedyogi"])  # FedAdam shares the moment code (aggregate._FedOpt)
def test_resumed_run_equals_the_uninterrupted_one(tmp_path, blob_map, aggregator):
    """FedAdam/FedYogi moments and the update-int8 downlink's residual carry over: 2 rounds,
    crash, 2 resumed rounds (new SuperNodes: new node ids, no rover state) = 4 rounds."""
    run = {**RUN, "rounds": 4, "aggregator": aggregator, "eta": 0.05, "uplink": "fp16", "downlink": "update-int8"}
    _, nodes = _team(tmp_path, blob_map)
    whole = FedmapStrategy(RunSettings.from_run_config({**run, "out": str(tmp_path / "whole")}))
    _run(whole, nodes, run, (1, 2, 3, 4))

    crashed_cfg = {**run, "out": str(tmp_path / "crashed")}
    crashed = FedmapStrategy(RunSettings.from_run_config(crashed_cfg), run_config=crashed_cfg)
    _run(crashed, nodes, run, (1, 2))
    del crashed  # the base station dies after round 2's checkpoint
    cfg = resume_config(tmp_path / "crashed")
    assert cfg["resume"].endswith("checkpoint_round0002") and cfg["rounds"] == 4
    resumed = FedmapStrategy(RunSettings.from_run_config(cfg), run_config=cfg)
    assert resumed.offset == 2
    new_nodes = {n + 100: c for n, c in nodes.items()}  # the rovers reconnect as new nodes
    _run(resumed, new_nodes, run, (1, 2))  # Flower counts this run's rounds from 1 again

    for k in whole.held:
        np.testing.assert_array_equal(resumed.held[k], whole.held[k])
    for got, want in zip(resumed.history, whole.history):
        assert got.aggregation_counts == want.aggregation_counts and got.uplink_bytes == want.uplink_bytes
        assert got.final_loss == pytest.approx(want.final_loss)
    assert [r.round for r in resumed.history] == [1, 2, 3, 4]
    assert resumed.history[1].keyframes == [0, 1, 2, 3]  # new rovers: round 2's model as keyframes

    # the test can fail: a resume that forgot the server optimiser's moments ends elsewhere
    forgetful = FedmapStrategy(RunSettings.from_run_config(cfg), run_config=cfg)
    forgetful.aggregator = RunSettings.from_run_config(cfg).federation.make_aggregator()
    _run(forgetful, new_nodes, run, (1, 2))
    assert any(not np.array_equal(forgetful.held[k], whole.held[k]) for k in whole.held)


def _state(r, n=1000):
    rng = np.random.default_rng(r)
    held = {"a": rng.standard_normal((n, 8)).astype(np.float32), "b": rng.standard_normal(8).astype(np.float32)}
    enc = Encoder("update-int8")
    enc.encode({k: v + 1 for k, v in held.items()}, reference=held)
    flower = FlowerRound(missing_why={1: "no reply before the round's deadline"}, node_errors={"77": "Flower error"},
                         uplink_bytes={0: 235}, downlink_bytes={0: 135}, final_broadcast_received_by=[0])
    rec = RoundRecord(round=r, final_loss={0: 0.5}, aggregation_counts={0: 1.0}, dropped={2: "stale model"}, missing=[1],
                      uplink_codec="fp32", downlink_codec="update-int8", uplink_bytes={0: 100}, downlink_bytes={0: 0},
                      keyframes=[0], seconds=1.5, flower=flower)
    return BaseState(r, held, {"m": {k: v.astype(np.float64) for k, v in held.items()}}, enc.state(), [rec], (24, 24),
                     {"rounds": 9})


def test_checkpoint_round_trip_and_bounded_count(tmp_path):
    for r in range(1, 6):
        write_checkpoint(tmp_path, _state(r))
        prune(tmp_path, 2)
    assert [r for r, _ in checkpoints(tmp_path)] == [4, 5]
    path, got = latest_checkpoint(tmp_path)
    want = _state(5)
    assert path.name == "checkpoint_round0005" and got.round == 5 and got.shape == (24, 24)
    assert list(got.held) == list(want.held)  # payload order survives
    for k in want.held:
        np.testing.assert_array_equal(got.held[k], want.held[k])
        np.testing.assert_array_equal(got.moments["m"][k], want.moments["m"][k])
    for k in want.down_encoder:
        np.testing.assert_array_equal(got.down_encoder[k], want.down_encoder[k])
    assert got.history == want.history  # typed records again, partition ids ints (Flower node ids stay strings)
    enc, enc2 = Encoder("update-int8"), Encoder("update-int8")
    enc.restore(got.down_encoder)
    enc2.restore(want.down_encoder)
    x = {k: v * 2 for k, v in want.held.items()}
    assert enc.encode(x, reference=want.held) == enc2.encode(x, reference=want.held)


#: One round of a checkpoint's state.json as the base station wrote it before round records were typed.
OLD_ROUND = {
    "round": 2, "final_loss": {"0": 0.0369, "2": 0.0393}, "weights": {"0": 1024.0, "2": 1024.0}, "dropped": {},
    "missing": [1], "codecs": {"uplink": "update-int8", "downlink": "update-int4+zstd"},
    "uplink_bytes": {"0": 52455, "2": 52455}, "downlink_bytes": {"0": 24073, "1": 202940}, "keyframes": [1],
    "seconds": 0.137, "missing_why": {"1": "no reply before the round's deadline"}, "node_errors": {"123": "Flower error"},
    "flower_uplink_bytes": {"0": 52590, "2": 52590}, "flower_downlink_bytes": {"0": 24208, "1": 203075},
}


def test_a_checkpoint_written_before_typed_records_still_loads(tmp_path):
    """An older checkpoint's history reads back as :class:`RoundRecord` and writes the same
    JSON again, but for the key ``weights``, now ``aggregation_counts``."""
    import json

    path = write_checkpoint(tmp_path, _state(2))
    meta = json.loads((path / "state.json").read_text())
    meta["history"] = [OLD_ROUND]
    (path / "state.json").write_text(json.dumps(meta))
    rec = read_checkpoint(path).history[0]
    assert rec.aggregation_counts == {0: 1024.0, 2: 1024.0} and rec.downlink_bytes == {0: 24073, 1: 202940}
    assert rec.uplink_codec == "update-int8" and rec.keyframes == [1] and rec.missing == [1]
    assert rec.flower is not None and rec.flower.missing_why == {1: "no reply before the round's deadline"}
    assert rec.flower.node_errors == {"123": "Flower error"} and rec.flower.final_broadcast_received_by is None
    # written back with its one renamed key: the aggregation counts were under "weights"
    new = {("aggregation_counts" if k == "weights" else k): v for k, v in OLD_ROUND.items()}
    assert json.loads(json.dumps(rec.to_dict())) == new


def test_a_damaged_checkpoint_is_skipped(tmp_path):
    write_checkpoint(tmp_path, _state(1))
    p2 = write_checkpoint(tmp_path, _state(2))
    blob = bytearray((p2 / "arrays.npz").read_bytes())
    blob[len(blob) // 2] ^= 0x10  # one flipped bit
    (p2 / "arrays.npz").write_bytes(bytes(blob))
    with pytest.raises(FedmapError, match="damaged"):
        read_checkpoint(p2)
    assert latest_checkpoint(tmp_path)[1].round == 1


WRITER = """
import sys, time
import numpy as np
from pathlib import Path
import fedmap.flower.checkpoint as ck
from tests.test_resume import _state

out = Path(sys.argv[1])
ck.write_checkpoint(out, _state(1))
def stalled_write(self, data):  # half of the file reaches the disk, then the parent kills us
    with open(self, "wb") as f:
        f.write(data[: len(data) // 2])
        f.flush()
        print("writing", flush=True)
        time.sleep(60)
Path.write_bytes = stalled_write
ck.write_checkpoint(out, _state(2, n=200_000))
"""


def test_a_writer_killed_mid_write_leaves_the_last_complete_checkpoint(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])}
    with subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                          env=env) as w:
        assert w.stdout is not None
        line = w.stdout.readline()  # bounded: the child prints this or exits
        w.send_signal(signal.SIGKILL)
        w.wait(timeout=30)
    assert line.strip() == "writing"
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".checkpoint_round0002")]
    assert leftovers  # the temporary folder of round 2 was being written ...
    assert [r for r, _ in checkpoints(tmp_path)] == [1]  # ... and is never listed
    assert latest_checkpoint(tmp_path)[1].round == 1
    prune(tmp_path, 3)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".checkpoint_round")]


def test_nothing_to_resume_is_one_line(tmp_path):
    with pytest.raises(FedmapError, match="^nothing to resume: no complete checkpoint in"):
        resume_config(tmp_path / "out")
    run_dir(tmp_path / "out").mkdir()
    with pytest.raises(FedmapError, match="^nothing to resume"):
        resume_config(tmp_path / "out")
