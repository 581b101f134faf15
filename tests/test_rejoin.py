"""Rejoin with any codec: model versions, keyframes, and the base's stale-reference check.

In-process here; the same scenario through the real Flower apps is in ``test_flower.py``.
"""

import numpy as np
import pytest

import fedmap.federation.runner as runner_mod
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.explore import explore
from fedmap.federation.aggregate import FedAvg, weighted_average
from fedmap.federation.codecs import Encoder, decode
from fedmap.federation.runner import (
    KEYFRAME,
    Broadcaster,
    FederationConfig,
    agent_seed,
    apply_downlink,
    base_step,
    model_version,
    run_federation,
)
from fedmap.nets.model import build_model, get_weights, set_weights
from fedmap.nets.training import TrainConfig, fit

LOCAL = TrainConfig(epochs=2, lr=1e-2)


def _fedavg(net, start, maps, agents, seed, r):
    """Reference by hand: train ``agents`` from ``start`` and FedAvg them by known cells."""
    ws = []
    for k in agents:
        model = build_model(net)
        set_weights(model, start)
        fit(model, maps[k], LOCAL, seed=agent_seed(seed, r, k))
        ws.append(get_weights(model))
    return weighted_average(ws, [maps[k].n_known for k in agents])


def test_model_version_is_a_content_hash():
    a = {"w": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.zeros(3, np.float32)}
    same = {"b": np.zeros(3, np.float32), "w": np.arange(6, dtype=np.float32).reshape(2, 3)}
    assert model_version(a) == model_version(same) and len(model_version(a)) == 16
    flipped = {**a, "w": a["w"].copy()}
    flipped["w"].view(np.uint32)[0, 0] ^= 1  # one bit
    assert model_version(flipped) != model_version(a)
    assert model_version({**a, "w": a["w"].reshape(3, 2)}) != model_version(a)  # shape counts


def test_broadcaster_sends_the_broadcast_or_a_keyframe():
    g0 = {"w": np.zeros(4, np.float32)}
    g1 = {"w": np.array([1, 2, 3, 4], np.float32)}
    g2 = {"w": np.array([2, 2, 2, 2], np.float32)}
    enc = Encoder("update-int8")
    bc = Broadcaster(g0)
    assert bc.for_rover(model_version(g0)).kind == "none"  # round 1: everyone holds the initial model
    p1 = enc.encode(g1, reference=g0)
    h1 = decode(p1, reference=g0)
    bc.advance(h1, p1)
    p2 = enc.encode(g2, reference=h1)
    h2 = decode(p2, reference=h1)
    bc.advance(h2, p2)
    up_to_date = bc.for_rover(model_version(h1))
    assert up_to_date.kind == "broadcast" and up_to_date.payload == p2
    for stale in (model_version(g0), None, "0123456789abcdef"):  # missed a round, unknown, restarted
        d = bc.for_rover(stale)
        assert d.kind == "keyframe"
        np.testing.assert_array_equal(apply_downlink(g0, d.kind, d.payload)["w"], h2["w"])  # exact, whatever it held
    # a rover holding g0 refuses the broadcast relative to h1 instead of decoding it wrongly
    with pytest.raises(RejectedUpdate, match="stale model"):
        apply_downlink(g0, "broadcast", p2, up_to_date.reference)
    wrong = decode(p2, reference=g0)  # what the old code did: a silently wrong model
    assert not np.allclose(wrong["w"], h2["w"])


def test_base_never_aggregates_an_update_made_from_another_model():
    held = {"w": np.ones(3, np.float32)}
    other = {"w": np.zeros(3, np.float32)}
    enc = Encoder("update-int8")
    payloads = {0: Encoder("update-int8").encode({"w": np.full(3, 2, np.float32)}, reference=held),
                1: enc.encode({"w": np.full(3, 2, np.float32)}, reference=other)}
    versions = {0: model_version(held), 1: model_version(other)}
    step = base_step(FedAvg(), held, payloads, {0: 1.0, 1: 1.0}, Encoder("fp32"), versions=versions)
    assert list(step.counts) == [0] and "stale reference" in step.dropped[1]
    np.testing.assert_allclose(step.held["w"], 2.0, atol=0.02)
    with pytest.raises(FedmapError, match="every agent's update was dropped"):
        base_step(FedAvg(), held, {1: payloads[1]}, {1: 1.0}, Encoder("fp32"), versions={1: versions[1]})


def test_missed_round_fp32_equals_fedavg_by_hand(tiny_net, blob_map):
    """Rover 1 misses round 2 of 3: round 2 averages 0, 2, 3; round 3 all four from that model."""
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    res = run_federation(init, tiny_net, maps, FederationConfig(rounds=3, local=LOCAL, seed=3), absent={2: [1]})
    g = _fedavg(tiny_net, init, maps, [0, 1, 2, 3], 3, 0)
    g = _fedavg(tiny_net, g, maps, [0, 2, 3], 3, 1)
    g = _fedavg(tiny_net, g, maps, [0, 1, 2, 3], 3, 2)
    for k in g:
        np.testing.assert_allclose(res.weights[k], g[k], atol=1e-5)
    assert res.history[1].missing == [1] and sorted(res.history[1].aggregation_counts) == [0, 2, 3]
    assert sorted(res.history[0].downlink_bytes) == [0, 2, 3]  # rover 1 never got round 1's broadcast


