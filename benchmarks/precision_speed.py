"""Training-step speed of the paper network per precision, against this CPU's matmul peaks.

    python benchmarks/precision_speed.py [--threads 2] [--sizes 128 256] [--steps 8] [--compile]

Prints, in one run:
- this machine's fp32 and bf16 matrix-multiply throughput (2048^3 products, best of 10);
- the paper network's full-grid Adam step (``fedmap.nets.training.fit``, the code every
  command runs) at each size for each implementation, each in a fresh process: ``fp32``
  and ``bf16`` (autocast matrix products, fp32 weights, loss and Adam), each with glibc's
  default allocator behaviour (``FEDMAP_MALLOC_TUNING=0``: the step before this change)
  and with fedmap's allocator setting (:func:`fedmap.nets.training.keep_freed_memory`);
  with ``--compile`` also ``torch.compile`` of the bf16 step, with its one-off compile time;
- achieved GFLOP/s of each step and its ratio to the matching matmul peak.

FLOPs of one step: forward 2*N*P_lin, backward 4*N*P_lin minus the first layer's input
gradient (2*N*256*256, not needed: the Fourier features are fixed), where N = H*W pixels
and P_lin = the linear layers' weights. BatchNorm, ReLU, sigmoid and Adam are not counted:
they are memory passes, which is exactly what the ratio to the peak exposes.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fedmap.maps.grid import GridMap
from fedmap.maps.terrain import generate_dem
from fedmap.maps.traversability import dem_to_traversability
from fedmap.nets.model import build_model, grid_coords
from fedmap.nets.training import TrainConfig, fit, native_bf16


def matmul_peak(dtype: torch.dtype, side: int = 2048, reps: int = 10) -> float:
    """Best-of-``reps`` GFLOP/s of a ``side``^3 matrix product in ``dtype``."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(side, side, generator=g).to(dtype), torch.randn(side, side, generator=g).to(dtype)
    a @ b  # warm-up
    best = float("inf")
    for _ in range(reps):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 2 * side**3 / best / 1e9


def step_flops(model: nn.Module, n_pixels: int) -> float:
    lins = [m for m in model.modules() if isinstance(m, nn.Linear)]
    p_lin = sum(m.weight.numel() for m in lins)
    return 6.0 * n_pixels * p_lin - 2.0 * n_pixels * lins[0].weight.numel()


def fit_step_seconds(grid: GridMap, precision: str, steps: int) -> float:
    """Median seconds per step of ``fit`` after its first step (which pays one-off setup)."""
    model = build_model(seed=0)
    stamps: list[float] = []
    fit(model, grid, TrainConfig(epochs=steps + 1, precision=precision), on_step=lambda s, _: stamps.append(
        time.perf_counter()))
    return statistics.median(np.diff(stamps).tolist())


def compiled_step_seconds(grid: GridMap, steps: int) -> tuple[float, float]:
    """(compile seconds, median step seconds) of ``torch.compile`` on the bf16 step."""
    model = build_model(seed=0)
    feats = model.features(grid_coords(*grid.shape)).detach().to(torch.bfloat16)
    target = torch.from_numpy(grid.to_rgb().reshape(-1, 3))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)

    def loss_fn(x: torch.Tensor) -> torch.Tensor:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = model.head(x)
        return ((out.float() - target) ** 2).mean()

    compiled = torch.compile(loss_fn)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        compiled(feats).backward()
        opt.step()

    t = time.perf_counter()
    step()
    first = time.perf_counter() - t
    ts = []
    for _ in range(steps):
        t = time.perf_counter()
        step()
        ts.append(time.perf_counter() - t)
    return first, statistics.median(ts)


def in_fresh_process(size: int, precision: str, steps: int, threads: int, tuned: bool) -> float:
    """:func:`fit_step_seconds` in a new interpreter, so allocator state never carries over."""
    env = {**os.environ, "FEDMAP_MALLOC_TUNING": "1" if tuned else "0"}
    here = str(Path(__file__).parent)
    code = (f"import json, sys, torch; torch.set_num_threads({threads}); sys.path.insert(0, {here!r}); "
            f"from precision_speed import _one; print(json.dumps(_one({size}, {precision!r}, {steps})))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    return float(json.loads(out.splitlines()[-1]))


def _one(size: int, precision: str, steps: int) -> float:
    return fit_step_seconds(dem_to_traversability(generate_dem("mars", size, seed=0)), precision, steps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--compile", action="store_true", help="also time torch.compile of the bf16 step")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    peaks = {"fp32": matmul_peak(torch.float32), "bf16": matmul_peak(torch.bfloat16)}
    print(f"torch {torch.__version__}, {args.threads} threads, native bf16: {native_bf16()}")
    print(f"matmul peak: fp32 {peaks['fp32']:.0f} GFLOP/s, bf16 {peaks['bf16']:.0f} GFLOP/s")
    print(f"{'size':>6} {'implementation':>26} {'ms/step':>8} {'GFLOP/s':>8} {'of peak':>8} {'vs fp32':>8}")
    for n in args.sizes:
        grid = dem_to_traversability(generate_dem("mars", n, seed=0))
        flops = step_flops(build_model(), n * n)
        rows = [(f"{p}{'' if tuned else ' (glibc default malloc)'}",
                 in_fresh_process(n, p, args.steps, args.threads, tuned), p)
                for p in ("fp32", "bf16") for tuned in (False, True)]
        if args.compile:
            compile_s, t = compiled_step_seconds(grid, args.steps)
            rows.append((f"bf16+compile ({compile_s:.0f} s compile)", t, "bf16"))
        base = rows[0][1]  # fp32 with the default allocator: the step before this change
        for name, t, peak in rows:
            gf = flops / t / 1e9
            print(f"{n:>4}^2 {name:>26} {t * 1e3:>8.0f} {gf:>8.0f} {gf / peaks[peak]:>7.0%} {base / t:>7.2f}x",
                  flush=True)


if __name__ == "__main__":
    main()
