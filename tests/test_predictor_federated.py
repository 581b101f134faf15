"""The map predictor's federated fine-tuning across sites (fedmap.training.predictorfed and
its Flower apps, fedmap.flower.predictor_*)."""

import json
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.mission.settings import MissionConfig
from fedmap.nets.predictor import MapPredictor, PredictorConfig, shipped_predictor
from fedmap.training.predictorfed import (
    FineTuning,
    Site,
    alone,
    evaluate_predictor,
    fedavg_predictor,
    federate,
    fine_tuning_samples,
    load_site_samples,
    local_round,
    pooled,
    predictor_from_weights,
    predictor_weights,
    save_site_samples,
    scores,
    site_maps,
)

TINY = PredictorConfig(stem=4, width=8, dilations=(1, 2))
QUICK = FineTuning(steps=3, batch=2, crop=16, lr=1e-2, seed=0)


def _init() -> dict:
    import torch

    torch.manual_seed(0)
    return predictor_weights(MapPredictor(TINY))


def _sites(n: int = 3, size: int = 24) -> list[Site]:
    rng = np.random.default_rng(7)
    out = []
    for k in range(n):
        truth = rng.choice([FREE, IMPASSABLE], size=(2 + k, size, size), p=[0.7, 0.3]).astype(np.uint8)
        belief = np.where(rng.random(truth.shape) < 0.4, truth, UNKNOWN).astype(np.uint8)
        target = np.where(rng.random(truth.shape) < 0.9, truth, UNKNOWN).astype(np.uint8)  # the site's final map
        out.append(Site(f"s{k}", belief, target))
    return out


def _federate(sites, training=QUICK, rounds=2):
    return federate(_init(), sites, training, rounds, config=TINY)


def test_fedavg_of_predictor_weights_is_the_hand_computed_weighted_mean():
    rng = np.random.default_rng(0)
    shapes = {k: v.shape for k, v in _init().items()}
    updates = [{k: rng.normal(size=s).astype(np.float32) for k, s in shapes.items()} for _ in range(3)]
    counts = [80, 40, 120]
    got = fedavg_predictor(updates, counts)
    assert set(got) == set(shapes)
    for k in shapes:
        want = (80 * updates[0][k].astype(np.float64) + 40 * updates[1][k].astype(np.float64)
                + 120 * updates[2][k].astype(np.float64)) / 240
        assert got[k].dtype == np.float32
        np.testing.assert_allclose(got[k], want.astype(np.float32), rtol=0, atol=1e-6)
    # equal counts: the plain mean; one update: itself
    mean = fedavg_predictor(updates, [1, 1, 1])
    np.testing.assert_allclose(mean["head.bias"], np.mean([u["head.bias"] for u in updates], axis=0), atol=1e-6)
    one = fedavg_predictor(updates[:1], [5])
    assert all(np.array_equal(one[k], updates[0][k]) for k in shapes)
    with pytest.raises(FedmapError):
        fedavg_predictor(updates, [1, 1])


def test_local_round_starts_from_the_given_weights_and_is_deterministic():
    s = _sites(1)[0]
    init = _init()
    a = local_round(init, s.beliefs, s.targets, QUICK, round=1, site=0, config=TINY)
    b = local_round(init, s.beliefs, s.targets, QUICK, round=1, site=0, config=TINY)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert any(not np.array_equal(a[k], init[k]) for k in a if k != "base_rate")  # it trained
    assert a["base_rate"] == init["base_rate"]  # the base-rate correction stays the model's
    other_site = local_round(init, s.beliefs, s.targets, QUICK, round=1, site=1, config=TINY)
    assert any(not np.array_equal(a[k], other_site[k]) for k in a)  # the site index seeds the draws
    moved = {k: v + 0.01 for k, v in init.items()}
    c = local_round(moved, s.beliefs, s.targets, QUICK, round=1, site=0, config=TINY)
    assert any(not np.array_equal(a[k], c[k]) for k in a)  # other start, other result


def test_in_process_federation_is_deterministic_with_a_seed():
    sites = _sites()
    a, b = _federate(sites), _federate(sites)
    assert len(a) == 2
    for wa, wb in zip(a, b):
        assert all(np.array_equal(wa[k], wb[k]) for k in wa)
    c = _federate(sites, replace(QUICK, seed=1))
    assert any(not np.array_equal(a[-1][k], c[-1][k]) for k in a[-1])
    # round 1 is FedAvg of the sites' local rounds from the initial weights
    ups = [local_round(_init(), s.beliefs, s.targets, QUICK, round=1, site=k, config=TINY) for k, s in enumerate(sites)]
    r1 = fedavg_predictor(ups, [s.count for s in sites])
    assert all(np.array_equal(a[0][k], r1[k]) for k in r1)


def test_federate_pooled_and_alone_on_the_shipped_shape():
    """The library's runs on the shipped network's shape: one round each, deterministic."""
    sites = _sites(2, size=16)
    init = predictor_weights(MapPredictor())
    t = replace(QUICK, steps=1)
    f1, f2 = federate(init, sites, t, 1), federate(init, sites, t, 1)
    assert all(np.array_equal(f1[0][k], f2[0][k]) for k in init)
    p = pooled(init, sites, t, 1)
    a = alone(init, sites[0], t, 1)
    assert len(p) == len(a) == 1 and set(p[0]) == set(a[0]) == set(init)
    assert any(not np.array_equal(p[0][k], f1[0][k]) for k in init)


