"""Tests for fedmap.maps.io: map and DEM files, errors, atomic writes."""

from __future__ import annotations

import math
import os
import re
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine
from PIL import Image
from rasterio.errors import NotGeoreferencedWarning
from rasterio.shutil import copy as rio_copy

from fedmap import _util
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, PALETTE, UNKNOWN, GridMap
from fedmap.maps.io import atomic_write_bytes, load_dem, load_map, save_map


def random_map(shape=(37, 53), seed=0, pixel_size=1.0) -> GridMap:
    rng = np.random.default_rng(seed)
    return GridMap(rng.integers(0, 3, size=shape).astype(np.uint8), pixel_size, "test")


def assert_one_line(exc: pytest.ExceptionInfo) -> None:
    assert "\n" not in str(exc.value)


# --------------------------------------------------------------------------- maps


@pytest.mark.parametrize("suffix", [".png", ".npy"])
def test_map_round_trip_exact(tmp_path, suffix):
    grid = random_map(seed=1)
    path = tmp_path / f"map{suffix}"
    save_map(grid, path)
    back = load_map(path)
    assert back.classes.dtype == np.uint8
    np.testing.assert_array_equal(back.classes, grid.classes)
    assert back.source == str(path)
    # every class occurs, so the test would notice a swapped colour
    assert set(np.unique(back.classes)) == {FREE, IMPASSABLE, UNKNOWN}


def test_png_is_8bit_rgb_in_palette_colours(tmp_path):
    grid = random_map(seed=2)
    save_map(grid, tmp_path / "m.png")
    with Image.open(tmp_path / "m.png") as img:
        assert img.mode == "RGB"
        rgb = np.asarray(img)
    np.testing.assert_array_equal(rgb[grid.classes == FREE][0], [0, 255, 0])
    np.testing.assert_array_equal(rgb[grid.classes == IMPASSABLE][0], [255, 0, 0])
    np.testing.assert_array_equal(rgb[grid.classes == UNKNOWN][0], [128, 128, 128])


def test_pixel_size_png_keeps_it_npy_takes_argument(tmp_path):
    grid = random_map(seed=3, pixel_size=0.25)
    save_map(grid, tmp_path / "m.png")
    save_map(grid, tmp_path / "m.npy")
    assert load_map(tmp_path / "m.png").pixel_size == 0.25
    assert load_map(tmp_path / "m.png", pixel_size=2.0).pixel_size == 2.0
    npy = load_map(tmp_path / "m.npy")
    assert npy.pixel_size == 1.0 and npy.meta["pixel_size_from"] == "default"
    assert load_map(tmp_path / "m.npy", pixel_size=0.25).pixel_size == 0.25


def test_noisy_rgb_png_maps_to_nearest_class(tmp_path):
    grid = random_map(seed=4)
    rng = np.random.default_rng(5)
    rgb = PALETTE[grid.classes] * 255.0 + rng.uniform(-60, 60, size=grid.classes.shape + (3,))
    rgb8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    Image.fromarray(rgb8).save(tmp_path / "noisy.png")
    back = load_map(tmp_path / "noisy.png")
    np.testing.assert_array_equal(back.classes, grid.classes)


def test_rgba_png_ignores_alpha(tmp_path):
    grid = random_map(seed=6)
    rgb8 = np.rint(PALETTE[grid.classes] * 255).astype(np.uint8)
    alpha = np.full(grid.shape + (1,), 200, np.uint8)
    Image.fromarray(np.concatenate([rgb8, alpha], axis=2)).save(tmp_path / "rgba.png")
    np.testing.assert_array_equal(load_map(tmp_path / "rgba.png").classes, grid.classes)


def test_grayscale_png_class_indices(tmp_path):
    grid = random_map(seed=7)
    Image.fromarray(grid.classes).save(tmp_path / "gray.png")
    back = load_map(tmp_path / "gray.png")
    np.testing.assert_array_equal(back.classes, grid.classes)
    assert back.meta["decoded_as"] == "classes"


