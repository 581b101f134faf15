"""A map's scores against ground truth, as one typed result."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fedmap.evaluation.metrics import image_scores
from fedmap.evaluation.paths import PathScores, path_f1


@dataclass(frozen=True)
class MapScores:
    """PSNR and SSIM of the renderings, cell accuracy and IoU, and the path F1."""

    psnr: float
    ssim: float
    accuracy: float
    iou_free: float
    iou_impassable: float
    path: PathScores

    def to_dict(self) -> dict:
        return {"psnr": self.psnr, "ssim": self.ssim, "accuracy": self.accuracy, "iou_free": self.iou_free,
                "iou_impassable": self.iou_impassable, "path": self.path.to_dict()}


def score_map(truth: np.ndarray, classes: np.ndarray, *, pairs: int, seed: int,
              unknown_passable: bool = False) -> MapScores:
    """Score the class map ``classes`` against the class map ``truth`` (both ``(H, W)``).

    ``pairs`` seeded start/goal pairs for the path F1 (``seed``); ``unknown_passable``
    lets the planner cross UNKNOWN cells.
    """
    img = image_scores(truth, classes)
    path = path_f1(truth, classes, n_pairs=pairs, seed=seed, unknown_passable=unknown_passable)
    return MapScores(img["psnr"], img["ssim"], img["accuracy"], img["iou_free"], img["iou_impassable"], path)
