"""Planning on a belief map: frontiers, coordinated target choice, and the path.

A rover plans on its *belief*: its own observations laid over the latest global map it
has received. How unknown cells are treated:

* **Rating targets.** The travel cost to a frontier cell is a geodesic cost over the
  belief (scikit-image's ``MCP_Geometric`` cost model, 8-connected, searched by a compiled
  Dijkstra only as far as a cell could still be chosen): a known free cell costs 1, an
  UNKNOWN cell ``unknown_cost`` (default 1.5: optimistic, but known ground is
  preferred), a known impassable cell cannot be crossed.
* **The path** to the chosen target is fedmap's one A* (:func:`fedmap.maps.planning.astar`)
  with UNKNOWN cells passable (optimistic). The rover senses before every move, so the
  next cell of its path is always observed; when it turns out impassable, the rover
  replans (it never enters an impassable cell of the truth).

A *frontier* cell is a known free cell with an UNKNOWN 4-neighbour. Its *gain* is the
number of UNKNOWN cells within sensor range of it. Targets are coordinated using only
what the rover knows: cells within two sensor radii of another rover's last known
position or target (as of the last sync it heard of) are penalised, so rovers spread
out instead of chasing the same frontier.

**With a predictor** (``[mission] predictor = "learned"``, :mod:`fedmap.nets.predictor`)
the rover also holds P(impassable) of every unknown cell, a guess that costs no bytes
and is never an observation. Three things change, nothing else:

* an unknown cell costs :func:`predicted_cost`: the expected cost of entering it,
  ``(1 - p) unknown_cost + p DETOUR``, so likely walls are avoided but never barred;
* a frontier's gain counts each unknown cell by the binary entropy of its prediction
  (bits, 1 for p = 1/2, 0 for a certain guess): the information a look would bring;
* the path is the cheapest one under the same costs (:func:`cheapest_path`), not the
  shortest.
"""

from __future__ import annotations

import functools
import heapq

import numpy as np

from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.planning import astar
from fedmap.mission.sensing import disk_offsets


def frontier_mask(belief: np.ndarray) -> np.ndarray:
    """Known free cells with at least one UNKNOWN 4-neighbour (map edges are not unknown)."""
    b = np.asarray(belief)
    unknown = b == UNKNOWN
    near = np.zeros_like(unknown)
    near[1:, :] |= unknown[:-1, :]
    near[:-1, :] |= unknown[1:, :]
    near[:, 1:] |= unknown[:, :-1]
    near[:, :-1] |= unknown[:, 1:]
    return (b == FREE) & near


#: What a cell that turns out impassable costs the rover, in cells: a detour of about a
#: sensor radius (8 cells at the default) around the blocked ground it belongs to.
DETOUR = 8.0


def predicted_cost(p_impassable: np.ndarray, unknown_cost: float) -> np.ndarray:
    """The travel cost of unknown cells whose predicted P(impassable) is ``p_impassable``:
    ``(1 - p) unknown_cost + p max(DETOUR, unknown_cost)``, the expected cost of entering
    the cell when a free one costs ``unknown_cost`` (the optimism premium of an unseen
    cell) and a blocked one a detour of :data:`DETOUR` cells. Grows with ``p``; equals
    ``unknown_cost`` at ``p = 0``. A guess never bars a cell: only an observation does."""
    p = np.clip(np.asarray(p_impassable, dtype=np.float64), 0.0, 1.0)
    return (1.0 - p) * unknown_cost + p * max(DETOUR, unknown_cost)


def entropy_bits(p: np.ndarray) -> np.ndarray:
    """Binary entropy of probabilities ``p``, bits (0 at 0 and 1, 1 at 1/2)."""
    q = np.clip(np.asarray(p, dtype=np.float64), 1e-12, 1 - 1e-12)
    return -(q * np.log2(q) + (1 - q) * np.log2(1 - q))


def _cell_costs(b: np.ndarray, unknown_cost: float, p_impassable: np.ndarray | None) -> np.ndarray:
    """Per-cell costs of ``b`` (1 free, ``unknown_cost`` or :func:`predicted_cost` unknown,
    -1 impassable: a barrier)."""
    unknown = unknown_cost if p_impassable is None else predicted_cost(p_impassable, unknown_cost)
    costs = np.where(b == FREE, 1.0, unknown)
    costs[b == IMPASSABLE] = -1.0
    return costs


