"""Coordinate network: Gaussian Fourier features of (x, y) -> per-pixel MLP -> RGB.

The paper's network is four 1x1 convolutions with ReLU and BatchNorm on a ``(1, C, H, W)``
image of encoded coordinates. A 1x1 convolution is a ``Linear`` layer applied to every
pixel, so here the pixels are the batch: ``(H*W, C)``. That is the same function (a test
checks it against the ``Conv2d`` form) and about 4x faster on CPU.

BatchNorm keeps **no running statistics** (``track_running_stats=False``): it always
normalises with the statistics of the batch it sees. In federation the payload is the
trainable parameters only (the paper's 199,683 numbers), and every agent renders the
global map from the full coordinate grid, so the statistics are recomputed identically
everywhere. :func:`render` computes exact full-grid statistics in chunks, so large maps
need little memory.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch
from torch import nn

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.maps.coords import pixel_centres

Weights = dict[str, np.ndarray]


@dataclass(frozen=True)
class NetConfig:
    """Everything needed to rebuild a network (stored with every checkpoint).

    ``encoding="fourier"`` is the paper's network (Fourier features -> MLP).
    ``encoding="grid"`` is a :class:`GridNet`: trainable multi-resolution feature grids
    (``grid_res``, ``grid_features`` channels each) read by bilinear interpolation and a
    small *frozen* decoder rebuilt from ``b_seed`` (never trained, never sent).
    """

    mapping_size: int = 128  # Fourier features: 2 * mapping_size input channels
    scale: float = 10.0  # std of the Gaussian frequencies B
    hidden: int = 256
    layers: int = 4  # linear layers, the last one maps to RGB
    batchnorm: bool = True
    b_seed: int = 0  # B (or the grid decoder) is drawn from this seed, shared, never sent
    encoding: str = "fourier"
    grid_res: tuple[int, ...] = ()
    grid_features: int = 2
    decoder_hidden: int = 32

    def __post_init__(self) -> None:
        object.__setattr__(self, "grid_res", tuple(int(r) for r in self.grid_res))
        if self.encoding not in ("fourier", "grid"):
            raise FedmapError(f"unknown encoding {self.encoding!r}; choose fourier or grid")
        if self.mapping_size <= 0 or self.hidden <= 0 or self.layers < 1 or self.scale <= 0:
            raise FedmapError(f"invalid network config: {self}")
        if self.encoding == "grid" and (not self.grid_res or min(self.grid_res) < 2
                                        or self.grid_features < 1 or self.decoder_hidden < 1):
            raise FedmapError(f"a grid network needs grid resolutions >= 2 and positive sizes, got {self}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["grid_res"] = list(self.grid_res)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> NetConfig:
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise FedmapError(f"unknown network config keys: {sorted(unknown)}")
        return cls(**d)


def grid_config(size: int, *, levels: int = 2, features: int = 4, seed: int = 0) -> NetConfig:
    """A :class:`GridNet` config for ``size x size`` maps: finest level at one cell per map
    pixel, each coarser level half the previous (at least 2)."""
    res = tuple(max(2, size >> i) for i in reversed(range(levels)))
    return NetConfig(encoding="grid", grid_res=res, grid_features=features, b_seed=seed)


PRESETS: dict[str, NetConfig] = {
    "paper": NetConfig(),
    "small": NetConfig(mapping_size=64, hidden=128),
}


NET_CHOICES = (*PRESETS, "grid")


def preset(name: str, size: int | None = None) -> NetConfig:
    """A named network: ``paper``, ``small``, or ``grid`` (sized to a ``size x size`` map)."""
    if name == "grid":
        return grid_config(size or 128)
    try:
        return PRESETS[name]
    except KeyError:
        raise FedmapError(f"unknown network {name!r}; choose one of {', '.join(NET_CHOICES)}") from None


class FourierFeatures(nn.Module):
    """gamma(v) = [cos(2 pi B v), sin(2 pi B v)] with B ~ N(0, scale^2), shape (mapping, 2).

    ``B`` is a non-persistent buffer: not trained, not in the state dict, not sent. It is
    rebuilt from ``b_seed`` with torch's CPU generator, so every agent has the same B.
    """

    B: torch.Tensor

    def __init__(self, mapping_size: int, scale: float, b_seed: int) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(b_seed)
        B = torch.randn(mapping_size, 2, generator=g) * scale
        self.register_buffer("B", B, persistent=False)

    def forward(self, v: torch.Tensor) -> torch.Tensor:  # (N, 2) -> (N, 2*mapping)
        proj = 2 * torch.pi * (v @ self.B.T)  # (N, mapping)
        return torch.cat([torch.cos(proj), torch.sin(proj)], dim=-1)


class CoordNet(nn.Module):
    """(N, 2) coordinates in (0, 1)^2 -> (N, 3) RGB in (0, 1)."""

    cacheable_features = True  # features do not depend on trained weights

    def __init__(self, config: NetConfig | None = None) -> None:
        super().__init__()
        self.config = config or NetConfig()
        c = self.config
        self.features = FourierFeatures(c.mapping_size, c.scale, c.b_seed)
        mods: list[nn.Module] = []
        width = 2 * c.mapping_size
        for _ in range(c.layers - 1):
            mods.append(nn.Linear(width, c.hidden))
            mods.append(nn.ReLU())
            if c.batchnorm:
                mods.append(nn.BatchNorm1d(c.hidden, track_running_stats=False))
            width = c.hidden
        mods.append(nn.Linear(width, 3))
        self.mlp = nn.Sequential(*mods)

    def forward(self, v: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(v))

    def head(self, feats: torch.Tensor) -> torch.Tensor:
        """The trainable part on precomputed features: (N, 2*mapping) -> (N, 3).

        Training caches ``features(coords)`` once per map (B is fixed), which saves the
        cos/sin of every pixel at every step.
        """
        return torch.sigmoid(self.mlp(feats).float())  # fp32 sigmoid, also under bf16 autocast


class GridNet(nn.Module):
    """(N, 2) coordinates -> (N, 3) RGB from multi-resolution feature grids.

    Every trainable parameter is a grid cell, so an agent's data only moves the cells
    whose bilinear footprint covers its observed pixels (parameters are *local in
    space*); with coverage-aware aggregation the federated model is then (nearly) the
    union of the local fits. The decoder (``L*F -> hidden -> 3``) is frozen and drawn
    from ``b_seed``; its last bias is set so that an all-zero grid renders grey 0.5
    (UNKNOWN): a fresh GridNet already *is* the empty-map prior.
    """

    cacheable_features = False
    w1: torch.Tensor
    b1: torch.Tensor
    w2: torch.Tensor
    r1: torch.Tensor
    c1: torch.Tensor

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = c = config
        self.grids = nn.ParameterList([nn.Parameter(torch.zeros(1, c.grid_features, r, r)) for r in c.grid_res])
        g = torch.Generator().manual_seed(c.b_seed)
        fan_in = c.grid_features * len(c.grid_res)
        w1 = torch.randn(c.decoder_hidden, fan_in, generator=g) * (2.0 / fan_in) ** 0.5 * 2.0
        b1 = torch.randn(c.decoder_hidden, generator=g) * 0.5
        w2 = torch.randn(3, c.decoder_hidden, generator=g) * (2.0 / c.decoder_hidden) ** 0.5 * 2.0
        # relu(z) - relu(b1) in place of relu(z) plus a last bias -(w2 relu(b1)): zero features give
        # hidden 0 and logits 0 exactly, so a fresh grid renders exactly grey (0.5) and a cell whose
        # target is grey has exactly no gradient. With the bias, the logits were a sum of terms that
        # cancel, whose rounding depends on the matrix kernel (the batch's size, the CPU): about 1e-8
        # on some, 0 on others, and Adam turns a gradient of 1e-8 into a full step (it scales by 1/√v)
        r1 = torch.relu(b1)
        for name, t in (("w1", w1), ("b1", b1), ("w2", w2), ("r1", r1), ("c1", b1 - r1)):
            self.register_buffer(name, t, persistent=False)

    def features(self, v: torch.Tensor) -> torch.Tensor:  # (N, 2) in (0,1)^2 -> (N, L*F)
        """Each level's bilinear reading at ``v``, one channel per batch entry.

        torch's CPU ``grid_sample`` (and its backward, which scatters into the grid) runs
        its batch entries in parallel and everything within one entry on one thread. A
        grid is one entry of ``F`` channels, so the whole step ran on one core. Read as
        ``F`` entries of one channel each, at the same points, the channels run on every
        thread and no two write the same gradient; each channel's arithmetic, and the
        order in which its cells' gradients add up, is unchanged, so the values and
        gradients are the same to the bit (``tests/test_model.py``). Features and backward
        at 1 M points of a 2048² grid (two levels of four channels), 2 threads on Zen 4: 502-594 ms
        before, 191-233 ms after; 63 against 43 ms at 1024² on one thread, where one
        channel at a time touches a quarter of the grid's memory."""
        gr = (v * 2 - 1).view(1, -1, 1, 2)  # grid_sample wants (x, y) in [-1, 1]
        out = []
        for G in self.grids:
            f = G.shape[1]
            one_each = G.view(f, 1, *G.shape[2:])  # (1, F, r, r) -> (F, 1, r, r): a view, no copy
            out.append(nn.functional.grid_sample(one_each, gr.expand(f, -1, -1, -1), mode="bilinear",
                                                 padding_mode="border", align_corners=False).view(f, -1).T)
        return torch.cat(out, dim=1)

    def head(self, feats: torch.Tensor) -> torch.Tensor:
        """The frozen decoder, ``sigmoid((relu(feats w1ᵀ + b1) - relu(b1)) w2ᵀ)``: zero features
        are exactly grey, whatever the kernels' summation order. Computed as
        ``max(feats w1ᵀ + c1, -r1) w2ᵀ`` (``r1 = relu(b1)``, ``c1 = b1 - r1 = min(b1, 0)``, both
        exact), its bias, clamp and sigmoid applied in place: a product's backward needs its
        inputs, not its output, so nothing autograd keeps is overwritten, and the values and
        gradients are those of the same operations out of place to the bit (``tests/test_model.py``).
        On every cell of a big map the decoder's 32-wide activations are memory traffic: its forward and backward on 4 M
        cells took 376-382 ms written out, 342-348 ms in place (Zen 4, 2 threads)."""
        hidden = feats @ self.w1.T
        hidden.add_(self.c1).clamp_min_(-self.r1)
        return (hidden @ self.w2.T).sigmoid_()

    def forward(self, v: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(v))


