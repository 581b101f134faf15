"""The paper's path F1 read literally (``PathScores.paper``, ``MapScores.paper_other_unknown``).

The paper's text defines TP (identical path), FP (a learned path where the truth has
none) and FN (no learned path where the truth has one); a pair where both maps have a
path but the paths differ is counted as ``differ`` and in none of them.

Every expected count here is made by hand: the pairs are drawn with the documented seeded
sampler (``sample_pairs(passable_mask(truth), n, seed)``, the pairs ``path_f1`` uses) and
classified by the geometry of small hand-made maps, or, for the random-map check, by
reachability from ``scipy.sparse.csgraph`` (never by the planner under test). Precision,
recall and F1 are recomputed from the hand counts with the documented conventions.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from fedmap.evaluation.paths import PaperScores, path_f1
from fedmap.evaluation.scores import score_map
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.planning import passable_mask, sample_pairs

F, X, U = FREE, IMPASSABLE, UNKNOWN


def grid(rows: list[str], *, min_side: int = 0) -> np.ndarray:
    """A class map from strings: ``.`` free, ``#`` impassable, ``?`` unknown; padded with
    impassable cells on the right and bottom up to ``min_side`` (``score_map``'s SSIM
    needs 7x7), which keeps every cell's coordinates and every path."""
    code = {".": F, "#": X, "?": U}
    m = np.array([[code[ch] for ch in row] for row in rows], np.uint8)
    h, w = m.shape
    return np.pad(m, ((0, max(0, min_side - h)), (0, max(0, min_side - w))), constant_values=X)


def prf(tp: int, fp: int, fn: int) -> tuple[float, float, float]:
    """Precision, recall, F1 by the documented conventions: precision 1 when nothing was
    claimed (tp + fp = 0), recall 1 when nothing was to be found (tp + fn = 0)."""
    p = 1.0 if tp + fp == 0 else tp / (tp + fp)
    r = 1.0 if tp + fn == 0 else tp / (tp + fn)
    return p, r, (0.0 if p + r == 0 else 2 * p * r / (p + r))


def assert_paper(s: PaperScores, *, tp: int, fp: int, fn: int, tn: int, differ: int) -> None:
    assert (s.tp, s.fp, s.fn, s.tn, s.differ) == (tp, fp, fn, tn, differ)
    p, r, f = prf(tp, fp, fn)
    assert s.precision == pytest.approx(p) and s.recall == pytest.approx(r) and s.f1 == pytest.approx(f)


def drawn(truth: np.ndarray, n: int, seed: int, *, unknown_passable: bool = False):
    return sample_pairs(passable_mask(truth, unknown_passable=unknown_passable), n, seed=seed)


# ----------------------------------------------------------------------------- one case per outcome


def test_identical_paths_are_true_positives():
    # A 1x6 corridor: every pair has exactly one path (straight along the row) on both maps.
    truth = grid(["......"])
    n = 20
    res = path_f1(truth, truth.copy(), n_pairs=n, seed=0)
    assert_paper(res.paper, tp=n, fp=0, fn=0, tn=0, differ=0)
    assert res.paper.f1 == 1.0


def test_a_learned_path_where_the_truth_has_none_is_a_false_positive():
    # Truth: two free cells split by a wall, so every drawn pair is {(0,0), (0,2)} and the
    # truth has no path; the learned map opens the wall and has one.
    truth, pred = grid([".#."]), grid(["..."])
    n = 12
    assert all({s, g} == {(0, 0), (0, 2)} for s, g in drawn(truth, n, 1))
    res = path_f1(truth, pred, n_pairs=n, seed=1)
    assert_paper(res.paper, tp=0, fp=n, fn=0, tn=0, differ=0)
    # hand: precision 0/n = 0, recall 1 (no true path to find), F1 0
    assert (res.paper.precision, res.paper.recall, res.paper.f1) == (0.0, 1.0, 0.0)
    assert (res.tp, res.fp, res.fn, res.tn) == (0, n, 0, 0)  # the strict reading agrees


