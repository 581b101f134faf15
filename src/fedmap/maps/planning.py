"""Deterministic grid A*: the one planner for exploration and for scoring.

Planner
-------
8-connected grid, step cost 1 (orthogonal) or sqrt(2) (diagonal); a diagonal move is
allowed only if both orthogonal cells it passes are passable (no corner cutting), so a
path never squeezes between two diagonal obstacles. The heuristic is the octile distance
(admissible and consistent), so A* returns a shortest path. Ties are broken by
``(f, h, flat index)`` and a node's parent only changes on a strictly shorter route, so
the same map always gives the same path. The search is compiled with numba (the same
algorithm, operation for operation, as the pure-Python planner it replaced, which the
tests keep as a reference: every path is identical, so strict path F1 is unchanged);
the compiled code is cached on disk after its first use.

Because diagonals need both orthogonal neighbours, two cells are connected exactly when
they are in the same 4-connected component; :func:`fedmap.evaluation.paths.path_f1` uses that to answer
"no path" without searching.

UNKNOWN cells are impassable by default (a rover does not plan through unobserved
ground); ``unknown_passable=True`` makes the planner optimistic instead.
"""

from __future__ import annotations

import functools
import heapq
import math

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, UNKNOWN

SQRT2 = math.sqrt(2.0)


def passable_mask(classes: np.ndarray, *, unknown_passable: bool = False) -> np.ndarray:
    """Cells the planner may enter: FREE (and UNKNOWN if ``unknown_passable``)."""
    classes = np.asarray(classes)
    ok = classes == FREE
    if unknown_passable:
        ok |= classes == UNKNOWN
    return ok


def astar(passable: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """Shortest 8-connected path from ``start`` to ``goal`` (both (row, col)), or None.

    The path includes both end points. Returns None when either end is not passable or
    the goal cannot be reached. The search runs compiled (:func:`_search`).
    """
    passable = np.asarray(passable, dtype=bool)
    h, w = passable.shape
    for name, (r, c) in (("start", start), ("goal", goal)):
        if not (0 <= r < h and 0 <= c < w):
            raise FedmapError(f"{name} {(r, c)} is outside the {h}x{w} map")
    if not (passable[start] and passable[goal]):
        return None
    # Pad with a blocked border so neighbour lookups need no bounds checks.
    W = w + 2
    free = np.pad(passable, 1, constant_values=False).ravel()
    s = (start[0] + 1) * W + start[1] + 1
    t = (goal[0] + 1) * W + goal[1] + 1
    parent, found = _compiled()(free, W, s, t)
    if not found:
        return None
    path = []
    i = t
    while i != -1:
        r, c = divmod(int(i), W)
        path.append((r - 1, c - 1))
        i = parent[i]
    return path[::-1]


@functools.cache
def _compiled():
    """:func:`_search` compiled with numba (cached on disk). Compiled at the first plan, not
    at import: importing numba costs every fedmap command about 0.2 s, most of which plan nothing."""
    from numba import njit

    return njit(cache=True)(_search)


def _search(free: np.ndarray, W: int, s: int, t: int) -> tuple[np.ndarray, bool]:
    """A* on the padded, flattened grid ``free`` (row length ``W``) from ``s`` to ``t``:
    ``(parent, found)``, ``parent[i]`` the cell ``i`` was reached from (-1: none).

    Compiled with numba; the heap key ``(f, h, flat index)``, the neighbour order (up,
    down, left, right, then NW, NE, SW, SE) and the 1e-9 rule for a shorter route are the
    module's tie-break, so the path is the same on every machine.
    """
    n = free.size
    g = np.full(n, np.inf)
    parent = np.full(n, -1, np.int64)
    closed = np.zeros(n, np.bool_)
    gr, gc = t // W, t % W
    orth = (-W, W, -1, 1)
    diag = (-W - 1, -W + 1, W - 1, W + 1)
    via_row = (-W, -W, W, W)  # the two orthogonal cells a diagonal move passes
    via_col = (-1, 1, -1, 1)
    dr, dc = abs(s // W - gr), abs(s % W - gc)
    h0 = (dr + dc) + (SQRT2 - 2.0) * min(dr, dc)
    g[s] = 0.0
    heap = [(h0, h0, s)]
    while len(heap):
        _, _, i = heapq.heappop(heap)
        if closed[i]:
            continue
        if i == t:
            return parent, True
        closed[i] = True
        gi = g[i]
        for k in range(8):
            if k < 4:
                j = i + orth[k]
                ok = free[j]
                step = 1.0
            else:
                j = i + diag[k - 4]
                ok = free[j] and free[i + via_row[k - 4]] and free[i + via_col[k - 4]]
                step = SQRT2
            if ok and not closed[j]:
                nj = gi + step
                if nj < g[j] - 1e-9:
                    g[j] = nj
                    parent[j] = i
                    r, c = j // W, j % W
                    dr, dc = abs(r - gr), abs(c - gc)
                    hj = (dr + dc) + (SQRT2 - 2.0) * min(dr, dc)
                    heapq.heappush(heap, (nj + hj, hj, j))
    return parent, False


def path_length(path: list[tuple[int, int]]) -> float:
    """Metric length of a path in cells (1 per orthogonal, sqrt 2 per diagonal step)."""
    total = 0.0
    for (r0, c0), (r1, c1) in zip(path, path[1:]):
        total += SQRT2 if (r0 != r1 and c0 != c1) else 1.0
    return total


def path_is_valid(passable: np.ndarray, path: list[tuple[int, int]]) -> bool:
    """Every cell passable, every step a legal 8-move without corner cutting."""
    for r, c in path:
        if not passable[r, c]:
            return False
    for (r0, c0), (r1, c1) in zip(path, path[1:]):
        dr, dc = r1 - r0, c1 - c0
        if max(abs(dr), abs(dc)) != 1:
            return False
        if dr and dc and not (passable[r0 + dr, c0] and passable[r0, c0 + dc]):
            return False
    return True


def sample_pairs(passable: np.ndarray, n_pairs: int, *, seed: int = 0) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """``n_pairs`` seeded (start, goal) pairs of distinct passable cells of ``passable``."""
    cells = np.argwhere(passable)
    if len(cells) < 2:
        raise FedmapError("the ground-truth map has fewer than two passable cells: cannot sample start/goal pairs")
    rng = np.random.default_rng(seed)
    pairs: list[tuple[tuple[int, int], tuple[int, int]]] = []
    for _ in range(n_pairs):
        a, b = rng.choice(len(cells), size=2, replace=False)
        pairs.append(((int(cells[a][0]), int(cells[a][1])), (int(cells[b][0]), int(cells[b][1]))))
    return pairs
