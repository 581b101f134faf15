"""The paper's path-planning F1 of a learned map against ground truth: strict, tolerant and
literal.

Both maps are planned on with the one A* of :mod:`fedmap.maps.planning`, for seeded
start/goal pairs drawn from the passable cells of the truth. Three readings of the same
plans (see :func:`path_f1`): strict (:class:`PathScores`: a different path is both a
false positive and a false negative), tolerant (:class:`TolerantScores`: a collision-free
path at most 5% longer is correct) and the paper's text read literally
(:class:`PaperScores`: a different path is not counted at all).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.planning import (
    astar_many,
    astar_regions,
    passable_mask,
    path_is_valid,
    path_length,
    region_blocks,
    sample_pairs,
)


@dataclass(frozen=True)
class TolerantScores:
    """A learned path counts as correct when it is collision-free on the true map and at
    most ``1 + length_tolerance`` times the true path's length."""

    length_tolerance: float
    tp: int
    fp: int
    fn: int
    precision: float
    recall: float
    f1: float


@dataclass(frozen=True)
class PaperScores:
    """The paper's path F1 read literally: its text defines only three outcomes.

    * ``tp``: the learned path is identical to the true one, cell for cell;
    * ``fp``: the learned map gives a path where the truth has none;
    * ``fn``: the learned map gives no path where the truth has one;
    * ``tn``: neither map has a path;
    * ``differ``: both maps have a path but the paths differ. The paper's text defines no
      outcome for this case, so it is counted here and left out of precision, recall and
      F1 (the strict :class:`PathScores` counts it once as FP and once as FN).

    Precision, recall and F1 use the strict F1's conventions for empty denominators: no
    TP + FP gives precision 1, no TP + FN gives recall 1. So a map whose every pair is a
    TN or ``differ`` scores precision = recall = F1 = 1.
    """

    tp: int
    fp: int
    fn: int
    tn: int
    differ: int
    precision: float
    recall: float
    f1: float


@dataclass(frozen=True)
class PathScores:
    """Counts and precision / recall / F1 of :func:`path_f1` (``to_dict`` for JSON).

    The top-level counts and scores are the strict reading; ``tolerant`` and ``paper`` (the
    paper's text read literally) score the same plans, with the same ``unknown_passable``.
    """

    pairs: int
    tp: int
    fp: int
    fn: int
    tn: int
    precision: float
    recall: float
    f1: float
    tolerant: TolerantScores
    mean_length_ratio: float | None
    unknown_passable: bool
    paper: PaperScores
    #: pairs where the truth has a path and the path planned on the learned map, driven on
    #: the truth, reaches the goal without entering an impassable cell
    executed: int
    #: ``executed`` over the pairs where the truth has a path (1.0 when it has none): the
    #: share of paths a rover planning on this map would drive safely to the goal
    success: float

    def to_dict(self) -> dict:
        return asdict(self)


def _prf(tp: int, fp: int, fn: int) -> tuple[float, float, float]:
    p = tp / (tp + fp) if tp + fp else 1.0
    r = tp / (tp + fn) if tp + fn else 1.0
    f = 2 * p * r / (p + r) if p + r else 0.0
    return p, r, f


Pair = tuple[tuple[int, int], tuple[int, int]]
Path = list[tuple[int, int]]

#: Recent truths' planned pairs (:func:`truth_paths`) with each search's region, least
#: recently used first.
_TRUTH_PATHS: OrderedDict[tuple, tuple[list, list]] = OrderedDict()
_TRUTH_PATHS_KEPT = 8


def truth_paths(passable: np.ndarray, n_pairs: int, seed: int) -> list[tuple[Pair, Path | None]]:
    """The seeded start/goal pairs of a truth's passable mask with the truth's path of each
    (None: unreachable). A truth does not change during a mission or a ``reproduce``
    terrain, so the last few are kept, keyed by the mask's bytes (a pure function of its
    arguments: the cache changes no result, only the time)."""
    return _truth_plans(passable, n_pairs, seed)[0]


def _truth_plans(passable: np.ndarray, n_pairs: int, seed: int) -> tuple[list[tuple[Pair, Path | None]],
                                                                          list[np.ndarray | None]]:
    """:func:`truth_paths` and the region of each pair's search (None: not searched), as
    :func:`~fedmap.maps.planning.astar_regions` gives them."""
    passable = np.ascontiguousarray(passable, dtype=bool)
    key = (passable.shape, hashlib.blake2b(passable.tobytes(), digest_size=16).digest(), n_pairs, seed)
    if key in _TRUTH_PATHS:
        _TRUTH_PATHS.move_to_end(key)
        return _TRUTH_PATHS[key]
    labels, _ = ndimage.label(passable)  # 4-connectivity == reachability (see module doc)
    pairs = sample_pairs(passable, n_pairs, seed=seed)
    joined = _joined(labels, pairs)
    paths: list[Path | None] = [None] * len(pairs)
    regions: list[np.ndarray | None] = [None] * len(pairs)
    for k, (path, region) in zip(joined, astar_regions(passable, [pairs[k] for k in joined])):
        paths[k], regions[k] = path, region
    _TRUTH_PATHS[key] = entry = (list(zip(pairs, paths)), regions)
    while len(_TRUTH_PATHS) > _TRUTH_PATHS_KEPT:
        _TRUTH_PATHS.popitem(last=False)
    return entry