def test_no_learned_path_where_the_truth_has_one_is_a_false_negative():
    # Truth: a 1x5 corridor. The learned map walls off the middle cell (0,2): a pair on one
    # side keeps its (only) path -> TP; a pair crossing or ending on (0,2) has none -> FN.
    truth = grid(["....."])
    pred = grid(["..#.."])
    n, seed = 40, 2

    def side(cell):
        return "L" if cell[1] < 2 else ("R" if cell[1] > 2 else "M")

    pairs = drawn(truth, n, seed)
    tp = sum(side(s) == side(g) != "M" for s, g in pairs)
    fn = n - tp
    assert 0 < tp < n
    res = path_f1(truth, pred, n_pairs=n, seed=seed)
    assert_paper(res.paper, tp=tp, fp=0, fn=fn, tn=0, differ=0)
    assert res.paper.precision == 1.0 and res.paper.recall == pytest.approx(tp / n)


def test_no_path_on_either_map_is_a_true_negative():
    # The same walled pair as the FP case, and the learned map keeps the wall.
    truth = grid([".#."])
    n = 9
    res = path_f1(truth, truth.copy(), n_pairs=n, seed=3)
    assert_paper(res.paper, tp=0, fp=0, fn=0, tn=n, differ=0)
    # the documented convention: nothing claimed and nothing to find -> P = R = F1 = 1
    assert (res.paper.precision, res.paper.recall, res.paper.f1) == (1.0, 1.0, 1.0)


def test_different_paths_are_fp_and_fn_strictly_but_not_counted_literally():
    #   truth   pred      Both maps are 1-wide trees (no 2x2 free block, so no diagonal
    #   . # .   . . .     move), so every path is the only one. Pairs come from truth's 7
    #   . # .   . # .     free cells. Hand classification:
    #   . . .   . # .     * both ends in col 0 or both in col 2: the same straight path -> TP;
    #   * an end on (2,1), blocked in pred -> FN;
    #   * one end in col 0, the other in col 2: truth goes round the bottom, pred round
    #     the top -> both found, different -> differ (strictly: FP and FN).
    truth = grid([".#.", ".#.", "..."])
    pred = grid(["...", ".#.", ".#."])
    n, seed = 100, 0
    pairs = drawn(truth, n, seed)
    same = sum(s[1] == g[1] for s, g in pairs)
    middle = sum((2, 1) in (s, g) for s, g in pairs)
    cross = n - same - middle
    assert same > 0 and middle > 0 and cross > 0
    res = path_f1(truth, pred, n_pairs=n, seed=seed)
    assert_paper(res.paper, tp=same, fp=0, fn=middle, tn=0, differ=cross)
    # the strict reading of the same plans counts each differing pair once as FP and once as FN
    assert (res.tp, res.fp, res.fn, res.tn) == (same, cross, cross + middle, 0)
    assert res.paper.f1 > res.f1  # hand: dropping the differing pairs only removes errors here


def test_when_every_path_differs_the_literal_f1_is_one():
    # The documented consequence of the empty-denominator conventions: with no TP, FP or
    # FN at all the literal F1 is 1, however wrong every path is. Same maps as above; pick
    # (by the hand classification, not the planner) a seed whose 3 drawn pairs all cross.
    truth = grid([".#.", ".#.", "..."])
    pred = grid(["...", ".#.", ".#."])
    n = 3
    seed = next(k for k in range(1000)
                if all({s[1], g[1]} == {0, 2} for s, g in drawn(truth, n, k)))
    res = path_f1(truth, pred, n_pairs=n, seed=seed)
    assert_paper(res.paper, tp=0, fp=0, fn=0, tn=0, differ=n)
    assert res.paper.f1 == 1.0
    assert (res.tp, res.fp, res.fn, res.f1) == (0, n, n, 0.0)  # strictly: all wrong


# ----------------------------------------------------------------------------- UNKNOWN cells


