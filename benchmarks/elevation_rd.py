"""Rate-distortion of sharing an elevation layer on six terrains: the built-in mars, moon
and ice, and ``../shared/data``'s Gale 1 m, Hadley Rille and Columbia Glacier DEMs, every
one at 128² (:mod:`fedmap.experiments.elevation`).

    python benchmarks/elevation_rd.py [--out benchmarks/results/elevation_rd] [--pairs 75]

Prints, per terrain, the fewest bytes at which each codec's re-derived classes reach path
F1 >= 0.9 and the codec that needs the fewest, then the neural / JPEG XL (matched RMSE) and
neural+residual / LERC (matched max error) ratios; writes ``elevation.json``, ``report.md``
and ``rd_elevation.png``. The same as ``fedmap bandwidth --layer elevation --data
../shared/data`` (75 path pairs, seed 0).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from fedmap.experiments.elevation import FAMILIES, elevation_markdown, elevation_rd, plot_rd, reach_rows, terrain_sources

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/elevation_rd")
    ap.add_argument("--pairs", type=int, default=75, help="A* start/goal pairs of the path F1 (the CLI's default)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    report = elevation_rd(terrain_sources(str(args.data)), pairs=args.pairs,
                          on_point=lambda what: print(what, flush=True))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "elevation.json").write_text(json.dumps(report, indent=1))
    (args.out / "report.md").write_text(elevation_markdown(report))
    (args.out / "rd_elevation.png").write_bytes(plot_rd(report))
    print("bytes to path F1 >= 0.9:", "  ".join(f"{f:>15s}" for f in (*FAMILIES, "wins")))
    for row in reach_rows(report):
        print(f"{row[0]:24s}", "  ".join(f"{c:>15s}" for c in row[1:]))
    for name, sm in report["summary"].items():
        jxl, lerc = sm["best_neural_vs_jxl"], sm["best_neural_residual_vs_lerc"]
        print(f"{name:10s} neural/JPEG XL {'-' if jxl is None else f'{jxl:.2f}'}   "
              f"neural+residual/LERC {'-' if lerc is None else f'{lerc:.2f}'}")
    print(f"wall time {time.perf_counter() - t0:.1f} s; outputs in {args.out}")


if __name__ == "__main__":
    main()
