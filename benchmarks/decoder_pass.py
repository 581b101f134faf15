"""A big GridNet step's decoder: written out in torch against the compiled pass, and the
``fit`` steps it is part of.

    python benchmarks/decoder_pass.py [--cells 4194304] [--side 4096] [--steps 6] [--repeats 7]

1. The frozen decoder, the loss and the loss's gradient on the features, on ``--cells``
   cells of seeded features and targets: in torch (forward, loss and ``autograd.grad`` in
   chunks of 2²⁰ cells, the in-place decoder) and in one compiled pass
   (``fedmap.nets.training.decoder_pass``). Prints the sorted times of ``--repeats`` runs
   of each, their ratio of medians, the cells whose gradients differ by more than 1e-4 of
   the largest gradient (a hidden unit at ReLU's edge, on one side in one order of
   rounding and on the other in the other), and the largest difference elsewhere.
2. ``fit`` on a seeded random ``--side``² map, the way a rover (one quadrant known) and the
   central bound (every cell) train: the median step after the first (which compiles or
   loads the kernel), in ms.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.nets.model import build_model, grid_config
from fedmap.nets.training import TrainConfig, decoder_pass, fit, keep_freed_memory, map_loss


def _torch_pass(net, feats, y, wt, total, chunk=1 << 20):
    grad, value = torch.empty_like(feats), 0.0
    for a in range(0, feats.shape[0], chunk):
        leaf = feats[a:a + chunk].detach().requires_grad_()
        part = map_loss(net.head(leaf), y[a:a + chunk], wt[a:a + chunk], total)
        grad[a:a + leaf.shape[0]] = torch.autograd.grad(part, leaf)[0]
        value += part.item()
    return grad, value


def _times(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1e3)
    return sorted(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", type=int, default=1 << 22)
    ap.add_argument("--side", type=int, default=4096, help="the fit's map side (0: skip the fit steps)")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    keep_freed_memory()
    print(f"torch threads: {torch.get_num_threads()}")
    net = build_model(grid_config(64))
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(a.cells, net.w1.shape[1], generator=g) * 0.5
    y = torch.rand(a.cells, 3, generator=g).round()
    wt = torch.rand(a.cells, generator=g)
    total = wt.sum()
    want, _ = _torch_pass(net, feats, y, wt, total)
    got, _ = decoder_pass(net, feats, y, wt, float(total))
    off = ((got - want).abs() > 1e-4 * want.abs().max()).any(dim=1)
    rel = float((got - want)[~off].abs().max() / want.abs().max())
    written = _times(lambda: _torch_pass(net, feats, y, wt, total), a.repeats)
    compiled = _times(lambda: decoder_pass(net, feats, y, wt, float(total)), a.repeats)
    print(f"decoder, loss and gradient on {a.cells:,} cells:")
    print(f"  torch    ms {[round(t) for t in written]}")
    print(f"  compiled ms {[round(t) for t in compiled]}")
    print(f"  torch / compiled (medians): {statistics.median(written) / statistics.median(compiled):.2f}x; "
          f"gradients within {rel:.1e} of the largest, but for {int(off.sum())} cell(s) at ReLU's edge")
    if a.side:
        rng = np.random.default_rng(0)
        classes = (rng.random((a.side, a.side)) < 0.2).astype(np.uint8)
        quadrant = classes.copy()
        half = a.side // 2
        quadrant[:, half:] = UNKNOWN
        quadrant[half:, :] = UNKNOWN
        for name, c in (("rover (one quadrant known)", quadrant), ("central (every cell)", classes)):
            stamps: list[float] = []
            model = build_model(grid_config(a.side))
            t0 = time.perf_counter()
            fit(model, GridMap(c, 1.0, "bench"), TrainConfig(epochs=a.steps, lr=0.05, masked=True),
                on_step=lambda s, loss: stamps.append(time.perf_counter()))
            steps = np.diff([t0, *stamps]) * 1e3
            print(f"fit {a.side}², {name}: median step {np.median(steps[1:]):.0f} ms (first {steps[0]:.0f} ms)")


if __name__ == "__main__":
    main()
