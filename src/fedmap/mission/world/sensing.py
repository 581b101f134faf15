"""The sensor footprint: the cells a rover observes from where it stands.

Without line of sight a rover observes every cell whose centre is within
``radius`` cells (Euclidean) of its own. With line of sight (an elevation grid given),
a cell is observed only if the straight sight line from the sensor, ``height_m`` above
the rover's ground, to the top of that cell passes above the terrain in between: the
line is sampled every half cell, and a sample blocks it when the elevation of the cell
it falls in is above the line. The rover's own cell and its 8 neighbours have no cell in
between, so they are always observed (a rover always sees where it can step next).
NaN elevation (nodata) never blocks.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=8)
def disk_offsets(radius: float) -> np.ndarray:
    """``(n, 2)`` integer (drow, dcol) offsets whose distance to (0, 0) is <= ``radius``."""
    r = int(np.floor(radius))
    d = np.arange(-r, r + 1)
    dr, dc = np.meshgrid(d, d, indexing="ij")
    keep = dr**2 + dc**2 <= radius**2 + 1e-9
    return np.stack([dr[keep], dc[keep]], axis=1)


@lru_cache(maxsize=8)
def _sight_samples(radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every disk offset: sample points strictly between the sensor and the cell.

    Returns ``(sample_dr, sample_dc, fraction, valid)``, each ``(n_offsets, n_samples)``;
    samples are rounded to the cell they fall in, and samples in the start or end cell are
    marked invalid (they cannot block)."""
    off = disk_offsets(radius).astype(np.float64)
    dist = np.hypot(off[:, 0], off[:, 1])
    n = max(int(np.ceil(2 * dist.max())), 1)
    f = (np.arange(1, n) / n)[None, :] * np.ones((len(off), 1))  # fractions in (0, 1)
    sr = np.rint(off[:, :1] * f).astype(np.int64)
    sc = np.rint(off[:, 1:] * f).astype(np.int64)
    valid = ~(((sr == 0) & (sc == 0)) | ((sr == off[:, :1]) & (sc == off[:, 1:])))
    return sr, sc, f, valid


def footprint(pos: tuple[int, int], shape: tuple[int, int], radius: float, *,
              elevation: np.ndarray | None = None, height_m: float = 1.5) -> np.ndarray:
    """Boolean ``shape`` mask of the cells a rover at ``pos`` observes.

    Parameters
    ----------
    pos : (row, col)
        The rover's cell.
    shape : (H, W)
        The map.
    radius : float
        Sensor range in cells.
    elevation : ndarray (H, W), optional
        Metres; given, the footprint is limited to the cells in line of sight.
    height_m : float
        Sensor height above the rover's ground (line of sight only).
    """
    h, w = shape
    off = disk_offsets(radius)
    rr, cc = off[:, 0] + pos[0], off[:, 1] + pos[1]
    inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    keep = inside.copy()
    if elevation is not None:
        z = np.asarray(elevation, dtype=np.float64)
        sr, sc, f, valid = _sight_samples(radius)
        z0 = z[pos] + height_m
        z0 = height_m if not np.isfinite(z0) else z0
        tr, tc = np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)
        zt = z[tr, tc]
        zt = np.where(np.isfinite(zt), zt, z0)
        line = z0 + (zt[:, None] - z0) * f  # the sight line's height above each sample
        pr, pc = np.clip(sr + pos[0], 0, h - 1), np.clip(sc + pos[1], 0, w - 1)
        zs = z[pr, pc]
        blocked = valid & np.isfinite(zs) & (zs > line + 1e-9)
        keep &= ~blocked.any(axis=1)
    mask = np.zeros(shape, dtype=bool)
    mask[rr[keep], cc[keep]] = True
    return mask


def block_classes(classes: np.ndarray, factor: int, unknown: int) -> np.ndarray:
    """The class of every ``factor`` x ``factor`` block of ``classes`` (blocks aligned to
    the map's origin; the last ones may be cut by the map's edge): the class of its cells
    when they all have the same one, else ``unknown`` (a mixed block)."""
    c = np.asarray(classes)
    h, w = c.shape
    bh, bw = -(-h // factor), -(-w // factor)
    pad = np.full((bh * factor, bw * factor), -1, dtype=np.int16)
    pad[:h, :w] = c
    blocks = pad.reshape(bh, factor, bw, factor).transpose(0, 2, 1, 3).reshape(bh, bw, -1)
    first = blocks.max(axis=2)  # the class (padding is -1, below every class)
    uniform = ((blocks == first[..., None]) | (blocks == -1)).all(axis=2)
    return np.where(uniform, first, unknown).astype(np.uint8)


def coarse_footprint(pos: tuple[int, int], shape: tuple[int, int], radius: float, factor: int) -> np.ndarray:
    """Boolean ``shape`` mask of the cells of every ``factor`` x ``factor`` block whose
    centre is within ``radius`` cells of ``pos`` (a coarse camera's footprint)."""
    h, w = shape
    bh, bw = -(-h // factor), -(-w // factor)
    cr = np.arange(bh) * factor + (factor - 1) / 2
    cc = np.arange(bw) * factor + (factor - 1) / 2
    near = (cr[:, None] - pos[0]) ** 2 + (cc[None, :] - pos[1]) ** 2 <= radius**2 + 1e-9
    return np.repeat(np.repeat(near, factor, axis=0), factor, axis=1)[:h, :w]
