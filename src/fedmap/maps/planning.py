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

import heapq
import math
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage

from fedmap._util import compiled_once, cpu_cores
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
    _check_ends(passable.shape, start, goal)
    if not (passable[start] and passable[goal]):
        return None
    free, W = _padded(passable)
    bufs = _buffers(free.size) if free.size <= _KEEP_BUFFERS else _new_buffers(free.size)
    return _unflatten(_compiled()(free, W, _flat(start, W), _flat(goal, W), *bufs, _NO_MARKS, 0), W)


def astar_many(passable: np.ndarray, pairs: list[tuple[tuple[int, int], tuple[int, int]]], *,
               workers: int | None = None) -> list[list[tuple[int, int]] | None]:
    """:func:`astar` for each (start, goal) of ``pairs`` on one map: the same paths, the
    searches shared among ``workers`` threads (default: this process's cores; the compiled
    search releases the GIL), the map padded once."""
    return [path for path, _ in _many(passable, pairs, workers, regions=False)]


#: The side of the square blocks of :func:`astar_regions`.
REGION_BLOCK = 8


def astar_regions(passable: np.ndarray, pairs: list[tuple[tuple[int, int], tuple[int, int]]], *,
                  workers: int | None = None) -> list[tuple[list[tuple[int, int]] | None, np.ndarray | None]]:
    """:func:`astar_many`, and for each search the region it depended on: the flat indices
    (row-major over a grid of :data:`REGION_BLOCK`-cell square blocks, ``ceil(H / 8)`` by
    ``ceil(W / 8)``) of the blocks holding a cell the search gave a cost to (None where
    nothing was searched: an end not passable).

    The search reads only those cells and their 8 neighbours. So on another map that agrees
    with ``passable`` on every block of the region and one cell around it, the search
    takes the same steps and returns the same path (:func:`fedmap.evaluation.paths.path_f1`
    uses this to skip searches on maps close to the truth)."""
    return _many(passable, pairs, workers, regions=True)