def travel_costs(belief: np.ndarray, start: tuple[int, int], unknown_cost: float, *,
                 targets: np.ndarray | None = None, slack: float = np.inf,
                 p_impassable: np.ndarray | None = None) -> np.ndarray:
    """Geodesic cost from ``start`` to every cell (inf where unreachable).

    8-connected, a step between cells of costs ``a`` and ``b`` costs ``(a + b) / 2`` times
    its length (1 or sqrt 2), as scikit-image's ``MCP_Geometric`` has it (the tests check
    every cost against it). With ``targets`` (a boolean mask) the search stops once it has
    settled every cell within ``slack`` of the cheapest target; the cells it did not settle
    are inf, the ones it did have their whole-map cost. A compiled Dijkstra (numba, cached
    on disk): the bound makes a target pick cost what the neighbourhood of the rover costs,
    not the whole map. With ``p_impassable`` an unknown cell costs :func:`predicted_cost`.
    """
    b = np.asarray(belief)
    h, w = b.shape
    costs = np.full((h + 2, w + 2), -1.0)  # a border of impassable cells: no bounds checks
    costs[1:-1, 1:-1] = _cell_costs(b, unknown_cost, p_impassable)
    stop = np.zeros((h + 2, w + 2), dtype=bool)
    if targets is not None:
        stop[1:-1, 1:-1] = targets
    s = (start[0] + 1) * (w + 2) + start[1] + 1
    cum = _dijkstra()(costs.ravel(), stop.ravel(), w + 2, s, targets is not None, float(slack))
    return cum.reshape(h + 2, w + 2)[1:-1, 1:-1]


@functools.cache
def _dijkstra():
    """:func:`_settle` compiled with numba (cached on disk), compiled at the first pick."""
    from numba import njit

    return njit(cache=True)(_settle)


def _settle(costs: np.ndarray, stop: np.ndarray, W: int, s: int, bounded: bool, slack: float) -> np.ndarray:
    """Dijkstra on the padded, flattened ``costs`` (row length ``W``, negative: a barrier)
    from ``s``: the settled cells' costs, inf elsewhere. ``bounded``: stop once a popped cost
    exceeds the first popped ``stop`` cell's cost plus ``slack``."""
    n = costs.size
    cum = np.full(n, np.inf)
    done = np.zeros(n, np.bool_)
    if costs[s] < 0:
        return cum
    steps = (-W, W, -1, 1, -W - 1, -W + 1, W - 1, W + 1)
    root2 = np.sqrt(2.0)
    bound = np.inf
    cum[s] = 0.0
    heap = [(0.0, s)]
    while len(heap):
        d, i = heapq.heappop(heap)
        if done[i]:
            continue
        if d > bound:
            break
        done[i] = True
        if bounded and stop[i] and bound == np.inf:
            bound = d + slack
        ci = costs[i]
        for k in range(8):
            j = i + steps[k]
            cj = costs[j]
            if cj < 0 or done[j]:
                continue
            nd = d + (1.0 if k < 4 else root2) * 0.5 * (ci + cj)
            if nd < cum[j]:
                cum[j] = nd
                heapq.heappush(heap, (nd, j))
    return np.where(done, cum, np.inf)  # a settled cell's cost is the one it was popped with


def gain_at(belief: np.ndarray, cells: np.ndarray, radius: float, *,
            weights: np.ndarray | None = None) -> np.ndarray:
    """The *gain* of the cells at flat indices ``cells``: the number of UNKNOWN cells within
    ``radius`` of each (cells outside the map count 0); with ``weights`` (a float per cell
    of the map), the sum of the UNKNOWN cells' weights instead."""
    off = disk_offsets(radius)
    r = int(np.abs(off).max())
    b = np.asarray(belief)
    h, w = b.shape
    dtype = np.int64 if weights is None else np.float64
    pad = np.zeros((h + 2 * r, w + 2 * r), dtype=dtype)
    pad[r:-r or None, r:-r or None] = b == UNKNOWN if weights is None else np.where(b == UNKNOWN, weights, 0.0)
    flat = pad.ravel()
    rows, cols = np.divmod(cells, w)
    base = (rows + r) * (w + 2 * r) + cols + r
    gain = np.zeros(len(cells), dtype=dtype)
    for dr, dc in off:
        gain += flat[base + dr * (w + 2 * r) + dc]
    return gain


