"""Would model mixing make the ``context`` codec reach half the best generic codec on
whole maps? A probe of ideal code lengths, not a codec.

    python benchmarks/context_mixing.py [--size 512] [--terrains mars moon ice]

For each built-in map: ``context``'s real bytes, the best generic codec's (from
``fedmap.experiments.bandwidth``'s lossless codecs), and the ideal code length (sum of
-log2 p, bytes) of raster-order adaptive models on causal templates of 10 cells (JBIG's
three-line template) and of logistic mixing (PAQ-style, one weight per model, learned
online by gradient descent on the code length) of 4-, 10-, 16- and 22-cell templates
(contexts of the larger ones hashed into 2^20 bins). Additive prior 0.25 on every count,
as ``context``.
"""

from __future__ import annotations

import argparse
import math
import time

import numba
import numpy as np

from fedmap.coding.mapcodec import encode_map
from fedmap.experiments.bandwidth import image_codecs
from fedmap.maps.sources import TerrainSource, load_truth

T4 = ((-1, -1), (-1, 0), (-1, 1), (0, -1))
T10 = ((-2, -1), (-2, 0), (-2, 1), (-1, -2), (-1, -1), (-1, 0), (-1, 1), (-1, 2), (0, -2), (0, -1))
T16 = T10 + ((-3, 0), (0, -3), (-2, -2), (-2, 2), (-3, -1), (-3, 1))
T22 = T16 + ((-4, 0), (0, -4), (-3, -2), (-3, 2), (-1, -3), (-1, 3))
BINS = 1 << 20


def contexts(classes: np.ndarray, template) -> np.ndarray:
    h, w = classes.shape
    pad = np.full((h + 5, w + 10), 2, dtype=np.int64)  # outside the map reads UNKNOWN
    pad[5:, 5:-5] = classes
    ctx = np.zeros((h, w), dtype=np.int64)
    for dr, dc in template:
        ctx = ctx * 3 + pad[5 + dr:5 + dr + h, 5 + dc:5 + dc + w]
    return (ctx % BINS).ravel()


@numba.njit(cache=True)
def mixed_bytes(sym, ctx, alpha, lr):
    n, m = ctx.shape
    counts = np.zeros((m, BINS, 3))
    w = np.full(m, 1.0 / m)
    lp = np.zeros((m, 3))
    bits = 0.0
    for i in range(n):
        for j in range(m):
            c = counts[j, ctx[i, j]]
            t = c[0] + c[1] + c[2] + 3 * alpha
            for s in range(3):
                lp[j, s] = math.log((c[s] + alpha) / t)
        z = np.zeros(3)
        for s in range(3):
            for j in range(m):
                z[s] += w[j] * lp[j, s]
        e = np.exp(z - z.max())
        p = e / e.sum()
        y = sym[i]
        bits -= math.log2(p[y])
        for j in range(m):
            w[j] += lr * (lp[j, y] - (p[0] * lp[j, 0] + p[1] * lp[j, 1] + p[2] * lp[j, 2]))
            counts[j, ctx[i, j], y] += 1
    return bits / 8


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--terrains", nargs="+", default=["mars", "moon", "ice"])
    args = ap.parse_args()
    codecs = [c for c in image_codecs() if c.lossless and c.family != "context"]
    print("| map | context B | best generic B | T10 ideal B | mix of 4 ideal B | context / generic | mix / generic |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in args.terrains:
        t0 = time.perf_counter()
        m = load_truth(TerrainSource(kind="builtin", terrain=name, size=args.size)).classes
        sym = m.ravel().astype(np.int64)
        ctx = len(encode_map(m))
        best = min(len(c.encode(m)) for c in codecs)
        t10 = mixed_bytes(sym, contexts(m, T10)[:, None], 0.25, 0.0)
        mix = mixed_bytes(sym, np.stack([contexts(m, t) for t in (T4, T10, T16, T22)], 1), 0.25, 0.002)
        print(f"| {name} {args.size}² | {ctx:,} | {best:,} | {t10:,.0f} | {mix:,.0f} | {ctx / best:.3f} | "
              f"{mix / best:.3f} |  ({time.perf_counter() - t0:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
