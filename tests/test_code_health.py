"""The code's own checks, run by the test command: layering contracts, lint and types.

Each fails the suite when the tree breaks its contract: a lower layer importing a higher
one, the library importing the CLI (or typer/rich), a module outside the Flower adapter
importing ``flwr`` (import-linter, contracts in ``pyproject.toml``), a lint error (ruff)
or a type error in ``src/`` (mypy).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    found = Path(sys.executable).parent / name
    path = str(found) if found.exists() else shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is not installed: pip install -e '.[test]'")
    return path


def _check(argv: list[str]) -> None:
    env = {**os.environ, "MYPY_CACHE_DIR": str(ROOT / ".mypy_cache")}
    r = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, f"{' '.join(argv[1:]) or argv[0]} failed:\n{r.stdout[-4000:]}{r.stderr[-2000:]}"


def test_import_contracts_hold():
    _check([_tool("lint-imports"), "--no-cache"])


def test_ruff_is_clean():
    _check([_tool("ruff"), "check", "src", "tests", "benchmarks"])


@pytest.mark.slow
def test_mypy_is_clean_on_src():
    _check([_tool("mypy")])


def test_importing_the_cli_or_the_rover_does_not_import_flwr():
    """The one import the contracts let through (the forked warm server imports the
    ClientApp inside ``serve``) must stay inside the function: importing the CLI or the
    rover's module does not load Flower."""
    code = ("import sys, fedmap.cli, fedmap.flower.rover, fedmap.flower.warm\n"
            "print(sorted(m for m in sys.modules if m == 'flwr' or m.startswith('flwr.')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout[-2000:] + r.stderr[-2000:]