def test_scores_by_hand():
    p = np.array([0.9, 0.2, 0.6, 0.1])
    y = np.array([True, False, False, False])
    s = scores(p, y)
    assert s["accuracy"] == 0.75 and s["accuracy_all_free"] == 0.75
    assert s["iou_impassable"] == 0.5  # guessed {0, 2}, truly {0}
    assert s["brier"] == pytest.approx((0.01 + 0.04 + 0.36 + 0.01) / 4)
    # bins: 0.9 -> [0.9, 1] (freq 1), 0.2 -> [0.2, 0.3), 0.6 -> [0.6, 0.7), 0.1 -> [0.1, 0.2): all freq 0
    assert s["ece"] == pytest.approx((0.1 + 0.2 + 0.6 + 0.1) / 4)


def test_site_maps_train_on_the_final_map_and_score_on_cells_nobody_observed(tmp_path):
    truth = load_truth(TerrainSource(kind="builtin", terrain="mars", size=64), seed=0)
    cfg = replace(MissionConfig(), rovers=2, steps=20)
    m = site_maps(cfg, truth, name="mars", every=10)
    assert m.beliefs.shape == (4, 64, 64) and list(m.steps) == [10, 10, 20, 20]
    known = m.final != UNKNOWN
    assert np.array_equal(m.final[known], truth.classes[known])  # the base's map: only observed cells
    assert (~known).any()  # ... and not the truth
    for b, nobody in zip(m.beliefs, m.nobody):
        assert not (nobody & (b != UNKNOWN)).any()
    beliefs, targets = fine_tuning_samples(m)
    assert all(np.array_equal(t, m.final) for t in targets)
    path = save_site_samples(tmp_path / "site.npz", beliefs, targets)
    b2, t2 = load_site_samples(path)
    assert np.array_equal(b2, beliefs) and np.array_equal(t2, targets)
    s = evaluate_predictor(predictor_from_weights(_init(), TINY), m, at=None)
    assert s["cells"] == int(m.nobody.sum())
    with pytest.raises(FedmapError):
        load_site_samples(tmp_path / "missing.npz")


def test_predictor_app_config_matches_the_run_defaults():
    from fedmap.flower.predictor.task import PREDICTOR_RUN_DEFAULTS, PredictorRun

    app = Path(__file__).resolve().parents[1] / "src/fedmap/flower/predictor/app/pyproject.toml"
    config = tomllib.loads(app.read_text())["tool"]["flwr"]["app"]["config"]
    assert config == PREDICTOR_RUN_DEFAULTS
    run = PredictorRun.from_run_config(config)
    assert run.training == FineTuning(steps=40, batch=8, crop=96, lr=5e-4, seed=0)
    with pytest.raises(FedmapError):
        PredictorRun.from_run_config({"roundz": 3})


@pytest.mark.slow
@pytest.mark.xdist_group("loopback-c")  # a long loopback run: see addopts in pyproject.toml
def test_flower_sites_on_real_processes_give_the_in_process_weights(tmp_path):
    """A SuperLink and two SuperNodes (one per site, each with only its own samples file) on
    loopback, two rounds: the global weights of every round equal federate()'s, bit for bit."""
    pytest.importorskip("flwr")
    from fedmap.flower.predictor.deploy import deploy_predictor

    sites = _sites(2, size=32)
    files = [save_site_samples(tmp_path / f"{s.name}.npz", s.beliefs, s.targets) for s in sites]
    t = FineTuning(steps=2, batch=2, crop=16, lr=1e-2, seed=3)
    got = deploy_predictor(files, out=tmp_path / "out", rounds=2,
                           run_config={"local-steps": t.steps, "batch": t.batch, "crop": t.crop, "lr": t.lr,
                                       "seed": t.seed})
    want = federate(predictor_weights(shipped_predictor()), sites, t, 2)
    assert len(got) == 2
    for g, w in zip(got, want):
        assert set(g) == set(w)
        assert all(np.array_equal(g[k], w[k]) for k in w)
    for k in range(2):  # every message ran in a ClientApp forked from the site's warm server, which logs it
        assert "flwr-clientapp" in (tmp_path / "out.run" / f"site{k}.clientapps.log").read_text()


def test_federate_predictor_command_writes_json_figure_and_weights(tmp_path):
    from fedmap.cli import main
    from fedmap.nets.predictor import load_predictor

    files = []
    for name, terrain in (("a", "mars"), ("b", "moon"), ("c", "ice")):
        f = tmp_path / f"mission_{name}.toml"
        f.write_text(f'seed = 0\n[terrain]\nkind = "builtin"\nterrain = "{terrain}"\nsize = 64\n'
                     "[mission]\nrovers = 2\n")
        files.append(str(f))
    out = tmp_path / "out"
    code = main(["federate-predictor", files[0], f"bee={files[1]}", "--held-out", files[2], "--steps", "50",
                 "--rounds", "2", "--local-steps", "1", "--crop", "16", "--batch", "2", "--held-out-seeds", "1",
                 "-o", str(out)])
    assert code == 0
    result = json.loads((out / "federated.json").read_text())
    assert result["sites"] == ["a", "bee"] and result["held_out"] == "c" and result["rounds"] == 2
    assert set(result["per_round"]) == {"federated", "pooled", "alone:a", "alone:bee"}
    assert all(len(rows) == 2 for rows in result["per_round"].values())
    assert 0 <= result["final"]["federated"]["accuracy"] <= 1
    assert (out / "rounds.png").stat().st_size > 1000
    load_predictor(out / "federated.safetensors")
    assert main(["federate-predictor", files[0], "--held-out", files[0], "--steps", "50", "-o", str(out)]) == 2
