"""The pipeline's shared stages after federation: what every rover makes of the global
weights, and how a run describes its ground truth.

The in-process pipeline, ``reproduce`` and the Flower base station all use these.
"""

from __future__ import annotations

import numpy as np

from fedmap.maps.grid import UNKNOWN, GridMap, classes_from_rgb
from fedmap.nets.model import CoordNet, GridNet, NetConfig, Weights, build_model, render, set_weights
from fedmap.refine import RefineConfig, refine


def global_map(net_config: NetConfig, weights: Weights, shape: tuple[int, int],
               refine_config: RefineConfig) -> tuple[CoordNet | GridNet, np.ndarray, np.ndarray, np.ndarray]:
    """What every rover makes of the global weights: the model, its (H, W, 3) rendering,
    the rendering snapped to classes, and the refined classes."""
    model = build_model(net_config)
    set_weights(model, weights)
    rgb = render(model, *shape)
    classes = classes_from_rgb(rgb)
    return model, rgb, classes, refine(classes, refine_config)


def truth_summary(truth: GridMap) -> dict:
    """The ground truth as ``metrics.json`` describes it."""
    h, w = truth.shape
    out = {"shape": [h, w], "pixel_size_m": truth.pixel_size, "source": truth.source, **truth.fractions()}
    if truth.meta.get("slope_limit_deg") is not None:  # the slope limit used (a percentile's, resolved)
        out["slope_limit_deg"] = truth.meta["slope_limit_deg"]
    return out


def union_map(local_maps: list[GridMap]) -> GridMap:
    """All agents' observations in one map: what the base would hold with raw maps."""
    out = np.full(local_maps[0].shape, UNKNOWN, dtype=np.uint8)
    for m in local_maps:
        out = np.where(m.known, m.classes, out)
    return local_maps[0].with_classes(out, "union of local maps")
