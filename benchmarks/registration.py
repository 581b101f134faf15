"""Registering maps in unknown frames on real terrain: fedmap's gated registration against
m-explore map_merge's OpenCV pipeline (AKAZE features, affine-partial RANSAC, its
confidence gate), on the same seeded pairs.

    python benchmarks/registration.py [--pairs 100] [--size 128] [--data ../shared/data]
                                      [--out benchmarks/results/registration] [--figure docs/img/registration_success.png]

Terrain: five DEMs classified with fedmap's own traversability rules
(:func:`fedmap.maps.traversability.dem_to_traversability`): Gale crater HiRISE 1 m
(default limits), Zion SRTM 74 m (default), Big Tujunga 30 m (slope limit p75), the Moon's
GLD100 2x2 tiles at Hadley Rille (default) and at 14-16 E 22-24 N (p75), 118 m.

A pair: map A is a ``size`` x ``size`` window of a terrain; map B a window of the same
terrain turned by a heading drawn uniformly in [0, 360) deg and placed so that its
footprint covers the requested share of A's (10 ... 80 %; the direction is drawn
uniformly). Both are then degraded independently: a rover-like exploration mask (discs of
12 cells along a random walk until 75 % of the window is known; the rest UNKNOWN) and 2 %
of the known cells flipped. The 0 % level holds pairs with no true overlap: B from
another terrain, or a window of the same terrain that does not meet A's. Every choice is
drawn from ``numpy.random.default_rng((seed, level, pair))``.

Correct: heading within 2 deg and the centre of the true overlap placed within 1 cell.
Confirmable: the gate's own check (kappa, shared cells, cells of each class; margin aside)
passes on the true placement. A pair that is not has a true overlap with too little
structure for any placement to be confirmed (refusing it is right); the report gives the
share correct of all pairs (the issue's measure) and of the confirmable ones.
Per overlap level and method: correct merges, wrong merges accepted (the hazard; of them,
those off by more than 5 deg or 3 cells, or with no overlap at all), refused merges (of
them, those whose estimate was right), and milliseconds per merge (estimate + gate, wall
and CPU). Records made under a lower kappa gate or a smaller evidence margin than the
library's defaults are judged by the defaults (:func:`regate`). AKAZE's gate is map_merge's
``estimation_confidence``: OpenCV's ``AffineBestOf2NearestMatcher`` confidence
``inliers / (8 + 0.3 matches)`` must reach 0.6 (the ROS 2 port's params.yaml; the ROS 1
node's default 1.0 is in the JSON too). The maps go to OpenCV as map_merge feeds them: the
OccupancyGrid bytes (free 0, occupied 100, unknown -1 = 255).

``--coverage 1 --flips 0`` gives the same pairs without noise (``--figure ''``: no figure).
Writes every pair's record to ``--out`` (``level_NN.json``, one file per overlap level, as
each level is done; ``--levels`` runs some levels only, and the runs over parts add up),
the table of every level there to ``registration.json``, and the success figure to
``--figure``; prints the table. Needs the data folder; the package never does.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from fedmap._util import to_json
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.io import load_dem, mosaic_heightmap_tiles
from fedmap.maps.registration import (
    DEFAULT_GATE,
    DEFAULT_MARGIN,
    DEFAULT_MIN_OVERLAP,
    FEW_PATCHES,
    RigidTransform,
    agreement,
    gate_verdict,
    register,
)
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability

LEVELS = (0, 10, 20, 30, 40, 50, 60, 70, 80)
HEADING_TOL, CELL_TOL = 2.0, 1.0
AKAZE_GATES = (0.6, 1.0)  # m-explore-ros2 params.yaml; m-explore (ROS 1) map_merge default


def terrains(data: Path) -> dict[str, np.ndarray]:
    """Name -> class grid of every terrain the pairs are cut from."""
    p75 = TraversabilityThresholds(max_slope_percentile=75)
    moon = data / "moon/gld100_256p"
    dems = {"gale_1m": (load_dem(data / "mars/missionDEM_gale_1m.tif"), None),
            "zion_74m": (load_dem(data / "earth/zion_srtm.tif"), None),
            "bigtujunga_30m": (load_dem(data / "earth/bigtujunga.tif"), p75),
            "hadley_118m": (mosaic_heightmap_tiles(moon, lon=0, lat=22, n=2), None),
            "moon14e_118m": (mosaic_heightmap_tiles(moon, lon=14, lat=22, n=2), p75)}
    return {name: dem_to_traversability(dem, t).classes for name, (dem, t) in dems.items()}


# --------------------------------------------------------------------------- pairs


def window(terrain: np.ndarray, centre: np.ndarray, heading: float, n: int) -> tuple[np.ndarray, RigidTransform]:
    """An ``n`` x ``n`` window of ``terrain`` turned by ``heading`` about ``centre``, and the
    transform from the window's frame into the terrain's."""
    c = np.array([(n - 1) / 2.0, (n - 1) / 2.0])
    r = RigidTransform(0.0, 0.0, heading).matrix()[:2, :2]
    t = centre - r @ c
    to_terrain = RigidTransform(float(t[0]), float(t[1]), heading)
    return to_terrain.inverse().apply(terrain, (n, n)), to_terrain


def covered(b_to_a: RigidTransform, n: int) -> np.ndarray:
    """A's cells that B's footprint covers (B is ``n`` x ``n``)."""
    rc = np.argwhere(np.ones((n, n), dtype=bool))
    back = b_to_a.inverse().map_points(rc)
    inside = np.all((back > -0.5) & (back < n - 0.5), axis=1)
    return inside.reshape(n, n)


def place(terrain: np.ndarray, n: int, share: float, rng: np.random.Generator):
    """Centres of A and B (B turned by a random heading) whose footprints overlap by ``share``
    of A, both inside the terrain; None when 200 draws find no room."""
    h, w = terrain.shape
    half_a, half_b = n / 2 + 1, n / math.sqrt(2) + 1
    for _ in range(200):
        heading, phi = rng.uniform(0.0, 360.0), rng.uniform(0.0, 2 * math.pi)
        u = np.array([math.sin(phi), math.cos(phi)])
        lo, hi = 0.0, 1.6 * n  # overlap falls with the distance: bisect for the share
        for _ in range(30):
            d = (lo + hi) / 2
            t = RigidTransform(*(u * d + (n - 1) / 2.0 - RigidTransform(0, 0, heading).matrix()[:2, :2]
                                 @ np.full(2, (n - 1) / 2.0)), heading)
            if covered(t, n).mean() > share:
                lo = d
            else:
                hi = d
        ca = np.array([rng.uniform(half_a, h - half_a), rng.uniform(half_a, w - half_a)])
        cb = ca + u * (lo + hi) / 2
        if half_b <= cb[0] <= h - half_b and half_b <= cb[1] <= w - half_b:
            return ca, cb, heading
    return None


def explore(n: int, rng: np.random.Generator, coverage: float = 0.75, radius: int = 12) -> np.ndarray:
    """Cells a rover sees along a random walk (discs of ``radius``) until ``coverage`` is known."""
    if coverage >= 1.0:
        return np.ones((n, n), dtype=bool)
    seen = np.zeros((n, n), dtype=bool)
    pos, heading = rng.uniform(0, n, size=2), rng.uniform(0, 2 * math.pi)
    rr, cc = np.mgrid[0:n, 0:n]
    while seen.mean() < coverage:
        seen |= (rr - pos[0]) ** 2 + (cc - pos[1]) ** 2 <= radius**2
        heading += rng.normal(0.0, 0.6)
        step = pos + 4.0 * np.array([math.sin(heading), math.cos(heading)])
        if not (0 <= step[0] < n and 0 <= step[1] < n):
            heading += math.pi  # turn back at the edge
            continue
        pos = step
    return seen


#: Noise of a pair's maps: the share of each window a rover explored, and of its known cells flipped.
NOISE = {"coverage": 0.75, "flips": 0.02}


def degrade(classes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An exploration mask (:data:`NOISE` coverage) and :data:`NOISE` flips of the known cells flipped."""
    flips = NOISE["flips"]
    out = classes.copy()
    out[~explore(classes.shape[0], rng, NOISE["coverage"])] = UNKNOWN
    known = out != UNKNOWN
    flip = known & (rng.random(out.shape) < flips)
    out[flip] = np.where(out[flip] == FREE, IMPASSABLE, FREE)
    return out


