import numpy as np
import pytest
import torch
from torch import nn

from fedmap.errors import FedmapError
from fedmap.nets.model import (
    CoordNet,
    NetConfig,
    build_model,
    count_parameters,
    get_weights,
    load_model,
    preset,
    render,
    save_model,
    set_weights,
)


def test_paper_preset_parameter_count():
    # Paper, Sec. IV-E: 65,792 per layer for layers 1-3, 512 per BatchNorm, 771 for the last layer.
    expected = 3 * (256 * 256 + 256) + 3 * (2 * 256) + (256 * 3 + 3)
    assert expected == 199_683
    assert count_parameters(CoordNet(preset("paper"))) == expected


def test_fourier_matrix_is_shared_and_never_sent():
    a, b = build_model(seed=1), build_model(seed=2)
    torch.testing.assert_close(a.features.B, b.features.B)  # same b_seed -> same B
    assert "features.B" not in a.state_dict()
    assert not any(p is a.features.B for p in a.parameters())
    other = CoordNet(NetConfig(b_seed=5))
    assert not torch.equal(a.features.B, other.features.B)
    # B ~ N(0, scale^2): the sample std of 256 draws is near 10
    assert 8.0 < float(a.features.B.std()) < 12.0


def test_encoding_formula():
    m = build_model()
    v = torch.tensor([[0.25, 0.75]])
    proj = 2 * np.pi * (v.numpy() @ m.features.B.numpy().T)
    expected = np.concatenate([np.cos(proj), np.sin(proj)], axis=1)
    np.testing.assert_allclose(m.features(v).numpy(), expected, atol=1e-4)


def _conv_twin(model: CoordNet) -> nn.Sequential:
    """The paper's layout: 1x1 Conv2d on (1, C, H, W), weights copied from the Linear net."""
    mods = []
    for layer in model.mlp:
        if isinstance(layer, nn.Linear):
            conv = nn.Conv2d(layer.in_features, layer.out_features, kernel_size=1)
            conv.weight.data = layer.weight.data[:, :, None, None].clone()
            conv.bias.data = layer.bias.data.clone()
            mods.append(conv)
        elif isinstance(layer, nn.BatchNorm1d):
            bn = nn.BatchNorm2d(layer.num_features, track_running_stats=False)
            bn.weight.data, bn.bias.data = layer.weight.data.clone(), layer.bias.data.clone()
            mods.append(bn)
        else:
            mods.append(layer)
    return nn.Sequential(*mods)


def test_linear_layout_equals_conv1x1_layout():
    torch.manual_seed(0)
    model = build_model(seed=3)
    h, w = 12, 10
    from fedmap.nets.model import grid_coords

    feats = model.features(grid_coords(h, w))  # (H*W, C)
    with torch.no_grad():
        for p in model.parameters():  # non-trivial BatchNorm affine parameters too
            p.add_(0.05 * torch.randn_like(p))
        lin = torch.sigmoid(model.mlp(feats)).reshape(h, w, 3)
        img = feats.reshape(h, w, -1).permute(2, 0, 1)[None]  # (1, C, H, W)
        conv = torch.sigmoid(_conv_twin(model)(img))[0].permute(1, 2, 0)
    torch.testing.assert_close(lin, conv, atol=1e-5, rtol=1e-4)


def test_chunked_render_equals_full_batch():
    model = build_model(NetConfig(mapping_size=16, hidden=32), seed=0)
    full = render(model, 20, 30, chunk=10_000)
    chunked = render(model, 20, 30, chunk=64)
    np.testing.assert_allclose(full, chunked, atol=2e-5)
    assert full.shape == (20, 30, 3) and full.min() >= 0 and full.max() <= 1


def test_seeded_init_is_reproducible():
    a, b, c = get_weights(build_model(seed=7)), get_weights(build_model(seed=7)), get_weights(build_model(seed=8))
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not all(np.array_equal(a[k], c[k]) for k in a)


def test_checkpoint_rebuilds_from_config_alone(tmp_path):
    cfg = NetConfig(mapping_size=8, hidden=16, layers=3, b_seed=4)
    m = build_model(cfg, seed=1)
    save_model(m, tmp_path / "m.safetensors")
    back = load_model(tmp_path / "m.safetensors")
    assert back.config == cfg
    np.testing.assert_array_equal(render(back, 8, 8), render(m, 8, 8))


