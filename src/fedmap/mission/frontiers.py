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


def travel_costs(belief: np.ndarray, start: tuple[int, int], unknown_cost: float, *,
                 targets: np.ndarray | None = None, slack: float = np.inf) -> np.ndarray:
    """Geodesic cost from ``start`` to every cell (inf where unreachable).

    8-connected, a step between cells of costs ``a`` and ``b`` costs ``(a + b) / 2`` times
    its length (1 or sqrt 2), as scikit-image's ``MCP_Geometric`` has it (the tests check
    every cost against it). With ``targets`` (a boolean mask) the search stops once it has
    settled every cell within ``slack`` of the cheapest target; the cells it did not settle
    are inf, the ones it did have their whole-map cost. A compiled Dijkstra (numba, cached
    on disk): the bound makes a target pick cost what the neighbourhood of the rover costs,
    not the whole map.
    """
    b = np.asarray(belief)
    h, w = b.shape
    costs = np.full((h + 2, w + 2), -1.0)  # a border of impassable cells: no bounds checks
    costs[1:-1, 1:-1] = np.where(b == FREE, 1.0, unknown_cost)
    costs[1:-1, 1:-1][b == IMPASSABLE] = -1.0
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


def gain_at(belief: np.ndarray, cells: np.ndarray, radius: float) -> np.ndarray:
    """The *gain* of the cells at flat indices ``cells``: the number of UNKNOWN cells within
    ``radius`` of each (cells outside the map count 0)."""
    off = disk_offsets(radius)
    r = int(np.abs(off).max())
    b = np.asarray(belief)
    h, w = b.shape
    pad = np.zeros((h + 2 * r, w + 2 * r), dtype=np.int64)
    pad[r:-r or None, r:-r or None] = b == UNKNOWN
    flat = pad.ravel()
    rows, cols = np.divmod(cells, w)
    base = (rows + r) * (w + 2 * r) + cols + r
    gain = np.zeros(len(cells), dtype=np.int64)
    for dr, dc in off:
        gain += flat[base + dr * (w + 2 * r) + dc]
    return gain


def choose_target(belief: np.ndarray, pos: tuple[int, int], *, radius: float, unknown_cost: float,
                  others: list[tuple[int, int]], allowed: np.ndarray | None = None,
                  excluded: set[tuple[int, int]] | frozenset = frozenset(),
                  heading: tuple[float, float, float] | None = None) -> tuple[int, int] | None:
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
    front = np.zeros(b.shape, dtype=bool)
    front.flat[cells] = True
    cost = travel_costs(b, pos, unknown_cost, targets=front, slack=8 * radius + 1).ravel()[cells]
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
