"""Deterministic grid A*: the one planner for exploration and for scoring.

Planner
-------
8-connected grid, step cost 1 (orthogonal) or sqrt(2) (diagonal); a diagonal move is
allowed only if both orthogonal cells it passes are passable (no corner cutting), so a
path never squeezes between two diagonal obstacles. The heuristic is the octile distance
(admissible and consistent), so A* returns a shortest path. Ties are broken by
``(f, h, flat index)`` and a node's parent only changes on a strictly shorter route, so
the same map always gives the same path.

Because diagonals need both orthogonal neighbours, two cells are connected exactly when
they are in the same 4-connected component; :func:`fedmap.evaluation.paths.path_f1` uses that to answer
"no path" without searching.

UNKNOWN cells are impassable by default (a rover does not plan through unobserved
ground); ``unknown_passable=True`` makes the planner optimistic instead.
"""

from __future__ import annotations

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
    the goal cannot be reached.
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
    free = np.pad(passable, 1, constant_values=False).ravel().tolist()
    s = (start[0] + 1) * W + start[1] + 1
    t = (goal[0] + 1) * W + goal[1] + 1
    gr, gc = divmod(t, W)
    orth = (-W, W, -1, 1)
    diag = ((-W - 1, -W, -1), (-W + 1, -W, 1), (W - 1, W, -1), (W + 1, W, 1))  # (move, via1, via2)

    def heur(i: int) -> float:
        r, c = divmod(i, W)
        dr, dc = abs(r - gr), abs(c - gc)
        return (dr + dc) + (SQRT2 - 2.0) * min(dr, dc)

    g = {s: 0.0}
    parent = {s: -1}
    closed = set()
    h0 = heur(s)
    heap = [(h0, h0, s)]
    push, pop = heapq.heappush, heapq.heappop
    while heap:
        _, _, i = pop(heap)
        if i in closed:
            continue
        if i == t:
            path = []
            while i != -1:
                r, c = divmod(i, W)
                path.append((r - 1, c - 1))
                i = parent[i]
            return path[::-1]
        closed.add(i)
        gi = g[i]
        for d in orth:
            j = i + d
            if free[j] and j not in closed:
                nj = gi + 1.0
                if nj < g.get(j, math.inf) - 1e-9:
                    g[j] = nj
                    parent[j] = i
                    hj = heur(j)
                    push(heap, (nj + hj, hj, j))
        for d, a, b in diag:
            j = i + d
            if free[j] and free[i + a] and free[i + b] and j not in closed:
                nj = gi + SQRT2
                if nj < g.get(j, math.inf) - 1e-9:
                    g[j] = nj
                    parent[j] = i
                    hj = heur(j)
                    push(heap, (nj + hj, hj, j))
    return None


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
