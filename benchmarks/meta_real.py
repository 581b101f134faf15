"""Meta-initialisation on real terrain: Reptile on Earth DEM tiles, Table I on other worlds.

    python benchmarks/meta_real.py [--data ../shared/data] [--out benchmarks/results/meta_real]

1. Training collection: the Earth GeoTIFFs in ``data/earth/`` cut into 64x64 tiles at their
   native resolution, one category per source/landform (Zion canyons 90 m, Mt Mongon
   volcanic massif 31 m, New Zealand ranges 1 km, Big Tujunga San Gabriel mountains 30 m).
2. Reptile from the empty-map prior with the ``fedmap meta-train`` defaults.
3. Table I (``fedmap.meta.ablation``) on out-of-distribution test sets: Moon GLD100 tiles
   (118 m), Mars Gale crater 1 m DEM, MOLA global topography (14.8 km, +-60 deg latitude),
   glacier DEMs (20-100 m). Adam lr 1e-4 (the paper's), N = 2 steps, plus lr 1e-3.

Traversability thresholds: the Gale DEM is at rover scale and uses the package defaults
(slope 15 deg, step 0.3 m, roughness 0.15 m). Every other source is 20 m to 15 km per
pixel, where a 15 deg limit marks almost nothing, so its slope limit is the 75th
percentile of its own slope (about a quarter of the cells impassable); the limit used
for each source is written to the JSON.

Needs the data folder (CI has it at ../shared/data); the package itself never does.
Several GeoTIFFs are LZW-compressed and need ``pip install imagecodecs`` to load.
The defaults (150 Reptile iterations, 8 test maps per set, cap 80 steps) are what the
README reports; the Earth meta-init is kept as ``benchmarks/results/meta_real_earth.safetensors``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from fedmap.maps.dem import Dem
from fedmap.maps.io import load_dem, mosaic_heightmap_tiles
from fedmap.maps.traversability import TraversabilityThresholds, slope_degrees
from fedmap.meta.ablation import AblationConfig, make_inits, pick_maps, run_ablation, write_ablation
from fedmap.meta.collections import MapCollection, dem_tiles
from fedmap.meta.reptile import MetaConfig, meta_train
from fedmap.nets.model import build_model, preset, save_model, set_weights
from fedmap.outputs import to_json

SIZE = 64
QUANTILE = 0.75
MARS_RADIUS_M = 3389.5e3


def quantile_thresholds(dem: Dem) -> TraversabilityThresholds:
    """Slope limit = the DEM's own 75th slope percentile (coarse DEMs, see module doc)."""
    z = dem.elevation
    s = slope_degrees(np.where(np.isfinite(z), z, np.nanmean(z)), dem.pixel_size)[np.isfinite(z)]
    return TraversabilityThresholds(max_slope_deg=float(np.clip(np.quantile(s, QUANTILE), 0.01, 89.0)))


def tiles(dem: Dem, *, rover_scale: bool = False, stride: int | None = None) -> tuple[list, dict]:
    th = TraversabilityThresholds() if rover_scale else quantile_thresholds(dem)
    return dem_tiles(dem, SIZE, th, stride=stride), {"source": dem.source, "pixel_size_m": dem.pixel_size,
                                                     "max_slope_deg": th.max_slope_deg}


def earth(data: Path) -> tuple[MapCollection, list]:
    e = data / "earth"
    sources = {"canyon (zion_srtm)": (e / "zion_srtm.tif", None),
               "volcanic (mongon_dem)": (e / "mongon_dem.tif", 16),  # 117x117: overlapping tiles
               "ranges (nz_elev)": (e / "nz_elev.tif", None),
               "mountains (bigtujunga)": (e / "bigtujunga.tif", None)}
    cats, info = {}, []
    for name, (path, stride) in sources.items():
        cats[name], i = tiles(load_dem(path), stride=stride)
        info.append({"category": name, "tiles": len(cats[name]), **i})
    return MapCollection("earth DEM tiles", cats), info


def mola(data: Path) -> Dem:
    px = 2 * np.pi * MARS_RADIUS_M / 1440  # one pixel = 1/4 degree along the equator
    z = load_dem(data / "mars/mola_megt90n000cb.img", shape=(720, 1440), dtype="int16", byteorder="big",
                 pixel_size=px).elevation
    # +-60 deg latitude (rows 120..600): no polar caps, and equal-angle pixels are within
    # a factor 2 of square there.
    return Dem(z[120:600], px, "MOLA MEGDR 4 px/deg, lat +-60")


