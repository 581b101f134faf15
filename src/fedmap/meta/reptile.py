"""Reptile meta-training (Nichol, Achiam & Schulman 2018) of a coordinate network.

One meta-iteration samples ``meta_batch`` tasks (a task is a category of maps), one map
from each, adapts a copy of theta to that map with ``inner_steps`` full-grid Adam steps
(:func:`fedmap.nets.training.fit`, a fresh optimiser every time) and moves theta toward the
adapted weights:

    theta <- theta + eps_i * (mean_b phi_b - theta)

with ``eps_i`` annealed linearly from ``eps_start`` to ``eps_end`` over the iterations
(the paper's serial/batched Reptile). theta starts from the empty-map prior
(:func:`fedmap.nets.init.empty_prior`).

Every random choice of iteration ``i`` comes from ``numpy.random.default_rng([seed, i])``,
so a run resumed from a checkpoint gives the same bytes as an uninterrupted one.
Checkpoints are written atomically with :func:`fedmap.nets.model.save_model` and carry the
iteration, the settings and the validation history.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.meta.ablation import psnr_curve
from fedmap.meta.collections import MapCollection
from fedmap.nets.init import empty_prior
from fedmap.nets.model import NetConfig, Weights, build_model, get_weights, load_model, save_model, set_weights
from fedmap.nets.training import TrainConfig, fit, resolve_precision


@dataclass(frozen=True)
class MetaConfig:
    """Reptile settings (defaults: the command that built the shipped weights)."""
    iterations: int = 300
    inner_steps: int = 5
    inner_lr: float = 1e-3
    meta_batch: int = 4
    eps_start: float = 1.0
    eps_end: float = 0.0
    prior_steps: int = 150
    val_every: int = 25
    val_steps: int = 2
    val_lr: float = 1e-4
    seed: int = 0
    precision: str = "auto"  # training precision of every inner fit (resolved: bf16 or fp32)

    def __post_init__(self) -> None:
        object.__setattr__(self, "precision", resolve_precision(self.precision))
        for name in ("iterations", "inner_steps", "meta_batch", "val_every", "val_steps"):
            if getattr(self, name) < 1:
                raise FedmapError(f"{name.replace('_', ' ')} must be at least 1, got {getattr(self, name)}")
        if self.prior_steps < 0:
            raise FedmapError(f"prior steps must be >= 0, got {self.prior_steps}")
        if not (self.inner_lr > 0 and self.val_lr > 0):
            raise FedmapError(f"learning rates must be positive, got inner {self.inner_lr}, validation {self.val_lr}")
        if not (0 <= self.eps_end <= 1 and 0 < self.eps_start <= 1):
            raise FedmapError(f"meta step sizes must lie in (0, 1], got {self.eps_start} -> {self.eps_end}")

    def to_dict(self) -> dict:
        return asdict(self)

    def epsilon(self, iteration: int) -> float:
        """Meta step size of iteration ``iteration`` (0-based): linear from start to end."""
        frac = iteration / max(self.iterations - 1, 1)
        return self.eps_start + (self.eps_end - self.eps_start) * frac


def reptile_update(theta: Weights, phis: list[Weights], epsilon: float) -> Weights:
    """theta + epsilon * (mean(phis) - theta), per tensor, in float64 then float32."""
    if not phis:
        raise FedmapError("a Reptile step needs at least one adapted model")
    out: Weights = {}
    for k, t in theta.items():
        t64 = np.asarray(t, dtype=np.float64)
        mean = sum(np.asarray(p[k], dtype=np.float64) for p in phis) / len(phis)
        out[k] = (t64 + epsilon * (mean - t64)).astype(np.float32)
    return out


@dataclass
class MetaResult:
    weights: Weights
    history: list[dict] = field(default_factory=list)  # {"iteration", "val_psnr", "epsilon"}
    iteration: int = 0


def validation_psnr(weights: Weights, net_config: NetConfig, maps: list[GridMap], *, steps: int, lr: float,
                    seed: int = 0, precision: str = "auto") -> float:
    """Mean PSNR (dB, raw RGB output) over ``maps`` after ``steps`` Adam steps from ``weights``."""
    return float(np.mean([psnr_curve(weights, net_config, m, steps=steps, lr=lr, seed=seed, precision=precision)[-1]
                          for m in maps]))


def read_checkpoint_info(path: str | Path) -> dict:
    """The ``extra`` metadata stored with a model file by :func:`fedmap.nets.model.save_model`."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
        return json.loads(meta["fedmap"]).get("extra", {})
    except (SafetensorError, KeyError, ValueError, OSError) as e:
        raise FedmapError(f"{path} is not a fedmap model file ({type(e).__name__})") from e


