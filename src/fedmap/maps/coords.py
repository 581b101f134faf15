"""The single pixel <-> coordinate convention used everywhere in fedmap.

A global frame is an ``H x W`` grid. Row ``r`` grows downwards (image order), column
``c`` grows to the right. The network sees the *centre* of each pixel as

    v = (x, y) = ((c + 0.5) / W, (r + 0.5) / H)   in (0, 1)^2

so ``x`` follows columns and ``y`` follows rows, and the same physical pixel has the
same coordinate for every agent. Coordinates are flattened in row-major (C) order,
which is what ``numpy.reshape(H, W)`` undoes.
"""

from __future__ import annotations

import numpy as np


def pixel_centres(height: int, width: int) -> np.ndarray:
    """Coordinates of all pixel centres of an ``height x width`` grid.

    Returns
    -------
    ndarray, shape (height * width, 2), float32
        Row-major order; column 0 is x (from columns), column 1 is y (from rows).
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"grid size must be positive, got {height}x{width}")
    ys = (np.arange(height, dtype=np.float64) + 0.5) / height  # (H,)
    xs = (np.arange(width, dtype=np.float64) + 0.5) / width  # (W,)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")  # (H, W) each
    return np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float32)


def coord_to_pixel(xy: np.ndarray, height: int, width: int) -> np.ndarray:
    """Inverse of :func:`pixel_centres`: ``(N, 2)`` (x, y) -> ``(N, 2)`` int (row, col).

    Coordinates are floored onto the pixel that contains them and clipped to the grid.
    """
    xy = np.asarray(xy, dtype=np.float64)
    cols = np.clip(np.floor(xy[:, 0] * width), 0, width - 1).astype(np.int64)
    rows = np.clip(np.floor(xy[:, 1] * height), 0, height - 1).astype(np.int64)
    return np.stack([rows, cols], axis=1)