def make_pair(maps: dict[str, np.ndarray], n: int, level: int, seed: int, index: int):
    """``(a, b, truth or None, record)`` of one pair (``truth``: B's frame -> A's)."""
    rng = np.random.default_rng((seed, level, index))
    names = sorted(maps)
    name = names[index % len(names)]
    terrain = maps[name]
    if level == 0:  # no true overlap: another terrain (odd pairs), or a window of this one that misses A
        ca = np.array([rng.uniform(n / 2 + 1, s - n / 2 - 1) for s in terrain.shape])
        a, _ = window(terrain, ca, 0.0, n)
        other = names[(index + 1 + int(rng.integers(len(names) - 1))) % len(names)] if index % 2 else name
        far = n / math.sqrt(2) + n / math.sqrt(2) + 2  # the two windows' circumscribed circles do not meet
        for _ in range(1000):
            cb = np.array([rng.uniform(n / math.sqrt(2) + 1, s - n / math.sqrt(2) - 1) for s in maps[other].shape])
            if other != name or np.linalg.norm(cb - ca) > far:
                break
            if _ == 999:  # this terrain has no room for two windows apart: take the next one
                other = names[(names.index(name) + 1) % len(names)]
        b, _ = window(maps[other], cb, rng.uniform(0.0, 360.0), n)
        return degrade(a, rng), degrade(b, rng), None, {"terrain": name, "b_terrain": other}
    placed = place(terrain, n, level / 100, rng)
    if placed is None:
        raise SystemExit(f"{name}: no room for {level} % overlap at size {n}")
    ca, cb, heading = placed
    a, a_to_t = window(terrain, ca, 0.0, n)
    b, b_to_t = window(terrain, cb, heading, n)
    truth = a_to_t.inverse().compose(b_to_t)
    return degrade(a, rng), degrade(b, rng), truth, {"terrain": name, "heading": heading,
                                                     "footprint_overlap": float(covered(truth, n).mean())}


