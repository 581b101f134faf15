"""``fedmap export`` and ``fedmap run --export/--rover/--max-slope pNN`` end to end."""

from __future__ import annotations

import tomllib
import warnings

import numpy as np
import pytest
import rasterio
import yaml
from affine import Affine

from fedmap.cli import main
from fedmap.maps.grid import GridMap
from fedmap.maps.io import load_map, save_map
from fedmap.maps.traversability import ROVER_PROFILES

TINY = ["--size", "64", "--local-epochs", "2", "--pairs", "5", "--no-central", "--agents", "2", "--explore", "strips"]


def test_export_command_formats(tmp_path, capsys):
    classes = np.random.default_rng(0).integers(0, 3, (20, 30)).astype(np.uint8)
    save_map(GridMap(classes, 0.25, "m"), tmp_path / "m.png")
    for fmt, suffix in (("geotiff", ".tif"), ("ros", ".yaml"), ("npy", ".npy")):
        assert main(["export", str(tmp_path / "m.png"), "--format", fmt]) == 0
        back = load_map(tmp_path / f"m{suffix}", pixel_size=0.25 if fmt == "npy" else None)
        np.testing.assert_array_equal(back.classes, classes)
        assert back.pixel_size == 0.25
    assert (tmp_path / "m.pgm").is_file()
    assert "m.tif: 20x30 cells of 0.25 m" in " ".join(capsys.readouterr().out.split())
    # GeoTIFF -> PNG to another name, then the refusals
    assert main(["export", str(tmp_path / "m.tif"), "-f", "png", "-o", str(tmp_path / "again.png")]) == 0
    np.testing.assert_array_equal(load_map(tmp_path / "again.png").classes, classes)
    capsys.readouterr()
    assert main(["export", str(tmp_path / "m.png"), "-f", "png"]) == 2
    assert main(["export", str(tmp_path / "m.png"), "-f", "shapefile"]) == 2
    err = capsys.readouterr().err
    assert "would overwrite it" in err
    assert "unknown export format 'shapefile'; choose one of geotiff, ros, png, npy, rosbag2" in err


def test_run_with_rover_percentile_and_exports_overlays_the_dem(tmp_path, capsys):
    rng = np.random.default_rng(3)
    z = (np.cumsum(np.cumsum(rng.normal(size=(80, 80)), axis=0), axis=1) * 0.02).astype(np.float32)
    t = Affine(0.5, 0, 300_000.0, 0, -0.5, 4_100_000.0)
    dem_path = tmp_path / "site.tif"
    with warnings.catch_warnings():
        with rasterio.open(dem_path, "w", driver="GTiff", height=80, width=80, count=1, dtype="float32",
                           crs="EPSG:32612", transform=t) as dst:
            dst.write(z, 1)
    out = tmp_path / "o"
    rc = main(["run", "--dem", str(dem_path), "--rover", "msl", "--max-slope", "p80", *TINY, "--export", "geotiff",
               "--export", "ros", "-o", str(out)])
    stdout, err = capsys.readouterr()
    assert rc == 0, err
    resolved = tomllib.loads((out / "config.toml").read_text())
    th = resolved["thresholds"]
    msl = ROVER_PROFILES["msl"].to_dict()
    assert th["rover"] == "msl" and th["max_slope_percentile"] == 80
    assert all(th[k] == v for k, v in msl.items() if k != "max_slope_deg")
    # 80 cells of 0.5 m resampled to 64 cells of 0.625 m, over the same ground
    truth = load_map(out / "truth.tif")
    assert truth.pixel_size == pytest.approx(0.625) and "UTM zone 12N" in truth.crs
    assert truth.transform @ (64, 64) == pytest.approx(t @ (80, 80)) and truth.transform @ (0, 0) == (t.c, t.f)
    np.testing.assert_array_equal(truth.classes, load_map(out / "truth.png").classes)
    for name in ("global_map", "refined_map", "rover0_local", "rover1_local"):
        assert load_map(out / f"{name}.tif").transform == truth.transform
        assert (out / f"{name}.yaml").is_file() and (out / f"{name}.pgm").is_file()
    ros = yaml.safe_load((out / "truth.yaml").read_text())
    assert ros["origin"] == pytest.approx([300_000.0, 4_100_000.0 - 40.0, 0.0]) and ros["resolution"] == 0.625
    # the p80 slope limit leaves (about) a fifth of the cells too steep for the slope test alone
    assert (truth.classes == 1).mean() >= 0.15
    # a bad format stops before the run
    assert main(["run", "--dem", str(dem_path), *TINY, "--export", "kml", "-o", str(tmp_path / "x")]) == 2
    assert "unknown export format 'kml'" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_demo_export_writes_local_frame_geotiffs(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--method", "fedmap", "--size", "64", "--local-epochs", "2", "--pairs", "5", "--no-central",
               "--export", "geotiff", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    truth = load_map(out / "truth.tif")  # built-in terrain: a local metric frame, lower-left corner at (0, 0)
    assert truth.crs is None and truth.transform @ (0, 64) == (0.0, 0.0)
    np.testing.assert_array_equal(truth.classes, load_map(out / "truth.png").classes)
    assert load_map(out / "refined_map.tif").transform == truth.transform


def test_one_class_warning_is_one_printed_line(tmp_path, capsys):
    z = np.zeros((64, 64), np.float32)  # flat: 100% free at any limits
    np.save(tmp_path / "flat.npy", z)
    rc = main(["run", "--dem", str(tmp_path / "flat.npy"), "--pixel-size", "118.45", *TINY, "-o", str(tmp_path / "o")])
    out = capsys.readouterr().out
    assert rc == 0
    lines = [ln for ln in out.splitlines() if ln.startswith("warning:")]
    assert len(lines) == 1 and "100.0% free at 118 m pixels" in lines[0] and lines[0].endswith("coarse DEM)")
