"""What a run leaves on disk for people: the Fig. 4 panel, maps, the model and metrics.

:func:`write_outputs` writes a :class:`~fedmap.pipeline.PipelineResult` as one atomic
folder (:class:`fedmap._util.AtomicDir`): the previous folder stays until the new one is
complete. :func:`write_comparison` writes several methods run on the same rovers (the
demo's paper-vs-fedmap view): one folder per method plus one figure and one table.
:func:`write_metrics` is the one writer of a run's ``metrics.json`` (these two and the
Flower base station's).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from fedmap._util import AtomicDir, to_json
from fedmap.evaluation.scores import MapScores
from fedmap.maps.export import check_formats, export_maps
from fedmap.maps.grid import GridMap, render_classes
from fedmap.maps.io import save_map
from fedmap.nets.model import save_model
from fedmap.pipeline import PipelineResult


def _json_ready(obj: Any) -> Any:
    """``obj`` with every typed record in it (a :class:`~fedmap.federation.runner.RoundRecord`,
    :class:`~fedmap.federation.runner.ByteTotals`, ...: anything with ``to_dict``) as its JSON layout."""
    if dataclasses.is_dataclass(obj) and hasattr(obj, "to_dict"):
        return obj.to_dict()
    if isinstance(obj, dict):
        return {k: _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_ready(v) for v in obj]
    return obj


def write_metrics(folder: Path, metrics: dict) -> Path:
    """Write ``metrics`` as ``folder/metrics.json``: the one writer of that file. Round records
    (``rounds``: :class:`~fedmap.federation.runner.RoundRecord`) become dicts here, at the JSON
    boundary (:meth:`~fedmap.federation.runner.RoundRecord.to_dict`)."""
    path = Path(folder) / "metrics.json"
    path.write_text(to_json(_json_ready(metrics)))
    return path


def _finish(fig, path: Path, *, title: str, legend_height: float, title_height: float) -> None:
    """The class legend (free / impassable / unknown) under the panels, the title above
    them, then save and close. Heights are fractions of the figure kept for each."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    handles = [Patch(color=(0, 1, 0), label="free"), Patch(color=(1, 0, 0), label="impassable"),
               Patch(color=(0.5, 0.5, 0.5), label="unknown")]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, legend_height, 1, 1 - title_height if title else 1))
    fig.savefig(path)
    plt.close(fig)


def fig4_panel(local_maps: list[GridMap], truth: GridMap, global_classes: np.ndarray, refined: np.ndarray,
               path: Path, *, title: str = "", scores: dict | None = None) -> None:
    """Agents' local maps | ground truth | federated global map | refined map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(f"rover {k} local map", m.classes) for k, m in enumerate(local_maps)]
    panels += [("ground truth", truth.classes), ("federated global map", global_classes), ("refined global map", refined)]
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(2.4 * n, 2.9), dpi=110)
    for ax, (name, cls) in zip(np.atleast_1d(axes), panels):
        ax.imshow(render_classes(cls), interpolation="nearest")
        label = name
        if scores and name in scores:
            s = scores[name]
            label += f"\nPSNR {s['psnr']:.1f}  F1 {s['f1']:.2f}"
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    _finish(fig, path, title=title, legend_height=0.07, title_height=0.05)


def panel_scores(global_scores: MapScores, refined_scores: MapScores) -> dict[str, dict[str, float]]:
    """The scores :func:`fig4_panel` prints under the global and refined maps."""
    return {"federated global map": {"psnr": global_scores.psnr, "f1": global_scores.path.f1},
            "refined global map": {"psnr": refined_scores.psnr, "f1": refined_scores.path.f1}}


def write_outputs(result: PipelineResult, out_dir: str | Path, *, extra: dict[str, str] | None = None,
                  extra_metrics: dict | None = None, export=None) -> Path:
    """Write metrics.json, config.json, the global model, maps and the Fig. 4 panel, atomically.

    ``extra`` maps further file names to text written into the same folder (e.g. the
    resolved run config); ``extra_metrics`` adds entries to ``metrics.json``. ``export``
    (formats of :data:`fedmap.maps.export.EXPORT_FORMATS`: geotiff, ros, png, npy) also
    writes every map in those formats, georeferenced like the truth (``truth.tif``, ...).
    """
    out = Path(out_dir)
    with AtomicDir(out) as tmp:
        write_metrics(tmp, {**result.metrics, **(extra_metrics or {}), "timings": result.timings})
        (tmp / "config.json").write_text(to_json(result.config.to_dict()))
        for name, text in (extra or {}).items():
            (tmp / name).write_text(text)
        save_model(result.model, tmp / "global_model.safetensors", extra={"pipeline": result.config.to_dict()})
        save_map(result.truth, tmp / "truth.png")
        save_map(result.truth.with_classes(result.global_classes, "federated global map"), tmp / "global_map.png")
        save_map(result.truth.with_classes(result.refined, "refined global map"), tmp / "refined_map.png")
        for k, m in enumerate(result.local_maps):
            save_map(m, tmp / f"rover{k}_local.png")
        if export:
            maps = {"truth": result.truth,
                    "global_map": result.truth.with_classes(result.global_classes, "federated global map"),
                    "refined_map": result.truth.with_classes(result.refined, "refined global map"),
                    **{f"rover{k}_local": m for k, m in enumerate(result.local_maps)}}
            export_maps(maps, tmp, check_formats(export), frame=result.truth)
        c = result.config
        init = c.model.start
        side = result.truth.shape[0]
        title = (f"{c.title} {side}x{side}, {c.explore.agents} agents ({c.explore.mode}), {c.model.net} net, {init}, "
                 f"{c.federation.aggregator} x {c.federation.rounds} round(s), {c.train.epochs} local epochs")
        fig4_panel(result.local_maps, result.truth, result.global_classes, result.refined, tmp / "figure.png",
                   title=title, scores=panel_scores(result.global_scores, result.refined_scores))
    return out


def comparison_rows(results: dict[str, PipelineResult]) -> list[dict]:
    """One row per method: the global and refined map's scores and the bytes each rover sent."""
    rows = []
    for name, r in results.items():
        b = r.federation.total_bytes()
        rows.append({
            "method": name, "net": r.config.model.net, "aggregator": r.config.federation.aggregator,
            "psnr": r.global_scores.psnr, "ssim": r.global_scores.ssim, "accuracy": r.global_scores.accuracy,
            "f1": r.global_scores.path.f1, "refined_psnr": r.refined_scores.psnr, "refined_f1": r.refined_scores.path.f1,
            "central_psnr": None if r.central_scores is None else r.central_scores.psnr,
            "uplink_bytes_per_rover_round": b.uplink_per_agent_round, "uplink_bytes": b.uplink,
            "downlink_bytes": b.downlink, "uplink_codec": r.config.federation.uplink,
            "precision": r.config.train.precision, "seconds": sum(r.timings.values()),
        })
    return rows


