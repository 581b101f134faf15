"""Hashes of every preset and example mission's ``metrics.json``, timings removed: the check
that a refactoring changed no behaviour (same metrics, same bytes per message).

    python benchmarks/mission_hashes.py                 # all eight missions (about 30 min on 2 cores)
    python benchmarks/mission_hashes.py default ramen   # some of them
    python benchmarks/mission_hashes.py --out DIR       # keep the outputs (metrics.json, report.md)

Prints one line per mission: the hash of the whole file (sha256, 16 hex digits) and one
per strategy (12 hex digits), so a change shows which strategy it touched. Run it before
and after a change (``git stash``) and compare the lines.

Float rounding differs between CPU kinds (AVX2, AVX-512, AMX), so the exact hashes do too.
Two more per mission tell what differs across machines: ``ledger`` hashes every strategy's
ledger (every message's step, sender, bytes and fate: the same ledger means the same
traffic, so the same maps were sent), and ``6sig`` the whole file with every float rounded
to 6 significant digits.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

from fedmap.cli import main
from fedmap.mission.outputs.report import without_timings

ROOT = Path(__file__).resolve().parent.parent
#: name -> the ``fedmap mission`` arguments
MISSIONS: dict[str, list[str]] = {
    "default": [],
    "cadre": ["--preset", "cadre"],
    "cadre-mesh": ["--preset", "cadre-mesh"],
    "ramen": ["--preset", "ramen"],
    "scout": ["--preset", "scout"],
    "mission_gale": [str(ROOT / "examples/mission_gale.toml")],
    "mission_hadley": [str(ROOT / "examples/mission_hadley.toml")],
    "mission_elevation": [str(ROOT / "examples/mission_elevation.toml")],
}


def digest(metrics, n: int) -> str:
    return hashlib.sha256(json.dumps(metrics, sort_keys=True).encode()).hexdigest()[:n]


def rounded(value, digits: int = 6):
    """``value`` with every float rounded to ``digits`` significant digits."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {k: rounded(v, digits) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v, digits) for v in value]
    return value


def main_(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("missions", nargs="*", help=f"some of {', '.join(MISSIONS)} (default: all)")
    p.add_argument("--out", type=Path, default=None, help="keep the outputs here (default: a temporary folder)")
    args = p.parse_args(argv)
    names = args.missions or list(MISSIONS)
    unknown = [n for n in names if n not in MISSIONS]
    if unknown:
        p.error(f"unknown mission(s) {', '.join(unknown)}; known: {', '.join(MISSIONS)}")
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        for name in names:
            folder = out / name
            with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):  # the mission's own table
                code = main(["--quiet", "mission", *MISSIONS[name], "--no-animation", "-o", str(folder)])
            if code:
                print(f"{name}: fedmap mission failed (exit {code})", file=sys.stderr)
                return code
            m = without_timings(json.loads((folder / "metrics.json").read_text()))
            m.pop("wire", None)  # newer than the hashes: what the transport carried, beside the ledger
            per = {s: digest(r, 12) for s, r in m["strategies"].items()}
            ledgers = {s: r.get("ledger") for s, r in m["strategies"].items()}
            print(f"{name:18s} {digest(m, 16)}  " + "  ".join(f"{s} {h}" for s, h in per.items())
                  + f"  ledger {digest(ledgers, 12)}  6sig {digest(rounded(m), 12)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main_())