# --------------------------------------------------------------------------- scoring


def error(est: RigidTransform, truth: RigidTransform, n: int) -> tuple[float, float]:
    """Heading error (deg) and the distance (cells) between where ``est`` and ``truth`` put the
    centre of the true overlap."""
    rc = np.argwhere(np.ones((n, n), dtype=bool))
    inside = np.all((truth.map_points(rc) > -0.5) & (truth.map_points(rc) < n - 0.5), axis=1)
    centre = rc[inside].mean(axis=0) if inside.any() else np.full(2, (n - 1) / 2.0)
    d = float(np.linalg.norm(est.map_points(centre) - truth.map_points(centre)))
    dh = abs((est.heading_deg - truth.heading_deg + 180.0) % 360.0 - 180.0)
    return float(dh), d


def truth_confirmable(a: np.ndarray, b: np.ndarray, truth: RigidTransform | None) -> bool:
    """Whether the gate's own check passes on the true placement (margin aside): the maps share
    at least ``min_overlap`` known cells there, with :data:`MIN_CLASS_CELLS` of each class in
    each map, at a kappa of at least the gate. A pair that fails it has a true overlap with too
    little structure to confirm any placement (an all-free stretch, say); refusing it is
    right, so the report also gives the share correct among the pairs that pass."""
    return truth is not None and gate_verdict(agreement(a, truth.apply(b, a.shape)))[0]


def with_truth_check(rows: list[dict], maps, n: int, seed: int) -> list[dict]:
    """``rows`` with ``truth_confirmable`` filled in where a record made before it lacks it
    (the pair is made again from its seed: no registration is run)."""
    out = []
    for r in rows:
        if "truth_confirmable" not in r:
            a, b, truth, _ = make_pair(maps, n, r["level"], seed, r["pair"])
            r = {**r, "truth_confirmable": truth_confirmable(a, b, truth)}
        out.append(r)
    return out


def occupancy_image(classes: np.ndarray) -> np.ndarray:
    """The bytes map_merge hands OpenCV: OccupancyGrid data (free 0, occupied 100, unknown -1) as uint8."""
    return np.select([classes == FREE, classes == IMPASSABLE], [0, 100], 255).astype(np.uint8)