def test_grayscale_png_other_values_is_error(tmp_path):
    mask = np.zeros((10, 10), np.uint8)
    mask[3:6] = 255
    Image.fromarray(mask).save(tmp_path / "mask.png")
    with pytest.raises(FedmapError, match="0, 255") as exc:
        load_map(tmp_path / "mask.png")
    assert str(tmp_path / "mask.png") in str(exc.value)


def test_npy_float_rgb_and_uint8_rgb(tmp_path):
    grid = random_map(seed=8)
    rgb = PALETTE[grid.classes] * 0.8 + 0.1  # shrunk towards grey, still nearest the right colour
    np.save(tmp_path / "rgb.npy", rgb.astype(np.float32))
    np.testing.assert_array_equal(load_map(tmp_path / "rgb.npy").classes, grid.classes)
    np.save(tmp_path / "rgb8.npy", np.rint(PALETTE[grid.classes] * 255).astype(np.uint8))
    np.testing.assert_array_equal(load_map(tmp_path / "rgb8.npy").classes, grid.classes)


def test_corrupt_png_is_fedmap_error(tmp_path):
    path = tmp_path / "bad.png"
    path.write_bytes(np.random.default_rng(9).bytes(500))
    with pytest.raises(FedmapError, match="cannot read map") as exc:
        load_map(path)
    assert str(path) in str(exc.value)
    assert_one_line(exc)


