"""Bits per new cell on the uplink streams of real missions: generic codecs, the
``context`` codec per message (``raw``), and the ``predictive`` coder with each of its
parts switched off (:mod:`fedmap.experiments.cellstreams`).

    python benchmarks/cell_streams.py [--missions default examples/mission_gale.toml ...]
        [--out benchmarks/results/cell_streams]

Prints one table per mission and writes ``cell_streams.json`` and ``cell_streams.md``.
Gale and Hadley read ``../shared/data`` (not shipped with fedmap).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from fedmap.experiments.cellstreams import cell_stream_report, markdown
from fedmap.mission import load_mission, mission_terrain

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--missions", nargs="+", default=["default", "examples/mission_gale.toml",
                                                       "examples/mission_hadley.toml"])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/cell_streams")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results, md = {}, []
    for name in args.missions:
        t0 = time.perf_counter()
        config, source, _ = load_mission(None if name == "default" else ROOT / name)
        truth, elevation, prior, _ = mission_terrain(config, source)
        report = cell_stream_report(config, truth, elevation=elevation, prior=prior)
        title = f"{name} ({source.label}, {truth.shape[0]}x{truth.shape[1]}, {config.rovers} rovers, " \
                f"{config.steps} steps)"
        table = markdown(report, title)
        print(table)
        print(f"wall time {time.perf_counter() - t0:.1f} s\n", flush=True)
        results[name] = report
        md.append(table)
    (args.out / "cell_streams.json").write_text(json.dumps(results, indent=1))
    (args.out / "cell_streams.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
