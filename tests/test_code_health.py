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


def test_the_suite_s_loopback_lanes_each_run_on_one_worker(tmp_path):
    """The suite runs its long loopback tests in lanes (``xdist_group``, see addopts in
    ``pyproject.toml``): each lane on one worker, the short tests around them. pytest 9.2
    with pytest-xdist 3.8 drops the groups without a word (pytest-dev/pytest-xdist#1386:
    xdist marks a group in the node ID, which pytest 9.2 no longer lets it change), so every
    loopback run started at once on every worker and the suite took minutes longer; the test
    extras keep pytest below 9.2. Three tests of one group, run by two workers, must share one."""
    tests = tmp_path / "t"
    tests.mkdir()
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    (tests / "test_lane.py").write_text(
        "import os, pathlib, time, pytest\n"
        + "".join(f"@pytest.mark.xdist_group('lane')\ndef test_{k}():\n    time.sleep(0.3)\n"
                  f"    pathlib.Path({str(tmp_path)!r}, '{k}').write_text(os.environ['PYTEST_XDIST_WORKER'])\n"
                  for k in range(3))
        + "def test_other():\n    pass\n")
    r = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-q", "-p", "no:cacheprovider",
                        "-c", str(tmp_path / "pytest.ini"), "--rootdir", str(tmp_path), str(tests)],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    workers = {(tmp_path / str(k)).read_text() for k in range(3)}
    assert len(workers) == 1, f"one group ran on workers {sorted(workers)}"


def test_the_flower_extra_never_downgrades_what_the_base_install_chose():
    """`pip install -e '.[flower]'` downgraded protobuf and rich: flwr 1.41 caps them. Every
    package both fedmap's base install and flwr require is bounded in fedmap within flwr's
    bounds, so adding the extra keeps what the base install chose."""
    import tomllib
    from importlib.metadata import requires

    from packaging.requirements import Requirement
    from packaging.version import Version

    def bounds(spec):
        lo = max((Version(s.version) for s in spec if s.operator in (">=", ">", "==")), default=None)
        hi = min((Version(s.version) for s in spec if s.operator in ("<", "<=", "==")), default=None)
        return lo, hi

    ours = {Requirement(r).name.lower(): Requirement(r).specifier
            for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]}
    theirs = {Requirement(r).name.lower(): Requirement(r).specifier
              for r in requires("flwr") or [] if "extra ==" not in r}
    shared = sorted(set(ours) & set(theirs))
    assert {"protobuf", "rich", "typer"} <= set(shared)
    for name in shared:
        (lo, hi), (tlo, thi) = bounds(ours[name]), bounds(theirs[name])
        if thi is not None:
            assert hi is not None and hi <= thi, f"{name}: fedmap {ours[name]} allows above flwr's {theirs[name]}"
        if tlo is not None:
            assert lo is not None and lo >= tlo, f"{name}: fedmap {ours[name]} allows below flwr's {theirs[name]}"