def test_truncated_png_is_fedmap_error(tmp_path):
    save_map(random_map((64, 64), seed=10), tmp_path / "m.png")
    data = (tmp_path / "m.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(FedmapError, match="cannot read map"):
        load_map(tmp_path / "cut.png")


@pytest.mark.parametrize("keep", [20, 200])
def test_truncated_npy_is_fedmap_error(tmp_path, keep):
    save_map(random_map((40, 40), seed=11), tmp_path / "m.npy")
    data = (tmp_path / "m.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:keep])
    with pytest.raises(FedmapError, match="cannot read map") as exc:
        load_map(tmp_path / "cut.npy")
    assert str(tmp_path / "cut.npy") in str(exc.value)
    assert_one_line(exc)


def test_missing_file_names_path(tmp_path):
    for path, loader in [(tmp_path / "nope.png", load_map), (tmp_path / "nope.npy", load_map),
                         (tmp_path / "nope.tif", load_dem), (tmp_path / "nope.npy", load_dem)]:
        with pytest.raises(FedmapError, match="no such file") as exc:
            loader(path)
        assert str(path) in str(exc.value)


@pytest.mark.parametrize(
    "array",
    [
        np.zeros((4, 5, 6), np.uint8),  # 3-D integer
        np.zeros(10, np.int64),  # 1-D
        np.zeros((4, 5, 4), np.float32),  # 4 channels
        np.zeros((4, 5), np.float32),  # float but not RGB
        np.zeros((4, 5), bool),
    ],
)
def test_wrong_shape_npy_is_fedmap_error(tmp_path, array):
    np.save(tmp_path / "m.npy", array)
    with pytest.raises(FedmapError, match="shape") as exc:
        load_map(tmp_path / "m.npy")
    assert str(tmp_path / "m.npy") in str(exc.value)


def test_npy_class_values_out_of_range(tmp_path):
    np.save(tmp_path / "m.npy", np.array([[0, 1], [2, 3]], np.int32))
    with pytest.raises(FedmapError, match="0..3"):
        load_map(tmp_path / "m.npy")


def test_npy_rgb_out_of_range(tmp_path):
    np.save(tmp_path / "m.npy", np.full((3, 3, 3), 255.0, np.float32))
    with pytest.raises(FedmapError, match=r"\[0, 1\]"):
        load_map(tmp_path / "m.npy")


def test_unsupported_suffix_lists_supported(tmp_path):
    (tmp_path / "m.jpg").write_bytes(b"x")
    with pytest.raises(FedmapError, match=r"\.png, \.npy"):
        load_map(tmp_path / "m.jpg")
    with pytest.raises(FedmapError, match=r"\.png, \.npy"):
        save_map(random_map(), tmp_path / "m.bmp")
    assert not (tmp_path / "m.bmp").exists()
    with pytest.raises(FedmapError, match=r"cannot read DEM .*m\.jpg"):
        load_dem(tmp_path / "m.jpg")  # GDAL reads by content: one b"x" is nothing it knows


def test_save_creates_parent_folder(tmp_path):
    path = tmp_path / "a" / "b" / "m.npy"
    save_map(random_map(seed=12), path)
    assert path.is_file()


# --------------------------------------------------------------------------- atomic writes


def test_save_is_atomic_no_temp_left(tmp_path):
    save_map(random_map(seed=13), tmp_path / "m.png")
    save_map(random_map(seed=14), tmp_path / "m.png")  # overwrite
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.png"]
    np.testing.assert_array_equal(load_map(tmp_path / "m.png").classes, random_map(seed=14).classes)


def test_failed_write_leaves_old_file(tmp_path, monkeypatch):
    path = tmp_path / "m.npy"
    save_map(random_map(seed=15), path)
    old = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_util.os, "replace", broken_replace)
    with pytest.raises(FedmapError, match="cannot write") as exc:
        save_map(random_map(seed=16), path)
    assert str(path) in str(exc.value)
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npy"]


def test_atomic_write_keeps_mode_of_existing_file(tmp_path):
    path = tmp_path / "f.bin"
    path.write_bytes(b"old")
    os.chmod(path, 0o640)
    atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"new"
    assert (os.stat(path).st_mode & 0o777) == 0o640


# --------------------------------------------------------------------------- DEMs (through GDAL)

MOON = "IAU_2015:30100"  # longitude/latitude on the IAU 2015 Moon sphere, 1737.4 km
MARS = "IAU_2015:49901"  # longitude/latitude (ographic) on the IAU 2015 Mars ellipsoid, 3396.19 x 3376.2 km


def write_raster(path, z, *, transform=None, crs=None, nodata=None, driver="GTiff", **kw):
    """Write ``z`` (H, W) or (B, H, W) with rasterio (GDAL); AAIGrid goes through a GeoTIFF copy."""
    z = np.asarray(z)
    bands = z if z.ndim == 3 else z[None]
    profile = dict(driver="GTiff" if driver == "AAIGrid" else driver, height=bands.shape[1], width=bands.shape[2],
                   count=bands.shape[0], dtype=bands.dtype.name, crs=crs, nodata=nodata, **kw)
    if transform is not None:
        profile["transform"] = transform
    target = str(path.with_suffix(".src.tif")) if driver == "AAIGrid" else str(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # files without a transform on purpose
        with rasterio.open(target, "w", **profile) as dst:
            dst.write(bands)
        if driver == "AAIGrid":
            rio_copy(target, str(path), driver="AAIGrid")
    return path


def plane(h, w, dx_m, dy_m, gx=0.1, gy=0.2, base=1000.0) -> np.ndarray:
    """Elevation rising ``gx`` m per metre east and ``gy`` per metre north (row 0 north)."""
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    return (base + gx * cols * dx_m - gy * rows * dy_m).astype(np.float32)


def test_projected_geotiff_pixel_size_nodata_and_transform(tmp_path):
    rng = np.random.default_rng(20)
    z = rng.uniform(100, 200, size=(30, 40)).astype(np.float32)
    z[2, 3] = z[10, 20] = -9999.0
    t = Affine(2.5, 0, 500000.0, 0, -2.5, 4000000.0)
    path = write_raster(tmp_path / "dem.tif", z, transform=t, crs="EPSG:32612", nodata=-9999.0)
    dem = load_dem(path)
    assert dem.pixel_size == pytest.approx(2.5) and dem.shape == (30, 40)
    nan = np.isnan(dem.elevation)
    assert nan.sum() == 2 and nan[2, 3] and nan[10, 20]
    np.testing.assert_array_equal(dem.elevation[~nan], z[z != -9999.0])
    assert dem.meta["nodata"] == -9999.0 and dem.meta["pixel_size_from"] == "crs"
    assert dem.transform == t and "UTM zone 12N" in dem.crs and dem.source == str(path)
    # arguments win over the file
    dem2 = load_dem(path, pixel_size=7.0, nodata=float(z[0, 0]))
    assert dem2.pixel_size == 7.0 and dem2.meta["pixel_size_from"] == "argument"
    assert np.isnan(dem2.elevation[0, 0]) and not np.isnan(dem2.elevation[2, 3])


def test_geotiff_in_us_survey_feet(tmp_path):
    z = np.arange(100, dtype=np.float32).reshape(10, 10)
    write_raster(tmp_path / "ft.tif", z, transform=Affine(10, 0, 6e6, 0, -10, 2e6), crs="EPSG:2227")  # CA zone 3 ftUS
    assert load_dem(tmp_path / "ft.tif").pixel_size == pytest.approx(10 * 1200 / 3937)


def test_int16_nodata_at_type_max_and_float32_lowest(tmp_path):
    z = np.full((8, 9), 500, np.int16)
    z[4, 4] = 32767
    write_raster(tmp_path / "i.tif", z, nodata=32767)
    dem = load_dem(tmp_path / "i.tif")
    assert np.isnan(dem.elevation).sum() == 1 and np.isnan(dem.elevation[4, 4]) and dem.elevation.dtype == np.float32
    f = np.full((6, 6), 12.5, np.float32)
    f[0, 0] = np.finfo(np.float32).min
    write_raster(tmp_path / "f.tif", f, nodata=float(np.finfo(np.float32).min))
    dem = load_dem(tmp_path / "f.tif")
    assert np.isnan(dem.elevation[0, 0]) and np.isnan(dem.elevation).sum() == 1


def test_scale_and_offset_are_applied(tmp_path):
    z = np.arange(20, dtype=np.int16).reshape(4, 5)
    path = write_raster(tmp_path / "so.tif", z, transform=Affine(1, 0, 0, 0, -1, 4), crs="EPSG:32612")
    with rasterio.open(path, "r+") as dst:
        dst.scales, dst.offsets = (0.5,), (-100.0,)
    np.testing.assert_array_equal(load_dem(path).elevation, z * 0.5 - 100.0)


def test_moon_geotiff_degrees_to_metres_on_the_moon_radius(tmp_path):
    h, w, deg = 60, 80, 1.0 / 64
    lat_top = 40.0 + h / 2 * deg  # centre latitude exactly 40 N
    m_per_deg = math.pi / 180 * 1_737_400.0  # by hand: the Moon sphere, not Earth
    dx_m, dy_m = deg * m_per_deg * math.cos(math.radians(40.0)), deg * m_per_deg
    z = plane(h, w, dx_m, dy_m)
    path = write_raster(tmp_path / "moon.tif", z, transform=Affine(deg, 0, 20.0, 0, -deg, lat_top), crs=MOON)
    dem = load_dem(path)
    assert dem.meta["crs_kind"] == "geographic" and dem.meta["centre_lat_deg"] == pytest.approx(40.0)
    assert dem.meta["radius_m"] == pytest.approx(1_737_400.0)
    assert dem.pixel_size == pytest.approx(dx_m, rel=1e-9)  # 363.5 m: the finer (east-west) spacing
    # rows resampled so that cells are square; the slopes are right in metres
    assert dem.shape == (round(h * dy_m / dx_m), w) and dem.meta["cells_resampled"]["axis"] == "rows"
    dz_dy, dz_dx = np.gradient(dem.elevation.astype(np.float64), dem.pixel_size)
    assert np.median(dz_dx) == pytest.approx(0.1, rel=0.01)
    assert np.median(-dz_dy) == pytest.approx(0.2, rel=0.01)
    # the transform still spans the file's extent
    assert dem.transform @ (dem.shape[1], dem.shape[0]) == pytest.approx((20.0 + w * deg, lat_top - h * deg))


def test_mars_ellipsoid_radii_from_the_crs(tmp_path):
    deg = 1.0 / 128
    z = np.ones((16, 16), np.float32)
    write_raster(tmp_path / "mars.tif", z, transform=Affine(deg, 0, 137.0, 0, -deg, 8 * deg), crs=MARS)  # equator
    dem = load_dem(tmp_path / "mars.tif")
    a, b = 3_396_190.0, 3_376_200.0
    dx = math.radians(deg) * a  # prime vertical radius at the equator is a
    dy = math.radians(deg) * b * b / a  # meridional radius at the equator is b^2 / a
    assert dem.pixel_size == pytest.approx(min(dx, dy), rel=1e-9)
    assert abs(dx - dy) / dy > 0.01  # 1.2%: more than the square-cell tolerance, so
    assert dem.meta["cells_resampled"]["axis"] == "columns"  # the coarser east-west axis is resampled
    note = dem.meta["cells_note"]  # what the CLI prints: one line of words, not a dict
    assert isinstance(note, str) and "\n" not in note and "columns were resampled to square cells" in note


def test_isis3_cube_in_a_moon_crs(tmp_path):
    z = plane(12, 10, 303.2, 303.2)
    z[0, 0] = -3.4028226550889045e38  # ISIS NULL
    path = write_raster(tmp_path / "site.cub", z, driver="ISIS3", crs=MOON, transform=Affine(0.01, 0, 10, 0, -0.01, 0.06))
    dem = load_dem(path)
    assert dem.meta["driver"] == "ISIS3"
    # GDAL writes the cube in simple cylindrical metres: 0.01 deg of the 1737.4 km sphere
    assert dem.pixel_size == pytest.approx(math.radians(0.01) * 1_737_400.0, rel=1e-9)
    assert np.isnan(dem.elevation[0, 0]) and np.isnan(dem.elevation).sum() == 1
    np.testing.assert_array_equal(dem.elevation.ravel()[1:], z.ravel()[1:])


def test_pds4_product(tmp_path):
    z = (np.arange(12 * 10).reshape(12, 10) - 40).astype(np.int16)
    z[5, 5] = -32768
    path = write_raster(tmp_path / "site.xml", z, driver="PDS4", crs=MOON, nodata=-32768,
                        transform=Affine(0.02, 0, 10, 0, -0.02, 0.1))
    dem = load_dem(path)
    assert dem.meta["driver"] == "PDS4" and np.isnan(dem.elevation[5, 5]) and np.isnan(dem.elevation).sum() == 1
    assert dem.pixel_size == pytest.approx(math.radians(0.02) * 1_737_400.0, rel=1e-9)
    ok = z != -32768
    np.testing.assert_array_equal(dem.elevation[ok], z[ok])


def test_aaigrid_with_nodata_and_prj(tmp_path):
    z = np.array([[1, 2, 3, 4], [5, -9999, 7, 8], [9, 10, 11, 12.5]], np.float32)
    path = write_raster(tmp_path / "g.asc", z, driver="AAIGrid", nodata=-9999.0,
                        transform=Affine(2.5, 0, 100, 0, -2.5, 207.5), crs="EPSG:32612")
    assert (tmp_path / "g.prj").is_file()
    dem = load_dem(path)
    assert dem.meta["driver"] == "AAIGrid" and dem.pixel_size == 2.5 and dem.meta["pixel_size_from"] == "crs"
    assert np.isnan(dem.elevation[1, 1]) and np.isnan(dem.elevation).sum() == 1
    np.testing.assert_array_equal(np.nan_to_num(dem.elevation, nan=-9999.0), z)
    # the lower-left corner of the header (xllcorner 100, yllcorner 200) is where the transform puts it
    assert dem.transform @ (0, 3) == pytest.approx((100.0, 200.0))


def test_handwritten_ascii_grid_without_prj(tmp_path):
    """An ESRI ASCII grid written from its spec, no .prj: metres assumed; degree-like refused."""
    text = "ncols 4\nnrows 3\nxllcenter 101.25\nyllcenter 201.25\ncellsize 2.5\nNODATA_value -9999\n"
    text += "1 2 3 4\n5 -9999 7 8\n9 10 11 12.5\n"
    (tmp_path / "h.asc").write_text(text)
    dem = load_dem(tmp_path / "h.asc")
    assert dem.pixel_size == 2.5 and dem.meta["pixel_size_from"] == "transform (assumed metres)"
    assert dem.elevation[2, 3] == 12.5 and np.isnan(dem.elevation[1, 1])
    assert dem.transform @ (0.5, 2.5) == pytest.approx((101.25, 201.25))  # centre of the lower-left cell
    (tmp_path / "deg.asc").write_text(text.replace("cellsize 2.5", "cellsize 0.000833333")
                                      .replace("xllcenter 101.25", "xllcenter -105.5")
                                      .replace("yllcenter 201.25", "yllcenter 40.1"))
    with pytest.raises(FedmapError, match="looks like degrees; pass crs") as exc:
        load_dem(tmp_path / "deg.asc")
    assert_one_line(exc)
    dem = load_dem(tmp_path / "deg.asc", crs="EPSG:4326")
    assert dem.meta["crs_kind"] == "geographic" and 60 < dem.pixel_size < 75  # 3" east-west at 40 N
    assert load_dem(tmp_path / "deg.asc", pixel_size=5.0).pixel_size == 5.0


@pytest.mark.parametrize("crs", [None, "EPSG:32613"])
def test_a_geotiff_of_arc_minute_cells_is_taken_for_degrees_with_or_without_a_projected_crs(tmp_path, crs):
    """2.5' cells (0.0417, a global DEM's clip) with no CRS were taken as 4 cm cells, and
    labelled UTM the same: both are refused in one line, and the file loads with its real CRS."""
    z = np.linspace(1500, 2500, 60 * 80, dtype=np.float32).reshape(60, 80)
    t = Affine(0.0416667, 0, -106.0, 0, -0.0416667, 41.0)
    path = write_raster(tmp_path / "arcmin.tif", z, transform=t, crs=crs)
    with pytest.raises(FedmapError, match="looks like degrees") as exc:
        load_dem(path)
    assert_one_line(exc)
    dem = load_dem(path, crs="EPSG:4326")
    assert dem.meta["crs_kind"] == "geographic" and 3400 < dem.pixel_size < 3600  # 2.5' east-west at 40 N
    metres = write_raster(tmp_path / "metres.tif", z, transform=Affine(0.5, 0, 0.0, 0, -0.5, 400.0), crs=crs)
    assert load_dem(metres).pixel_size == 0.5  # half-metre cells off the lon/lat box stay metres


def test_a_dem_of_non_square_cells_says_so_in_words_with_or_without_a_size(tmp_path):
    """A geographic grid away from the equator has non-square cells: the user is told in one
    line of words (it was a raw dict), and still told when --size resamples the map too."""
    from fedmap.maps.sources import TerrainSource, load_terrain

    deg = 1.0 / 1200  # 3" cells at 60 N: about 46 m east-west, 93 m north-south
    z = np.random.default_rng(1).normal(0, 3, (120, 240)).cumsum(axis=1).astype(np.float32)
    path = write_raster(tmp_path / "north.tif", z, transform=Affine(deg, 0, 10.0, 0, -deg, 60.05), crs="EPSG:4326")
    for size in (None, 48):
        truth, _ = load_terrain(TerrainSource(kind="dem", path=str(path), size=size))
        note = truth.meta["cells_note"]
        assert isinstance(note, str) and "\n" not in note and "north-south" in note
        assert ("resampled" in truth.meta) == (size is not None)


def test_a_dem_spanning_many_latitudes_is_told_its_cell_size_holds_only_at_its_centre(tmp_path):
    """A lat/lon DEM from 0 to 60 N got one cell size everywhere (its centre's), true only
    there: the user is told how far off it is; a one-degree clip is not flagged."""
    from fedmap.maps.sources import TerrainSource, load_terrain

    z = np.random.default_rng(2).normal(0, 50, (120, 120)).cumsum(axis=0).astype(np.float32)
    wide = write_raster(tmp_path / "wide.tif", z, transform=Affine(0.5, 0, 0.0, 0, -0.5, 60.0), crs="EPSG:4326")
    truth, _ = load_terrain(TerrainSource(kind="dem", path=str(wide)))
    note = truth.meta["latitude_note"]
    # east-west at 60 N is half the equator's: cos(60) = 0.5 (by hand, on the WGS84 ellipsoid to 1 %)
    lo, hi = (float(v.replace(",", "")) for v in re.search(r"cells are ([\d,]+) to ([\d,]+) m", note).groups())
    assert "latitudes 0.00 to 60.00" in note and lo / hi == pytest.approx(0.5, rel=0.01)
    clip = write_raster(tmp_path / "clip.tif", z, transform=Affine(1 / 120, 0, 10.0, 0, -1 / 120, 41.0),
                        crs="EPSG:4326")
    assert "latitude_note" not in load_terrain(TerrainSource(kind="dem", path=str(clip)))[0].meta


def test_south_up_grid_is_flipped_rotated_grid_refused(tmp_path):
    z = np.arange(30, dtype=np.float32).reshape(5, 6)
    t = Affine(10, 0, 1000, 0, 10, 5000)  # row 0 is the south edge
    dem = load_dem(write_raster(tmp_path / "south.tif", z, transform=t, crs="EPSG:32612"))
    np.testing.assert_array_equal(dem.elevation, z[::-1])
    assert dem.transform.e < 0 and dem.meta["flipped"] == ["rows (south-up file)"]
    # a cell keeps its ground coordinate: file cell (row 0, col 2) is now row 4
    assert dem.transform @ (2.5, 4.5) == pytest.approx(t @ (2.5, 0.5))
    rotated = Affine(10, 1, 1000, 1, -10, 5000)
    write_raster(tmp_path / "rot.tif", z, transform=rotated, crs="EPSG:32612")
    with pytest.raises(FedmapError, match="rot.tif has a rotated geotransform") as exc:
        load_dem(tmp_path / "rot.tif")
    assert_one_line(exc)


def test_raw_samples_through_a_gdal_vrt(tmp_path):
    rng = np.random.default_rng(3)
    z = rng.integers(-4000, 4000, size=(30, 40)).astype(np.int16)
    z[3, 4] = -4200
    for order, code in (("big", ">i2"), ("little", "<i2")):
        path = tmp_path / f"t_{order}.img"
        path.write_bytes(b"HEAD" + z.astype(code).tobytes())
        dem = load_dem(path, shape=(30, 40), byteorder=order, header_bytes=4, pixel_size=100.0, nodata=-4200)
        assert dem.pixel_size == 100.0 and np.isnan(dem.elevation).sum() == 1
        np.testing.assert_array_equal(np.nan_to_num(dem.elevation, nan=-4200), z)
    other = load_dem(tmp_path / "t_big.img", shape=(30, 40), byteorder="little", header_bytes=4).elevation
    assert not np.array_equal(other, z)
    with pytest.raises(FedmapError, match="does not recognise its format; raw samples without a label need shape=") as exc:
        load_dem(tmp_path / "t_big.img")
    assert_one_line(exc)
    with pytest.raises(FedmapError, match="bytes but 4 header"):
        load_dem(tmp_path / "t_big.img", shape=(30, 41), header_bytes=4)
    with pytest.raises(FedmapError, match="byteorder"):
        load_dem(tmp_path / "t_big.img", shape=(30, 40), header_bytes=4, byteorder="middle")


def test_band_option_and_plain_tiff_defaults(tmp_path):
    z = np.stack([np.full((5, 6), 3.0), np.full((5, 6), 9.0)]).astype(np.float32)
    path = write_raster(tmp_path / "two.tif", z)
    dem = load_dem(path)
    assert dem.shape == (5, 6) and np.all(dem.elevation == 3.0)
    assert dem.pixel_size == 1.0 and dem.meta["pixel_size_from"] == "default" and dem.transform is None
    assert np.all(load_dem(path, band=2).elevation == 9.0)
    with pytest.raises(FedmapError, match="has 2 band.*band 3"):
        load_dem(path, band=3)
    with pytest.raises(FedmapError, match="heightmap .png tiles only"):
        load_dem(path, offset=0.0)


def test_all_nodata_dem_is_error(tmp_path):
    write_raster(tmp_path / "empty.tif", np.full((10, 10), -9999.0, np.float32), nodata=-9999.0)
    with pytest.raises(FedmapError, match="nodata") as exc:
        load_dem(tmp_path / "empty.tif")
    assert str(tmp_path / "empty.tif") in str(exc.value)
    np.save(tmp_path / "empty.npy", np.full((10, 10), np.nan))
    with pytest.raises(FedmapError, match="nodata"):
        load_dem(tmp_path / "empty.npy")


def test_npy_dem(tmp_path):
    z = np.arange(30, dtype=np.float64).reshape(5, 6)
    z[1, 1], z[2, 2], z[3, 3] = np.nan, np.inf, -5.0
    np.save(tmp_path / "d.npy", z)
    dem = load_dem(tmp_path / "d.npy", pixel_size=0.5, nodata=-5.0)
    assert dem.pixel_size == 0.5 and dem.elevation.dtype == np.float32
    assert np.isnan(dem.elevation).sum() == 3
    assert load_dem(tmp_path / "d.npy").pixel_size == 1.0
    np.save(tmp_path / "bad.npy", np.zeros((3, 4, 5)))
    with pytest.raises(FedmapError, match="2-D"):
        load_dem(tmp_path / "bad.npy")


def test_corrupt_tiff_is_fedmap_error(tmp_path):
    path = tmp_path / "bad.tif"
    path.write_bytes(b"II*\x00" + np.random.default_rng(21).bytes(300))
    with pytest.raises(FedmapError, match="cannot read DEM") as exc:
        load_dem(path)
    assert str(path) in str(exc.value)
    assert_one_line(exc)
    path2 = tmp_path / "junk.tiff"
    path2.write_bytes(b"not a tiff at all")
    with pytest.raises(FedmapError, match="cannot read DEM"):
        load_dem(path2)


PDS3_LABEL = """PDS_VERSION_ID = PDS3
RECORD_TYPE = FIXED_LENGTH
RECORD_BYTES = 16
FILE_RECORDS = 6
^IMAGE = ("site.img", 1)
OBJECT = IMAGE
  LINES = 6
  LINE_SAMPLES = 8
  SAMPLE_TYPE = MSB_INTEGER
  SAMPLE_BITS = 16
  MISSING_CONSTANT = -32768
  SCALING_FACTOR = 0.5
  OFFSET = 1000.0
END_OBJECT = IMAGE
OBJECT = IMAGE_MAP_PROJECTION
  MAP_PROJECTION_TYPE = "EQUIRECTANGULAR"
  A_AXIS_RADIUS = 3396.19 <KM>
  B_AXIS_RADIUS = 3396.19 <KM>
  C_AXIS_RADIUS = 3396.19 <KM>
  CENTER_LATITUDE = 0.0 <DEG>
  CENTER_LONGITUDE = 180.0 <DEG>
  MAP_SCALE = 0.25 <KM/PIXEL>
  LINE_PROJECTION_OFFSET = 100.5 <PIXEL>
  SAMPLE_PROJECTION_OFFSET = -200.5 <PIXEL>
  POSITIVE_LONGITUDE_DIRECTION = EAST
END_OBJECT = IMAGE_MAP_PROJECTION
END
"""


def test_pds3_detached_label_written_from_the_standard(tmp_path):
    """A PDS3 label by hand (PDS Standards Reference ch. 5: IMAGE and IMAGE_MAP_PROJECTION objects)."""
    z = (np.arange(48).reshape(6, 8) * 10 - 100).astype(">i2")
    z[2, 3] = -32768
    (tmp_path / "site.lbl").write_text(PDS3_LABEL)
    (tmp_path / "site.img").write_bytes(z.tobytes())
    dem = load_dem(tmp_path / "site.lbl")
    assert dem.meta["driver"] == "PDS" and dem.pixel_size == pytest.approx(250.0)  # MAP_SCALE 0.25 km/pixel
    assert np.isnan(dem.elevation[2, 3]) and np.isnan(dem.elevation).sum() == 1
    ok = z != -32768
    np.testing.assert_array_equal(dem.elevation[ok], z[ok] * 0.5 + 1000.0)  # SCALING_FACTOR, OFFSET
    assert "Mars" in dem.crs or "3396190" in dem.crs


def test_cloud_optimized_geotiff(tmp_path):
    z = plane(64, 64, 5.0, 5.0)
    src = write_raster(tmp_path / "src.tif", z, transform=Affine(5, 0, 0, 0, -5, 320), crs="EPSG:32612")
    rio_copy(str(src), str(tmp_path / "cog.tif"), driver="COG")
    dem = load_dem(tmp_path / "cog.tif")
    np.testing.assert_array_equal(dem.elevation, z)
    assert dem.pixel_size == 5.0 and dem.transform == Affine(5, 0, 0, 0, -5, 320)
