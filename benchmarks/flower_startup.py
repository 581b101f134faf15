"""Where a Flower deployment's start-up goes: base station up, rovers connected, round 1 sent.

    python benchmarks/flower_startup.py [--repeats 2] [--modes warm cold]

A 4-rover loopback run of one short round (the small network, 1 epoch, 64² maps), started
the way an operator starts it: ``fedmap base-station`` logic in this process, four
``fedmap rover`` processes once it is ready. Printed per mode and repeat:

- *base ready*: SuperLink start to the run submitted (``ready``);
- *rovers in*: ready to every rover connected and round 1 sent;
- *start-up*: the sum, as in ``benchmarks/flower_vs_inprocess.py``;
- *round 1*: round 1 sent to aggregated.

and, measured alone, what each process imports before it can work (CPU seconds of
``python -c 'import M'``). All processes share one 2-core machine here; on a real team each
rover has its own CPU, so its start-up is the import times of its own processes only.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fedmap.explore import explore
from fedmap.flower.launch import Processes, flower_env, free_port, run_base_station
from fedmap.maps.io import save_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.pipeline import PipelineConfig

IMPORTS = {
    "`fedmap rover` (the supervising CLI)": "fedmap.cli",
    "one cold ClientApp (a warm server forks from the rover: ~0.1 s)": "fedmap.flower.snapshot.client",
    "SuperNode (fedmap.flower.supernode)": "fedmap.flower.supernode",
}


def import_cpu(module: str) -> float:
    """CPU seconds (user + system) of a fresh Python importing ``module``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", f"import {module}"], check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def one_run(tmp: Path, warm: bool) -> dict[str, float]:
    truth = load_truth(TerrainSource(terrain="mars", size=64), seed=0)
    maps = explore(truth, 4, "quadrants", seed=0, sensor_radius=PipelineConfig().explore.sensor_radius)
    for k, m in enumerate(maps):
        save_map(m, tmp / f"local{k}.npy")
    port = free_port()
    run = {"net": "small", "init": "random", "epochs": 1, "seed": 0, "rovers": 4, "min-rovers": 4, "rounds": 1,
           "deadline": 300.0, "connect-timeout": 300.0, "pairs": 5, "out": str(tmp / "out")}
    marks: dict[str, float] = {}

    def on_ready(rovers: Processes) -> None:
        marks["ready"] = time.perf_counter()
        for k in range(4):
            argv = [sys.executable, "-m", "fedmap", "rover", "--superlink", f"127.0.0.1:{port}", "--partition-id",
                    str(k), "--map", str(tmp / f"local{k}.npy"), "--warm" if warm else "--cold"]
            rovers.start(f"rover{k}", argv, env=flower_env(tmp / f"home{k}"), log=tmp / f"rover{k}.log")

    def on_status(st: dict) -> None:
        if st.get("state") == "running" and st.get("round") == 1 and "sent" not in marks:
            marks["sent"] = time.perf_counter()
        if st.get("saved") and "aggregated" not in marks:
            marks["aggregated"] = time.perf_counter()

    t0 = time.perf_counter()
    with Processes() as rovers:
        run_base_station(run, host="127.0.0.1", port=port, on_ready=lambda: on_ready(rovers), on_status=on_status)
    end = time.perf_counter()
    return {"base ready": marks["ready"] - t0, "rovers in": marks["sent"] - marks["ready"],
            "start-up": marks["sent"] - t0, "round 1": marks.get("aggregated", end) - marks["sent"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--modes", nargs="+", default=["warm", "cold"], choices=["warm", "cold"])
    args = ap.parse_args()
    print("import cost, CPU seconds of a fresh Python (median of 3):")
    for what, module in IMPORTS.items():
        print(f"  {what:64s} {statistics.median(import_cpu(module) for _ in range(3)):5.2f} s")
    for mode in args.modes:
        rows = []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory(prefix="fedmap-startup-") as tmp:
                rows.append(one_run(Path(tmp), warm=mode == "warm"))
        print(f"{mode}: " + ", ".join(f"{k} {statistics.median(r[k] for r in rows):.1f} s" for k in rows[0])
              + f" (median of {len(rows)})")


if __name__ == "__main__":
    main()
