"""The import graph of ``fedmap``, read from the source: no cycles, no import of a higher layer.

import-linter checks the layers of ``pyproject.toml``, but from the modules' import
statements as Python runs them at import time; an import inside a function (done to dodge
a cycle, or to keep a heavy dependency lazy) can hide a cycle or an upward import from
it. This test parses every module under ``src/fedmap`` with :mod:`ast` and collects every
import statement, at module level and inside functions, classes, ``if`` and ``try``
blocks alike:

* ``import fedmap.a.b`` and ``from fedmap.a.b import name`` import ``fedmap.a.b`` (the
  deepest module the dotted name reaches: ``import fedmap.a.b.attr`` imports ``fedmap.a.b``);
* ``from fedmap.a import b`` imports the submodule ``fedmap.a.b`` when there is one, else
  the package ``fedmap.a`` (its ``__init__``);
* relative imports are resolved against the importing module's package.

An import of a module does not add edges to its parent packages (Python does run their
``__init__`` first), so a package ``__init__`` that re-exports its own submodules
(``fedmap.a -> fedmap.a.b``) is an ordinary edge and no cycle by itself; a submodule that
imports a name back from its package's ``__init__`` (``fedmap.a.b -> fedmap.a``) is counted,
and then is a real cycle. No edge is excluded.

Then: every strongly connected component of the graph among fedmap modules must be a single
module (a cycle names its modules and the file:line of each import on it), and no module
may import a module of a higher layer of the ``layers`` contract in ``pyproject.toml`` (nor
a sibling of an independent ``a | b`` layer).
"""

from __future__ import annotations

import ast
import tomllib
from collections import deque
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"
PACKAGE = "fedmap"


@dataclass(frozen=True)
class Import:
    """One import statement's edge: ``source`` imports ``target`` at ``path:line``."""

    source: str
    target: str
    path: str
    line: int
    local: bool  # inside a function (not run when the module is imported)

    def where(self) -> str:
        return f"{self.path}:{self.line}{' (function-local)' if self.local else ''}"


