"""How long a user waits for the CLI to answer a mistake: a mistyped command, a bad option,
``--help``, each a fresh process (best of three).

    python benchmarks/cli_latency.py
"""

from __future__ import annotations

import subprocess
import sys
import time

CASES = {"mistyped command (fedmap mision)": ["mision"],
         "bad option (fedmap mission --bogus)": ["mission", "--bogus"],
         "help (fedmap --help)": ["--help"]}


def main() -> None:
    for label, argv in CASES.items():
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "fedmap", *argv], capture_output=True, timeout=120)
            times.append(time.perf_counter() - t0)
        print(f"{label}: {min(times):.2f} s")


if __name__ == "__main__":
    main()
