"""Wall time of a 4-rover one-round run via Flower (real processes on loopback) vs in process,
and the bytes each rover sends and receives per round.

    python benchmarks/flower_vs_inprocess.py [--net paper] [--size 64] [--epochs 20]

Flower's time is from starting the SuperLink to the base station's outputs on disk
(SuperLink + 4 SuperNodes start, ``flwr run``, one ClientApp process per rover and
message, the final broadcast, render/refine/evaluate); the round alone (push of the
train messages to aggregation) is printed too. The in-process time is
``run_federation`` alone plus the same render/refine/evaluate.
"""

from __future__ import annotations

import argparse
import json
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
    args = ap.parse_args()
    torch.set_num_threads(2)
    run = {"net": args.net, "init": "random", "epochs": args.epochs, "seed": args.seed, "rovers": 4, "min-rovers": 4,
           "deadline": 600.0, "connect-timeout": 300.0, "pairs": 75}
    pc = PipelineConfig(terrain="mars", size=args.size, seed=args.seed)
    truth = load_truth(TerrainSource(terrain="mars", size=args.size), seed=args.seed)
    maps = explore(truth, 4, "quadrants", seed=args.seed, sensor_radius=pc.sensor_radius)

    t = time.perf_counter()
    net = preset(args.net, args.size)
    fed = run_federation(get_weights(build_model(net, seed=args.seed)), net, maps,
                         RunSettings.from_run_config(run).federation)
    model = build_model(net)
    set_weights(model, fed.weights)
    classes = classes_from_rgb(render(model, args.size, args.size))
    psnr = score_map(truth.classes, classes, pairs=pc.eval_pairs, seed=pc.seed).psnr
    score_map(truth.classes, refine(classes, RefineConfig()), pairs=pc.eval_pairs, seed=pc.seed)
    in_process_s = time.perf_counter() - t

    with tempfile.TemporaryDirectory(prefix="fedmap-bench-") as tmp:
        tmp = Path(tmp)
        save_map(truth, tmp / "truth.npy")
        for k, m in enumerate(maps):
            save_map(m, tmp / f"local{k}.npy")
        port, out = free_port(), tmp / "out"

        def start_rovers(procs: Processes) -> None:
            for k in range(4):
                argv = [sys.executable, "-m", "fedmap", "rover", "--superlink", f"127.0.0.1:{port}",
                        "--partition-id", str(k), "--map", str(tmp / f"local{k}.npy"), "--port", str(free_port())]
                procs.start(f"rover{k}", argv, env=flower_env(tmp / f"home{k}"), log=tmp / f"rover{k}.log")

        t = time.perf_counter()
        with Processes() as rovers:
            run_base_station({**run, "out": str(out), "truth": str(tmp / "truth.npy")}, host="127.0.0.1", port=port,
                             on_ready=lambda: start_rovers(rovers))
        flower_s = time.perf_counter() - t
        m = json.loads((out / "metrics.json").read_text())
    rnd = m["rounds"][0]
    print(f"4 rovers, 1 round, {args.net} net, mars {args.size}x{args.size}, {args.epochs} local epochs, fp32 payloads")
    print(f"in process : {in_process_s:7.1f} s  (run_federation + render/refine/evaluate)")
    print(f"via Flower : {flower_s:7.1f} s  (SuperLink + 4 SuperNodes + flwr run + outputs); "
          f"the round itself {rnd['seconds']:.1f} s")
    for k in sorted(rnd["uplink_bytes"], key=int):
        print(f"rover {k}: uplink {rnd['uplink_bytes'][k]:,} B (Flower counts {rnd['flower_uplink_bytes'][k]:,} B), "
              f"downlink {rnd['downlink_bytes'][k]:,} B (Flower {rnd['flower_downlink_bytes'][k]:,} B)")
    print(f"global map PSNR: {m['global']['psnr']:.3f} dB via Flower, {psnr:.3f} dB in process")


if __name__ == "__main__":
    main()
