"""Wall time of the default mission (built-in mars 128², 4 rovers, 150 steps, a sync every
10 steps, strategies none, raw, fedmap, central) and, with ``--paper``, of the ``paper``
strategy on the same mission; per strategy and in total, with the load average (the
machine is shared: a loaded machine is slower, and the figures say so).

    python benchmarks/mission_timing.py [--paper] [--out benchmarks/results/mission_timing]

Prints a table and writes ``timing.json`` in ``--out``. The requirement it checks: the
default mission finishes in under 2 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

from fedmap._util import atomic_write_bytes, to_json
from fedmap.maps.sources import load_truth
from fedmap.mission import load_mission, run_mission

LIMIT_S = 120.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paper", action="store_true", help="also time the paper strategy (Fourier MLP + FedAvg)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/mission_timing"))
    args = ap.parse_args()
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    cfg, source, _ = load_mission()
    truth = load_truth(source, seed=cfg.seed)
    result = run_mission(cfg, truth)
    default_s = time.perf_counter() - t0
    rows = {name: run.seconds for name, run in result.runs.items()}
    paper_s = None
    if args.paper:
        pcfg, _, _ = load_mission(mission={"strategies": ["paper"]})
        t1 = time.perf_counter()
        paper = run_mission(pcfg, truth)
        paper_s = time.perf_counter() - t1
        rows["paper"] = paper.runs["paper"].seconds
    out = {
        "mission": {"terrain": source.label, "size": truth.shape[0], "rovers": cfg.rovers, "steps": cfg.steps,
                    "sync_every": cfg.sync_every, "strategies": list(cfg.strategies)},
        "torch_threads": torch.get_num_threads(), "cpus": os.cpu_count(),
        "load_average_before": load_before, "load_average_after": os.getloadavg(),
        "default_mission_s": default_s, "limit_s": LIMIT_S, "within_limit": default_s < LIMIT_S,
        "per_strategy_s": rows, "paper_s": paper_s,
        "summaries": {n: r.summary.to_dict() for n, r in result.runs.items()},
    }
    print(f"default mission ({source.label} {truth.shape[0]}², {cfg.rovers} rovers, {cfg.steps} steps, "
          f"{len(cfg.sync_steps)} syncs), load average before {load_before[0]:.2f}:")
    for name, s in rows.items():
        print(f"  {name:8s} {s:7.1f} s")
    print(f"  {'total':8s} {default_s:7.1f} s (default strategies; limit {LIMIT_S:.0f} s: "
          f"{'ok' if default_s < LIMIT_S else 'OVER'})")
    if paper_s is not None:
        print(f"  paper strategy alone: {paper_s:.1f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(args.out / "timing.json", to_json(out).encode())
    print(f"wrote {args.out / 'timing.json'}")


if __name__ == "__main__":
    main()
    raise SystemExit(0)
