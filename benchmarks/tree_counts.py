"""The structure of the package in numbers: lines per folder, the largest classes, and the
import arrows that run back up a layer or close a cycle (from ``tests/test_import_graph.py``,
function-local imports included).

    python benchmarks/tree_counts.py             # this checkout
    python benchmarks/tree_counts.py --src DIR   # another checkout's src/ (before and after a change)
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=ROOT / "src")
    a = ap.parse_args()
    pkg = a.src / "fedmap"
    sys.path.insert(0, str(ROOT / "tests"))
    import test_import_graph as g  # noqa: PLC0415  (the suite's own graph, run on any checkout)

    folders: dict[str, list[int]] = {}
    classes = []
    for f in sorted(pkg.rglob("*.py")):
        rel = f.relative_to(pkg)
        folder = rel.parts[0] if len(rel.parts) > 1 else "."
        text = f.read_text()
        folders.setdefault(folder, []).append(len(text.splitlines()))
        for n in ast.walk(ast.parse(text)):
            if isinstance(n, ast.ClassDef):
                classes.append((n.end_lineno - n.lineno + 1, f"{rel}:{n.name}"))  # type: ignore[operator]
    for folder, lines in sorted(folders.items()):
        print(f"{folder:<12} {len(lines):>3} files {sum(lines):>6} lines")
    print("largest classes:", ", ".join(f"{name} {n}" for n, name in sorted(classes)[-5:][::-1]))
    edges = g.import_graph(a.src, "fedmap")
    cycles = g.find_cycles(g._graph(edges))
    up = g.upward_imports(edges, g.layers(a.src.parent / "pyproject.toml"))
    print(f"import cycles {len(cycles)}, arrows back up a layer {len(up)}")


if __name__ == "__main__":
    main()
