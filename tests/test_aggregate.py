import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.federation.aggregate import FedAdam, FedAvg, FedYogi, make_aggregator, weighted_average


def W(*vals):
    return {"w": np.array(vals, dtype=np.float32)}


def test_fedavg_weighted_by_counts():
    # hand: (1*[2, -2] + 3*[4, 0]) / 4 = [3.5, -0.5]
    out = FedAvg().aggregate(W(0, 0), [W(2, -2), W(4, 0)], [1, 3])
    np.testing.assert_allclose(out["w"], [3.5, -0.5])
    assert out["w"].dtype == np.float32


def test_fedavg_ignores_key_order_and_checks_shapes():
    a = {"a": np.ones(2, np.float32), "b": np.zeros(1, np.float32)}
    b = {"b": np.ones(1, np.float32), "a": np.zeros(2, np.float32)}
    out = weighted_average([a, b], [1, 1])
    np.testing.assert_allclose(out["a"], [0.5, 0.5])
    np.testing.assert_allclose(out["b"], [0.5])
    with pytest.raises(FedmapError, match="shape"):
        weighted_average([a, {"a": np.ones(3, np.float32), "b": np.ones(1, np.float32)}], [1, 1])
    with pytest.raises(FedmapError, match="positive sum"):
        weighted_average([a, b], [0, 0])
    with pytest.raises(FedmapError, match="no agent"):
        weighted_average([], [])


def test_fedadam_two_rounds_by_hand():
    eta, b1, b2, tau = 0.1, 0.9, 0.99, 0.05
    agg = FedAdam(eta=eta, beta1=b1, beta2=b2, tau=tau)
    g = W(1.0, -2.0)
    # round 1: avg = [3.5, -0.5], delta = [2.5, 1.5]
    # m = 0.1*delta = [0.25, 0.15]; v = 0.01*delta^2 = [0.0625, 0.0225]; sqrt v = [0.25, 0.15]
    # theta = [1 + 0.1*0.25/(0.25+0.05), -2 + 0.1*0.15/(0.15+0.05)] = [1.0833333, -1.925]
    g1 = agg.aggregate(g, [W(2, -2), W(4, 0)], [1, 3])
    np.testing.assert_allclose(g1["w"], [1 + 0.1 * 0.25 / 0.30, -2 + 0.1 * 0.15 / 0.20], rtol=1e-6)
    # round 2: both agents send [0, 0] -> delta = -g1 = [-1.0833333, 1.925]
    d = -np.array([1 + 0.025 / 0.30, -2 + 0.015 / 0.20])
    m = 0.9 * np.array([0.25, 0.15]) + 0.1 * d
    v = 0.99 * np.array([0.0625, 0.0225]) + 0.01 * d**2
    expected = -d + eta * m / (np.sqrt(v) + tau)
    g2 = agg.aggregate(g1, [W(0, 0), W(0, 0)], [1, 1])
    np.testing.assert_allclose(g2["w"], expected, rtol=1e-5)


def test_fedyogi_second_moment_by_hand():
    eta, b1, b2, tau = 0.1, 0.9, 0.99, 0.05
    agg = FedYogi(eta=eta, beta1=b1, beta2=b2, tau=tau)
    # round 1 from v = 0: v - 0.01*d^2*sign(0 - d^2) = +0.01*d^2, same as Adam
    g1 = agg.aggregate(W(1.0, -2.0), [W(2, -2), W(4, 0)], [1, 3])
    np.testing.assert_allclose(g1["w"], [1 + 0.1 * 0.25 / 0.30, -2 + 0.1 * 0.15 / 0.20], rtol=1e-6)
    # round 2: tiny delta -> d^2 < v so Yogi *decreases* v additively: v - 0.01*d^2
    g1v = g1["w"].astype(np.float64)
    target = g1v + np.array([1e-3, -2e-3])
    d = target.astype(np.float32).astype(np.float64) - g1v
    v_prev = np.array([0.0625, 0.0225])
    v = v_prev - 0.01 * d**2 * np.sign(v_prev - d**2)
    np.testing.assert_allclose(v, v_prev - 0.01 * d**2)  # the Yogi branch this test is about
    m = 0.9 * np.array([0.25, 0.15]) + 0.1 * d
    g2 = agg.aggregate(g1, [{"w": target.astype(np.float32)}], [5])
    np.testing.assert_allclose(g2["w"], g1v + eta * m / (np.sqrt(v) + tau), rtol=1e-6)
    np.testing.assert_allclose(agg.v["w"], v, rtol=1e-9)


def test_fedadam_one_shot_is_about_eta_sign():
    # documented property: with m, v = 0 the first step is ~ eta * sign(delta) when |delta| >> tau
    agg = FedAdam(eta=0.01, tau=1e-9)
    out = agg.aggregate(W(0, 0, 0), [W(5, -0.3, 1e-2)], [1])
    np.testing.assert_allclose(out["w"], [0.01, -0.01, 0.01], rtol=1e-4)


def test_make_aggregator():
    assert isinstance(make_aggregator("FedAvg"), FedAvg)
    a = make_aggregator("fedyogi", eta=0.5, tau=None)
    assert isinstance(a, FedYogi) and a.eta == 0.5 and a.tau == 1e-3
    with pytest.raises(FedmapError, match="unknown aggregator"):
        make_aggregator("fedsgd")
    with pytest.raises(FedmapError, match="betas"):
        FedAdam(beta1=1.0)


def test_coverage_average_by_hand():
    from fedmap.federation.aggregate import CoverageAvg, coverage_average

    g = W(1.0, 1.0, 1.0, 1.0)
    a = W(3.0, 1.0, 5.0, 1.0)  # touches entries 0 and 2
    b = W(1.0, 7.0, 9.0, 1.0)  # touches entries 1 and 2
    out = coverage_average(g, [a, b], [1, 3])
    # hand: entry 0 only a -> 3; entry 1 only b -> 7; entry 2 both -> (1*5 + 3*9)/4 = 8;
    # entry 3 nobody -> keeps the global 1 (plain FedAvg would give the same here, but
    # would give (3 + 3*1)/4 = 1.5 for entry 0 and (1 + 21)/4 = 5.5 for entry 1)
    np.testing.assert_allclose(out["w"], [3.0, 7.0, 8.0, 1.0])
    np.testing.assert_allclose(weighted_average([a, b], [1, 3])["w"], [1.5, 5.5, 8.0, 1.0])
    assert isinstance(make_aggregator("coverage"), CoverageAvg)