def region_blocks(changed: np.ndarray) -> np.ndarray:
    """Which :data:`REGION_BLOCK` blocks hold a cell of ``changed`` (bool, the map's shape)
    or one of its 8 neighbours: a bool array over the block grid of :func:`astar_regions`.
    A search whose region has none of them reads no changed cell."""
    near = ndimage.binary_dilation(np.asarray(changed, dtype=bool), structure=np.ones((3, 3), bool))
    h, w = near.shape
    b = REGION_BLOCK
    padded = np.zeros((-(-h // b) * b, -(-w // b) * b), bool)
    padded[:h, :w] = near
    return padded.reshape(padded.shape[0] // b, b, padded.shape[1] // b, b).any(axis=(1, 3)).ravel()


def _many(passable: np.ndarray, pairs: list[tuple[tuple[int, int], tuple[int, int]]], workers: int | None,
          *, regions: bool) -> list[tuple[list[tuple[int, int]] | None, np.ndarray | None]]:
    passable = np.asarray(passable, dtype=bool)
    for s, g in pairs:
        _check_ends(passable.shape, s, g)
    todo = [k for k, (s, g) in enumerate(pairs) if passable[s] and passable[g]]
    out: list[tuple[list[tuple[int, int]] | None, np.ndarray | None]] = [(None, None)] * len(pairs)
    if not todo:
        return out
    free, W = _padded(passable)
    h, w = passable.shape
    bw = -(-w // REGION_BLOCK)
    search = _compiled()
    workers = max(1, min(workers or cpu_cores(), len(todo)))

    def run(part: list[int]) -> None:
        bufs = _new_buffers(free.size)  # each thread its own; the search leaves them as found
        marks = np.zeros(-(-h // REGION_BLOCK) * bw, np.bool_) if regions else _NO_MARKS
        for k in part:
            s, g = pairs[k]
            path = _unflatten(search(free, W, _flat(s, W), _flat(g, W), *bufs, marks, bw), W)
            region = None
            if regions:
                region = np.flatnonzero(marks).astype(np.int32)
                marks[region] = False
            out[k] = (path, region)

    if workers == 1:
        run(todo)
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(run, [todo[w::workers] for w in range(workers)]))
    return out


_NO_MARKS = np.zeros(0, np.bool_)


def _check_ends(shape: tuple[int, ...], start: tuple[int, int], goal: tuple[int, int]) -> None:
    h, w = shape
    for name, (r, c) in (("start", start), ("goal", goal)):
        if not (0 <= r < h and 0 <= c < w):
            raise FedmapError(f"{name} {(r, c)} is outside the {h}x{w} map")


def _padded(passable: np.ndarray) -> tuple[np.ndarray, int]:
    """The map with a blocked border (neighbour lookups need no bounds checks), flattened,
    and its row length."""
    return np.pad(passable, 1, constant_values=False).ravel(), passable.shape[1] + 2


def _flat(cell: tuple[int, int], W: int) -> int:
    return (cell[0] + 1) * W + cell[1] + 1


def _unflatten(path: np.ndarray, W: int) -> list[tuple[int, int]] | None:
    if not len(path):
        return None
    rows, cols = np.divmod(path, W)
    return list(zip((rows - 1).tolist(), (cols - 1).tolist()))


#: Maps up to this many (padded) cells keep one set of search buffers per thread between
#: plans (exploration and missions plan thousands of paths on small maps); a bigger map's
#: buffers (17 bytes a cell) are made for each plan and freed after it.
_KEEP_BUFFERS = 1 << 21
_LOCAL = threading.local()


def _new_buffers(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The search's g (inf), parent (-1) and closed (False) arrays for ``n`` cells."""
    return np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros(n, np.bool_)


def _buffers(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """This thread's kept buffers for ``n`` cells (made anew when the size changes)."""
    kept = getattr(_LOCAL, "bufs", None)
    if kept is None or kept[0].size != n:
        kept = _LOCAL.bufs = _new_buffers(n)
    return kept


@compiled_once
def _compiled():
    """:func:`_search` compiled with numba (cached on disk), releasing the GIL. Compiled at
    the first plan, not at import: importing numba costs every fedmap command about 0.2 s,
    most of which plan nothing."""
    from numba import njit

    search = njit(cache=True, nogil=True)(_search)
    free, W = _padded(np.ones((1, 2), bool))  # compiled (or loaded) here, once, not by threads racing to do it
    search(free, W, _flat((0, 0), W), _flat((0, 1), W), *_new_buffers(free.size), _NO_MARKS, 0)
    return search


def _search(free: np.ndarray, W: int, s: int, t: int, g: np.ndarray, parent: np.ndarray,
            closed: np.ndarray, marks: np.ndarray, bw: int) -> np.ndarray:
    """A* on the padded, flattened grid ``free`` (row length ``W``) from ``s`` to ``t``:
    the path's flat indices, start first (empty: no path).

    ``g`` (all inf), ``parent`` (all -1) and ``closed`` (all False) are working arrays of
    ``free``'s size; the search resets every cell it touched before it returns, so they can
    be used again. Unless ``marks`` is empty, the search sets ``marks[b]`` for the block
    ``b`` (:data:`REGION_BLOCK` cells square, ``bw`` blocks a row, unpadded) of every cell
    it gave a cost to. Compiled with numba; the heap key ``(f, h, flat index)``, the neighbour
    order (up, down, left, right, then NW, NE, SW, SE) and the 1e-9 rule for a shorter
    route are the module's tie-break, so the path is the same on every machine.
    """
    touched = np.empty(1024, np.int64)  # every cell given a g, to reset at the end
    nt = 1
    touched[0] = s
    gr, gc = t // W, t % W
    orth = (-W, W, -1, 1)
    diag = (-W - 1, -W + 1, W - 1, W + 1)
    via_row = (-W, -W, W, W)  # the two orthogonal cells a diagonal move passes
    via_col = (-1, 1, -1, 1)
    dr, dc = abs(s // W - gr), abs(s % W - gc)
    h0 = (dr + dc) + (SQRT2 - 2.0) * min(dr, dc)
    g[s] = 0.0
    heap = [(h0, h0, s)]
    found = False
    while len(heap):
        _, _, i = heapq.heappop(heap)
        if closed[i]:
            continue
        if i == t:
            found = True
            break
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
                    if g[j] == np.inf:
                        if nt == touched.size:
                            touched = np.concatenate((touched, np.empty(nt, np.int64)))
                        touched[nt] = j
                        nt += 1
                    g[j] = nj
                    parent[j] = i
                    r, c = j // W, j % W
                    dr, dc = abs(r - gr), abs(c - gc)
                    hj = (dr + dc) + (SQRT2 - 2.0) * min(dr, dc)
                    heapq.heappush(heap, (nj + hj, hj, j))
    n_path = 0
    if found:
        i = t
        while i != -1:
            n_path += 1
            i = parent[i]
    path = np.empty(n_path, np.int64)
    i = t
    for k in range(n_path - 1, -1, -1):
        path[k] = i
        i = parent[i]
    for k in range(nt):
        j = touched[k]
        if marks.size:
            marks[((j // W - 1) // REGION_BLOCK) * bw + (j % W - 1) // REGION_BLOCK] = True
        g[j] = np.inf
        parent[j] = -1
        closed[j] = False
    return path


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
