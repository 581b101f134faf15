"""Tests for fedmap.maps.planning: A*, path validity, and the path-planning F1.

Reference values come from an independent shortest-path solver: a graph built here
cell by cell (8-connected, cost 1 / sqrt 2, a diagonal only when both orthogonal cells
are passable) and solved with ``scipy.sparse.csgraph.dijkstra``. Path counts for
"is the shortest path unique?" come from a dynamic programme over that graph.

The path-F1 counts depend on which start/goal pairs are drawn; the tests draw them with
the module's documented seeded sampler (``sample_pairs(passable_mask(truth), n, seed)``,
the pairs ``path_f1`` says it uses) and classify each pair by hand-defined geometry or by
the reference solver, never with the planner under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from fedmap.errors import FedmapError
from fedmap.evaluation.paths import path_f1
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.planning import (
    astar,
    astar_many,
    passable_mask,
    path_is_valid,
    path_length,
    region_blocks,
    sample_pairs,
)

SQ2 = math.sqrt(2.0)

# ----------------------------------------------------------------------------- reference


def ref_graph(passable: np.ndarray):
    """Sparse adjacency (flat index r*w+c) of the 8-connected, no-corner-cutting grid."""
    p = np.asarray(passable, dtype=bool)
    h, w = p.shape
    rows, cols, wts = [], [], []
    for r in range(h):
        for c in range(w):
            if not p[r, c]:
                continue
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    if dr == 0 and dc == 0:
                        continue
                    r2, c2 = r + dr, c + dc
                    if not (0 <= r2 < h and 0 <= c2 < w) or not p[r2, c2]:
                        continue
                    if dr and dc:
                        if not (p[r + dr, c] and p[r, c + dc]):
                            continue  # would cut a corner
                        wt = SQ2
                    else:
                        wt = 1.0
                    rows.append(r * w + c)
                    cols.append(r2 * w + c2)
                    wts.append(wt)
    return coo_matrix((wts, (rows, cols)), shape=(h * w, h * w)).tocsr()


def ref_dist(passable: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """(H, W) shortest distances from ``start`` (inf where unreachable)."""
    p = np.asarray(passable, dtype=bool)
    h, w = p.shape
    d = dijkstra(ref_graph(p), directed=True, indices=start[0] * w + start[1])
    return d.reshape(h, w)


def ref_n_shortest(passable: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """(H, W) number of distinct shortest paths from ``start`` (DP over the dijkstra DAG)."""
    p = np.asarray(passable, dtype=bool)
    h, w = p.shape
    G = ref_graph(p).tocoo()
    d = ref_dist(p, start).ravel()
    into = [[] for _ in range(h * w)]
    for a, b, wt in zip(G.row, G.col, G.data):
        into[b].append((a, wt))
    s = start[0] * w + start[1]
    count = np.zeros(h * w)
    count[s] = 1.0
    for v in np.argsort(d, kind="stable"):
        if v == s or not np.isfinite(d[v]):
            continue
        count[v] = sum(count[a] for a, wt in into[v] if abs(d[a] + wt - d[v]) < 1e-9)
    return count.reshape(h, w)


def ref_length(path) -> float:
    """Length of a path of cells, written independently of path_length."""
    total = 0.0
    for (r0, c0), (r1, c1) in zip(path, path[1:]):
        total += math.hypot(r1 - r0, c1 - c0)
    return total


def ref_valid(passable: np.ndarray, path) -> bool:
    p = np.asarray(passable, dtype=bool)
    if not all(p[r, c] for r, c in path):
        return False
    for (r0, c0), (r1, c1) in zip(path, path[1:]):
        dr, dc = r1 - r0, c1 - c0
        if (dr, dc) == (0, 0) or abs(dr) > 1 or abs(dc) > 1:
            return False
        if dr and dc and not (p[r0 + dr, c0] and p[r0, c0 + dc]):
            return False
    return True


def random_passable(seed: int, shape=(12, 15), blocked=0.3) -> np.ndarray:
    return np.random.default_rng(seed).random(shape) >= blocked


# ----------------------------------------------------------------------------- A*


def test_reference_solver_on_a_hand_case():
    # Sanity check of the reference itself. Hand: on an open 3x4 grid the distance from
    # (0,0) to (2,3) is octile: 2 diagonals + 1 straight = 1 + 2*sqrt(2).
    d = ref_dist(np.ones((3, 4), bool), (0, 0))
    assert d[2, 3] == pytest.approx(1 + 2 * SQ2, abs=1e-12)
    # Hand: two diagonal cells with both orthogonals blocked are not connected.
    d = ref_dist(np.array([[1, 0], [0, 1]], bool), (0, 0))
    assert math.isinf(d[1, 1])


def random_queries(seed: int, passable: np.ndarray, n: int = 12):
    """Start/goal cells: two thirds drawn among passable cells, the rest anywhere."""
    h, w = passable.shape
    rng = np.random.default_rng(1000 + seed)
    cells = np.argwhere(passable)
    out = []
    for k in range(n):
        if k % 3 == 2:
            a = (int(rng.integers(h)), int(rng.integers(w)))
            b = (int(rng.integers(h)), int(rng.integers(w)))
        else:
            i, j = rng.integers(len(cells), size=2)
            a, b = tuple(int(v) for v in cells[i]), tuple(int(v) for v in cells[j])
        out.append((a, b))
    return out


@pytest.mark.parametrize("seed", range(30))
def test_astar_cost_matches_dijkstra_on_random_grids(seed):
    passable = random_passable(seed)
    for start, goal in random_queries(seed, passable):
        dist = ref_dist(passable, start)[goal] if passable[start] else math.inf
        path = astar(passable, start, goal)
        if math.isinf(dist):
            assert path is None, (start, goal)
            continue
        assert path is not None, (start, goal)
        assert path[0] == start and path[-1] == goal
        assert ref_valid(passable, path)
        assert path_is_valid(passable, path)
        assert len(set(path)) == len(path)  # a shortest path never revisits a cell
        assert ref_length(path) == pytest.approx(dist, abs=1e-9)
        assert path_length(path) == pytest.approx(dist, abs=1e-9)


@pytest.mark.parametrize("seed", range(24))
def test_astar_cost_matches_dijkstra_on_larger_grids(seed):
    # Longer routes make optimal paths differ in many diagonal steps, which small grids
    # rarely exercise (a wrong diagonal cost can go unnoticed there).
    passable = random_passable(200 + seed, shape=(45, 45), blocked=0.2)
    for start, goal in random_queries(seed, passable, n=6):
        dist = ref_dist(passable, start)[goal] if passable[start] else math.inf
        path = astar(passable, start, goal)
        if math.isinf(dist):
            assert path is None
        else:
            assert ref_valid(passable, path) and path[0] == start and path[-1] == goal
            assert ref_length(path) == pytest.approx(dist, abs=1e-9)


def test_random_queries_cover_all_cases():
    # The parametrised test above must meet every branch: reachable goals, passable but
    # unreachable goals, and blocked end points. Counted with the reference only.
    kinds = {"reachable": 0, "unreachable": 0, "blocked": 0}
    for seed in range(30):
        passable = random_passable(seed)
        for s, g in random_queries(seed, passable):
            if not (passable[s] and passable[g]):
                kinds["blocked"] += 1
            elif math.isinf(ref_dist(passable, s)[g]):
                kinds["unreachable"] += 1
            else:
                kinds["reachable"] += 1
    assert min(kinds.values()) >= 10, kinds


@pytest.mark.parametrize("seed", range(5))
def test_astar_none_exactly_when_unreachable_all_goals(seed):
    # Every goal of one start: A* is None exactly where dijkstra says inf.
    passable = random_passable(100 + seed, blocked=0.4)
    cells = np.argwhere(passable)
    start = tuple(int(v) for v in cells[len(cells) // 2])
    dist = ref_dist(passable, start)
    for r in range(passable.shape[0]):
        for c in range(passable.shape[1]):
            path = astar(passable, start, (r, c))
            if math.isinf(dist[r, c]):
                assert path is None
            else:
                assert path is not None and ref_length(path) == pytest.approx(dist[r, c], abs=1e-9)


def test_astar_trivial_and_blocked_end_points():
    p = np.ones((3, 3), bool)
    assert astar(p, (1, 1), (1, 1)) == [(1, 1)]
    p[0, 0] = False
    assert astar(p, (0, 0), (2, 2)) is None  # blocked start
    assert astar(p, (2, 2), (0, 0)) is None  # blocked goal


def test_astar_out_of_bounds_raises():
    p = np.ones((3, 4), bool)
    with pytest.raises(FedmapError, match="outside"):
        astar(p, (3, 0), (0, 0))
    with pytest.raises(FedmapError, match="outside"):
        astar(p, (0, 0), (0, -1))


def test_astar_refuses_corner_cutting():
    # Hand-made 2x2: the only route from (0,0) to (1,1) is the diagonal squeezing
    # between two blocked cells, which is forbidden.
    p = np.array([[1, 0], [0, 1]], bool)
    assert astar(p, (0, 0), (1, 1)) is None
    assert astar(p, (1, 1), (0, 0)) is None
    # With one orthogonal cell open the diagonal is still forbidden (both must be open):
    # hand: the path goes round through (0,1), length 2.
    p = np.array([[1, 1], [0, 1]], bool)
    assert astar(p, (0, 0), (1, 1)) == [(0, 0), (0, 1), (1, 1)]
    # With both open the diagonal is taken: length sqrt 2.
    p = np.ones((2, 2), bool)
    assert astar(p, (0, 0), (1, 1)) == [(0, 0), (1, 1)]


def test_astar_is_deterministic():
    passable = random_passable(7, shape=(25, 25), blocked=0.2)
    cells = np.argwhere(passable)
    s, g = tuple(int(v) for v in cells[0]), tuple(int(v) for v in cells[-1])
    first = astar(passable, s, g)
    assert first is not None
    for _ in range(3):
        assert astar(passable.copy(), s, g) == first
    # same mask given as integers
    assert astar(passable.astype(np.uint8), s, g) == first


# ----------------------------------------------------------------------------- helpers


def test_path_length_and_validity_by_hand():
    # hand: 2 orthogonal + 1 diagonal step
    assert path_length([(0, 0), (0, 1), (1, 2), (2, 2)]) == pytest.approx(2 + SQ2)
    assert path_length([(3, 3)]) == 0.0
    p = np.ones((3, 3), bool)
    p[1, 1] = False
    assert path_is_valid(p, [(0, 0), (0, 1), (0, 2), (1, 2)])
    assert not path_is_valid(p, [(0, 0), (1, 1)])  # blocked cell
    assert not path_is_valid(p, [(0, 1), (1, 2)])  # cuts the corner at (1,1)
    assert not path_is_valid(p, [(0, 0), (0, 2)])  # jump of 2 cells
    assert not path_is_valid(p, [(0, 0), (0, 0)])  # standing still is not a move


def test_passable_mask_unknown_handling():
    c = np.array([[FREE, IMPASSABLE, UNKNOWN]], np.uint8)
    np.testing.assert_array_equal(passable_mask(c), [[True, False, False]])
    np.testing.assert_array_equal(passable_mask(c, unknown_passable=True), [[True, False, True]])


def test_sample_pairs_properties():
    p = random_passable(3, shape=(10, 10))
    pairs = sample_pairs(p, 40, seed=5)
    assert len(pairs) == 40
    for s, g in pairs:
        assert s != g and p[s] and p[g]
    assert sample_pairs(p, 40, seed=5) == pairs
    assert sample_pairs(p, 40, seed=6) != pairs
    one = np.zeros((4, 4), bool)
    one[1, 1] = True
    with pytest.raises(FedmapError, match="fewer than two"):
        sample_pairs(one, 3)


# ----------------------------------------------------------------------------- path F1


def comb() -> np.ndarray:
    """A 5x15 tree of 1-wide corridors: a spine on row 2 (cols 1..13) and teeth on
    cols 2, 6, 10 (rows 0..4). No 2x2 free block, so no diagonal move exists and, being a
    tree, every pair of cells has exactly one shortest path."""
    c = np.full((5, 15), IMPASSABLE, np.uint8)
    c[2, 1:14] = FREE
    for col in (2, 6, 10):
        c[:, col] = FREE
    return c


def test_comb_has_unique_shortest_paths():
    # precondition of the TP counts below, checked with the reference DP
    p = comb() == FREE
    for s in map(tuple, np.argwhere(p)):
        n = ref_n_shortest(p, s)
        assert np.all(n[p] == 1)


@pytest.mark.parametrize("seed", [0, 1])
def test_path_f1_identical_maps(seed):
    classes = np.where(random_passable(seed, shape=(16, 18), blocked=0.35), FREE, IMPASSABLE).astype(np.uint8)
    n = 60
    res = path_f1(classes, classes.copy(), n_pairs=n, seed=seed)
    pairs = sample_pairs(classes == FREE, n, seed=seed)
    with_path = sum(np.isfinite(ref_dist(classes == FREE, s)[g]) for s, g in pairs)
    assert 0 < with_path < n  # the grid has both reachable and unreachable pairs
    assert res.tp == with_path
    assert res.tn == n - with_path
    assert res.fp == res.fn == 0
    assert res.precision == res.recall == res.f1 == 1.0
    assert res.tolerant.tp == with_path and res.tolerant.f1 == 1.0
    assert res.mean_length_ratio == 1.0
    assert res.pairs == n


def test_path_f1_blocked_corridor_counts_false_negatives():
    truth = comb()
    pred = truth.copy()
    pred[2, 8] = IMPASSABLE  # cuts the spine between the teeth at cols 6 and 10
    n = 80
    res = path_f1(truth, pred, n_pairs=n, seed=3)
    # Hand classification: in pred the left part is cols <= 7 and the right part cols
    # >= 9; a pair on one side keeps its (unique) truth path -> TP; a pair crossing, or
    # with an end on the blocked cell (2,8), loses its path -> FN. Truth is connected,
    # so no TN and, since pred only removes cells, no FP.
    def side(cell):
        return "L" if cell[1] <= 7 else ("R" if cell[1] >= 9 else "X")

    pairs = sample_pairs(truth == FREE, n, seed=3)
    tp = sum(side(s) == side(g) != "X" for s, g in pairs)
    fn = n - tp
    assert 0 < tp < n
    assert (res.tp, res.fp, res.fn, res.tn) == (tp, 0, fn, 0)
    assert res.precision == 1.0
    assert res.recall == pytest.approx(tp / (tp + fn))
    assert res.f1 == pytest.approx(2 * tp / (2 * tp + fn))
    # tolerant variant: nothing to tolerate
    assert (res.tolerant.tp, res.tolerant.fp, res.tolerant.fn) == (tp, 0, fn)


def test_path_f1_opened_wall_counts_false_positives():
    pred = comb()
    truth = pred.copy()
    truth[2, 8] = IMPASSABLE  # truth has two components; the learned map joins them
    n = 80
    res = path_f1(truth, pred, n_pairs=n, seed=4)
    # Hand: pairs are drawn from truth's free cells (never (2,8)); same side -> TP
    # (unique path in both trees), crossing -> truth none, pred path -> FP.
    pairs = sample_pairs(truth == FREE, n, seed=4)
    tp = sum((s[1] <= 7) == (g[1] <= 7) for s, g in pairs)
    fp = n - tp
    assert 0 < tp < n
    assert (res.tp, res.fp, res.fn, res.tn) == (tp, fp, 0, 0)
    assert res.precision == pytest.approx(tp / (tp + fp))
    assert res.recall == 1.0
    assert res.f1 == pytest.approx(2 * tp / (2 * tp + fp))
    assert res.tolerant.fp == fp  # a path through a truth wall is never tolerated


def loop_map() -> np.ndarray:
    """7x11: a 1-wide rectangular loop on rows 1..5, cols 1..9, whose top-left corner is
    a 2x2 free block (cell (2,2) added) so the loop takes one diagonal (2,1)->(1,2).

    With one sqrt-2 step in the loop, two ways round can only tie when both are integer,
    which happens only from the corner cells (1,1)/(2,2) to the far corner (5,9)."""
    c = np.full((7, 11), IMPASSABLE, np.uint8)
    c[1, 1:10] = FREE
    c[5, 1:10] = FREE
    c[1:6, 1] = FREE
    c[1:6, 9] = FREE
    c[2, 2] = FREE
    return c


def test_loop_detour_ratio_by_hand():
    # Hand: blocking the far corner (5,9), the pair (5,8)->(4,9) (truth: 2 steps through
    # the corner) must go round: left 7 to (5,1), up 3 to (2,1), diagonal to (1,2),
    # right 7 to (1,9), down 3 to (4,9): 20 + sqrt 2.
    truth = loop_map() == FREE
    pred = truth.copy()
    pred[5, 9] = False
    assert ref_dist(truth, (5, 8))[4, 9] == pytest.approx(2.0)
    assert ref_dist(pred, (5, 8))[4, 9] == pytest.approx(20 + SQ2)
    path = astar(pred, (5, 8), (4, 9))
    assert ref_length(path) == pytest.approx(20 + SQ2)


@pytest.mark.parametrize("tolerance", [0.0, 0.05, 0.5, 5.0, 1e6])
def test_path_f1_longer_route_is_fp_and_fn_tolerant_within_tolerance(tolerance):
    truth = loop_map()
    pred = truth.copy()
    pred[5, 9] = IMPASSABLE  # the only change: every route through this corner detours
    pt, pp = truth == FREE, pred == FREE
    n, seed = 120, 2
    res = path_f1(truth, pred, n_pairs=n, seed=seed, length_tolerance=tolerance)

    exp = dict(tp=0, fp=0, fn=0, tol_tp=0, tol_fp=0, tol_fn=0)
    ratios = []
    for s, g in sample_pairs(pt, n, seed=seed):
        dt = ref_dist(pt, s)[g]
        dp = ref_dist(pp, s)[g] if pp[s] else math.inf
        assert np.isfinite(dt)  # the loop is connected
        if math.isinf(dp):
            exp["fn"] += 1
            exp["tol_fn"] += 1
            continue
        # pred's cells are a subset of truth's, so a pred path of length dt is a truth
        # shortest path; with a unique truth shortest path it is *the* truth path.
        assert ref_n_shortest(pt, s)[g] == 1, "construction: ties only through (5,9)"
        ratio = dp / dt
        ratios.append(ratio)
        if dp == pytest.approx(dt, abs=1e-9):
            exp["tp"] += 1
        else:
            exp["fp"] += 1
            exp["fn"] += 1
        # pred paths are valid on truth (subset), so only the length decides
        if ratio <= 1 + tolerance:
            exp["tol_tp"] += 1
        else:
            exp["tol_fp"] += 1
            exp["tol_fn"] += 1

    assert exp["fp"] > 0 and exp["tp"] > 0  # both kinds of pair occur
    assert (res.tp, res.fp, res.fn, res.tn) == (exp["tp"], exp["fp"], exp["fn"], 0)
    tol = res.tolerant
    assert (tol.tp, tol.fp, tol.fn) == (exp["tol_tp"], exp["tol_fp"], exp["tol_fn"])
    assert tol.length_tolerance == tolerance
    assert res.mean_length_ratio == pytest.approx(float(np.mean(ratios)))
    if tolerance == 0.0:
        assert tol.tp == res.tp  # no detour accepted
    if tolerance == 1e6:
        assert tol.tp == res.tp + res.fp  # every detour accepted
    # hand: precision/recall from the counts
    p = exp["tp"] / (exp["tp"] + exp["fp"])
    r = exp["tp"] / (exp["tp"] + exp["fn"])
    assert res.precision == pytest.approx(p) and res.recall == pytest.approx(r)
    assert res.f1 == pytest.approx(2 * p * r / (p + r))


def test_path_f1_single_detour_ratio_within_and_beyond_tolerance():
    # A corridor A-M-B (row 1) with a bypass over the top (row 0): pred blocks M.
    #   row 0:  F F F
    #   row 1:  A M B
    #   row 2:  # # #
    # Truth path A->B = 2 (through M, unique: the diagonals A->(0,1) need M open).
    # Pred path A->(0,0)->(0,1)->(0,2)->B = 4, so the ratio is 4/2 = 2 exactly (hand).
    truth = np.array([[FREE] * 3, [FREE] * 3, [IMPASSABLE] * 3], np.uint8)
    pred = truth.copy()
    pred[1, 1] = IMPASSABLE
    pt = truth == FREE
    assert ref_n_shortest(pt, (1, 0))[1, 2] == 1  # the truth path A->B is unique
    n, seed = 200, 0
    # Count, by hand classification, the (A,B) pairs among the drawn ones.
    pairs = sample_pairs(pt, n, seed=seed)
    ab = sum({s, g} == {(1, 0), (1, 2)} for s, g in pairs)
    assert ab > 0
    within = path_f1(truth, pred, n_pairs=n, seed=seed, length_tolerance=1.0)  # 2 <= 1 + 1
    beyond = path_f1(truth, pred, n_pairs=n, seed=seed, length_tolerance=0.99)  # 2 > 1.99
    for res in (within, beyond):
        # every (A,B) pair changes route: FP and FN; strict never accepts it
        assert res.fp >= ab and res.fn >= ab
    # Hand: the other pairs with a pred path have ratios 1 (unchanged), sqrt 2 (e.g.
    # A->(0,1): diagonal sqrt 2 in truth, 2 round (0,0) in pred) or 3/(1+sqrt 2) = 1.24
    # (e.g. A->(0,2)); only (A,B) has a ratio in (1.99, 2], so the tolerant scores of
    # the two tolerances differ by exactly the (A,B) pairs.
    assert within.tolerant.tp - beyond.tolerant.tp == ab
    assert beyond.tolerant.fp - within.tolerant.fp == ab
    assert beyond.tolerant.fn - within.tolerant.fn == ab


def test_tolerant_score_rejects_paths_through_truth_obstacles():
    #   truth        pred
    #   F # F        F F F      pred opens (0,1) and blocks (2,1); both maps are
    #   F # F        F # F      1-wide paths (trees), so every shortest path is unique.
    #   F F F        F # F
    # Hand classification of the pairs (drawn from truth's 7 free cells):
    #  * both ends in col 0 or both in col 2: same path in both maps -> TP;
    #  * an end on (2,1): blocked in pred -> FN;
    #  * one end in col 0, the other in col 2: truth goes along the bottom, pred over the
    #    top through a truth obstacle -> FP + FN, and the tolerant score must reject it
    #    however generous the tolerance (ratios range from 2/6 to 6/2).
    truth = np.full((3, 3), FREE, np.uint8)
    truth[0:2, 1] = IMPASSABLE
    pred = np.full((3, 3), FREE, np.uint8)
    pred[1:3, 1] = IMPASSABLE
    n, seed = 100, 0
    pairs = sample_pairs(truth == FREE, n, seed=seed)
    same = sum(s[1] == g[1] for s, g in pairs)
    middle = sum((2, 1) in (s, g) for s, g in pairs)
    cross = n - same - middle
    assert same > 0 and middle > 0 and cross > 0
    res = path_f1(truth, pred, n_pairs=n, seed=seed, length_tolerance=1e6)
    assert (res.tp, res.fp, res.fn, res.tn) == (same, cross, cross + middle, 0)
    tol = res.tolerant
    assert (tol.tp, tol.fp, tol.fn) == (same, cross, cross + middle)


def test_path_f1_unknown_is_impassable_by_default():
    # A 1x9 corridor; pred has an UNKNOWN cell in the middle.
    truth = np.full((1, 9), FREE, np.uint8)
    pred = truth.copy()
    pred[0, 4] = UNKNOWN
    n = 60
    # default: the UNKNOWN cell blocks the corridor -> crossing pairs and pairs ending on
    # (0,4) are FN; same-side pairs keep the (unique) straight path -> TP.
    res = path_f1(truth, pred, n_pairs=n, seed=1)
    pairs = sample_pairs(truth == FREE, n, seed=1)
    tp = sum((s[1] < 4 and g[1] < 4) or (s[1] > 4 and g[1] > 4) for s, g in pairs)
    assert 0 < tp < n
    assert (res.tp, res.fp, res.fn, res.tn) == (tp, 0, n - tp, 0)
    # optimistic: the UNKNOWN cell is passable, the maps plan identically -> all TP
    # (the drawn pairs are the same: truth has no UNKNOWN cell)
    res = path_f1(truth, pred, n_pairs=n, seed=1, unknown_passable=True)
    assert (res.tp, res.fp, res.fn, res.tn) == (n, 0, 0, 0)
    assert res.unknown_passable is True


def test_path_f1_unknown_in_truth_default_and_optimistic():
    # Truth: F F U F F. Default: pairs come from the 4 FREE cells; crossing pairs have
    # no path in either map -> TN. Optimistic: all 5 cells are drawn, all connected.
    truth = np.array([[FREE, FREE, UNKNOWN, FREE, FREE]], np.uint8)
    n = 50
    res = path_f1(truth, truth.copy(), n_pairs=n, seed=2)
    pairs = sample_pairs(truth == FREE, n, seed=2)
    cross = sum((s[1] < 2) != (g[1] < 2) for s, g in pairs)
    assert 0 < cross < n
    assert (res.tp, res.fp, res.fn, res.tn) == (n - cross, 0, 0, cross)
    res = path_f1(truth, truth.copy(), n_pairs=n, seed=2, unknown_passable=True)
    assert (res.tp, res.fp, res.fn, res.tn) == (n, 0, 0, 0)


def test_path_f1_argument_errors():
    a = np.zeros((5, 6), np.uint8)
    with pytest.raises(FedmapError, match="differ in size"):
        path_f1(a, np.zeros((6, 5), np.uint8))
    with pytest.raises(FedmapError, match="differ in size"):
        path_f1(a, np.zeros((5, 7), np.uint8))
    with pytest.raises(FedmapError, match="n_pairs"):
        path_f1(a, a, n_pairs=0)
    with pytest.raises(FedmapError, match="fewer than two"):
        path_f1(np.full((5, 6), IMPASSABLE, np.uint8), a)


# ----------------------------------------------------------------------------- the compiled search


def reference_astar(passable: np.ndarray, start, goal):
    """The pure-Python A* fedmap used before its search was compiled (same tie-break:
    heap key (f, h, flat index), orthogonal moves before diagonal ones, a parent changes
    only on a route shorter by more than 1e-9). Kept here as the reference."""
    import heapq

    passable = np.asarray(passable, dtype=bool)
    if not (passable[start] and passable[goal]):
        return None
    W = passable.shape[1] + 2
    free = np.pad(passable, 1, constant_values=False).ravel().tolist()
    s, t = (start[0] + 1) * W + start[1] + 1, (goal[0] + 1) * W + goal[1] + 1
    gr, gc = divmod(t, W)

    def heur(i):
        r, c = divmod(i, W)
        dr, dc = abs(r - gr), abs(c - gc)
        return (dr + dc) + (math.sqrt(2.0) - 2.0) * min(dr, dc)

    g, parent, closed = {s: 0.0}, {s: -1}, set()
    heap = [(heur(s), heur(s), s)]
    moves = [(d, None, None, 1.0) for d in (-W, W, -1, 1)] + [
        (-W - 1, -W, -1, math.sqrt(2.0)), (-W + 1, -W, 1, math.sqrt(2.0)),
        (W - 1, W, -1, math.sqrt(2.0)), (W + 1, W, 1, math.sqrt(2.0))]
    while heap:
        _, _, i = heapq.heappop(heap)
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
        for d, a, b, step in moves:
            j = i + d
            if free[j] and (a is None or (free[i + a] and free[i + b])) and j not in closed:
                nj = g[i] + step
                if nj < g.get(j, math.inf) - 1e-9:
                    g[j], parent[j] = nj, i
                    heapq.heappush(heap, (nj + heur(j), heur(j), j))
    return None


@pytest.mark.parametrize("seed", range(6))
def test_compiled_astar_gives_the_reference_path_cell_for_cell(seed):
    """Strict path F1 counts identical paths, so the compiled search must keep the tie-break:
    every path equal to the pure-Python reference's, not just as short."""
    passable = random_passable(100 + seed, shape=(30, 41), blocked=0.15 + 0.05 * seed)
    rng = np.random.default_rng(seed)
    cells = np.argwhere(passable)
    for _ in range(40):
        a, b = rng.choice(len(cells), size=2, replace=False)
        s, g = tuple(int(v) for v in cells[a]), tuple(int(v) for v in cells[b])
        assert astar(passable, s, g) == reference_astar(passable, s, g)


