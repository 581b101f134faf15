"""ROS map_server maps: a round trip, and YAML + PGM written here from the format's
specification (ROS map_server docs: p = (255 - x) / 255, or x / 255 with negate;
occupied if p > occupied_thresh, free if p < free_thresh, else unknown; row 0 = top)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml  # PyYAML (installed with the test extras): an independent YAML reader and writer
from affine import Affine
from PIL import Image

from fedmap.errors import FedmapError
from fedmap.maps.georef import crs_wkt
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.io import load_map, save_map
from fedmap.maps.ros import parse_map_yaml


def pgm_p5(values: np.ndarray) -> bytes:
    """A binary PGM (P5) by hand: header, then one byte per pixel, row 0 first."""
    h, w = values.shape
    return f"P5\n{w} {h}\n255\n".encode() + values.astype(np.uint8).tobytes()


def test_round_trip_classes_origin_and_trinary_values(tmp_path):
    rng = np.random.default_rng(0)
    classes = rng.integers(0, 3, (12, 9)).astype(np.uint8)
    t = Affine(0.5, 0, 100.0, 0, -0.5, 206.0)  # lower-left corner (100, 200)
    grid = GridMap(classes, 0.5, "g", transform=t, crs=crs_wkt("EPSG:32612"))
    save_map(grid, tmp_path / "map.yaml")
    # the files as map_server reads them
    doc = yaml.safe_load((tmp_path / "map.yaml").read_text())
    assert doc == {"image": "map.pgm", "mode": "trinary", "resolution": 0.5, "origin": [100.0, 200.0, 0.0],
                   "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196}
    with Image.open(tmp_path / "map.pgm") as img:
        assert img.format == "PPM" and img.mode == "L"
        pix = np.asarray(img)
    np.testing.assert_array_equal(pix, np.choose(classes, [254, 0, 205]))  # free 254, occupied 0, unknown 205
    back = load_map(tmp_path / "map.yaml")
    np.testing.assert_array_equal(back.classes, classes)
    assert back.pixel_size == 0.5 and back.transform == t


def test_geographic_map_gets_a_zero_origin(tmp_path):
    grid = GridMap(np.zeros((4, 4), np.uint8), 100.0, "moon",
                   transform=Affine(0.01, 0, 10, 0, -0.01, 20), crs=crs_wkt("IAU_2015:30100"))
    save_map(grid, tmp_path / "m.yaml")
    assert yaml.safe_load((tmp_path / "m.yaml").read_text())["origin"] == [0.0, 0.0, 0.0]


def spec_map(tmp_path, *, negate=0, mode="trinary", occ=0.65, free=0.25, block=False):
    """A 2x4 map and its YAML, written from the spec with PyYAML (block or flow style)."""
    values = np.array([[0, 60, 100, 128], [200, 205, 230, 255]], dtype=np.uint8)
    (tmp_path / "img.pgm").write_bytes(pgm_p5(values))
    doc = {"image": "img.pgm", "resolution": 0.05, "origin": [-1.5, 2.0, 0.0], "negate": negate,
           "occupied_thresh": occ, "free_thresh": free, "mode": mode}
    text = yaml.safe_dump(doc, default_flow_style=False if block else None)
    (tmp_path / "m.yaml").write_text("# written by hand\n" + text)
    return values, tmp_path / "m.yaml"


def expected_classes(values, negate, occ, free, raw=False):
    out = np.empty(values.shape, np.uint8)
    for idx, v in np.ndenumerate(values):
        if raw:
            p = v / 100.0
            out[idx] = UNKNOWN if v > 100 else (IMPASSABLE if p > occ else FREE if p < free else UNKNOWN)
            continue
        p = v / 255.0 if negate else (255.0 - v) / 255.0
        out[idx] = IMPASSABLE if p > occ else FREE if p < free else UNKNOWN
    return out


@pytest.mark.parametrize("negate", [0, 1])
@pytest.mark.parametrize("mode", ["trinary", "scale"])
@pytest.mark.parametrize("block", [False, True])
def test_spec_written_map_reads_by_the_spec(tmp_path, negate, mode, block):
    values, path = spec_map(tmp_path, negate=negate, mode=mode, block=block)
    g = load_map(path)
    np.testing.assert_array_equal(g.classes, expected_classes(values, negate, 0.65, 0.25))
    # by hand for negate 0: 0 -> p 1 occupied; 60 -> 0.76 occupied; 100 -> 0.61 unknown; 128 -> 0.50 unknown;
    # 200 -> 0.216 free; 205 -> 0.196 free (with free_thresh 0.25!); 230, 255 free
    if negate == 0:
        assert g.classes.tolist() == [[1, 1, 2, 2], [0, 0, 0, 0]]
    assert g.pixel_size == 0.05
    # row 0 is the top: the lower-left cell's lower-left corner is the origin
    assert g.transform @ (0, 2) == pytest.approx((-1.5, 2.0))


def test_raw_mode_and_thresholds(tmp_path):
    values, path = spec_map(tmp_path, mode="raw", occ=0.5, free=0.1)
    g = load_map(path)
    np.testing.assert_array_equal(g.classes, expected_classes(values, 0, 0.5, 0.1, raw=True))
    assert g.classes.tolist() == [[0, 1, 1, 2], [2, 2, 2, 2]]  # 0 free, 60/100 occupied, >100 unknown


def test_parse_map_yaml_minimal_reader_agrees_with_pyyaml():
    text = ("image: 'my map.pgm'  # comment\nresolution: 0.050000\norigin: [-12.5, 3, 0.0]\nnegate: 0\n"
            "occupied_thresh: 0.65\nfree_thresh: 0.196\nmode: trinary\n")
    assert parse_map_yaml(text) == yaml.safe_load(text)
    block = yaml.safe_dump({"image": "a.pgm", "origin": [1.0, 2.0, 0.5], "resolution": 1})
    assert parse_map_yaml(block) == yaml.safe_load(block)


def test_bad_ros_maps_are_one_line_errors(tmp_path):
    (tmp_path / "a.yaml").write_text("image: missing.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    with pytest.raises(FedmapError, match="image .*missing.pgm not found") as exc:
        load_map(tmp_path / "a.yaml")
    assert "\n" not in str(exc.value)
    (tmp_path / "img.pgm").write_bytes(pgm_p5(np.zeros((2, 2))))
    (tmp_path / "b.yaml").write_text("image: img.pgm\nresolution: fast\n")
    with pytest.raises(FedmapError, match="resolution must be a number"):
        load_map(tmp_path / "b.yaml")
    (tmp_path / "c.yaml").write_text("image: img.pgm\nresolution: 1\nmode: fancy\n")
    with pytest.raises(FedmapError, match="mode must be one of trinary, scale, raw"):
        load_map(tmp_path / "c.yaml")
