"""Memory over a mission's steps: what one step's record holds, and the peak RSS of the
default mission (``raw``) at 1,000 and 10,000 steps, each in a fresh process.

    python benchmarks/mission_memory.py            # both (the 10,000 steps take a few minutes)
    python benchmarks/mission_memory.py --records  # only the bytes a step's record holds

Prints one line per figure; the figures behind ``fedmap.mission.sim.STEP_RECORD_BYTES``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))


def record_bytes() -> None:
    """Python-side bytes held per step (steps 200 to 600 of raw on a 48x48 maze), by team size."""
    from conftest import maze
    from fedmap.mission import LinkConfig, MissionConfig
    from fedmap.mission.sim import STEP_RECORD_BYTES, prepare_mission

    for rovers in (1, 3, 6):
        cfg = MissionConfig(rovers=rovers, steps=600, sync_every=10, sensor_radius=4.0, eval_pairs=12,
                            strategies=("raw",), link=LinkConfig(loss=0.1, seed=1))
        run = prepare_mission(cfg, maze(48, 3), frames=1).new_run("raw")
        seen: dict[int, int] = {}

        def on_step(name: str, t: int, coverage: float) -> None:
            if t in (200, 600):
                seen[t] = tracemalloc.get_traced_memory()[0]

        tracemalloc.start()
        run.run(on_step)
        tracemalloc.stop()
        bound = STEP_RECORD_BYTES[0] + STEP_RECORD_BYTES[1] * rovers
        print(f"{rovers} rover(s): {(seen[600] - seen[200]) / 400:,.0f} B a step (bound {bound:,} B)")


def peak_rss(steps: int) -> tuple[float, float]:
    """Peak RSS (MiB) and wall time (s) of `fedmap mission --steps N --strategies raw --no-animation`."""
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "fedmap", "--quiet", "mission", "--steps", str(steps),
                                 "--strategies", "raw", "--no-animation", "-o", str(Path(tmp) / "out")],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, status, usage = os.wait4(proc.pid, 0)
        if status != 0:
            raise SystemExit(f"fedmap mission --steps {steps} failed: {proc.stderr.read().decode()[-500:]}")
        return usage.ru_maxrss / 1024, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", action="store_true", help="only the bytes a step's record holds")
    args = ap.parse_args()
    record_bytes()
    if args.records:
        return
    peaks = {}
    for steps in (1000, 10000):
        peaks[steps], secs = peak_rss(steps)
        print(f"default mission, raw, {steps:,} steps: peak RSS {peaks[steps]:,.0f} MiB ({secs:.0f} s)")
    print(f"10,000 against 1,000 steps: {peaks[10000] / peaks[1000] - 1:+.1%}")


if __name__ == "__main__":
    main()
