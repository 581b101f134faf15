"""Bits per new cell of the ``predictive`` strategy with the map predictor's guess as a
context of its coder (issue 35, coding): ``[strategies.predictive] predictor`` = ``none``
(today's coder), ``mix`` (logistic mixing) and ``bins`` (guess bins as a context digit).

    python benchmarks/predictor_coding.py --threads 1
        [--missions default examples/mission_gale.toml examples/mission_hadley.toml]
        [--out benchmarks/results/predictor_coding]

For every mission, the ``predictive`` strategy runs once per variant; the trajectories and
the delivered cells are the same in every run (the coder is lossless, the benchmark checks
that the final maps are equal). Bits per new cell = 8 x the uplink bytes delivered / the
cells of the base's final map, as ``benchmarks/cell_streams.py`` counts them (today's
0.65-0.92 there); every header, trail, target and check byte is included. It also splits
out the cells' own share: the ideal code length of the cell symbols (-log2 of the coder's
probability, summed) on the uplink, to show how much of a message the guess can touch at all.

And two bounds, from the uplink cells of the ``mix`` run (the count model's probabilities
are those of today's coder: the same symbols fold into the same counts): the bits of
the carried cells' FREE/IMPASSABLE split under today's coder; under the best logistic
mixing of it with the guess *fitted on the same cells* per level (an oracle no coder can
beat with these two inputs mixed this way); and with a perfect split (0 bits).

Prints a table and writes ``predictor_coding.json`` and ``predictor_coding.md`` under
``--out``. Gale and Hadley read ``../shared/data`` (not shipped with fedmap).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from fedmap.coding import streamcodec
from fedmap.maps.grid import UNKNOWN
from fedmap.mission import load_mission, mission_terrain, run_mission

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("none", "mix", "bins")


class _CellBits:
    """Counts the ideal bits of the cell symbols the coder encodes
    (:func:`fedmap.coding.streamcodec.observe_cells`; both ends code the same symbols, so only
    encoders are counted), split by uplink (one anchor) and downlink."""

    def __init__(self) -> None:
        self.bits = {"up": 0.0, "down": 0.0}
        #: uplink cells coded with a guess mixed in (mix runs): (level, count model's probs, guess, symbol)
        self.mixed: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self._observing = streamcodec.observe_cells(self._seen)

    def _seen(self, c: streamcodec.CellSymbols) -> None:
        if not c.encoding:
            return
        side = "up" if c.anchors == 1 else "down"
        self.bits[side] += c.bits()
        if side == "up" and c.counts is not None and c.guess is not None:
            self.mixed.append((c.level, c.counts, c.guess, c.symbols.copy()))

    def __enter__(self) -> _CellBits:
        self._observing.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._observing.__exit__(*exc)


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-4, 1 - 1e-4)
    return np.log(p) - np.log1p(-p)


def mixing_bounds(mixed: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]) -> dict:
    """Bits of the carried cells' FREE/IMPASSABLE split: today's, and with the per-level
    logistic mixing of today's P(IMPASSABLE | carried) and the guess fitted on these cells."""
    out: dict = {"levels": {}}
    today = best = 0.0
    for level, name in enumerate(("s=1", "s=2", "s>=4")):
        parts = [(p, g, y) for lev, p, g, y in mixed if lev == level]
        if not parts:
            continue
        p = np.concatenate([a for a, _, _ in parts])
        g = np.concatenate([b for _, b, _ in parts]).astype(np.float64)
        y = np.concatenate([c for _, _, c in parts])
        carried = y != 2
        r = (p[:, 1] / (p[:, 0] + p[:, 1]))[carried]
        t = (y[carried] == 1).astype(np.float64)
        x = np.stack([_logit(r), _logit(g[carried]), np.ones_like(r)], axis=1)
        w = np.array([1.0, 0.0, 0.0])
        for _ in range(50):  # Newton's method on the log loss
            z = 1 / (1 + np.exp(-x @ w))
            w -= np.linalg.solve((x * (z * (1 - z))[:, None]).T @ x + 1e-6 * np.eye(3), x.T @ (z - t))
        z = np.clip(1 / (1 + np.exp(-x @ w)), 1e-12, 1 - 1e-12)
        b0 = float(-np.where(t == 1, np.log2(r), np.log2(1 - r)).sum())
        b1 = float(-np.where(t == 1, np.log2(z), np.log2(1 - z)).sum())
        out["levels"][name] = {"carried_cells": int(carried.sum()), "split_bits": round(b0, 1),
                               "oracle_mix_bits": round(b1, 1), "oracle_weights": [round(float(v), 3) for v in w]}
        today, best = today + b0, best + b1
    out["split_bits"], out["oracle_mix_bits"] = round(today, 1), round(best, 1)
    return out


