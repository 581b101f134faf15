"""A run's GeoTIFF output overlays the DEM it came from: a figure and the measured offset.

    python benchmarks/georef_overlay.py [--data ../shared/data] [--out benchmarks/results/georef_overlay]

The Gale crater HiRISE 1 m DEM is cropped off-centre (rows 40..290, cols 60..310) and
resampled to 100 x 100 cells (2.5 m), classified, and written with ``save_map`` as a
class GeoTIFF. Both files are then read back with rasterio alone (GDAL's reader, not
fedmap's), and the class map is drawn over the DEM's hillshade, each placed by its own
geotransform. The offset is measured too: each class cell's centre, mapped into the
DEM's pixel grid, must land on the centre of the 2.5 x 2.5 block of DEM cells it was
made from. Writes ``overlay.png`` and ``overlay.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import rasterio

from fedmap.maps.grid import render_classes
from fedmap.maps.io import save_map
from fedmap.maps.sources import TerrainSource, load_truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/georef_overlay"))
    args = ap.parse_args()
    dem_path = args.data / "mars/missionDEM_gale_1m.tif"
    r0, r1, c0, c1 = 40, 290, 60, 310
    truth = load_truth(TerrainSource(kind="dem", path=str(dem_path), crop=(r0, r1, c0, c1), size=100))
    args.out.mkdir(parents=True, exist_ok=True)
    save_map(truth, args.out / "truth.tif")
    with rasterio.open(dem_path) as dem, rasterio.open(args.out / "truth.tif") as cls:
        z, dem_t, dem_crs = dem.read(1, masked=True).filled(np.nan), dem.transform, dem.crs
        classes, cls_t, cls_crs = cls.read(1), cls.transform, cls.crs
    # offset: class cell (i, j) centre -> DEM pixel coordinates; expected block centre
    rows, cols = np.mgrid[0:100, 0:100]
    x, y = cls_t @ (cols + 0.5, rows + 0.5)
    dcol, drow = ~dem_t @ (x, y)
    step = (r1 - r0) / 100
    err = np.hypot(dcol - (c0 + (cols + 0.5) * step), drow - (r0 + (rows + 0.5) * step))
    record = {"dem": dem_path.name, "crop": [r0, r1, c0, c1], "cells": 100, "cell_m": truth.pixel_size,
              "same_crs": bool(dem_crs == cls_crs), "max_offset_dem_pixels": float(err.max()),
              "max_offset_m": float(err.max() * abs(dem_t.a))}
    print(json.dumps(record))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource

    shade = LightSource(azdeg=315, altdeg=45).hillshade(np.nan_to_num(z, nan=np.nanmean(z)), dx=1.0, dy=1.0)
    h, w = z.shape
    dem_extent = (dem_t.c, dem_t.c + w * dem_t.a, dem_t.f + h * dem_t.e, dem_t.f)
    cls_extent = (cls_t.c, cls_t.c + 100 * cls_t.a, cls_t.f + 100 * cls_t.e, cls_t.f)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=110)
    ax.imshow(shade, cmap="gray", extent=dem_extent, interpolation="nearest")
    ax.imshow(render_classes(classes), extent=cls_extent, alpha=0.45, interpolation="nearest")
    ax.plot([cls_extent[0], cls_extent[1], cls_extent[1], cls_extent[0], cls_extent[0]],
            [cls_extent[2], cls_extent[2], cls_extent[3], cls_extent[3], cls_extent[2]], "k-", lw=0.8)
    ax.set_title(f"Gale 1 m DEM hillshade with truth.tif (100 x 100 cells of {truth.pixel_size:g} m) placed by its own\n"
                 f"geotransform: max offset {record['max_offset_m']:.2g} m", fontsize=8)
    ax.set_xlabel("x (m, Mars equidistant cylindrical)", fontsize=8)
    ax.set_ylabel("y (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(args.out / "overlay.png")
    (args.out / "overlay.json").write_text(json.dumps(record, indent=1))
    (args.out / "truth.tif").unlink()  # the figure and JSON are the result; the GeoTIFF is rebuilt on each run
    print(f"wrote {args.out}/overlay.png, overlay.json")


if __name__ == "__main__":
    main()
