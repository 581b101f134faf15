"""The Foxglove layout's panels drawn from a recording's own data (no viewer runs here).

Records a mission (``fedmap mission --record``), reads the MCAP back with the project's
reader (``fedmap.mission.outputs.recording.read_recording`` / ``decode`` / ``grid_arrays``: the
``mcap`` package and the Foxglove schemas stored in the file), and draws what the layout in
``docs/foxglove_layout.json`` shows at one step: the truth, one rover's belief and the
global map with every rover's pose and trail (``/<s>/poses``), and the scores plot
(``/<s>/scores``) of every strategy over the mission.

    python benchmarks/recording_panels.py                       # default mission, 150 steps
    python benchmarks/recording_panels.py --mcap run.mcap --step 100 --out panels.png
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from fedmap.maps.grid import PALETTE
from fedmap.mission.outputs.recording import decode, grid_arrays, read_recording

ROOT = Path(__file__).resolve().parents[1]


def _rgb(classes: np.ndarray) -> np.ndarray:
    return np.asarray(PALETTE, dtype=float)[classes]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mcap", type=Path, help="an existing recording (default: record the default mission)")
    ap.add_argument("--strategy", default="predictive")
    ap.add_argument("--step", type=int, default=100)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "robotics_recording_panels.png")
    args = ap.parse_args()
    path = args.mcap
    if path is None:
        tmp = Path(tempfile.mkdtemp())
        path = tmp / "mission.mcap"
        subprocess.run([sys.executable, "-m", "fedmap", "mission", "--strategies", "none,raw,predictive,central",
                        "--no-animation", "--record", str(path), "-o", str(tmp / "out")], check=True)
    messages, schemas = read_recording(path)
    s, t_ns = args.strategy, args.step * 1_000_000_000

    def last(topic: str) -> dict:  # the newest message on a topic at or before the step
        got = [m for m in messages if m.topic == topic and m.log_time <= t_ns]
        if not got:
            raise SystemExit(f"no message on {topic} by step {args.step}")
        return decode(max(got, key=lambda m: m.log_time), schemas)

    truth = grid_arrays(last("/truth"))["classes"]
    belief = grid_arrays(last(f"/{s}/belief/0"))["classes"]
    glob = grid_arrays(last(f"/{s}/global_map"))["classes"]
    poses = [m for m in messages if m.topic == f"/{s}/poses" and m.log_time <= t_ns]
    track = [[(p["position"]["x"], p["position"]["y"]) for p in decode(m, schemas)["poses"]] for m in poses]
    px = float(last("/truth")["cell_size"]["x"])
    scores: dict[str, list[tuple[float, float, float]]] = {}
    for m in messages:
        if m.topic.endswith("/scores"):
            d = decode(m, schemas)
            scores.setdefault(m.topic.split("/")[1], []).append((m.log_time / 1e9, d["coverage"], d["accuracy_mean"]))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 4.2))
    h, w = truth.shape
    extent = (0, w * px, 0, h * px)  # the map frame: x east, y north, metres from the lower-left corner
    for ax, grid, title in ((axes[0], truth, "/truth"), (axes[1], belief, f"/{s}/belief/0"),
                            (axes[2], glob, f"/{s}/global_map + /{s}/poses")):
        ax.imshow(_rgb(grid), extent=extent, interpolation="nearest")
        ax.set(title=title, xlabel="x (m, map frame)")
    axes[0].set_ylabel("y (m)")
    for k in range(len(track[0])):
        xy = np.array([p[k] for p in track])
        axes[2].plot(xy[:, 0], xy[:, 1], lw=1.2, color=f"C{k}")
        axes[2].scatter(*xy[-1], s=30, color=f"C{k}", edgecolors="k", zorder=3)
    for i, (name, rows) in enumerate(scores.items()):
        r = np.array(rows)
        axes[3].plot(r[:, 0], r[:, 2], label=f"{name}", color=f"C{i}")
    axes[3].axvline(args.step, color="0.6", ls="--", lw=0.8)
    axes[3].set(title="/<strategy>/scores: accuracy_mean", xlabel="mission clock (s = steps)", ylim=(0, 1))
    axes[3].legend()
    fig.suptitle(f"{path.name} at step {args.step}: the layout's panels drawn from the recording", y=1.02)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100, bbox_inches="tight")
    print(f"{args.out}: {len(messages):,} messages, {path.stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