def test_corrupt_checkpoint(tmp_path):
    p = tmp_path / "bad.safetensors"
    p.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not json at all")
    with pytest.raises(FedmapError, match="not a fedmap model"):
        load_model(p)
    with pytest.raises(FedmapError, match="no such model"):
        load_model(tmp_path / "missing.safetensors")


def test_set_weights_rejects_bad_updates():
    m = build_model()
    w = get_weights(m)
    k = next(iter(w))
    bad = dict(w)
    bad[k] = np.full_like(w[k], np.nan)
    with pytest.raises(FedmapError, match="NaN"):
        set_weights(m, bad)
    bad[k] = np.zeros((2, 2), np.float32)
    with pytest.raises(FedmapError, match="shape"):
        set_weights(m, bad)
    with pytest.raises(FedmapError, match="missing"):
        set_weights(m, {kk: v for kk, v in w.items() if kk != k})


def test_unknown_preset():
    with pytest.raises(FedmapError, match="unknown network"):
        preset("huge")


def test_batchnorm_keeps_no_running_statistics():
    # Federation contract: the state is exactly the trainable parameters (no running
    # mean/var/num_batches to average or to send), and BatchNorm always normalises with
    # the statistics of the batch it sees, in train and eval mode alike.
    m = build_model(seed=0)
    sd = m.state_dict()
    assert not [k for k in sd if "running" in k or "num_batches" in k]
    assert sum(v.numel() for v in sd.values()) == count_parameters(m) == 199_683
    x = torch.rand(64, 2)
    with torch.no_grad():
        m.train()
        a = m(x)
        m.eval()
        b = m(x)
    torch.testing.assert_close(a, b)
    # ... so a pixel's colour depends on the batch: rendering uses the full grid
    with torch.no_grad():
        part = m(x[:8])
    assert not torch.allclose(part, a[:8])


def test_grid_net_starts_as_the_empty_map_and_is_local():
    from fedmap.nets.model import grid_config, grid_coords

    cfg = grid_config(32, levels=3, features=2)
    assert cfg.grid_res == (8, 16, 32)
    m = build_model(cfg)
    # zero grids + the decoder's bias choice -> every pixel renders UNKNOWN grey
    np.testing.assert_allclose(render(m, 32, 32), 0.5, atol=1e-6)
    # the frozen decoder is not part of the state (never trained, never sent)
    assert set(m.state_dict()) == {"grids.0", "grids.1", "grids.2"}
    assert count_parameters(m) == 2 * (8 * 8 + 16 * 16 + 32 * 32)
    # locality: the loss on the left half's pixels has zero gradient on every grid cell
    # whose bilinear footprint lies in the right half (beyond one cell of the border)
    for p in m.parameters():
        p.data.normal_()
    v = grid_coords(32, 32).reshape(32, 32, 2)[:, :16].reshape(-1, 2)  # columns 0..15
    m(v).sum().backward()
    for G, r in zip(m.grids, cfg.grid_res):
        g = G.grad[0].abs().sum(0)  # (r, r): rows y, columns x
        cell_px = 32 / r
        last_touched = int(np.ceil(16 / cell_px))  # the cell containing the border + 1 for interpolation
        assert torch.all(g[:, last_touched + 1 :] == 0), f"level {r}: gradient leaks right"
        assert torch.all(g[:, : max(last_touched - 1, 1)].sum(0) > 0)  # and the left cells do learn


