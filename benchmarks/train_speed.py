"""Per-step training time of the paper network: Linear (fedmap) vs Conv2d 1x1 (paper) layout.

    python benchmarks/train_speed.py [--threads 2] [--sizes 64 128 256]

One step = forward + backward + Adam on the full grid (the paper's setup). Prints the
median of several steps after warm-up, per layout and map size.
"""

import argparse
import statistics
import time

import torch
from torch import nn

from fedmap.maps.grid import FREE, GridMap
from fedmap.nets.model import build_model, grid_coords
from fedmap.nets.training import TrainConfig, fit


def conv_twin(model) -> nn.Sequential:
    mods = []
    for layer in model.mlp:
        if isinstance(layer, nn.Linear):
            mods.append(nn.Conv2d(layer.in_features, layer.out_features, 1))
        elif isinstance(layer, nn.BatchNorm1d):
            mods.append(nn.BatchNorm2d(layer.num_features, track_running_stats=False))
        else:
            mods.append(layer)
    return nn.Sequential(*mods)


def time_steps(step, n: int) -> float:
    step()  # warm-up
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        step()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--steps", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} threads; median seconds per full-grid Adam step")
    print(f"{'size':>6} {'Linear (fedmap)':>16} {'Conv2d 1x1':>12} {'speed-up':>9} {'fedmap.fit':>11}")
    for n in args.sizes:
        model = build_model(seed=0)
        feats = model.features(grid_coords(n, n)).detach()
        target = torch.rand(n * n, 3)
        opt = torch.optim.Adam(model.parameters(), 1e-3)

        def lin_step():
            opt.zero_grad()
            loss = ((torch.sigmoid(model.mlp(feats)) - target) ** 2).mean()
            loss.backward()
            opt.step()

        conv = conv_twin(model)
        img = feats.T.reshape(1, -1, n, n).contiguous()
        timg = target.T.reshape(1, 3, n, n)
        copt = torch.optim.Adam(conv.parameters(), 1e-3)

        def conv_step():
            copt.zero_grad()
            loss = ((torch.sigmoid(conv(img)) - timg) ** 2).mean()
            loss.backward()
            copt.step()

        tl, tc = time_steps(lin_step, args.steps), time_steps(conv_step, args.steps)
        grid = GridMap(torch.zeros(n, n, dtype=torch.uint8).numpy() + FREE)
        m2 = build_model(seed=0)
        t = time.perf_counter()
        fit(m2, grid, TrainConfig(epochs=args.steps))
        tf = (time.perf_counter() - t) / args.steps
        print(f"{n:>4}^2 {tl:>16.3f} {tc:>12.3f} {tc / tl:>8.1f}x {tf:>11.3f}", flush=True)


if __name__ == "__main__":
    main()
