"""Every speed figure of the project's speed targets in one run, each as a ratio where one
exists, on this CPU (its model and the instructions that decide the precision are printed).

    python benchmarks/speed_report.py              # peaks, the demo against its FLOP floor, default mission (~2 min)
    python benchmarks/speed_report.py --paper-mission  # + the paper strategy's default mission (about 2 min)
    python benchmarks/speed_report.py --deployed   # + a mission on processes against in process (predictive, 4 rovers)
    python benchmarks/speed_report.py --big        # + 1024², 16 rovers, 300 steps, raw + central (several minutes)
    python benchmarks/speed_report.py --scaling    # + the growth exponent with steps growing with the side (~1.5 min)
    python benchmarks/speed_report.py --suite      # + the README's test command, timed (install excluded)
    python benchmarks/speed_report.py --fp32       # + the demo in fp32 against the fp32 peak (where bf16 is native)

The figures:

- **matmul peaks**: best GFLOP/s of a 2048³ product in fp32, and in bf16 where it is native
  (an emulated bf16 peak is not a peak anyone should train at).
- **the demo** (``fedmap demo``, the README's main job, run as that command): its wall time,
  and its paper half against the FLOP floor, the paper network's matrix-product FLOPs
  (forward and backward, :func:`precision_speed.step_flops`) over every pixel-pass it
  trains (4 rovers x epochs x cells federated, epochs x cells centralised) at the matmul
  peak of the precision it trained in.
- **federated against centralised**, per pixel-pass, and each one's GFLOP/s against the peak.
- **the default mission** (``fedmap mission --no-animation``, as that command): its wall time.
- ``--paper-mission``: ``fedmap mission --strategies paper --no-animation``, its wall time.
- ``--deployed``: the default mission's ``predictive`` run on processes (SuperLink, a
  SuperNode per rover, the ServerApp; :mod:`mission_processes`) over the same in process.
- ``--big``: ``raw`` + ``central`` at 1024² with 16 rovers for 300 steps (:mod:`mission_scaling`).
- ``--scaling``: the growth exponent of a mission's time against cells x agents, 128², 256²
  and 512² with 4 and 8 rovers and 100, 200 and 400 steps (steps growing with the side;
  ``none``, ``raw``, ``central``; :mod:`mission_scaling`).
- ``--suite``: ``python -m pytest`` in this checkout.
- ``--fp32``: where bf16 is native, the demo again with ``--precision fp32``, against the
  fp32 peak: what an AVX2-only CPU runs (it has no bf16), as ratios comparable across CPUs.

Writes ``benchmarks/results/speed_report.json`` (``--out``) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from precision_speed import matmul_peak, step_flops  # noqa: E402

from fedmap.config import load_run  # noqa: E402
from fedmap.nets.model import build_model  # noqa: E402
from fedmap.nets.training import native_bf16, resolve_precision  # noqa: E402

OUT = HERE / "results" / "speed_report.json"
DEMO_TARGET_S, DEMO_FLOOR_RATIO, MISSION_TARGET_S, SUITE_TARGET_S = 45.0, 1.3, 25.0, 420.0
PAPER_MISSION_TARGET_S = 120.0


def cpu() -> dict:
    """The CPU's model name, cores and the instructions that decide bf16 and the matmul peak."""
    model, flags = "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():  # every core repeats both: take the first
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    model = model or platform.processor() or platform.machine()
    wanted = ("avx2", "fma", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile")
    return {"model": model, "cores": os.cpu_count(), "usable_cores": len(os.sched_getaffinity(0)),
            "flags": [f for f in wanted if f in flags], "native_bf16": native_bf16()}


def timed(argv: list[str], cwd: Path | None = None) -> tuple[float, subprocess.CompletedProcess]:
    t = time.perf_counter()
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True)
    seconds = time.perf_counter() - t
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return seconds, done


