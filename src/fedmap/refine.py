"""Map refinement: majority-vote gap filling and small-component removal (paper, Sec. III-D).

1. **Gap filling.** An UNKNOWN cell (a gap) takes the majority class of the known cells
   among its ``window x window`` neighbours (ties go to FREE) when that class holds at
   least ``min_votes`` of them; repeated ``iterations`` times. With the defaults (3x3,
   5 votes) only narrow gaps (one or two cells wide, or their corners) fill: the edge
   of a large unexplored area has too few known voters and stays UNKNOWN, as it should.
2. **Noise removal.** Connected IMPASSABLE components (8-connectivity) smaller than
   ``min_size`` cells become FREE, and enclosed UNKNOWN islands smaller than
   ``min_size`` take the majority class of their rim. The paper used 200 px
   (:data:`PAPER_REFINE`). fedmap's default is 0 (off): at rover scale small impassable
   blobs are real boulders, and removing them breaks planning. Refining the *ground
   truth* of the built-in mars map (128x128) with min_size 4 / 8 / 200 already drops its
   own path F1 from 1.0 to 0.72 / 0.68 / 0.35 (``benchmarks/refine_truth.py``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from fedmap._schema import setting
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN


@dataclass(frozen=True)
class RefineConfig:
    """Refinement of a global map: the ``[refine]`` section of a run config."""

    window: int = setting(3, help="Refinement: side of the majority-vote window that fills UNKNOWN gaps (odd)")
    min_votes: int = setting(5, help="Refinement: known neighbours of one class needed to fill a gap")
    iterations: int = setting(2, help="Refinement: gap-filling passes")
    min_size: int = setting(0, help="Refinement: remove impassable blobs smaller than this many cells (paper: 200; "
                            "0 = off)")

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise FedmapError(f"refine window must be an odd number >= 3, got {self.window}")
        if not 1 <= self.min_votes <= self.window * self.window - 1:
            raise FedmapError(f"min_votes must be in 1..{self.window ** 2 - 1}, got {self.min_votes}")
        if self.iterations < 0 or self.min_size < 0:
            raise FedmapError("refine iterations and min_size must be >= 0")

    def to_dict(self) -> dict:
        return asdict(self)


#: The paper's settings (noise blobs under 200 px removed).
PAPER_REFINE = RefineConfig(min_size=200)


def fill_gaps(classes: np.ndarray, *, window: int = 3, min_votes: int = 5, iterations: int = 2) -> np.ndarray:
    """Majority-vote filling of UNKNOWN cells from their known neighbours."""
    out = np.array(classes, dtype=np.uint8, copy=True)
    kernel = np.ones((window, window), dtype=np.int32)
    kernel[window // 2, window // 2] = 0  # a cell does not vote for itself
    for _ in range(iterations):
        gaps = out == UNKNOWN
        if not gaps.any():
            break
        n_free = ndimage.convolve((out == FREE).astype(np.int32), kernel, mode="constant")
        n_imp = ndimage.convolve((out == IMPASSABLE).astype(np.int32), kernel, mode="constant")
        to_free = gaps & (n_free >= n_imp) & (n_free >= min_votes)
        to_imp = gaps & (n_imp > n_free) & (n_imp >= min_votes)
        out[to_free] = FREE
        out[to_imp] = IMPASSABLE
    return out


def remove_small_components(classes: np.ndarray, *, min_size: int = 200) -> np.ndarray:
    """IMPASSABLE blobs under ``min_size`` cells -> FREE; enclosed small UNKNOWN -> rim majority."""
    out = np.array(classes, dtype=np.uint8, copy=True)
    if min_size <= 1:
        return out
    eight = np.ones((3, 3), dtype=bool)
    labels, n = ndimage.label(out == IMPASSABLE, structure=eight)
    if n:
        sizes = np.bincount(labels.ravel())
        small = sizes < min_size
        small[0] = False
        out[small[labels]] = FREE
    labels, n = ndimage.label(out == UNKNOWN, structure=eight)
    if n:
        sizes = np.bincount(labels.ravel())
        h, w = out.shape
        boxes = ndimage.find_objects(labels)
        for lab in np.flatnonzero(sizes < min_size):
            if lab == 0:
                continue
            sl = boxes[lab - 1]
            sl = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, lim)) for s, lim in zip(sl, (h, w)))
            blob = labels[sl] == lab
            rim = ndimage.binary_dilation(blob, structure=eight) & ~blob
            touches_border = (sl[0].start == 0 and blob[0].any()) or (sl[0].stop == h and blob[-1].any()) \
                or (sl[1].start == 0 and blob[:, 0].any()) or (sl[1].stop == w and blob[:, -1].any())
            vals = out[sl][rim]
            vals = vals[vals != UNKNOWN]
            if touches_border or vals.size == 0:
                continue  # not enclosed: may be real unexplored space
            out[sl][blob] = FREE if (vals == FREE).sum() >= (vals == IMPASSABLE).sum() else IMPASSABLE
    return out


def refine(classes: np.ndarray, config: RefineConfig | None = None) -> np.ndarray:
    """Gap filling, then small-component removal."""
    c = config or RefineConfig()
    out = fill_gaps(classes, window=c.window, min_votes=c.min_votes, iterations=c.iterations)
    return remove_small_components(out, min_size=c.min_size)
