"""A neural height field: the paper's Fourier-feature network with one output, heights in
metres, coded as a payload of int8 weights.

:func:`fit_heights` fits :class:`HeightNet` (Fourier features of the cell centre -> MLP ->
one value) to an elevation layer's known cells, normalised to zero mean and unit std, with
Adam on the mean squared error, full batch, seeded. Then it fine-tunes with the weights
fake-quantised to int8 (quantisation-aware: the straight-through estimator), so the
payload decodes to what was trained. :func:`encode_heightnet` writes the payload: a small
JSON header (the network's shape, ``B``'s seed, the normalisation) and every tensor as int8
with one float32 scale, zstd. :func:`decode_heightnet` rebuilds the network from it and
renders the heights. ``B`` is rebuilt from its seed on both ends and never sent.
"""

from __future__ import annotations

import json
import struct
from dataclasses import asdict, dataclass

import numpy as np
import torch
import zstandard
from torch import nn

from fedmap._util import inflate_zstd
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import MAX_WIRE_SIDE
from fedmap.nets.model import FourierFeatures

_LEN = struct.Struct("<I")


#: The widest and deepest network a height-field payload may claim (its map: :data:`MAX_WIRE_SIDE`).
_MAX_WIDTH, _MAX_LAYERS = 1024, 16


@dataclass(frozen=True)
class HeightNetConfig:
    """The network's shape: ``mapping`` Fourier frequencies of std ``scale`` (drawn from
    ``b_seed``), ``layers`` linear layers of ``hidden`` units (ReLU), one output."""

    mapping: int = 32
    scale: float = 6.0
    hidden: int = 32
    layers: int = 3
    b_seed: int = 0

    def __post_init__(self) -> None:
        if self.mapping < 1 or self.hidden < 1 or self.layers < 2 or not self.scale > 0:
            raise FedmapError(f"invalid height network: {self}")


class HeightNet(nn.Module):
    """(N, 2) coordinates in (0, 1)^2 -> (N,) normalised heights."""

    def __init__(self, config: HeightNetConfig) -> None:
        super().__init__()
        self.config = c = config
        self.features = FourierFeatures(c.mapping, c.scale, c.b_seed)
        mods: list[nn.Module] = []
        width = 2 * c.mapping
        for _ in range(c.layers - 1):
            mods += [nn.Linear(width, c.hidden), nn.ReLU()]
            width = c.hidden
        mods.append(nn.Linear(width, 1))
        self.mlp = nn.Sequential(*mods)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        return self.mlp(feats).squeeze(-1)


def _coords(h: int, w: int) -> torch.Tensor:
    r = (torch.arange(h, dtype=torch.float32) + 0.5) / max(h, w)
    c = (torch.arange(w, dtype=torch.float32) + 0.5) / max(h, w)
    rr, cc = torch.meshgrid(r, c, indexing="ij")
    return torch.stack([rr.reshape(-1), cc.reshape(-1)], dim=1)


def _fake_int8(w: torch.Tensor) -> torch.Tensor:
    """``w`` rounded to int8 steps of ``max|w| / 127``, with a straight-through gradient."""
    s = w.detach().abs().max().clamp_min(1e-12) / 127
    return w + (torch.round(w / s).clamp(-127, 127) * s - w).detach()


def _quantised_forward(net: HeightNet, feats: torch.Tensor) -> torch.Tensor:
    x = feats
    for m in net.mlp:
        x = nn.functional.linear(x, _fake_int8(m.weight), _fake_int8(m.bias)) if isinstance(m, nn.Linear) else m(x)
    return x.squeeze(-1)


@dataclass(frozen=True)
class HeightFit:
    """A fitted height field: the network, and the normalisation of its output."""

    net: HeightNet
    mean: float
    std: float
    shape: tuple[int, int]


def fit_heights(z: np.ndarray, config: HeightNetConfig = HeightNetConfig(), *, steps: int = 1500,
                qat_steps: int = 300, lr: float = 5e-3, seed: int = 0) -> HeightFit:
    """Fit a :class:`HeightNet` to the known (finite) cells of ``z`` (see the module docstring)."""
    z = np.asarray(z, dtype=np.float64)
    known = np.isfinite(z)
    if z.ndim != 2 or not known.any():
        raise FedmapError("a height field needs a 2-D elevation layer with at least one known cell")
    mean, std = float(z[known].mean()), float(z[known].std()) or 1.0
    torch.manual_seed(seed)
    net = HeightNet(config)
    with torch.no_grad():
        feats = net.features(_coords(*z.shape))[torch.from_numpy(known.reshape(-1))]
    target = torch.from_numpy(((z[known] - mean) / std).astype(np.float32))
    opt = torch.optim.Adam(net.mlp.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps + qat_steps, 1))
    for i in range(steps + qat_steps):
        opt.zero_grad(set_to_none=True)
        pred = net(feats) if i < steps else _quantised_forward(net, feats)
        loss = torch.mean((pred - target) ** 2)
        loss.backward()
        opt.step()
        sched.step()
    if not np.isfinite(loss.item()):
        raise RejectedUpdate("the height field's training diverged")
    return HeightFit(net, mean, std, z.shape)