def _joined(labels: np.ndarray, pairs: list[Pair]) -> list[int]:
    """The pairs whose ends the 4-connected ``labels`` join (the only ones with a path)."""
    return [k for k, (s, g) in enumerate(pairs) if labels[s] and labels[s] == labels[g]]


def _pred_paths(pp: np.ndarray, pt: np.ndarray, planned: list[tuple[Pair, Path | None]],
                regions: list[np.ndarray | None]) -> list[Path | None]:
    """The learned map's path of each planned pair. A pair whose truth search read no cell
    where the learned map's passability differs (no changed cell or neighbour in its
    region: :func:`~fedmap.maps.planning.region_blocks`) would take the same steps on the
    learned map, so its truth path is taken without a search; the rest are searched where
    the learned map's 4-connected components join their ends."""
    near = region_blocks(pp != pt)
    out: list[Path | None] = [None] * len(planned)
    search = []
    for k, ((_, path), region) in enumerate(zip(planned, regions)):
        if region is not None and not near[region].any():
            out[k] = path
        else:
            search.append(k)
    if search:
        labels, _ = ndimage.label(pp)
        todo = [search[k] for k in _joined(labels, [planned[k][0] for k in search])]
        for k, path in zip(todo, astar_many(pp, [planned[k][0] for k in todo])):
            out[k] = path
    return out


def path_f1(
    truth: np.ndarray,
    pred: np.ndarray,
    *,
    n_pairs: int = 75,
    seed: int = 0,
    unknown_passable: bool = False,
    length_tolerance: float = 0.05,
) -> PathScores:
    """The paper's path-planning F1 (strict), plus a tolerant and a literal reading.

    For ``n_pairs`` seeded start/goal pairs drawn from the passable cells of ``truth``,
    plan with the same A* on both maps:

    * TP: both find a path and the paths are identical, cell for cell;
    * FP: the learned map gives a path that is not the true one (the truth has none, or
      a different one);
    * FN: the truth has a path that the learned map does not reproduce (none found, or a
      different one). So a different path counts once as FP and once as FN;
    * TN: neither map has a path.

    Conventions for empty denominators: with no learned path at all precision is 1
    (nothing was claimed wrongly); with no true path at all recall is 1; so when every
    pair has no path on either map, precision, recall and F1 are all 1.

    The tolerant variant counts a learned path as correct when it is collision-free on
    the true map and at most ``(1 + length_tolerance)`` times the true path's length.

    ``success`` is the executed reading: over the pairs the truth connects, the share
    whose learned path, driven on the truth, reaches the goal without entering an
    impassable cell (whatever its length).

    ``paper`` (:class:`PaperScores`) reads the paper's text literally, from the same plans
    of the same pairs: TP and TN as above, FP only where the truth has no path, FN only
    where the learned map has none; a pair where both maps have a path but the paths differ
    is counted as ``differ`` and in none of TP, FP, FN. Same empty-denominator conventions.
    """
    truth = np.asarray(truth)
    pred = np.asarray(pred)
    if truth.shape != pred.shape:
        raise FedmapError(f"learned map {pred.shape} and ground truth {truth.shape} differ in size")
    if n_pairs <= 0:
        raise FedmapError(f"n_pairs must be positive, got {n_pairs}")
    pt = passable_mask(truth, unknown_passable=unknown_passable)
    pp = passable_mask(pred, unknown_passable=unknown_passable)
    tp = fp = fn = tn = 0
    tol_tp = tol_fp = tol_fn = 0
    pap_fp = pap_fn = differ = 0  # the literal reading: its TP and TN are the strict ones
    ratios = []
    executed = reachable = 0
    planned, regions = _truth_plans(pt, n_pairs, seed)
    for (_, true_path), pred_path in zip(planned, _pred_paths(pp, pt, planned, regions)):
        if true_path is not None:
            reachable += 1
            executed += pred_path is not None and path_is_valid(pt, pred_path)
        if true_path is None and pred_path is None:
            tn += 1
            continue
        if true_path is not None and pred_path is not None and true_path == pred_path:
            tp += 1
        else:
            fp += pred_path is not None
            fn += true_path is not None
            if true_path is not None and pred_path is not None:
                differ += 1
            else:
                pap_fp += pred_path is not None
                pap_fn += true_path is not None
        # tolerant variant
        if true_path is not None and pred_path is not None:
            ratio = path_length(pred_path) / max(path_length(true_path), 1e-12)
            ratios.append(ratio)
            if path_is_valid(pt, pred_path) and ratio <= 1 + length_tolerance:
                tol_tp += 1
            else:
                tol_fp += 1
                tol_fn += 1
        else:
            tol_fp += pred_path is not None
            tol_fn += true_path is not None

    p, r, f = _prf(tp, fp, fn)
    tp_, tr_, tf_ = _prf(tol_tp, tol_fp, tol_fn)
    tolerant = TolerantScores(length_tolerance, tol_tp, tol_fp, tol_fn, tp_, tr_, tf_)
    paper = PaperScores(tp, pap_fp, pap_fn, tn, differ, *_prf(tp, pap_fp, pap_fn))
    return PathScores(n_pairs, tp, fp, fn, tn, p, r, f, tolerant, float(np.mean(ratios)) if ratios else None,
                      unknown_passable, paper, executed, executed / reachable if reachable else 1.0)