def test_truth_paths_are_cached_without_changing_a_score():
    from fedmap.evaluation import paths

    truth = np.where(random_passable(3, shape=(20, 24), blocked=0.3), FREE, IMPASSABLE).astype(np.uint8)
    pred = truth.copy()
    pred[5, :] = IMPASSABLE
    paths._TRUTH_PATHS.clear()
    cold = path_f1(truth, pred, n_pairs=30, seed=2)
    assert len(paths._TRUTH_PATHS) == 1
    warm = path_f1(truth, pred, n_pairs=30, seed=2)  # the truth's plans come from the cache
    assert warm == cold and len(paths._TRUTH_PATHS) == 1
    planned = paths.truth_paths(truth == FREE, 30, 2)
    assert [p for _, p in planned] == [reference_astar(truth == FREE, s, g) for (s, g), _ in planned]
    for k in range(paths._TRUTH_PATHS_KEPT + 2):  # other seeds: the oldest entries leave
        paths.truth_paths(truth == FREE, 5, 100 + k)
    assert len(paths._TRUTH_PATHS) == paths._TRUTH_PATHS_KEPT


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_astar_many_gives_each_pairs_reference_path_in_order(workers):
    """The searches shared among threads, each with working arrays used again from pair to
    pair: every path the reference's, in the pairs' order (blocked ends and unreachable
    goals included)."""
    passable = random_passable(7, shape=(37, 29), blocked=0.3)
    rng = np.random.default_rng(workers)
    cells = np.argwhere(np.ones_like(passable))
    pairs = []
    for _ in range(60):
        a, b = rng.choice(len(cells), size=2, replace=False)
        pairs.append((tuple(int(v) for v in cells[a]), tuple(int(v) for v in cells[b])))
    want = [reference_astar(passable, s, g) for s, g in pairs]
    assert any(p is None for p in want) and sum(p is not None for p in want) > 20
    assert astar_many(passable, pairs, workers=workers) == want