def test_unknown_passable_turns_false_negatives_into_differing_paths():
    #   truth   pred      pred is truth's U (open at the bottom) turned upside down, with
    #   . # .   . ? .     the new top-middle cell UNKNOWN. Truth has no UNKNOWN cell, so the
    #   . # .   . # .     drawn pairs are the same with either setting.
    #   . . .   . # .
    # UNKNOWN impassable: pred's free cells are two disconnected columns. Same column ->
    #   TP; an end on (2,1) -> FN; crossing -> FN.
    # UNKNOWN passable: pred is the top-open U (a tree). Same column -> TP; an end on
    #   (2,1) -> FN; crossing -> both found, different -> differ.
    truth = grid([".#.", ".#.", "..."], min_side=7)
    pred = grid([".?.", ".#.", ".#."], min_side=7)
    n, seed = 90, 5
    pairs = drawn(truth, n, seed)
    assert pairs == drawn(truth, n, seed, unknown_passable=True)
    same = sum(s[1] == g[1] for s, g in pairs)
    middle = sum((2, 1) in (s, g) for s, g in pairs)
    cross = n - same - middle
    assert same > 0 and middle > 0 and cross > 0

    impassable = dict(tp=same, fp=0, fn=middle + cross, tn=0, differ=0)
    passable = dict(tp=same, fp=0, fn=middle, tn=0, differ=cross)
    assert_paper(path_f1(truth, pred, n_pairs=n, seed=seed).paper, **impassable)
    assert_paper(path_f1(truth, pred, n_pairs=n, seed=seed, unknown_passable=True).paper, **passable)
    # hand: recall rises from same / n to same / (same + middle); precision stays 1
    imp = path_f1(truth, pred, n_pairs=n, seed=seed).paper
    pas = path_f1(truth, pred, n_pairs=n, seed=seed, unknown_passable=True).paper
    assert imp.recall == pytest.approx(same / n) and pas.recall == pytest.approx(same / (same + middle))
    assert imp.precision == pas.precision == 1.0

    # score_map reports both settings whatever the run's own setting is
    for run_setting in (False, True):
        m = score_map(truth, pred, pairs=n, seed=seed, unknown_passable=run_setting)
        assert m.path.unknown_passable is run_setting
        assert m.paper_unknown_impassable is not None and m.paper_unknown_passable is not None
        assert_paper(m.paper_unknown_impassable, **impassable)
        assert_paper(m.paper_unknown_passable, **passable)
        assert m.paper_other_unknown == (m.paper_unknown_impassable if run_setting else m.paper_unknown_passable)
        d = m.to_dict()
        assert d["paper_other_unknown"]["unknown_passable"] is (not run_setting)
        assert d["path"]["paper"]["differ"] == (cross if run_setting else 0)


def test_unknown_passable_turns_true_negatives_into_false_positives():
    # Truth: a corridor cut by a wall at (0,2); the learned map has UNKNOWN there.
    # Impassable: same side -> TP (one straight path), crossing -> no path on either -> TN.
    # Passable: crossing -> the learned map has a path and the truth none -> FP.
    truth = grid(["..#.."], min_side=7)
    pred = grid(["..?.."], min_side=7)
    n, seed = 40, 6
    pairs = drawn(truth, n, seed)
    same = sum((s[1] < 2) == (g[1] < 2) for s, g in pairs)
    cross = n - same
    assert 0 < same < n
    m = score_map(truth, pred, pairs=n, seed=seed)
    assert_paper(m.paper_unknown_impassable, tp=same, fp=0, fn=0, tn=cross, differ=0)
    assert_paper(m.paper_unknown_passable, tp=same, fp=cross, fn=0, tn=0, differ=0)
    assert m.paper_unknown_impassable.f1 == 1.0
    assert m.paper_unknown_passable.precision == pytest.approx(same / n)


