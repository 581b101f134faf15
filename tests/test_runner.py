import numpy as np
import pytest

import fedmap.federation.runner as runner_mod
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.explore import explore
from fedmap.federation.aggregate import weighted_average
from fedmap.federation.codecs import Encoder, decode
from fedmap.federation.runner import FederationConfig, agent_seed, run_federation
from fedmap.maps.grid import GridMap
from fedmap.nets.model import build_model, get_weights, set_weights
from fedmap.nets.training import TrainConfig, fit


def _manual_round(net, init, maps, local, seed, r):
    """Reference: train each agent independently from ``init`` and FedAvg by known cells."""
    ws, counts = [], []
    for k, m in enumerate(maps):
        model = build_model(net)
        set_weights(model, init)
        fit(model, m, local, seed=agent_seed(seed, r, k))
        ws.append(get_weights(model))
        counts.append(m.n_known)
    return weighted_average(ws, counts)


def test_two_rounds_match_manual_fedavg(tiny_net, blob_map):
    maps = explore(blob_map, 4, "quadrants")
    local = TrainConfig(epochs=3, lr=1e-2)
    init = get_weights(build_model(tiny_net, seed=0))
    res = run_federation(init, tiny_net, maps, FederationConfig(rounds=2, local=local, seed=5))
    ref = _manual_round(tiny_net, init, maps, local, 5, 0)
    ref = _manual_round(tiny_net, ref, maps, local, 5, 1)
    for k in ref:
        np.testing.assert_allclose(res.weights[k], ref[k], atol=1e-6)
    assert [r.round for r in res.history] == [1, 2]


def test_byte_counts_are_serialised_sizes(tiny_net, blob_map):
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    res = run_federation(init, tiny_net, maps, FederationConfig(local=TrainConfig(epochs=1)))
    n = len(Encoder("fp32").encode(init))  # fp32 payload: same size both ways
    rec = res.history[0]
    assert rec.uplink_bytes == {k: n for k in range(4)}
    assert rec.downlink_bytes == {k: n for k in range(4)}
    b = res.total_bytes()
    assert (b.uplink, b.downlink, b.uplink_per_agent_round) == (4 * n, 4 * n, n)
    ledger = res.ledger()
    assert len(ledger) == 8 and {r["direction"] for r in ledger} == {"uplink", "downlink"}
    assert all(r["bytes"] == n and r["codec"] == "fp32" for r in ledger)


def test_codecs_go_through_real_bytes(tiny_net, blob_map):
    """The runner's global model equals a manual round with the same encode/decode steps."""
    maps = explore(blob_map, 4, "quadrants")
    local = TrainConfig(epochs=2, lr=1e-2)
    init = get_weights(build_model(tiny_net, seed=0))
    cfg = FederationConfig(local=local, seed=2, uplink="topk:0.05", downlink="fp16")
    res = run_federation(init, tiny_net, maps, cfg)
    ws = []
    for k, m in enumerate(maps):  # round 1 starts from the initial model every rover holds
        model = build_model(tiny_net)
        set_weights(model, init)
        fit(model, m, local, seed=agent_seed(2, 0, k))
        payload = Encoder("topk:0.05").encode(get_weights(model), reference=init)
        assert res.history[0].uplink_bytes[k] == len(payload)
        ws.append(decode(payload, reference=init))
    broadcast = Encoder("fp16").encode(weighted_average(ws, [m.n_known for m in maps]))
    assert res.history[0].downlink_bytes == {k: len(broadcast) for k in range(4)}
    ref = decode(broadcast)  # what the rovers render: the decoded fp16 broadcast
    for k in ref:
        np.testing.assert_allclose(res.weights[k], ref[k], atol=1e-6)
    # the sparse uplink is far smaller than the dense downlink
    assert res.history[0].uplink_bytes[0] < res.history[0].downlink_bytes[0] / 5


def test_malformed_payload_drops_that_agent(tiny_net, blob_map, monkeypatch):
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    real_encode = Encoder.encode
    calls = {"n": 0}

    def truncating(self, weights, reference=None):
        data = real_encode(self, weights, reference)
        calls["n"] += 1
        return data[:-3] if calls["n"] == 2 else data  # calls 1.. = agents 0.., then the broadcast

    monkeypatch.setattr(Encoder, "encode", truncating)
    res = run_federation(init, tiny_net, maps, FederationConfig(local=TrainConfig(epochs=1)))
    dropped = res.history[0].dropped
    assert list(dropped) == [1] and "malformed payload" in dropped[1]
    assert sorted(res.history[0].aggregation_counts) == [0, 2, 3]


def test_nan_update_is_dropped(tiny_net, blob_map, monkeypatch):
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    real_fit = runner_mod.fit

    def poisoned(model, grid, config, *, seed, on_step=None):
        out = real_fit(model, grid, config, seed=seed, on_step=on_step)
        if grid.meta.get("agent") == 2:
            for p in model.parameters():
                p.data.fill_(float("nan"))
        return out

    monkeypatch.setattr(runner_mod, "fit", poisoned)
    local = TrainConfig(epochs=2)
    res = run_federation(init, tiny_net, maps, FederationConfig(local=local, seed=1))
    rec = res.history[0]
    assert list(rec.dropped) == [2] and "NaN" in rec.dropped[2]
    assert 2 not in rec.uplink_bytes
    survivors = [m for m in maps if m.meta["agent"] != 2]
    ws = []
    for m in survivors:
        model = build_model(tiny_net)
        set_weights(model, init)
        real_fit(model, m, local, seed=agent_seed(1, 0, m.meta["agent"]))
        ws.append(get_weights(model))
    ref = weighted_average(ws, [m.n_known for m in survivors])
    for k in ref:
        np.testing.assert_allclose(res.weights[k], ref[k], atol=1e-6)


