"""Leave one site out: does the map predictor pay on terrain it never trained on?

    python benchmarks/predictor_loso.py                      # 12 held-out sites x 10 seeds (~45 min on 2 cores)
    python benchmarks/predictor_loso.py --sites gale,zion --seeds 0-1 --train-steps 50   # a quick look
    python benchmarks/predictor_loso.py --report-only        # the tables and figure again from results.json

**Units.** Every real site of ``../shared/data`` that gives a map a rover could cross (the
DEMs of Gale, the Hadley Rille, Mars' MOLA, Zion, Big Tujunga, Mt Mongón, Baltoro,
Columbia glacier and South Glacier) and every built-in terrain family (``mars``,
``moon``, ``ice``). Each unit has *training variants*: the same DEM at several scales (crops
of 128 to 512 cells resampled to 128², so 1x to 4x the cell size; tiles 2, 4 and 8 for the
Moon), or its generator at cell sizes of 0.5, 1 and 2 m from other seeds. New Zealand's
1 km DEM is left out: every 256-cell crop of it is half sea (nodata); so are the
landlab grids of 37 to 122 cells a side (too small for a 128² mission) and the tidal marsh (flat). The built-in
Earth-like collection (the shipped predictor's training maps) is in every fold's corpus.

**Folds.** For each held-out unit a predictor is trained (``train_predictor``, the shipped
recipe with ``--train-steps``) on exploration samples (``raw`` missions, 150 steps, the
rovers' maps every 10 steps, as ``fedmap meta-predictor``) of every *other* unit: the test
site, and its DEM at any other scale, is never in its corpus. Two corpora, to measure what
each part adds: ``loso`` (every variant: many scales) and ``loso-1scale`` (only the variant
at the test's scale). Beside them the shipped predictor (Earth-like maps only), and
``loso`` without the base-rate correction (``predict(adapt=False)``).

**Missions.** On each held-out site, ``predictive``, 4 rovers, ``--steps`` steps, seeds
``--seeds`` (each seed moves the starts, and a built-in family's map), three ways, all with the
fold's ``loso`` model: ``none`` (no predictor), ``check`` (``predictor = "learned"``, the
default check: steps aside where the guesses do not beat "all free" on its own map by 3 points) and
``adapt`` (the check and ``predictor_adapt``: each rover fine-tunes its copy on its own map).

**Reported per held-out site:**

* the guesses on cells nobody observed (in the ``none`` runs, every rover's map at steps 50,
  100, 150 and 200, pooled): accuracy against "all free", impassable IoU, Brier and ECE, for
  each model; and the issue's bar: accuracy >= "all free" + 3 points with IoU > 0.2;
* steps to a plannable **observed** belief (the team's mean strict path F1 >= 0.9; a run
  that never gets there counts as steps + 10), mean and 95 % t interval, for each way;
* steps to a plannable **filled** belief in the ``check`` runs: the rovers' maps with the
  guesses filled in, against the same maps filled with "all free" (no site here has an
  orbital prior);
* how often the checks let the guesses in, bytes with / without, false-free observed and
  filled against ``none``'s.

Writes ``results.json``, ``results.md`` and ``loso.png`` to ``--out``
(``benchmarks/results/predictor_loso``); samples and models are cached in ``--work``.
Needs ``../shared/data`` (``--data``); the package never does.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from predictor_planning import NEVER, steps_or_never, t_interval  # (this folder: a run that never gets there)

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "predictor_loso"
WORK = ROOT / "benchmarks" / "results" / "predictor_loso" / "work"  # git-ignored (models, samples)
MODES = {"none": {}, "check": {"predictor": "learned"},
         "adapt": {"predictor": "learned", "predictor_adapt": True}}
MODELS = ("shipped", "loso-1scale", "loso", "loso-noshift")
GUESS_STEPS = (50, 100, 150, 200)
BINS = 10


@dataclass(frozen=True)
class Unit:
    """A held-out candidate: how its test missions load it, and its training variants (the
    first at the test's scale). Each spec is (mission file or None, terrain table, thresholds, seed); a
    test mission runs with its own seed whatever the spec's."""

    name: str
    kind: str  #: "site" (real DEM) or "family" (built-in generator)
    test: tuple
    variants: list[tuple] = field(default_factory=list)


def units(data: Path) -> dict[str, Unit]:
    def dem(path: str, crop, slope: float, **extra) -> tuple:
        t = {"kind": "dem", "path": str(data / path), "size": 128, **extra}
        if crop is not None:
            t["crop"] = crop
        return (None, t, {"max_slope_deg": slope}, 0)

    def crops(path: str, sides, slope: float, **extra) -> list[tuple]:
        return [dem(path, side, slope, **extra) for side in sides]

    mola = {"options": {"shape": [720, 1440], "dtype": "int16", "byteorder": "big", "pixel_size": 14800}}
    moon = {"kind": "tiles", "path": str(data / "moon/gld100_256p"), "lon": 0, "lat": 22, "size": 128,
            "options": {"pixel_size": 118.45}}
    gale_file = ROOT / "examples/mission_gale.toml"
    out = {
        "gale": Unit("gale", "site", (gale_file, None, None, 0),
                     [(gale_file, None, None, 0), (gale_file, {"crop": 128}, None, 0),
                      (gale_file, {"crop": 336}, None, 0)]),
        "hadley": Unit("hadley", "site", (ROOT / "examples/mission_hadley.toml", None, None, 0),
                       [(None, {**moon, "tiles": n}, {"max_slope_deg": 10.0}, 0) for n in (8, 4, 2)]),
        "mola": Unit("mola", "site", dem("mars/mola_megt90n000cb.img", [200, 456, 100, 356], 1.0, **mola),
                     [dem("mars/mola_megt90n000cb.img", [200 + o, 456 - o, 100 + o, 356 - o], 1.0, **mola)
                      for o in (0, 64)] + [dem("mars/mola_megt90n000cb.img", [72, 584, 0, 512], 1.0, **mola)]),
        "zion": Unit("zion", "site", dem("earth/zion_srtm.tif", 256, 25.0),
                     crops("earth/zion_srtm.tif", (256, 128, 448), 25.0)),
        "tujunga": Unit("tujunga", "site", dem("earth/bigtujunga.tif", 256, 25.0),
                        crops("earth/bigtujunga.tif", (256, 128, 512), 25.0)),
        "mongon": Unit("mongon", "site", dem("earth/mongon_dem.tif", None, 25.0),
                       [dem("earth/mongon_dem.tif", None, 25.0), *crops("earth/mongon_dem.tif", (64, 96), 25.0)]),
        "baltoro": Unit("baltoro", "site", dem("ice/test-files_baltoro_srtm_clip.tif", 256, 35.0),
                        crops("ice/test-files_baltoro_srtm_clip.tif", (256, 128, 420), 35.0)),
        "columbia": Unit("columbia", "site", dem("ice/test-files_columbia_dem_Columbia.tif", 256, 20.0),
                         crops("ice/test-files_columbia_dem_Columbia.tif", (256, 128, 512), 20.0)),
        "south-glacier": Unit("south-glacier", "site", dem("ice/benchmarks_south_glacier_dem_SouthGlacier.tif", 192,
                                                           30.0),
                              crops("ice/benchmarks_south_glacier_dem_SouthGlacier.tif", (192, 128, 248), 30.0)),
    }
    for kind in ("mars", "moon", "ice"):
        gen = {"kind": "builtin", "terrain": kind, "size": 128}
        out[f"{kind}-gen"] = Unit(f"{kind}-gen", "family", (None, gen, None, None),
                                  [(None, {**gen, "options": {"pixel_size": px}}, None, 1000 + i)
                                   for i, px in enumerate((1.0, 0.5, 2.0))])
    return out


# -- loading -------------------------------------------------------------------------------

def load(spec: tuple, seed: int, mission: dict | None = None):
    """(config, truth, elevation, prior, profiles, thresholds) of a spec at ``seed``."""
    from fedmap.mission import load_mission, mission_terrain

    path, terrain, thresholds, fixed = spec
    overrides: list[dict] = [{"seed": seed if fixed is None else fixed}]
    if mission:
        overrides.append({"mission": mission})
    if thresholds:
        overrides.insert(0, {"thresholds": thresholds})
    if path is not None and terrain is not None:  # the file's terrain with other grid keys
        import tomllib

        base = tomllib.loads(Path(path).read_text())["terrain"]
        terrain = {**base, "path": str((Path(path).parent / base["path"]).resolve()), **terrain}
    config, source, _ = load_mission(path, terrain=terrain, overrides=overrides)
    truth, elevation, prior, profiles = mission_terrain(config, source)
    return config, truth, elevation, prior, profiles, source.thresholds


# -- phase 1: exploration samples ----------------------------------------------------------

def samples_job(job: tuple[str, tuple, int, str]) -> str:
    """Exploration samples of one training variant (cached)."""
    name, spec, index, work = job
    path = Path(work) / "samples" / f"{name}-{index}.npz"
    if path.exists():
        return str(path)
    from fedmap.meta.collections import MapCollection, earth_like
    from fedmap.training.predictorprior import exploration_samples

    if name == "earth-like":
        coll = earth_like(size=128, per_category=3, seed=0)
    else:
        truth = load(spec, 0)[1]
        coll = MapCollection(f"{name}-{index}", {name: [truth]})
    beliefs, truths = exploration_samples(coll, steps=150, every=10, seed=7 * index)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, beliefs=beliefs, truths=truths)
    tmp.replace(path)
    return str(path)


