"""Planning on a belief map: frontiers, coordinated target choice, and the path.

A rover plans on its *belief*: its own observations laid over the latest global map it
has received. How unknown cells are treated:

* **Rating targets.** The travel cost to a frontier cell is a geodesic cost over the
  belief (scikit-image's ``MCP_Geometric`` cost model, 8-connected, with the path
  planner's rule that a diagonal step needs both cells it passes crossable, searched by a
  compiled Dijkstra only as far as a cell could still be chosen): a known free cell costs
  1, an UNKNOWN cell ``unknown_cost`` (default 1.5: optimistic, but known ground is
  preferred), a known impassable cell cannot be crossed. A cell the search reaches is a
  cell the path can reach, so a rover shut in by diagonal gaps it cannot drive through
  finds no target at once, instead of rating the whole map for targets its path never
  reaches.
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

import heapq
import threading

import numpy as np

from fedmap._util import compiled_once
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, beside_unknown
from fedmap.maps.planning import astar
from fedmap.mission.world.sensing import disk_offsets


def frontier_mask(belief: np.ndarray) -> np.ndarray:
    """Known free cells with at least one UNKNOWN 4-neighbour (map edges are not unknown)."""
    return (np.asarray(belief) == FREE) & beside_unknown(belief)


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
    its length (1 or sqrt 2), as scikit-image's ``MCP_Geometric`` has it, and a diagonal
    step needs both cells it passes crossable (no corner cutting, as the path planner
    :func:`fedmap.maps.planning.astar` has it; the tests check every cost against SciPy's
    Dijkstra on that graph). With ``targets`` (a boolean mask) the search stops once it has
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


@compiled_once
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
    via_row, via_col = (-W, -W, W, W), (-1, 1, -1, 1)  # the two cells each diagonal step passes
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
            if k >= 4 and (costs[i + via_row[k - 4]] < 0 or costs[i + via_col[k - 4]] < 0):
                continue  # no corner cutting: both cells a diagonal step passes are crossable
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

    One compiled search (:func:`_candidates`) does the work near the rover only: a
    Dijkstra from the rover that recognises a candidate (a frontier cell, allowed, not
    excluded, with an unknown cell in range) as it settles it and stops once no cell left
    could win. A cell's score is at least its cost minus ``2 radius`` (the most gain) and,
    with a heading, minus ``radius``, so the search stops when the cost it reaches exceeds
    the best score so far by that much. Nothing is done for the whole map: a pick costs what
    the rover's neighbourhood costs, whatever the map's size. The candidates it settled are
    then scored as above, so the choice is the one a whole-map rating makes (the tests
    compare them).

    ``p_impassable`` (a predictor's P(impassable) of every cell): unknown cells cost
    :func:`predicted_cost` and count :func:`entropy_bits` of their prediction in the gain.
    The candidates stay the frontier cells with an unknown cell in range.
    """
    b = np.ascontiguousarray(belief, dtype=np.uint8)
    h, w = b.shape
    # the compiled search reads these arrays unchecked: a wrong shape is a one-line error here
    if not (0 <= pos[0] < h and 0 <= pos[1] < w):
        raise FedmapError(f"rover position {tuple(pos)} is outside the {h}x{w} map")
    for name, layer in (("allowed", allowed), ("p_impassable", p_impassable)):
        if layer is not None and np.shape(layer) != b.shape:
            raise FedmapError(f"{name} is {'x'.join(map(str, np.shape(layer)))}, the map is {h}x{w}")
    off = disk_offsets(radius)
    per = 2 * radius / len(off)  # the score of one unit of gain
    empty_f, empty_b = np.zeros(0), np.zeros(0, dtype=np.bool_)
    pcost = empty_f if p_impassable is None else predicted_cost(p_impassable, unknown_cost).ravel()
    weights = empty_f if p_impassable is None else entropy_bits(p_impassable).ravel()
    ok = empty_b if allowed is None else np.ascontiguousarray(allowed, dtype=np.bool_).ravel()
    excl = np.array(sorted(r * w + c for r, c in excluded if 0 <= r < h and 0 <= c < w), dtype=np.int64)
    head = (0.0, 0.0, 0.0) if heading is None else (float(heading[0]), float(heading[1]), float(heading[2]))
    oth = np.array(others, dtype=np.float64).reshape(-1, 2)
    cum, done, touched, found = _pick_buffers(b.size)
    n = _candidate_search()(b.ravel(), h, w, pos[0] * w + pos[1], float(unknown_cost), pcost, weights, ok, excl,
                            off[:, 0].copy(), off[:, 1].copy(), float(radius), per, heading is not None,
                            head[0], head[1], np.sin(head[2]), np.cos(head[2]), oth, cum, done, touched, found)
    cells = np.sort(found[:n])
    cost = cum[cells]
    _reset_pick_buffers(cum, done, touched)
    if n == 0:
        return None
    gain = gain_at(b, cells, radius) if p_impassable is None else gain_at(b, cells, radius,
                                                                             weights=weights.reshape(h, w))
    score = cost - 2 * radius * gain / len(off)
    rows, cols = np.divmod(cells, w)
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
    return divmod(int(cells[int(np.argmin(score))]), w)


