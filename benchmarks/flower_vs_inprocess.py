"""Where a Flower round's time goes: a 4-rover run via Flower (real processes on loopback)
vs in process, with warm rovers (default) and cold ones, and the bytes per rover.

    python benchmarks/flower_vs_inprocess.py [--net paper] [--size 64] [--epochs 20] [--rounds 2]
                                             [--modes warm cold]

Printed per mode: *start-up* (SuperLink start to every rover connected and round 1 sent),
each round's seconds as the base measures it (train messages sent to aggregation; round 1
also includes every rover building its initial model), the total from SuperLink start to
outputs on disk, and the ratio of the steady rounds (2..R) to the in-process rounds. The
cost a cold ClientApp pays per message before it trains (a new Python importing flwr,
torch and fedmap) is measured on its own. ``warm``: each rover's ClientApp processes are
forked from one process that imported all that once (:mod:`fedmap.flower.warm`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from fedmap.evaluation.scores import score_map
from fedmap.explore import explore
from fedmap.federation.runner import run_federation
from fedmap.flower.launch import Processes, flower_env, free_port, run_base_station
from fedmap.flower.settings import RunSettings
from fedmap.maps.grid import classes_from_rgb
from fedmap.maps.io import save_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.nets.model import build_model, get_weights, preset, render, set_weights
from fedmap.pipeline import PipelineConfig
from fedmap.refine import RefineConfig, refine


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--net", default="paper")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--modes", nargs="+", default=["warm", "cold"], choices=["warm", "cold"])
    args = ap.parse_args()
    torch.set_num_threads(2)
    run = {"net": args.net, "init": "random", "epochs": args.epochs, "seed": args.seed, "rovers": 4, "min-rovers": 4,
           "rounds": args.rounds,
           "deadline": 600.0, "connect-timeout": 300.0, "pairs": 75}
    pc = PipelineConfig(terrain=TerrainSource(terrain="mars", size=args.size), seed=args.seed)
    truth = load_truth(TerrainSource(terrain="mars", size=args.size), seed=args.seed)
    maps = explore(truth, 4, "quadrants", seed=args.seed, sensor_radius=pc.explore.sensor_radius)

    t = time.perf_counter()
    net = preset(args.net, args.size)
    fed = run_federation(get_weights(build_model(net, seed=args.seed)), net, maps,
                         RunSettings.from_run_config(run).federation)
    model = build_model(net)
    set_weights(model, fed.weights)
    classes = classes_from_rgb(render(model, args.size, args.size))
    psnr = score_map(truth.classes, classes, pairs=pc.evaluate.pairs, seed=pc.seed).psnr
    score_map(truth.classes, refine(classes, RefineConfig()), pairs=pc.evaluate.pairs, seed=pc.seed)
    in_process_s = time.perf_counter() - t

    ref_rounds = [r.seconds for r in fed.history]
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import fedmap.flower.snapshot.client"], check=True)
    cold_import_s = time.perf_counter() - t
    print(f"4 rovers, {args.rounds} round(s), {args.net} net, mars {args.size}x{args.size}, {args.epochs} local epochs, "
          f"fp32 payloads")
    print(f"in process : {in_process_s:7.1f} s  (run_federation + render/refine/evaluate); rounds "
          + ", ".join(f"{x:.1f}" for x in ref_rounds) + " s")
    print(f"cold ClientApp start (python -c 'import fedmap.flower.snapshot.client'): {cold_import_s:.1f} s per message")
    for mode in args.modes:
        m, flower_s, startup_s = _flower(run, truth, maps, mode, args.size)
        rounds = [r["seconds"] for r in m["rounds"]]
        steady = sum(rounds[1:]) / sum(ref_rounds[1:]) if len(rounds) > 1 else rounds[0] / ref_rounds[0]
        print(f"via Flower ({mode}): start-up {startup_s:.1f} s; rounds " + ", ".join(f"{x:.1f}" for x in rounds)
              + f" s; total {flower_s:.1f} s; steady round / in-process round = {steady:.2f}x")
        rnd = m["rounds"][-1]
        for k in sorted(rnd["uplink_bytes"], key=int):
            print(f"  rover {k}: uplink {rnd['uplink_bytes'][k]:,} B (Flower counts {rnd['flower_uplink_bytes'][k]:,} B)"
                  f", downlink {rnd['downlink_bytes'][k]:,} B (Flower {rnd['flower_downlink_bytes'][k]:,} B)")
        print(f"  global map PSNR: {m['global']['psnr']:.3f} dB via Flower, {psnr:.3f} dB in process")


def _flower(run: dict, truth, maps, mode: str, size: int) -> tuple[dict, float, float]:
    """One Flower run: metrics.json, total seconds, start-up seconds (to round 1 sent)."""
    with tempfile.TemporaryDirectory(prefix="fedmap-bench-") as tmp:
        tmp = Path(tmp)
        save_map(truth, tmp / "truth.npy")
        for k, m in enumerate(maps):
            save_map(m, tmp / f"local{k}.npy")
        port, out = free_port(), tmp / "out"

        def start_rovers(procs: Processes) -> None:
            for k in range(4):
                argv = [sys.executable, "-m", "fedmap", "rover", "--superlink", f"127.0.0.1:{port}",
                        "--partition-id", str(k), "--map", str(tmp / f"local{k}.npy"), "--port", str(free_port()),
                        f"--{mode}"]
                procs.start(f"rover{k}", argv, env=flower_env(tmp / f"home{k}"), log=tmp / f"rover{k}.log")

        started: list[float] = []

        def on_status(st: dict) -> None:
            if st["state"] == "running" and st.get("round") == 1 and not started:
                started.append(time.perf_counter())

        t = time.perf_counter()
        with Processes() as rovers:
            run_base_station({**run, "out": str(out), "truth": str(tmp / "truth.npy")}, host="127.0.0.1", port=port,
                             on_ready=lambda: start_rovers(rovers), on_status=on_status)
        flower_s = time.perf_counter() - t
        m = json.loads((out / "metrics.json").read_text())
    return m, flower_s, (started[0] - t) if started else float("nan")


if __name__ == "__main__":
    main()
