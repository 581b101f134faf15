"""The ``context`` class-map codec against zstd-2bit, WebP-lossless and PNG: whole maps and
a rover's incremental update, in bytes, plus encode + decode time.

    python benchmarks/map_codec.py [--data ../shared/data] [--out benchmarks/results/map_codec]

Whole maps: the built-in mars, moon and ice maps at 128, 512 and 2048 cells, and the real
terrains ``fedmap reproduce --data`` maps, at 128 cells (as in ``reproduce``) and at their
full resolution. Update: the receiver holds the map with its south-east quadrant unknown;
a rover then observes the north-west quarter of that quadrant. ``context`` codes the
rover's new map against the receiver's map (the reference); the generic codecs code the
same update as a class map holding the newly observed cells and UNKNOWN elsewhere (what a
receiver can overlay on its map). Every payload is decoded and checked to be exact.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from fedmap.coding.mapcodec import decode_map, encode_map
from fedmap.experiments.bandwidth import ImageCodec
from fedmap.experiments.real_terrain import REAL_TERRAINS
from fedmap.maps.grid import UNKNOWN
from fedmap.maps.sources import TerrainSource, load_truth

GENERIC = ("zstd-2bit", "webp-lossless", "png-palette", "png-gray")


def maps(data: Path | None) -> dict[str, np.ndarray]:
    out = {f"{t} {n}": load_truth(TerrainSource(terrain=t, size=n)).classes
           for t in ("mars", "moon", "ice") for n in (128, 512, 2048)}
    if data is not None:
        for name, (_, src) in REAL_TERRAINS.items():
            path = data / str(src.path)
            if not path.exists():
                print(f"skip {name}: {path} missing")
                continue
            for size in (128, None):
                grid = load_truth(replace(src, path=str(path), size=size))
                out[f"{name} {grid.shape[0]}x{grid.shape[1]}"] = grid.classes
    return out


def generic_best(m: np.ndarray) -> tuple[str, int]:
    sizes = {}
    for name in GENERIC:
        payload, back = ImageCodec(name).roundtrip(m)
        assert np.array_equal(back, m)
        sizes[name] = len(payload)
    best = min(sizes, key=sizes.__getitem__)
    return best, sizes[best]


def timed(m: np.ndarray, reference: np.ndarray | None = None) -> tuple[int, float]:
    t = time.perf_counter()
    payload = encode_map(m, reference=reference)
    back = decode_map(payload, reference=reference)
    seconds = time.perf_counter() - t
    assert np.array_equal(back, m)
    return len(payload), seconds


def update_case(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(receiver's map, rover's new map, the update as a class map with UNKNOWN elsewhere)."""
    h, w = m.shape
    before = m.copy()
    before[h // 2:, w // 2:] = UNKNOWN
    seen = np.zeros(m.shape, dtype=bool)
    seen[h // 2:h // 2 + h // 4, w // 2:w // 2 + w // 4] = True
    after = np.where(seen, m, before).astype(np.uint8)
    update = np.where(seen, m, UNKNOWN).astype(np.uint8)
    return before, after, update


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/map_codec"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    data = args.data if args.data.is_dir() else None
    rows = []
    print("| map | cells | context B | best generic (B) | ratio | update: context B | best generic (B) | ratio "
          "| enc+dec s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, m in maps(data).items():
        ctx_bytes, seconds = timed(m)
        best, best_bytes = generic_best(m)
        before, after, update = update_case(m)
        up_bytes, _ = timed(after, before)
        up_best, up_best_bytes = generic_best(update)
        row = {"map": name, "shape": list(m.shape), "context": ctx_bytes, "best_generic": best,
               "best_generic_bytes": best_bytes, "ratio": ctx_bytes / best_bytes, "update_context": up_bytes,
               "update_best_generic": up_best, "update_best_generic_bytes": up_best_bytes,
               "update_ratio": up_bytes / up_best_bytes, "encode_decode_s": seconds}
        rows.append(row)
        print(f"| {name} | {m.size:,} | {ctx_bytes:,} | {best_bytes:,} ({best}) | {row['ratio']:.2f} | {up_bytes:,} | "
              f"{up_best_bytes:,} ({up_best}) | {row['update_ratio']:.2f} | {seconds:.2f} |", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"results: {args.out / 'results.json'}")


if __name__ == "__main__":
    main()