def encode_heightnet(fit: HeightFit) -> bytes:
    """The payload of a fitted height field (see the module docstring)."""
    head = json.dumps({"config": asdict(fit.net.config), "mean": fit.mean, "std": fit.std,
                       "shape": list(fit.shape)}, separators=(",", ":")).encode()
    body = bytearray()
    for p in fit.net.mlp.parameters():
        w = p.detach().numpy().astype(np.float64).ravel()
        s = max(float(np.abs(w).max()), 1e-12) / 127
        body += struct.pack("<f", s) + np.clip(np.round(w / s), -127, 127).astype(np.int8).tobytes()
    packed = zstandard.ZstdCompressor(level=19).compress(bytes(body))
    return _LEN.pack(len(head)) + head + packed


def decode_heightnet(payload: bytes) -> np.ndarray:
    """The heights (metres, the layer's shape) a :func:`encode_heightnet` payload renders."""
    try:
        (n,) = _LEN.unpack_from(payload)
        meta = json.loads(payload[_LEN.size:_LEN.size + n])
        config = HeightNetConfig(**meta["config"])
        h, w = (int(v) for v in meta["shape"])
    except (struct.error, ValueError, KeyError, TypeError, FedmapError) as exc:
        raise RejectedUpdate(f"height-field payload: damaged ({type(exc).__name__})") from exc
    # what a payload claims is checked before anything of that size is made
    if max(config.mapping, config.hidden) > _MAX_WIDTH or config.layers > _MAX_LAYERS or not (
            0 < h <= MAX_WIRE_SIDE and 0 < w <= MAX_WIRE_SIDE):
        raise RejectedUpdate(f"height-field payload: it claims a {config} network for a {h}x{w} map, beyond the "
                             f"limits (width {_MAX_WIDTH}, {_MAX_LAYERS} layers, sides {MAX_WIRE_SIDE})")
    net = HeightNet(config)
    try:
        raw = inflate_zstd(payload[_LEN.size + n:], sum(4 + p.numel() for p in net.mlp.parameters()))
    except ValueError as exc:
        raise RejectedUpdate(f"height-field payload: damaged weights ({exc})") from exc
    off = 0
    with torch.no_grad():
        for p in net.mlp.parameters():
            if off + 4 + p.numel() > len(raw):
                raise RejectedUpdate("height-field payload: truncated weights")
            (s,) = struct.unpack_from("<f", raw, off)
            q = np.frombuffer(raw, dtype=np.int8, count=p.numel(), offset=off + 4)
            p.copy_(torch.from_numpy((q.astype(np.float32) * s).reshape(tuple(p.shape))))
            off += 4 + p.numel()
        out = net(net.features(_coords(h, w))).numpy().astype(np.float64)
    return out.reshape(h, w) * float(meta["std"]) + float(meta["mean"])


class HeightGrid(nn.Module):
    """fedmap's GridNet with an elevation head: trainable one-channel grids at ``resolutions``
    (bilinear, corners aligned to the map's corners), summed into one normalised height.
    A grid entry only moves where its cells have data, so coverage-aware averaging
    (:func:`~fedmap.federation.aggregate.coverage_average`) merges the rovers' fits into
    their union."""

    def __init__(self, resolutions: tuple[int, ...]) -> None:
        super().__init__()
        if not resolutions or min(resolutions) < 2:
            raise FedmapError(f"a height grid needs resolutions >= 2, got {resolutions}")
        self.resolutions = tuple(int(r) for r in resolutions)
        self.grids = nn.ParameterList([nn.Parameter(torch.zeros(1, 1, r, r)) for r in self.resolutions])

    def forward(self, coords: torch.Tensor) -> torch.Tensor:  # (N, 2) in (0, 1)^2 -> (N,)
        g = (coords * 2 - 1).flip(-1).view(1, -1, 1, 2)  # grid_sample takes (x, y) = (col, row)
        out = torch.zeros(coords.shape[0])
        for p in self.grids:
            out = out + nn.functional.grid_sample(p, g, mode="bilinear", align_corners=False).view(-1)
        return out


def fit_height_grid(model: HeightGrid, z: np.ndarray, *, mean: float, std: float, steps: int = 300,
                    lr: float = 0.1) -> list[float]:
    """Train ``model`` in place on the known cells of ``z`` (normalised by ``mean``/``std``,
    the team's, so every rover's grid is on one scale); full batch, Adam."""
    z = np.asarray(z, dtype=np.float64)
    known = np.isfinite(z)
    if not known.any():
        raise RejectedUpdate("no known height to train on")
    coords = _coords(*z.shape)[torch.from_numpy(known.reshape(-1))]
    target = torch.from_numpy(((z[known] - mean) / std).astype(np.float32))
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        loss = torch.mean((model(coords) - target) ** 2)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    if not np.isfinite(losses[-1]):
        raise RejectedUpdate("the height grid's training diverged")
    return losses


def render_height_grid(model: HeightGrid, shape: tuple[int, int], *, mean: float, std: float) -> np.ndarray:
    """The heights (metres) a height grid renders on a ``shape`` map."""
    with torch.no_grad():
        out = model(_coords(*shape)).numpy().astype(np.float64)
    return out.reshape(shape) * std + mean


def render_fit(fit: HeightFit) -> np.ndarray:
    """What the receiver decodes from :func:`encode_heightnet` of ``fit`` (the int8 weights)."""
    return decode_heightnet(encode_heightnet(fit))