# -- phase 2: a predictor per fold ---------------------------------------------------------

def train_job(job: tuple[str, str, list[str], int, str]) -> str:
    fold, corpus, files, steps, work = job
    path = Path(work) / "models" / f"{fold}-{corpus}.safetensors"
    if path.exists():
        return str(path)
    from fedmap.nets.predictor import PredictorTraining, save_predictor, train_predictor

    parts = [np.load(f) for f in files]
    beliefs = np.concatenate([p["beliefs"] for p in parts])
    truths = np.concatenate([p["truths"] for p in parts])
    model = train_predictor(beliefs, truths, training=PredictorTraining(steps=steps, seed=0))
    path.parent.mkdir(parents=True, exist_ok=True)
    save_predictor(model, path, extra={"fold": fold, "corpus": corpus, "samples": int(len(beliefs)),
                                       "files": [Path(f).name for f in files]})
    return str(path)


# -- phase 3: missions ---------------------------------------------------------------------

def guess_stats(p: np.ndarray, y: np.ndarray) -> list[float]:
    """Sufficient statistics of :func:`fedmap.evaluation.metrics.prediction_scores` (pooled over runs):
    cells, right, all-free right, intersection, union, Brier sum, then per bin: count, impassable, sum of P."""
    g = p > 0.5
    which = np.clip(np.digitize(p, np.linspace(0, 1, BINS + 1)[1:-1]), 0, BINS - 1)
    per_bin = []
    for i in range(BINS):
        sel = which == i
        per_bin += [float(sel.sum()), float(y[sel].sum()), float(p[sel].sum())]
    return [float(len(p)), float((g == y).sum()), float((~y).sum()), float((g & y).sum()), float((g | y).sum()),
            float(((p - y) ** 2).sum()), *per_bin]


