"""Does planning with the map predictor pay? Steps until the team's belief is good enough to
plan on, with and without the predictor, on the default mission, Gale and Hadley.

    python benchmarks/predictor_planning.py                   # 3 missions x 10 seeds, 400 steps (~4 min)
    python benchmarks/predictor_planning.py --seeds 0 1 --missions default   # a quick look
    python benchmarks/predictor_planning.py --combine A/planning.json B/planning.json --out C   # several calls as one

Every mission runs ``predictive`` twice from the same seed: without the predictor (today)
and with ``[mission] predictor = "learned"`` (planning with the guesses). The measure is the
issue's: the first evaluation step the rovers' mean strict path F1 reaches 0.9, scored on
the belief the team plans on: the observed belief without the predictor, the belief with
the guesses filled in with it (``summary.predicted_belief.f1_step``). Beside it: the first
step the observed belief reaches 0.9 with the predictor, and the same guesses filled into
the beliefs of the run *without* it (``fill only``: the predictor run on the map each rover
holds at every evaluation, exploration unchanged, so the bytes are the same to the byte);
95 % coverage; the team's bytes over the mission and up to the step the goal was reached;
false-free of the observed and the filled beliefs at the end; accuracy of the guesses on
the cells nobody observed, at the end and pooled over every evaluation up to step 200
(``MID_STEP``; against guessing every such cell free), which is when they can make the
belief good enough sooner.

The missions run 400 steps (the default mission's file has 150, Gale's and Hadley's 300):
long enough for the runs without the predictor to reach the goal, so that "sooner" can be
measured. A run that never reaches it counts as 410 steps (said in the table). "Sooner" is
``1 - mean(with) / mean(without)`` over the seeds of a mission, and the paired difference
per seed is given with its 95 % Student's t interval.

``--ablation`` takes one of the predictor's two planning uses away in the runs with it:
``no-uncertainty`` counts every unknown cell 1 in a frontier's gain (not the entropy of its
guess), ``no-costs`` gives every unknown cell the plain ``unknown_cost`` (not the expected
cost of its guess; paths are then the shortest again). Two other gains were tried in place of
the entropy: ``expected-error`` counts an unknown cell by how likely its filled guess is
wrong, ``2 min(p, 1 - p)`` (1 at p = 1/2, as the entropy, but lower for fairly sure
guesses), and ``half-floor`` by ``1/2 + 1/2 entropy`` (no cell worth nothing).
``shrunk-rate`` changes the guesses instead: the base-rate correction reads the map's
impassable share with 4,096 cells (a quarter of a 128² map) of the training maps' share
added, so a few hundred known cells around the start no longer set it alone. Heights are never an input, and
every run uses the shipped offline model (no fine-tuning), so those two ablations are the
rows without ``--ablation``.

Gale and Hadley need ``../shared/data`` (``--data``); the package never does. Writes
``planning.json``, ``planning.md`` and ``planning.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MISSIONS = ("default", "gale", "hadley")
ABLATIONS = ("none", "no-uncertainty", "no-costs", "expected-error", "half-floor", "shrunk-rate")
NEVER = 10  #: a run that never reaches a level counts as steps + NEVER
MID_STEP = 200  #: the guesses' accuracy mid-mission is pooled over the evaluations up to this step


def mission_file(name: str) -> Path | None:
    return None if name == "default" else ROOT / f"examples/mission_{name}.toml"


def ablate(what: str) -> None:
    """Take one planning use of the predictor away in this process (see ``--ablation``)."""
    from fedmap.mission.world import frontiers

    if what == "no-uncertainty":
        frontiers.entropy_bits = lambda p: np.ones(np.shape(p))  # type: ignore[assignment]
    elif what == "expected-error":
        frontiers.entropy_bits = lambda p: 2 * np.minimum(np.asarray(p, float), 1 - np.asarray(p, float))  # type: ignore[assignment]
    elif what == "half-floor":
        entropy = frontiers.entropy_bits  # the library's: ablate() runs once per process (init_worker)
        frontiers.entropy_bits = lambda p: 0.5 + 0.5 * entropy(p)  # type: ignore[assignment]
    elif what == "shrunk-rate":  # the map's share read with 4,096 cells of the training share added
        from fedmap.nets import predictor

        predictor.known_rate = functools.partial(  # type: ignore[assignment]
            predictor.known_rate, cells=4096.0, rate=float(predictor.shipped_predictor().base_rate))
    elif what == "no-costs":
        frontiers.predicted_cost = lambda p, unknown_cost: np.full(np.shape(p), float(unknown_cost))  # type: ignore[assignment]


def init_worker(ablation: str) -> None:
    """A worker process, once: one thread, and the ablation (a wrapper applied per job would wrap itself)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    ablate(ablation)