def akaze(a: np.ndarray, b: np.ndarray) -> tuple[RigidTransform | None, float]:
    """map_merge's estimate of B's frame -> A's and its confidence (None when OpenCV finds none)."""
    finder = cv2.AKAZE_create()
    fa = cv2.detail.computeImageFeatures2(finder, occupancy_image(a))
    fb = cv2.detail.computeImageFeatures2(finder, occupancy_image(b))
    if min(len(fa.keypoints), len(fb.keypoints)) < 2:  # OpenCV's 2-nearest matcher needs two features a side
        return None, 0.0
    info = cv2.detail_AffineBestOf2NearestMatcher(False, False, 0.3).apply(fb, fa)  # points of B -> points of A
    if info.H is None or info.num_inliers == 0:
        return None, float(info.confidence)
    h = np.asarray(info.H, dtype=np.float64)
    swap = np.array([[0, 1, 0], [1, 0, 0], [0, 0, 1]], dtype=np.float64)  # OpenCV's (x, y) = our (col, row)
    return RigidTransform.from_matrix(swap @ h @ swap), float(info.confidence)


def judge(accepted: bool, est: RigidTransform | None, truth: RigidTransform | None, n: int) -> tuple[str, float, float]:
    """``correct``, ``wrong`` (accepted but wrong: the hazard), ``refused``, or ``missed``
    (refused although the estimate was right), with the errors."""
    if truth is None or est is None:
        return ("wrong" if accepted else "refused"), math.nan, math.nan
    dh, d = error(est, truth, n)
    good = dh <= HEADING_TOL and d <= CELL_TOL
    if accepted:
        return ("correct" if good else "wrong"), dh, d
    return ("missed" if good else "refused"), dh, d


# --------------------------------------------------------------------------- run


def progress(done: int, total: int, t0: float) -> None:
    line = f"  {done}/{total} pairs, {time.perf_counter() - t0:.0f} s"
    if sys.stdout.isatty():
        print("\r" + line, end="" if done < total else "\n", flush=True)
    elif done == total or done % 25 == 0:
        print(line, flush=True)


def run(maps, n: int, pairs: int, seed: int, levels, out: Path) -> None:
    """Every pair of ``levels``; each level's records go to ``out/level_NN.json`` when it is done."""
    total, t0, done = pairs * len(levels), time.perf_counter(), 0
    for level in levels:
        rows = []
        for i in range(pairs):
            a, b, truth, rec = make_pair(maps, n, level, seed, i)
            rec.update(level=level, pair=i, truth_confirmable=truth_confirmable(a, b, truth))
            cpu = time.process_time()
            reg = register(a, b)
            rec["fedmap"] = dict(zip(("outcome", "heading_err", "cell_err"), judge(reg.accepted, reg.transform, truth, n)),
                                 kappa=reg.confidence, overlap=reg.check.overlap, margin=reg.margin,
                                 patches=reg.patches,
                                 reason=reg.reason, ms=1000 * reg.seconds, cpu_ms=1000 * (time.process_time() - cpu))
            t, cpu = time.perf_counter(), time.process_time()
            est, conf = akaze(a, b)
            ms, cpu_ms = 1000 * (time.perf_counter() - t), 1000 * (time.process_time() - cpu)
            for gate in AKAZE_GATES:
                rec[f"akaze_{gate:g}"] = dict(zip(("outcome", "heading_err", "cell_err"),
                                                  judge(est is not None and conf >= gate, est, truth, n)),
                                              confidence=conf, ms=ms, cpu_ms=cpu_ms)
            rows.append(rec)
            done += 1
            progress(done, total, t0)
        out.mkdir(parents=True, exist_ok=True)
        (out / f"level_{level:02d}.json").write_text(to_json({"pairs": pairs, "size": n, "seed": seed, "noise": NOISE,
                                                               "rows": rows}))