def measure(name: str) -> dict:
    config, source, _ = load_mission(None if name == "default" else ROOT / name)
    truth, elevation, prior, _ = mission_terrain(config, source)
    rows, maps, bounds = [], [], {}
    for variant in VARIANTS:
        c = replace(config, strategies=("predictive",),
                    methods={**config.methods, "predictive": {**config.methods.get("predictive", {}),
                                                              "predictor": variant}})
        t0 = time.perf_counter()
        with _CellBits() as counter:
            run = run_mission(c, truth, elevation=elevation, prior=prior, frames=1).runs["predictive"]
        wall = time.perf_counter() - t0
        if variant == "mix":
            bounds = mixing_bounds(counter.mixed)
        up = [m for m in run.ledger if m.direction == "up" and m.status == "delivered"]
        down = [m for m in run.ledger if m.direction != "up" and m.status == "delivered"]
        final = run.sharing.global_map()
        maps.append(final)
        n_final = int((final != UNKNOWN).sum())
        up_bytes = sum(m.bytes for m in up)
        rows.append({"predictor": variant, "messages": len(up), "uplink_bytes": up_bytes,
                     "downlink_bytes": sum(m.bytes for m in down), "final_map_cells": n_final,
                     "bits_per_new_cell": 8 * up_bytes / max(n_final, 1),
                     "uplink_cell_symbol_bits": round(counter.bits["up"], 1),
                     "uplink_cell_share": counter.bits["up"] / max(8 * up_bytes, 1),
                     "wall_s": round(wall, 1)})
    same = all(np.array_equal(maps[0], m) for m in maps[1:])
    base = rows[0]
    for r in rows:
        r["ratio"] = r["bits_per_new_cell"] / base["bits_per_new_cell"]
        r["cell_bits_ratio"] = r["uplink_cell_symbol_bits"] / max(base["uplink_cell_symbol_bits"], 1e-9)
        r["downlink_ratio"] = r["downlink_bytes"] / max(base["downlink_bytes"], 1)
    if bounds:  # what the uplink would cost with these split bits instead of today's
        b = 8 * base["uplink_bytes"]
        bounds["ratio_oracle_mix"] = (b - bounds["split_bits"] + bounds["oracle_mix_bits"]) / b
        bounds["ratio_perfect_split"] = (b - bounds["split_bits"]) / b
    return {"bounds": bounds, "mission": name, "terrain": source.label, "shape": list(truth.shape), "rovers": config.rovers,
            "steps": config.steps, "same_final_map": same, "rows": rows}


def markdown(results: list[dict]) -> str:
    lines = ["| mission | predictor | uplink bytes | bits per new cell | × today | cell symbols' bits "
             "(share of uplink) | × today | downlink bytes (× today) | wall s |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for res in results:
        for r in res["rows"]:
            lines.append(f"| {res['mission']} | {r['predictor']} | {r['uplink_bytes']:,} | "
                         f"{r['bits_per_new_cell']:.3f} | {r['ratio']:.3f} | "
                         f"{r['uplink_cell_symbol_bits']:,.0f} ({r['uplink_cell_share']:.0%}) | "
                         f"{r['cell_bits_ratio']:.3f} | {r['downlink_bytes']:,} ({r['downlink_ratio']:.3f}) | "
                         f"{r['wall_s']} |")
    lines += ["", "Bounds on the uplink (ratio to today's bits per new cell): the FREE/IMPASSABLE split of the "
              "carried cells mixed with the guess by the best logistic weights per level fitted on the same cells "
              "(oracle), or coded for free (perfect guess).", "",
              "| mission | split bits today | oracle mix | × today (oracle) | × today (perfect split) |",
              "|---|---:|---:|---:|---:|"]
    for res in results:
        b = res.get("bounds") or {}
        if b:
            lines.append(f"| {res['mission']} | {b['split_bits']:,.0f} | {b['oracle_mix_bits']:,.0f} | "
                         f"{b['ratio_oracle_mix']:.3f} | {b['ratio_perfect_split']:.3f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--missions", nargs="+", default=["default", "examples/mission_gale.toml",
                                                       "examples/mission_hadley.toml"])
    ap.add_argument("--threads", type=int, default=1, help="torch threads (predict itself always runs on one)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/predictor_coding")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for name in args.missions:
        res = measure(name)
        results.append(res)
        print(markdown([res]), flush=True)
        if not res["same_final_map"]:
            print(f"WARNING: {name}: the variants delivered different final maps", flush=True)
    md = markdown(results)
    meta = {"command": "python benchmarks/predictor_coding.py --threads 1", "python": platform.python_version(),
            "torch": torch.__version__, "machine": platform.machine(), "mix_weights": streamcodec.MIX,
            "guess_bin_edges": streamcodec.GUESS_EDGES.tolist()}
    (args.out / "predictor_coding.json").write_text(json.dumps({"meta": meta, "missions": results}, indent=1))
    (args.out / "predictor_coding.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
