"""Does a rover that checks its guesses step aside where they cannot help, and keep them where they do?

    python benchmarks/predictor_step_aside.py [--seeds 0-3] [--steps 250] [--sites default,gale,hadley,zion,tujunga]

Per site and seed, the same `raw` mission three ways: without the predictor (``none``), with
it always on (``always``: ``predictor_check = false``), and with the check
(``check``: every 10 steps each rover hides patches of its own map's known cells next to its
frontier, guesses them, and plans with the guesses only while they beat "all free" there by 3 points).
It reports, on the **observed** belief, the first step the team's mean belief F1 reached 0.9
(``team_f1_step``; a run that never did counts as the mission's length) with its mean and 95 %
interval over the seeds, and how often the checks let the guesses in. ``zion`` and
``tujunga`` are DEMs the shipped predictor never saw (Earth, 90 m and 30 m cells); ``gale`` and
``hadley`` are the project's own sites. Results go to
``benchmarks/results/predictor_step_aside/`` (``results.json``, ``results.md``).
Needs ``../shared/data`` for the real sites.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

from predictor_planning import t_interval  # (this folder: mean and 95 % t interval)

from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.sim import prepare_mission

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "predictor_step_aside"
MODES = {"none": {}, "always": {"predictor": "learned", "predictor_check": False},
         "check": {"predictor": "learned", "predictor_check": True}}


def sites(data: Path) -> dict[str, tuple[Path | None, dict | None, dict | None]]:
    """name -> (mission file or None for the default, terrain replacing the file's, thresholds laid over)."""
    tujunga = {"kind": "dem", "path": str(data / "earth/bigtujunga.tif"), "crop": 256, "size": 128}
    zion = {"kind": "dem", "path": str(data / "earth/zion_srtm.tif"), "crop": 256, "size": 128}
    return {"default": (None, None, None),
            "gale": (ROOT / "examples/mission_gale.toml", None, None),
            "hadley": (ROOT / "examples/mission_hadley.toml", None, None),
            "zion": (ROOT / "examples/mission_hadley.toml", zion, {"max_slope_deg": 25.0}),
            "tujunga": (ROOT / "examples/mission_hadley.toml", tujunga, {"max_slope_deg": 25.0})}


def one(spec, mode: str, seed: int, steps: int) -> dict:
    path, terrain, thresholds = spec
    overrides = [{"seed": seed, "mission": {"steps": steps, "strategies": ["raw"], **MODES[mode]}}]
    if thresholds:
        overrides.insert(0, {"thresholds": thresholds})
    config, source, _ = load_mission(path, terrain=terrain, overrides=overrides)
    truth, elevation, prior, profiles = mission_terrain(config, source)
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                        thresholds=source.thresholds, frames=1)
    run = m.new_run("raw")
    t0 = time.perf_counter()
    s = run.run().summary
    checks = run.world.checks
    return {"seed": seed, "team_f1_step": s.team_f1_step, "ready_step": s.ready_step,
            "coverage_95": s.coverage_steps.get(0.95), "seconds": round(time.perf_counter() - t0, 1),
            "checks": len(checks), "guessing_share": round(sum(c[5] for c in checks) / len(checks), 3) if checks else None,
            "check_accuracy": round(statistics.mean(c[3] for c in checks if c[2]), 3) if checks else None,
            "check_all_free": round(statistics.mean(c[4] for c in checks if c[2]), 3) if checks else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-3", help="A-B or a comma list")
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--sites", default="default,gale,hadley,zion,tujunga")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    lo, _, hi = a.seeds.partition("-")
    seeds = list(range(int(lo), int(hi) + 1)) if hi else [int(x) for x in a.seeds.split(",")]
    known = sites(a.data)
    rows = []
    for name in a.sites.split(","):
        for mode in MODES:
            runs = [one(known[name], mode, s, a.steps) for s in seeds]
            steps = [r["team_f1_step"] if r["team_f1_step"] is not None else a.steps for r in runs]
            mean, low, high = t_interval(steps)
            row = {"site": name, "mode": mode, "team_f1_step": [round(mean, 1), round(low, 1), round(high, 1)],
                   "reached": sum(r["team_f1_step"] is not None for r in runs), "runs": runs}
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "runs"}), flush=True)
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "results.json").write_text(json.dumps({"cpu": cpu, "seeds": seeds, "steps": a.steps, "rows": rows},
                                                   indent=1))
    lines = [f"# Stepping aside: `raw`, {a.steps} steps, seeds {a.seeds} ({cpu})", "",
             "| site | predictor | team belief F1 >= 0.9 at step (mean [95 %]) | reached | guesses in use, share of checks "
             "| checks: guesses right / all free |", "|---|---|---|---:|---:|---|"]
    for r in rows:
        m, lo_, hi_ = r["team_f1_step"]
        share = [x["guessing_share"] for x in r["runs"] if x["guessing_share"] is not None]
        acc = [(x["check_accuracy"], x["check_all_free"]) for x in r["runs"] if x["check_accuracy"] is not None]
        lines.append(f"| {r['site']} | {r['mode']} | {m:.0f} [{lo_:.0f}, {hi_:.0f}] | {r['reached']}/{len(seeds)} | "
                     + (f"{statistics.mean(share):.2f}" if share else "-") + " | "
                     + (f"{statistics.mean(a_ for a_, _ in acc):.3f} / {statistics.mean(f for _, f in acc):.3f}"
                        if acc else "-") + " |")
    (a.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
