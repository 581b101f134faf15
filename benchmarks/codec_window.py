"""The map codec's window: a patch of new cells on a large grid, coded as the whole grid
(format version 1's work) and as the window that changed (version 2).

    python benchmarks/codec_window.py [--size 1024] [--patches 24 64 200] [--repeats 3]

Built-in mars at ``--size``; the update is a ``p x p`` patch of the truth, every other cell
UNKNOWN (a rover's new cells), and the same patch given the rest of the truth as the
reference (a downlink against what the receiver holds). Prints the median encode and
decode time and the bytes of each.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from fedmap.coding import mapcodec
from fedmap.maps.grid import UNKNOWN
from fedmap.maps.sources import TerrainSource, load_truth


def _median(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--patches", type=int, nargs="+", default=[24, 64, 200])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    truth = load_truth(TerrainSource(terrain="mars", size=args.size)).classes
    r0, c0 = args.size // 2, args.size // 3
    print(f"mars {args.size}x{args.size}; median of {args.repeats}; ms and bytes")
    print(f"{'patch':>7} {'case':>9} | {'whole grid: enc':>15} {'bytes':>6} | {'window: enc':>11} {'dec':>6} {'bytes':>6}")
    for p in args.patches:
        sl = np.s_[r0:r0 + p, c0:c0 + p]
        new = np.full(truth.shape, UNKNOWN, np.uint8)
        new[sl] = truth[sl]
        ref = truth.copy()
        ref[sl] = UNKNOWN
        for case, m, reference in (("new cells", new, None), ("vs ref", truth, ref)):
            whole = _median(lambda: mapcodec.encode_map(m, reference=reference, window=False),  # noqa: B023
                            args.repeats)
            whole_bytes = len(mapcodec.encode_map(m, reference=reference, window=False))
            data = mapcodec.encode_map(m, reference=reference)
            enc = _median(lambda: mapcodec.encode_map(m, reference=reference), args.repeats)  # noqa: B023
            dec = _median(lambda: mapcodec.decode_map(data, reference=reference), args.repeats)  # noqa: B023
            print(f"{p:>5}^2 {case:>9} | {1000 * whole:>15.0f} {whole_bytes:>6} | {1000 * enc:>11.0f} "
                  f"{1000 * dec:>6.0f} {len(data):>6}")


if __name__ == "__main__":
    main()