def test_other_setting_is_skipped_when_it_leaves_no_pairs():
    # Truth with one FREE cell and UNKNOWN elsewhere: scored with UNKNOWN passable there are
    # pairs to draw, with UNKNOWN impassable there are not (fewer than two cells).
    truth = grid([".??"], min_side=7)
    m = score_map(truth, truth.copy(), pairs=5, seed=0, unknown_passable=True)
    assert m.paper_other_unknown is None and m.paper_unknown_impassable is None
    assert m.to_dict()["paper_other_unknown"] is None
    assert_paper(m.paper_unknown_passable, tp=5, fp=0, fn=0, tn=0, differ=0)


# ----------------------------------------------------------------------------- against reachability


def reach_labels(passable: np.ndarray) -> np.ndarray:
    """Connected components of the 8-connected no-corner-cutting grid, built here cell by
    cell and labelled by scipy (-1 on blocked cells)."""
    h, w = passable.shape
    rows, cols = [], []
    for r in range(h):
        for c in range(w):
            if not passable[r, c]:
                continue
            for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
                r2, c2 = r + dr, c + dc
                if not (0 <= r2 < h and 0 <= c2 < w) or not passable[r2, c2]:
                    continue
                if dr and dc and not (passable[r + dr, c] and passable[r, c + dc]):
                    continue
                rows.append(r * w + c)
                cols.append(r2 * w + c2)
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(h * w, h * w))
    _, lab = connected_components(g, directed=False)
    return np.where(passable, lab.reshape(h, w), -1)


@pytest.mark.parametrize("seed", range(6))
def test_literal_counts_follow_reachability_on_random_maps(seed):
    # FP, FN and TN need only "is there a path?" on each map, so they are counted here
    # from independent reachability; TP + differ is every pair reachable on both maps, and
    # TP is the strict TP (tested in test_planning.py). The strict counts then follow.
    rng = np.random.default_rng(seed)
    truth = np.where(rng.random((14, 16)) < 0.3, X, F).astype(np.uint8)
    pred = truth.copy()
    flip = rng.random(truth.shape) < 0.12
    pred[flip] = rng.choice([F, X, U], size=int(flip.sum()))
    n = 60
    for up in (False, True):
        pt, pp = passable_mask(truth, unknown_passable=up), passable_mask(pred, unknown_passable=up)
        lt, lp = reach_labels(pt), reach_labels(pp)
        both = fp = fn = tn = 0
        for s, g in drawn(truth, n, seed, unknown_passable=up):
            t_has = lt[s] == lt[g]
            p_has = lp[s] >= 0 and lp[s] == lp[g]
            both += t_has and p_has
            fp += p_has and not t_has
            fn += t_has and not p_has
            tn += not (t_has or p_has)
        res = path_f1(truth, pred, n_pairs=n, seed=seed, unknown_passable=up)
        pap = res.paper
        assert (pap.fp, pap.fn, pap.tn) == (fp, fn, tn)
        assert pap.tp == res.tp and pap.tp + pap.differ == both
        assert (res.fp, res.fn, res.tn) == (fp + pap.differ, fn + pap.differ, tn)
        assert_paper(pap, tp=pap.tp, fp=fp, fn=fn, tn=tn, differ=both - pap.tp)


# ----------------------------------------------------------------------------- JSON


def test_json_keeps_existing_keys_and_appends_the_literal_reading():
    truth = grid(["....."], min_side=7)
    pred = grid(["..?.."], min_side=7)
    m = score_map(truth, pred, pairs=10, seed=0)
    d = m.to_dict()
    assert list(d) == ["psnr", "ssim", "accuracy", "iou_free", "iou_impassable", "path", "paper_other_unknown"]
    assert list(d["path"]) == ["pairs", "tp", "fp", "fn", "tn", "precision", "recall", "f1", "tolerant",
                               "mean_length_ratio", "unknown_passable", "paper", "executed", "success"]
    assert list(d["path"]["paper"]) == ["tp", "fp", "fn", "tn", "differ", "precision", "recall", "f1"]
    assert list(d["paper_other_unknown"]) == ["unknown_passable", "tp", "fp", "fn", "tn", "differ", "precision",
                                              "recall", "f1"]
