"""``fedmap run`` end to end on tiny terrain, and its bad-input contract."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fedmap._util import OUTPUT_MARKER
from fedmap.cli import main
from fedmap.maps.dem import Dem
from fedmap.maps.io import load_map
from fedmap.maps.traversability import dem_to_traversability

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = ["--size", "64", "--local-epochs", "2", "--pairs", "5", "--no-central"]


def _run(args, capsys):
    rc = main(["run", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.slow
def test_run_example_builtin_config_tiny(tmp_path, capsys):
    out = tmp_path / "o"
    rc, stdout, err = _run([EXAMPLES / "builtin.toml", *TINY, "--set", "refine.min_size=20", "-o", out], capsys)
    assert rc == 0, err
    assert "wall time" in stdout
    resolved = tomllib.loads((out / "config.toml").read_text())
    assert resolved["terrain"] == {"kind": "builtin", "terrain": "mars", "size": 64}
    assert resolved["train"]["epochs"] == 2 and resolved["refine"]["min_size"] == 20
    assert resolved["evaluate"]["central"] is False and resolved["method"] == "paper"
    assert json.loads((out / "run_config.json").read_text()) == resolved
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["agents"]) == 4 and "central" not in metrics
    assert json.loads((out / "config.json").read_text())["federation"]["local"]["epochs"] == 2
    for name in ("figure.png", "truth.png", "global_map.png", "refined_map.png", "global_model.safetensors"):
        assert (out / name).is_file()
    # the written config reproduces the run byte for byte
    again = tmp_path / "again"
    assert _run([out / "config.toml", "-o", again], capsys)[0] == 0
    m1, m2 = (json.loads((d / "metrics.json").read_text()) for d in (out, again))
    for key in ("global", "refined", "agents", "truth", "bytes", "ledger"):
        assert m1[key] == m2[key]
    assert (again / "global_model.safetensors").read_bytes() == (out / "global_model.safetensors").read_bytes()


def test_run_on_a_dem_file(tmp_path, capsys):
    rng = np.random.default_rng(3)
    z = np.cumsum(np.cumsum(rng.normal(size=(80, 96)), axis=0), axis=1) * 0.02
    asc = tmp_path / "hill.asc"
    body = "\n".join(" ".join(f"{v:.4f}" for v in row) for row in z)
    asc.write_text(f"ncols 96\nnrows 80\nxllcorner 0\nyllcorner 0\ncellsize 1.5\nNODATA_value -9999\n{body}\n")
    out = tmp_path / "o"
    rc, stdout, err = _run(["--dem", asc, "--agents", "2", "--explore", "strips", "--max-slope", "20", *TINY,
                            "-o", out], capsys)
    assert rc == 0, err
    assert "hill.asc, 64x64 cells of 1.88 m" in stdout  # 80 cells of 1.5 m -> 64 cells
    resolved = tomllib.loads((out / "config.toml").read_text())
    assert resolved["terrain"]["kind"] == "dem" and resolved["terrain"]["path"] == str(asc.resolve())
    assert resolved["thresholds"]["max_slope_deg"] == 20.0
    # the truth written is the traversability of the centred square, block-averaged 80 -> 64
    square = z[:, 8:88].astype(np.float32)
    from fedmap.maps.regrid import area_weights

    w = area_weights(80, 64)
    ref = dem_to_traversability(Dem(w @ square @ w.T, 1.875), resolved_thresholds(resolved))
    np.testing.assert_array_equal(load_map(out / "truth.png").classes, ref.classes)


def resolved_thresholds(resolved):
    from fedmap.maps.traversability import TraversabilityThresholds

    return TraversabilityThresholds(**resolved["thresholds"])


@pytest.mark.parametrize("args,message", [
    (["--dem", "nope.tif"], "error: no such file: "),
    (["--terrain", "venus"], "error: unknown terrain kind 'venus'"),
    (["--terrain", "mars", "--dem", "x.tif"], "error: give at most one of --dem, --map and --terrain"),
    (["--terrain", "mars", "--size", "32"], "error: terrain size must be an integer in [64, 4096], got 32"),
    (["--set", "explore.agnets=3"], "error: unknown key 'agnets' in [explore] of the command-line options "
                                    "(did you mean 'agents'?)"),
    (["missing.toml"], "error: no such config file: missing.toml"),
    # a newcomer's slips: each line says what is wrong and what to do
    (["site.tif"], "error: site.tif is not a TOML config (it looks like a terrain file): pass it with --dem (a DEM) "
                   "or --map (a class map)"),
    (["--dem", "notes.tif"], "error: cannot read DEM {tmp}/notes.tif: it is a text file, not a raster (the wrong file?)"),
    (["--dem", "noise.tif"], "error: cannot read DEM {tmp}/noise.tif: GDAL does not recognise it as a raster (a damaged "
                             "file, or not what its .tif name says)"),
    (["--dem", "site.tif", "--size", "-64"], "error: terrain size must be at least 3 cells (the side the map is "
                                             "resampled to), got -64"),
])
def test_bad_run_input_one_line_exit_2(tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    np.save(tmp_path / "dem.npy", np.arange(64 * 64, dtype=np.float32).reshape(64, 64) * 0.01)
    (tmp_path / "site.tif").write_bytes(b"II*\x00" + bytes(range(256)) * 4)  # binary, not TOML (and no raster)
    (tmp_path / "notes.tif").write_text("my notes about the site\nnot a raster\n")
    (tmp_path / "noise.tif").write_bytes(bytes((i * 7919) % 256 for i in range(3000)))
    rc, _, err = _run([*args, "-o", tmp_path / "o"], capsys)
    assert rc == 2
    message = message.replace("{tmp}", str(tmp_path.resolve()))  # --dem paths are made absolute
    assert err.startswith(message) and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_bad_toml_and_earlier_results_kept(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    (out / OUTPUT_MARKER).write_text("")  # an earlier run's folder
    cfg = tmp_path / "run.toml"
    cfg.write_text("[explore]\nagnets = 3\n")
    rc, _, err = _run([cfg, "-o", out], capsys)
    assert rc == 2
    assert err == "error: unknown key 'agnets' in [explore] of run.toml (did you mean 'agents'?)\n"
    assert (out / "metrics.json").read_text() == "{}"
    grey = tmp_path / "grey.png"
    from PIL import Image

    Image.fromarray(np.zeros((70, 70), np.uint8)).save(grey)
    rc, _, err = _run(["--dem", grey, "-o", out], capsys)
    assert rc == 2 and "is a L PNG" in err and err.count("\n") == 1
    np.save(tmp_path / "small.npy", np.zeros((40, 50), np.float32))
    rc, _, err = _run(["--dem", tmp_path / "small.npy", "-o", out], capsys)
    assert rc == 2 and err.startswith("error: the terrain map is 40x40 cells; the pipeline needs a square map of 64..4096")
    assert (out / "metrics.json").read_text() == "{}"


def test_demo_is_run_with_the_demos_defaults(tmp_path, capsys):
    """`fedmap demo` runs the paper and fedmap presets side by side on the same rovers. Its
    paper half and `fedmap run --method paper` build one config and give the same map,
    model bytes and metrics; both start the paper network from the shipped meta-init. Its
    fedmap half equals `fedmap run --method fedmap`."""
    demo, b, c = tmp_path / "demo", tmp_path / "run", tmp_path / "run_fedmap"
    rc, _, err = _run(["--method", "paper", *TINY, "-o", b], capsys)
    assert rc == 0, err
    rc, _, err = _run(["--method", "fedmap", *TINY, "-o", c], capsys)
    assert rc == 0, err
    rc = main(["demo", *TINY, "-o", str(demo)])
    out = capsys.readouterr().out
    assert rc == 0
    a = demo / "paper"
    assert (demo / "fedmap" / "global_model.safetensors").read_bytes() == (c / "global_model.safetensors").read_bytes()
    rows = json.loads((demo / "metrics.json").read_text())["methods"]
    assert [r["method"] for r in rows] == ["paper", "fedmap"]
    for r, run_dir in zip(rows, (b, c)):  # the side-by-side table holds each run's own numbers
        m = json.loads((run_dir / "metrics.json").read_text())
        assert r["f1"] == m["global"]["path"]["f1"] and r["psnr"] == m["global"]["psnr"]
        n_up = sum(len(x["uplink_bytes"]) for x in m["rounds"])
        assert r["uplink_bytes_per_rover_round"] == sum(sum(x["uplink_bytes"].values()) for x in m["rounds"]) / n_up
        assert f"{r['uplink_bytes_per_rover_round']:,.0f}" in out
    assert (demo / "figure.png").stat().st_size > 10_000
    assert (a / "global_model.safetensors").read_bytes() == (b / "global_model.safetensors").read_bytes()
    assert (a / "global_map.png").read_bytes() == (b / "global_map.png").read_bytes()
    ma, mb = (json.loads((p / "metrics.json").read_text()) for p in (a, b))
    for m in (ma, mb):
        m.pop("timings")
        for r in m["rounds"]:
            r.pop("seconds")
    assert ma == mb
    assert json.loads((a / "config.json").read_text())["model"]["init"] == "meta"
    assert (a / "config.toml").read_text() == (b / "config.toml").read_text()


def test_a_percentile_slope_limit_is_reported_in_degrees(tmp_path, capsys):
    """p75 resolves to an angle: the console, metrics.json and config.toml say which, and
    config.toml keeps only the setting that was used."""
    from fedmap.maps.terrain import generate_dem
    from fedmap.maps.traversability import slope_degrees

    dem = generate_dem("moon", 64, seed=1, pixel_size=100.0)
    np.save(tmp_path / "dem.npy", dem.elevation)
    out = tmp_path / "o"
    rc, stdout, err = _run(["--dem", tmp_path / "dem.npy", "--pixel-size", "100", "--max-slope", "p75",
                            "--local-epochs", "1", "--no-central", "--pairs", "3", "-o", out], capsys)
    assert rc == 0, err
    want = float(np.percentile(slope_degrees(dem.elevation, 100.0), 75))  # coarse: the slope test alone
    got = json.loads((out / "metrics.json").read_text())["truth"]["slope_limit_deg"]
    assert got == pytest.approx(want)
    assert f"slope limit {want:.3g} deg (p75 of the map's slopes)" in " ".join(stdout.split())
    saved = tomllib.loads((out / "config.toml").read_text())["thresholds"]
    assert saved["max_slope_percentile"] == 75.0 and "max_slope_deg" not in saved