def build_model(config: NetConfig | None = None, *, seed: int = 0) -> CoordNet | GridNet:
    """A freshly initialised network; ``seed`` fixes the initial weights."""
    config = config or NetConfig()
    if config.encoding == "grid":
        return GridNet(config)  # deterministic: zero grids, decoder from b_seed
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return CoordNet(config)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


# -- weights as plain numpy (what aggregation and payloads work on) -------------------

def get_weights(model: nn.Module) -> Weights:
    """Trainable state as ``{name: float32 array}`` (copies)."""
    return {k: v.detach().cpu().numpy().copy() for k, v in model.state_dict().items()}


def set_weights(model: nn.Module, weights: Weights) -> None:
    """Load weights, checking names and shapes with a clear error."""
    own = model.state_dict()
    if set(own) != set(weights):
        missing, extra = sorted(set(own) - set(weights)), sorted(set(weights) - set(own))
        raise FedmapError(f"weights do not fit the model: missing {missing}, unexpected {extra}")
    for k, v in weights.items():
        if tuple(own[k].shape) != tuple(np.shape(v)):
            raise FedmapError(f"weight {k!r} has shape {tuple(np.shape(v))}, the model needs {tuple(own[k].shape)}")
        if not np.all(np.isfinite(v)):
            raise FedmapError(f"weight {k!r} holds NaN or infinite values")
    model.load_state_dict({k: torch.as_tensor(np.asarray(v, dtype=np.float32)) for k, v in weights.items()})


