"""Tests for the built-in terrain generators (fedmap.maps.terrain)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE
from fedmap.maps.terrain import TERRAIN_KINDS, generate_dem
from fedmap.maps.traversability import dem_to_traversability


def _impassable(dem: Dem) -> np.ndarray:
    return dem_to_traversability(dem).classes == IMPASSABLE


def test_kinds_are_the_documented_ones():
    assert TERRAIN_KINDS == ("mars", "moon", "ice")


# --------------------------------------------------------------------------- basics


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
def test_same_seed_gives_identical_bytes(kind):
    a = generate_dem(kind, 96, seed=7)
    b = generate_dem(kind, 96, seed=7)
    assert a.elevation.tobytes() == b.elevation.tobytes()
    assert a.source == b.source
    assert a.meta == b.meta


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
def test_different_seeds_differ(kind):
    a = generate_dem(kind, 96, seed=0)
    b = generate_dem(kind, 96, seed=1)
    assert not np.array_equal(a.elevation, b.elevation)


def test_generation_leaves_global_rng_alone():
    np.random.seed(123)
    expected = np.random.random(3)
    np.random.seed(123)
    generate_dem("mars", 64, seed=3)
    assert np.array_equal(np.random.random(3), expected)


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
@pytest.mark.parametrize("size", [64, 300])
def test_shape_dtype_and_no_nodata(kind, size):
    dem = generate_dem(kind, size, seed=2)
    assert isinstance(dem, Dem)
    assert dem.elevation.shape == (size, size)
    assert dem.elevation.dtype == np.float32
    assert np.isfinite(dem.elevation).all()
    assert dem.pixel_size == 1.0
    assert dem.source == f"builtin:{kind}(size={size},seed=2)"
    assert dem.meta["kind"] == kind
    assert dem.meta["seed"] == 2
    assert dem.meta["size"] == size
    # Relief must exist: a flat map would trivially be all FREE.
    assert float(np.ptp(dem.elevation)) > 1.0


def test_pixel_size_override_is_used():
    dem = generate_dem("moon", 128, seed=0, pixel_size=0.5)
    assert dem.pixel_size == 0.5
    assert dem.meta["pixel_size"] == 0.5
    assert np.isfinite(dem.elevation).all()


@pytest.mark.parametrize("kind", ["mars", "moon"])
def test_crater_sizes_are_physical(kind):
    """The same 256 m of ground at 1 m and at 2 m cells holds about as many craters of
    >= 3 m radius, of the same size in metres: sizes scale with metres, not cells."""
    count_fine = count_coarse = 0
    radii_fine: list[float] = []
    radii_coarse: list[float] = []
    for seed in (0, 1, 2):
        fine = generate_dem(kind, 256, seed=seed)
        coarse = generate_dem(kind, 128, seed=seed, pixel_size=2.0)
        rf = np.array([r for _, _, r in fine.meta["craters"]]) * fine.pixel_size
        rc = np.array([r for _, _, r in coarse.meta["craters"]]) * coarse.pixel_size
        count_fine += int((rf >= 3).sum())
        count_coarse += int((rc >= 3).sum())
        radii_fine += list(rf[rf >= 3])
        radii_coarse += list(rc[rc >= 3])
    assert count_fine > 50 and count_coarse > 50
    assert 0.6 < count_fine / count_coarse < 1.6
    assert 0.8 < np.median(radii_fine) / np.median(radii_coarse) < 1.25


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize("kind", ["venus", "", "MARS", None])
def test_bad_kind_raises(kind):
    with pytest.raises(FedmapError, match="mars, moon, ice"):
        generate_dem(kind, 128)  # type: ignore[arg-type]


@pytest.mark.parametrize("size", [0, 63, 4097, -5, 128.0, "128", True])
def test_bad_size_raises(size):
    with pytest.raises(FedmapError, match=r"\[64, 4096\]"):
        generate_dem("mars", size)  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", [-1, 1.5, "0"])
def test_bad_seed_raises(seed):
    with pytest.raises(FedmapError, match="seed"):
        generate_dem("ice", 64, seed=seed)  # type: ignore[arg-type]


@pytest.mark.parametrize("pixel_size", [0.0, -1.0, float("nan"), float("inf"), "x"])
def test_bad_pixel_size_raises(pixel_size):
    with pytest.raises(FedmapError, match="pixel size"):
        generate_dem("moon", 64, pixel_size=pixel_size)  # type: ignore[arg-type]


def test_error_messages_are_one_line():
    for call in (lambda: generate_dem("venus", 64), lambda: generate_dem("mars", 10)):
        with pytest.raises(FedmapError) as info:
            call()
        assert "\n" not in str(info.value)


# --------------------------------------------------------------------------- traversability


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
@pytest.mark.parametrize("size", [128, 256])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_impassable_fraction_in_target_band(kind, size, seed):
    grid = dem_to_traversability(generate_dem(kind, size, seed=seed))
    frac = grid.fractions()["impassable"]
    assert 0.08 <= frac <= 0.30, f"{kind} {size} seed {seed}: impassable fraction {frac:.3f}"


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
@pytest.mark.parametrize("size", [128, 256])
def test_free_space_is_mostly_one_component(kind, size):
    classes = dem_to_traversability(generate_dem(kind, size, seed=0)).classes
    labels, count = ndimage.label(classes == FREE)
    assert count >= 1
    sizes = np.bincount(labels.ravel())[1:]
    assert sizes.max() / sizes.sum() > 0.7


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
def test_obstacles_are_structured_not_salt_and_pepper(kind):
    """Impassable cells form connected features: few of them are isolated single cells,
    and far fewer components exist than for the same amount of independent noise."""
    bad = _impassable(generate_dem(kind, 256, seed=0))
    _, n_components = ndimage.label(bad, structure=np.ones((3, 3)))
    rng = np.random.default_rng(0)
    noise = rng.random(bad.shape) < bad.mean()
    _, n_noise = ndimage.label(noise, structure=np.ones((3, 3)))
    assert n_components < 0.2 * n_noise
    neighbours = ndimage.convolve(bad.astype(int), np.ones((3, 3), int), mode="constant") - bad
    isolated = bad & (neighbours == 0)
    assert isolated.sum() < 0.02 * bad.sum()


# --------------------------------------------------------------------------- structure


def _ring_and_centre(shape, row, col, radius):
    yy, xx = np.indices(shape)
    d = np.hypot(yy - row, xx - col)
    return (d > 0.6 * radius) & (d < 1.0 * radius), d < max(0.25 * radius, 1.0), (d > 0.85 * radius) & (d < 1.1 * radius)


def _inner_craters(dem: Dem, key: str, min_radius: float):
    n = dem.shape[0]
    return [(r, c, rad) for r, c, rad in dem.meta[key] if rad >= min_radius and min(r, c, n - 1 - r, n - 1 - c) > 1.2 * rad]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mars_craters_have_raised_rims_and_impassable_walls(seed):
    dem = generate_dem("mars", 256, seed=seed)
    bad = _impassable(dem)
    craters = _inner_craters(dem, "craters", 4.0)
    assert len(craters) >= 3
    rim_higher = 0
    wall, centre = [], []
    for r, c, rad in craters:
        ring, middle, rim = _ring_and_centre(dem.shape, r, c, rad)
        rim_higher += dem.elevation[rim].mean() > dem.elevation[middle].mean()
        wall.append(bad[ring].mean())
        centre.append(bad[middle].mean())
    # Craters are bowls with raised rims: the rim stands above the floor centre.
    assert rim_higher >= 0.9 * len(craters)
    # ... and show as red rings around passable floors.
    assert np.mean(wall) > np.mean(centre) + 0.3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_moon_fresh_craters_are_rings(seed):
    dem = generate_dem("moon", 256, seed=seed)
    assert len(dem.meta["craters"]) > len(dem.meta["fresh_craters"]) > 0
    bad = _impassable(dem)
    fresh = _inner_craters(dem, "fresh_craters", 4.0)
    assert len(fresh) >= 3
    wall, centre, rim_higher = [], [], 0
    for r, c, rad in fresh:
        ring, middle, rim = _ring_and_centre(dem.shape, r, c, rad)
        rim_higher += dem.elevation[rim].mean() > dem.elevation[middle].mean()
        wall.append(bad[ring].mean())
        centre.append(bad[middle].mean())
    assert rim_higher >= 0.8 * len(fresh)
    assert np.mean(wall) > np.mean(centre) + 0.2


def test_moon_is_crater_saturated():
    """Many craters per area, over a wide range of sizes (a power law, not one size)."""
    dem = generate_dem("moon", 256, seed=0)
    radii_m = np.array([r for _, _, r in dem.meta["craters"]]) * dem.pixel_size
    assert radii_m.size / (256 * 256) > 2e-3
    assert radii_m.max() / radii_m.min() > 5
    # Cumulative counts fall with size: many more small craters than large ones.
    assert (radii_m > 2 * radii_m.min()).sum() < 0.5 * radii_m.size


def _orientation(mask: np.ndarray) -> tuple[float, float]:
    """Coherence in [0, 1] and dominant gradient direction (degrees mod 180, from +column
    towards +row) of a binary mask, from its structure tensor."""
    m = ndimage.gaussian_filter(mask.astype(float), 1.0)
    gy, gx = np.gradient(m)
    jxx, jyy, jxy = float((gx * gx).sum()), float((gy * gy).sum()), float((gx * gy).sum())
    coherence = math.hypot(jxx - jyy, 2 * jxy) / max(jxx + jyy, 1e-12)
    return coherence, 0.5 * math.degrees(math.atan2(2 * jxy, jxx - jyy)) % 180.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_ice_crevasses_are_oriented_across_the_flow(seed):
    dem = generate_dem("ice", 256, seed=seed)
    coherence, direction = _orientation(_impassable(dem))
    # Plain noise and crater fields give coherence near 0; parallel crevasses near 1.
    assert coherence > 0.3
    # Crevasses run across the flow, so the obstacles' gradients point along it.
    flow = dem.meta["flow_direction_deg"] % 180.0
    assert abs((direction - flow + 90.0) % 180.0 - 90.0) < 20.0


def test_orientation_check_rejects_isotropic_terrain():
    """The anisotropy measure used above does separate crevasses from isotropic fields."""
    coherence, _ = _orientation(_impassable(generate_dem("moon", 256, seed=0)))
    assert coherence < 0.2
    rng = np.random.default_rng(0)
    coherence, _ = _orientation(ndimage.gaussian_filter(rng.random((256, 256)), 2) > 0.52)
    assert coherence < 0.2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mars_dune_slip_faces_face_downwind(seed):
    """Dunes have gentle stoss and steep lee faces downwind: along the wind the ground
    falls steeply far more often than it rises steeply, while across the wind steep
    rises and falls balance (a control that fails for a mis-oriented pattern)."""
    dem = generate_dem("mars", 512, seed=seed)
    wind = math.radians(dem.meta["wind_direction_deg"])
    gy, gx = np.gradient(dem.elevation.astype(float), dem.pixel_size)
    along = gx * math.cos(wind) + gy * math.sin(wind)
    across = -gx * math.sin(wind) + gy * math.cos(wind)
    assert (along < -0.3).sum() > 1.5 * (along > 0.3).sum()
    ratio_across = (across < -0.3).sum() / max((across > 0.3).sum(), 1)
    assert 0.67 < ratio_across < 1.5


# --------------------------------------------------------------------------- scale


@pytest.mark.slow
@pytest.mark.parametrize("kind", TERRAIN_KINDS)
def test_small_and_large_maps_stay_in_band(kind):
    for size, seed in ((64, 0), (64, 5), (1024, 0)):
        frac = dem_to_traversability(generate_dem(kind, size, seed=seed)).fractions()["impassable"]
        assert 0.08 <= frac <= 0.30, f"{kind} {size} seed {seed}: {frac:.3f}"


def test_larger_map_shows_more_craters_of_the_same_sizes():
    small = generate_dem("mars", 128, seed=0)
    large = generate_dem("mars", 512, seed=0)
    # 16x the area: roughly 16x the craters (at least 8x allowing for chance).
    assert len(large.meta["craters"]) > 8 * len(small.meta["craters"])
    small_median = np.median([r for _, _, r in small.meta["craters"]])
    large_median = np.median([r for _, _, r in large.meta["craters"]])
    assert 0.5 < large_median / small_median < 2.0
