"""Maps out of a mission: the final global maps and beliefs as GridMaps in the truth's frame
(:func:`fedmap.mission.mission_maps`), written as GeoTIFF / ROS / PNG
(:func:`fedmap.mission.write_mission_maps`), and ``fedmap export <mission folder>``."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.crs import CRS
from typer.testing import CliRunner

from conftest import maze
from fedmap.cli import app, main
from fedmap.errors import FedmapError
from fedmap.maps.grid import UNKNOWN
from fedmap.maps.io import load_map
from fedmap.maps.sources import TerrainSource
from fedmap.mission import LinkConfig, MissionConfig, mission_maps, mission_terrain, run_mission, write_mission_maps

GALE = Path(__file__).resolve().parents[2] / "shared" / "data" / "mars" / "missionDEM_gale_1m.tif"
CONFIG = MissionConfig(rovers=2, steps=20, sync_every=5, sensor_radius=4.0, eval_pairs=5,
                       strategies=("none", "raw"), link=LinkConfig(loss=0.0))


def _finals(result) -> dict[str, np.ndarray]:
    """What the maps must hold, by name, straight from the frames: every strategy's last
    global map that holds a cell, and every rover's last belief."""
    out = {}
    for name, run in result.runs.items():
        last = run.frames[-1]
        if (last.global_map != UNKNOWN).any():
            out[f"{name}_global"] = last.global_map
        out |= {f"{name}_rover{k}": b for k, b in enumerate(last.beliefs)}
    return out


@pytest.fixture(scope="module")
def gale():
    """A 20-step mission on a 48x48 crop of the Gale DEM (2 m cells, Mars2000 CRS); frames=1
    keeps only step 0 and the last step, as a mission without animation does."""
    if not GALE.is_file():
        pytest.skip(f"needs the Gale DEM (real terrain data) at {GALE}")
    truth, elevation, _, _ = mission_terrain(CONFIG, TerrainSource(kind="dem", path=str(GALE), crop=96, size=48))
    assert truth.transform is not None and truth.crs  # the CRS check below means something
    return run_mission(CONFIG, truth, elevation=elevation, frames=1)


@pytest.fixture(scope="module")
def builtin():
    """The same mission on a 32x32 maze: no data needed, no georeferencing."""
    return run_mission(CONFIG, maze(32, 3), frames=1)


def test_mission_maps_are_the_last_frames_in_the_truths_frame(gale):
    truth = gale.truth
    maps = mission_maps(gale, beliefs=True)
    # none's base receives nothing: its all-unknown global map is left out, its beliefs are not
    assert not (gale.runs["none"].frames[-1].global_map != UNKNOWN).any()
    assert list(maps) == ["none_rover0", "none_rover1", "raw_global", "raw_rover0", "raw_rover1"]
    assert list(mission_maps(gale)) == ["raw_global"]
    assert all(run.frames[-1].step == CONFIG.steps for run in gale.runs.values())  # frames=1 keeps the last step
    assert set(_finals(gale)) == set(maps)
    for key, want in _finals(gale).items():
        g = maps[key]
        np.testing.assert_array_equal(g.classes, want)
        assert (g.pixel_size, g.transform, g.crs) == (truth.pixel_size, truth.transform, truth.crs)
        assert not set(g.layers) - {"classes"}  # the truth's elevation is not carried over
    assert (maps["raw_global"].classes != UNKNOWN).mean() > 0.1  # raw's base holds what the rovers saw


