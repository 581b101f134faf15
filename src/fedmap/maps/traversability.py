"""DEM -> traversability classes from slope, roughness and step height.

All three are computed in metres using the DEM's pixel size:

* **slope** (degrees): from central differences, ``atan(|grad z|)`` with the gradient in
  metres per metre. Valid at any resolution.
* **step height** (m): the largest absolute elevation difference between a cell and its
  8 neighbours. A cell is a step when that rise exceeds ``max_step_m`` *and* is steeper
  than the slope limit over the neighbour distance (a smooth slope under the limit is
  never a step, however coarse the pixels). A step is a rover-scale obstacle, so it is
  only tested when the pixel is no larger than ``rover_scale_max_px`` metres (on a 100 m
  DEM every neighbour difference is a hillside, which the slope test already covers).
* **roughness** (m): the standard deviation of the elevation residual after removing the
  least-squares plane of the 3x3 window (so a smooth slope has zero roughness), also
  only at rover scale.

A cell is IMPASSABLE if any test fails, FREE otherwise, and UNKNOWN where the DEM has
nodata or any cell of its 3x3 neighbourhood does (the slope there is undefined).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap


@dataclass(frozen=True)
class TraversabilityThresholds:
    """Rover limits. Defaults fit a small planetary rover (CADRE/Curiosity-like)."""

    max_slope_deg: float = 15.0
    max_step_m: float = 0.3
    max_roughness_m: float = 0.15
    rover_scale_max_px: float = 2.0

    def __post_init__(self) -> None:
        if not 0 < self.max_slope_deg < 90:
            raise FedmapError(f"max_slope_deg must be in (0, 90), got {self.max_slope_deg}")
        for name in ("max_step_m", "max_roughness_m", "rover_scale_max_px"):
            if not getattr(self, name) > 0:
                raise FedmapError(f"{name} must be positive, got {getattr(self, name)}")

    def to_dict(self) -> dict:
        return asdict(self)


def slope_degrees(elevation: np.ndarray, pixel_size: float) -> np.ndarray:
    """Slope in degrees from central differences (one-sided at the border)."""
    dz_dy, dz_dx = np.gradient(elevation.astype(np.float64), pixel_size)
    return np.degrees(np.arctan(np.hypot(dz_dx, dz_dy)))


def step_height(elevation: np.ndarray) -> np.ndarray:
    """Largest |z - z_neighbour| over the 8-neighbourhood, in metres (border replicated)."""
    z = elevation.astype(np.float64)
    zmax = ndimage.maximum_filter(z, size=3, mode="nearest")
    zmin = ndimage.minimum_filter(z, size=3, mode="nearest")
    return np.maximum(zmax - z, z - zmin)


def steepest_rise(elevation: np.ndarray, pixel_size: float) -> np.ndarray:
    """Largest |z - z_neighbour| / distance over the 8 neighbours (m per m, border replicated)."""
    z = np.pad(elevation.astype(np.float64), 1, mode="edge")
    h, w = elevation.shape
    out = np.zeros((h, w))
    centre = z[1:-1, 1:-1]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                nb = z[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w]
                out = np.maximum(out, np.abs(nb - centre) / (pixel_size * np.hypot(dr, dc)))
    return out


def roughness(elevation: np.ndarray) -> np.ndarray:
    """Std of the residual from the least-squares plane of each 3x3 window, in metres.

    With window offsets x, y in {-1, 0, 1} the plane's slopes are ``sum(x z) / 6`` and
    ``sum(y z) / 6`` and it explains ``6 (b^2 + c^2) / 9`` of the window's variance.
    """
    z = elevation.astype(np.float64)
    mean = ndimage.uniform_filter(z, size=3, mode="nearest")
    mean_sq = ndimage.uniform_filter(z * z, size=3, mode="nearest")
    kx = np.array([[-1, 0, 1]] * 3, dtype=np.float64)  # x offset of each window cell
    b = ndimage.correlate(z, kx, mode="nearest") / 6.0
    c = ndimage.correlate(z, kx.T, mode="nearest") / 6.0
    var = mean_sq - mean * mean - 6.0 * (b * b + c * c) / 9.0
    return np.sqrt(np.maximum(var, 0.0))


def dem_to_traversability(dem: Dem, thresholds: TraversabilityThresholds | None = None) -> GridMap:
    """Classify every DEM cell as FREE, IMPASSABLE or UNKNOWN (nodata)."""
    t = thresholds or TraversabilityThresholds()
    valid = dem.valid
    # Fill nodata with the nearest valid elevation so filters stay finite; the cells
    # touched by nodata are set UNKNOWN below anyway.
    z = dem.elevation
    if not valid.all():
        idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        z = z[tuple(idx)]
    bad = slope_degrees(z, dem.pixel_size) > t.max_slope_deg
    if dem.pixel_size <= t.rover_scale_max_px:
        steep = steepest_rise(z, dem.pixel_size) > np.tan(np.radians(t.max_slope_deg))
        bad |= (step_height(z) > t.max_step_m) & steep
        bad |= roughness(z) > t.max_roughness_m
    classes = np.where(bad, IMPASSABLE, FREE).astype(np.uint8)
    near_nodata = ~ndimage.minimum_filter(valid, size=3, mode="nearest")
    classes[near_nodata] = UNKNOWN
    if not (classes != UNKNOWN).any():
        raise FedmapError(f"DEM {dem.source} has no cell with a defined slope: too much nodata")
    meta = {"thresholds": t.to_dict(), "dem_source": dem.source}
    return GridMap(classes, dem.pixel_size, f"traversability({dem.source})", meta)