def run_one(job: tuple[str, int, str, int, str]) -> dict:
    """One ``predictive`` mission: its figures (see the module docstring)."""
    name, seed, predictor, steps, data = job
    from fedmap.maps.grid import FREE
    from fedmap.mission import load_mission, mission_terrain
    from fedmap.mission.results import false_free
    from fedmap.mission.sim import prepare_mission
    from fedmap.mission.world.world import PredictedView
    from fedmap.nets.predictor import shipped_predictor

    path = mission_file(name)
    if path is not None and not (Path(data) / "mars").exists():
        raise SystemExit(f"{name}: needs the data folder, {data} has none (--data)")
    config, source, _ = load_mission(path, seed=seed,
                                     mission={"steps": steps, "strategies": ["predictive"], "predictor": predictor})
    truth, elevation, prior, profiles = mission_terrain(config, source)
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles, thresholds=source.thresholds)
    model = shipped_predictor()
    fill: dict[int, tuple[float, float]] = {}  # without the predictor: the guesses filled into the same beliefs
    mid = np.zeros(3, dtype=np.int64)  # up to MID_STEP: cells nobody observed, guessed right, free (all-free right)

    def look(snap) -> None:
        if snap.eval is None:
            return
        f1s, ff = [], []
        for view in snap.views[:config.rovers]:
            filled = PredictedView.of(model, view)
            if snap.step <= MID_STEP:
                unseen = filled.predicted
                np.add(mid, (int(unseen.sum()), int((filled.classes == truth.classes)[unseen].sum()),
                             int((truth.classes == FREE)[unseen].sum())), out=mid)
            if predictor == "none":
                f1s.append(m.scorer.path(filled.classes).f1)
                ff.append(false_free(filled.classes == FREE, truth.classes))
        if f1s:
            fill[snap.step] = (float(np.mean(f1s)), float(np.mean(ff)))

    t0 = time.perf_counter()
    r = m.new_run("predictive", on_snapshot=look).run()
    s = r.summary
    total = [int(np.sum(u) + np.sum(d)) for u, d in zip(r.series.bytes_up, r.series.bytes_down)]
    at = dict(zip(r.series.step, total))
    pb = s.predicted_belief or {}
    goal = pb.get("f1_step") if predictor != "none" else s.team_f1_step
    fill_step = next((t for t, (f, _) in sorted(fill.items()) if f >= 0.9 - 1e-12), None)
    return {"mission": name, "seed": seed, "predictor": predictor, "seconds": time.perf_counter() - t0,
            "goal_step": goal, "observed_f1_step": s.team_f1_step, "fill_only_step": fill_step,
            "coverage_95": s.coverage_steps[0.95], "bytes": s.bytes_up + s.bytes_down,
            "bytes_to_goal": None if goal is None else at[goal],
            "false_free": s.final_false_free_mean,
            "filled_false_free": pb.get("final_false_free") if predictor != "none" else
            (fill[max(fill)][1] if fill else None),
            "unobserved_accuracy": (s.final_prediction or {}).get("accuracy"),
            "unobserved_all_free": (s.final_prediction or {}).get("accuracy_all_free"),
            "mid_unobserved": int(mid[0]), "mid_guessed_right": int(mid[1]), "mid_all_free_right": int(mid[2])}


def steps_or_never(v: int | None, steps: int) -> int:
    return steps + NEVER if v is None else int(v)


def t_interval(diffs: list[float]) -> tuple[float, float, float]:
    from scipy import stats

    d = np.asarray(diffs, dtype=float)
    if len(d) < 2:
        return float(d.mean()), float(d.mean()), float(d.mean())
    half = float(stats.t.ppf(0.975, len(d) - 1)) * float(d.std(ddof=1)) / np.sqrt(len(d))
    return float(d.mean()), float(d.mean() - half), float(d.mean() + half)


