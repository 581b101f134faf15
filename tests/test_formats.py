"""fedmap's own DEM reader (RGB-packed PNG tiles), mosaics, crops and resampling. All on
small files the tests write; the GDAL-read formats are in test_io.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.io import (
    GLD100_PIXEL_SIZE_M,
    centre_crop,
    crop_dem,
    gld100_tile_path,
    load_dem,
    mosaic_heightmap_tiles,
    mosaic_tiles,
    resample_dem,
)
from fedmap.maps.regrid import area_weights


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


# --------------------------------------------------------------------------- RGB-packed heightmap PNG


def pack(metres, offset=10000.0) -> np.ndarray:
    raw = np.asarray(np.rint(np.asarray(metres) + offset), dtype=np.int64)
    return np.stack([raw % 256, (raw // 256) % 256, raw // 65536], axis=-1).astype(np.uint8)


def test_heightmap_png_decoding_against_hand_values(tmp_path):
    rgb = np.zeros((3, 3, 3), dtype=np.uint8)
    rgb[0, 0] = (16, 39, 0)      # 16 + 256*39 = 10000 -> 0 m
    rgb[0, 1] = (0, 0, 1)        # 65536 -> 55536 m
    rgb[0, 2] = (255, 255, 0)    # 65535 -> 55535 m
    rgb[1, 0] = (1, 0, 0)        # 1 -> -9999 m
    rgb[1, 1] = (0, 0, 0)        # 0: gap
    rgb[1, 2] = (200, 3, 2)      # 200 + 768 + 131072 = 132040 -> 122040 m
    rgb[2] = (16, 39, 0)
    path = tmp_path / "t.png"
    Image.fromarray(rgb).save(path)
    dem = load_dem(path, pixel_size=118.0)
    expected = np.array([[0, 55536, 55535], [-9999, np.nan, 122040], [0, 0, 0]], dtype=np.float32)
    np.testing.assert_array_equal(dem.elevation, expected)
    assert dem.pixel_size == 118.0
    kept = load_dem(path, pixel_size=118.0, zero_is_nodata=False, offset=0.0)
    assert kept.elevation[1, 1] == 0.0 and kept.elevation[0, 0] == 10000.0
    assert load_dem(path, nodata=0.0).meta["nodata_cells"] == 5  # 4 zeros in metres + the gap


def test_heightmap_png_refuses_grey_paletted_and_corrupt(tmp_path):
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "grey.png")
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).convert("P").save(tmp_path / "pal.png")
    for name, mode in (("grey.png", "L"), ("pal.png", "P")):
        with pytest.raises(FedmapError, match=f"is a {mode} PNG.*RGB-packed") as exc:
            load_dem(tmp_path / name)
        one_line(exc)
    good = tmp_path / "good.png"
    Image.fromarray(pack(np.full((8, 8), 5.0))).save(good)
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[:40])
    with pytest.raises(FedmapError, match="cut.png: not a valid PNG") as exc:
        load_dem(tmp_path / "cut.png")
    one_line(exc)
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "gap.png")
    with pytest.raises(FedmapError, match="every cell is nodata"):
        load_dem(tmp_path / "gap.png")


def test_mosaic_2x2_gld100_orientation(tmp_path):
    # Each tile's value encodes its (lon, lat); rows within a tile go north->south.
    values = {}
    for lon in (10, 11):
        for lat in (20, 21):
            z = 1000.0 * (lon - 10) + 100.0 * (lat - 20) + np.arange(4)[:, None] * 10.0 + np.zeros((4, 5))
            values[lon, lat] = z
            Image.fromarray(pack(z)).save(gld100_tile_path(tmp_path, lon, lat))
    dem = mosaic_heightmap_tiles(tmp_path, lon=10, lat=20, n=2)
    assert dem.shape == (8, 10) and dem.pixel_size == pytest.approx(118.45, abs=0.01)
    assert GLD100_PIXEL_SIZE_M == pytest.approx(2 * math.pi * 1737400 / 360 / 256)
    np.testing.assert_array_equal(dem.elevation[:4, :5], values[10, 21])   # north-west
    np.testing.assert_array_equal(dem.elevation[:4, 5:], values[11, 21])   # north-east
    np.testing.assert_array_equal(dem.elevation[4:, :5], values[10, 20])   # south-west
    np.testing.assert_array_equal(dem.elevation[4:, 5:], values[11, 20])   # south-east
    # the generic mosaic with an explicit north-first grid is the same thing
    grid = [[gld100_tile_path(tmp_path, 10, 21), gld100_tile_path(tmp_path, 11, 21)],
            [gld100_tile_path(tmp_path, 10, 20), gld100_tile_path(tmp_path, 11, 20)]]
    np.testing.assert_array_equal(mosaic_tiles(grid, pixel_size=1.0).elevation, dem.elevation)
    with pytest.raises(FedmapError, match=r"mosaic tile missing: .*256p\+12\+2[01].png") as exc:
        mosaic_heightmap_tiles(tmp_path, lon=11, lat=20, n=2)
    one_line(exc)
    Image.fromarray(pack(np.zeros((3, 5)))).save(gld100_tile_path(tmp_path, 12, 20))
    with pytest.raises(FedmapError, match="is 3x5"):
        mosaic_tiles([[gld100_tile_path(tmp_path, 11, 20), gld100_tile_path(tmp_path, 12, 20)]])


# --------------------------------------------------------------------------- resample / crop


def dem_of(z, px=2.0) -> Dem:
    return Dem(np.asarray(z, dtype=np.float32), px, "test")


def test_area_resample_matches_block_mean_and_keeps_extent():
    z = np.random.default_rng(0).normal(size=(12, 18)).astype(np.float32)
    out = resample_dem(dem_of(z), (4, 6))
    np.testing.assert_allclose(out.elevation, z.reshape(4, 3, 6, 3).mean(axis=(1, 3)), rtol=1e-5, atol=1e-6)
    assert out.pixel_size == pytest.approx(6.0)  # 12 x 2 m = 4 x 6 m
    # area weights: rows sum to 1, and a non-integer factor splits a cell in two
    w = area_weights(3, 2)
    np.testing.assert_allclose(w, [[2 / 3, 1 / 3, 0], [0, 1 / 3, 2 / 3]])


def test_bilinear_resample_matches_scipy_zoom_and_hand_values():
    z = np.random.default_rng(1).normal(size=(10, 10)).astype(np.float32)
    out = resample_dem(dem_of(z), 25, method="bilinear")
    ref = ndimage.zoom(z.astype(np.float64), 2.5, order=1, mode="nearest", grid_mode=True)
    np.testing.assert_allclose(out.elevation, ref, rtol=1e-5, atol=1e-5)
    # hand: 2x2 -> 4x4, target centres at source coordinates -0.25, 0.25, 0.75, 1.25 (edges clamp)
    up = resample_dem(dem_of([[0, 4, 0], [8, 12, 0], [0, 0, 0]]), 6, method="bilinear").elevation
    assert up[1, 1] == pytest.approx(0.75 * 0.75 * 0 + 0.75 * 0.25 * 4 + 0.25 * 0.75 * 8 + 0.25 * 0.25 * 12)
    assert up[0, 0] == pytest.approx(0.0)


def test_resample_nodata_propagates_by_majority():
    z = np.arange(36, dtype=np.float32).reshape(6, 6)
    z[0, 0] = z[0, 1] = z[1, 0] = np.nan        # 3 of 4 cells of block (0, 0): nodata
    z[4, 4] = np.nan                            # 1 of 4 cells of block (2, 2)
    z[0, 2] = z[0, 3] = np.nan                  # exactly half of block (0, 1): still valid
    out = resample_dem(dem_of(z), 3).elevation
    assert np.isnan(out[0, 0])
    assert out[2, 2] == pytest.approx(np.mean([29, 34, 35]))  # z[4, 4] = 28 is nodata
    assert out[0, 1] == pytest.approx(np.mean([8, 9]))
    assert out[1, 1] == pytest.approx(np.mean([14, 15, 20, 21]))
    assert np.isnan(out).sum() == 1


def test_resample_errors():
    d = dem_of(np.zeros((10, 20)))
    with pytest.raises(FedmapError, match="non-square cells"):
        resample_dem(d, 5)
    with pytest.raises(FedmapError, match="unknown resample method"):
        resample_dem(d, (5, 10), method="cubic")


def test_crop_and_centre_crop():
    z = np.arange(7 * 9, dtype=np.float32).reshape(7, 9)
    d = dem_of(z)
    np.testing.assert_array_equal(crop_dem(d, (1, 4), slice(2, None)).elevation, z[1:4, 2:])
    np.testing.assert_array_equal(centre_crop(d).elevation, z[:, 1:8])
    np.testing.assert_array_equal(centre_crop(d, 3).elevation, z[2:5, 3:6])
    with pytest.raises(FedmapError, match="outside"):
        crop_dem(d, (0, 8), (0, 3))
    with pytest.raises(FedmapError, match="cannot crop 8x8"):
        centre_crop(d, 8)