def meta_train(
    collection: MapCollection,
    net_config: NetConfig,
    config: MetaConfig,
    *,
    val_maps: Sequence[GridMap] = (),
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 25,
    resume: bool = False,
    extra: dict | None = None,
    on_step: Callable[[int, dict], None] | None = None,
) -> MetaResult:
    """Reptile from the empty-map prior over ``collection``'s categories.

    ``checkpoint`` is rewritten atomically every ``checkpoint_every`` iterations and at
    the end; with ``resume=True`` training continues from it (its settings must match).
    ``on_step(iteration, info)`` is called after every meta-iteration.
    """
    if not collection.categories:
        raise FedmapError(f"collection {collection.name!r} has no maps")
    model = build_model(net_config, seed=config.seed)
    history: list[dict] = []
    start = 0
    if resume:
        if checkpoint is None or not Path(checkpoint).is_file():
            raise FedmapError(f"cannot resume: no checkpoint at {checkpoint}")
        saved = read_checkpoint_info(checkpoint).get("meta_train")
        if not saved:
            raise FedmapError(f"{checkpoint} is not a meta-training checkpoint")
        if saved["config"] != config.to_dict() or saved["collection"] != collection.name:
            raise FedmapError(f"{checkpoint} was written with other settings or another collection; "
                              "resume with the same options or start afresh")
        loaded = load_model(checkpoint)
        if loaded.config != net_config:
            raise FedmapError(f"{checkpoint} holds a different network ({loaded.config})")
        theta = get_weights(loaded)
        history, start = list(saved["history"]), int(saved["iteration"])
    elif config.prior_steps > 0:
        theta = get_weights(empty_prior(net_config, steps=config.prior_steps, seed=config.seed,
                                        precision=config.precision))
    else:
        theta = get_weights(model)

    def save(iteration: int) -> None:
        assert checkpoint is not None  # save() is only called with a checkpoint path
        set_weights(model, theta)
        info = {"iteration": iteration, "config": config.to_dict(), "collection": collection.name,
                "history": history}
        save_model(model, checkpoint, extra={**(extra or {}), "meta_train": info})

    def validate() -> float:
        return validation_psnr(theta, net_config, list(val_maps), steps=config.val_steps, lr=config.val_lr,
                               seed=config.seed, precision=config.precision)

    if val_maps and start == 0:
        history.append({"iteration": 0, "val_psnr": validate(), "epsilon": None})  # theta_0
    inner = TrainConfig(epochs=config.inner_steps, lr=config.inner_lr, precision=config.precision)
    for it in range(start, config.iterations):
        rng = np.random.default_rng([config.seed, it])
        phis = []
        for _ in range(config.meta_batch):
            grid = collection.sample(rng)
            set_weights(model, theta)
            fit(model, grid, inner, seed=config.seed)
            phis.append(get_weights(model))
        eps = config.epsilon(it)
        theta = reptile_update(theta, phis, eps)
        done = it + 1
        info: dict = {"epsilon": eps}
        if val_maps and (done % config.val_every == 0 or done == config.iterations):
            val = validate()
            history.append({"iteration": done, "val_psnr": val, "epsilon": eps})
            info["val_psnr"] = val
        if checkpoint is not None and (done % checkpoint_every == 0 or done == config.iterations):
            save(done)
        if on_step is not None:
            on_step(done, info)
    return MetaResult(theta, history, config.iterations)
