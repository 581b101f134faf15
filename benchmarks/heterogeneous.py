"""Heterogeneous rover teams: different sensor radii, amounts of driving, overlapping regions.

    python benchmarks/heterogeneous.py [--size 128] [--terrain mars]

Runs fedmap's method (grid + coverage-aware FedAvg, int4 update uplink) and the paper's
method on built-in terrain for several team set-ups and prints federated vs centralised
(the same network trained on the union of what the team saw) quality. In traverse modes
the team does not see the whole map, so scores are against the full ground truth and
the centralised bound is the fair comparison.
"""

from __future__ import annotations

import argparse
import time

import torch

from fedmap.config import method_config
from fedmap.explore import explore
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.pipeline import run_pipeline

TEAMS = {
    "quadrants, no overlap": dict(mode="quadrants"),
    "quadrants, 8-cell overlap": dict(mode="quadrants", overlap=8),
    "traverse, radii 6/10/14/18": dict(mode="traverse", sensor_radius=[6.0, 10.0, 14.0, 18.0]),
    "traverse, radius 12, 2/4/8/12 waypoints": dict(mode="traverse", waypoints=[2, 4, 8, 12]),
}

def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--terrain", default="mars")
    ap.add_argument("--methods", nargs="+", default=["fedmap"])
    args = ap.parse_args()
    torch.set_num_threads(2)
    truth = load_truth(TerrainSource(terrain=args.terrain, size=args.size))
    print("| team | method | seen | federated PSNR / F1 | central PSNR / F1 | uplink B/rover | s |")
    print("|---|---|---|---|---|---|---|")
    for tname, team in TEAMS.items():
        for mname in args.methods:
            kw = dict(team)
            mode = kw.pop("mode")
            local = explore(truth, 4, mode, seed=0, **kw)
            seen = sum(m.known for m in local).clip(0, 1).mean()
            overrides = {"uplink": "fp16", "downlink": "fp16", "init": "random"} if mname == "paper" else {}
            cfg = method_config(mname, size=args.size, **overrides)
            t = time.perf_counter()
            r = run_pipeline(cfg, truth=truth, local_maps=local)
            g, c = r.global_scores, r.central_scores
            assert c is not None  # central is on in both presets
            fmt = lambda x: "inf" if x == float("inf") else f"{x:.1f}"  # noqa: E731
            print(f"| {tname} | {mname} | {seen:.0%} | {fmt(g.psnr)} / {g.path.f1:.2f} | "
                  f"{fmt(c.psnr)} / {c.path.f1:.2f} | {r.federation.total_bytes().uplink_per_agent_round:,.0f} | "
                  f"{time.perf_counter() - t:.0f} |", flush=True)


if __name__ == "__main__":
    main()
