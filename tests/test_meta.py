"""Meta-initialisation: Reptile math, meta-training, collections, the ablation, shipped weights."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from fedmap.cli import main
from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import psnr
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.io import save_map
from fedmap.meta.ablation import AblationConfig, adapted_render, psnr_curve, run_ablation, steps_to_reach
from fedmap.meta.collections import BUILTIN_CATEGORIES, MapCollection, earth_like, load_collection, resize_classes
from fedmap.meta.reptile import MetaConfig, meta_train, read_checkpoint_info, reptile_update, validation_psnr
from fedmap.nets.init import SHIPPED_WEIGHTS, empty_prior, load_init_weights
from fedmap.nets.model import build_model, count_parameters, get_weights, load_model, preset, render


@pytest.fixture(autouse=True)
def one_thread():
    """These tests run many tiny full-grid steps: one thread avoids oversubscription."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# -- Reptile ---------------------------------------------------------------------------

def test_reptile_update_matches_hand_computation():
    theta = {"w": np.array([1.0, 2.0], np.float32), "b": np.array([[0.0]], np.float32)}
    phis = [{"w": np.array([3.0, 2.0], np.float32), "b": np.array([[1.0]], np.float32)},
            {"w": np.array([5.0, 0.0], np.float32), "b": np.array([[-3.0]], np.float32)}]
    # mean(phi) = w [4, 1], b [[-1]]; theta + 0.5 (mean - theta) = w [2.5, 1.5], b [[-0.5]]
    out = reptile_update(theta, phis, 0.5)
    np.testing.assert_array_equal(out["w"], [2.5, 1.5])
    np.testing.assert_array_equal(out["b"], [[-0.5]])
    np.testing.assert_array_equal(reptile_update(theta, phis, 1.0)["w"], [4.0, 1.0])  # eps 1: the mean
    np.testing.assert_array_equal(reptile_update(theta, phis, 0.0)["w"], theta["w"])  # eps 0: no move
    with pytest.raises(FedmapError):
        reptile_update(theta, [], 0.5)


def test_epsilon_schedule_is_linear():
    c = MetaConfig(iterations=5, eps_start=1.0, eps_end=0.0)
    assert [c.epsilon(i) for i in range(5)] == [1.0, 0.75, 0.5, 0.25, 0.0]
    with pytest.raises(FedmapError):
        MetaConfig(eps_start=1.5)


def _small_collection(n=6, size=24, seed=0):
    return earth_like(size=size, per_category=n, seed=seed)


def test_meta_training_lowers_two_step_validation_loss(tiny_net):
    coll = _small_collection()
    train, val = coll.split(holdout=1, seed=0)
    config = MetaConfig(iterations=20, inner_steps=3, inner_lr=1e-2, meta_batch=2, prior_steps=30, val_every=20,
                        val_lr=1e-3)
    res = meta_train(train, tiny_net, config, val_maps=val)
    start, end = res.history[0], res.history[-1]
    assert start["iteration"] == 0 and end["iteration"] == 20
    # theta_0 (the empty prior) scored independently of the history
    theta0 = get_weights(empty_prior(tiny_net, steps=30, seed=0))
    assert start["val_psnr"] == pytest.approx(validation_psnr(theta0, tiny_net, val, steps=2, lr=1e-3))
    # the meta update must move theta toward the maps: > 1 dB better after 2 steps
    assert end["val_psnr"] > start["val_psnr"] + 1.0


def test_meta_training_resume_gives_identical_bytes(tmp_path, tiny_net):
    coll = _small_collection(n=3, size=16)
    config = MetaConfig(iterations=4, inner_steps=2, meta_batch=2, prior_steps=5, val_every=2)
    val = coll.maps()[:2]
    straight = meta_train(coll, tiny_net, config, val_maps=val)

    ckpt = tmp_path / "ckpt.safetensors"

    def stop_after_two(it, info):
        if it == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        meta_train(coll, tiny_net, config, val_maps=val, checkpoint=ckpt, checkpoint_every=1, on_step=stop_after_two)
    assert read_checkpoint_info(ckpt)["meta_train"]["iteration"] == 2
    resumed = meta_train(coll, tiny_net, config, val_maps=val, checkpoint=ckpt, resume=True)
    for k in straight.weights:
        np.testing.assert_array_equal(straight.weights[k], resumed.weights[k])
    assert resumed.history == straight.history
    with pytest.raises(FedmapError, match="other settings"):
        meta_train(coll, tiny_net, MetaConfig(iterations=5, prior_steps=5), checkpoint=ckpt, resume=True)
    with pytest.raises(FedmapError, match="no checkpoint"):
        meta_train(coll, tiny_net, config, checkpoint=tmp_path / "none.safetensors", resume=True)


