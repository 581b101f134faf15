"""``fedmap bandwidth``: the paper's Table III, redone with real bytes and scored decodes.

Three parts, written as one folder (``report.md``, ``bandwidth.json``, ``rd.png``):

1. **Table III** as the paper computes it (:func:`fedmap.experiments.bandwidth.paper_table3`).
2. **The model on the link**: the paper network's payload in every fedmap codec, each
   the ``len()`` of a real payload (dense codecs: the weights; update codecs: the
   difference between two seeded initialisations, standing in for a local update).
3. **Rate-distortion on one map**: image codecs of the whole map (what the base would
   need to hold it) against fedmap's federated runs on the same map, whose bytes are the
   total uplink of all rovers over all rounds and whose quality is the decoded global map.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from fedmap._util import AtomicDir, to_json
from fedmap.config import method_config
from fedmap.experiments.bandwidth import compare_image_codecs, markdown_table, paper_table3, rd_figure
from fedmap.federation.codecs import Encoder
from fedmap.maps.grid import GridMap
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.nets.model import build_model, count_parameters, get_weights
from fedmap.pipeline import run_pipeline

MODEL_CODECS = ("fp32", "fp16", "bf16", "int8", "int8-tensor", "int4", "int4+zstd",
                "topk:0.01,values=fp16", "topk:0.01,values=int8+zstd", "topk:0.005,values=int8+zstd")

#: fedmap configurations drawn beside the image codecs: label -> (method, rounds, epochs, overrides)
FEDERATED_RUNS: dict[str, tuple[str, int, int, dict]] = {
    "paper net, FedAvg R=1, fp16": ("paper", 1, 100, {"uplink": "fp16", "downlink": "fp16"}),
    "paper net, FedAvg R=3, top-k 1% int8": ("paper", 3, 34, {"uplink": "topk:0.01,values=int8+zstd",
                                                              "downlink": "update-int8+zstd"}),
    "grid+coverage R=1, update int4+zstd": ("fedmap", 1, 100, {}),
    "grid+coverage R=3, update int8+zstd": ("fedmap", 3, 34, {"uplink": "update-int8+zstd"}),
}


def model_payloads(seed: int = 0) -> list[dict]:
    """Bytes of the paper network in every codec in :data:`MODEL_CODECS`."""
    w = get_weights(build_model(seed=seed))
    ref = get_weights(build_model(seed=seed + 1))
    n = count_parameters(build_model(seed=seed))
    rows = []
    for label in MODEL_CODECS:
        data = Encoder(label).encode(w, reference=ref)
        rows.append({"codec": label, "bytes": len(data), "bytes_per_param": len(data) / n, "params": n})
    return rows


def federated_points(truth: GridMap, *, seed: int, pairs: int, on_stage: Callable[[str, int], None] | None = None,
                     on_step: Callable[[int, float], None] | None = None) -> list[dict]:
    points = []
    for label, (method, rounds, epochs, overrides) in FEDERATED_RUNS.items():
        cfg = method_config(method, rounds=rounds, epochs=epochs, seed=seed, pairs=pairs, central=False,
                            size=truth.shape[0], **overrides)
        if on_stage:
            on_stage(label, 0)
        res = run_pipeline(cfg, truth=truth, on_step=on_step)
        g = res.global_scores
        b = res.federation.total_bytes()
        points.append({"label": label, "bytes": b.uplink, "uplink_per_agent_round": b.uplink_per_agent_round,
                       "downlink": b.downlink, "rounds": cfg.federation.rounds, "psnr": g.psnr,
                       "ssim": g.ssim, "f1": g.path.f1, "f1_tolerant": g.path.tolerant.f1})
    return points


def bandwidth_report(out: str | Path, *, terrain: str = "mars", size: int = 256, pairs: int = 75, seed: int = 0,
                     federated: bool = True, truth: GridMap | None = None,
                     on_stage: Callable[[str | None, int], None] | None = None,
                     on_step: Callable[[int, float], None] | None = None) -> dict:
    """Write the bandwidth report for a built-in terrain, or for ``truth`` (a GridMap) if given."""
    if truth is None:
        truth = load_truth(TerrainSource(terrain=terrain, size=size), seed=seed)
    else:
        terrain, size = truth.source, truth.shape[0]
    if on_stage:
        on_stage("image codecs", 0)
    image_rows = compare_image_codecs(truth, n_pairs=pairs, seed=seed)
    points = federated_points(truth, seed=seed, pairs=pairs, on_stage=on_stage, on_step=on_step) if federated else []
    result: dict[str, Any] = {
        "map": {"terrain": terrain, "size": size, "seed": seed, "source": truth.source, **truth.fractions()},
        "table3": paper_table3(), "model_payloads": model_payloads(seed), "image_codecs": image_rows,
        "federated": points}
    md = [f"# Bytes on the link — {terrain} {size}x{size} (seed {seed})", "",
          "## The paper's Table III, recomputed", "", markdown_table(result["table3"]),
          "## The paper network (199,683 parameters) in fedmap's codecs", "",
          "| codec | bytes | bytes/param |", "|---|---:|---:|"]
    md += [f"| {r['codec']} | {r['bytes']:,} | {r['bytes_per_param']:.3f} |" for r in result["model_payloads"]]
    md += ["", f"## Image codecs of the whole {size}x{size} map", "", markdown_table(image_rows)]
    if points:
        md += ["## fedmap on the same map (bytes = all rovers' uplink over all rounds)", "",
               "| run | uplink total B | per rover per round B | PSNR | SSIM | path F1 | tol. F1 |",
               "|---|---:|---:|---:|---:|---:|---:|"]
        md += [f"| {p['label']} | {p['bytes']:,} | {p['uplink_per_agent_round']:,.0f} | {p['psnr']:.2f} | "
               f"{p['ssim']:.3f} | {p['f1']:.2f} | {p['f1_tolerant']:.2f} |" for p in points]
    with AtomicDir(out) as tmp:
        (tmp / "bandwidth.json").write_text(to_json(result))
        (tmp / "report.md").write_text("\n".join(md) + "\n")
        rd_figure(image_rows, tmp / "rd.png", model_points=points,
                  title=f"{terrain} {size}x{size}: bytes to get the map to the base vs quality")
    return result