def module_files(src: Path = SRC, package: str = PACKAGE) -> dict[str, Path]:
    """Dotted module name -> file, for every module of ``package`` under ``src``."""
    out = {}
    for path in sorted((src / package).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _resolve(name: str, modules: set[str]) -> str | None:
    """The deepest module of ``modules`` that the dotted ``name`` reaches (None: not ours)."""
    parts = name.split(".")
    while parts:
        if ".".join(parts) in modules:
            return ".".join(parts)
        parts.pop()
    return None


def _function_nodes(tree: ast.AST) -> set[int]:
    """ids of every node inside a function body (its imports run only when it is called)."""
    inside = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            inside.update(id(n) for n in ast.walk(node) if n is not node)
    return inside


def imports_of(module: str, source: str, modules: set[str], *, is_package: bool = False,
               path: str = "<string>") -> list[Import]:
    """Every import in ``source`` (the code of ``module``) of a module in ``modules``."""
    tree = ast.parse(source, filename=path)
    local = _function_nodes(tree)
    package = module if is_package else module.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [t for a in node.names if (t := _resolve(a.name, modules))]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                if node.level > 1:
                    base_parts = base_parts[: -(node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for a in node.names:
                sub = f"{base}.{a.name}"
                t = sub if sub in modules else _resolve(base, modules)
                if t:
                    targets.append(t)
        for t in dict.fromkeys(targets):
            if t != module:
                out.append(Import(module, t, path, node.lineno, id(node) in local))
    return out


def import_graph(src: Path = SRC, package: str = PACKAGE) -> list[Import]:
    """Every import among the modules of ``package`` (one entry per statement and target)."""
    files = module_files(src, package)
    modules = set(files)
    edges = []
    for module, path in files.items():
        rel = str(path.relative_to(src.parent))
        edges += imports_of(module, path.read_text(), modules, is_package=path.name == "__init__.py", path=rel)
    return edges


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of ``graph`` (node -> successors), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    nodes = sorted(set(graph) | {m for succ in graph.values() for m in succ})

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            out.append(sorted(comp))

    for v in nodes:
        if v not in index:
            visit(v)
    return out


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One shortest cycle ``[a, b, ..., a]`` through the first module of every strongly
    connected component of more than one module (self-imports are ignored)."""
    cycles = []
    for comp in strongly_connected(graph):
        if len(comp) < 2:
            continue
        members, start = set(comp), comp[0]
        prev: dict[str, str] = {}
        queue = deque([start])
        while queue:  # BFS inside the component back to start
            v = queue.popleft()
            for w in sorted(graph.get(v, ())):
                if w == start and v != start:
                    path = [v]  # v, its predecessor, ..., start
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    cycles.append([*reversed(path), start])
                    queue.clear()
                    break
                if w in members and w not in prev and w != start:
                    prev[w] = v
                    queue.append(w)
    return cycles


def _graph(edges: list[Import]) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
    return graph


def layers(pyproject: Path = ROOT / "pyproject.toml") -> list[list[str]]:
    """The ``layers`` contract of ``[tool.importlinter]``, highest first; each layer is its
    modules (``a | b`` or ``a : b`` are two modules of one layer)."""
    contracts = tomllib.loads(pyproject.read_text())["tool"]["importlinter"]["contracts"]
    found = [c for c in contracts if c["type"] == "layers"]
    assert len(found) == 1, "expected one layers contract in pyproject.toml"
    return [[m.strip() for m in layer.replace(":", "|").split("|")] for layer in found[0]["layers"]]


def _independent(pyproject: Path = ROOT / "pyproject.toml") -> list[bool]:
    contracts = tomllib.loads(pyproject.read_text())["tool"]["importlinter"]["contracts"]
    return ["|" in layer for c in contracts if c["type"] == "layers" for layer in c["layers"]]


def _layer_of(module: str, stack: list[list[str]]) -> tuple[int, str] | None:
    """(layer index, the layer's module) that ``module`` belongs to, or None."""
    for i, layer in enumerate(stack):
        for top in layer:
            if module == top or module.startswith(top + "."):
                return i, top
    return None


def upward_imports(edges: list[Import], stack: list[list[str]], independent: list[bool] | None = None) -> list[str]:
    """Imports of a higher layer (or of an independent sibling), one line each."""
    independent = independent or [False] * len(stack)
    bad = []
    for e in edges:
        src, dst = _layer_of(e.source, stack), _layer_of(e.target, stack)
        if src is None or dst is None:
            continue
        if dst[0] < src[0]:
            bad.append(f"{e.where()}: {e.source} (layer {src[1]}) imports {e.target} (higher layer {dst[1]})")
        elif dst[0] == src[0] and dst[1] != src[1] and independent[src[0]]:
            bad.append(f"{e.where()}: {e.source} imports {e.target} (independent layers {src[1]} | {dst[1]})")
    return bad


# --------------------------------------------------------------------------- the checks


def test_no_import_cycles_among_fedmap_modules():
    edges = import_graph()
    assert len({e.source for e in edges}) > 20  # the parser found the package's imports
    by_pair = {}
    for e in edges:
        by_pair.setdefault((e.source, e.target), e)
    problems = []
    for cycle in find_cycles(_graph(edges)):
        steps = [f"  {a} -> {b}  [{by_pair[a, b].where()}]" for a, b in zip(cycle, cycle[1:])]
        problems.append(f"import cycle {' -> '.join(cycle)}:\n" + "\n".join(steps))
    assert not problems, "\n".join(problems)


def test_no_module_imports_a_higher_layer_not_even_inside_a_function():
    stack = layers()
    modules = set(module_files())
    for layer in stack:  # a typo in the contract would silently check nothing
        for top in layer:
            assert top in modules, f"layer {top!r} of pyproject.toml is not a fedmap module"
    bad = upward_imports(import_graph(), stack, _independent())
    assert not bad, "imports of a higher layer:\n" + "\n".join(bad)


# --------------------------------------------------------------------------- the checks can fail


def test_cycle_finder_on_hand_made_graphs():
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    assert find_cycles({"a": {"a"}}) == []  # a self-import is no cycle between modules
    assert find_cycles({"a": {"b"}, "b": {"a"}}) == [["a", "b", "a"]]
    # a 3-cycle with a tail into it and a second, separate cycle
    graph = {"t": {"a"}, "a": {"b"}, "b": {"c"}, "c": {"a"}, "x": {"y"}, "y": {"x", "z"}, "z": set()}
    assert sorted(find_cycles(graph)) == [["a", "b", "c", "a"], ["x", "y", "x"]]
    assert sorted(c for c in strongly_connected(graph) if len(c) > 1) == [["a", "b", "c"], ["x", "y"]]
    # the shortest way round is reported when the component has several
    assert find_cycles({"a": {"b", "c"}, "b": {"c"}, "c": {"a"}}) == [["a", "c", "a"]]


def test_collector_sees_function_local_relative_and_submodule_imports():
    modules = {"pkg", "pkg.a", "pkg.b", "pkg.sub", "pkg.sub.c", "pkg.sub.d"}
    code = (
        "import os\n"
        "from pkg.a import thing\n"            # a name from a module: the module
        "from pkg import b\n"                  # a submodule: the submodule
        "import pkg.sub.c.attr\n"              # deepest module reached
        "def f():\n"
        "    from . import d\n"                # relative, inside a function
        "    from .. import thing\n"           # a name from a package: its __init__
    )
    got = {(e.target, e.line, e.local) for e in imports_of("pkg.sub.x", code, modules)}
    assert got == {("pkg.a", 2, False), ("pkg.b", 3, False), ("pkg.sub.c", 4, False), ("pkg.sub.d", 6, True),
                   ("pkg", 7, True)}
    # in a package's __init__, "." is the package itself
    got = {e.target for e in imports_of("pkg.sub", "from . import c\nfrom .d import y\n", modules, is_package=True)}
    assert got == {"pkg.sub.c", "pkg.sub.d"}
    # the hidden cycle this test exists for: a -> b at module level, b -> a inside a function
    edges = imports_of("pkg.a", "from pkg.b import x\n", modules) + \
        imports_of("pkg.b", "def f():\n    from pkg.a import y\n", modules)
    assert find_cycles(_graph(edges)) == [["pkg.a", "pkg.b", "pkg.a"]]


def test_layer_check_on_a_hand_made_graph():
    stack = [["p.top"], ["p.mid1", "p.mid2"], ["p.low"]]
    edges = [Import("p.top.x", "p.low", "top/x.py", 3, False),  # downward: fine
             Import("p.low", "p.mid1.y", "low.py", 7, True),  # upward, function-local
             Import("p.mid1", "p.mid2", "mid1.py", 1, False),  # sibling
             Import("p.top", "q.other", "top.py", 2, False)]  # not in any layer
    assert upward_imports(edges, stack) == [
        "low.py:7 (function-local): p.low (layer p.low) imports p.mid1.y (higher layer p.mid1)"]
    assert upward_imports(edges, stack, [False, True, False])[1] == \
        "mid1.py:1: p.mid1 imports p.mid2 (independent layers p.mid1 | p.mid2)"
