"""Planning on a belief map: frontiers, coordinated target choice, and the path.

A rover plans on its *belief*: its own observations laid over the latest global map it
has received. How unknown cells are treated:

* **Rating targets.** The travel cost to every cell is a geodesic cost over the belief
  (scikit-image's minimum-cost path, 8-connected): a known free cell costs 1, an
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

import numpy as np
from scipy import ndimage
from skimage.graph import MCP_Geometric

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


def gain_map(belief: np.ndarray, radius: float) -> np.ndarray:
    """Number of UNKNOWN cells within ``radius`` of every cell (outside the map counts 0)."""
    off = disk_offsets(radius)
    r = int(np.abs(off).max())
    kernel = np.zeros((2 * r + 1, 2 * r + 1))
    kernel[off[:, 0] + r, off[:, 1] + r] = 1.0
    return np.rint(ndimage.convolve((np.asarray(belief) == UNKNOWN).astype(np.float64), kernel,
                                    mode="constant", cval=0.0)).astype(np.int64)


def travel_costs(belief: np.ndarray, start: tuple[int, int], unknown_cost: float) -> np.ndarray:
    """Geodesic cost from ``start`` to every cell (inf where unreachable)."""
    b = np.asarray(belief)
    costs = np.where(b == FREE, 1.0, unknown_cost)
    costs[b == IMPASSABLE] = -1.0  # negative: impassable to MCP
    mcp = MCP_Geometric(costs, fully_connected=True)
    cum, _ = mcp.find_costs([start])
    return np.where(np.isfinite(cum) & (costs >= 0), cum, np.inf)


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
    """
    b = np.asarray(belief)
    front = frontier_mask(b)
    if allowed is not None:
        front &= allowed
    for cell in excluded:
        front[cell] = False
    if not front.any():
        return None
    gain = gain_map(b, radius)
    front &= gain > 0
    if not front.any():
        return None
    cost = travel_costs(b, pos, unknown_cost)
    front &= np.isfinite(cost)
    if not front.any():
        return None
    score = cost - 2 * radius * gain / len(disk_offsets(radius))
    rows, cols = np.indices(b.shape)
    if heading is not None:
        r0, c0, angle = heading
        dr, dc = rows - r0, cols - c0
        norm = np.maximum(np.hypot(dr, dc), 1e-9)
        score = score - radius * (dr * np.sin(angle) + dc * np.cos(angle)) / norm
    if others:
        crowd = np.zeros(b.shape, dtype=bool)
        for r, c in others:
            crowd |= (rows - r) ** 2 + (cols - c) ** 2 <= (2 * radius) ** 2
        score = score + 4 * radius * crowd
    score = np.where(front, score, np.inf)
    i = int(np.argmin(score))
    return divmod(i, b.shape[1])


def plan_path(belief: np.ndarray, pos: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """A* on the belief with UNKNOWN passable; the path without ``pos`` (None: no path)."""
    b = np.asarray(belief)
    path = astar((b == FREE) | (b == UNKNOWN), pos, goal)
    return None if path is None else path[1:]