def demo(peaks: dict[str, float], precision: str | None = None) -> dict:
    """``fedmap demo`` as the README runs it (``precision``: with ``--precision``), and its
    paper half against its FLOP floor."""
    with tempfile.TemporaryDirectory(prefix="fedmap-speed-") as tmp:
        wall, _ = timed([sys.executable, "-m", "fedmap", "demo", "-o", str(Path(tmp) / "demo"),
                         *(["--precision", precision] if precision else [])])
        timings = {m: json.loads((Path(tmp) / "demo" / m / "metrics.json").read_text())["timings"]
                   for m in ("paper", "fedmap")}
    _, _, truth, pc = load_run(None, [{"method": "paper"}])
    # the paper trains every cell (unknown ones towards grey), full batch: an epoch is a pass over the map
    assert not pc.federation.local.masked and not pc.train.masked, "the paper preset trains every cell"
    n = truth.classes.size
    flop = step_flops(build_model(pc.model.network(truth.shape[0])), 1)  # per pixel-pass
    fed_passes = pc.explore.agents * pc.federation.rounds * pc.federation.local.epochs * n
    central_passes = pc.federation.rounds * pc.train.epochs * n
    precision = precision or resolve_precision(pc.train.precision)
    peak = peaks[precision]
    t = timings["paper"]
    fed_s, central_s = t["federation_s"], t["central_s"]
    floor = (fed_passes + central_passes) * flop / (peak * 1e9)
    inside = sum(sum(v.values()) for v in timings.values())
    return {"wall_s": round(wall, 1), "inside_s": round(inside, 1), "paper_s": round(sum(t.values()), 1),
            "paper_federated_s": round(fed_s, 1), "paper_central_s": round(central_s, 1),
            "fedmap_s": round(sum(timings["fedmap"].values()), 1), "precision": precision,
            "flop_per_pixel_pass": flop, "tflop": round((fed_passes + central_passes) * flop / 1e12, 2),
            "flop_floor_s": round(floor, 1), "paper_training_over_floor": round((fed_s + central_s) / floor, 2),
            "wall_over_floor": round(wall / floor, 2),
            "federated_us_per_pixel_pass": round(fed_s / fed_passes * 1e6, 2),
            "central_us_per_pixel_pass": round(central_s / central_passes * 1e6, 2),
            "federated_over_central": round((fed_s / fed_passes) / (central_s / central_passes), 3),
            "federated_of_peak": round(fed_passes * flop / fed_s / 1e9 / peak, 3),
            "central_of_peak": round(central_passes * flop / central_s / 1e9 / peak, 3)}


def fit_steps(peaks: dict[str, float], precision: str, steps: int = 25) -> dict:
    """The paper network's training steps alone: ``fit`` (the code every rover and the
    centralised bound train with) on the demo's 128² map, every cell, full batch, in
    ``precision``; the median step (after 5 to warm up) against the FLOP floor of a step
    at that precision's matmul peak. The demo's stage times add each stage's rendering,
    encoding and scoring to these steps."""
    from dataclasses import replace

    from fedmap.nets.training import fit

    _, _, truth, pc = load_run(None, [{"method": "paper"}])
    model = build_model(pc.model.network(truth.shape[0]))
    stamps: list[float] = []
    fit(model, truth, replace(pc.train, epochs=steps, precision=precision),
        on_step=lambda step, loss: stamps.append(time.perf_counter()))
    step_s = float(np.median(np.diff(stamps)[5:]))
    flop = step_flops(model, 1) * truth.classes.size
    return {"precision": precision, "steps": steps, "median_step_ms": round(step_s * 1e3, 1),
            "gflops": round(flop / step_s / 1e9, 1), "of_peak": round(flop / step_s / 1e9 / peaks[precision], 3)}


def mission() -> dict:
    with tempfile.TemporaryDirectory(prefix="fedmap-speed-") as tmp:
        wall, _ = timed([sys.executable, "-m", "fedmap", "mission", "--no-animation", "-o", str(Path(tmp) / "m")])
    return {"wall_s": round(wall, 1)}


def paper_mission() -> dict:
    """The paper strategy in the default mission, whole-map training (its default)."""
    with tempfile.TemporaryDirectory(prefix="fedmap-speed-") as tmp:
        wall, _ = timed([sys.executable, "-m", "fedmap", "mission", "--strategies", "paper", "--no-animation",
                         "-o", str(Path(tmp) / "m")])
    return {"wall_s": round(wall, 1)}


