"""docs/walkthrough.md runs verbatim: every ``fedmap`` line of its bash blocks, in order, on
two small DEMs this test writes (a UTM GeoTIFF at 5 m and ESRI ASCII at 10 m)."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

from fedmap.cli import main
from fedmap.maps.terrain import generate_dem

PAGE = Path(__file__).resolve().parents[1] / "docs" / "walkthrough.md"


def _commands() -> list[list[str]]:
    blocks = re.findall(r"```bash\n(.*?)```", PAGE.read_text(), flags=re.S)
    lines = [ln.strip() for b in blocks for ln in b.splitlines() if ln.strip().startswith("fedmap ")]
    return [shlex.split(ln)[1:] for ln in lines]


def _write_site(folder: Path) -> np.ndarray:
    z = generate_dem("moon", 64, seed=5, pixel_size=5.0).elevation.astype(np.float32)
    with rasterio.open(folder / "site.tif", "w", driver="GTiff", height=64, width=64, count=1, dtype="float32",
                       crs="EPSG:32612", transform=Affine(5.0, 0, 500_000.0, 0, -5.0, 4_000_000.0)) as dst:
        dst.write(z, 1)
    wide = generate_dem("moon", 64, seed=6, pixel_size=10.0).elevation  # a wider view at 10 m
    header = "ncols 64\nnrows 64\nxllcorner 499840\nyllcorner 3999520\ncellsize 10\nNODATA_value -9999\n"
    rows = "\n".join(" ".join(f"{v:.3f}" for v in row) for row in wide)
    (folder / "site.asc").write_text(header + rows + "\n")
    return z


def test_the_walkthrough_runs_verbatim(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _write_site(tmp_path)
    commands = _commands()
    assert [c[0] for c in commands] == ["run", "run", "export", "export", "mission"]
    outputs = []
    for args in commands:
        rc = main(args)
        captured = capsys.readouterr()
        assert rc == 0, f"fedmap {shlex.join(args)}: {captured.err}"
        outputs.append(captured.out)
    # what the page says each step shows
    first = " ".join(outputs[0].split())
    limit = json.loads((tmp_path / "out/site/metrics.json").read_text())["truth"]["slope_limit_deg"]
    assert f"slope limit {limit:.3g} deg (p75 of the map's slopes)" in first
    assert "64x64 cells of 5 m" in first
    for name in ("truth.png", "refined_map.png", "rover0_local.png", "figure.png", "config.toml"):
        assert (tmp_path / "out/site" / name).is_file(), name
    assert "64x64 cells of 10 m" in " ".join(outputs[1].split())
    with rasterio.open(tmp_path / "out/site/refined_map.tif") as src:  # what QGIS opens
        assert src.crs.to_epsg() == 32612 and src.transform.a == 5.0
    assert (tmp_path / "out/site/map.yaml").is_file() and (tmp_path / "out/site/map.pgm").is_file()
    report = (tmp_path / "out/mission/report.md").read_text()
    for words in ("team bytes up", "belief acc. at step 0", "uplinks not delivered", "Best map:"):
        assert words in report, words
    saved = (tmp_path / "out/mission/mission.toml").read_text()
    assert "rovers = 3" in saved and 'rover = "cadre"' in saved and "max_slope_percentile = 75.0" in saved