@pytest.mark.parametrize("event", ["absent", "restarted"])
def test_rejoin_with_an_update_downlink_trains_from_the_global_model(tiny_net, blob_map, monkeypatch, event):
    """update-int4+zstd downlink, rover 1 misses round 2 of 4 (or restarts before round 3): in
    round 3 it trains from exactly the base's model (a keyframe), and every update is used."""
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    started: dict[tuple[int, int], str] = {}
    real = runner_mod.rover_step

    def spy(model, local, held, encoder, config, *, round_idx, agent, on_step=None):
        started[(round_idx + 1, agent)] = model_version(held)
        return real(model, local, held, encoder, config, round_idx=round_idx, agent=agent, on_step=on_step)

    monkeypatch.setattr(runner_mod, "rover_step", spy)
    globals_: dict[int, str] = {}
    models: dict[int, dict] = {}
    cfg = FederationConfig(rounds=4, local=LOCAL, seed=3, uplink="update-int8", downlink="update-int4+zstd")
    kw = {"absent": {2: [1]}} if event == "absent" else {"restarted": {3: [1]}}
    res = run_federation(init, tiny_net, maps, cfg,
                         on_round=lambda rec, w: (globals_.update({rec.round: model_version(w)}),
                                                  models.update({rec.round: {k: v.copy() for k, v in w.items()}})),
                         **kw)
    for r in (2, 3, 4):
        for k in range(4):
            if (r, k) in started:
                assert started[(r, k)] == globals_[r - 1], (r, k)
    assert all(not rec.dropped for rec in res.history)
    assert res.history[1].keyframes == [1]  # round 2's model reached rover 1 as a keyframe
    key = len(Encoder(KEYFRAME).encode(models[res.history[1].round]))  # that round's model, whole
    assert res.history[1].downlink_bytes[1] == key > res.history[1].downlink_bytes[0]
    rows = [r for r in res.ledger() if r["round"] == 2 and r["direction"] == "downlink"]
    assert {r["agent"]: r["codec"] for r in rows}[1] == f"{KEYFRAME} keyframe"


def test_a_window_serves_the_chain_of_missed_broadcasts_and_rebases_old_updates():
    from fedmap.federation.aggregate import FedAvg
    from fedmap.federation.runner import base_step, pack_chain, unpack_chain
    rng = np.random.default_rng(0)
    models = [{"w": rng.normal(size=600).astype(np.float32), "b": rng.normal(size=40).astype(np.float32)}
              for _ in range(5)]
    enc = Encoder("update-int8")  # a chain of 3 int8 broadcasts is smaller than the fp32 keyframe
    bc = Broadcaster(models[0], window=3)
    held = [models[0]]  # what base and rovers hold after each broadcast
    for m in models[1:]:
        p = enc.encode(m, reference=held[-1])
        held.append(decode(p, reference=held[-1]))
        bc.advance(held[-1], p)
    assert sorted(bc.window) == sorted(model_version(m) for m in held[1:4])  # the last 3 older models
    d = bc.for_rover(model_version(held[1]))  # three broadcasts behind
    assert d.kind == "chain" and len(unpack_chain(d.payload)) == 3
    got = apply_downlink(held[1], d.kind, d.payload, d.reference)
    assert model_version(got) == bc.version  # exactly the base's model
    assert bc.for_rover(model_version(held[3])).kind == "broadcast"
    assert bc.for_rover(model_version(held[0])).kind == "keyframe"  # out of the window
    with pytest.raises(RejectedUpdate, match="stale model"):
        apply_downlink(held[2], d.kind, d.payload, d.reference)
    with pytest.raises(RejectedUpdate, match="malformed chain"):
        unpack_chain(pack_chain([b"ab", b"cde"])[:-1])
    # an update made from an older model in the window is applied as a delta: held + (u - its model)
    old = held[2]
    u = {"w": old["w"] + 0.5, "b": old["b"] - 1.0}
    payload = Encoder("update-fp32").encode(u, reference=old)
    step = base_step(FedAvg(), bc.held, {0: payload}, {0: 1.0}, Encoder("fp32"),
                     versions={0: model_version(old)}, window=bc.window)
    for n in ("w", "b"):
        np.testing.assert_allclose(step.held[n], bc.held[n] + (u[n] - old[n]), rtol=0, atol=1e-6)
    # without the window the same update is dropped as stale
    with pytest.raises(FedmapError, match="stale reference"):
        base_step(FedAvg(), bc.held, {0: payload}, {0: 1.0}, Encoder("fp32"), versions={0: model_version(old)})
