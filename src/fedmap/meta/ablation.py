"""Table I of the paper: how fast a network fits new maps from each initialisation.

For every test map and every initialisation (random, empty-map prior, meta) the network
is fitted with full-grid Adam (:func:`fedmap.nets.training.fit`, MSE on the RGB rendering,
UNKNOWN cells trained as grey) and its PSNR is recorded after every step. Reported:

* PSNR (and SSIM) after ``n_steps`` steps, mean and std over the maps;
* for each initialisation, the number of steps it needs to reach the **meta** network's
  ``n_steps``-step PSNR on the same map (mean +- std); a run that does not reach it
  within ``max_steps`` counts as ``max_steps`` and is reported as capped.

PSNR is computed on the raw network output (RGB in [0, 1]) against the map rendered
in the palette, data range 1. With full-grid training the loss before step ``t`` *is*
the MSE of the output after ``t - 1`` steps (BatchNorm uses the full-grid statistics, as
:func:`fedmap.nets.model.render` does), so the PSNR curve comes from the training losses:
``psnr_t = -10 log10(loss_{t+1})``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fedmap._util import AtomicDir, to_json
from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import psnr, ssim
from fedmap.maps.grid import GridMap
from fedmap.nets.init import empty_prior, load_init_weights
from fedmap.nets.model import NetConfig, Weights, build_model, get_weights, preset, render, set_weights
from fedmap.nets.training import TrainConfig, fit, resolve_precision


@dataclass(frozen=True)
class AblationConfig:
    n_steps: int = 2
    lr: float = 1e-4
    max_steps: int = 150
    fig_steps: int = 4  # Fig. 3 shows the reconstructions after 0..fig_steps steps
    seed: int = 0
    precision: str = "auto"  # training precision of every adaptation (resolved: bf16 or fp32)

    def __post_init__(self) -> None:
        object.__setattr__(self, "precision", resolve_precision(self.precision))
        if self.n_steps < 1 or self.max_steps < self.n_steps:
            raise FedmapError(f"need 1 <= n_steps <= max_steps, got {self.n_steps}, {self.max_steps}")
        if not self.lr > 0:
            raise FedmapError(f"learning rate must be positive, got {self.lr}")

    def to_dict(self) -> dict:
        return asdict(self)


def psnr_from_mse(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def psnr_curve(weights: Weights, net_config: NetConfig, grid: GridMap, *, steps: int, lr: float,
               seed: int = 0, precision: str = "auto") -> list[float]:
    """PSNR (dB) of the network's output after 0, 1, ..., ``steps`` Adam steps from ``weights``."""
    model = build_model(net_config)
    set_weights(model, weights)
    # the last step's update is unused: its loss is the PSNR after `steps` steps
    losses = fit(model, grid, TrainConfig(epochs=steps + 1, lr=lr, precision=precision), seed=seed)
    return [psnr_from_mse(x) for x in losses]


def adapted_render(weights: Weights, net_config: NetConfig, grid: GridMap, *, steps: int, lr: float,
                   seed: int = 0, precision: str = "auto") -> np.ndarray:
    """The network's (H, W, 3) output after ``steps`` Adam steps from ``weights``."""
    model = build_model(net_config)
    set_weights(model, weights)
    if steps:
        fit(model, grid, TrainConfig(epochs=steps, lr=lr, precision=precision), seed=seed)
    return render(model, *grid.shape)


def steps_to_reach(curve: list[float], target: float) -> int | None:
    """First step count whose PSNR is >= ``target`` (None if the curve never gets there)."""
    for t, p in enumerate(curve):
        if p >= target:
            return t
    return None


def _stats(x: Sequence[float]) -> dict:
    a = np.asarray(x, dtype=np.float64)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if a.size > 1 else 0.0, "n": int(a.size)}


