"""Terrain sources: built-in, DEM files, class maps and tiles -> ground-truth maps."""

from __future__ import annotations

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import GridMap
from fedmap.maps.io import save_map
from fedmap.maps.sources import TerrainSource, load_source_dem, load_truth
from fedmap.maps.terrain import generate_dem
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability


def test_builtin_matches_generator():
    t = TraversabilityThresholds(max_slope_deg=12.0)
    truth = load_truth(TerrainSource(terrain="ice", size=64, thresholds=t), seed=5)
    ref = dem_to_traversability(generate_dem("ice", 64, seed=5), t)
    np.testing.assert_array_equal(truth.classes, ref.classes)
    assert TerrainSource().size == 128  # built-in default side


def test_dem_source_squares_crops_and_block_means(tmp_path):
    rng = np.random.default_rng(0)
    z = np.cumsum(rng.normal(size=(128, 160)), axis=1).astype(np.float32)
    np.save(tmp_path / "d.npy", z)
    src = TerrainSource(kind="dem", path=str(tmp_path / "d.npy"), size=64, options={"pixel_size": 0.5})
    dem = load_source_dem(src)
    # reference: the centred 128 x 128 square, then 2 x 2 block means
    ref = z[:, 16:144].reshape(64, 2, 64, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(dem.elevation, ref, rtol=1e-5, atol=1e-4)
    assert dem.pixel_size == 1.0
    truth = load_truth(src)
    np.testing.assert_array_equal(truth.classes, dem_to_traversability(Dem(ref, 1.0)).classes)
    # a crop box, squared inside itself (rows 10..50 x cols 20..100 -> cols 40..80)
    boxed = load_source_dem(TerrainSource(kind="dem", path=str(tmp_path / "d.npy"), crop=(10, 50, 20, 100)))
    np.testing.assert_array_equal(boxed.elevation, z[10:50, 40:80])


def test_map_source_crops_and_resamples_by_nearest(tmp_path):
    classes = np.random.default_rng(1).integers(0, 3, size=(96, 128)).astype(np.uint8)
    save_map(GridMap(classes, 0.5), tmp_path / "m.png")
    truth = load_truth(TerrainSource(kind="map", path=str(tmp_path / "m.png"), size=48))
    # centred square = cols 16..112; target cell i has centre (i + 0.5) * 2 -> source cell 2i + 1
    np.testing.assert_array_equal(truth.classes, classes[1::2, 17:112:2])
    assert truth.pixel_size == 1.0


def test_round_trip_and_errors(tmp_path):
    src = TerrainSource(kind="tiles", path="t", lon=3, lat=4, tiles=2, crop=[0, 4, 0, 4], size=64,
                        options={"offset": 0.0})
    d = src.to_dict()
    assert d["crop"] == [0, 4, 0, 4] and "terrain" not in d
    assert TerrainSource.from_dict(d) == src
    with pytest.raises(FedmapError, match="unknown key 'sise' in terrain source \\(did you mean 'size'\\?\\)"):
        TerrainSource.from_dict({"kind": "dem", "path": "x", "sise": 3})
    with pytest.raises(FedmapError, match="crop does not apply to built-in terrain"):
        TerrainSource(crop=64)
    with pytest.raises(FedmapError, match="needs a path"):
        TerrainSource(kind="dem")
    with pytest.raises(FedmapError, match="needs lon and lat"):
        TerrainSource(kind="tiles", path="t")
    with pytest.raises(FedmapError, match="unknown reader option 'shap'"):
        TerrainSource(kind="dem", path="x", options={"shap": [1, 2]})
    np.save(tmp_path / "d.npy", np.zeros((40, 40), np.float32))
    with pytest.raises(FedmapError, match="crop 50 is larger than the 40x40"):
        load_truth(TerrainSource(kind="dem", path=str(tmp_path / "d.npy"), crop=50))
    with pytest.raises(FedmapError, match="no such file"):
        load_truth(TerrainSource(kind="dem", path=str(tmp_path / "missing.tif")))
    with pytest.raises(FedmapError, match="do not apply to heightmap tiles"):
        load_truth(TerrainSource(kind="tiles", path=str(tmp_path), lon=0, lat=0, options={"nodata": 1.0}))
