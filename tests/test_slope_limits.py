"""A percentile slope limit is resolved once, on the truth, and an elevation layer never
makes a rover's map worse than the classes alone.

The bug these tests pin down: a mission with ``--max-slope p75`` and an elevation layer
re-took the 75th percentile of each rover's own few heights (a different angle per rover
and per step), and a ``team`` rover let classes re-derived from shared, quantised heights
overwrite the exact classes it had been sent (a cell at a limit flips with 1 cm of error).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, resolved_slope
from fedmap.mission import load_mission, mission_terrain, run_mission

GALE = Path(__file__).resolve().parents[2] / "shared" / "data" / "mars" / "missionDEM_gale_1m.tif"


def _slopes_by_hand(z: np.ndarray, px: float) -> np.ndarray:
    """Slope in degrees from numpy's central differences (the textbook formula)."""
    gy, gx = np.gradient(z.astype(np.float64), px)
    return np.degrees(np.arctan(np.sqrt(gx * gx + gy * gy)))


def test_a_percentile_limit_resolves_to_the_truths_percentile_in_degrees():
    rng = np.random.default_rng(4)
    z = np.cumsum(rng.normal(0, 2.0, (40, 40)), axis=0) + np.cumsum(rng.normal(0, 2.0, (40, 40)), axis=1)
    z = z.astype(np.float32)
    dem = Dem(z, 10.0)  # 10 m pixels: slope only, no rover-scale tests
    truth = dem_to_traversability(dem, TraversabilityThresholds(max_slope_percentile=75))
    s = _slopes_by_hand(z, 10.0)  # the border's one-sided differences are numpy's too
    expected = np.percentile(s, 75)
    limits = resolved_slope(TraversabilityThresholds(max_slope_percentile=75), truth)
    assert limits.max_slope_percentile is None
    assert limits.max_slope_deg == pytest.approx(expected, rel=1e-9)
    assert (s > limits.max_slope_deg).mean() == pytest.approx(0.25, abs=1e-3)
    # degrees come back as they were
    degrees = TraversabilityThresholds(max_slope_deg=12.0)
    assert resolved_slope(degrees, truth) is degrees


def test_a_percentile_cannot_be_resolved_on_a_map_not_classified_from_a_dem():
    grid = GridMap(np.zeros((8, 8), np.uint8), 1.0, "drawn.png")
    with pytest.raises(FedmapError, match="percentile.*degrees"):
        resolved_slope(TraversabilityThresholds(max_slope_percentile=75), grid)


def test_part_of_the_terrain_classified_with_the_resolved_limit_agrees_with_the_truth():
    """What a rover holding a quarter of the heights derives: with the resolved degrees its
    inner cells are the truth's classes; with the percentile re-taken on its own heights
    (the old behaviour) they are not."""
    rng = np.random.default_rng(9)
    z = np.cumsum(rng.normal(0, 2.0, (48, 48)), axis=0)
    z[:24, :24] *= 0.2  # a gentle quarter: its own 75th percentile is a much lower angle
    dem = Dem(z.astype(np.float32), 10.0)
    p75 = TraversabilityThresholds(max_slope_percentile=75)
    truth = dem_to_traversability(dem, p75)
    part = np.full(z.shape, np.nan, np.float32)
    part[:24, :24] = z[:24, :24]
    inner = np.zeros(z.shape, bool)
    inner[1:23, 1:23] = True
    right = dem_to_traversability(Dem(part, 10.0), resolved_slope(p75, truth)).classes
    assert np.array_equal(right[inner], truth.classes[inner])
    retaken = dem_to_traversability(Dem(part, 10.0), p75).classes
    assert not np.array_equal(retaken[inner], truth.classes[inner])


def _team(layers: str, slope: str, terrain: dict, size: int, **mission):
    cfg, source, _ = load_mission(
        mission={"rovers": 3, "steps": 40, "sync_every": 8, "eval_pairs": 16, "strategies": "raw",
                 "layers": layers, "elevation_noise_m": 0.0, **mission},
        terrain=terrain, size=size,
        overrides=[{"thresholds": {"max_slope_percentile": 75.0} if slope == "p75" else {"max_slope_deg": 15.0}}])
    truth, elevation, prior, profiles = mission_terrain(cfg, source)
    res = run_mission(cfg, truth, elevation=elevation, prior=prior, profiles=profiles,
                      thresholds=source.thresholds, frames=1)
    return truth, res


TERRAINS = [pytest.param({"kind": "builtin", "terrain": "mars"}, 64, id="builtin-mars"),
            pytest.param({"kind": "dem", "path": str(GALE), "crop": 256}, 64, id="gale",
                         marks=pytest.mark.skipif(not GALE.exists(), reason="shared/data is not beside the repo"))]


@pytest.mark.parametrize("slope", ["degrees", "p75"])
@pytest.mark.parametrize("terrain,size", TERRAINS)
def test_exact_heights_never_lower_raw_belief_f1_or_path_success(terrain, size, slope):
    truth, classes_only = _team("classes", slope, terrain, size)
    _, with_heights = _team("classes,elevation", slope, terrain, size)
    a, b = classes_only.runs["raw"], with_heights.runs["raw"]
    assert b.summary.final_belief_f1_mean >= a.summary.final_belief_f1_mean
    assert b.summary.final_path_success_mean >= a.summary.final_path_success_mean
    # and no rover's view (what it plans on and is scored on) contradicts the truth on a cell it holds
    for view in b.views:
        known = view != UNKNOWN
        assert known.any() and np.array_equal(view[known], truth.classes[known])


def test_the_orbital_prior_uses_the_truths_limit_in_degrees():
    terrain = {"kind": "builtin", "terrain": "mars"}
    cfg, source, _ = load_mission(mission={"rovers": 2, "steps": 4, "strategies": "raw"}, terrain=terrain, size=64,
                                  overrides=[{"thresholds": {"max_slope_percentile": 75.0},
                                              "prior": {"kind": "orbital", "factor": 4}}])
    truth, _, prior, _ = mission_terrain(cfg, source)
    degrees = truth.meta["slope_limit_deg"]
    cfg2, source2, _ = load_mission(mission={"rovers": 2, "steps": 4, "strategies": "raw"}, terrain=terrain,
                                    size=64, overrides=[{"thresholds": {"max_slope_deg": degrees},
                                                         "prior": {"kind": "orbital", "factor": 4}}])
    truth2, _, prior2, _ = mission_terrain(cfg2, source2)
    assert np.array_equal(truth.classes, truth2.classes)
    assert prior is not None and np.array_equal(prior, prior2)