# -- rendering -------------------------------------------------------------------------

def grid_coords(height: int, width: int) -> torch.Tensor:
    """Pixel-centre coordinates of the global frame as a tensor, (H*W, 2)."""
    return torch.from_numpy(pixel_centres(height, width))


@torch.no_grad()
def render(model: nn.Module, height: int, width: int, *, chunk: int = 1 << 16) -> np.ndarray:
    """The model's map of the whole frame: (H, W, 3) float32 RGB in [0, 1].

    BatchNorm uses the exact statistics of the full grid (as in training on the full
    grid). They are accumulated chunk by chunk, one pass per BatchNorm layer, so memory
    stays at ``chunk`` rows whatever the map size.
    """
    coords = grid_coords(height, width)
    n = coords.shape[0]
    if n <= chunk or not any(isinstance(m, nn.BatchNorm1d) for m in model.modules()):
        # per-pixel function (no batch statistics): plain chunks are exact
        return torch.cat([model(coords[a : a + chunk]) for a in range(0, n, chunk)]).reshape(height, width, 3).numpy()
    # Only a CoordNet has BatchNorm layers (a GridNet returned above): it has ``mlp`` and ``features``.
    layers = list(cast(nn.Sequential, model.mlp))
    features = cast(nn.Module, model.features)
    stats: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def run(x: torch.Tensor, upto: int) -> torch.Tensor:
        for i, layer in enumerate(layers[:upto]):
            if isinstance(layer, nn.BatchNorm1d):
                mean, var = stats[i]
                x = (x - mean) / torch.sqrt(var + layer.eps) * layer.weight + layer.bias
            else:
                x = layer(x)
        return x

    for i, layer in enumerate(layers):
        if isinstance(layer, nn.BatchNorm1d):
            s = torch.zeros(layer.num_features, dtype=torch.float64)
            s2 = torch.zeros_like(s)
            for a in range(0, n, chunk):
                x = run(features(coords[a : a + chunk]), i).double()
                s += x.sum(0)
                s2 += (x * x).sum(0)
            mean = s / n
            var = (s2 / n - mean * mean).clamp_min(0)  # biased, as BatchNorm normalises
            stats[i] = (mean.float(), var.float())
    out = torch.empty(n, 3)
    for a in range(0, n, chunk):
        out[a : a + chunk] = torch.sigmoid(run(features(coords[a : a + chunk]), len(layers)))
    return out.reshape(height, width, 3).numpy()