def test_astar_keeps_no_state_between_maps_of_one_size():
    """A search resets the cells it touched: a plan on one map, then on another of the same
    size, is the reference's on the second."""
    first, second = random_passable(11, shape=(25, 25), blocked=0.1), random_passable(12, shape=(25, 25), blocked=0.35)
    cells = np.argwhere(first & second)
    s, g = tuple(int(v) for v in cells[0]), tuple(int(v) for v in cells[-1])
    astar(first, s, g)
    assert astar(second, s, g) == reference_astar(second, s, g)
    assert astar_many(second, [(s, g)], workers=2) == [reference_astar(second, s, g)]


def _brute_path_f1_counts(truth: np.ndarray, pred: np.ndarray, n_pairs: int, seed: int, unknown_passable: bool):
    """Strict, literal and executed counts with every pair planned by the reference on both maps."""
    pt, pp = passable_mask(truth, unknown_passable=unknown_passable), passable_mask(pred, unknown_passable=unknown_passable)
    out = {"tp": 0, "fp": 0, "fn": 0, "tn": 0, "differ": 0, "executed": 0}
    for s, g in sample_pairs(pt, n_pairs, seed=seed):
        a, b = reference_astar(pt, s, g), reference_astar(pp, s, g)
        out["executed"] += a is not None and b is not None and ref_valid(pt, b)
        if a is None and b is None:
            out["tn"] += 1
        elif a == b:
            out["tp"] += 1
        else:
            out["fp"] += b is not None
            out["fn"] += a is not None
            out["differ"] += a is not None and b is not None
    return out