def test_mismatched_grids_and_bad_config(tiny_net, blob_map):
    other = GridMap(np.zeros((10, 10), np.uint8), 1.0, "small")
    init = get_weights(build_model(tiny_net))
    with pytest.raises(FedmapError, match="one global grid"):
        run_federation(init, tiny_net, [blob_map, other], FederationConfig(local=TrainConfig(epochs=1)))
    with pytest.raises(FedmapError, match="unknown aggregator"):
        FederationConfig(aggregator="fedprox")
    with pytest.raises(FedmapError, match="rounds"):
        FederationConfig(rounds=0)


def test_one_shot_cache_reuses_rover_training(tiny_net, blob_map):
    """One-round runs that differ only in the aggregator give the same result with the
    cache, and the second run trains nothing; a two-round run never uses it."""
    from dataclasses import replace

    from fedmap.explore import explore
    from fedmap.federation.runner import FederationConfig, run_federation
    from fedmap.nets.model import build_model, get_weights
    from fedmap.nets.training import TrainConfig

    maps = explore(blob_map, 4, "quadrants", seed=0)
    init = get_weights(build_model(tiny_net, seed=1))
    base = FederationConfig(rounds=1, aggregator="fedavg", local=TrainConfig(epochs=3, lr=1e-3), seed=2)
    cache: dict = {}
    steps: list[int] = []
    run_federation(init, tiny_net, maps, base, one_shot_cache=cache, on_step=lambda s, loss: steps.append(s))
    n_first = len(steps)
    for agg in ("fedadam", "fedyogi"):
        cfg = replace(base, aggregator=agg)
        cached = run_federation(init, tiny_net, maps, cfg, one_shot_cache=cache,
                                on_step=lambda s, loss: steps.append(s))
        fresh = run_federation(init, tiny_net, maps, cfg)
        for k in fresh.weights:
            np.testing.assert_array_equal(cached.weights[k], fresh.weights[k])
        assert cached.history[0].uplink_bytes == fresh.history[0].uplink_bytes
    assert n_first > 0 and len(steps) == n_first  # the cached runs trained nothing
    # a different seed, or more rounds, trains again
    run_federation(init, tiny_net, maps, replace(base, seed=3), one_shot_cache=cache,
                   on_step=lambda s, loss: steps.append(s))
    assert len(steps) == 2 * n_first
    run_federation(init, tiny_net, maps, replace(base, rounds=2), one_shot_cache=cache,
                   on_step=lambda s, loss: steps.append(s))
    assert len(steps) == 4 * n_first


def test_a_mistake_inside_fit_stops_the_run_at_once(tiny_net, blob_map, monkeypatch):
    """Only a RejectedUpdate drops a rover; any other FedmapError is a mistake and stops the
    run on the first rover that hits it (no rover after it trains)."""
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    real_fit = runner_mod.fit
    trained = []

    def mistaken(model, grid, config, *, seed, on_step=None):
        trained.append(grid.meta["agent"])
        if grid.meta["agent"] == 1:
            raise FedmapError("a configuration mistake")
        return real_fit(model, grid, config, seed=seed, on_step=on_step)

    monkeypatch.setattr(runner_mod, "fit", mistaken)
    with pytest.raises(FedmapError, match="^a configuration mistake$"):
        run_federation(init, tiny_net, maps, FederationConfig(local=TrainConfig(epochs=2), seed=1))
    assert trained == [0, 1]


def test_rejected_update_from_fit_drops_that_rover(tiny_net, blob_map, monkeypatch):
    """A RejectedUpdate raised in a rover's training (as fit's divergence check does, see
    test_training) drops that rover; the round aggregates the others."""
    maps = explore(blob_map, 4, "quadrants")
    init = get_weights(build_model(tiny_net, seed=0))
    real_fit = runner_mod.fit

    def diverging(model, grid, config, *, seed, on_step=None):
        if grid.meta["agent"] == 3:
            raise RejectedUpdate("training diverged on 'x' (loss is nan); lower the learning rate")
        return real_fit(model, grid, config, seed=seed, on_step=on_step)

    monkeypatch.setattr(runner_mod, "fit", diverging)
    res = run_federation(init, tiny_net, maps, FederationConfig(local=TrainConfig(epochs=2), seed=1))
    assert list(res.history[0].dropped) == [3] and "diverged" in res.history[0].dropped[3]


@pytest.mark.parametrize("uplink", ["fp32", "update-int8"])
def test_update_that_does_not_fit_the_model_is_dropped(tiny_net, blob_map, uplink):
    """A payload made for another model (other tensor shapes) is a rejected update at the
    base, for dense and update codecs alike; the others are averaged."""
    from fedmap.federation.aggregate import FedAvg
    from fedmap.federation.runner import base_step

    held = get_weights(build_model(tiny_net, seed=0))
    good = {k: v + 0.01 for k, v in held.items()}
    name = next(iter(held))
    wrong_ref = {**held, name: np.zeros((*np.shape(held[name])[:-1], np.shape(held[name])[-1] + 1), np.float32)}
    wrong = {**wrong_ref, name: wrong_ref[name] + 0.5}
    payloads = {0: Encoder(uplink).encode(good, reference=held), 1: Encoder(uplink).encode(wrong, reference=wrong_ref)}
    step = base_step(FedAvg(), held, payloads, {0: 10.0, 1: 10.0}, Encoder("fp32"))
    assert list(step.dropped) == [1] and step.dropped[1].startswith("malformed payload")
    assert list(step.counts) == [0]
    for k in held:  # FedAvg of the one rover left is its own (decoded) update
        np.testing.assert_allclose(step.held[k], decode(payloads[0], reference=held)[k], atol=1e-7)