def regate(rec: dict) -> dict:
    """A record made under a lower kappa gate or a smaller evidence margin than
    :data:`DEFAULT_GATE` and :data:`DEFAULT_MARGIN`, judged by them.

    A higher gate or a larger margin only refuses more, so an accepted record whose recorded
    kappa or margin falls short is refused now (and every other verdict stands): what a new
    run would give, without the new run."""
    f = dict(rec["fedmap"])
    if f["outcome"] in ("correct", "wrong") and f["kappa"] < DEFAULT_GATE:
        f["outcome"] = "missed" if f["outcome"] == "correct" else "refused"
        f["reason"] = f"confidence {f['kappa']:.2f} is below the gate {DEFAULT_GATE:.2f} ({f['overlap']} shared cells)"
    if f["outcome"] in ("correct", "wrong") and f["margin"] < DEFAULT_MARGIN:
        f["outcome"] = "missed" if f["outcome"] == "correct" else "refused"
        f["reason"] = (f"ambiguous: another placement fits almost as well (evidence margin {f['margin']:.1f}, "
                       f"needs {DEFAULT_MARGIN:g})")
    return {**rec, "fedmap": f}


def table(rows: list[dict], methods: tuple[str, ...], levels) -> list[dict]:
    out = []
    for level in levels:
        for m in methods:
            sel = [r[m] for r in rows if r["level"] == level]
            k = len(sel)
            count = lambda o: sum(s["outcome"] == o for s in sel)
            # a wrong merge far off (not a near miss): heading off by more than 5 deg or 3 cells, or no overlap at all
            far = sum(s["outcome"] == "wrong" and (level == 0 or s["heading_err"] > 5 or s["cell_err"] > 3) for s in sel)
            sure = [r[m] for r in rows if r["level"] == level and r.get("truth_confirmable")]
            out.append({"overlap": level, "method": m, "pairs": k, "correct": count("correct") / k,
                        "confirmable": len(sure),
                        "correct_of_confirmable": sum(s["outcome"] == "correct" for s in sure) / max(len(sure), 1),
                        "wrong_of_confirmable": sum(s["outcome"] == "wrong" for s in sure) / max(len(sure), 1),
                        "wrong_accepted": count("wrong") / k, "wrong_far_off": far / k,
                        "refused": (count("refused") + count("missed")) / k, "refused_but_right": count("missed") / k,
                        "ms_per_merge": float(np.mean([s["ms"] for s in sel])),
                        "cpu_ms_per_merge": float(np.mean([s["cpu_ms"] for s in sel]))})
    return out


