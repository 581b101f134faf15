"""Tests for the named layers of fedmap.maps.grid.GridMap ("classes", an optional "elevation", and a
new layer declared by one LAYER_SPECS entry)."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
from affine import Affine

from fedmap.errors import FedmapError
from fedmap.explore import ExploreConfig
from fedmap.maps.grid import FREE, IMPASSABLE, LAYER_SPECS, LAYERS, UNKNOWN, GridMap, LayerSpec
from fedmap.maps.io import load_map, save_map


def _map(shape=(12, 17), seed=0) -> GridMap:
    rng = np.random.default_rng(seed)
    return GridMap(rng.integers(0, 3, size=shape).astype(np.uint8), 0.5, "layers", {"note": "x"},
                   transform=Affine(0.5, 0.0, 100.0, 0.0, -0.5, 200.0))


def test_classes_is_always_a_layer_and_elevation_only_when_present():
    assert LAYERS == ("classes", "elevation")
    assert list(_map().layers) == ["classes"]
    z = np.linspace(0, 1, 12 * 17).reshape(12, 17)
    g = _map().with_layer("elevation", z)
    assert list(g.layers) == ["classes", "elevation"] and g.layers["elevation"] is g.layer("elevation")
    assert g.layers["elevation"].dtype == np.float32 and np.allclose(g.layers["elevation"], z)
    assert _map().layers.get("elevation") is None


def test_layers_classes_is_the_same_data_as_classes():
    grid = _map()
    assert grid.layers["classes"] is grid.classes
    assert grid.layer("classes") is grid.classes
    grid.classes[0, 0] = IMPASSABLE  # in-place edits show through, as before
    assert grid.layers["classes"][0, 0] == IMPASSABLE


def test_layers_mapping_is_read_only():
    grid = _map()
    with pytest.raises(TypeError):
        grid.layers["classes"] = np.zeros(grid.shape, np.uint8)  # type: ignore[index]


def test_with_layer_rejects_wrong_shape_naming_layer_and_both_shapes():
    grid = _map((12, 17))
    with pytest.raises(FedmapError) as exc:
        grid.with_layer("classes", np.zeros((17, 12), np.uint8))
    msg = str(exc.value)
    assert "\n" not in msg
    assert "'classes'" in msg and "17x12" in msg and "12x17" in msg


def test_with_layer_keeps_class_checks():
    grid = _map()
    with pytest.raises(FedmapError, match="classes"):
        grid.with_layer("classes", np.full(grid.shape, 3, np.uint8))
    with pytest.raises(FedmapError, match="integer"):
        grid.with_layer("classes", np.zeros(grid.shape, np.float32))


def test_with_layer_unknown_name_is_refused():
    with pytest.raises(FedmapError, match="'slope'.*"):
        _map().with_layer("slope", np.zeros((12, 17), np.float32))


def test_elevation_layer_checks_and_travels_with_the_classes():
    grid = _map()
    with pytest.raises(FedmapError, match="'elevation' has shape 3x3, but the map is 12x17"):
        grid.with_layer("elevation", np.zeros((3, 3)))
    with pytest.raises(FedmapError, match="infinite"):
        grid.with_layer("elevation", np.full(grid.shape, np.inf))
    with pytest.raises(FedmapError, match="heights in metres"):
        grid.with_layer("elevation", np.full(grid.shape, "x"))
    z = np.full(grid.shape, np.nan)
    z[2:5, 3:9] = 12.5
    g = grid.with_layer("elevation", z)
    assert "elevation" not in grid.layers  # the original untouched
    moved = g.with_classes(np.zeros(grid.shape, np.uint8))
    assert moved.layers["elevation"] is g.layers["elevation"]  # carried along
    assert np.isnan(moved.layer("elevation")[0, 0]) and moved.layer("elevation")[3, 4] == 12.5


def test_with_layer_returns_a_new_map_with_the_rest_kept():
    grid = _map()
    new = np.full(grid.shape, FREE, np.int64)
    out = grid.with_layer("classes", new)
    assert out is not grid
    assert out.classes.dtype == np.uint8
    np.testing.assert_array_equal(out.layer("classes"), new)
    assert set(np.unique(grid.classes)) == {FREE, IMPASSABLE, UNKNOWN}  # original untouched
    assert (out.pixel_size, out.source, out.meta, out.transform, out.crs) == \
        (grid.pixel_size, grid.source, grid.meta, grid.transform, grid.crs)
    assert out.meta is not grid.meta


def test_missing_layer_error_lists_available_layers():
    with pytest.raises(FedmapError) as exc:
        _map().layer("elevation")
    msg = str(exc.value)
    assert "\n" not in msg
    assert "'elevation'" in msg and "available layers: classes" in msg


@pytest.mark.parametrize("suffix", [".npy", ".png"])
def test_layers_survive_save_and_load(tmp_path, suffix):
    grid = _map((23, 31), seed=4)
    path = tmp_path / f"m{suffix}"
    save_map(grid, path)
    back = load_map(path)
    assert list(back.layers) == list(grid.layers)
    assert back.layer("classes").dtype == np.uint8
    np.testing.assert_array_equal(back.layers["classes"], grid.layers["classes"])


def test_constructor_takes_the_other_layers_checked_and_in_registry_order():
    z = np.arange(12 * 17, dtype=np.float64).reshape(12, 17)
    g = GridMap(np.zeros((12, 17), np.uint8), 0.5, layers={"elevation": z})
    assert list(g.layers) == ["classes", "elevation"] and g.layers["elevation"].dtype == np.float32
    with pytest.raises(FedmapError, match="layer 'elevation' has shape 3x3, but the map is 12x17"):
        GridMap(np.zeros((12, 17), np.uint8), layers={"elevation": np.zeros((3, 3))})
    with pytest.raises(FedmapError, match="'slop'.*"):
        GridMap(np.zeros((12, 17), np.uint8), layers={"slop": z})
    with pytest.raises(FedmapError, match="first argument"):  # the classes are not given twice
        GridMap(g.classes, layers=g.layers)


def test_a_map_with_layers_pickles_and_copies():
    g = _map().with_layer("elevation", np.ones((12, 17)))
    for back in (pickle.loads(pickle.dumps(g)), copy.deepcopy(g)):
        assert list(back.layers) == ["classes", "elevation"] and back.layers["classes"] is back.classes
        np.testing.assert_array_equal(back.layer("elevation"), g.layer("elevation"))


def _slopes(a: np.ndarray, what: str) -> np.ndarray:
    if not np.issubdtype(a.dtype, np.number):
        raise FedmapError(f"{what} must hold slopes in degrees, got {a.dtype}")
    if (a[~np.isnan(a)] > 90).any():
        raise FedmapError(f"{what} holds slopes above 90 degrees")
    return a


def test_a_new_layer_is_one_registry_entry(monkeypatch):
    """Declaring a layer in LAYER_SPECS is all a map needs to hold, check and carry it,
    and for a run's rovers to observe it."""
    with pytest.raises(FedmapError, match="unknown map layer 'slope'"):
        _map().with_layer("slope", np.zeros((12, 17)))
    monkeypatch.setitem(LAYER_SPECS, "slope", LayerSpec("slope", np.float16, float("nan"), _slopes))
    grid = _map()
    s = np.linspace(0, 45, 12 * 17).reshape(12, 17)
    g = grid.with_layer("slope", s).with_layer("elevation", np.zeros((12, 17)))
    assert list(g.layers) == ["classes", "elevation", "slope"]  # registry order, whatever the order set
    assert g.layer("slope").dtype == np.float16 and np.allclose(g.layer("slope"), s, atol=0.05)
    moved = g.with_classes(np.full(g.shape, FREE, np.uint8))
    assert moved.layers["slope"] is g.layers["slope"] and list(moved.layers) == list(g.layers)
    assert list(GridMap(grid.classes, layers={"slope": s}).layers) == ["classes", "slope"]
    with pytest.raises(FedmapError, match="layer 'slope' has shape 3x3, but the map is 12x17"):
        grid.with_layer("slope", np.zeros((3, 3)))
    with pytest.raises(FedmapError, match="layer 'slope' holds slopes above 90 degrees"):
        grid.with_layer("slope", np.full(grid.shape, 91.0))
    with pytest.raises(FedmapError, match="layer 'slope' must hold slopes in degrees, got bool"):
        GridMap(grid.classes, layers={"slope": np.ones(grid.shape, bool)})
    # the rovers of a run observe it: the truth's slopes where they saw, the unknown value elsewhere
    truth = GridMap(np.zeros((32, 32), np.uint8), 1.0).with_layer("slope", np.full((32, 32), 10.0))
    for m in ExploreConfig(agents=4, layers=("classes", "slope")).local_maps(truth, seed=0):
        got = m.layer("slope")
        assert np.all(got[m.known] == 10.0) and np.all(np.isnan(got[~m.known])) and m.known.any()
