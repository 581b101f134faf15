"""Tests for fedmap.maps.traversability: slope, step height, roughness, classification.

All reference values are hand-derived from the documented definitions:
* slope: atan(|grad z|) in degrees, gradient in metres per metre, so a plane
  z = (a*col + b*row) * pixel_size has slope atan(hypot(a, b)) everywhere (central and
  one-sided differences are exact on a linear function);
* step height: largest |z - z_neighbour| over the 8 neighbours;
* roughness: standard deviation of z in the 3x3 window (residual from the 3x3 mean);
* a cell is IMPASSABLE if any test fails, the step/roughness tests only run when
  pixel_size <= rover_scale_max_px, and cells with nodata in their 3x3 are UNKNOWN.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.traversability import (
    TraversabilityThresholds,
    dem_to_traversability,
    roughness,
    slope_degrees,
    step_height,
)


def plane(shape, pixel_size, deg_x=0.0, deg_y=0.0):
    """z = (col*tan(deg_x) + row*tan(deg_y)) * pixel_size, in metres."""
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    return (cols * math.tan(math.radians(deg_x)) + rows * math.tan(math.radians(deg_y))) * pixel_size


# ----------------------------------------------------------------------------- slope


@pytest.mark.parametrize("deg", [10.0, 20.0])
@pytest.mark.parametrize("pixel_size", [0.5, 30.0])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_slope_of_inclined_plane_is_exact(deg, pixel_size, axis):
    z = plane((12, 14), pixel_size, **({"deg_x": deg} if axis == "x" else {"deg_y": deg}))
    s = slope_degrees(z, pixel_size)
    np.testing.assert_allclose(s[1:-1, 1:-1], deg, rtol=0, atol=1e-9)
    np.testing.assert_allclose(s, deg, rtol=0, atol=1e-9)  # one-sided edges are exact too


def test_slope_of_oblique_plane():
    # hand: gradient (tan 10, tan 20) -> slope atan(hypot(tan 10deg, tan 20deg))
    z = plane((10, 10), 2.0, deg_x=10.0, deg_y=20.0)
    hand = math.degrees(math.atan(math.hypot(math.tan(math.radians(10)), math.tan(math.radians(20)))))
    np.testing.assert_allclose(slope_degrees(z, 2.0)[1:-1, 1:-1], hand, rtol=0, atol=1e-9)


@pytest.mark.parametrize("pixel_size", [0.5, 30.0])
def test_plane_classification_around_15_degrees(pixel_size):
    # 10 deg < 15 -> FREE; 20 deg > 15 -> IMPASSABLE. At 0.5 m the rover-scale tests
    # also run: on the 10 deg plane the step is tan(10)*0.5 = 0.088 m < 0.3 and the 3x3
    # std is 0.088*sqrt(2/3) = 0.072 m < 0.15, so they do not fire (hand).
    for deg, cls in ((10.0, FREE), (20.0, IMPASSABLE)):
        for axis in ("deg_x", "deg_y"):
            g = dem_to_traversability(Dem(plane((12, 14), pixel_size, **{axis: deg}), pixel_size))
            assert (g.classes == cls).all(), (deg, axis)
            assert g.pixel_size == pixel_size


def test_threshold_is_strict_greater_than():
    # Flat DEM: slope 0, not > any positive threshold.
    g = dem_to_traversability(Dem(np.zeros((6, 6)), 1.0))
    assert (g.classes == FREE).all()


# ----------------------------------------------------------------------------- smooth slopes
# A perfectly smooth plane below max_slope_deg has no step and no roughness in any
# physical sense, so it must be FREE at rover scale too.


def test_smooth_12deg_plane_at_1m_is_free():
    # 12 deg < 15 deg. Step to a neighbour: tan(12)*1 = 0.213 m < 0.3. But the 3x3 std
    # of a plane is a*sqrt(2/3) with a = 0.213 m -> 0.174 m > 0.15: the roughness test,
    # which does not remove the local slope, flags a smooth hillside.
    z = plane((15, 20), 1.0, deg_x=12.0)
    g = dem_to_traversability(Dem(z, 1.0))
    flagged = float((g.classes == IMPASSABLE).mean())
    assert flagged == 0.0, f"{flagged:.0%} of a smooth 12 deg plane at 1 m flagged IMPASSABLE"


def test_smooth_10deg_plane_at_2m_passes_the_step_test():
    # 10 deg < 15 deg; with the roughness test out of the way (threshold 10 m), a smooth
    # plane has no step, but the neighbour difference tan(10)*2 = 0.353 m > 0.3 is
    # counted as one at 2 m pixels (still "rover scale"): any slope above
    # atan(0.3/2) = 8.5 deg is flagged as a step.
    z = plane((15, 20), 2.0, deg_x=10.0)
    t = TraversabilityThresholds(max_roughness_m=10.0)
    g = dem_to_traversability(Dem(z, 2.0), t)
    flagged = float((g.classes == IMPASSABLE).mean())
    assert flagged == 0.0, f"{flagged:.0%} of a smooth 10 deg plane at 2 m flagged IMPASSABLE"


# ----------------------------------------------------------------------------- step


def step_dem(pixel_size, height=0.5):
    z = np.zeros((12, 20))
    z[:, 10:] = height  # a step (0.5 m by default) between columns 9 and 10
    return Dem(z, pixel_size)


def test_step_height_by_hand():
    sh = step_height(step_dem(1.0).elevation)
    # hand: columns 9 and 10 touch the other level -> 0.5; all others 0
    expected = np.zeros((12, 20))
    expected[:, 9:11] = 0.5
    np.testing.assert_allclose(sh, expected, atol=1e-7)


def test_step_is_impassable_at_rover_scale():
    g = dem_to_traversability(step_dem(1.0))
    expected = np.full((12, 20), FREE, np.uint8)
    expected[:, 9:11] = IMPASSABLE
    np.testing.assert_array_equal(g.classes, expected)
    # the step test alone (roughness disabled) flags exactly the same cells ...
    g = dem_to_traversability(step_dem(1.0), TraversabilityThresholds(max_roughness_m=10.0))
    np.testing.assert_array_equal(g.classes, expected)
    # ... while slope alone does not: hand, central difference 0.5 / (2*1 m) = 0.25,
    # atan(0.25) = 14.04 deg < 15 deg
    s = slope_degrees(step_dem(1.0).elevation, 1.0)
    np.testing.assert_allclose(s[:, 9:11], math.degrees(math.atan(0.25)), atol=1e-6)
    t = TraversabilityThresholds(max_step_m=10.0, max_roughness_m=10.0)
    assert (dem_to_traversability(step_dem(1.0), t).classes == FREE).all()
    # with a 14 deg limit the slope test catches it: 14.04 > 14
    t = TraversabilityThresholds(max_slope_deg=14.0, max_step_m=10.0, max_roughness_m=10.0)
    np.testing.assert_array_equal(dem_to_traversability(step_dem(1.0), t).classes, expected)


def test_step_roughness_is_plane_removed():
    # hand: the 3x3 window at column 9 holds rows of (0, 0, 0.5): population variance
    # 0.5^2 * (1/3)(2/3) = 0.05556; the window's plane has slope b = sum(x z)/6 = 3*0.5/6 =
    # 0.25 per pixel and explains 6 b^2 / 9 = 0.04167, leaving 0.01389 -> std 0.5/(3 sqrt 2)
    # = 0.11785 m (same at column 10 by symmetry). That is < 0.15, so roughness alone
    # does not flag the step; the step test does.
    r = roughness(step_dem(1.0).elevation)
    np.testing.assert_allclose(r[:, 9:11], 0.5 / (3 * math.sqrt(2)), atol=1e-9)
    np.testing.assert_allclose(r[:, :8], 0.0, atol=1e-7)
    g = dem_to_traversability(step_dem(1.0), TraversabilityThresholds(max_step_m=10.0))
    assert (g.classes == FREE).all()


def test_smooth_plane_has_zero_roughness():
    # a plane is its own least-squares fit: residual 0 whatever its slope
    rows, cols = np.mgrid[0:9, 0:10]
    np.testing.assert_allclose(roughness(0.7 * cols - 0.3 * rows + 2.0)[1:-1, 1:-1], 0.0, atol=1e-6)  # float cancellation


def test_step_not_tested_on_a_30m_dem():
    # At 30 m pixels the step/roughness tests are off (30 > rover_scale_max_px = 2); the
    # slope there is atan(0.5 / (2*30 m)) = 0.477 deg (hand), far below 15 deg.
    dem = step_dem(30.0)
    s = slope_degrees(dem.elevation, 30.0)
    np.testing.assert_allclose(s[:, 9:11], math.degrees(math.atan(0.5 / 60.0)), atol=1e-6)
    g = dem_to_traversability(dem)
    assert (g.classes == FREE).all()
    # the raw step height is unchanged by the pixel size: only the rule switches it off
    assert step_height(dem.elevation).max() == pytest.approx(0.5)
    # just above/below the rover-scale limit, with a 0.8 m step: at 2 m pixels the rise
    # 0.8 m > 0.3 m and 0.8 / 2 = 0.4 > tan(15 deg) = 0.268 -> a step; at 2.01 m the step
    # test is off and the central-difference slope atan(0.8 / 4.02) = 11.3 deg < 15 -> FREE
    assert (dem_to_traversability(step_dem(2.0, 0.8)).classes[:, 9:11] == IMPASSABLE).all()
    assert (dem_to_traversability(step_dem(2.01, 0.8)).classes == FREE).all()
    # a 0.5 m step at 2 m pixels is no steeper than 14 deg over one pixel: not a step
    assert (dem_to_traversability(step_dem(2.0)).classes == FREE).all()


# ----------------------------------------------------------------------------- roughness


def test_roughness_of_checkerboard():
    h = 0.4
    rows, cols = np.mgrid[0:9, 0:10]
    z = h * ((rows + cols) % 2).astype(np.float64)
    r = roughness(z)
    # hand: every interior 3x3 window holds 5 cells of one level and 4 of the other:
    # variance h^2 * (5/9)(4/9), std = h*sqrt(20)/9 = 0.19876 m for h = 0.4
    np.testing.assert_allclose(r[1:-1, 1:-1], h * math.sqrt(20) / 9, atol=1e-9)
    # a constant surface has zero roughness
    np.testing.assert_allclose(roughness(np.full((5, 5), 7.0)), 0.0, atol=1e-12)
    # the checkerboard is rough at rover scale: 0.199 > 0.15, step 0.4 > 0.3
    g = dem_to_traversability(Dem(z, 1.0), TraversabilityThresholds(max_step_m=10.0))
    assert (g.classes[1:-1, 1:-1] == IMPASSABLE).all()
    g = dem_to_traversability(Dem(z, 1.0), TraversabilityThresholds(max_step_m=10.0, max_roughness_m=0.2))
    # 0.19876 < 0.2 and the slope of the checkerboard interior is 0 (central differences
    # of an alternating pattern cancel), so the interior is FREE
    assert (g.classes[1:-1, 1:-1] == FREE).all()


# ----------------------------------------------------------------------------- nodata


def test_nodata_and_its_neighbours_are_unknown():
    z = plane((10, 12), 1.0, deg_x=5.0)
    z[4, 5] = np.nan
    z[0, 0] = np.nan
    z[9, 11] = np.inf  # treated as nodata too
    g = dem_to_traversability(Dem(z, 1.0))
    expected = np.full((10, 12), FREE, np.uint8)
    expected[3:6, 4:7] = UNKNOWN  # 3x3 around (4,5)
    expected[0:2, 0:2] = UNKNOWN  # 3x3 around (0,0) clipped
    expected[8:10, 10:12] = UNKNOWN
    # 5 deg plane at 1 m: slope 5 < 15, step 0.087 < 0.3, std 0.071 < 0.15 -> FREE
    np.testing.assert_array_equal(g.classes, expected)


def test_nodata_hole_in_a_slope_does_not_spread():
    # The nodata fill must not create obstacles beyond the hole's 8-neighbourhood.
    z = plane((12, 12), 1.0, deg_y=8.0)
    z[5:7, 5:7] = np.nan
    g = dem_to_traversability(Dem(z, 1.0))
    expected = np.full((12, 12), FREE, np.uint8)
    expected[4:8, 4:8] = UNKNOWN
    np.testing.assert_array_equal(g.classes, expected)


def test_all_nan_dem_raises():
    with pytest.raises(FedmapError, match="no valid elevation"):
        dem_to_traversability(Dem(np.full((5, 5), np.nan), 1.0))


def test_dem_without_any_defined_slope_raises():
    # Every cell of a 3x3 DEM has the central nodata cell in its neighbourhood.
    z = np.zeros((3, 3))
    z[1, 1] = np.nan
    with pytest.raises(FedmapError, match="no cell with a defined slope"):
        dem_to_traversability(Dem(z, 1.0, "tiny"))


# ----------------------------------------------------------------------------- thresholds


def test_thresholds_defaults_and_meta():
    t = TraversabilityThresholds()
    assert t.to_dict() == {"max_slope_deg": 15.0, "max_step_m": 0.3, "max_roughness_m": 0.15,
                           "rover_scale_max_px": 2.0}
    g = dem_to_traversability(Dem(np.zeros((4, 4)), 1.0, "flat"))
    assert g.meta["thresholds"] == t.to_dict()
    assert g.meta["dem_source"] == "flat"


@pytest.mark.parametrize(
    "kwargs",
    [
        {"max_slope_deg": 0.0},
        {"max_slope_deg": 90.0},
        {"max_slope_deg": -5.0},
        {"max_slope_deg": float("nan")},
        {"max_step_m": 0.0},
        {"max_step_m": -0.1},
        {"max_step_m": float("nan")},
        {"max_roughness_m": 0.0},
        {"rover_scale_max_px": 0.0},
        {"rover_scale_max_px": -1.0},
    ],
)
def test_thresholds_validation(kwargs):
    with pytest.raises(FedmapError):
        TraversabilityThresholds(**kwargs)


# ----------------------------------------------------------------------------- windows, profiles, percentiles


def brute_roughness(z: np.ndarray, size: int) -> np.ndarray:
    """Std of the residual of a least-squares plane (np.linalg.lstsq) over each window, edges replicated."""
    r = size // 2
    zp = np.pad(z, r, mode="edge")
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    a = np.column_stack([np.ones(size * size), xx.ravel(), yy.ravel()])
    out = np.empty(z.shape)
    for i in range(z.shape[0]):
        for j in range(z.shape[1]):
            win = zp[i:i + size, j:j + size].ravel()
            coef = np.linalg.lstsq(a, win, rcond=None)[0]
            out[i, j] = np.sqrt(np.mean((win - a @ coef) ** 2))
    return out


@pytest.mark.parametrize("size", [3, 5, 7])
def test_roughness_window_matches_lstsq_plane_fit(size):
    z = np.random.default_rng(size).normal(size=(9, 11)) + plane((9, 11), 1.0, deg_x=20.0)
    np.testing.assert_allclose(roughness(z, size), brute_roughness(z, size), atol=1e-9)


def test_footprint_tilt_of_a_plane_is_exact():
    from fedmap.maps.traversability import footprint_tilt

    hand = math.degrees(math.atan(math.hypot(math.tan(math.radians(10)), math.tan(math.radians(20)))))
    z = plane((15, 15), 0.5, deg_x=10.0, deg_y=20.0)
    np.testing.assert_allclose(footprint_tilt(z, 0.5, 5)[2:-2, 2:-2], hand, atol=1e-9)


def test_window_steps_match_brute_force():
    from fedmap.maps.traversability import window_steps

    rng = np.random.default_rng(5)
    z = rng.uniform(0, 0.5, size=(8, 9))
    px, step, deg, size = 0.1, 0.2, 30.0, 5
    got = window_steps(z, px, size, step, deg)
    zp = np.pad(z, 2, mode="edge")
    want = np.zeros_like(got)
    for i in range(8):
        for j in range(9):
            for dr in range(-2, 3):
                for dc in range(-2, 3):
                    rise = abs(zp[i + 2 + dr, j + 2 + dc] - z[i, j])
                    if (dr or dc) and rise > step and rise > math.tan(math.radians(deg)) * px * math.hypot(dr, dc):
                        want[i, j] = True
    np.testing.assert_array_equal(got, want)


def test_window_cells():
    from fedmap.maps.traversability import window_cells

    assert window_cells(None, 1.0) == 3
    assert window_cells(0.5, 1.0) == 3  # never below 3x3
    assert window_cells(0.5, 0.1) == 5 and window_cells(0.6, 0.1) == 7  # odd, about the metres asked
    assert window_cells(100.0, 0.1) == 255 and window_cells(100.0, 0.1, cap=31) == 31  # capped


def rock_dem(height: float, pixel_size: float = 0.05, n: int = 40) -> Dem:
    """Flat ground with one square rock of ``height`` metres, 4x4 cells, in the middle."""
    z = np.zeros((n, n))
    z[n // 2 - 2:n // 2 + 2, n // 2 - 2:n // 2 + 2] = height
    return Dem(z, pixel_size, f"rock {height} m")


def test_rover_profiles_a_rock_stops_the_small_rover_not_curiosity():
    from fedmap.maps.traversability import ROVER_PROFILES, rover_profile

    assert set(ROVER_PROFILES) == {"cadre", "mer", "msl"}
    for name, t in ROVER_PROFILES.items():
        assert t.rover == name and t.step_window_m and t.footprint_m
        assert t.max_roughness_m == pytest.approx(t.max_step_m / 3)
    # published figures: MER 26 cm wheels and 30 deg; MSL 50 cm wheels, 65 cm obstacles, 30 deg
    assert (ROVER_PROFILES["mer"].step_window_m, ROVER_PROFILES["mer"].max_slope_deg) == (0.26, 30.0)
    assert (ROVER_PROFILES["msl"].step_window_m, ROVER_PROFILES["msl"].max_step_m) == (0.50, 0.65)
    rock = rock_dem(0.3)
    impassable = {name: int((dem_to_traversability(rock, rover_profile(name)).classes == IMPASSABLE).sum())
                  for name in ROVER_PROFILES}
    assert impassable["cadre"] > 0 and impassable["mer"] > 0  # 0.3 m is above their 0.05 / 0.20 m steps
    assert impassable["msl"] == 0  # Curiosity rolls over 0.3 m (65 cm limit); its footprint smooths the rock
    with pytest.raises(FedmapError, match="unknown rover 'vikram'; choose one of cadre, mer, msl"):
        rover_profile("vikram")


def test_slope_percentile_and_parse():
    from fedmap.maps.terrain import generate_dem
    from fedmap.maps.traversability import parse_slope_limit

    assert parse_slope_limit("p75") == {"max_slope_percentile": 75.0}
    assert parse_slope_limit(" 25 ") == {"max_slope_deg": 25.0}
    with pytest.raises(FedmapError, match="p75"):
        parse_slope_limit("steep")
    dem = generate_dem("moon", 64, seed=1, pixel_size=100.0)  # coarse: only the slope test runs
    t = TraversabilityThresholds(max_slope_percentile=75)
    g = dem_to_traversability(dem, t)
    want = float(np.percentile(slope_degrees(dem.elevation, 100.0), 75))
    assert g.meta["slope_limit_deg"] == pytest.approx(want)
    assert (g.classes == IMPASSABLE).mean() == pytest.approx(0.25, abs=1 / 64**2)
    with pytest.raises(FedmapError, match="max_slope_percentile"):
        TraversabilityThresholds(max_slope_percentile=0)


def test_one_class_maps_warn_in_one_line():
    flat = dem_to_traversability(Dem(np.zeros((10, 10)), 118.45, "flat"))
    w = flat.meta["warning"]
    assert "100.0% free at 118 m pixels" in w and "slope 15 deg" in w and "\n" not in w
    steep = dem_to_traversability(Dem(plane((10, 10), 1.0, deg_x=40.0), 1.0, "wall"))
    assert "100.0% impassable at 1 m pixels" in steep.meta["warning"]
    z = plane((10, 10), 1.0, deg_x=10.0)
    z[:, 5:] = plane((10, 5), 1.0, deg_x=40.0) + z[0, 5]
    assert "warning" not in dem_to_traversability(Dem(z, 1.0, "half")).meta


@pytest.mark.parametrize("steep_cols, warns", [(2, False), (8, False), (9, True)])
def test_a_mostly_impassable_map_warns_above_80_percent(steep_cols, warns):
    """Vancouver at 15 deg was 83% impassable with no word: above 80% impassable the map warns
    (a map 80% free is what planetary terrain often is, and does not)."""
    z = plane((10, 10), 1.0, deg_x=5.0)
    if steep_cols:
        z[:, 10 - steep_cols:] = plane((10, steep_cols), 1.0, deg_x=40.0) + z[0, 10 - steep_cols]
    g = dem_to_traversability(Dem(z, 1.0, "part steep"))
    share = float((g.classes == IMPASSABLE).mean())
    assert ("warning" in g.meta) == warns == (share > 0.8), share
    if warns:
        assert "impassable" in g.meta["warning"] and "--max-slope" in g.meta["warning"]


def test_classes_keep_the_dem_georeferencing():
    from affine import Affine

    t = Affine(2.0, 0, 100.0, 0, -2.0, 500.0)
    g = dem_to_traversability(Dem(np.zeros((6, 6)), 2.0, "geo", transform=t, crs="EPSG:32612"))
    assert g.transform == t and g.crs == "EPSG:32612"


def test_rover_in_the_config_and_explicit_limits_win(tmp_path):
    from fedmap.config import resolve
    from fedmap.maps.traversability import ROVER_PROFILES

    cfg = tmp_path / "run.toml"
    cfg.write_text('[thresholds]\nrover = "mer"\nmax_step_m = 0.1\n')
    th = resolve(cfg)["thresholds"]
    assert th == {**ROVER_PROFILES["mer"].to_dict(), "max_step_m": 0.1}
    th = resolve(cfg, [{"thresholds": {"rover": "msl", "max_slope_percentile": 75}}])["thresholds"]
    assert th["rover"] == "msl" and th["max_step_m"] == 0.1 and th["footprint_m"] == 3.0
    assert th["max_slope_percentile"] == 75
    TraversabilityThresholds(**th)  # what the pipeline builds from it
    cfg.write_text('[thresholds]\nrover = "rover-x"\n')
    with pytest.raises(FedmapError, match="unknown rover 'rover-x'"):
        resolve(cfg)


def test_a_dem_classified_again_gives_its_own_map_and_the_same_classes():
    """The last classification is kept (the built-in terrain classifies its DEM twice):
    the second map equals the first, its arrays and meta are its own, and another DEM,
    pixel size or threshold is classified anew (checked against a cleared memory)."""
    from fedmap.maps import traversability

    rng = np.random.default_rng(3)
    z = np.cumsum(rng.normal(0, 0.3, (40, 44)), axis=0)
    first = dem_to_traversability(Dem(z, 1.0, source="a"))
    first.classes[:] = UNKNOWN  # a caller changing its map changes no later one
    first.meta["note"] = "changed"
    second = dem_to_traversability(Dem(z.copy(), 1.0, source="b"))
    traversability._LAST.clear()
    fresh = dem_to_traversability(Dem(z, 1.0, source="b"))
    assert np.array_equal(second.classes, fresh.classes) and second.meta == fresh.meta
    assert 0 < (second.classes == IMPASSABLE).mean() < 1
    strict = TraversabilityThresholds(max_slope_deg=5.0)
    for other, t in ((Dem(z * 3, 1.0), None), (Dem(z, 0.5), None), (Dem(z, 1.0), strict)):
        got = dem_to_traversability(other, t)
        traversability._LAST.clear()
        assert np.array_equal(got.classes, dem_to_traversability(other, t).classes)
        assert not np.array_equal(got.classes, second.classes)
