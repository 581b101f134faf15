"""Every ```python block of the docs and the README runs as written (in a scratch folder,
with the ``gale.tif`` the running page's snippet reads written there first)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from fedmap.maps.terrain import generate_dem

ROOT = Path(__file__).resolve().parents[1]
PAGES = [*sorted((ROOT / "docs").rglob("*.md")), ROOT / "README.md"]
SNIPPETS = [(p.relative_to(ROOT), i, code) for p in PAGES
            for i, code in enumerate(re.findall(r"```python\n(.*?)```", p.read_text(), flags=re.S))]


def test_the_docs_have_python_snippets():
    assert len(SNIPPETS) >= 2  # the walk below would pass vacuously without them


@pytest.mark.parametrize("page, index, code", SNIPPETS, ids=[f"{p}#{i}" for p, i, _ in SNIPPETS])
def test_a_docs_python_snippet_runs(page, index, code, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    z = generate_dem("mars", 300, seed=3, pixel_size=1.0).elevation.astype(np.float32)
    with rasterio.open(tmp_path / "gale.tif", "w", driver="GTiff", height=300, width=300, count=1, dtype="float32",
                       crs="EPSG:32612", transform=Affine(1.0, 0, 0.0, 0, -1.0, 300.0)) as dst:
        dst.write(z, 1)
    exec(compile(code, f"{page} python block {index}", "exec"), {"__name__": "__snippet__"})
