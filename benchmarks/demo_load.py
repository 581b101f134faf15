"""``fedmap demo`` on an idle machine and with busy processes beside it: how its time grows
under load, against what a fair share of the cores predicts.

    python benchmarks/demo_load.py [--busy 2] [--env OMP_WAIT_POLICY=ACTIVE ...]

Runs the demo (a fresh process, ``--quiet``, a temporary output folder) once idle and once
with ``--busy`` processes spinning on pure Python beside it, and prints the wall time and
the CPU time (user + system) of each, and the slowdown. A fair share predicts a slowdown of
about ``(threads + busy) / cores`` for the demo's ``threads`` busy threads; CPU time that grows
under load is time spent waiting by spinning (OpenMP threads at a barrier whose partner
was descheduled). ``--env`` sets variables for the demo's process (e.g. the OpenMP wait
policy fedmap sets by default, to compare).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

BUSY = "while True: pass"


def run_demo(env: dict[str, str]) -> tuple[float, float]:
    """Wall and CPU seconds of one ``fedmap demo`` in a fresh process."""
    with tempfile.TemporaryDirectory() as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "fedmap", "--quiet", "demo", "-o", os.path.join(tmp, "demo")],
                       env=env, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--busy", type=int, default=2, help="busy processes beside the loaded run")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE", help="set for the demo's process")
    args = p.parse_args()
    env = dict(os.environ)
    for kv in args.env:
        key, _, value = kv.partition("=")
        env[key] = value
    idle_wall, idle_cpu = run_demo(env)
    print(f"idle: {idle_wall:.1f} s wall, {idle_cpu:.1f} s CPU", flush=True)
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.busy)]
    try:
        wall, cpu = run_demo(env)
    finally:
        for b in busy:
            b.kill()
            b.wait()
    cores = len(os.sched_getaffinity(0))
    print(f"with {args.busy} busy processes: {wall:.1f} s wall, {cpu:.1f} s CPU; {wall / idle_wall:.1f}x the idle "
          f"time ({cores} cores; a fair share of them predicts about {(min(cores, 2) + args.busy) / cores:.1f}x)")


if __name__ == "__main__":
    main()