def stats_scores(s: list[float]) -> dict:
    n = s[0]
    ece = sum(abs(s[6 + 3 * i + 1] - s[6 + 3 * i + 2]) for i in range(BINS)) / n if n else 0.0
    return {"cells": int(n), "accuracy": s[1] / n, "all_free": s[2] / n, "iou": s[3] / s[4] if s[4] else 1.0,
            "brier": s[5] / n, "ece": ece}


def init_worker() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


def mission_job(job: tuple) -> dict:
    site, spec, seed, mode, steps, models = job
    import fedmap.mission.world.world as world_module
    from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
    from fedmap.mission.results import F1_GOAL
    from fedmap.mission.sim import prepare_mission
    from fedmap.nets.predictor import MIN_CHECK_CELLS, load_predictor, predict, shipped_predictor

    loaded = {name: (shipped_predictor() if name == "shipped" else load_predictor(path))
              for name, path in models.items()}
    world_module.shipped_predictor = lambda: loaded["loso"]  # the fold's model plans (the coder keeps its own)
    config, truth, elevation, prior, profiles, thresholds = load(  # the run's seed: its starts (a family: its map)
        (*spec[:3], None), seed, {"steps": steps, "strategies": ["predictive"], **MODES[mode]})
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles, thresholds=thresholds,
                        frames=1)
    y_all = truth.classes
    stats: dict[str, list[float] | None] = {name: None for name in MODELS} if mode == "none" else {}
    free_fill: list[tuple[int, float]] = []

    def look(snap) -> None:
        if snap.eval is None:
            return
        views = snap.views[:config.rovers]
        if mode == "check":  # the same maps filled with "all free"
            f1 = [m.scorer.path(np.where(v == UNKNOWN, FREE, v).astype(np.uint8)).f1 for v in views]
            free_fill.append((snap.step, float(np.mean(f1))))
        if mode == "none" and snap.step in GUESS_STEPS:
            nobody = np.all([b == UNKNOWN for b in snap.beliefs], axis=0) & (y_all != UNKNOWN)
            if not nobody.any():
                return
            y = np.tile(y_all[nobody] == IMPASSABLE, len(views))
            for name in MODELS:
                model = loaded["loso" if name == "loso-noshift" else name]
                p = np.concatenate([predict(model, v, adapt=name != "loso-noshift")[1][nobody] for v in views])
                s = guess_stats(p.astype(np.float64), y)
                stats[name] = s if stats[name] is None else [a + b for a, b in zip(stats[name], s)]

    t0 = time.perf_counter()
    run = m.new_run("predictive", on_snapshot=look)
    s = run.run().summary
    pb = s.predicted_belief or {}
    checks = run.world.checks
    free_step = next((t for t, f in free_fill if f >= F1_GOAL - 1e-12), None)
    return {"site": site, "seed": seed, "mode": mode, "seconds": round(time.perf_counter() - t0, 1),
            "observed_step": s.team_f1_step, "filled_step": pb.get("f1_step"), "all_free_filled_step": free_step,
            "bytes": s.bytes_up + s.bytes_down, "false_free": s.final_false_free_mean,
            "filled_false_free": pb.get("final_false_free"),
            "guessing_share": (sum(c[5] for c in checks) / len(checks)) if checks else None,
            "check_margin": (float(np.mean([c[3] - c[4] for c in checks if c[2] >= MIN_CHECK_CELLS]))
                             if any(c[2] >= MIN_CHECK_CELLS for c in checks) else None),
            "impassable": float((y_all == IMPASSABLE).mean()), "stats": stats}


