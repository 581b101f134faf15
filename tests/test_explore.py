"""Tests for fedmap.explore: partition masks and agents' local maps.

Expected masks are hand-derived (even sizes: exact halves) or checked by properties
(disjoint, covering, rectangles of nearly equal size). For the traverse mode the sensor
footprint is checked by brute force with a k-d tree (scipy.spatial.cKDTree), independent
of the distance transform the module uses.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fedmap.errors import FedmapError
from fedmap.explore import explore, region_masks
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap


def bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    rr, cc = np.nonzero(mask)
    return int(rr.min()), int(rr.max()) + 1, int(cc.min()), int(cc.max()) + 1


def is_rectangle(mask: np.ndarray) -> bool:
    r0, r1, c0, c1 = bbox(mask)
    return bool(mask[r0:r1, c0:c1].all()) and int(mask.sum()) == (r1 - r0) * (c1 - c0)


def random_truth(shape=(48, 52), seed=0, blocked=0.15) -> GridMap:
    rng = np.random.default_rng(seed)
    return GridMap(np.where(rng.random(shape) < blocked, IMPASSABLE, FREE).astype(np.uint8), 1.0, "t")


# ----------------------------------------------------------------------------- partitions


@pytest.mark.parametrize("shape", [(65, 67), (64, 64), (3, 5)])
def test_quadrants_disjoint_and_covering(shape):
    masks = region_masks(shape, 4, "quadrants")
    assert len(masks) == 4
    count = np.sum(masks, axis=0)
    assert (count == 1).all()  # disjoint and covering
    h, w = shape
    heights, widths = set(), set()
    for m in masks:
        assert m.shape == shape and m.dtype == bool
        assert is_rectangle(m)
        r0, r1, c0, c1 = bbox(m)
        heights.add(r1 - r0)
        widths.add(c1 - c0)
    # nearly equal halves: sizes floor(n/2) or ceil(n/2)
    assert heights <= {h // 2, h - h // 2} and widths <= {w // 2, w - w // 2}
    # row-major order: top-left, top-right, bottom-left, bottom-right
    assert masks[0][0, 0] and masks[1][0, w - 1] and masks[2][h - 1, 0] and masks[3][h - 1, w - 1]


def test_quadrants_even_size_by_hand():
    masks = region_masks((40, 60), 4, "quadrants")
    expected = [np.zeros((40, 60), bool) for _ in range(4)]
    expected[0][:20, :30] = True
    expected[1][:20, 30:] = True
    expected[2][20:, :30] = True
    expected[3][20:, 30:] = True
    for m, e in zip(masks, expected):
        np.testing.assert_array_equal(m, e)


@pytest.mark.parametrize("overlap", [1, 3])
def test_overlap_widens_each_block(overlap):
    shape = (65, 67)
    base = region_masks(shape, 4, "quadrants")
    wide = region_masks(shape, 4, "quadrants", overlap=overlap)
    h, w = shape
    for b, m in zip(base, wide):
        # hand: the base rectangle grown by `overlap` on every side, clipped to the map
        r0, r1, c0, c1 = bbox(b)
        e = np.zeros(shape, bool)
        e[max(r0 - overlap, 0):min(r1 + overlap, h), max(c0 - overlap, 0):min(c1 + overlap, w)] = True
        np.testing.assert_array_equal(m, e)
    count = np.sum(wide, axis=0)
    assert (count >= 1).all()
    # the shared margin: a band of 2*overlap rows/cols around each internal boundary
    assert (count >= 2).sum() > 0
    rb = bbox(base[0])[1]  # first row of the bottom quadrants
    assert (count[rb - overlap:rb + overlap, :] >= 2).all()


@pytest.mark.parametrize("shape", [(10, 31), (7, 9), (5, 3)])
def test_strips_for_three_agents(shape):
    h, w = shape
    masks = region_masks(shape, 3, "strips")
    assert len(masks) == 3
    assert (np.sum(masks, axis=0) == 1).all()
    prev_end = 0
    widths = []
    for m in masks:
        assert is_rectangle(m)
        r0, r1, c0, c1 = bbox(m)
        assert (r0, r1) == (0, h)  # full height
        assert c0 == prev_end  # left to right, contiguous
        prev_end = c1
        widths.append(c1 - c0)
    assert prev_end == w
    assert max(widths) - min(widths) <= 1 and sum(widths) == w


def test_strips_by_hand():
    # 12 columns among 3 agents: 4 each
    masks = region_masks((2, 12), 3, "strips")
    for k, m in enumerate(masks):
        e = np.zeros((2, 12), bool)
        e[:, 4 * k:4 * k + 4] = True
        np.testing.assert_array_equal(m, e)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_quadrants_needs_exactly_four(n):
    with pytest.raises(FedmapError, match="exactly 4"):
        region_masks((20, 20), n, "quadrants")
    truth = random_truth((20, 20))
    with pytest.raises(FedmapError, match="exactly 4"):
        explore(truth, n, "quadrants")


def test_unknown_mode_and_bad_counts_raise():
    truth = random_truth((20, 20))
    with pytest.raises(FedmapError, match="unknown exploration mode"):
        region_masks((20, 20), 4, "spiral")
    with pytest.raises(FedmapError, match="unknown exploration mode"):
        explore(truth, 4, "spiral")
    with pytest.raises(FedmapError, match=">= 1"):
        region_masks((20, 20), 0, "strips")
    with pytest.raises(FedmapError, match="cannot split"):
        region_masks((20, 3), 4, "strips")


# ----------------------------------------------------------------------------- local maps


def test_local_maps_keep_truth_inside_region_only():
    rng = np.random.default_rng(3)
    truth = GridMap(rng.integers(0, 3, (40, 60)).astype(np.uint8), 2.5, "truth")
    keep = truth.classes.copy()
    local = explore(truth, 4, "quadrants")
    # hand-derived quadrants of a 40x60 map
    blocks = [np.s_[:20, :30], np.s_[:20, 30:], np.s_[20:, :30], np.s_[20:, 30:]]
    for k, (m, sl) in enumerate(zip(local, blocks)):
        inside = np.zeros((40, 60), bool)
        inside[sl] = True
        np.testing.assert_array_equal(m.classes[inside], truth.classes[inside])
        assert (m.classes[~inside] == UNKNOWN).all()
        assert m.shape == truth.shape and m.pixel_size == 2.5
        assert m.meta["agent"] == k and m.meta["mode"] == "quadrants"
    np.testing.assert_array_equal(truth.classes, keep)  # the truth is not modified


def test_local_maps_with_strips_and_overlap():
    truth = random_truth((30, 45), seed=1)
    local = explore(truth, 3, "strips", overlap=2)
    masks = region_masks((30, 45), 3, "strips", overlap=2)
    for m, mask in zip(local, masks):
        np.testing.assert_array_equal(m.classes[mask], truth.classes[mask])
        assert (m.classes[~mask] == UNKNOWN).all()


def test_agent_observing_only_nodata_raises():
    c = np.full((20, 20), FREE, np.uint8)
    c[:10, :10] = UNKNOWN  # agent 0's quadrant is all nodata
    with pytest.raises(FedmapError, match="observed nothing"):
        explore(GridMap(c), 4, "quadrants")


# ----------------------------------------------------------------------------- traverse


TRAVERSE = dict(mode="traverse", sensor_radius=3.0, waypoints=3)


def test_traverse_is_deterministic_per_seed():
    truth = random_truth(seed=2)
    a = explore(truth, 4, seed=7, **TRAVERSE)
    b = explore(truth, 4, seed=7, **TRAVERSE)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.classes, y.classes)


def test_traverse_differs_across_seeds():
    truth = random_truth(seed=2)
    a = explore(truth, 4, seed=0, **TRAVERSE)
    b = explore(truth, 4, seed=1, **TRAVERSE)
    assert any((x.classes != y.classes).any() for x, y in zip(a, b))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("radius", [2.0, 4.5])
def test_traverse_sees_only_near_its_free_route(seed, radius):
    truth = random_truth(seed=seed)
    local = explore(truth, 4, "traverse", seed=seed, sensor_radius=radius, waypoints=3)
    regions = region_masks(truth.shape, 4, "grid")
    for m, region in zip(local, regions):
        seen = m.classes != UNKNOWN
        # observed cells keep their true class
        np.testing.assert_array_equal(m.classes[seen], truth.classes[seen])
        # it drives on FREE cells, starting inside its own block
        free_seen = np.argwhere(seen & (m.classes == FREE))
        assert len(free_seen) > 0
        assert (seen & region & (m.classes == FREE)).any()
        # every observed cell lies within the sensor radius of an observed FREE cell
        # (the route is made of FREE cells, all observed); brute-force nearest neighbour
        dist, _ = cKDTree(free_seen).query(np.argwhere(seen))
        assert dist.max() <= radius + 1e-9
        # partial coverage: a short drive with a small sensor does not see everything
        assert seen.mean() < 1.0


@pytest.mark.parametrize("radius", [2.0, 3.0, 3.7])
@pytest.mark.parametrize("seed", [0, 5])
def test_traverse_footprint_is_the_sensor_disc_round_a_corridor(radius, seed):
    # Truth: IMPASSABLE except two 1-wide FREE rows (7 and 22) across a 30x30 map. Each
    # agent of the 2x2 tiling can only drive along its row inside its block, so its route
    # is one interval of that row, and it must observe exactly the cells within `radius`
    # of some interval [a, b] inside its block (hand: distance from (i,j) to
    # {(r,c): a<=c<=b} is hypot(i - r, max(a - j, 0, j - b))).
    c = np.full((30, 30), IMPASSABLE, np.uint8)
    c[7, :] = FREE
    c[22, :] = FREE
    truth = GridMap(c)
    local = explore(truth, 4, "traverse", seed=seed, sensor_radius=radius, waypoints=3)
    ii, jj = np.mgrid[0:30, 0:30]
    blocks = [(7, range(0, 15)), (7, range(15, 30)), (22, range(0, 15)), (22, range(15, 30))]
    for m, (row, cols) in zip(local, blocks):
        seen = m.classes != UNKNOWN
        # hand: the rows seen are exactly row +- floor(radius)
        rows_seen = np.flatnonzero(seen.any(axis=1))
        k = int(np.floor(radius))
        assert (rows_seen.min(), rows_seen.max()) == (row - k, row + k)
        matches = [
            (a, b) for a in cols for b in cols if b >= a
            and np.array_equal(seen, np.hypot(ii - row, np.maximum(np.maximum(a - jj, 0), jj - b)) <= radius)
        ]
        assert matches  # (near the map edge several intervals give the same footprint)


def test_traverse_region_without_free_cells_raises():
    c = np.full((30, 30), FREE, np.uint8)
    c[:15, :15] = IMPASSABLE  # agent 0's block (2x2 grid) has nothing to drive on
    with pytest.raises(FedmapError, match="no free cell"):
        explore(GridMap(c), 4, **TRAVERSE)


def test_traverse_rejects_non_positive_sensor_radius():
    truth = random_truth((20, 20))
    for r in (0.0, -1.0):
        with pytest.raises(FedmapError, match="sensor radius"):
            explore(truth, 4, "traverse", sensor_radius=r)


def test_traverse_heterogeneous_sensor_radii():
    from fedmap.maps.grid import GridMap as _G

    truth = _G(np.zeros((48, 48), np.uint8), 1.0, "flat")
    maps = explore(truth, 4, "traverse", seed=1, sensor_radius=[2.0, 4.0, 6.0, 8.0])
    # with the same route generator per agent, a larger radius sees more (monotone here on flat ground)
    seen = [m.n_known for m in maps]
    single = [explore(truth, 4, "traverse", seed=1, sensor_radius=r)[k].n_known for k, r in enumerate([2.0, 4.0, 6.0, 8.0])]
    assert seen == single  # per-agent values act exactly like running each agent with its own value
    with pytest.raises(FedmapError, match="one per agent"):
        explore(truth, 4, "traverse", sensor_radius=[2.0, 4.0])