def test_sets(data: Path) -> dict[str, tuple[list, list]]:
    out: dict[str, tuple[list, list]] = {}
    moon = data / "moon/gld100_256p"
    maps, info = [], []
    for lon, lat in [(0, 22), (3, 25), (6, 28), (14, 22), (17, 25), (20, 28), (30, 9), (60, 3), (90, 15), (120, 30)]:
        m, i = tiles(mosaic_heightmap_tiles(moon, lon=lon, lat=lat, n=1))
        maps += m
        info.append(i)
    out["Moon GLD100 (118 m)"] = (maps, info)
    m, i = tiles(load_dem(data / "mars/missionDEM_gale_1m.tif"), rover_scale=True)
    out["Mars Gale (1 m)"] = (m, [i])
    m, i = tiles(mola(data))
    out["Mars MOLA (14.8 km)"] = (m, [i])
    maps, info = [], []
    for p in sorted((data / "ice").glob("*.tif")):
        if "thickness" in p.name:
            continue  # an ice-thickness raster, not a DEM
        m, i = tiles(load_dem(p))
        maps += m
        info.append(i)
    out["glaciers (20-100 m)"] = (maps, info)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/meta_real"))
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--maps", type=int, default=8, help="test maps per test set")
    ap.add_argument("--max-steps", type=int, default=80)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"data folder {args.data} not found (pass --data)")
    torch.set_num_threads(args.threads)
    net = preset("paper")
    t0 = time.perf_counter()
    coll, earth_info = earth(args.data)
    train, val = coll.split(holdout=2, seed=0)
    mconf = MetaConfig(iterations=args.iterations)
    log = lambda it, info: print(f"  reptile {it}/{mconf.iterations} val {info['val_psnr']:.2f} dB", flush=True) \
        if "val_psnr" in info else None
    print(f"earth: {coll.n_maps} tiles {[(c['category'], c['tiles'], round(c['max_slope_deg'], 2)) for c in earth_info]}")
    ckpt = args.out.parent / "meta_real_earth.safetensors.ckpt"
    res = meta_train(train, net, mconf, val_maps=val, checkpoint=ckpt, on_step=log)
    meta_s = time.perf_counter() - t0
    model = build_model(net)
    set_weights(model, res.weights)
    weights_path = args.out.parent / "meta_real_earth.safetensors"
    save_model(model, weights_path, extra={"benchmark": "meta_real", "history": res.history})
    ckpt.unlink(missing_ok=True)
    inits = make_inits(init_weights=weights_path, prior_steps=mconf.prior_steps, seed=1, net_config=net)
    rows = []
    sets = test_sets(args.data)
    for name, (maps, info) in sets.items():
        test = pick_maps(maps, args.maps, seed=1)
        for lr in (1e-4, 1e-3):
            conf = AblationConfig(lr=lr, max_steps=args.max_steps if lr == 1e-4 else 30, seed=1)
            t = time.perf_counter()
            r = run_ablation(test if lr == 1e-4 else test[: max(1, len(test) // 2)], inits, net, conf)
            r.update(test_set=name, sources=info, available_maps=len(maps), wall_s=time.perf_counter() - t)
            rows.append(r)
            slug = name.split(" (")[0].lower().replace(" ", "_")
            write_ablation(r, test[0], inits, conf, args.out / f"{slug}_lr{lr:g}",
                           title=f"{name}, {r['n_maps']} maps {SIZE}x{SIZE}, Earth meta-init")
            tb = r["table"]
            print(f"{name} lr {lr:g}: PSNR@2 meta {tb['meta']['psnr']['mean']:.2f} empty {tb['empty']['psnr']['mean']:.2f} "
                  f"random {tb['random']['psnr']['mean']:.2f}; steps to meta: random "
                  f"{tb['random']['steps_to_meta']['mean']:.1f} (capped {tb['random']['steps_to_meta']['capped']}) "
                  f"empty {tb['empty']['steps_to_meta']['mean']:.1f}  [{time.perf_counter() - t:.0f} s]", flush=True)
    summary = {"earth": earth_info, "meta_history": res.history, "meta_config": mconf.to_dict(),
               "meta_train_s": meta_s, "total_s": time.perf_counter() - t0, "size": SIZE, "results": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "meta_real.json").write_text(to_json(summary))
    (args.out / "table.md").write_text(markdown(rows, summary))
    print(markdown(rows, summary))


def markdown(rows: list[dict], s: dict) -> str:
    lines = [f"Reptile on {sum(c['tiles'] for c in s['earth'])} Earth DEM tiles ({s['size']}x{s['size']}), "
             f"{s['meta_config']['iterations']} iterations ({s['meta_train_s'] / 60:.1f} min); Table I, N = 2 steps, "
             "mean ± std over test maps; steps to reach meta's 2-step PSNR (capped runs count as the cap).", "",
             "| test set | lr | maps | PSNR@2 meta | empty | random | SSIM@2 meta / empty / random "
             "| steps: empty | steps: random (capped) | random/meta steps |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r["table"]
        ps = lambda k: f"{t[k]['psnr']['mean']:.2f} ± {t[k]['psnr']['std']:.2f}"
        st = lambda k: f"{t[k]['steps_to_meta']['mean']:.1f} ± {t[k]['steps_to_meta']['std']:.1f}"
        lines.append(f"| {r['test_set']} | {r['config']['lr']:g} | {r['n_maps']} | "
                     f"{ps('meta')} | {ps('empty')} | {ps('random')} | "
                     f"{t['meta']['ssim']['mean']:.3f} / {t['empty']['ssim']['mean']:.3f} / "
                     f"{t['random']['ssim']['mean']:.3f} | "
                     f"{st('empty')} | {st('random')} ({t['random']['steps_to_meta']['capped']}, "
                     f"cap {r['config']['max_steps']}) | "
                     f"{r['random_over_meta_steps']:.1f}x |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