@pytest.mark.parametrize("seed", range(5))
def test_path_f1_skips_searches_the_changes_cannot_reach_without_changing_a_score(seed, monkeypatch):
    """A learned map that differs from the truth in a few cells: the pairs whose truth
    search never came near a change take the truth's path unsearched. Every count must
    equal planning every pair on both maps with the reference, and some searches must
    have been skipped (else the test would not test the shortcut)."""
    from fedmap.evaluation import paths

    rng = np.random.default_rng(seed)
    truth = np.where(random_passable(200 + seed, shape=(64, 72), blocked=0.25), FREE, IMPASSABLE).astype(np.uint8)
    truth[rng.random(truth.shape) < 0.02] = UNKNOWN
    pred = truth.copy()
    r0, c0 = int(rng.integers(0, 56)), int(rng.integers(0, 64))  # a few changes in one 8x8 patch
    patch = pred[r0:r0 + 8, c0:c0 + 8]
    flip = rng.random(patch.shape) < 0.4
    patch[flip] = rng.integers(0, 3, int(flip.sum()))
    searched = []
    real = paths.astar_many
    monkeypatch.setattr(paths, "astar_many", lambda pas, pairs, **kw: searched.extend(pairs) or real(pas, pairs, **kw))
    for unknown_passable in (False, True):
        paths._TRUTH_PATHS.clear()
        searched.clear()
        got = path_f1(truth, pred, n_pairs=60, seed=seed, unknown_passable=unknown_passable)
        want = _brute_path_f1_counts(truth, pred, 60, seed, unknown_passable)
        assert {"tp": got.tp, "fp": got.fp, "fn": got.fn, "tn": got.tn, "differ": got.paper.differ,
                "executed": got.executed} == want
        assert len(searched) < 60 - got.tn


