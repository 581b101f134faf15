"""The readers on the real DEMs in ``../shared/data`` (skipped where the folder is absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.io import load_dem, mosaic_heightmap_tiles

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real terrain data not found at {DATA}")


def data_file(rel: str) -> Path:
    path = DATA / rel
    if not path.exists():
        pytest.skip(f"{path} not found")
    return path


@needs_data
@pytest.mark.parametrize("name", ["DEM_10m", "zSW3", "hugo_site", "west_bijou_gully", "kootenai_1m",
                                  "pre_runout_DEM", "bijou_gully_5m"])
def test_projected_ascii_grids(name):
    path = data_file(f"earth/{name}.asc")
    header = dict(line.split()[:2] for line in path.read_text().splitlines()[:5])
    cell = float({k.lower(): v for k, v in header.items()}["cellsize"])
    dem = load_dem(path)
    assert dem.pixel_size == pytest.approx(cell)
    assert np.isfinite(dem.elevation).sum() > 0.2 * dem.elevation.size
    assert -100 < np.nanmin(dem.elevation) < np.nanmax(dem.elevation) < 9000  # metres, nodata gone


@needs_data
def test_geographic_ascii_grid_boulder():
    path = data_file("earth/srtmgl3_boulder_a.asc")
    with pytest.raises(FedmapError, match="looks like degrees"):
        load_dem(path)  # no .prj: the grid's unit is not in the file
    dem = load_dem(path, crs="EPSG:4326")
    # 3 arc-seconds on WGS84 at 40.15 N, by hand: prime-vertical radius N = a / sqrt(1 - e2 sin^2),
    # meridional M = a (1 - e2) / (1 - e2 sin^2)^1.5; east-west N cos(lat), north-south M
    a, f, lat = 6378137.0, 1 / 298.257223563, np.radians(40.150417)
    e2 = f * (2 - f)
    w = np.sqrt(1 - e2 * np.sin(lat) ** 2)
    dx, dy = np.radians(3 / 3600) * a / w * np.cos(lat), np.radians(3 / 3600) * a * (1 - e2) / w**3
    assert dem.pixel_size == pytest.approx(dx, rel=1e-6)  # 71.0 m; rows resampled to it
    assert dem.shape == (round(144 * dy / dx), 240)
    assert 1500 < np.nanmin(dem.elevation) < np.nanmax(dem.elevation) < 4400  # Boulder, Colorado foothills


@needs_data
def test_mola_megdr_raw_big_endian():
    dem = load_dem(data_file("mars/mola_megt90n000cb.img"), shape=(720, 1440), dtype="int16", byteorder="big")
    z = dem.elevation
    r, c = np.unravel_index(np.nanargmax(z), z.shape)
    lat, lon = 90 - (r + 0.5) / 4, (c + 0.5) / 4
    # Olympus Mons: 18.65 N, 226.2 E, about 21.2 km above the areoid
    assert abs(lat - 18.65) < 2 and abs(lon - 226.2) < 2
    assert 20_500 < z[r, c] < 22_000
    # Hellas floor is the lowest, around -8 km; the south polar plateau is ~5 km above the north
    assert -8_500 < np.nanmin(z) < -7_500
    assert z[-4:].mean() - z[:4].mean() > 4_000


@needs_data
def test_gld100_hadley_8x8_mosaic():
    dem = mosaic_heightmap_tiles(data_file("moon/gld100_256p"), lon=0, lat=22, n=8)
    z = dem.elevation
    assert z.shape == (2048, 2048) and np.isfinite(z).all()
    assert dem.pixel_size == pytest.approx(118.45, abs=0.01)
    assert 3_000 < np.ptp(z) < 10_000  # mare, rille and Apennine massifs
    # georeferenced on the Moon sphere: the north-west corner is (0 E, 30 N), 256 cells per degree
    assert dem.transform @ (0, 0) == (0.0, 30.0) and dem.transform @ (2048, 2048) == (8.0, 22.0)
    assert "Moon" in dem.crs
    # Orientation: across a tile seam neighbouring rows/columns differ as little as inside a
    # tile; a flipped tile would put its far edge at the seam.
    for k in range(1, 8):
        s = 256 * k
        inside = np.abs(z[s - 2] - z[s - 1]).mean()
        assert np.abs(z[s - 1] - z[s]).mean() < 2 * inside
        inside_c = np.abs(z[:, s - 2] - z[:, s - 1]).mean()
        assert np.abs(z[:, s - 1] - z[:, s]).mean() < 2 * inside_c


@needs_data
def test_gld100_gap_tile_is_nodata():
    gaps = sorted(data_file("moon/gld100_256p").glob("256p+170+*.png"))
    if not gaps:
        pytest.skip("no lon >= 160 tiles")
    with pytest.raises(FedmapError, match="every cell is nodata"):
        load_dem(gaps[0], pixel_size=118.45)


@needs_data
def test_gale_geotiff():
    dem = load_dem(data_file("mars/missionDEM_gale_1m.tif"))
    assert dem.shape == (337, 348) and dem.pixel_size == pytest.approx(1.0, rel=0.01)
    assert dem.meta["pixel_size_from"] == "crs" and "Mars" in (dem.crs or "")  # Mars2000 equidistant cylindrical
    assert -4_600 < np.nanmin(dem.elevation) < np.nanmax(dem.elevation) < -4_300  # Gale floor, below datum


@needs_data
def test_lzw_geotiff():
    """Mt Mongón is LZW-compressed; compared with Pillow's independent TIFF decoder."""
    from PIL import Image

    path = data_file("earth/mongon_dem.tif")
    with Image.open(path) as img:
        assert img.info.get("compression") == "tiff_lzw"
        raw = np.asarray(img)
    dem = load_dem(path)
    assert dem.shape == raw.shape == (117, 117)
    assert dem.pixel_size == pytest.approx(30.85, abs=0.01)
    valid = np.isfinite(dem.elevation)
    np.testing.assert_allclose(dem.elevation[valid], raw[valid].astype(np.float32))
    assert 0 < np.nanmin(dem.elevation) < np.nanmax(dem.elevation) < 2000  # a coastal massif (~1,100 m), metres
