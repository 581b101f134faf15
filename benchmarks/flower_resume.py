"""A base station killed with ``kill -9`` after round 1, resumed with ``--resume``: real
processes on loopback, the commands as an operator types them.

    python benchmarks/flower_resume.py [--rounds 3] [--epochs 30]

Two rovers (``fedmap rover``) keep running throughout. The script prints whether the port
was free after the kill, how the rovers reconnected, the wall times, and the largest
difference between the resumed run's global model and an uninterrupted in-process run
with the same settings (FedAdam, ``update-int8`` downlink: the server moments and the
downlink residual must both survive the crash for this to be 0).
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fedmap.explore import explore
from fedmap.federation.runner import run_federation
from fedmap.flower.launch import Processes, flower_env, free_port
from fedmap.flower.settings import RunSettings
from fedmap.flower.task import initial_weights
from fedmap.maps.io import save_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.nets.model import get_weights, load_model, preset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--epochs", type=int, default=30)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="fedmap-resume-") as tmp_s:
        tmp = Path(tmp_s)
        truth = load_truth(TerrainSource(terrain="mars", size=64), seed=1)
        maps = explore(truth, 2, "strips", seed=1)
        save_map(truth, tmp / "truth.npy")
        for k, m in enumerate(maps):
            save_map(m, tmp / f"local{k}.npy")
        port, out = free_port(), tmp / "out"
        fedmap = [sys.executable, "-m", "fedmap"]
        common = ["--port", str(port), "--host", "127.0.0.1"]
        run = ["--rovers", "2", "--min-rovers", "2", "--rounds", str(args.rounds), "--net", "small", "--init", "random",
               "--local-epochs", str(args.epochs), "--aggregator", "fedadam", "--downlink", "update-int8",
               "--truth", str(tmp / "truth.npy"), "--pairs", "5", "-o", str(out)]
        env = flower_env(tmp / "home")
        t0 = time.perf_counter()
        with Processes() as procs:
            base = procs.start("base", fedmap + ["base-station", *run, *common], env=env, log=tmp / "base1.log")
            time.sleep(5)
            for k in range(2):
                procs.start(f"rover{k}", fedmap + ["rover", "--superlink", f"127.0.0.1:{port}", "--partition-id", str(k),
                                                   "--map", str(tmp / f"local{k}.npy"), "--max-wait", "200"],
                            env=flower_env(tmp / f"home{k}"), log=tmp / f"rover{k}.log")
            ckpt = out.with_name("out.run") / "checkpoint_round0001"
            t_end = time.monotonic() + 600
            while not ckpt.is_dir() and time.monotonic() < t_end:
                time.sleep(0.5)
            base.send_signal(signal.SIGKILL)  # the base alone: its SuperLink must go with it
            base.wait()
            killed_at = time.perf_counter() - t0
            time.sleep(2)
            with socket.socket() as s:
                free = s.connect_ex(("127.0.0.1", port)) != 0
            t1 = time.perf_counter()
            r = subprocess.run(fedmap + ["base-station", "--resume", str(out), *common], env=env, capture_output=True,
                               text=True, timeout=1800)
            resumed_s = time.perf_counter() - t1
            codes = [procs.procs[f"rover{k}"].wait(timeout=300) for k in range(2)]
        rover_lines = [ln for k in range(2) for ln in (tmp / f"rover{k}.log").read_text().splitlines()
                       if ln.startswith("rover ")]
        settings = RunSettings.from_run_config({"rovers": 2, "min-rovers": 2, "rounds": args.rounds, "net": "small",
                                                "init": "random", "epochs": args.epochs, "aggregator": "fedadam",
                                                "downlink": "update-int8"})
        ref = run_federation(initial_weights(settings, 64), preset("small", 64), maps, settings.federation)
        got = get_weights(load_model(out / "global_model.safetensors")) if r.returncode == 0 else None
    print(f"base killed (SIGKILL) after round 1 at {killed_at:.1f} s; port {port} free afterwards: {free}")
    print(f"fedmap base-station --resume: exit {r.returncode} in {resumed_s:.1f} s; rovers exited {codes}")
    for ln in rover_lines:
        print("  " + ln)
    if got is not None:
        diff = max(float(np.abs(got[k] - ref.weights[k]).max()) for k in got)
        print(f"max |resumed - uninterrupted in-process| over all weights: {diff:g}")
    else:
        print(r.stderr.strip().splitlines()[-1:])


if __name__ == "__main__":
    main()
