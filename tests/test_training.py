import numpy as np
import pytest
import torch

from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.nets.model import build_model, get_weights, render
from fedmap.nets.training import TrainConfig, fit, map_targets, steps_per_epoch


def test_fit_lowers_loss_and_learns_the_map(tiny_net, blob_map):
    model = build_model(tiny_net, seed=0)
    losses = fit(model, blob_map, TrainConfig(epochs=150, lr=1e-2), seed=0)
    assert len(losses) == 150
    assert losses[-1] < 0.2 * losses[0]
    from fedmap.maps.grid import classes_from_rgb

    learned = classes_from_rgb(render(model, 24, 24))
    assert (learned == blob_map.classes).mean() > 0.95


def test_fit_is_seeded(tiny_net, blob_map):
    cfg = TrainConfig(epochs=5, lr=1e-2, batch=100)
    ws = []
    for seed in (1, 1, 2):
        m = build_model(tiny_net, seed=0)
        fit(m, blob_map, cfg, seed=seed)
        ws.append(get_weights(m))
    assert all(np.array_equal(ws[0][k], ws[1][k]) for k in ws[0])
    assert not all(np.array_equal(ws[0][k], ws[2][k]) for k in ws[0])


def test_sampled_epochs_cover_all_pixels(blob_map):
    cfg = TrainConfig(epochs=2, batch=100)
    assert steps_per_epoch(576, cfg) == 6  # 5 full batches + one of 76
    assert steps_per_epoch(501, cfg) == 5  # a last batch of 1 is dropped (BatchNorm)
    assert steps_per_epoch(576, TrainConfig()) == 1


def test_masked_targets_ignore_unknown(tiny_net, blob_map):
    c = blob_map.classes.copy()
    c[:, 12:] = UNKNOWN
    half = GridMap(c, 1.0, "half")
    coords, target, weight = map_targets(half, masked=True)
    assert weight.sum() == (c != UNKNOWN).sum()
    np.testing.assert_allclose(target.numpy().reshape(24, 24, 3)[0, 20], [0.5, 0.5, 0.5])
    # Masking changes training (unknown cells no longer pull towards grey).
    a, b = build_model(tiny_net, seed=0), build_model(tiny_net, seed=0)
    fit(a, half, TrainConfig(epochs=3, masked=True), seed=0)
    fit(b, half, TrainConfig(epochs=3, masked=False), seed=0)
    wa, wb = get_weights(a), get_weights(b)
    assert not all(np.allclose(wa[k], wb[k]) for k in wa)


def test_masked_loss_gradient_zero_from_unknown_cells(tiny_net):
    # Gradient of the masked loss w.r.t. the network output is exactly 0 on UNKNOWN cells.
    from fedmap.nets.training import map_loss

    pred = torch.rand(6, 3, requires_grad=True)
    target = torch.rand(6, 3)
    weight = torch.tensor([1.0, 0, 1, 0, 0, 1])
    map_loss(pred, target, weight).backward()
    assert torch.all(pred.grad[weight == 0] == 0) and torch.all(pred.grad[weight == 1] != 0)


def test_all_unknown_masked_is_a_rejected_update(tiny_net):
    blank = GridMap(np.full((8, 8), UNKNOWN, np.uint8), 1.0, "blank")
    with pytest.raises(RejectedUpdate, match="no known cell"):
        fit(build_model(tiny_net), blank, TrainConfig(epochs=1, masked=True))


def test_divergence_is_a_rejected_update(tiny_net, blob_map):
    """An absurd learning rate makes the loss NaN within 20 steps: the round can leave this
    rover out (RejectedUpdate), where a bad setting such as lr=0 is a plain FedmapError."""
    with pytest.raises(RejectedUpdate, match="training diverged on 'blobs'"):
        fit(build_model(tiny_net, seed=0), blob_map, TrainConfig(epochs=20, lr=1e20), seed=0)


def test_config_validation():
    with pytest.raises(FedmapError):
        TrainConfig(lr=0)
    with pytest.raises(FedmapError):
        TrainConfig(epochs=-1)
    with pytest.raises(FedmapError):
        TrainConfig(batch=1)


def test_training_on_a_selection_is_training_on_the_map_with_the_rest_unknown(tiny_net, blob_map):
    """``select`` keeps only those cells: with masked training that is the same as a map whose
    other cells are UNKNOWN (an independent way to say "train on these cells only"; without
    BatchNorm, whose batch statistics would see the unknown rows)."""
    from dataclasses import replace

    net = replace(tiny_net, batchnorm=False)
    rng = np.random.default_rng(0)
    select = rng.random(blob_map.shape) < 0.3
    cfg = TrainConfig(epochs=5, lr=1e-2, masked=True, precision="fp32")
    a, b = build_model(net, seed=0), build_model(net, seed=0)
    init = get_weights(a)
    la = fit(a, blob_map, cfg, seed=3, select=select)
    lb = fit(b, blob_map.with_classes(np.where(select, blob_map.classes, UNKNOWN)), cfg, seed=3)
    np.testing.assert_allclose(la, lb, rtol=1e-5)
    for k, v in get_weights(a).items():
        np.testing.assert_allclose(v, get_weights(b)[k], rtol=1e-5, atol=1e-6)
    assert any(not np.array_equal(v, init[k]) for k, v in get_weights(a).items())
    with pytest.raises(FedmapError, match="selection"):
        fit(a, blob_map, cfg, select=select[:-1])
    with pytest.raises(RejectedUpdate, match="no selected cell"):
        fit(a, blob_map, cfg, select=np.zeros(blob_map.shape, bool))


