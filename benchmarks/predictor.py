"""The map predictor (fedmap.nets.predictor) on held-out real terrain: its speed, its
calibration, and whether planning with it pays (``[mission] predictor = "learned"``).

    python benchmarks/predictor.py                      # speed, calibration and missions
    python benchmarks/predictor.py --part speed         # only the inference time (kept with earlier missions)
    python benchmarks/predictor.py --seeds 0 --steps 100 --sites gale   # a quick look

Parts:

``speed``        inference time at 128x128 (best and median of 30 calls): ``predict``, which
                 always runs on one thread, and the bare network on 2 threads.
``missions``     every site x seed x strategy (raw, predictive) x predictor (none, learned):
                 team coverage and mean belief F1 at fixed steps, the first step the team's
                 mean belief F1 reaches 0.9, bytes, false-free, and the share of cells nobody
                 observed that the predictor gets right (on every rover's map, at the fixed
                 steps), beside the share an "all free" guess gets right.
``calibration``  from the predictor = none runs of ``missions``: every rover's map at the
                 fixed steps, P(impassable) of every cell nobody observed (truth known),
                 binned in tenths: the mean prediction vs the observed frequency of
                 impassable, ECE, Brier score; ``reliability.png``.

Sites (never seen in training: the predictor learns on fedmap's Earth-like collection):
Gale 1 m (examples/mission_gale.toml: line of sight, small-rover limits), Hadley Rille
(examples/mission_hadley.toml) and Big Tujunga, an Earth mountain DEM (30 m; the Hadley
mission on a 256-cell crop, slope limit 25 degrees: 33 % impassable). Needs
``../shared/data``; the package itself never does.
Writes ``predictor.json``, ``predictor.md`` and ``reliability.png`` to ``--out``.
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

from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.sim import prepare_mission
from fedmap.mission.world.world import PredictedView
from fedmap.nets.predictor import count_parameters, one_hot, predict, shipped_predictor

ROOT = Path(__file__).resolve().parents[1]
AT = (50, 100, 150, 200)  #: the fixed steps of the tables
BINS = 10


def sites(data: Path) -> dict[str, tuple[Path, dict | None, dict | None]]:
    """name -> (mission file, terrain replacing the file's or None, thresholds laid over the file's or None)."""
    tujunga = {"kind": "dem", "path": str(data / "earth/bigtujunga.tif"), "crop": 256, "size": 128}
    return {"gale": (ROOT / "examples/mission_gale.toml", None, None),
            "hadley": (ROOT / "examples/mission_hadley.toml", None, None),
            "tujunga": (ROOT / "examples/mission_hadley.toml", tujunga, {"max_slope_deg": 25.0})}


def _timed(f, n: int = 30) -> dict:
    for _ in range(3):
        f()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return {"best": 1e3 * min(ts), "median": 1e3 * float(np.median(ts))}


def speed() -> dict:
    """``predict`` at 128x128 (it always runs on one thread), and the bare network on 2 threads."""
    model = shipped_predictor()
    b = np.full((128, 128), UNKNOWN, dtype=np.uint8)
    b[40:90, 30:100] = np.random.default_rng(0).choice([FREE, IMPASSABLE], size=(50, 70), p=[0.8, 0.2])
    out = {"parameters": count_parameters(model), "size": [128, 128],
           "predict_1_thread_ms": _timed(lambda: predict(model, b))}
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    x = one_hot(b)[None]
    with torch.inference_mode():
        out["network_2_threads_ms"] = _timed(lambda: model(x))
    torch.set_num_threads(threads)
    return out


def run_one(path: Path, terrain: dict | None, thresholds: dict | None, *, seed: int, strategy: str, predictor: str,
            steps: int) -> tuple[dict, dict]:
    """One mission: its row of the tables, and the cells nobody observed at the fixed steps
    (``{"p": P(impassable), "truth": impassable?}``) for the calibration."""
    config, source, _ = load_mission(path, terrain=terrain, seed=seed,
                                     overrides=[{"thresholds": thresholds}] if thresholds else None,
                                     mission={"steps": steps, "strategies": [strategy], "predictor": predictor})
    truth, elevation, prior, profiles = mission_terrain(config, source)
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles, thresholds=source.thresholds)
    model = shipped_predictor()
    at = [t for t in AT if t <= steps]
    holder: dict = {}
    right: dict[int, list[float]] = {}
    all_free: dict[int, list[float]] = {}
    filled_f1: dict[int, list[float]] = {}
    cal_p: list[np.ndarray] = []
    cal_y: list[np.ndarray] = []

    def look(snap) -> None:
        if snap.step not in at:
            return
        team = holder["run"].team
        nobody = ~np.any([r.local != UNKNOWN for r in team], axis=0) & (truth.classes != UNKNOWN)
        for view in snap.views[:config.rovers]:
            guess = PredictedView.of(model, view)
            t = truth.classes[nobody]
            right.setdefault(snap.step, []).append(float((guess.classes[nobody] == t).mean()) if nobody.any() else 1.0)
            all_free.setdefault(snap.step, []).append(float((t == FREE).mean()) if nobody.any() else 1.0)
            filled_f1.setdefault(snap.step, []).append(m.scorer.path(guess.classes).f1)
            if predictor == "none":
                cal_p.append(guess.p_impassable[nobody])
                cal_y.append(t == IMPASSABLE)

    run = m.new_run(strategy, on_snapshot=look)
    holder["run"] = run
    t0 = time.perf_counter()
    r = run.run()
    s = r.summary
    series = r.series
    coverage = dict(zip(series.step, series.coverage))
    f1 = {t: float(np.mean(v)) for t, v in zip(series.eval.step, series.eval.belief_f1)}  # mean over rovers
    row = {"coverage": {t: coverage[t] for t in at}, "belief_f1": {t: f1[t] for t in at if t in f1},
           "seconds": time.perf_counter() - t0, "bytes": s.bytes_up + s.bytes_down,
           "false_free": s.final_false_free_mean, "team_f1_step": s.team_f1_step,
           "coverage_steps": {str(k): v for k, v in s.coverage_steps.items()},
           "unobserved_right": {t: float(np.mean(v)) for t, v in right.items()},
           "unobserved_all_free": {t: float(np.mean(v)) for t, v in all_free.items()},
           "filled_belief_f1": {t: float(np.mean(v)) for t, v in filled_f1.items()}}
    cal = {"p": np.concatenate(cal_p) if cal_p else np.zeros(0), "truth": np.concatenate(cal_y) if cal_y else np.zeros(0)}
    return row, cal


def calibration(p: np.ndarray, y: np.ndarray) -> dict:
    """Reliability in ``BINS`` equal bins of P(impassable): mean prediction, observed
    frequency and count per bin; ECE (count-weighted |frequency - prediction|), Brier score."""
    edges = np.linspace(0, 1, BINS + 1)
    which = np.clip(np.digitize(p, edges[1:-1]), 0, BINS - 1)
    rows = []
    ece = 0.0
    for i in range(BINS):
        sel = which == i
        n = int(sel.sum())
        conf = float(p[sel].mean()) if n else None
        freq = float(y[sel].mean()) if n else None
        rows.append({"bin": [float(edges[i]), float(edges[i + 1])], "n": n, "mean_p": conf, "frequency": freq})
        if n:
            ece += n / len(p) * abs(freq - conf)
    return {"cells": int(len(p)), "base_rate": float(y.mean()), "ece": ece,
            "brier": float(np.mean((p - y) ** 2)), "brier_base_rate": float(np.mean((y.mean() - y) ** 2)),
            "accuracy": float(((p > 0.5) == y).mean()), "accuracy_all_free": float((~y.astype(bool)).mean()),
            "bins": rows}


def plot_reliability(cal: dict, per_site: dict[str, dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, hist) = plt.subplots(2, 1, figsize=(5, 6.4), gridspec_kw={"height_ratios": [3, 1]}, sharex=True)
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls="--", label="perfectly calibrated")
    for name, c in [("all sites", cal), *per_site.items()]:
        pts = [(b["mean_p"], b["frequency"]) for b in c["bins"] if b["n"]]
        ax.plot(*zip(*pts), marker="o", lw=2 if name == "all sites" else 1,
                label=f"{name} (ECE {c['ece']:.3f}, {c['cells']:,} cells)")
    ax.set_ylabel("observed frequency of impassable")
    ax.set_title("Map predictor on cells nobody observed\n(held-out real terrain, rovers' maps at steps 50-200)")
    ax.legend(fontsize=7, loc="upper left")
    hist.bar([(b["bin"][0] + b["bin"][1]) / 2 for b in cal["bins"]], [b["n"] for b in cal["bins"]], width=0.09,
             color="tab:blue")
    hist.set_yscale("log")
    hist.set_xlabel("predicted P(impassable)")
    hist.set_ylabel("cells")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def markdown(result: dict) -> str:
    lines = []
    sp = result.get("speed")
    if sp:
        p1, n2 = sp["predict_1_thread_ms"], sp["network_2_threads_ms"]
        lines += [f"Inference at 128x128, {sp['parameters']:,} parameters: predict (one thread) {p1['best']:.1f} ms "
                  f"best / {p1['median']:.1f} ms median; the bare network on 2 threads {n2['best']:.1f} / "
                  f"{n2['median']:.1f} ms", ""]
    cal = result.get("calibration")
    if cal:
        lines += [f"Calibration on {cal['cells']:,} cells nobody observed: ECE {cal['ece']:.3f}, Brier "
                  f"{cal['brier']:.3f} (base rate alone {cal['brier_base_rate']:.3f}), accuracy {cal['accuracy']:.3f} "
                  f"(all free {cal['accuracy_all_free']:.3f})", ""]
    runs = result.get("missions")
    if runs:
        at = [str(t) for t in AT if str(t) in runs[0]["coverage"]]
        lines += ["| site | seed | strategy | predictor | " + " | ".join(f"cov@{t}" for t in at) + " | "
                  + " | ".join(f"F1@{t}" for t in at) + " | F1>=0.9 step | bytes | false-free | "
                  + " | ".join(f"right@{t} (all free)" for t in at) + " |",
                  "|" + "---|" * (7 + 3 * len(at))]
        for r in runs:
            f = lambda d, t, fmt="{:.3f}": fmt.format(d[t]) if t in d else "-"
            lines.append(f"| {r['site']} | {r['seed']} | {r['strategy']} | {r['predictor']} | "
                         + " | ".join(f(r["coverage"], t) for t in at) + " | "
                         + " | ".join(f(r["belief_f1"], t) for t in at)
                         + f" | {r['team_f1_step']} | {r['bytes']:,} | {r['false_free']:.4f} | "
                         + " | ".join(f"{f(r['unobserved_right'], t)} ({f(r['unobserved_all_free'], t)})" for t in at)
                         + " |")
        lines += ["", "Means over sites and seeds (learned minus none):", ""]
        for strategy in sorted({r["strategy"] for r in runs}):
            pairs = [(a, b) for a in runs for b in runs if a["strategy"] == b["strategy"] == strategy
                     and a["site"] == b["site"] and a["seed"] == b["seed"] and a["predictor"] == "none"
                     and b["predictor"] == "learned"]
            for t in at:
                dc = np.mean([b["coverage"][t] - a["coverage"][t] for a, b in pairs])
                df = np.mean([b["belief_f1"][t] - a["belief_f1"][t] for a, b in pairs if t in a["belief_f1"]])
                lines.append(f"- {strategy} step {t}: coverage {dc:+.4f}, belief F1 {df:+.4f}")
            reached = [(a["team_f1_step"], b["team_f1_step"]) for a, b in pairs]
            lines.append(f"- {strategy}: first step of team belief F1 >= 0.9 (none -> learned): {reached}")
            db = np.mean([b["bytes"] / a["bytes"] - 1 for a, b in pairs])
            lines.append(f"- {strategy}: bytes {db:+.2%}")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=["all", "speed", "missions"], default="all",
                    help="missions includes the calibration")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared/data")
    ap.add_argument("--sites", nargs="+", default=None, help="some of gale, hadley, tujunga (default: all)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--strategies", nargs="+", default=["raw", "predictive"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=1, help="torch threads in the missions (predict uses one anyway)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/predictor")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    result: dict = {"machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__}}
    result["speed"] = speed()
    print(markdown({"speed": result["speed"]}), flush=True)
    result["command"] = "python benchmarks/predictor.py " + " ".join(sys.argv[1:])
    if args.part in ("all", "missions"):
        torch.set_num_threads(args.threads)
        all_sites = sites(args.data)
        names = args.sites or list(all_sites)
        runs, cals = [], {}
        for name in names:
            path, terrain, thresholds = all_sites[name]
            for seed in args.seeds:
                for strategy in args.strategies:
                    for predictor in ("none", "learned"):
                        row, cal = run_one(path, terrain, thresholds, seed=seed, strategy=strategy, predictor=predictor,
                                           steps=args.steps)
                        row = {"site": name, "seed": seed, "strategy": strategy, "predictor": predictor, **row}
                        runs.append(row)
                        if predictor == "none" and strategy == args.strategies[0]:
                            cals.setdefault(name, []).append(cal)
                        print(f"{name} seed {seed} {strategy} {predictor}: coverage {row['coverage']} belief F1 "
                              f"{row['belief_f1']} F1>=0.9 at {row['team_f1_step']} right on unobserved "
                              f"{row['unobserved_right']} ({row['seconds']:.0f} s)", flush=True)
        result["missions"] = runs
        per_site = {n: calibration(np.concatenate([c["p"] for c in cs]), np.concatenate([c["truth"] for c in cs]))
                    for n, cs in cals.items()}
        every = [c for cs in cals.values() for c in cs]
        result["calibration"] = calibration(np.concatenate([c["p"] for c in every]),
                                            np.concatenate([c["truth"] for c in every]))
        result["calibration_per_site"] = per_site
        plot_reliability(result["calibration"], per_site, args.out / "reliability.png")
    result = json.loads(json.dumps(result, default=str))  # the step keys as JSON has them (strings)
    old = args.out / "predictor.json"
    if args.part == "speed" and old.is_file():  # keep the missions of an earlier run
        result = {**json.loads(old.read_text()), **{k: result[k] for k in ("machine", "speed")}}
    text = markdown(result)
    print(text)
    (args.out / "predictor.json").write_text(json.dumps(result, indent=1))
    (args.out / "predictor.md").write_text(text)


if __name__ == "__main__":
    main()