def comparison_panel(results: dict[str, PipelineResult], path: Path, *, title: str = "") -> None:
    """Top row: the rovers' local maps and the truth (shared by every method). Then one row
    per method: its federated global map and refined map, with PSNR, F1 and bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(results.values()))
    top = [(f"rover {k} local map", m.classes) for k, m in enumerate(first.local_maps)]
    top.append(("ground truth", first.truth.classes))
    ncols = max(len(top), 2)
    fig, axes = plt.subplots(1 + len(results), ncols, figsize=(2.3 * ncols, 2.5 * (1 + len(results))), dpi=110,
                             squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, (name, cls) in zip(axes[0], top):
        ax.imshow(render_classes(cls), interpolation="nearest")
        ax.set_title(name, fontsize=8)
    for row, (method, r) in zip(axes[1:], results.items()):
        per_rover = r.federation.total_bytes().uplink_per_agent_round
        for ax, (what, cls, sc) in zip(row, (("global map", r.global_classes, r.global_scores),
                                              ("refined", r.refined, r.refined_scores))):
            ax.imshow(render_classes(cls), interpolation="nearest")
            ax.set_title(f"{method}: {what}\nPSNR {sc.psnr:.1f}  F1 {sc.path.f1:.2f}", fontsize=8)  # inf: "inf"
        col = 2
        if r.central_classes is not None and r.central_scores is not None and ncols > 3:
            row[2].imshow(render_classes(r.central_classes), interpolation="nearest")
            row[2].set_title(f"central bound\nPSNR {r.central_scores.psnr:.1f}  F1 {r.central_scores.path.f1:.2f}",
                             fontsize=8)
            col = 3
        row[col].text(0, 0.5, f"{method}\n{r.config.model.net} net, {r.config.federation.aggregator}\n"
                      f"{per_rover:,.0f} B per rover per round\n({r.config.federation.uplink} uplink)",
                      fontsize=8, va="center", transform=row[col].transAxes)
    _finish(fig, path, title=title, legend_height=0.04, title_height=0.04)


def write_comparison(results: dict[str, PipelineResult], out_dir: str | Path, *,
                     extra: dict[str, dict[str, str]] | None = None, export=None) -> Path:
    """Several methods on the same rovers, atomically: ``<method>/`` (a full
    :func:`write_outputs` folder each), ``figure.png`` (:func:`comparison_panel`) and
    ``metrics.json`` (``methods``: the table rows; ``<method>``: each run's metrics)."""
    out = Path(out_dir)
    with AtomicDir(out) as tmp:
        for name, r in results.items():
            write_outputs(r, tmp / name, extra=(extra or {}).get(name), export=export)
        first_run = next(iter(results.values()))
        first, side = first_run.config, first_run.truth.shape[0]
        title = (f"{first.title} {side}x{side}, {first.explore.agents} rovers ({first.explore.mode}): "
                 f"{' vs '.join(results)}")
        comparison_panel(results, tmp / "figure.png", title=title)
        write_metrics(tmp, {"methods": comparison_rows(results), **{k: r.metrics for k, r in results.items()}})
    return out