def run_ablation(
    maps: list[GridMap],
    inits: dict[str, Weights],
    net_config: NetConfig,
    config: AblationConfig,
    *,
    on_map: Callable[[int, str], None] | None = None,
) -> dict:
    """Table I over ``maps`` for the named initialisations (``inits`` must include ``meta``).

    Returns a JSON-ready dict: ``table`` (per init: PSNR/SSIM after N steps, steps to reach
    meta's N-step PSNR, how many runs were capped), ``curves`` (mean PSNR per step) and
    ``per_map`` values.
    """
    if "meta" not in inits:
        raise FedmapError("the ablation needs a 'meta' initialisation (the target PSNR is its N-step PSNR)")
    if not maps:
        raise FedmapError("the ablation needs at least one test map")
    curves: dict[str, list[list[float]]] = {k: [] for k in inits}
    ssims: dict[str, list[float]] = {k: [] for k in inits}
    for i, grid in enumerate(maps):
        for name, w in inits.items():
            curves[name].append(psnr_curve(w, net_config, grid, steps=config.max_steps, lr=config.lr, seed=config.seed,
                                           precision=config.precision))
            out = adapted_render(w, net_config, grid, steps=config.n_steps, lr=config.lr, seed=config.seed,
                                 precision=config.precision)
            ssims[name].append(ssim(grid.to_rgb(), out))
            if on_map is not None:
                on_map(i, name)
    n = config.n_steps
    targets = [c[n] for c in curves["meta"]]
    table, per_map = {}, {}
    for name in inits:
        reach = [steps_to_reach(c, tgt) for c, tgt in zip(curves[name], targets)]
        capped = sum(r is None for r in reach)
        counted = [config.max_steps if r is None else r for r in reach]
        table[name] = {
            "psnr": _stats([c[n] for c in curves[name]]),
            "ssim": _stats(ssims[name]),
            "psnr_step0": _stats([c[0] for c in curves[name]]),
            "steps_to_meta": {**_stats(counted), "capped": capped},
        }
        per_map[name] = {"psnr": [c[n] for c in curves[name]], "steps_to_meta": reach, "ssim": ssims[name]}
    ratio = table["random"]["steps_to_meta"]["mean"] / n if "random" in table else None
    return {
        "config": config.to_dict(),
        "n_maps": len(maps),
        "sources": [m.source for m in maps],
        "table": table,
        "random_over_meta_steps": ratio,
        "curves": {k: np.mean(np.asarray(v), axis=0).tolist() for k, v in curves.items()},
        "per_map": per_map,
    }


def fig3(grid: GridMap, inits: dict[str, Weights], net_config: NetConfig, config: AblationConfig, path,
         *, title: str = "") -> None:
    """Reconstructions after 0..fig_steps steps, one row per initialisation, truth at the right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    steps = list(range(config.fig_steps + 1))
    fig, axes = plt.subplots(len(inits), len(steps) + 1, figsize=(1.9 * (len(steps) + 1), 2.0 * len(inits)),
                             dpi=110, squeeze=False)
    truth = grid.to_rgb()
    for r, (name, w) in enumerate(inits.items()):
        for c, s in enumerate(steps):
            img = adapted_render(w, net_config, grid, steps=s, lr=config.lr, seed=config.seed,
                                 precision=config.precision)
            axes[r, c].imshow(np.clip(img, 0, 1), interpolation="nearest")
            axes[r, c].set_title(f"{name}, step {s}\n{psnr(truth, img):.2f} dB", fontsize=7)
        axes[r, -1].imshow(truth, interpolation="nearest")
        axes[r, -1].set_title("ground truth", fontsize=7)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def curve_plot(result: dict, path, *, title: str = "") -> None:
    """Mean PSNR vs optimisation step for each initialisation, meta's N-step PSNR dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 3.4), dpi=110)
    for name, curve in result["curves"].items():
        ax.plot(range(len(curve)), curve, label=name)
    n = result["config"]["n_steps"]
    ax.axhline(result["table"]["meta"]["psnr"]["mean"], color="grey", ls="--", lw=0.8,
               label=f"meta after {n} steps")
    ax.set_xlabel(f"Adam steps (lr {result['config']['lr']:g})")
    ax.set_ylabel("PSNR (dB), mean over maps")
    ax.set_xscale("symlog", linthresh=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def pick_maps(all_maps: list, n: int, *, seed: int) -> list:
    """A seeded choice of ``n`` maps (all of them if there are no more), in their order."""
    if len(all_maps) <= n:
        return list(all_maps)
    idx = np.random.default_rng(seed).choice(len(all_maps), n, replace=False)
    return [all_maps[i] for i in sorted(idx)]


def make_inits(*, init_weights: str | Path | None, prior_steps: int, seed: int,
               net_config: NetConfig | None = None, precision: str = "auto") -> dict[str, Weights]:
    """The three initialisations of Table I: random, empty-map prior, meta (default: shipped)."""

    net_config = net_config or preset("paper")
    meta = load_init_weights(net_config, init_weights)  # first: a wrong file is refused before the prior's fit
    return {
        "random": get_weights(build_model(net_config, seed=seed)),
        "empty": get_weights(empty_prior(net_config, steps=prior_steps, seed=seed, precision=precision)),
        "meta": meta,
    }


def write_ablation(result: dict, fig_map: GridMap, inits: dict[str, Weights], config: AblationConfig,
                   out: str | Path, *, title: str, net_config: NetConfig | None = None) -> None:
    """ablation.json, fig3.png (reconstructions at steps 0..4) and psnr_curve.png, atomically."""

    with AtomicDir(out) as tmp:
        (tmp / "ablation.json").write_text(to_json(result))
        fig3(fig_map, {k: inits[k] for k in ("random", "meta")}, net_config or preset("paper"), config,
             tmp / "fig3.png", title=f"{title}: {fig_map.source}")
        curve_plot(result, tmp / "psnr_curve.png", title=title)
