"""Time and memory of one big ``fedmap run``, per stage.

    python benchmarks/big_run.py [--size 4096] [--method fedmap] [--out DIR] [-- extra fedmap run args]

Runs ``fedmap run --size SIZE --method METHOD`` in a child process, samples its resident
memory every 0.2 s and reads its stage lines ("stage 'x' started / done"), then prints
each stage's wall time and the highest RSS sampled while it ran, the whole run's wall
time and its peak RSS (the kernel's high-water mark, ``ru_maxrss``, which a sample can
miss), and where the peak fell. Writes ``DIR/big_run.json`` with the same figures.
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

STAGE = re.compile(r"stage '([^']+)' (started|done)")


def _rss_gb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS"):
                    return int(line.split()[1]) * 1024 / 1e9
    except FileNotFoundError:
        return None
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--method", default="fedmap")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/big_run"))
    ap.add_argument("extra", nargs="*", help="more `fedmap run` arguments (after --)")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="fedmap-big-") as tmp:
        cmd = [sys.executable, "-m", "fedmap", "run", "--size", str(a.size), "--method", a.method,
               "-o", str(Path(tmp) / "run"), *a.extra]
        t0 = time.monotonic()
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        current = ["start"]
        peak_in: dict[str, float] = {}
        times: dict[str, float] = {}
        started: dict[str, float] = {}

        def sample() -> None:
            while p.poll() is None:
                r = _rss_gb(p.pid)
                if r is not None:
                    peak_in[current[0]] = max(peak_in.get(current[0], 0.0), r)
                time.sleep(0.2)

        threading.Thread(target=sample, daemon=True).start()
        assert p.stdout is not None
        tail: list[str] = []
        for line in p.stdout:
            tail = (tail + [line.rstrip()])[-15:]
            m = STAGE.search(line)
            if m:
                name, what = m.groups()
                now = time.monotonic() - t0
                if what == "started":
                    started[name], current[0] = now, name
                else:
                    times[name] = now - started.get(name, now)
                    current[0] = f"after {name}"
        code = p.wait()
        wall = time.monotonic() - t0
    if code:
        print("\n".join(tail), file=sys.stderr)
        raise SystemExit(f"fedmap run failed with exit code {code}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1e9  # kB on Linux
    where = max(peak_in, key=lambda k: peak_in[k]) if peak_in else "-"
    print(f"fedmap run --size {a.size} --method {a.method}: {wall:.1f} s, peak RSS {peak:.2f} GB (sampled highest: "
          f"{peak_in.get(where, 0.0):.2f} GB, {where})")
    for name in peak_in:
        took = f"{times[name]:7.1f} s" if name in times else "        -"
        print(f"  {name:32s} {took}   highest RSS {peak_in[name]:.2f} GB")
    (a.out / "big_run.json").write_text(json.dumps({
        "size": a.size, "method": a.method, "extra": a.extra, "wall_s": wall, "peak_rss_gb": peak,
        "peak_stage": where, "stage_s": times, "stage_peak_rss_gb": peak_in}, indent=1) + "\n")


if __name__ == "__main__":
    main()
