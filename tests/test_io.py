"""Tests for fedmap.maps.io: map and DEM files, errors, atomic writes."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import tifffile
from PIL import Image

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
    with pytest.raises(FedmapError, match=r"\.tif, \.tiff, \.npy"):
        load_dem(tmp_path / "m.jpg")


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


# --------------------------------------------------------------------------- DEMs


def geokeys(model_type: int, extra: list[tuple[int, int]] = ()) -> tuple[int, ...]:
    """A GeoKeyDirectoryTag with short (inline) keys only."""
    keys = [(1024, model_type), (1025, 1)] + list(extra)
    out = [1, 1, 0, len(keys)]
    for key, value in keys:
        out += [key, 0, 1, value]
    return tuple(out)


def write_geotiff(path, data, *, scale, tiepoint, model_type, nodata=None, extra_keys=()):
    extratags = [
        (33550, "d", 3, (scale[0], scale[1], 0.0), True),
        (33922, "d", 6, (0.0, 0.0, 0.0, tiepoint[0], tiepoint[1], 0.0), True),
        (34735, "H", len(geokeys(model_type, extra_keys)), geokeys(model_type, extra_keys), True),
    ]
    if nodata is not None:
        extratags.append((42113, "s", 0, nodata, True))
    tifffile.imwrite(path, data, extratags=extratags)


def test_projected_geotiff_pixel_size_and_nodata(tmp_path):
    rng = np.random.default_rng(20)
    z = rng.uniform(100, 200, size=(30, 40)).astype(np.float32)
    z[2, 3] = z[10, 20] = -9999.0
    path = tmp_path / "dem.tif"
    write_geotiff(path, z, scale=(2.5, 2.5), tiepoint=(500000.0, 4000000.0), model_type=1,
                  nodata="-9999", extra_keys=[(3076, 9001)])
    dem = load_dem(path)
    assert dem.pixel_size == pytest.approx(2.5)
    assert dem.shape == (30, 40)
    nan = np.isnan(dem.elevation)
    assert nan.sum() == 2 and nan[2, 3] and nan[10, 20]
    np.testing.assert_array_equal(dem.elevation[~nan], z[z != -9999.0])
    assert dem.meta["nodata"] == -9999.0 and dem.meta["nodata_from"] == "geotiff"
    assert dem.meta["pixel_size_from"] == "geotiff"
    assert dem.source == str(path)
    # arguments win over the tags
    dem2 = load_dem(path, pixel_size=7.0, nodata=float(z[0, 0]))
    assert dem2.pixel_size == 7.0 and dem2.meta["pixel_size_from"] == "argument"
    assert np.isnan(dem2.elevation[0, 0]) and not np.isnan(dem2.elevation[2, 3])


def test_geotiff_in_feet(tmp_path):
    z = np.arange(100, dtype=np.float32).reshape(10, 10)
    write_geotiff(tmp_path / "ft.tif", z, scale=(10.0, 10.0), tiepoint=(0.0, 0.0), model_type=1,
                  extra_keys=[(3076, 9002)])
    assert load_dem(tmp_path / "ft.tif").pixel_size == pytest.approx(3.048)


def test_int16_geotiff_nodata_at_type_max(tmp_path):
    z = np.full((8, 9), 500, np.int16)
    z[4, 4] = 32767
    write_geotiff(tmp_path / "i.tif", z, scale=(30.0, 30.0), tiepoint=(0.0, 0.0), model_type=1, nodata="32767")
    dem = load_dem(tmp_path / "i.tif")
    assert np.isnan(dem.elevation).sum() == 1 and np.isnan(dem.elevation[4, 4])
    assert dem.elevation.dtype == np.float32


def test_float32_lowest_nodata(tmp_path):
    z = np.full((6, 6), 12.5, np.float32)
    z[0, 0] = np.finfo(np.float32).min
    write_geotiff(tmp_path / "f.tif", z, scale=(1.0, 1.0), tiepoint=(0.0, 0.0), model_type=1,
                  nodata="-3.40282346638529e+38")
    dem = load_dem(tmp_path / "f.tif")
    assert np.isnan(dem.elevation[0, 0]) and np.isnan(dem.elevation).sum() == 1


def test_geographic_geotiff_pixel_size_in_metres(tmp_path):
    h, w = 60, 80
    deg = 1.0 / 1200.0
    lat_top = 40.0 + h / 2 * deg  # centre latitude exactly 40
    # a plane rising 0.1 m per metre east and 0.2 m per metre north
    m_per_deg = math.pi / 180.0 * 6371000.0
    dx_m, dy_m = deg * m_per_deg * math.cos(math.radians(40.0)), deg * m_per_deg
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    z = (1000.0 + 0.1 * cols * dx_m - 0.2 * rows * dy_m).astype(np.float32)
    path = tmp_path / "geo.tif"
    write_geotiff(path, z, scale=(deg, deg), tiepoint=(-105.0, lat_top), model_type=2)
    dem = load_dem(path)
    assert dem.meta["crs"] == "geographic"
    assert dem.meta["centre_lat_deg"] == pytest.approx(40.0)
    # by hand: 1/1200 deg = 92.66 m north-south, 70.98 m east-west at 40 deg
    assert dem.meta["pixel_size_y_m"] == pytest.approx(92.66, rel=0.01)
    assert dem.meta["pixel_size_x_m"] == pytest.approx(70.98, rel=0.01)
    assert dem.pixel_size == pytest.approx(70.98, rel=0.01)
    # cells are made square: rows resampled to the finer east-west spacing
    assert dem.shape == (round(h * dy_m / dx_m), w)
    assert dem.meta["resampled"]["axis"] == "rows"
    dz_dy, dz_dx = np.gradient(dem.elevation.astype(np.float64), dem.pixel_size)
    assert np.median(dz_dx) == pytest.approx(0.1, rel=0.01)
    assert np.median(-dz_dy) == pytest.approx(0.2, rel=0.01)


def test_geographic_without_tiepoint_needs_pixel_size(tmp_path):
    z = np.ones((5, 5), np.float32)
    keys = geokeys(2)
    tifffile.imwrite(tmp_path / "g.tif", z, extratags=[(33550, "d", 3, (0.001, 0.001, 0.0), True),
                                                       (34735, "H", len(keys), keys, True)])
    with pytest.raises(FedmapError, match="pass pixel_size"):
        load_dem(tmp_path / "g.tif")
    assert load_dem(tmp_path / "g.tif", pixel_size=90.0).pixel_size == 90.0


def test_plain_tiff_defaults_and_first_band(tmp_path):
    z = np.stack([np.full((5, 6), 3.0), np.full((5, 6), 9.0)], axis=-1).astype(np.float32)
    tifffile.imwrite(tmp_path / "rgbish.tif", z, photometric="minisblack", planarconfig="contig")
    dem = load_dem(tmp_path / "rgbish.tif")
    assert dem.shape == (5, 6) and np.all(dem.elevation == 3.0)
    assert dem.pixel_size == 1.0 and dem.meta["pixel_size_from"] == "default"


def test_all_nodata_dem_is_error(tmp_path):
    z = np.full((10, 10), -9999.0, np.float32)
    write_geotiff(tmp_path / "empty.tif", z, scale=(1.0, 1.0), tiepoint=(0.0, 0.0), model_type=1, nodata="-9999")
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