# -- report --------------------------------------------------------------------------------

def summarise(rows: list[dict], steps: int) -> list[dict]:
    out = []
    for site in dict.fromkeys(r["site"] for r in rows):
        by = {(r["mode"], r["seed"]): r for r in rows if r["site"] == site}
        seeds = sorted({s for _, s in by})
        row: dict = {"site": site, "seeds": len(seeds), "impassable": by[("none", seeds[0])]["impassable"]}
        pooled: dict[str, list[float]] = {}
        for sd in seeds:
            for name, st in by[("none", sd)]["stats"].items():
                if st is not None:
                    pooled[name] = st if name not in pooled else [a + b for a, b in zip(pooled[name], st)]
        row["guesses"] = {name: stats_scores(st) for name, st in pooled.items()}
        for mode in MODES:
            runs = [by[(mode, sd)] for sd in seeds if (mode, sd) in by]
            if not runs:
                continue
            row[mode] = {"observed": t_interval([steps_or_never(r["observed_step"], steps) for r in runs]),
                         "reached": sum(r["observed_step"] is not None for r in runs),
                         "bytes": statistics.mean(r["bytes"] for r in runs),
                         "false_free": statistics.mean(r["false_free"] for r in runs),
                         "seconds": statistics.mean(r["seconds"] for r in runs)}
            if mode != "none":
                row[mode]["filled"] = t_interval([steps_or_never(r["filled_step"], steps) for r in runs])
                row[mode]["filled_false_free"] = statistics.mean(r["filled_false_free"] for r in runs
                                                                 if r["filled_false_free"] is not None)
                row[mode]["guessing_share"] = statistics.mean(r["guessing_share"] for r in runs
                                                              if r["guessing_share"] is not None)
            if mode == "check":
                row[mode]["all_free_filled"] = t_interval([steps_or_never(r["all_free_filled_step"], steps) for r in runs])
        out.append(row)
    return out


def verdicts(row: dict) -> dict:
    """The issue's bars for one held-out site."""
    g = row["guesses"].get("loso")
    out = {}
    if g:
        out["guesses_pay"] = g["accuracy"] >= g["all_free"] + 0.03 and g["iou"] > 0.2
    none, check = row.get("none"), row.get("check")
    if none and check:
        out["steps_aside"] = check["guessing_share"] < 0.5
        out["never_later"] = check["observed"][1] <= none["observed"][2]  # the intervals overlap or it is sooner
        out["sooner_10"] = check["observed"][0] <= 0.9 * none["observed"][0]
        out["bytes_within_2"] = abs(check["bytes"] / none["bytes"] - 1) <= 0.02
        out["filled_sooner_10"] = check["filled"][0] <= 0.9 * check["all_free_filled"][0]
        out["false_free_ok"] = check["false_free"] <= none["false_free"] + 0.01
    return out


