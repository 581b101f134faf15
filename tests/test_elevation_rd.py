"""``fedmap bandwidth --layer elevation``: the fewest bytes before the re-derived classes are
good enough to plan on (path F1 >= 0.9), the percentile slope limit resolved once on the
true heights, and ``--dem`` (the user's own DEM as the terrain, or a one-line error).

The "bytes to F1" figures are checked against values worked out by hand from hand-built
points, and against a brute force over seeded random points."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from fedmap.cli import main
from fedmap.experiments.elevation import (
    F1_TARGET,
    FAMILIES,
    Point,
    bytes_to_f1,
    elevation_markdown,
    summarise,
    terrain_sources,
    winner,
)
from fedmap.maps.dem import Dem
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, resolved_slope

#: A fast run: small map, few path pairs, short neural fits (with :func:`_one_small_net`).
FAST = ["--size", "32", "--pairs", "8", "--neural-steps", "20"]


@pytest.fixture
def _one_small_net(monkeypatch):
    """One tiny neural height field instead of three (its fixed 300 QAT steps dominate a small run)."""
    import fedmap.experiments.elevation as elevation

    monkeypatch.setattr(elevation, "NEURAL_SIZES", ((4, 8),))


def _pt(codec: str, n_bytes: int, f1: float, terrain: str = "t", setting: str | None = None) -> Point:
    if setting is None:  # LERC's setting names its max error, which a neural+residual point must match
        setting = f"max err {n_bytes} m" if codec == "lerc" else f"{codec} {n_bytes}"
    return Point(terrain, codec, setting, n_bytes, 8.0 * n_bytes / 100, 0.1, 0.2, f1)


def _hand_points() -> list[Point]:
    return [
        # jxl: F1 not monotone in bytes; the smallest reaching point is 500 B, the next smaller 300 B
        _pt("jxl", 1200, 0.99), _pt("jxl", 300, 0.50), _pt("jxl", 800, 0.85), _pt("jxl", 500, 0.95),
        # lossless: only the exact point reaches, exactly at the target (>= counts)
        _pt("lossless", 4000, 0.90), _pt("lossless", 1500, 0.89),
        # lerc: never reaches
        _pt("lerc", 2000, 0.80), _pt("lerc", 900, 0.40),
        # j2k: its smallest point reaches, nothing below it
        _pt("j2k", 700, 1.0), _pt("j2k", 1100, 0.92),
    ]


def test_bytes_to_f1_by_hand():
    reach = bytes_to_f1(_hand_points())
    assert reach["lerc"] is None
    jxl, lossless, j2k = reach["jxl"], reach["lossless"], reach["j2k"]
    assert jxl is not None and lossless is not None and j2k is not None
    assert (jxl.bytes, jxl.below, jxl.path_f1, jxl.setting) == (500, 300, 0.95, "jxl 500")
    assert (lossless.bytes, lossless.below) == (4000, 1500)
    assert (j2k.bytes, j2k.below) == (700, None)
    assert winner(reach) == "jxl"
    # a stricter target: jxl needs its 1200 B point, j2k its 700 B one, which now wins
    strict = bytes_to_f1(_hand_points(), target=0.97)
    assert strict["jxl"] is not None and strict["jxl"].bytes == 1200 and strict["jxl"].below == 800
    assert winner(strict) == "j2k"


@pytest.mark.parametrize("seed", range(5))
def test_bytes_to_f1_matches_a_brute_force(seed):
    rng = np.random.default_rng(seed)
    pts = [_pt(str(rng.choice(FAMILIES)), int(b), float(f))
           for b, f in zip(rng.choice(np.arange(10, 10_000), 30, replace=False), rng.random(30))]
    reach = bytes_to_f1(pts)
    for fam in {p.codec for p in pts}:
        ok = [p.bytes for p in pts if p.codec == fam and p.path_f1 >= F1_TARGET]
        r = reach[fam]
        if not ok:
            assert r is None
            continue
        assert r is not None and r.bytes == min(ok)
        under = [p.bytes for p in pts if p.codec == fam and p.bytes < min(ok)]
        assert r.below == (max(under) if under else None)
    hits = {f: min(p.bytes for p in pts if p.codec == f and p.path_f1 >= F1_TARGET)
            for f in {p.codec for p in pts if p.path_f1 >= F1_TARGET}}
    assert winner(reach) == (min(hits, key=hits.__getitem__) if hits else None)


def test_not_reached_when_no_point_reaches():
    pts = [_pt(f, 100 * (i + 1), 0.2 + 0.1 * i, setting="n, max err 200 m" if f == "neural+residual" else None)
           for i, f in enumerate(FAMILIES)]  # F1 0.2 .. 0.7
    sm = summarise(pts)["t"]
    assert sm["bytes_to_f1"] == dict.fromkeys(FAMILIES) and sm["winner_at_f1"] is None
    md = elevation_markdown({"points": [p.to_dict() for p in pts], "summary": summarise(pts)})
    row = next(line for line in md.splitlines() if line.startswith("| t | not reached"))
    assert row.count("not reached") == len(FAMILIES) and row.endswith("| none |")


def test_summary_and_markdown_carry_the_reach_and_winner():
    pts = _hand_points() + [_pt("neural", 3000, 0.3), _pt("neural+residual", 3500, 0.36, setting="n, max err 900 m"),
                            _pt("lerc", 3600, 0.97, terrain="u")]
    sm = summarise(pts)
    assert sm["t"]["bytes_to_f1"]["jxl"]["bytes"] == 500 and sm["t"]["winner_at_f1"] == "jxl"
    # the neural+residual point's ratio to LERC at the same max error, with both path F1s
    (vs,) = sm["t"]["neural_residual_vs_lerc"]
    assert (vs["ratio"], vs["path_f1"], vs["lerc_path_f1"]) == (pytest.approx(3500 / 900), 0.36, 0.40)
    assert sm["u"]["winner_at_f1"] == "lerc" and sm["u"]["bytes_to_f1"] == {"lerc": sm["u"]["bytes_to_f1"]["lerc"]}
    md = elevation_markdown({"points": [p.to_dict() for p in pts], "summary": sm})
    t_row = next(line for line in md.splitlines() if line.startswith("| t | "))
    # lossless, lerc, jxl, j2k, neural, neural+residual, wins
    assert t_row == "| t | 4,000 | not reached | 500 | 700 | not reached | not reached | jxl |"
    assert "| u | - | 3,600 | - | - | - | - | lerc |" in md  # "-": the family was not measured there


def _sloped_dem(n: int = 40) -> Dem:
    rng = np.random.default_rng(1)
    z = np.cumsum(np.cumsum(rng.normal(size=(n, n)), axis=0), axis=1) * 0.05
    return Dem(z.astype(np.float32), 1.0)


def test_a_percentile_limit_is_resolved_once_on_the_truth():
    dem = _sloped_dem()
    p75 = TraversabilityThresholds(max_slope_percentile=75.0)
    truth = dem_to_traversability(dem, p75)
    t = resolved_slope(p75, truth)
    assert t.max_slope_percentile is None and t.max_slope_deg == pytest.approx(truth.meta["slope_limit_deg"])
    np.testing.assert_array_equal(dem_to_traversability(dem, t).classes, truth.classes)
    # flattened heights: the resolved degrees find fewer steep cells; a percentile of the
    # flattened map's own slopes would still call a quarter of them steep
    flat = Dem((dem.elevation * 0.5).astype(np.float32), dem.pixel_size)
    steep_deg = (dem_to_traversability(flat, t).classes == 1).mean()
    steep_pct = (dem_to_traversability(flat, p75).classes == 1).mean()
    assert steep_deg < steep_pct - 0.1
    degrees = TraversabilityThresholds(max_slope_deg=20.0)
    assert resolved_slope(degrees, truth) is degrees


def test_every_decoded_map_is_classified_with_the_truths_degrees(monkeypatch, _one_small_net):
    import fedmap.experiments.elevation as elevation

    used: list[TraversabilityThresholds | None] = []

    def spy(dem, thresholds=None):
        used.append(thresholds)
        return dem_to_traversability(dem, thresholds)

    monkeypatch.setattr(elevation, "dem_to_traversability", spy)
    dem = _sloped_dem(32)
    p75 = TraversabilityThresholds(max_slope_percentile=75.0)
    points = elevation.terrain_rd("s", dem, thresholds=p75, pairs=4, neural_steps=2)
    want = dem_to_traversability(dem, p75).meta["slope_limit_deg"]
    assert used[0] == p75 and len(used) == 1 + len(points)
    assert all(t is not None and t.max_slope_percentile is None and t.max_slope_deg == want for t in used[1:])


def test_terrain_sources_take_size_and_thresholds():
    p75 = TraversabilityThresholds(max_slope_percentile=75.0)
    src = terrain_sources(None, size=64, thresholds=p75)
    assert list(src) == ["mars", "moon", "ice"]  # the real terrains need a data folder
    assert all(s.size == 64 and s.thresholds == p75 for s in src.values())
    assert terrain_sources(None)["mars"].size == 128


def _write_geotiff(path, z: np.ndarray, px: float = 1.0) -> None:
    with warnings.catch_warnings():
        with rasterio.open(path, "w", driver="GTiff", height=z.shape[0], width=z.shape[1], count=1, dtype="float32",
                           crs="EPSG:32612", transform=Affine(px, 0, 300_000.0, 0, -px, 4_100_000.0)) as dst:
            dst.write(z.astype(np.float32), 1)


def test_dem_runs_alone_and_reports_that_terrain(tmp_path, capsys, _one_small_net):
    z = _sloped_dem(48).elevation
    z[:3, :3] = np.nan  # nodata survives the trip
    dem_path = tmp_path / "my_site.tif"
    _write_geotiff(dem_path, z, px=0.5)
    out = tmp_path / "o"
    rc = main(["bandwidth", "--layer", "elevation", "--dem", str(dem_path), "--max-slope", "p75", *FAST, "-o", str(out)])
    stdout, err = capsys.readouterr()
    assert rc == 0, err
    report = json.loads((out / "elevation.json").read_text())
    assert list(report["summary"]) == ["my_site"] and {p["terrain"] for p in report["points"]} == {"my_site"}
    exact = next(p for p in report["points"] if p["setting"] == "float32")
    # exact heights re-derive the truth's classes: the p75 limit was resolved on the truth, not re-taken
    assert exact["rmse_m"] == 0 and exact["path_f1"] == 1.0
    sm = report["summary"]["my_site"]
    assert sm["bytes_to_f1"]["lossless"]["bytes"] <= exact["bytes"] and sm["winner_at_f1"] in FAMILIES
    assert "my_site" in " ".join(stdout.split())
    assert "| my_site |" in (out / "report.md").read_text()
    assert {p["codec"] for p in report["points"]} == set(FAMILIES)


@pytest.mark.parametrize("case", ["missing", "folder", "text", "with_data", "classes_layer"])
def test_a_bad_dem_is_a_one_line_error(tmp_path, capsys, case):
    bad = {"missing": tmp_path / "nope.tif", "folder": tmp_path, "text": tmp_path / "notes.tif"}.get(case)
    if case == "text":
        bad.write_text("not a raster\n")
    args = ["bandwidth", "--layer", "elevation", "--dem", str(bad or tmp_path / "x.tif"), *FAST, "-o",
            str(tmp_path / "o")]
    if case in ("with_data", "classes_layer"):
        _write_geotiff(tmp_path / "x.tif", _sloped_dem(32).elevation)
        args += ["--data", str(tmp_path)] if case == "with_data" else ["--layer", "classes"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
