"""Federated vs centralised global maps on real terrain (issue 7's table).

    python benchmarks/federated_gap.py [--data ../shared/data] [--size 256] [--out benchmarks/results/federated_gap]

For each terrain (Mars Gale 1 m DEM, a Moon GLD100 2x2 tile mosaic, the Columbia glacier
DEM) and each method, runs the full pipeline with 4 quadrant agents that together see the
whole map and prints / writes (Markdown + JSON) PSNR, SSIM, path F1, uplink bytes per
agent per round and wall time, next to the centralised upper bound: the same
architecture and step budget trained on the union of the local maps.

Needs the data folder (CI has it); the package itself never does.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from fedmap.config import method_config
from fedmap.maps.io import centre_crop, load_dem, mosaic_heightmap_tiles
from fedmap.maps.traversability import dem_to_traversability
from fedmap.pipeline import run_pipeline


def terrains(data: Path, n: int) -> dict:
    return {
        "mars (Gale 1 m)": centre_crop(load_dem(data / "mars/missionDEM_gale_1m.tif"), n),
        "moon (GLD100 Hadley)": centre_crop(mosaic_heightmap_tiles(data / "moon/gld100_256p", lon=3, lat=25, n=2), n),
        "ice (Columbia 100 m)": centre_crop(load_dem(data / "ice/test-files_columbia_dem_Columbia.tif"), n),
    }


#: label -> (method, rounds, local epochs, overrides); see src/fedmap/presets/*.toml
METHODS = {
    "grid+coverage R=1 (update int4+zstd)": ("fedmap", 1, 100, {}),
    "grid+coverage R=3 (update int4+zstd)": ("fedmap", 3, 34, {}),
    "grid+coverage R=3 (top-k 4% int8: too sparse)": ("fedmap", 3, 34, {"uplink": "topk:0.04,values=int8+zstd"}),
    # the paper: Fourier MLP, random init, FedAvg, UNKNOWN trained as grey, 100 local epochs, R = 1
    "paper (fourier, fedavg, R=1)": ("paper", 1, 100, {"uplink": "fp16", "downlink": "fp16", "init": "random"}),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/federated_gap"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    rows = []
    for tname, dem in terrains(args.data, args.size).items():
        truth = dem_to_traversability(dem)
        print(f"\n{tname}: {dem.source}, {truth.shape[0]}x{truth.shape[1]} at {dem.pixel_size:.1f} m, "
              f"{truth.fractions()['impassable']:.1%} impassable", flush=True)
        for mname, spec in METHODS.items():
            t = time.perf_counter()
            method, rounds, epochs, overrides = spec
            cfg = method_config(method, rounds=rounds, epochs=epochs, seed=args.seed, size=truth.shape[0],
                                **overrides)
            res = run_pipeline(cfg, truth=truth)
            wall = time.perf_counter() - t
            g, c, b = res.global_scores, res.central_scores, res.federation.total_bytes()
            assert c is not None  # central is on in both presets
            row = {
                "terrain": tname, "method": mname,
                "psnr": g.psnr, "ssim": g.ssim, "f1": g.path.f1,
                "central_psnr": c.psnr, "central_ssim": c.ssim, "central_f1": c.path.f1,
                "uplink_B_per_agent_round": b.uplink_per_agent_round,
                "downlink_B_total": b.downlink,
                "rounds": res.config.federation.rounds, "wall_s": wall - res.timings.get("central_s", 0.0),
            }
            rows.append(row)
            write(rows, args.out)
            print(f"  {mname:38} PSNR {row['psnr']:6.2f} SSIM {row['ssim']:.3f} F1 {row['f1']:.2f} | central "
                  f"{row['central_psnr']:6.2f} / {row['central_f1']:.2f} | uplink "
                  f"{row['uplink_B_per_agent_round'] / 1000:7.1f} kB/agent/round | {row['wall_s']:.0f} s", flush=True)
    print("\n" + write(rows, args.out))


def write(rows: list[dict], out: Path) -> str:
    from fedmap._util import to_json

    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(to_json(rows))
    md = ["| terrain | method | PSNR dB | SSIM | path F1 | central PSNR / F1 | uplink kB/agent/round | wall s |",
          "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        fmt = lambda x: "inf" if x == float("inf") else f"{x:.2f}"  # noqa: E731
        md.append(f"| {r['terrain']} | {r['method']} | {fmt(r['psnr'])} | {r['ssim']:.3f} | {r['f1']:.2f} | "
                  f"{fmt(r['central_psnr'])} / {r['central_f1']:.2f} | {r['uplink_B_per_agent_round'] / 1000:.1f} | "
                  f"{r['wall_s']:.0f} |")
    (out / "results.md").write_text("\n".join(md) + "\n")
    return "\n".join(md)


if __name__ == "__main__":
    main()