# -- collections -----------------------------------------------------------------------

def test_builtin_collection_is_seeded_and_non_trivial():
    a, b, c = earth_like(size=32, per_category=3, seed=0), earth_like(size=32, per_category=3, seed=0), \
        earth_like(size=32, per_category=3, seed=1)
    assert tuple(a.categories) == tuple(sorted(BUILTIN_CATEGORIES))
    for m1, m2, m3 in zip(a.maps(), b.maps(), c.maps()):
        np.testing.assert_array_equal(m1.classes, m2.classes)
        assert m1.shape == (32, 32)
        assert not np.array_equal(m1.classes, m3.classes)
        f = m1.fractions()
        assert 0.03 < f["impassable"] < 0.97 and f["unknown"] == 0.0
    with pytest.raises(FedmapError, match="unknown built-in category"):
        earth_like(categories=("lava",))


def test_collection_sample_and_split():
    coll = MapCollection("t", {"a": [GridMap(np.zeros((4, 4), np.uint8))] * 3,
                               "b": [GridMap(np.ones((4, 4), np.uint8))]})
    train, held = coll.split(holdout=1, seed=0)
    assert len(train.categories["a"]) == 2 and len(train.categories["b"]) == 1 and len(held) == 1
    rng = np.random.default_rng(0)
    picks = [coll.sample(rng).classes[0, 0] for _ in range(400)]
    assert 0.4 < np.mean(picks) < 0.6  # categories are sampled uniformly, not maps
    with pytest.raises(FedmapError):
        MapCollection("empty", {})


def test_resize_classes_nearest():
    c = np.arange(16, dtype=np.uint8).reshape(4, 4) % 3
    np.testing.assert_array_equal(resize_classes(c, 2), c[np.ix_([1, 3], [1, 3])])
    np.testing.assert_array_equal(resize_classes(c, 8), np.repeat(np.repeat(c, 2, 0), 2, 1))


