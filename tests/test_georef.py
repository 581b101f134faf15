"""Georeferencing carried through: crop and resample keep cell centres on the same ground
coordinates, and class GeoTIFFs hold classes, colour table, CRS and transform (read back
with rasterio, GDAL's own reader)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.georef import body_radii, cell_centre, cell_size_m, crs_wkt
from fedmap.maps.geotiff import CLASS_COLORMAP
from fedmap.maps.grid import GridMap
from fedmap.maps.io import load_map, save_map
from fedmap.maps.regrid import centre_crop, crop_dem, resample_dem
from fedmap.maps.sources import TerrainSource, load_truth

UTM = "EPSG:32612"


def geo_dem(h=40, w=40, px=2.0) -> Dem:
    z = np.random.default_rng(1).normal(size=(h, w)).astype(np.float32)
    return Dem(z, px, "geo", transform=Affine(px, 0, 500_000.0, 0, -px, 4_000_000.0), crs=crs_wkt(UTM))


def test_crop_keeps_ground_coordinates():
    dem = geo_dem()
    c = crop_dem(dem, (5, 25), (7, 33))
    for r, col in ((0, 0), (3, 11), (19, 25)):
        assert cell_centre(c.transform, r, col) == cell_centre(dem.transform, r + 5, col + 7)
    np.testing.assert_array_equal(c.elevation[3, 11], dem.elevation[8, 18])
    cc = centre_crop(dem, 10)
    assert cell_centre(cc.transform, 0, 0) == cell_centre(dem.transform, 15, 15) and cc.crs == dem.crs


def test_resample_keeps_extent_and_maps_centres_to_the_same_ground():
    dem = geo_dem()
    half = resample_dem(dem, 20)  # 2x2 blocks: new cell (i, j) covers old cells 2i..2i+1
    # the centre of new cell (i, j) is the shared corner of old cells (2i, 2j) .. (2i+1, 2j+1)
    for i, j in ((0, 0), (7, 12), (19, 19)):
        x, y = cell_centre(half.transform, i, j)
        assert (x, y) == pytest.approx(dem.transform @ (2 * j + 1, 2 * i + 1))
    # extent kept: the far corner is the same
    assert half.transform @ (20, 20) == pytest.approx(dem.transform @ (40, 40))
    assert half.pixel_size == pytest.approx(4.0) and abs(half.transform.a) == pytest.approx(4.0)
    up = resample_dem(dem, 80, method="bilinear")
    assert up.transform @ (80, 80) == pytest.approx(dem.transform @ (40, 40))
    # crop then resample: a cell centre is where the source puts it
    cr = resample_dem(crop_dem(dem, (10, 30), (4, 24)), 10)
    assert cell_centre(cr.transform, 2, 3) == pytest.approx(dem.transform @ (4 + 2 * 3 + 1, 10 + 2 * 2 + 1))


def test_class_map_source_crop_and_resize_keep_the_transform(tmp_path):
    grid = GridMap(np.random.default_rng(2).integers(0, 3, (30, 40)).astype(np.uint8), 2.0, "g",
                   transform=Affine(2.0, 0, 1000.0, 0, -2.0, 9000.0), crs=crs_wkt(UTM))
    save_map(grid, tmp_path / "g.tif")
    truth = load_truth(TerrainSource(kind="map", path=str(tmp_path / "g.tif"), size=15))
    # centred 30x30 square from column 5, then 30 -> 15 cells
    assert truth.pixel_size == pytest.approx(4.0)
    assert truth.transform @ (0, 0) == pytest.approx(grid.transform @ (5, 0))
    assert truth.transform @ (15, 15) == pytest.approx(grid.transform @ (35, 30))
    assert truth.crs == grid.crs


def test_class_geotiff_round_trip_with_gdal():
    grid = GridMap(np.random.default_rng(3).integers(0, 3, (17, 23)).astype(np.uint8), 2.0, "g",
                   transform=Affine(2.0, 0, 500_000.0, 0, -2.0, 4_000_000.0), crs=crs_wkt(UTM))
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "map.tif"
        save_map(grid, path)
        with rasterio.open(path) as src:  # what QGIS sees
            assert src.dtypes == ("uint8",) and src.count == 1 and src.crs.to_epsg() == 32612
            assert src.transform == grid.transform
            np.testing.assert_array_equal(src.read(1), grid.classes)
            cmap = src.colormap(1)
            assert all(cmap[c] == CLASS_COLORMAP[c] for c in (0, 1, 2))
            assert cmap[0] == (0, 255, 0, 255) and cmap[1] == (255, 0, 0, 255)  # free green, impassable red
        back = load_map(path)
        np.testing.assert_array_equal(back.classes, grid.classes)
        assert back.pixel_size == 2.0 and back.transform == grid.transform and back.crs == grid.crs
        # same map, same bytes
        save_map(grid, Path(d) / "again.tif")
        assert (Path(d) / "again.tif").read_bytes() == path.read_bytes()


def test_geotiff_of_ungeoreferenced_map_is_a_local_metric_frame(tmp_path):
    grid = GridMap(np.zeros((4, 6), np.uint8), 0.5, "gen")
    save_map(grid, tmp_path / "m.tif")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = load_map(tmp_path / "m.tif")
    assert back.crs is None and back.pixel_size == 0.5
    assert back.transform @ (0, 4) == (0.0, 0.0)  # lower-left corner at the origin


def test_body_radii_sphere_and_wgs84_by_hand():
    m, n = body_radii("IAU_2015:30100", 45.0)
    assert m == n == pytest.approx(1_737_400.0)
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    m, n = body_radii("EPSG:4326", 0.0)
    assert n == pytest.approx(a) and m == pytest.approx(a * (1 - e2))
    dx, dy, info = cell_size_m("IAU_2015:30100", Affine(1 / 256, 0, 0, 0, -1 / 256, 1.0), (256, 256))
    assert dy == pytest.approx(math.radians(1 / 256) * 1_737_400.0)  # the GLD100 118.45 m
    assert dx == pytest.approx(dy * math.cos(math.radians(0.5)))
    with pytest.raises(FedmapError, match="not a coordinate reference system"):
        crs_wkt("EPSG:999999")


def test_a_runs_png_maps_keep_their_place_on_the_body(tmp_path, capsys):
    """The README pairs `fedmap export truth.png --format geotiff` with "overlays its DEM in
    QGIS": a run's PNGs carry the truth's CRS and transform (text chunks, and a GDAL .aux.xml
    sidecar that QGIS reads), and exporting one keeps them, as rasterio reads it back."""
    from fedmap.cli import main
    from fedmap.maps.terrain import generate_dem

    dem = geo_dem(64, 64, 2.0)
    z = generate_dem("mars", 64, seed=2, pixel_size=2.0).elevation.astype(np.float32)
    with rasterio.open(tmp_path / "site.tif", "w", driver="GTiff", height=64, width=64, count=1, dtype="float32",
                       crs=UTM, transform=dem.transform) as dst:
        dst.write(z, 1)
    out = tmp_path / "run"
    rc = main(["run", "--dem", str(tmp_path / "site.tif"), "--max-slope", "p75", "--local-epochs", "1",
               "--no-central", "--pairs", "3", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    for name in ("truth.png", "refined_map.png", "rover0_local.png"):
        with rasterio.open(out / name) as src:  # GDAL reads the sidecar: what QGIS sees
            assert src.crs.to_epsg() == 32612 and src.transform == dem.transform, name
    rc = main(["export", str(out / "truth.png"), "--format", "geotiff", "-o", str(tmp_path / "truth.tif")])
    assert rc == 0
    said = capsys.readouterr().out
    assert "no georeferencing" not in said and "georeferenced (transform and CRS)" in said
    rc = main(["export", str(out / "truth.png"), "--format", "npy", "-o", str(tmp_path / "truth.npy")])
    said = " ".join(capsys.readouterr().out.split())
    assert rc == 0 and "not georeferenced: npy holds no georeferencing" in said and "georeferenced (" not in said
    with rasterio.open(tmp_path / "truth.tif") as src:
        assert src.crs.to_epsg() == 32612 and src.transform == dem.transform
        truth = load_map(out / "truth.png")
        np.testing.assert_array_equal(src.read(1), truth.classes)
    # a map in a local frame writes no sidecar
    save_map(GridMap(np.zeros((4, 4), np.uint8), 1.0, "local"), tmp_path / "local.png")
    assert not (tmp_path / "local.png.aux.xml").exists() and load_map(tmp_path / "local.png").transform is None


def test_cell_of_is_the_inverse_of_cell_centre():
    """A point falls in the cell whose centre the forward transform gives, anywhere in the
    cell; by hand on a north-up grid whose lower-left corner is (1, 2) m, cells of 0.5 m and
    64 rows: (6.1, 4.85) m is column 10, row (2 + 32 - 4.85) / 0.5 = 58.3, so row 58."""
    from affine import Affine

    from fedmap.maps.georef import cell_centre, cell_of

    t = Affine(0.5, 0.0, 1.0, 0.0, -0.5, 2.0 + 64 * 0.5)
    assert cell_of(t, 6.1, 4.85) == (58, 10)
    rng = np.random.default_rng(5)
    for row, col in rng.integers(0, 64, (20, 2)):
        x, y = cell_centre(t, row, col)
        dx, dy = rng.uniform(-0.24, 0.24, 2)
        assert cell_of(t, x + dx, y + dy) == (row, col)
    assert cell_of(t, 0.9, 4.85) == (58, -1)  # left of the grid: outside, not clamped
