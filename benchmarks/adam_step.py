"""One Adam step over a GridNet's parameters: torch's fused CPU kernel against the
multi-tensor (``foreach``) kernels, in time and in the memory the step allocates.

    python benchmarks/adam_step.py [--side 2048] [--steps 6] [--threads 2]

The parameters are those of ``fedmap.nets.model.grid_config(side)`` (a rover's GridNet for
a ``side x side`` map: 21 M at 2048², 84 M at 4096²), their gradients seeded noise of a
grid fit's size (the same at every step). Each kernel runs ``--steps`` steps (the first, which allocates the moments,
is left out of the median), each in a fresh process, and the two alternate twice so that
neither gets the warmer machine. What a step allocates is that process's peak RSS less its
RSS after the first step (the moments exist by then). Prints the best median step time of
each, their ratio, the step's allocation, and the largest difference between the two
kernels' parameters after the same steps (they round differently in the last bit).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import torch

from fedmap.nets.model import build_model, grid_config


def _rss_gb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9


def run(kind: str, side: int, steps: int) -> tuple[float, list[torch.Tensor], float]:
    """Median step time after the first, final parameters, GB a step allocates."""
    model = build_model(grid_config(side))
    params = list(model.parameters())
    kw = {"fused": True} if kind == "fused" else {"foreach": True}
    opt = torch.optim.Adam(params, lr=1e-2, eps=1e-8 * 2**16 / side**2, **kw)  # type: ignore[arg-type]
    g = torch.Generator().manual_seed(1)
    for p in params:  # one gradient for every step: nothing but the step allocates in the loop
        p.grad = torch.randn(p.shape, generator=g) * 1e-6
    times = []
    after_first = 0.0
    for it in range(steps):
        t = time.perf_counter()
        opt.step()
        times.append(time.perf_counter() - t)
        if it == 0:
            after_first = _rss_gb()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9  # kB on Linux
    return statistics.median(times[1:]), [p.detach().clone() for p in params], max(peak - after_first, 0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=2048)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--kind", choices=("foreach", "fused"), help=argparse.SUPPRESS)  # one child's run
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.kind:
        t, _, g = run(a.kind, a.side, a.steps)
        print(json.dumps({"step_s": t, "alloc_gb": g}))
        return
    n = sum(p.numel() for p in build_model(grid_config(a.side)).parameters())
    print(f"GridNet for {a.side}²: {n / 1e6:.1f} M parameters, {a.threads} threads")
    best: dict[str, list[float]] = {"foreach": [], "fused": []}
    final: dict[str, list[torch.Tensor]] = {}
    grow: dict[str, float] = {}
    for kind in ("foreach", "fused", "foreach", "fused"):
        out = subprocess.run([sys.executable, __file__, "--side", str(a.side), "--steps", str(a.steps),
                              "--threads", str(a.threads), "--kind", kind], check=True, capture_output=True, text=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        best[kind].append(r["step_s"])
        grow[kind] = max(grow.get(kind, 0.0), r["alloc_gb"])
    for kind, ts in best.items():
        print(f"{kind:8s} step {min(ts) * 1e3:8.1f} ms (medians: "
              f"{', '.join(f'{x * 1e3:.1f}' for x in ts)}), a step allocates {grow[kind]:.2f} GB")
    for kind in ("foreach", "fused"):
        final[kind] = run(kind, a.side, a.steps)[1]
    print(f"fused / foreach: {min(best['fused']) / min(best['foreach']):.3f}x")
    diff = max((x - y).abs().max().item() for x, y in zip(final["foreach"], final["fused"]))
    print(f"largest parameter difference after {a.steps} steps: {diff:.3g}")


if __name__ == "__main__":
    main()
