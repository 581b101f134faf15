"""Tests for fedmap.refine: gap filling, small-component removal, RefineConfig.

Every expected map is worked out by hand from the documented rules (majority of the
known 8-neighbours with at least ``min_votes`` of them; IMPASSABLE blobs under
``min_size`` become FREE; enclosed UNKNOWN islands under ``min_size`` take their rim's
majority; UNKNOWN touching the border is left alone).
"""

from __future__ import annotations

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.refine import PAPER_REFINE, RefineConfig, fill_gaps, refine, remove_small_components


def full(shape, value=FREE):
    return np.full(shape, value, np.uint8)


# ----------------------------------------------------------------------------- fill_gaps


def test_single_gap_in_free_becomes_free():
    c = full((7, 7))
    c[3, 3] = UNKNOWN
    out = fill_gaps(c)
    expected = full((7, 7))  # hand: 8 FREE voters >= 5
    np.testing.assert_array_equal(out, expected)


def test_single_gap_takes_the_majority():
    # hand: neighbours of (2,2) are 5 IMPASSABLE and 3 FREE -> IMPASSABLE
    c = full((5, 5))
    c[1, 1:4] = IMPASSABLE
    c[2, 1] = c[2, 3] = IMPASSABLE
    c[2, 2] = UNKNOWN
    out = fill_gaps(c, iterations=1)
    assert out[2, 2] == IMPASSABLE
    out[2, 2] = UNKNOWN
    np.testing.assert_array_equal(out, c)  # nothing else changes


def test_gap_with_too_few_voters_stays_unknown():
    # (0,0) of a map has only 3 neighbours, all FREE: 3 < min_votes = 5.
    c = full((6, 6))
    c[0, 0] = UNKNOWN
    assert fill_gaps(c)[0, 0] == UNKNOWN
    # with min_votes = 3 it is filled
    assert fill_gaps(c, min_votes=3)[0, 0] == FREE


def test_large_unknown_block_keeps_its_interior():
    c = full((40, 40))
    c[10:30, 10:30] = UNKNOWN
    out = fill_gaps(c)  # window 3, min_votes 5, iterations 2
    # Hand: in pass 1 only the 4 block corners see 5 known neighbours (an edge cell sees
    # 3); in pass 2 an edge cell next to a filled corner sees 3 + 1 = 4 < 5 and an inner
    # cell at most 1, so exactly the 4 corners are filled.
    expected = c.copy()
    for r, cc in ((10, 10), (10, 29), (29, 10), (29, 29)):
        expected[r, cc] = FREE
    np.testing.assert_array_equal(out, expected)
    # the process has stalled: more iterations change nothing
    np.testing.assert_array_equal(fill_gaps(c, iterations=10), expected)
    assert (out[12:28, 12:28] == UNKNOWN).all()


def test_fill_gaps_zero_iterations_is_identity():
    c = full((5, 5))
    c[2, 2] = UNKNOWN
    np.testing.assert_array_equal(fill_gaps(c, iterations=0), c)


# ----------------------------------------------------------------------------- components


@pytest.mark.parametrize("min_size,kept", [(200, False), (10, False), (9, True), (5, True)])
def test_small_impassable_blob_removed_below_min_size(min_size, kept):
    c = full((30, 30))
    c[10:13, 10:13] = IMPASSABLE  # 9 cells
    out = remove_small_components(c, min_size=min_size)
    # hand: "smaller than min_size" -> removed iff 9 < min_size
    expected = c if kept else full((30, 30))
    np.testing.assert_array_equal(out, expected)


def test_large_impassable_blob_is_kept():
    c = full((40, 40))
    c[5:20, 5:20] = IMPASSABLE  # 15 x 15 = 225 >= 200
    np.testing.assert_array_equal(remove_small_components(c, min_size=200), c)
    np.testing.assert_array_equal(remove_small_components(c, min_size=225), c)
    np.testing.assert_array_equal(remove_small_components(c, min_size=226), full((40, 40)))


def test_blob_size_uses_8_connectivity():
    # Two 3x3 squares touching only at a corner form one 8-connected blob of 18 cells.
    c = full((20, 20))
    c[2:5, 2:5] = IMPASSABLE
    c[5:8, 5:8] = IMPASSABLE
    np.testing.assert_array_equal(remove_small_components(c, min_size=18), c)
    np.testing.assert_array_equal(remove_small_components(c, min_size=19), full((20, 20)))


def test_enclosed_unknown_island_in_impassable_becomes_impassable():
    # A large (kept) IMPASSABLE area with a 2x2 UNKNOWN hole: hole rim is all IMPASSABLE.
    c = full((40, 40))
    c[5:25, 5:25] = IMPASSABLE  # 400 cells, minus the hole: 396 >= 200
    c[14:16, 14:16] = UNKNOWN
    out = remove_small_components(c, min_size=200)
    expected = c.copy()
    expected[14:16, 14:16] = IMPASSABLE
    np.testing.assert_array_equal(out, expected)