def test_written_geotiff_and_ros_round_trip(gale, tmp_path):
    written = write_mission_maps(gale, tmp_path, beliefs=True)
    names = {p.name for p in written}
    maps_dir = tmp_path / "maps"
    for stem in ("raw_global", "raw_rover0", "raw_rover1", "none_rover0", "none_rover1"):
        assert {f"{stem}.png", f"{stem}.tif", f"{stem}.yaml", f"{stem}.pgm"} <= names
    assert not any(n.startswith("none_global") for n in names)
    assert all(p.parent == maps_dir and p.is_file() for p in written)
    truth = gale.truth
    for stem, want in _finals(gale).items():
        # the GeoTIFF as GDAL reads it: the classes cell for cell, the truth's CRS and transform
        with rasterio.open(maps_dir / f"{stem}.tif") as src:
            np.testing.assert_array_equal(src.read(1), want)
            assert src.crs == CRS.from_wkt(truth.crs)
            assert src.transform == truth.transform
        # ROS map_server YAML + PGM and the PNG back through fedmap's reader
        ros = load_map(maps_dir / f"{stem}.yaml")
        np.testing.assert_array_equal(ros.classes, want)
        assert ros.pixel_size == pytest.approx(truth.pixel_size)
        np.testing.assert_array_equal(load_map(maps_dir / f"{stem}.png").classes, want)


def test_formats_are_checked_before_anything_is_written(builtin, tmp_path):
    with pytest.raises(FedmapError, match="unknown export format 'kml'"):
        write_mission_maps(builtin, tmp_path, formats=("png", "kml"))
    assert not (tmp_path / "maps").exists()
    assert [p.name for p in write_mission_maps(builtin, tmp_path, formats=("npy",))] == ["raw_global.npy"]


def test_a_global_map_that_holds_nothing_is_left_out():
    """Not only none's: raw over a link that loses everything has an all-unknown base map too."""
    lost = run_mission(replace(CONFIG, strategies=("raw",), link=LinkConfig(loss=1.0)), maze(32, 3), frames=1)
    assert list(mission_maps(lost, beliefs=True)) == ["raw_rover0", "raw_rover1"]


def test_export_a_mission_folder(builtin, tmp_path):
    folder = tmp_path / "mission"
    write_mission_maps(builtin, folder, beliefs=True, formats=("geotiff",))
    want = _finals(builtin)
    runner = CliRunner()
    r = runner.invoke(app, ["export", str(folder), "--format", "ros"])
    assert r.exit_code == 0, r.output
    for stem, classes in want.items():
        assert (folder / "maps" / f"{stem}.pgm").is_file() and f"{stem}.yaml" in r.output
        back = load_map(folder / "maps" / f"{stem}.yaml")
        np.testing.assert_array_equal(back.classes, classes)
        # built-in terrain: the GeoTIFF's local metric frame, lower-left corner at (0, 0)
        assert back.transform == load_map(folder / "maps" / f"{stem}.tif").transform
    # -o DIR: into another folder, which is made
    r = runner.invoke(app, ["export", str(folder), "-f", "png", "-o", str(tmp_path / "png")])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "png").iterdir() if p.suffix == ".png") == sorted(f"{s}.png" for s in want)
    np.testing.assert_array_equal(load_map(tmp_path / "png" / "raw_global.png").classes, want["raw_global"])


def test_export_folder_refusals_are_one_line(builtin, tmp_path, capsys):
    runner = CliRunner()
    bare = tmp_path / "bare"
    bare.mkdir()
    r = runner.invoke(app, ["export", str(bare), "--format", "ros"])
    assert r.exit_code != 0 and "has no maps/ folder" in str(r.exception)
    assert main(["export", str(bare), "--format", "ros"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "has no maps/ folder" in err
    # a GeoTIFF exported as geotiff into its own folder would overwrite itself: refused, nothing written
    folder = tmp_path / "mission"
    write_mission_maps(builtin, folder, formats=("geotiff",))
    before = {p.name: p.stat().st_mtime_ns for p in (folder / "maps").iterdir()}
    assert main(["export", str(folder), "--format", "geotiff"]) == 2
    assert "would overwrite it; pass -o DIR" in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in (folder / "maps").iterdir()} == before
    (folder / "maps" / "raw_global.tif").unlink()
    assert main(["export", str(folder), "--format", "ros"]) == 2
    assert "holds no map" in capsys.readouterr().err
