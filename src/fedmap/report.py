"""Figures and JSON for people: the paper's Fig. 4 panel and atomic result writing."""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from fedmap.maps.grid import GridMap, render_classes


def _clean(obj):
    """JSON-safe copy: inf/nan -> None, numpy scalars -> Python, keys -> str."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def to_json(obj) -> str:
    return json.dumps(_clean(obj), indent=2, sort_keys=False) + "\n"


def fig4_panel(local_maps: list[GridMap], truth: GridMap, global_classes: np.ndarray, refined: np.ndarray,
               path: Path, *, title: str = "", scores: dict | None = None) -> None:
    """Agents' local maps | ground truth | federated global map | refined map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    panels = [(f"agent {k + 1} local map", m.classes) for k, m in enumerate(local_maps)]
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
    handles = [Patch(color=(0, 1, 0), label="free"), Patch(color=(1, 0, 0), label="impassable"),
               Patch(color=(0.5, 0.5, 0.5), label="unknown")]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 0.95 if title else 1))
    fig.savefig(path)
    plt.close(fig)


class AtomicDir:
    """Write a result folder completely or not at all.

    Files go into a temporary sibling folder; :meth:`commit` swaps it into place (the old
    folder is removed only after the new one is complete). On an exception nothing of
    the new run is left behind and the old folder is untouched.
    """

    def __init__(self, target: str | os.PathLike) -> None:
        self.target = Path(target)

    def __enter__(self) -> Path:
        self.target.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.tmp-", dir=self.target.parent))
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return
        old = None
        if self.target.exists():
            old = self.target.with_name(f".{self.target.name}.old-{os.getpid()}")
            os.replace(self.target, old)
        os.replace(self.tmp, self.target)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