# -- checkpoints -------------------------------------------------------------------------

def save_model(model: CoordNet | GridNet, path: str | os.PathLike, *, extra: dict | None = None) -> None:
    """Write weights + the config that built them as safetensors, atomically."""
    from safetensors.torch import save

    # One metadata key: safetensors keeps metadata in a hash map whose order varies
    # between calls, so several keys would make identical models differ in bytes.
    meta = {"fedmap": json.dumps({"config": model.config.to_dict(), "extra": extra or {}}, sort_keys=True)}
    data = save({k: v.contiguous() for k, v in model.state_dict().items()}, metadata=meta)

    atomic_write_bytes(path, data)


def load_model(path: str | os.PathLike) -> CoordNet | GridNet:
    """Rebuild a network from a checkpoint alone (config is stored inside)."""
    from safetensors import SafetensorError
    from safetensors.torch import load

    p = Path(path)
    if not p.is_file():
        raise FedmapError(f"no such model file: {p}")
    raw = p.read_bytes()
    try:
        tensors = load(raw)
        header_len = int.from_bytes(raw[:8], "little")
        header = json.loads(raw[8 : 8 + header_len])
        config = NetConfig.from_dict(json.loads(header["__metadata__"]["fedmap"])["config"])
    except (SafetensorError, KeyError, ValueError, TypeError) as e:
        raise FedmapError(f"{p} is not a fedmap model file ({type(e).__name__}: {e})".splitlines()[0]) from e
    model = build_model(config)
    set_weights(model, {k: v.numpy() for k, v in tensors.items()})
    return model


__all__ = [
    "NetConfig", "PRESETS", "preset", "FourierFeatures", "CoordNet", "build_model", "count_parameters",
    "get_weights", "set_weights", "grid_coords", "render", "save_model", "load_model",
    "Weights",
]