def _bilinear_border(grid: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A hand-written reading of ``grid`` (C, r, r) at ``v`` (N, 2) in (x, y) = (col, row)
    fractions: pixel centres at (i + 0.5) / r, clamped to the border (align_corners=False)."""
    c, r, _ = grid.shape
    x = np.clip(v[:, 0] * r - 0.5, 0, r - 1)
    y = np.clip(v[:, 1] * r - 0.5, 0, r - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, r - 1), np.minimum(y0 + 1, r - 1)
    fx, fy = x - x0, y - y0
    return ((1 - fy) * (1 - fx) * grid[:, y0, x0] + (1 - fy) * fx * grid[:, y0, x1]
            + fy * (1 - fx) * grid[:, y1, x0] + fy * fx * grid[:, y1, x1]).T


def test_grid_net_features_are_the_bilinear_reading_and_its_gradient_to_the_bit():
    """GridNet reads its F channels as F batch entries (so torch runs them on every thread).
    Its features match a hand-written bilinear reading, and its features and gradients
    equal torch's ``grid_sample`` of the grid as one entry of F channels, bit for bit."""
    from fedmap.nets.model import grid_config

    torch.set_num_threads(2)  # the parallel path (the autouse fixture restores the worker's threads)
    m = build_model(grid_config(64, levels=2, features=4))
    g = torch.Generator().manual_seed(5)
    for p in m.parameters():
        p.data.copy_(torch.randn(p.shape, generator=g))
    v = torch.rand(5000, 2, generator=g) * 1.2 - 0.1  # some points beyond the border
    upstream = torch.randn(5000, 8, generator=g)

    feats = m.features(v)
    feats.backward(upstream)
    got = [p.grad.clone() for p in m.grids]

    ref = []
    for G in m.grids:
        G.grad = None
        ref.append(nn.functional.grid_sample(G, (v * 2 - 1).view(1, -1, 1, 2), mode="bilinear",
                                             padding_mode="border", align_corners=False).view(G.shape[1], -1).T)
    ref_feats = torch.cat(ref, dim=1)
    ref_feats.backward(upstream)
    assert torch.equal(feats, ref_feats)
    for a, p in zip(got, m.grids):
        assert torch.equal(a, p.grad)
    hand = np.concatenate([_bilinear_border(G.detach()[0].double().numpy(), v.double().numpy()) for G in m.grids], axis=1)
    np.testing.assert_allclose(feats.detach().numpy(), hand, atol=1e-5)


def test_grid_net_decoder_in_place_is_the_plain_expression_to_the_bit():
    """GridNet.head applies its bias, ReLU and sigmoid in place; its values and its gradient
    on the features equal the written-out expression's, bit for bit."""
    from fedmap.nets.model import grid_config

    m = build_model(grid_config(32, levels=2, features=4))
    g = torch.Generator().manual_seed(7)
    feats = torch.randn(3000, 8, generator=g)
    upstream = torch.randn(3000, 3, generator=g)

    def plain(x):  # the same operations, out of place
        return torch.sigmoid(torch.clamp_min(x @ m.w1.T + m.c1, -m.r1) @ m.w2.T)

    def textbook(x):  # the decoder as written in its docstring, in float64
        w1, b1, w2 = (t.double() for t in (m.w1, m.b1, m.w2))
        return torch.sigmoid((torch.relu(x.double() @ w1.T + b1) - torch.relu(b1)) @ w2.T)

    outs, grads = [], []
    for fn in (m.head, plain, textbook):
        x = feats.clone().requires_grad_()
        out = fn(x)
        out.backward(upstream.to(out.dtype))
        outs.append(out.detach())
        grads.append(x.grad)
    assert torch.equal(outs[0], outs[1]) and torch.equal(grads[0], grads[1])
    np.testing.assert_allclose(outs[0].numpy(), outs[2].numpy(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(grads[0].numpy(), grads[2].numpy(), rtol=1e-4, atol=1e-6)
    assert outs[0].std() > 0 and grads[0].abs().sum() > 0  # not a constant output or a zero gradient


@pytest.mark.parametrize("rows", [1, 7, 300, 5000])
def test_a_fresh_grid_is_exactly_grey_and_a_grey_target_has_no_gradient(rows):
    """Zero features decode to exactly 0.5 (UNKNOWN's grey) at every batch size, whatever
    kernel the matrix product picks, so a cell whose target is grey has a gradient of exactly
    0: Adam (which divides by √v) would turn rounding noise of 1e-8 there into a full step
    (the streamed and one-pass fits of a map with unknown cells parted by 4.7 % on an Intel
    Xeon when the logits were a sum of terms that should cancel)."""
    from fedmap.nets.model import grid_config

    m = build_model(grid_config(32, levels=2, features=4))
    x = torch.zeros(rows, 8, requires_grad=True)
    out = m.head(x)
    assert torch.equal(out, torch.full((rows, 3), 0.5))
    ((out - 0.5) ** 2).sum().backward()
    assert not x.grad.any()
