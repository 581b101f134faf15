"""Federated fine-tuning of the map predictor across sites, leave one site out
(fedmap.training.predictorfed; issue 35, part 3).

    python benchmarks/predictor_federated.py                       # leave-one-out over the four sites
    python benchmarks/predictor_federated.py --held-out hadley     # one fold
    python benchmarks/predictor_federated.py --rounds 3 --local-steps 5 --sites gale,hadley,tujunga   # a quick look

Every site is a mission's base station: a ``raw`` mission (4 rovers, ``--steps`` steps,
seed 0) runs on it; the site fine-tunes the shipped predictor on its members' maps (every
10 steps) with its base station's **final map** as the target (never the truth). For every
held-out site, the other sites train:

``federated``   ``--rounds`` rounds of FedAvg, each site ``--local-steps`` Adam steps per round;
``pooled``      all training sites' samples on one machine, the same Adam steps per round;
``alone:<s>``   site ``s`` by itself, the same Adam steps per round;
``offline``     the shipped model, not fine-tuned.

``--target truth`` (an ablation) trains on the truth instead of the final map.

Each is scored after every round on the held-out site's cells nobody had observed (truth
known), on every rover's map at steps 50, 100, 150 and 200 of its missions with seeds 0
and 1: accuracy, impassable IoU, Brier score, ECE. Sites: Gale 1 m
(examples/mission_gale.toml), Hadley Rille (examples/mission_hadley.toml), Big Tujunga
(Earth, 30 m, slope limit 25 degrees) and Zion (Earth SRTM, 90 m canyons, slope limit 25
degrees), as benchmarks/predictor.py loads them. Needs ``../shared/data``; the package
itself never does. Writes ``predictor_federated.json``, ``predictor_federated.md`` and
``rounds.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from fedmap.mission import load_mission, mission_terrain
from fedmap.nets.predictor import shipped_predictor
from fedmap.training.predictorfed import FineTuning, Site, compare, plot_rounds, predictor_weights, site_maps

ROOT = Path(__file__).resolve().parents[1]


def sites(data: Path) -> dict[str, tuple[Path, dict | None, dict | None]]:
    """name -> (mission file, terrain replacing the file's or None, thresholds laid over the file's or None)."""
    tujunga = {"kind": "dem", "path": str(data / "earth/bigtujunga.tif"), "crop": 256, "size": 128}
    zion = {"kind": "dem", "path": str(data / "earth/zion_srtm.tif"), "crop": 256, "size": 128}
    return {"gale": (ROOT / "examples/mission_gale.toml", None, None),
            "hadley": (ROOT / "examples/mission_hadley.toml", None, None),
            "tujunga": (ROOT / "examples/mission_hadley.toml", tujunga, {"max_slope_deg": 25.0}),
            "zion": (ROOT / "examples/mission_hadley.toml", zion, {"max_slope_deg": 25.0})}


def load_site(name: str, spec, *, seed: int, steps: int):
    path, terrain, thresholds = spec
    config, source, _ = load_mission(path, terrain=terrain, seed=seed,
                                     overrides=[{"thresholds": thresholds}] if thresholds else None,
                                     mission={"steps": steps, "strategies": ["raw"]})
    truth, elevation, _, profiles = mission_terrain(config, source)
    return site_maps(config, truth, name=name, every=10, elevation=elevation, profiles=profiles,
                     thresholds=source.thresholds)


def markdown(result: dict) -> str:
    lines = ["| held out | method | accuracy | IoU impassable | Brier | ECE | all free |", "|---|---|---|---|---|---|---|"]
    for fold in result["folds"]:
        for name, s in fold["final"].items():
            lines.append(f"| {fold['held_out']} | {name} | {s['accuracy']:.3f} | {s['iou_impassable']:.3f} | "
                         f"{s['brier']:.3f} | {s['ece']:.3f} | {s['accuracy_all_free']:.3f} |")
    lines += ["", "| held out | federated - pooled (accuracy points) | federated - offline |", "|---|---|---|"]
    for fold in result["folds"]:
        lines.append(f"| {fold['held_out']} | {100 * fold['federated_minus_pooled']:+.1f} | "
                     f"{100 * fold['federated_minus_offline']:+.1f} |")
    m = result["mean"]
    lines += ["", "Mean over the folds: " + ", ".join(f"{k} {v['accuracy']:.3f} (Brier {v['brier']:.3f}, ECE "
                                                       f"{v['ece']:.3f})" for k, v in m.items())]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--sites", default="gale,hadley,tujunga,zion")
    ap.add_argument("--held-out", default=None, help="one site (default: every site in turn)")
    ap.add_argument("--steps", type=int, default=200, help="mission steps")
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--local-steps", type=int, default=15)
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target", choices=("final", "truth"), default="final",
                    help="what the sites train on: their base station's final map (honest), or the truth (ablation)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/predictor_federated")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    specs = sites(a.data)
    names = a.sites.split(",")
    t0 = time.perf_counter()
    maps = {}
    for n in names:
        t1 = time.perf_counter()
        maps[n] = load_site(n, specs[n], seed=0, steps=a.steps)
        print(f"site {n}: {len(maps[n])} maps, {100 * (maps[n].truth == 1).mean():.0f} % impassable, "
              f"final map knows {100 * (maps[n].final != 2).mean():.0f} % ({time.perf_counter() - t1:.0f} s)",
              flush=True)
    training = FineTuning(steps=a.local_steps, crop=a.crop, lr=a.lr, seed=a.seed)
    init = predictor_weights(shipped_predictor())
    folds = []
    for held in ([a.held_out] if a.held_out else names):
        t1 = time.perf_counter()
        scored = maps[held].join(load_site(held, specs[held], seed=1, steps=a.steps))
        train = [Site.of(maps[n]) if a.target == "final" else
                 Site(n, maps[n].beliefs, np.broadcast_to(maps[n].truth, maps[n].beliefs.shape).copy())
                 for n in names if n != held]
        fold = compare(init, train, scored, training, a.rounds,
                       on_progress=lambda what: print(f"  {held}: {what}", flush=True))
        fold["seconds"] = time.perf_counter() - t1
        folds.append(fold)
        f = fold["final"]
        print(f"held out {held}: offline {f['offline']['accuracy']:.3f} federated {f['federated']['accuracy']:.3f} "
              f"pooled {f['pooled']['accuracy']:.3f} ({fold['seconds']:.0f} s)", flush=True)
    methods = ["offline", "federated", "pooled"]
    mean = {m: {k: float(np.mean([f["final"][m][k] for f in folds])) for k in ("accuracy", "iou_impassable", "brier",
                                                                                 "ece", "accuracy_all_free")}
            for m in methods}
    mean["alone (mean of sites)"] = {k: float(np.mean([s[k] for f in folds for n, s in f["final"].items()
                                                       if n.startswith("alone:")]))
                                     for k in ("accuracy", "iou_impassable", "brier", "ece", "accuracy_all_free")}
    result = {"command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
              "machine": {"python": platform.python_version(), "torch": torch.__version__,
                          "processor": platform.processor() or platform.machine(), "threads": a.threads},
              "mission_steps": a.steps, "target": a.target, "folds": folds, "mean": mean,
              "seconds": time.perf_counter() - t0}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "predictor_federated.json").write_text(json.dumps(result, indent=1))
    (a.out / "predictor_federated.md").write_text(markdown(result))
    plot_rounds(folds, a.out / "rounds.png")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