@pytest.mark.parametrize("masked", [True, False])
def test_a_streamed_full_batch_step_is_the_one_pass_step(monkeypatch, blob_map, masked):
    """Above STREAM_CELLS a full-batch step runs chunk by chunk, and above KNOWN_ONLY_ABOVE a
    masked map trains on its known cells only; the fitted weights and losses equal the
    one-pass, every-cell step's to float rounding."""
    from fedmap.nets import training
    from fedmap.nets.model import grid_config

    c = blob_map.classes.copy()
    c[:, :9] = UNKNOWN  # unknown cells: weight 0 when masked
    grid = blob_map.with_classes(c, "part known")
    cfg = TrainConfig(epochs=6, lr=0.05, masked=masked)
    penalty_model = {}

    def penalty():
        return 1e-3 * sum((p ** 2).sum() for p in penalty_model["m"].parameters())

    monkeypatch.setattr(training, "_adam_eps", lambda model, n: training.ADAM_EPS)  # the same Adam in both runs
    runs = []
    for cells, grid_chunk in ((1 << 20, 1 << 22), (50, 120)):  # one pass on every cell; known cells only, streamed
        # above 50 cells (a GridNet's threshold is DECODER_PASS_ABOVE), the grids read 120 at a time (576 cells in all)
        monkeypatch.setattr(training, "STREAM_CELLS", cells)
        monkeypatch.setattr(training, "DECODER_PASS_ABOVE", cells)
        monkeypatch.setattr(training, "GRID_CHUNK", grid_chunk)
        monkeypatch.setattr(training, "KNOWN_ONLY_ABOVE", cells)
        model = build_model(grid_config(24), seed=0)
        penalty_model["m"] = model
        losses = fit(model, grid, cfg, seed=0, penalty=penalty)
        runs.append((losses, get_weights(model)))
    (l1, w1), (l2, w2) = runs
    assert l1[-1] < l1[0]  # it learns
    np.testing.assert_allclose(l2, l1, rtol=1e-5, atol=1e-7)
    for k in w1:
        np.testing.assert_allclose(w2[k], w1[k], rtol=1e-4, atol=1e-6)


def test_the_compiled_decoder_pass_is_the_decoder_loss_and_its_gradient(monkeypatch):
    """The compiled pass of a streamed GridNet step against torch autograd in float64 on the
    written-out decoder and loss: the same loss and feature gradients to float rounding,
    nothing where a cell's weight is 0, and the same bits whether its parts run on one
    thread or two (parts of 700 cells, blocks of 256: every kind of remainder)."""
    from fedmap.nets import training
    from fedmap.nets.model import grid_config

    net = build_model(grid_config(16), seed=3)
    g = torch.Generator().manual_seed(0)
    n = 2_000
    feats = torch.randn(n, 8, generator=g) * 0.7
    y = torch.rand(n, 3, generator=g).round()
    wt = (torch.rand(n, generator=g) < 0.8).float()
    total = float(wt.sum()) + 5.0  # the whole batch's weight (a chunk's is less)

    leaf = feats.double().requires_grad_()
    w1, b1, w2 = (t.double() for t in (net.w1, net.b1, net.w2))
    pred = torch.sigmoid((torch.relu(leaf @ w1.T + b1) - torch.relu(b1)) @ w2.T)
    want = (((pred - y.double()) ** 2).mean(dim=1) * wt.double()).sum() / total
    want.backward()

    monkeypatch.setattr(training, "DECODER_PART", 700)
    results = []
    for threads in (1, 2):
        monkeypatch.setattr(torch, "get_num_threads", lambda threads=threads: threads)
        results.append(training.decoder_pass(net, feats, y, wt, total))
    (grad, loss), (grad2, loss2) = results
    assert torch.equal(grad, grad2) and loss == loss2
    assert loss == pytest.approx(want.item(), rel=1e-5)
    scale = leaf.grad.abs().max().item()
    np.testing.assert_allclose(grad.numpy(), leaf.grad.numpy(), rtol=1e-4, atol=1e-5 * scale)
    assert not grad[wt == 0].any()
    assert grad[wt > 0].abs().sum(dim=1).gt(0).float().mean() > 0.5  # and not nothing where it counts


def test_a_large_grid_fit_is_adam_on_a_loss_scaled_to_the_reference_size(monkeypatch, blob_map):
    """Above KNOWN_ONLY_CELLS a GridNet's Adam eps is scaled by KNOWN_ONLY_CELLS / n: the same
    steps as Adam with the default eps on the loss times n / KNOWN_ONLY_CELLS (a hand loop)."""
    from fedmap.nets import training
    from fedmap.nets.model import grid_config, grid_coords

    monkeypatch.setattr(training, "KNOWN_ONLY_CELLS", 100)
    cfg = TrainConfig(epochs=8, lr=0.05, masked=True)
    model = build_model(grid_config(24), seed=0)
    fit(model, blob_map, cfg, seed=0)
    ref = build_model(grid_config(24), seed=0)
    opt = torch.optim.Adam(ref.parameters(), lr=0.05)
    x = grid_coords(24, 24)
    y = torch.from_numpy(blob_map.to_rgb().reshape(-1, 3))
    for _ in range(8):
        opt.zero_grad()
        (((ref(x) - y) ** 2).mean(dim=1).mean() * (576 / 100)).backward()
        opt.step()
    got, want = get_weights(model), get_weights(ref)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=1e-4, atol=1e-6)
    # and it is not the unscaled step: with eps at its default the weights differ
    plain = build_model(grid_config(24), seed=0)
    monkeypatch.setattr(training, "KNOWN_ONLY_CELLS", 1 << 20)
    fit(plain, blob_map, cfg, seed=0)
    assert any(not np.allclose(get_weights(plain)[k], want[k], rtol=1e-4, atol=1e-6) for k in want)