def _map(value, size=16):
    c = np.full((size, size), FREE, np.uint8)
    c[: size // 2] = value
    return GridMap(c, 1.0, "m")


def test_maps_and_kitti_layouts(tmp_path):
    root = tmp_path / "maps"
    save_map(_map(IMPASSABLE), root / "Road" / "a.png")
    save_map(_map(UNKNOWN, 32), root / "Road" / "b.npy")
    save_map(_map(FREE), root / "City" / "c.png")
    coll = load_collection(root, layout="maps", size=16)
    assert sorted(coll.categories) == ["City", "Road"] and coll.n_maps == 3
    b = coll.categories["Road"][1]
    assert b.shape == (16, 16) and (b.classes[:8] == UNKNOWN).all() and (b.classes[8:] == FREE).all()

    kitti = tmp_path / "kitti"
    save_map(_map(IMPASSABLE), kitti / "Residential" / "2011_09_26_drive_0019" / "000000.png")
    save_map(_map(IMPASSABLE), kitti / "Residential" / "2011_09_26_drive_0020" / "000000.png")
    save_map(_map(FREE), kitti / "Road" / "2011_09_26_drive_0015" / "000003.png")
    k = load_collection(kitti, layout="kitti", size=16)
    assert {n: len(v) for n, v in k.categories.items()} == {"Residential": 2, "Road": 1}
    np.testing.assert_array_equal(k.categories["Residential"][0].classes, _map(IMPASSABLE).classes)


def test_domars_layout_marks_edges_impassable(tmp_path):
    img = np.full((64, 64), 40, np.uint8)
    img[16:48, 16:48] = 220  # a bright square: its outline is the only edge
    for split, cls in (("train", "crater"), ("test", "crater"), ("val", "ridge")):
        (tmp_path / split / cls).mkdir(parents=True)
        Image.fromarray(img).save(tmp_path / split / cls / "x.jpg", quality=95)
    coll = load_collection(tmp_path, layout="domars", size=32)
    assert {n: len(v) for n, v in coll.categories.items()} == {"crater": 2, "ridge": 1}
    m = coll.categories["crater"][0].classes
    assert 0.05 < (m == IMPASSABLE).mean() <= 0.2 + 1e-9
    edge = np.zeros((32, 32), bool)
    edge[6:10, 6:26] = edge[22:26, 6:26] = edge[6:26, 6:10] = edge[6:26, 22:26] = True
    assert edge[m == IMPASSABLE].all()  # every impassable cell lies on the square's outline
    with pytest.raises(FedmapError, match="DoMars16k"):
        load_collection(tmp_path / "train", layout="domars")


def test_dem_layout_tiles_and_thresholds(tmp_path):
    z = np.zeros((40, 70), np.float32)
    z[:, 35:] = np.arange(35, dtype=np.float32) * 1.0  # 45 deg ramp on the right half, flat left
    (tmp_path / "hills").mkdir()
    np.save(tmp_path / "hills" / "a.npy", z)
    np.save(tmp_path / "flat.npy", np.zeros((20, 20), np.float32))
    coll = load_collection(tmp_path, layout="dem", size=20)
    assert {n: len(v) for n, v in coll.categories.items()} == {"hills": 2 * 3, "flat": 1}
    left, right = coll.categories["hills"][0], coll.categories["hills"][2]
    assert (left.classes == FREE).all()
    assert (right.classes[:, 2:-2] == IMPASSABLE).all()  # 45 deg > 15 deg
    from fedmap.maps.traversability import TraversabilityThresholds

    lax = load_collection(tmp_path, layout="dem", size=20,
                          thresholds=TraversabilityThresholds(max_slope_deg=60, rover_scale_max_px=0.5))
    assert (lax.categories["hills"][2].classes == FREE).all()


@pytest.mark.parametrize("kwargs, match", [({"layout": "csv"}, "unknown collection layout"),
                                           ({"layout": "maps"}, "no maps found")])
def test_collection_errors(tmp_path, kwargs, match):
    with pytest.raises(FedmapError, match=match):
        load_collection(tmp_path, **kwargs)
    with pytest.raises(FedmapError, match="does not exist"):
        load_collection(tmp_path / "missing")


# -- ablation --------------------------------------------------------------------------

def test_psnr_curve_matches_rendered_psnr(tiny_net, blob_map):
    """The curve is read off the training loss; an independent path (fp32 render + scikit-image
    PSNR) gives the same numbers in fp32, and within bf16 rounding of the forward pass in bf16."""
    w = get_weights(build_model(tiny_net, seed=3))
    truth = blob_map.to_rgb()
    for precision, tol in (("fp32", 1e-3), ("bf16", 0.1)):
        curve = psnr_curve(w, tiny_net, blob_map, steps=3, lr=1e-3, precision=precision)
        assert len(curve) == 4
        for s in (0, 3):
            rendered = adapted_render(w, tiny_net, blob_map, steps=s, lr=1e-3, precision=precision)
            assert curve[s] == pytest.approx(psnr(truth, rendered), abs=tol)


def test_steps_to_reach():
    assert steps_to_reach([5.0, 6.0, 7.0], 6.0) == 1
    assert steps_to_reach([5.0, 6.0, 7.0], 4.0) == 0
    assert steps_to_reach([5.0, 6.0, 7.0], 7.5) is None


def test_run_ablation_table(tiny_net):
    maps = earth_like(size=16, per_category=1, seed=2).maps()[:2]
    coll = earth_like(size=16, per_category=4, seed=5)
    meta = meta_train(coll, tiny_net, MetaConfig(iterations=10, inner_steps=2, meta_batch=2, prior_steps=10)).weights
    inits = {"random": get_weights(build_model(tiny_net, seed=1)),
             "empty": get_weights(empty_prior(tiny_net, steps=10, seed=1)), "meta": meta}
    r = run_ablation(maps, inits, tiny_net, AblationConfig(n_steps=2, lr=1e-3, max_steps=6))
    assert r["n_maps"] == 2 and set(r["table"]) == {"random", "empty", "meta"}
    for reach in r["per_map"]["meta"]["steps_to_meta"]:
        assert reach is not None and reach <= 2  # meta reaches its own 2-step PSNR by step 2
    for name in inits:
        assert len(r["curves"][name]) == 7
        s = r["table"][name]["steps_to_meta"]
        assert s["capped"] == sum(x is None for x in r["per_map"][name]["steps_to_meta"])
    with pytest.raises(FedmapError, match="meta"):
        run_ablation(maps, {"random": inits["random"]}, tiny_net, AblationConfig())


# -- shipped weights -------------------------------------------------------------------

def test_shipped_weights_rebuild_from_stored_config_alone():
    assert SHIPPED_WEIGHTS.is_file()
    model = load_model(SHIPPED_WEIGHTS)
    assert model.config == preset("paper")
    assert count_parameters(model) == 199_683
    info = read_checkpoint_info(SHIPPED_WEIGHTS)
    assert info["command"].startswith("fedmap meta-train")
    assert info["meta_train"]["iteration"] == info["meta_train"]["config"]["iterations"]
    hist = info["meta_train"]["history"]
    assert hist[-1]["val_psnr"] > hist[0]["val_psnr"]  # meta-training improved on theta_0
    rgb = render(model, 48, 48)
    assert np.isfinite(rgb).all()
    w = load_init_weights(preset("paper"))
    for k, v in get_weights(model).items():
        np.testing.assert_array_equal(w[k], v)


def test_init_weights_errors(tmp_path, tiny_net):
    with pytest.raises(FedmapError, match="built with"):
        load_init_weights(tiny_net)  # the shipped file holds the paper network
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a model")
    with pytest.raises(FedmapError, match="not a fedmap model file"):
        load_init_weights(preset("paper"), bad)
    with pytest.raises(FedmapError, match="no such model file"):
        load_init_weights(preset("paper"), tmp_path / "missing.safetensors")


def test_pipeline_meta_init_config_errors():
    from fedmap.nets.init import ModelConfig

    with pytest.raises(FedmapError, match="grid network"):
        ModelConfig(init="meta", net="grid")
    with pytest.raises(FedmapError, match="only used with init 'meta'"):
        ModelConfig(init="random", init_weights="x.safetensors")


# -- CLI -------------------------------------------------------------------------------

@pytest.mark.slow
def test_cli_meta_train_then_ablate(tmp_path, capsys, monkeypatch):
    w = tmp_path / "w.safetensors"
    rc = main(["meta-train", "--net", "small", "--size", "16", "--per-category", "3", "--iterations", "2",
               "--inner-steps", "1", "--meta-batch", "1", "--prior-steps", "2", "--holdout", "1", "--threads", "1",
               "-o", str(w)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert load_model(w).config == preset("small")
    assert read_checkpoint_info(w)["command"].startswith("fedmap meta-train")
    # the ablation runs the paper network: a small-network file is refused in one line, before
    # the empty-map prior's fit (150 steps of the paper network by default) is started
    import fedmap.meta.ablation as ablation

    fitted: list[int] = []
    with monkeypatch.context() as m:
        m.setattr(ablation, "empty_prior", lambda *a, **k: fitted.append(1))
        rc = main(["ablate-init", "--size", "16", "--maps", "1", "--init-weights", str(w), "-o", str(tmp_path / "a")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error:") and "built with" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "a").exists() and fitted == []

    rc = main(["ablate-init", "--size", "16", "--maps", "2", "--max-steps", "4", "--prior-steps", "2",
               "--threads", "1", "-o", str(tmp_path / "a")])
    out = capsys.readouterr()
    assert rc == 0, out.err
    res = json.loads((tmp_path / "a" / "ablation.json").read_text())
    assert res["n_maps"] == 2 and res["init_weights"] == "shipped"
    for png in ("fig3.png", "psnr_curve.png"):
        with Image.open(tmp_path / "a" / png) as im:
            assert im.size[0] > 100


def test_cli_meta_errors(tmp_path, capsys):
    rc = main(["meta-train", "--collection", str(tmp_path), "--layout", "zip", "-o", str(tmp_path / "w")])
    err = capsys.readouterr().err
    assert rc == 2 and "unknown collection layout" in err
    rc = main(["meta-train", "--net", "grid", "-o", str(tmp_path / "w")])
    assert rc == 2 and "Fourier" in capsys.readouterr().err