#: Maps up to this many cells keep one set of pick buffers per thread between picks (a
#: mission picks thousands of targets on one map); a bigger map's are made for each pick.
_KEEP_PICK = 1 << 21
_PICK = threading.local()


def _new_pick_buffers(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A pick's costs (inf), settled flags, touched cells and found candidates for ``n`` cells;
    ``touched[0]`` counts the touched cells (their indices follow it)."""
    return np.full(n, np.inf), np.zeros(n, np.bool_), np.zeros(n + 1, np.int64), np.zeros(n, np.int64)


def _pick_buffers(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if n > _KEEP_PICK:
        return _new_pick_buffers(n)
    kept = getattr(_PICK, "bufs", None)
    if kept is None or kept[0].size != n:
        kept = _PICK.bufs = _new_pick_buffers(n)
    return kept


def _reset_pick_buffers(cum: np.ndarray, done: np.ndarray, touched: np.ndarray) -> None:
    """Put back what a search touched (the next pick finds the buffers as made)."""
    idx = touched[1:touched[0] + 1]
    cum[idx] = np.inf
    done[idx] = False
    touched[0] = 0


@compiled_once
def _candidate_search():
    """:func:`_candidates` compiled with numba (cached on disk), compiled at the first pick,
    in one thread."""
    from numba import njit

    return njit(cache=True)(_candidates)


def _candidates(b: np.ndarray, h: int, w: int, s: int, ucost: float, pcost: np.ndarray, weights: np.ndarray,
                allowed: np.ndarray, excl: np.ndarray, offr: np.ndarray, offc: np.ndarray, radius: float, per: float,
                use_heading: bool, hr: float, hc: float, hsin: float, hcos: float, others: np.ndarray,
                cum: np.ndarray, done: np.ndarray, touched: np.ndarray, found: np.ndarray) -> int:
    """Dijkstra on the flattened belief ``b`` (``h`` x ``w``) from ``s`` with the costs of
    :func:`travel_costs` (``pcost``, if not empty, for unknown cells), recording every
    settled candidate in ``found`` (returns how many; their costs are left in ``cum``).

    A candidate is a FREE cell with an UNKNOWN 4-neighbour, ``allowed`` (if not empty), not
    in ``excl`` (sorted flat indices), with an UNKNOWN cell within the disk ``offr, offc``.
    Its score is estimated as :func:`choose_target` computes it (gain: the count, or the
    sum of ``weights`` if not empty, times ``per``); the search stops when a popped cost
    exceeds the best estimate by more than any cell's score can fall below its cost (the
    most gain, and ``radius`` with a heading) plus 1e-6 (the estimate's rounding), so
    every cell that could win is settled. The buffers' touched cells are listed in
    ``touched`` (after the count in ``touched[0]``) for :func:`_reset_pick_buffers`."""
    n_found = 0
    nt = 0
    if b[s] == IMPASSABLE:
        return 0
    below = 2.0 * radius + (radius if use_heading else 0.0) + 1e-6  # how far a score can fall below its cost
    best = np.inf
    root2 = np.sqrt(2.0)
    quad = (2.0 * radius) ** 2
    dr8 = (-1, 1, 0, 0, -1, -1, 1, 1)
    dc8 = (0, 0, -1, 1, -1, 1, -1, 1)
    cum[s] = 0.0
    nt += 1
    touched[nt] = s
    heap = [(0.0, s)]
    while len(heap):
        d, i = heapq.heappop(heap)
        if done[i]:
            continue
        if d > best + below:
            break
        done[i] = True
        r, c = i // w, i % w
        bi = b[i]
        ci = 1.0 if bi == FREE else (pcost[i] if pcost.size else ucost)
        if bi == FREE and (allowed.size == 0 or allowed[i]):
            front = ((r > 0 and b[i - w] == UNKNOWN) or (r < h - 1 and b[i + w] == UNKNOWN)
                     or (c > 0 and b[i - 1] == UNKNOWN) or (c < w - 1 and b[i + 1] == UNKNOWN))
            if front:
                at = np.searchsorted(excl, i)
                if at < excl.size and excl[at] == i:
                    front = False
            if front:
                count = 0
                total = 0.0
                for m in range(offr.size):
                    rr, cc = r + offr[m], c + offc[m]
                    if 0 <= rr < h and 0 <= cc < w and b[rr * w + cc] == UNKNOWN:
                        count += 1
                        if weights.size:
                            total += weights[rr * w + cc]
                if count > 0:
                    found[n_found] = i
                    n_found += 1
                    score = d - per * (total if weights.size else count)
                    if use_heading:
                        dr, dc = r - hr, c - hc
                        score -= radius * (dr * hsin + dc * hcos) / max(np.hypot(dr, dc), 1e-9)
                    for o in range(others.shape[0]):
                        if (r - others[o, 0]) ** 2 + (c - others[o, 1]) ** 2 <= quad:
                            score += 4.0 * radius
                            break
                    if score < best:
                        best = score
        for k in range(8):
            rr, cc = r + dr8[k], c + dc8[k]
            if rr < 0 or rr >= h or cc < 0 or cc >= w:
                continue
            j = rr * w + cc
            bj = b[j]
            if bj == IMPASSABLE or done[j]:
                continue
            if k >= 4 and (b[rr * w + c] == IMPASSABLE or b[r * w + cc] == IMPASSABLE):
                continue  # no corner cutting, as travel_costs
            cj = 1.0 if bj == FREE else (pcost[j] if pcost.size else ucost)
            nd = d + (1.0 if k < 4 else root2) * 0.5 * (ci + cj)
            if nd < cum[j]:
                if cum[j] == np.inf:
                    nt += 1
                    touched[nt] = j
                cum[j] = nd
                heapq.heappush(heap, (nd, j))
    touched[0] = nt
    return n_found


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
                    if dr and dc and (costs[rr, c] < 0 or costs[r, cc] < 0):
                        continue  # no corner cutting
                    step = (1.0 if dr == 0 or dc == 0 else np.sqrt(2.0)) * 0.5 * (costs[rr, cc] + costs[r, c])
                    if cum[rr, cc] + step < best_cost and cum[rr, cc] < cum[r, c]:
                        best, best_cost = (rr, cc), cum[rr, cc] + step
        if best is None:  # cannot happen on a settled cell; never loop
            return None
        cell = best
        path.append(cell)
    return path[::-1][1:]