def choose_target(belief: np.ndarray, pos: tuple[int, int], *, radius: float, unknown_cost: float,
                  others: list[tuple[int, int]], allowed: np.ndarray | None = None,
                  excluded: set[tuple[int, int]] | frozenset = frozenset(),
                  heading: tuple[float, float, float] | None = None,
                  p_impassable: np.ndarray | None = None) -> tuple[int, int] | None:
    """The frontier cell this rover should head for, or None when none is left.

    Score (lower is better): travel cost, minus the gain scaled to at most ``2 radius``,
    plus ``4 radius`` if the cell is within ``2 radius`` of a cell in ``others`` (other
    rovers' last known positions and targets). Ties go to the lowest flat index.
    ``allowed`` restricts the targets (e.g. within radio range of the base). ``heading``
    ``(origin row, origin col, angle)`` subtracts ``radius * cos`` of the angle between the
    heading and the direction from the origin to the cell.

    Only frontier cells are rated, and the travel costs are searched only as far as a cell
    could still win: a cell costing more than the cheapest candidate ``c0`` plus ``8 radius``
    scores above it whatever its gain (at most ``2 radius``), heading (at most ``radius``
    either way) and crowding (``4 radius``), so the choice is the one a whole-map rating
    makes (the tests compare them).

    ``p_impassable`` (a predictor's P(impassable) of every cell): unknown cells cost
    :func:`predicted_cost` and count :func:`entropy_bits` of their prediction in the gain.
    The candidates stay the frontier cells with an unknown cell in range.
    """
    b = np.asarray(belief)
    front = frontier_mask(b)
    if allowed is not None:
        front &= allowed
    for cell in excluded:
        front[cell] = False
    cells = np.flatnonzero(front)
    if not len(cells):
        return None
    gain = gain_at(b, cells, radius)
    keep = gain > 0
    cells, gain = cells[keep], gain[keep]
    if not len(cells):
        return None
    if p_impassable is not None:
        gain = gain_at(b, cells, radius, weights=entropy_bits(p_impassable))
    front = np.zeros(b.shape, dtype=bool)
    front.flat[cells] = True
    cost = travel_costs(b, pos, unknown_cost, targets=front, slack=8 * radius + 1,
                        p_impassable=p_impassable).ravel()[cells]
    keep = np.isfinite(cost)
    cells, gain, cost = cells[keep], gain[keep], cost[keep]
    if not len(cells):
        return None
    score = cost - 2 * radius * gain / len(disk_offsets(radius))
    rows, cols = np.divmod(cells, b.shape[1])
    if heading is not None:
        r0, c0, angle = heading
        dr, dc = rows - r0, cols - c0
        norm = np.maximum(np.hypot(dr, dc), 1e-9)
        score = score - radius * (dr * np.sin(angle) + dc * np.cos(angle)) / norm
    if others:
        crowd = np.zeros(len(cells), dtype=bool)
        for r, c in others:
            crowd |= (rows - r) ** 2 + (cols - c) ** 2 <= (2 * radius) ** 2
        score = score + 4 * radius * crowd
    return divmod(int(cells[int(np.argmin(score))]), b.shape[1])


def plan_path(belief: np.ndarray, pos: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """A* on the belief with UNKNOWN passable; the path without ``pos`` (None: no path)."""
    b = np.asarray(belief)
    path = astar((b == FREE) | (b == UNKNOWN), pos, goal)
    return None if path is None else path[1:]


def cheapest_path(belief: np.ndarray, pos: tuple[int, int], goal: tuple[int, int], unknown_cost: float,
                  p_impassable: np.ndarray) -> list[tuple[int, int]] | None:
    """The cheapest 8-connected path from ``pos`` to ``goal`` under :func:`travel_costs` with
    a prediction (unknown cells cost :func:`predicted_cost`), without ``pos`` (None: none).

    Dijkstra from ``pos`` until ``goal`` is settled, then back from ``goal``: each cell's
    predecessor is the settled neighbour through which its cost was reached (the lowest
    flat index among equals), so the path is deterministic.
    """
    b = np.asarray(belief)
    h, w = b.shape
    if b[pos] == IMPASSABLE or b[goal] == IMPASSABLE:
        return None
    at_goal = np.zeros(b.shape, dtype=bool)
    at_goal[goal] = True
    cum = travel_costs(b, pos, unknown_cost, targets=at_goal, slack=0.0, p_impassable=p_impassable)
    if not np.isfinite(cum[goal]):
        return None
    costs = _cell_costs(b, unknown_cost, p_impassable)
    path = [goal]
    cell = goal
    while cell != pos:
        r, c = cell
        best, best_cost = None, np.inf
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if (dr or dc) and 0 <= rr < h and 0 <= cc < w and np.isfinite(cum[rr, cc]) and costs[rr, cc] >= 0:
                    step = (1.0 if dr == 0 or dc == 0 else np.sqrt(2.0)) * 0.5 * (costs[rr, cc] + costs[r, c])
                    if cum[rr, cc] + step < best_cost and cum[rr, cc] < cum[r, c]:
                        best, best_cost = (rr, cc), cum[rr, cc] + step
        if best is None:  # cannot happen on a settled cell; never loop
            return None
        cell = best
        path.append(cell)
    return path[::-1][1:]