def summarise(rows: list[dict], steps: int) -> list[dict]:
    out = []
    for name in [*dict.fromkeys(r["mission"] for r in rows), "all"]:
        pairs = [(a, b) for a in rows for b in rows if a["mission"] == b["mission"] and a["seed"] == b["seed"]
                 and a["predictor"] == "none" and b["predictor"] == "learned" and name in ("all", a["mission"])]
        if not pairs:
            continue
        base = [steps_or_never(a["goal_step"], steps) for a, _ in pairs]
        learned = [steps_or_never(b["goal_step"], steps) for _, b in pairs]
        fill = [steps_or_never(a["fill_only_step"], steps) for a, _ in pairs]
        obs = [steps_or_never(b["observed_f1_step"], steps) for _, b in pairs]
        cov_a = [steps_or_never(a["coverage_95"], steps) for a, _ in pairs]
        cov_b = [steps_or_never(b["coverage_95"], steps) for _, b in pairs]
        mean = float(np.mean(base))
        out.append({
            "mission": name, "seeds": len(pairs),
            "never": {"without": sum(a["goal_step"] is None for a, _ in pairs),
                      "with": sum(b["goal_step"] is None for _, b in pairs)},
            "goal_without": mean, "goal_with": float(np.mean(learned)),
            "sooner": 1 - float(np.mean(learned)) / mean,
            "sooner_paired_steps": t_interval([a - b for a, b in zip(base, learned)]),
            "sooner_per_seed": [1 - b / a for a, b in zip(base, learned)],
            "with_sooner_later": [sum(b < a for a, b in zip(base, learned)), sum(b > a for a, b in zip(base, learned))],
            "observed_with": float(np.mean(obs)), "observed_sooner": 1 - float(np.mean(obs)) / mean,
            "fill_only": float(np.mean(fill)), "fill_only_sooner": 1 - float(np.mean(fill)) / mean,
            "coverage95_without": float(np.mean(cov_a)), "coverage95_with": float(np.mean(cov_b)),
            "bytes_ratio": sum(b["bytes"] for _, b in pairs) / sum(a["bytes"] for a, _ in pairs),
            "bytes_to_goal_ratio": (sum(b["bytes_to_goal"] or 0 for _, b in pairs)
                                    / max(sum(a["bytes_to_goal"] or 0 for a, _ in pairs), 1)
                                    if all(a["bytes_to_goal"] and b["bytes_to_goal"] for a, b in pairs) else None),
            "false_free_without": float(np.mean([a["false_free"] for a, _ in pairs])),
            "false_free_with": float(np.mean([b["false_free"] for _, b in pairs])),
            "filled_false_free_with": float(np.mean([b["filled_false_free"] for _, b in pairs])),
            "unobserved_accuracy": float(np.mean([b["unobserved_accuracy"] for _, b in pairs
                                                  if b["unobserved_accuracy"] is not None] or [np.nan])),
            "unobserved_all_free": float(np.mean([b["unobserved_all_free"] for _, b in pairs
                                                  if b["unobserved_all_free"] is not None] or [np.nan])),
            "mid_accuracy": _pooled(pairs, "mid_guessed_right"),
            "mid_all_free": _pooled(pairs, "mid_all_free_right"),
        })
    return out


def _pooled(pairs, key: str) -> float | None:
    """A share of the cells nobody had observed, pooled over the runs with the predictor
    (None for records made before it was counted)."""
    runs = [b for _, b in pairs if "mid_unobserved" in b]
    return sum(b[key] for b in runs) / max(sum(b["mid_unobserved"] for b in runs), 1) if runs else None


def markdown(result: dict) -> str:
    steps = result["steps"]
    ablation = result.get("ablation", "none")
    lines = [f"`{result['command']}` ({result['machine']}); {steps} steps, `predictive`, 4 rovers; a run that "
             f"never reaches a level counts as {steps + NEVER}"
             + ("." if ablation == "none" else f"; ablation: **{ablation}** in the runs with the predictor."), "",
             "| mission | seeds | F1≥0.9 without (observed belief) | with (guesses filled in) | sooner | paired, "
             "steps [95 % CI] | sooner / later | with: observed belief | fill only (no planning use) | 95 % "
             "coverage without → with | bytes with / without | bytes to the goal | false-free observed, "
             "without / with | false-free filled, with | guesses right on unobserved (all free) | the same, "
             f"every evaluation to step {MID_STEP} |",
             "|---|---:|---:|---:|---:|---|---|---:|---:|---|---:|---:|---|---:|---|---|"]
    for s in result["summary"]:
        d, lo, hi = s["sooner_paired_steps"]
        never = s["never"]
        lines.append(
            f"| {s['mission']} | {s['seeds']} | {s['goal_without']:.0f}"
            + (f" ({never['without']} never)" if never["without"] else "")
            + f" | {s['goal_with']:.0f}" + (f" ({never['with']} never)" if never["with"] else "")
            + f" | **{s['sooner']:.1%}** | {d:.1f} [{lo:.1f}, {hi:.1f}] | {s['with_sooner_later'][0]} / "
            f"{s['with_sooner_later'][1]} | {s['observed_with']:.0f} ({s['observed_sooner']:.1%}) | "
            f"{s['fill_only']:.0f} ({s['fill_only_sooner']:.1%}) | {s['coverage95_without']:.0f} → "
            f"{s['coverage95_with']:.0f} | {s['bytes_ratio']:.3f} | "
            + ("-" if s["bytes_to_goal_ratio"] is None else f"{s['bytes_to_goal_ratio']:.3f}")
            + f" | {s['false_free_without']:.4f} / {s['false_free_with']:.4f} | {s['filled_false_free_with']:.4f} | "
            f"{s['unobserved_accuracy']:.3f} ({s['unobserved_all_free']:.3f}) | "
            + ("-" if s.get("mid_accuracy") is None else f"{s['mid_accuracy']:.3f} ({s['mid_all_free']:.3f})") + " |")
    return "\n".join(lines) + "\n"


