"""How a mission's cost grows with the map and the team: built-in terrain at several sizes
and team sizes, a fixed number of steps, the chosen strategies; wall time per strategy,
time per step, peak RSS and the team's bytes, and the growth exponent of the time against
cells x agents (a least-squares fit in log-log).

    python benchmarks/mission_scaling.py [--sizes 128 256 512] [--agents 4 8] [--steps 100] [--steps-grow P]
        [--strategies none,raw,fedmap,central] [--out benchmarks/results/mission_scaling]

Each configuration runs in its own process, so its peak RSS is its own. Writes
``scaling.json`` and ``scaling.png`` (log-log) in ``--out`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def one(size: int, agents: int, steps: int, strategies: str, terrain: str, workers: int = 1) -> dict:
    """One configuration, in this process: the numbers of its row."""
    from fedmap.maps.sources import load_truth
    from fedmap.mission import load_mission, run_mission

    t0 = time.perf_counter()
    cfg, source, _ = load_mission(terrain={"kind": "builtin", "terrain": terrain}, size=size,
                                  mission={"rovers": agents, "steps": steps, "strategies": strategies})
    truth = load_truth(source, seed=cfg.seed)
    result = run_mission(cfg, truth, workers=workers)
    return {"size": size, "agents": agents, "steps": steps, "cells_x_agents": size * size * agents,
            "seconds": time.perf_counter() - t0,
            "per_strategy_s": {n: r.seconds for n, r in result.runs.items()},
            "per_step_ms": {n: 1000 * r.seconds / steps for n, r in result.runs.items()},
            "team_bytes": {n: r.summary.bytes_up + r.summary.bytes_down for n, r in result.runs.items()},
            "coverage": {n: r.summary.final_coverage for n, r in result.runs.items()},
            "workers": workers,  # strategies side by side in forked processes: the largest process's peak
            "peak_rss_mb": max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF,
                                                                             resource.RUSAGE_CHILDREN)) / 1024}


def fit_exponent(x: list[float], y: list[float]) -> float | None:
    """Slope of log(y) against log(x), least squares (None with fewer than two x values)."""
    if len(set(x)) < 2:
        return None
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def plot(rows: list[dict], names: list[str], exponents: dict, steps: int | str, terrain: str, path: Path) -> None:
    """Log-log: every configuration's time per strategy (marker: team size) and the fitted line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    x = np.array([r["cells_x_agents"] for r in rows], dtype=float)
    markers = dict(zip(sorted({r["agents"] for r in rows}), "o^sDv"))
    for i, n in enumerate(names):
        y = np.array([r["per_strategy_s"][n] for r in rows])
        for r, xi, yi in zip(rows, x, y):
            ax.loglog(xi, yi, markers[r["agents"]], color=f"C{i}", ms=5)
        e = exponents[n]
        if e is not None:
            b = np.polyfit(np.log(x), np.log(y), 1)[1]
            xs = np.array([x.min(), x.max()])
            ax.loglog(xs, np.exp(b) * xs ** e, "-", color=f"C{i}", lw=1, label=f"{n}: time ~ (cells x agents)^{e:.2f}")
    for a, m in markers.items():
        ax.plot([], [], m, color="gray", label=f"{a} agents")
    ax.set(xlabel="cells x agents", ylabel=f"wall time of {steps} steps, s",
           title=f"Mission cost vs map and team size (built-in {terrain}, 2 cores)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _steps_label(steps: int, grow: float, rows: list[dict]) -> int | str:
    """The plot's step count: a number, or how it grew with the map."""
    if not grow:
        return steps
    return f"{steps} x (side / {min(r['size'] for r in rows)})^{grow:g}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--agents", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--steps-grow", type=float, default=0.0, metavar="P",
                    help="steps grow with the map: --steps x (size / smallest size)^P (1: with the side, the "
                         "issue's comparison; 0: the same steps everywhere)")
    ap.add_argument("--strategies", default="none,raw,fedmap,central")
    # moon: at every size its map centre (the lander) opens onto most of the free ground;
    # built-in mars at 512² puts the lander in a free pocket of 101 cells, and the rovers stay in it
    ap.add_argument("--terrain", default="moon")
    ap.add_argument("--workers", type=int, default=1,
                    help="strategies side by side in this many processes (fedmap mission's default: one per core)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/mission_scaling"))
    ap.add_argument("--one", nargs=2, type=int, help=argparse.SUPPRESS)  # size agents: run one, print JSON
    ap.add_argument("--replot", action="store_true", help="Redraw scaling.png from --out's scaling.json")
    args = ap.parse_args()
    if args.replot:
        d = json.loads((args.out / "scaling.json").read_text())
        plot(d["rows"], d["strategies"], d["exponents"], _steps_label(d["steps"], d.get("steps_grow", 0.0), d["rows"]),
             d["terrain"], args.out / "scaling.png")
        return
    if args.one:
        print(json.dumps(one(args.one[0], args.one[1], args.steps, args.strategies, args.terrain, args.workers)))
        return
    rows = []
    load = os.getloadavg()[0]
    for size in args.sizes:
        steps = round(args.steps * (size / min(args.sizes)) ** args.steps_grow)
        for agents in args.agents:
            cmd = [sys.executable, __file__, "--one", str(size), str(agents), "--steps", str(steps),
                   "--strategies", args.strategies, "--terrain", args.terrain, "--workers", str(args.workers)]
            done = subprocess.run(cmd, capture_output=True, text=True, check=True)
            row = json.loads(done.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"{size:5d}² {agents:3d} agents {steps:4d} steps: {row['seconds']:7.1f} s, "
                  f"peak {row['peak_rss_mb']:6.0f} MB, "
                  f"coverage {max(row['coverage'].values()):.3f}; "
                  + ", ".join(f"{n} {s:.1f} s" for n, s in row["per_strategy_s"].items()), flush=True)
    names = list(rows[0]["per_strategy_s"])
    x = [r["cells_x_agents"] for r in rows]
    exponents = {n: fit_exponent(x, [r["per_strategy_s"][n] for r in rows]) for n in names}
    exponents["all"] = fit_exponent(x, [r["seconds"] for r in rows])
    print("growth exponent of the time against cells x agents: "
          + ", ".join(f"{n} {e:.2f}" for n, e in exponents.items() if e is not None))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scaling.json").write_text(json.dumps({"steps": args.steps, "steps_grow": args.steps_grow,
                                                       "terrain": args.terrain,
                                                       "strategies": names, "rows": rows,
                                                       "exponents": exponents, "load_average_before": load,
                                                       "cpus": os.cpu_count()}, indent=1))
    plot(rows, names, exponents, _steps_label(args.steps, args.steps_grow, rows), args.terrain, args.out / "scaling.png")
    print(f"wrote {args.out}/scaling.json and scaling.png")


if __name__ == "__main__":
    main()
