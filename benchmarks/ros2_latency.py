"""The latency from a map on a rover's ``/map`` to the team map on ``/fedmap/team_map``,
and the CPU and memory of a ``fedmap node rover --ros2`` process.

    python benchmarks/ros2_latency.py [--maps 10] [--step-seconds 0.05]

On loopback, in a ROS 2 domain confined to this machine: ``fedmap node base`` (its own
process) runs a raw mission over Zenoh with four ``fedmap node rover`` processes, every node
on its own clock (``--step-seconds``: a step every that many seconds, a sync every
``sync_every`` steps); rover 0 has ``--ros2``. This process plays rover 0's mapping stack:
every second it publishes on ``/map`` a map with a new disc of cells observed (cells no
rover of the team has observed yet: the team map holds none of them), and watches
``/fedmap/team_map`` for the first team map that holds them. The latency is the time between
the two; it is bounded below by the time to the rover's next sync (the rover sends its new
cells at its sync, the base answers at its next round), so it is given beside the sync period.
The rover node's CPU time and peak RSS are read from ``/proc`` at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fedmap.flower.launch import free_port
from fedmap.maps import ros2dds
from fedmap.maps.grid import UNKNOWN
from fedmap.mission.settings import load_mission, mission_toml
from fedmap.mission.sim import mission_terrain

OUT = Path(__file__).resolve().parent / "results" / "ros2_latency"
DOMAIN = 120


def cpu_rss(pid: int) -> tuple[float, float]:
    """CPU seconds (user + system) and peak RSS (MB) of process ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks
    peak = next(int(ln.split()[1]) for ln in Path(f"/proc/{pid}/status").read_text().splitlines()
                if ln.startswith("VmHWM:")) / 1024
    return cpu, peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", type=int, default=10)
    ap.add_argument("--step-seconds", type=float, default=0.05)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    steps = int((a.maps + 4) / a.step_seconds)
    config, source, resolved = load_mission(overrides=[{"mission": {"steps": steps, "strategies": ["raw"]},
                                                        "terrain": {"size": 256}, "link": {"loss": 0.0}}])
    truth, *_ = mission_terrain(config, source)
    rows, cols = np.indices(truth.shape)
    rng = np.random.default_rng(0)
    centres = [(int(rng.integers(6, 250)), int(rng.integers(6, 250))) for _ in range(400)]
    dp = ros2dds.participant(DOMAIN, loopback=True)
    pub = ros2dds.MapPublisher(dp, "/map", resolution=truth.pixel_size)
    team = ros2dds.MapSubscriber(dp, "/fedmap/team_map")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    port = free_port()
    node = [sys.executable, "-m", "fedmap", "--quiet", "node"]
    latencies: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "mission.toml").write_text(mission_toml(resolved))
        observed = np.full(truth.shape, UNKNOWN, np.uint8)
        pub.publish(observed, time.time_ns())  # an empty map first: the node joins on it
        rovers = [subprocess.Popen([*node, "rover", "--rover", str(k), "--connect", f"127.0.0.1:{port}",
                                    "--team", "lat", "--state", f"{tmp}/rover{k}",
                                    *(["--ros2", "--domain", str(DOMAIN), "--ros2-loopback", "--first-map", "30"]
                                      if k == 0 else [])], env=env, stdout=subprocess.DEVNULL) for k in range(4)]
        base = subprocess.Popen([*node, "base", f"{tmp}/mission.toml", "--listen", f"127.0.0.1:{port}", "--team",
                                 "lat", "--out", f"{tmp}/out", "--step-seconds", str(a.step_seconds)], env=env,
                                stdout=subprocess.DEVNULL)
        try:
            while team.poll() is None:  # the mission has started: rover 0 answered its first order
                time.sleep(0.01)
            skipped = 0
            for _ in range(a.maps):
                latest = team.poll()  # a disc nobody in the team has observed yet (so its cells are news)
                known = latest.classes != UNKNOWN if latest is not None else np.zeros(truth.shape, bool)
                for cy, cx in centres:
                    disc = (rows - cy) ** 2 + (cols - cx) ** 2 <= 25
                    if not known[disc].any():
                        break
                else:
                    skipped += 1
                    continue
                observed = np.where(disc, truth.classes, observed).astype(np.uint8)
                t0 = time.perf_counter()
                pub.publish(observed, time.time_ns())
                while True:
                    grid = team.poll()
                    if grid is not None and (grid.classes[disc] != UNKNOWN).all():
                        latencies.append(time.perf_counter() - t0)
                        break
                    if time.perf_counter() - t0 > 30:
                        raise SystemExit("error: no team map held the new cells within 30 s")
                    time.sleep(0.002)
                time.sleep(max(0.0, 1.0 - (time.perf_counter() - t0)))
            cpu, peak = cpu_rss(rovers[0].pid)
            base.wait(timeout=600)
        finally:
            for p in (*rovers, base):
                if p.poll() is None:
                    p.kill()
    sync_s = config.sync_every * a.step_seconds
    cpu_name = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                     if ln.startswith("model name")), "")
    result = {"cpu": cpu_name, "maps": a.maps, "step_seconds": a.step_seconds, "sync_period_s": sync_s,
              "latency_median_s": round(statistics.median(latencies), 3),
              "latency_max_s": round(max(latencies), 3), "latencies_s": [round(x, 3) for x in latencies],
              "rover_cpu_s": round(cpu, 2), "rover_peak_rss_mb": round(peak, 1),
              "skipped": skipped}
    print(json.dumps(result, indent=1))
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "results.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
