"""Fuzz every decoder of what crosses the link (tests/fuzz_targets.py) with seeded mutated
and random inputs, and print how many each answered cleanly.

    python benchmarks/fuzz_link.py [--cases 100000] [--seed 0]

A case passes when the decoder returns or raises a one-line FedmapError; anything else
stops the run with the target, the seed and the exception. Cases are shared round-robin
over the targets; one in four is random bytes, the rest mutations of a valid sample
(with a trailing CRC-32 kept valid where the format has one).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from fuzz_targets import TARGETS, mutate, run_case  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    names = sorted(TARGETS)
    samples = {n: TARGETS[n].sample() for n in names}
    counts = {n: {"ok": 0, "rejected": 0} for n in names}
    t0 = time.perf_counter()
    for i in range(args.cases):
        name = names[i % len(names)]
        t = TARGETS[name]
        rng = np.random.default_rng([args.seed, i])
        if rng.random() < 0.25:
            data = rng.integers(0, 256, size=int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
        else:
            data = mutate(samples[name], rng, crc=t.crc)
        try:
            counts[name][run_case(t, data)] += 1
        except AssertionError as e:
            sys.exit(f"case {i} (seed [{args.seed}, {i}]) of {name}: {e}")
        if (i + 1) % 10_000 == 0:
            print(f"{i + 1:,} cases, {time.perf_counter() - t0:.0f} s", flush=True)
    print("| target | cases | decoded | rejected with a one-line error |")
    print("|---|---:|---:|---:|")
    for n in names:
        c = counts[n]
        print(f"| {n} | {c['ok'] + c['rejected']:,} | {c['ok']:,} | {c['rejected']:,} |")
    print(f"{args.cases:,} cases, no other outcome, in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
