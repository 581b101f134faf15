"""Rover profiles and percentile slope limits on real DEMs: class fractions and a figure.

    python benchmarks/rover_profiles.py [--data ../shared/data] [--out benchmarks/results/rover_profiles]

Row 1: the Gale crater HiRISE 1 m DEM (central 256 x 256 m) classified with the generic
default limits and with each rover profile (``cadre``, ``mer``, ``msl``). Row 2: two
coarse DEMs (MOLA 14.8 km over Tharsis, GLD100 2x2 tiles resampled to 237 m) with the fixed 15 deg
default and with ``max_slope_percentile=75`` (the ``--max-slope p75`` of ``fedmap run``).
Writes ``rover_profiles.png`` and ``rover_profiles.json`` (fractions, slope limits used,
the one-class warnings, seconds per classification). Needs the data folder; the package
never does.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from fedmap.maps.dem import Dem
from fedmap.maps.grid import render_classes
from fedmap.maps.io import load_dem, mosaic_heightmap_tiles
from fedmap.maps.regrid import centre_crop, resample_dem
from fedmap.maps.traversability import ROVER_PROFILES, TraversabilityThresholds, dem_to_traversability


def classify(dem, thresholds, label):
    t0 = time.perf_counter()
    g = dem_to_traversability(dem, thresholds)
    seconds = time.perf_counter() - t0
    f = g.fractions()
    return g, {"label": label, "dem": Path(dem.source).name, "pixel_size_m": dem.pixel_size, "shape": list(dem.shape),
               "free": f["free"], "impassable": f["impassable"], "unknown": f["unknown"],
               "slope_limit_deg": g.meta["slope_limit_deg"], "thresholds": thresholds.to_dict(),
               "warning": g.meta.get("warning"), "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/rover_profiles"))
    args = ap.parse_args()
    gale = centre_crop(load_dem(args.data / "mars/missionDEM_gale_1m.tif"), 256)
    rows = [[(gale, TraversabilityThresholds(), "Gale 1 m: default")]
            + [(gale, t, f"Gale 1 m: {name}") for name, t in ROVER_PROFILES.items()]]
    mola = load_dem(args.data / "mars/mola_megt90n000cb.img", shape=(720, 1440), dtype="int16", byteorder="big")
    mola = Dem(mola.elevation[200:328, 360:488], 14_800.0, mola.source)  # 128 x 128 cells of 1/4 deg
    gld = resample_dem(mosaic_heightmap_tiles(args.data / "moon/gld100_256p", lon=0, lat=22, n=2), 256)
    coarse = [(mola, "MOLA 14.8 km"), (gld, "GLD100 237 m")]
    rows.append([(d, TraversabilityThresholds(), f"{n}: 15 deg") for d, n in coarse]
                + [(d, TraversabilityThresholds(max_slope_percentile=75), f"{n}: p75") for d, n in coarse])
    records, maps = [], []
    for row in rows:
        maps.append([])
        for dem, t, label in row:
            g, rec = classify(dem, t, label)
            records.append(rec)
            maps[-1].append((label, g, rec))
            print(f"{label:24s} {dem.pixel_size:9.2f} m  free {rec['free']:6.1%}  impassable {rec['impassable']:6.1%}  "
                  f"slope limit {rec['slope_limit_deg']:6.2f} deg  {rec['seconds'] * 1000:7.1f} ms"
                  + (f"  WARNING {rec['warning']}" if rec["warning"] else ""))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncol = max(len(r) for r in maps)
    fig, axes = plt.subplots(len(maps), ncol, figsize=(2.6 * ncol, 3.2 * len(maps)), dpi=110, squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for row_axes, row in zip(axes, maps):
        for ax, (label, g, rec) in zip(row_axes, row):
            ax.imshow(render_classes(g.classes), interpolation="nearest")
            ax.set_title(f"{label}\n{rec['impassable']:.1%} impassable, slope {rec['slope_limit_deg']:.3g} deg",
                         fontsize=7)
    fig.suptitle("Traversability: rover profiles at rover scale (top), fixed vs percentile slope limit on orbital DEMs",
                 fontsize=8)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "rover_profiles.png")
    (args.out / "rover_profiles.json").write_text(json.dumps(records, indent=1, default=float))
    print(f"wrote {args.out}/rover_profiles.png, rover_profiles.json")


if __name__ == "__main__":
    main()
