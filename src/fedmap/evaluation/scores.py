"""A map's scores against ground truth, as one typed result."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from fedmap._schema import setting
from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import image_scores
from fedmap.evaluation.paths import PaperScores, PathScores, path_f1
from fedmap.maps.planning import passable_mask


@dataclass(frozen=True)
class MapScores:
    """PSNR and SSIM of the renderings, cell accuracy and IoU, and the path F1.

    ``path`` plans with the run's ``unknown_passable`` (``path.unknown_passable``), and
    ``path.paper`` is the paper's F1 read literally with that setting.
    ``paper_other_unknown`` is the same literal reading with the *other* setting (UNKNOWN
    cells passable if the run's planner treats them as impassable, and vice versa), so
    every report has the literal F1 both ways: :attr:`paper_unknown_impassable` and
    :attr:`paper_unknown_passable` pick the right one. It is None only when the other
    setting leaves fewer than two passable cells in the truth to draw pairs from (a truth
    that is mostly UNKNOWN, scored with UNKNOWN passable).
    """

    psnr: float
    ssim: float
    accuracy: float
    iou_free: float
    iou_impassable: float
    path: PathScores
    paper_other_unknown: PaperScores | None

    @property
    def paper_unknown_impassable(self) -> PaperScores | None:
        """The paper's F1 read literally, UNKNOWN cells impassable to the planner."""
        return self.paper_other_unknown if self.path.unknown_passable else self.path.paper

    @property
    def paper_unknown_passable(self) -> PaperScores | None:
        """The paper's F1 read literally, UNKNOWN cells passable to the planner."""
        return self.path.paper if self.path.unknown_passable else self.paper_other_unknown

    def to_dict(self) -> dict:
        """JSON form; ``paper_other_unknown`` carries the ``unknown_passable`` it was planned with."""
        other = self.paper_other_unknown
        return {"psnr": self.psnr, "ssim": self.ssim, "accuracy": self.accuracy, "iou_free": self.iou_free,
                "iou_impassable": self.iou_impassable, "path": self.path.to_dict(),
                "paper_other_unknown": None if other is None else
                {"unknown_passable": not self.path.unknown_passable, **asdict(other)}}


@dataclass(frozen=True)
class EvaluateConfig:
    """How a run's maps are scored: the ``[evaluate]`` section of a run config."""

    pairs: int = setting(75, help="Seeded start/goal pairs of the A* path F1")
    unknown_passable: bool = setting(False, help="Let the path planner cross UNKNOWN cells")
    central: bool = setting(True, help="Also fit one network to the union of the local maps (the centralised upper "
                            "bound)")

    def __post_init__(self) -> None:
        if isinstance(self.pairs, bool) or not isinstance(self.pairs, int) or self.pairs <= 0:
            raise FedmapError(f"eval pairs must be positive, got {self.pairs}")

    def score(self, truth: np.ndarray, classes: np.ndarray, *, seed: int) -> MapScores:
        """``classes`` scored against ``truth`` with these pairs and planner."""
        return score_map(truth, classes, pairs=self.pairs, seed=seed, unknown_passable=self.unknown_passable)


def score_map(truth: np.ndarray, classes: np.ndarray, *, pairs: int, seed: int,
              unknown_passable: bool = False) -> MapScores:
    """Score the class map ``classes`` against the class map ``truth`` (both ``(H, W)``).

    ``pairs`` seeded start/goal pairs for the path F1 (``seed``); ``unknown_passable``
    lets the planner cross UNKNOWN cells. The paper-literal F1 is also planned once more
    with the other ``unknown_passable`` (``paper_other_unknown``).
    """
    img = image_scores(truth, classes)
    path = path_f1(truth, classes, n_pairs=pairs, seed=seed, unknown_passable=unknown_passable)
    other = None
    if passable_mask(truth, unknown_passable=not unknown_passable).sum() >= 2:  # else no pairs to draw
        other = path_f1(truth, classes, n_pairs=pairs, seed=seed, unknown_passable=not unknown_passable).paper
    return MapScores(img["psnr"], img["ssim"], img["accuracy"], img["iou_free"], img["iou_impassable"], path, other)