def test_region_blocks_cover_each_change_and_its_neighbours():
    changed = np.zeros((20, 17), bool)
    changed[8, 7] = True  # its neighbours reach rows 7-9, cols 6-8: blocks (0, 0), (1, 0), (0, 1), (1, 1)
    changed[19, 16] = True  # neighbours rows 18-19, cols 15-16: blocks (2, 1) and the partial (2, 2)
    near = region_blocks(changed).reshape(3, 3)
    assert near.tolist() == [[True, True, False], [True, True, False], [False, True, True]]


def test_a_kernel_is_compiled_once_however_many_threads_ask_at_once():
    """Threads that ask for a compiled kernel before the first has it wait for that one's
    (``functools.cache`` alone would run the builder in each: 4 here). Every numba kernel
    fedmap builds is built this way."""
    import threading
    import time

    from fedmap._util import compiled_once
    from fedmap.evaluation import metrics
    from fedmap.maps import planning
    from fedmap.mission.world import frontiers
    from fedmap.nets import training

    built: list[int] = []

    def build() -> object:
        built.append(threading.get_ident())
        time.sleep(0.2)  # a compilation: long enough for every thread to ask meanwhile
        return object()

    kernel = compiled_once(build)
    start = threading.Barrier(4)
    got: list[object] = []

    def ask() -> None:
        start.wait()
        got.append(kernel())

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(built) == 1 and len(got) == 4 and all(g is got[0] for g in got)
    for builder in (planning._compiled, metrics._ssim_kernel, frontiers._dijkstra, frontiers._candidate_search,
                    training._decoder_kernel):
        assert builder.__code__ is kernel.__code__, builder.__name__  # built by compiled_once