def figure(summary: list[dict], path: Path, pairs: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.8), dpi=110)
    styles = {"fedmap": ("fedmap (gated)", "C0"),
              "akaze_0.6": ("map_merge AKAZE (gate 0.6)", "C3"), "akaze_1": ("map_merge AKAZE (gate 1.0)", "C1")}
    for m, (label, colour) in styles.items():
        rows = [r for r in summary if r["method"] == m and r["overlap"] > 0]
        x = [r["overlap"] for r in rows]
        ax.plot(x, [100 * r["correct"] for r in rows], "o-", color=colour, label=f"{label}: correct")
        ax.plot(x, [100 * r["wrong_accepted"] for r in rows], "x--", color=colour, label=f"{label}: wrong accepted")
    ax.set_xlabel("overlap (% of map A)")
    ax.set_ylabel(f"% of {pairs} pairs per level")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6.5, loc="center right")
    ax.set_title(f"Registering 128² traversability maps in unknown frames (5 real terrains,\n"
                 f"heading 0-360°, {NOISE['coverage']:.0%} explored, {NOISE['flips']:.0%} of cells flipped)", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/registration"))
    ap.add_argument("--figure", type=Path, default=Path("docs/img/registration_success.png"))
    ap.add_argument("--pairs", type=int, default=100, help="pairs per overlap level")
    ap.add_argument("--size", type=int, default=128, help="side of each map, cells")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--coverage", type=float, default=NOISE["coverage"], help="share of each window explored (1: all)")
    ap.add_argument("--flips", type=float, default=NOISE["flips"], help="share of known cells flipped")
    ap.add_argument("--levels", help="run these overlap levels only, e.g. 0,10,20 (the report holds every level in --out)")
    ap.add_argument("--report-only", action="store_true", help="no new pairs: the report of the levels in --out")
    args = ap.parse_args()
    NOISE.update(coverage=args.coverage, flips=args.flips)
    cv2.setNumThreads(1)
    maps = terrains(args.data)
    for name, c in maps.items():
        print(f"{name:16s} {c.shape[0]}x{c.shape[1]} cells, {np.mean(c == IMPASSABLE):.1%} impassable")
    levels = LEVELS if args.levels is None else tuple(int(v) for v in args.levels.split(","))
    if not args.report_only:
        run(maps, args.size, args.pairs, args.seed, levels, args.out)
    # the report: every level whose records are in --out (runs over parts of LEVELS add up)
    parts = [json.loads(p.read_text()) for p in sorted(args.out.glob("level_*.json"))]
    found = {(p["pairs"], p["size"], p["seed"]) for p in parts}
    parts = [p for p in parts if (p["pairs"], p["size"], p["seed"], p["noise"]) == (args.pairs, args.size, args.seed, NOISE)]
    if not parts:  # nothing to report: keep the report that is there
        raise SystemExit(f"no records in {args.out} for --pairs {args.pairs} --size {args.size} --seed {args.seed} and "
                         f"this noise (there: {sorted(found) or 'none'} as (pairs, size, seed))")
    rows = with_truth_check([regate(r) for p in parts for r in p["rows"]], maps, args.size, args.seed)
    have = sorted({r["level"] for r in rows})
    methods = ("fedmap", *(f"akaze_{g:g}" for g in AKAZE_GATES))
    summary = table(rows, methods, have)
    print(f"\n{'overlap':>7s}  {'method':10s} {'correct':>8s} {'wrong acc.':>10s} {'refused':>8s} {'ms/merge':>9s}"
          f"  {'confirmable':>11s} {'correct of them':>15s}")
    for r in summary:
        print(f"{r['overlap']:6d}%  {r['method']:10s} {r['correct']:8.1%} {r['wrong_accepted']:10.1%} {r['refused']:8.1%} "
              f"{r['ms_per_merge']:9.0f}  {r['confirmable']:11d} {r['correct_of_confirmable']:15.1%}")
    sel = [r for r in rows if r["level"] >= 30]  # the measure: every pair at >= 30 % overlap
    sure = [r for r in sel if r.get("truth_confirmable")]
    for m in methods if sel else ():
        right = lambda rs: sum(r[m]["outcome"] == "correct" for r in rs)
        wrong = lambda rs: sum(r[m]["outcome"] == "wrong" for r in rs)
        print(f"{m:10s} at >= 30 %: correct {right(sel)}/{len(sel)} ({right(sel) / len(sel):.1%}), wrong accepted "
              f"{wrong(sel)} ({wrong(sel) / len(sel):.1%}); of the {len(sure)} pairs the gate can confirm at the truth: "
              f"correct {right(sure) / max(len(sure), 1):.1%}, wrong {wrong(sure) / max(len(sure), 1):.1%}")
    placed = [r for r in rows if r["fedmap"]["outcome"] in ("correct", "wrong")]
    weak = [r for r in placed if r["fedmap"].get("patches", math.inf) < FEW_PATCHES]
    print(f"fedmap placements flagged as resting on fewer than {FEW_PATCHES:g} independent patches (every level): "
          f"{len(weak)} of {len(placed)}: {sum(r['fedmap']['outcome'] == 'correct' for r in weak)} correct, "
          f"{sum(r['fedmap']['outcome'] == 'wrong' for r in weak)} wrong (of "
          f"{sum(r['fedmap']['outcome'] == 'wrong' for r in placed)} wrong in all)")
    record = {"pairs_per_level": args.pairs, "size": args.size, "seed": args.seed, "noise": NOISE, "gate": DEFAULT_GATE,
              "min_margin": DEFAULT_MARGIN, "min_overlap": DEFAULT_MIN_OVERLAP,
              "akaze_gates": AKAZE_GATES, "tolerance": {"heading_deg": HEADING_TOL, "cells": CELL_TOL},
              "opencv": cv2.__version__, "levels": have, "records": [f"level_{v:02d}.json" for v in have],
              "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "registration.json").write_text(to_json(record))
    if args.figure.suffix:
        figure(summary, args.figure, args.pairs)
    print(f"wrote {args.out}/registration.json" + (f" and {args.figure}" if args.figure.suffix else ""))


if __name__ == "__main__":
    main()
