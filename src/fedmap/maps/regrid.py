"""Cropping and resampling DEMs to the grid a run needs.

:func:`resample_dem` keeps the ground extent (the pixel size changes with the cell
count) and propagates nodata: a target cell is nodata when more than half of what it is
made from is nodata. :func:`crop_dem` and :func:`centre_crop` cut a window in cells.
All three keep the DEM's CRS and move its affine transform with the grid, so a cell
centre stays on the same ground coordinate (:mod:`fedmap.maps.georef`).
"""

from __future__ import annotations

from typing import SupportsInt, cast

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.georef import crop_transform, scale_transform

RESAMPLE_METHODS = ("area", "bilinear")

#: Largest relative difference of the x and y scale factors that still keeps cells square.
ASPECT_TOLERANCE = 0.01


def _target_shape(shape, dem: Dem) -> tuple[int, int]:
    if isinstance(shape, (int, np.integer)) and not isinstance(shape, bool):
        h, w = int(shape), int(shape)
    else:
        try:
            h, w = (int(v) for v in shape)
        except (TypeError, ValueError):
            raise FedmapError(f"resample target must be a size or (rows, cols), got {shape!r}") from None
    if h < 3 or w < 3:
        raise FedmapError(f"resample target must be at least 3x3 cells, got {h}x{w}")
    fy, fx = dem.shape[0] / h, dem.shape[1] / w
    if abs(fy - fx) > ASPECT_TOLERANCE * min(fy, fx):
        raise FedmapError(
            f"resampling a {dem.shape[0]}x{dem.shape[1]} DEM to {h}x{w} would make non-square cells; "
            f"crop it to the target's aspect ratio first"
        )
    return h, w


def area_weights(n_in: int, n_out: int) -> np.ndarray:
    """``(n_out, n_in)`` matrix of the fraction of each output cell covered by each input cell.

    Output cell ``i`` spans ``[i, i + 1) * n_in / n_out`` in input cells; rows sum to 1.
    """
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    j = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)
    return overlap / (n_in / n_out)


def resample_dem(dem: Dem, shape, *, method: str = "area") -> Dem:
    """Resample a DEM to ``shape`` (an int for square, or ``(rows, cols)``), keeping its extent.

    ``method="area"``: each target cell is the area-weighted mean of the source cells it
    covers (exact block means for integer factors; piecewise constant when enlarging).
    ``method="bilinear"``: linear interpolation between cell centres
    (:func:`scipy.ndimage.zoom` with ``grid_mode=True``). Either way nodata cells carry no
    weight, and a target cell is nodata when more than half of its weight falls on nodata.
    The aspect ratio must be kept (within 1%) so cells stay square.
    """
    if method not in RESAMPLE_METHODS:
        raise FedmapError(f"unknown resample method {method!r}; choose one of {', '.join(RESAMPLE_METHODS)}")
    h, w = _target_shape(shape, dem)
    valid = dem.valid.astype(np.float64)
    filled = np.where(dem.valid, dem.elevation, 0.0).astype(np.float64)
    if method == "area":
        wr, wc = area_weights(dem.shape[0], h), area_weights(dem.shape[1], w)
        weight = wr @ valid @ wc.T
        total = wr @ filled @ wc.T
    else:
        zoom = (h / dem.shape[0], w / dem.shape[1])
        weight = ndimage.zoom(valid, zoom, order=1, mode="nearest", grid_mode=True)
        total = ndimage.zoom(filled, zoom, order=1, mode="nearest", grid_mode=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        # Exactly half valid stays valid (1e-9: the weights' rounding).
        elev = np.where(weight >= 0.5 - 1e-9, total / weight, np.nan)
    px = dem.pixel_size * np.sqrt((dem.shape[0] / h) * (dem.shape[1] / w))
    meta = {**dem.meta, "resampled_to": [h, w], "resample_method": method, "pixel_size": float(px)}
    return Dem(elev.astype(np.float32), float(px), dem.source, meta,
               transform=scale_transform(dem.transform, dem.shape, (h, w)), crs=dem.crs)


def crop_dem(dem: Dem, rows, cols) -> Dem:
    """The window ``rows`` x ``cols`` of a DEM; each is ``(start, stop)`` in cells (or a slice)."""
    bounds = []
    for name, spec, n in (("rows", rows, dem.shape[0]), ("cols", cols, dem.shape[1])):
        if isinstance(spec, slice):
            if spec.step not in (None, 1):
                raise FedmapError(f"crop {name} must be contiguous, got step {spec.step}")
            spec = (0 if spec.start is None else spec.start, n if spec.stop is None else spec.stop)
        try:
            start, stop = (int(v) for v in spec)
        except (TypeError, ValueError):
            raise FedmapError(f"crop {name} must be (start, stop), got {spec!r}") from None
        if not 0 <= start < stop <= n:
            raise FedmapError(f"crop {name} ({start}, {stop}) is outside the DEM's 0..{n}")
        bounds.append((start, stop))
    (r0, r1), (c0, c1) = bounds
    meta = {**dem.meta, "crop": {"rows": [r0, r1], "cols": [c0, c1]}}
    return Dem(dem.elevation[r0:r1, c0:c1], dem.pixel_size, dem.source, meta,
               transform=crop_transform(dem.transform, r0, c0), crs=dem.crs)


def centre_crop(dem: Dem, size=None) -> Dem:
    """The central ``size`` x ``size`` (or ``(rows, cols)``) window; ``None``: the largest square."""
    if size is None:
        size = min(dem.shape)
    if np.isscalar(size):
        h = w = int(cast(SupportsInt, size))  # isscalar's TypeGuard also admits complex, which int() refuses
    else:
        h, w = (int(v) for v in size)
    if h > dem.shape[0] or w > dem.shape[1]:
        raise FedmapError(f"cannot crop {h}x{w} from a {dem.shape[0]}x{dem.shape[1]} DEM")
    r0, c0 = (dem.shape[0] - h) // 2, (dem.shape[1] - w) // 2
    return crop_dem(dem, (r0, r0 + h), (c0, c0 + w))