def markdown(result: dict) -> str:
    steps = result["steps"]
    lines = [f"`{result['command']}` ({result['machine']}); `predictive`, 4 rovers, {steps} steps, seeds "
             f"{result['seeds'][0]}-{result['seeds'][-1]}; a run that never reaches a level counts as {steps + NEVER}. "
             f"Models trained with {result['train_steps']} steps.", "",
             "## The guesses on cells nobody observed (steps 50-200 of the `none` runs, pooled)", "",
             "| held out | impassable | all free | " + " | ".join(f"{m}: acc / IoU / Brier / ECE" for m in MODELS)
             + " | pays (loso: ≥ 3 points, IoU > 0.2) |", "|---|---:|---:|" + "---|" * len(MODELS) + "---|"]
    for r in result["summary"]:
        g = r["guesses"]
        if not g:
            continue
        af = g["loso"]["all_free"]
        cells = [f"{g[m]['accuracy']:.3f} / {g[m]['iou']:.2f} / {g[m]['brier']:.3f} / {g[m]['ece']:.3f}"
                 if m in g else "-" for m in MODELS]
        lines.append(f"| {r['site']} | {r['impassable']:.2f} | {af:.3f} | " + " | ".join(cells)
                     + f" | {'yes' if verdicts(r).get('guesses_pay') else 'no'} |")
    lines += ["", "## Steps to a plannable belief (team mean path F1 ≥ 0.9), mean [95 %]", "",
              "| held out | observed: none | observed: check | observed: adapt | guesses in use (check / adapt) "
              "| filled with the guesses (check) | the same maps, all free | bytes check / none | false-free none / "
              "check / filled |", "|---|---|---|---|---|---|---|---:|---|"]

    def iv(x):
        return f"{x[0]:.0f} [{x[1]:.0f}, {x[2]:.0f}]"

    for r in result["summary"]:
        if "none" not in r or "check" not in r:
            continue
        n, c, a = r["none"], r["check"], r.get("adapt")
        lines.append(
            f"| {r['site']} | {iv(n['observed'])} | {iv(c['observed'])} | {iv(a['observed']) if a else '-'} | "
            f"{c['guessing_share']:.2f} / {a['guessing_share'] if a else float('nan'):.2f} | {iv(c['filled'])} | "
            f"{iv(c['all_free_filled'])} | {c['bytes'] / n['bytes']:.3f} | {n['false_free']:.4f} / "
            f"{c['false_free']:.4f} / {c['filled_false_free']:.4f} |")
    lines += ["", "## The issue's bars, per held-out site", "",
              "| held out | guesses pay | steps aside (guesses in use < half the checks) | observed: never later "
              "| observed: ≥ 10 % sooner | bytes within 2 % | filled ≥ 10 % sooner than all free | false-free ok |",
              "|---|---|---|---|---|---|---|---|"]
    for r in result["summary"]:
        v = verdicts(r)
        lines.append(f"| {r['site']} | " + " | ".join({True: "yes", False: "no", None: "-"}[v.get(k)] for k in (
            "guesses_pay", "steps_aside", "never_later", "sooner_10", "bytes_within_2", "filled_sooner_10",
            "false_free_ok")) + " |")
    return "\n".join(lines) + "\n"