def test_enclosed_unknown_island_in_thin_ring():
    # A 1-cell IMPASSABLE ring (12 cells) round a 2x2 UNKNOWN hole inside FREE ground.
    c = full((12, 12))
    c[4:8, 4:8] = IMPASSABLE
    c[5:7, 5:7] = UNKNOWN
    # min_size 5: the ring (12) stays; the hole (4 < 5) takes its rim's class.
    expected = c.copy()
    expected[5:7, 5:7] = IMPASSABLE
    np.testing.assert_array_equal(remove_small_components(c, min_size=5), expected)
    # min_size 200: the ring is removed first (-> FREE), then the hole is enclosed by FREE.
    np.testing.assert_array_equal(remove_small_components(c, min_size=200), full((12, 12)))


def test_enclosed_unknown_island_takes_rim_majority():
    # 1x1 UNKNOWN at (5,5); rim: 5 IMPASSABLE (row 4 cols 4..6, (5,4), (5,6)) vs 3 FREE.
    # The IMPASSABLE blob is 8-connected with 5 cells, kept with min_size 5.
    c = full((11, 11))
    c[4, 4:7] = IMPASSABLE
    c[5, 4] = c[5, 6] = IMPASSABLE
    c[5, 5] = UNKNOWN
    out = remove_small_components(c, min_size=5)
    assert out[5, 5] == IMPASSABLE


@pytest.mark.parametrize("where", ["top", "bottom", "left", "right"])
def test_unknown_touching_the_border_is_not_filled(where):
    c = full((30, 30))
    sl = {"top": np.s_[0:3, 10:13], "bottom": np.s_[27:30, 10:13],
          "left": np.s_[10:13, 0:3], "right": np.s_[10:13, 27:30]}[where]
    c[sl] = UNKNOWN
    np.testing.assert_array_equal(remove_small_components(c, min_size=200), c)


@pytest.mark.parametrize("where", ["top", "bottom", "left", "right"])
def test_unknown_one_cell_from_the_border_is_filled(where):
    # The same 3x3 island moved one cell inwards is enclosed by FREE -> FREE.
    c = full((30, 30))
    sl = {"top": np.s_[1:4, 10:13], "bottom": np.s_[26:29, 10:13],
          "left": np.s_[10:13, 1:4], "right": np.s_[10:13, 26:29]}[where]
    c[sl] = UNKNOWN
    np.testing.assert_array_equal(remove_small_components(c, min_size=200), full((30, 30)))


def test_large_unknown_area_is_not_filled():
    c = full((40, 40))
    c[10:30, 10:30] = UNKNOWN  # 400 >= 200
    np.testing.assert_array_equal(remove_small_components(c, min_size=200), c)


def test_min_size_one_or_zero_changes_nothing():
    c = full((8, 8))
    c[3, 3] = IMPASSABLE
    c[5, 5] = UNKNOWN
    for m in (0, 1):
        np.testing.assert_array_equal(remove_small_components(c, min_size=m), c)


# ----------------------------------------------------------------------------- refine


def test_refine_fills_gap_and_removes_noise():
    c = full((40, 40))
    c[5:25, 5:25] = IMPASSABLE  # real obstacle, kept
    c[30, 30] = IMPASSABLE  # noise, removed
    c[32, 10] = UNKNOWN  # gap, filled FREE
    c[0:2, 30:40] = UNKNOWN  # unexplored strip on the border: 20 cells
    out = refine(c, PAPER_REFINE)
    assert np.array_equal(refine(c)[30, 30], IMPASSABLE)  # fedmap's default keeps small blobs
    expected = full((40, 40))
    expected[5:25, 5:25] = IMPASSABLE
    # hand: gap filling turns the strip's inner corner (1,30) FREE (5 FREE voters) and,
    # in pass 2, (0,30) sees (1,30) + (0,29) + (1,29) = 3 < 5; (1,31) sees 3 + 1 = 4 < 5.
    expected[0:2, 30:40] = UNKNOWN
    expected[1, 30] = FREE
    np.testing.assert_array_equal(out, expected)


def test_refine_config_defaults_and_dict():
    cfg = RefineConfig()
    assert cfg.to_dict() == {"window": 3, "min_votes": 5, "iterations": 2, "min_size": 0}
    assert PAPER_REFINE.min_size == 200  # the paper's threshold
    RefineConfig(window=5, min_votes=24)  # the largest legal vote count for a 5x5 window


@pytest.mark.parametrize(
    "kwargs",
    [
        {"window": 1},
        {"window": 2},
        {"window": 4},
        {"min_votes": 0},
        {"min_votes": 9},  # window 3 has only 8 voters
        {"window": 5, "min_votes": 25},
        {"iterations": -1},
        {"min_size": -1},
    ],
)
def test_refine_config_validation(kwargs):
    with pytest.raises(FedmapError):
        RefineConfig(**kwargs)


def test_inputs_are_not_modified():
    rng = np.random.default_rng(0)
    c = rng.choice([FREE, IMPASSABLE, UNKNOWN], size=(30, 30), p=[0.6, 0.2, 0.2]).astype(np.uint8)
    keep = c.copy()
    out1 = fill_gaps(c)
    out2 = remove_small_components(c, min_size=50)
    out3 = refine(c, RefineConfig(min_size=50))
    np.testing.assert_array_equal(c, keep)
    for out in (out1, out2, out3):
        assert out is not c and not np.shares_memory(out, c)
        assert out.dtype == np.uint8
    # the random map is rich enough for each function to change something
    assert (out1 != c).any() and (out2 != c).any() and (out3 != c).any()