def deployed() -> dict:
    from mission_processes import one

    row = one("predictive", 4, 150, 0.05)
    return {k: row[k] for k in ("in_process_s", "on_processes_run_s", "ratio_run", "per_round_s", "start_up_s",
                                "on_processes_wall_s", "ratio_wall", "same_metrics")}


def big() -> dict:
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fedmap-speed-") as tmp:
        _, done = timed([sys.executable, str(HERE / "mission_scaling.py"), "--sizes", "1024", "--agents", "16",
                         "--steps", "300", "--strategies", "raw,central", "--workers", "2", "--out", tmp])
    return {"wall_s": round(time.perf_counter() - t, 1), "output": done.stdout[-1500:]}


def scaling() -> dict:
    with tempfile.TemporaryDirectory(prefix="fedmap-speed-") as tmp:
        timed([sys.executable, str(HERE / "mission_scaling.py"), "--sizes", "128", "256", "512", "--agents", "4", "8",
               "--steps", "100", "--steps-grow", "1", "--strategies", "none,raw,central", "--out", tmp])
        return {"exponents": json.loads((Path(tmp) / "scaling.json").read_text())["exponents"]}


def suite() -> dict:
    wall, done = timed([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=HERE.parent)
    return {"wall_s": round(wall, 1), "summary": done.stdout.strip().splitlines()[-1]}


def table(r: dict) -> list[str]:
    p, d, m = r["peaks_gflops"], r["demo"], r["mission"]
    rows = [("matmul peak", f"fp32 {p['fp32']:.0f} GFLOP/s" + (f", bf16 {p['bf16']:.0f}" if "bf16" in p else
                                                              " (bf16 not native: not measured)"), "-"),
            ("`fedmap demo` wall (README command)", f"{d['wall_s']} s (inside {d['inside_s']} s: paper "
             f"{d['paper_s']} s, fedmap {d['fedmap_s']} s), {d['precision']}",
             f"< {DEMO_TARGET_S:.0f} s where bf16 is native: {'met' if d['wall_s'] < DEMO_TARGET_S else 'not met'}"),
            ("paper training / its FLOP floor", f"{d['paper_training_over_floor']}x ({d['tflop']} TFLOP, floor "
             f"{d['flop_floor_s']} s at the {d['precision']} peak); demo wall / floor {d['wall_over_floor']}x",
             f"demo <= {DEMO_FLOOR_RATIO}x its fp32 floor on AVX2-only CPUs"),
            ("federated / central per pixel-pass", f"{d['federated_over_central']}x ({d['federated_us_per_pixel_pass']}"
             f" vs {d['central_us_per_pixel_pass']} us)", "<= 1.05x"),
            ("paper steps against the peak", f"federated {d['federated_of_peak']:.0%}, central {d['central_of_peak']:.0%}"
             f" of the {d['precision']} peak (stage times: each rover's fit, render, encode and scoring; the "
             f"bound's fit, render and scoring)", ">= 70 %"),
            ("paper training steps alone (`fit`'s loop, 128², median step)",
             ", ".join(f"{f['precision']} {f['median_step_ms']} ms, {f['gflops']:.0f} GFLOP/s, {f['of_peak']:.0%} of its "
                       "peak" for f in r["fit_steps"]), ">= 70 %"),
            ("`fedmap mission --no-animation` wall", f"{m['wall_s']} s",
             f"< {MISSION_TARGET_S:.0f} s: {'met' if m['wall_s'] < MISSION_TARGET_S else 'not met'}")]
    if "demo_fp32" in r:
        f = r["demo_fp32"]
        rows += [("in fp32 (what an AVX2-only CPU runs): `fedmap demo --precision fp32` wall / its fp32 floor",
                  f"{f['wall_over_floor']}x ({f['wall_s']} s, floor {f['flop_floor_s']} s; paper training "
                  f"{f['paper_training_over_floor']}x)", f"<= {DEMO_FLOOR_RATIO}x"),
                 ("in fp32: federated / central per pixel-pass", f"{f['federated_over_central']}x", "<= 1.05x"),
                 ("in fp32: paper steps against the fp32 peak", f"federated {f['federated_of_peak']:.0%}, "
                  f"central {f['central_of_peak']:.0%}", ">= 70 %")]
    if "paper_mission" in r:
        w = r["paper_mission"]["wall_s"]
        rows.append(("`fedmap mission --strategies paper --no-animation` wall", f"{w} s",
                     f"< {PAPER_MISSION_TARGET_S:.0f} s: {'met' if w < PAPER_MISSION_TARGET_S else 'not met'}"))
    if "deployed" in r:
        e = r["deployed"]
        rows.append(("predictive, 4 rovers: on processes / in process", f"{e['ratio_run']}x ({e['on_processes_run_s']}"
                     f" vs {e['in_process_s']} s; {e['per_round_s']} s a round; {e['ratio_wall']}x with start-up)",
                     "<= 1.5x"))
    if "big" in r:
        rows.append(("1024², 16 rovers, 300 steps, raw + central", f"{r['big']['wall_s']} s", "< 300 s"))
    if "scaling" in r:
        e = {n: v for n, v in r["scaling"]["exponents"].items() if v is not None}
        rows.append(("growth exponent against cells x agents (steps grow with the side)",
                     ", ".join(f"{n} {v:.2f}" for n, v in e.items()),
                     f"<= 1.1: {'met' if max(e.values()) <= 1.1 else 'not met'}"))
    if "suite" in r:
        s = r["suite"]
        rows.append(("the README's test command", f"{s['wall_s']} s ({s['summary']})", f"< {SUITE_TARGET_S:.0f} s"))
    lines = ["| what | measured | target |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paper-mission", action="store_true",
                    help="also the paper strategy's default mission (about 2 min)")
    ap.add_argument("--deployed", action="store_true", help="also a mission on processes (about 2 min)")
    ap.add_argument("--big", action="store_true", help="also 1024², 16 rovers, 300 steps (several minutes)")
    ap.add_argument("--scaling", action="store_true", help="also the growth exponent (about 1.5 min)")
    ap.add_argument("--suite", action="store_true", help="also the README's test command (10-15 min)")
    ap.add_argument("--fp32", action="store_true", help="also the demo in fp32 against the fp32 peak, what an "
                    "AVX2-only CPU runs (about 1.5 min where bf16 is native)")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    r: dict = {"cpu": cpu(), "threads": torch.get_num_threads(), "load_average_before": os.getloadavg()[0]}
    print(f"CPU: {r['cpu']['model']}, {r['cpu']['usable_cores']} cores, {' '.join(r['cpu']['flags'])}; "
          f"bf16 {'native' if r['cpu']['native_bf16'] else 'not native'}")
    r["peaks_gflops"] = {"fp32": round(matmul_peak(torch.float32), 1)}
    if r["cpu"]["native_bf16"]:
        r["peaks_gflops"]["bf16"] = round(matmul_peak(torch.bfloat16), 1)
    r["fit_steps"] = [fit_steps(r["peaks_gflops"], p) for p in r["peaks_gflops"]]
    r["demo"] = demo(r["peaks_gflops"])
    if a.fp32 and r["demo"]["precision"] != "fp32":
        r["demo_fp32"] = demo(r["peaks_gflops"], "fp32")
    r["mission"] = mission()
    if a.paper_mission:
        r["paper_mission"] = paper_mission()
    if a.deployed:
        r["deployed"] = deployed()
    if a.big:
        r["big"] = big()
    if a.scaling:
        r["scaling"] = scaling()
    if a.suite:
        r["suite"] = suite()
    r["load_average_after"] = os.getloadavg()[0]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(r, indent=1))
    print("\n".join(table(r)))
    print(f"load average {r['load_average_before']:.1f} before, {r['load_average_after']:.1f} after; wrote {a.out}")


if __name__ == "__main__":
    main()