def figure(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in result["summary"] if "none" in r and "check" in r]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.6))
    x = np.arange(len(rows))
    for i, (mode, key, label) in enumerate((("none", "observed", "observed, no predictor"),
                                             ("check", "observed", "observed, predictor (check)"),
                                             ("adapt", "observed", "observed, predictor (check + adapt)"),
                                             ("check", "filled", "filled with the guesses"),
                                             ("check", "all_free_filled", "filled with all free"))):
        vals = [r[mode][key] if mode in r else [np.nan] * 3 for r in rows]
        m = np.array([v[0] for v in vals])
        err = np.array([[v[0] - v[1] for v in vals], [v[2] - v[0] for v in vals]])
        a1.errorbar(x + (i - 2) * 0.14, m, yerr=err, fmt="o", ms=4, capsize=2, label=label)
    a1.set_xticks(x, [r["site"] for r in rows], rotation=45, ha="right")
    a1.set(ylabel="step the team's belief reached F1 ≥ 0.9", title="Plannable belief, held-out sites (95 % CI)")
    a1.legend(fontsize=7)
    g = [r for r in result["summary"] if r["guesses"]]
    xg = np.arange(len(g))
    a2.bar(xg - 0.3, [r["guesses"]["loso"]["all_free"] for r in g], 0.2, label="all free", color="0.7")
    for j, name in enumerate(("shipped", "loso-1scale", "loso")):
        a2.bar(xg - 0.1 + 0.2 * j, [r["guesses"][name]["accuracy"] for r in g], 0.2, label=name)
    a2.set_xticks(xg, [r["site"] for r in g], rotation=45, ha="right")
    a2.set(ylim=(0.3, 1.0), ylabel="guesses right on cells nobody observed", title="Guesses on held-out sites")
    a2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(result: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(result, indent=1))
    md = markdown(result)
    (out / "results.md").write_text(md)
    figure(result, out / "loso.png")
    print(md)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sites", default=None, help="held-out units, comma-separated (default: all)")
    ap.add_argument("--seeds", default="0-9", help="A-B or a comma list")
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--train-steps", type=int, default=400)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--work", type=Path, default=WORK)
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--keep-from", type=Path, default=None,
                    help="a results.json whose runs of the other modes are kept (only --modes run again)")
    a = ap.parse_args()
    if a.report_only:
        result = json.loads((a.out / "results.json").read_text())
        result["summary"] = summarise(result["runs"], result["steps"])
        write(result, a.out)
        return
    if not (a.data / "mars").is_dir():
        raise SystemExit(f"needs the data folder: {a.data} has no mars/ (--data)")
    lo, _, hi = a.seeds.partition("-")
    seeds = list(range(int(lo), int(hi) + 1)) if hi else [int(x) for x in a.seeds.split(",")]
    every = units(a.data)
    held = a.sites.split(",") if a.sites else list(every)
    unknown = [s for s in held if s not in every]
    if unknown:
        raise SystemExit(f"unknown site {unknown[0]!r}; choose from {', '.join(every)}")
    modes = a.modes.split(",")
    t0 = time.perf_counter()
    work = str(a.work)
    with ProcessPoolExecutor(a.workers, initializer=init_worker) as pool:
        jobs = [("earth-like", None, 0, work)] + [(u.name, spec, i, work) for u in every.values()
                                                  for i, spec in enumerate(u.variants)]
        files: dict[tuple[str, int], str] = {}
        for (name, _, i, _), f in zip(jobs, pool.map(samples_job, jobs)):
            files[(name, i)] = f
            print(f"  samples {name}-{i} ({time.perf_counter() - t0:.0f} s)", flush=True)
        train = []
        for fold in held:
            rest = [k for k in files if k[0] != fold]
            train.append((fold, "loso", [files[k] for k in rest], a.train_steps, work))
            train.append((fold, "loso-1scale", [files[k] for k in rest if k[1] == 0], a.train_steps, work))
        models: dict[tuple[str, str], str] = {}
        for job, f in zip(train, pool.map(train_job, train)):
            models[(job[0], job[1])] = f
            print(f"  model {job[0]} {job[1]} ({time.perf_counter() - t0:.0f} s)", flush=True)
        runs = [(site, every[site].test, sd, mode, a.steps,
                 {"shipped": "", "loso": models[(site, "loso")], "loso-1scale": models[(site, "loso-1scale")]})
                for site in held for sd in seeds for mode in modes]
        rows = []
        for i, row in enumerate(pool.map(mission_job, runs), 1):
            rows.append(row)
            print(f"  {i}/{len(runs)} {row['site']} seed {row['seed']} {row['mode']}: observed F1>=0.9 at "
                  f"{row['observed_step']} ({row['seconds']} s; {time.perf_counter() - t0:.0f} s)", flush=True)
    if a.keep_from is not None:
        kept = json.loads(a.keep_from.read_text())
        if kept["steps"] != a.steps:
            raise SystemExit(f"--keep-from: {a.keep_from} has {kept['steps']} steps, not {a.steps}")
        rows = [r for r in kept["runs"] if r["mode"] not in modes and r["site"] in held] + rows
    info = Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []
    cpu = next((ln.split(":", 1)[1].strip() for ln in info if ln.startswith("model name")), platform.machine())
    result = {"command": "python benchmarks/predictor_loso.py " + " ".join(sys.argv[1:]), "machine": cpu,
              "steps": a.steps, "seeds": seeds, "train_steps": a.train_steps, "runs": rows,
              "summary": summarise(rows, a.steps), "seconds": round(time.perf_counter() - t0)}
    write(result, a.out)


if __name__ == "__main__":
    main()