def figure(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = result["steps"]
    fig, ax = plt.subplots(figsize=(5.2, 5))
    for i, name in enumerate(dict.fromkeys(r["mission"] for r in result["runs"])):
        by = {(r["seed"], r["predictor"]): r for r in result["runs"] if r["mission"] == name}
        xs = [steps_or_never(by[(s, "none")]["goal_step"], steps) for s, p in by if p == "none" and (s, "learned") in by]
        ys = [steps_or_never(by[(s, "learned")]["goal_step"], steps) for s, p in by if p == "none" and (s, "learned") in by]
        ax.scatter(xs, ys, color=f"C{i}", label=name, alpha=0.8)
    lo, hi = 0, steps + NEVER + 10
    ax.plot([lo, hi], [lo, hi], color="0.5", lw=1, label="as soon")
    ax.plot([lo, hi], [lo, 0.85 * hi], color="0.5", lw=1, ls="--", label="15 % sooner")
    ax.axvline(steps, color="0.7", lw=0.8, ls=":", label=f"end of the mission ({steps + NEVER}: never)")
    ax.axhline(steps, color="0.7", lw=0.8, ls=":")
    ax.set(xlim=(lo, hi), ylim=(lo, hi), xlabel="without the predictor: step the observed belief reached F1 ≥ 0.9",
           ylabel="with it: step the belief with the guesses reached F1 ≥ 0.9",
           title="Team belief good enough to plan on (predictive)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write(result: dict, out: Path) -> None:
    """``planning.json``, ``planning.md`` and ``planning.png`` of ``result`` in ``out``; prints the table."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "planning.json").write_text(json.dumps(result, indent=1))
    md = markdown(result)
    (out / "planning.md").write_text(md)
    figure(result, out / "planning.png")
    print(md)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--missions", nargs="+", choices=MISSIONS, default=list(MISSIONS))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--ablation", choices=ABLATIONS, default="none", help="take a planning use away (see above)")
    ap.add_argument("--workers", type=int, default=2, help="missions run side by side, one thread each")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared/data")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/predictor_planning")
    ap.add_argument("--combine", type=Path, nargs="+", default=None,
                    help="planning.json files of earlier calls (same steps and ablation): their runs summarised as one, "
                         "no mission run")
    args = ap.parse_args()
    if args.combine:
        missing = [str(f) for f in args.combine if not f.is_file()]
        if missing:
            raise SystemExit(f"--combine: no such file: {', '.join(missing)}")
        parts = [json.loads(f.read_text()) for f in args.combine]
        if len({(q["steps"], q.get("ablation", "none")) for q in parts}) != 1:
            raise SystemExit("--combine: the files were made with other steps or ablations; combine like with like")
        rows = [r for q in parts for r in q["runs"]]
        seen = [(r["mission"], r["seed"], r["predictor"]) for r in rows]
        if len(set(seen)) != len(seen):
            raise SystemExit("--combine: a mission and seed is in two files; each run may count once")
        result = {**parts[0], "command": "python benchmarks/predictor_planning.py " + " ".join(sys.argv[1:]),
                  "runs": rows, "summary": summarise(rows, parts[0]["steps"]),
                  "seconds": sum(q["seconds"] for q in parts)}
        write(result, args.out)
        return
    jobs = [(name, seed, p, args.steps, str(args.data)) for name in args.missions for seed in args.seeds
            for p in ("none", "learned")]
    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(args.workers, initializer=init_worker, initargs=(args.ablation,)) as pool:
        for i, row in enumerate(pool.map(run_one, jobs), 1):
            rows.append(row)
            print(f"  {i}/{len(jobs)} {row['mission']} seed {row['seed']} {row['predictor']}: F1>=0.9 at "
                  f"{row['goal_step']}, {row['bytes']:,} B ({time.perf_counter() - t0:.0f} s)", flush=True)
    info = Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []
    cpu = next((ln.split(":", 1)[1].strip() for ln in info if ln.startswith("model name")), platform.machine())
    result = {"command": "python benchmarks/predictor_planning.py " + " ".join(sys.argv[1:]), "machine": cpu,
              "steps": args.steps, "ablation": args.ablation, "runs": rows, "summary": summarise(rows, args.steps),
              "seconds": time.perf_counter() - t0}
    write(result, args.out)


if __name__ == "__main__":
    main()
