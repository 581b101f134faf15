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

Rover profiles (:data:`ROVER_PROFILES`, :func:`rover_profile`) replace the generic
default with one rover's limits: ``cadre``, ``mer`` and ``msl``. A profile measures the
step over a window of about one wheel diameter (``step_window_m``), and fits a plane over
the rover's footprint (``footprint_m``): its tilt is the slope tested (at rover scale) and
the residual's std is the roughness. Windows are converted to odd cell counts at the
DEM's pixel size (:func:`window_cells`). For coarse orbital DEMs, where no fixed angle means much,
the slope limit can be a percentile of the map's own slopes (``max_slope_percentile``,
``--max-slope p75``).

A classified map that comes out more than 99% free or more than 99% impassable carries
a one-line warning in ``meta["warning"]`` naming the pixel size and thresholds
(:func:`class_balance_warning`); the CLI prints it.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy import ndimage

from fedmap._schema import setting
from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap

#: The named rover profiles (:data:`ROVER_PROFILES`).
ROVER_NAMES: tuple[str, ...] = ("cadre", "mer", "msl")


@dataclass(frozen=True)
class TraversabilityThresholds:
    """Rover limits. The defaults are a generic small planetary rover; see
    :data:`ROVER_PROFILES` for named rovers.

    Parameters
    ----------
    max_slope_deg : float
        Steepest traversable slope.
    max_step_m : float
        Highest traversable step (rise between a cell and a neighbour within the step window).
    max_roughness_m : float
        Largest std of the elevation residual from the best-fit plane over the footprint.
    rover_scale_max_px : float
        Step and roughness are only tested when the pixel is at most this many metres
        (coarser DEMs cannot show rover-scale obstacles).
    step_window_m : float, optional
        Side of the square window the step is measured over (about one wheel diameter);
        None: the 8 neighbours.
    footprint_m : float, optional
        Side of the square window of the roughness plane fit (the rover's footprint);
        None: 3x3 cells.
    max_slope_percentile : float, optional
        When set, the slope limit is this percentile (0-100] of the map's slopes, and
        ``max_slope_deg`` is ignored.
    rover : str, optional
        The profile these limits came from (a label).
    """

    max_slope_deg: float = setting(15.0, help="Steepest traversable slope, degrees")
    max_step_m: float = setting(0.3, help="Highest traversable step, metres", cli="--max-step")
    max_roughness_m: float = setting(0.15, help="Largest roughness (plane-fit residual std over the footprint), metres",
                                     cli="--max-roughness")
    rover_scale_max_px: float = setting(2.0, help="Step and roughness are tested only at pixels of at most this many "
                                        "metres")
    step_window_m: float | None = setting(None, help="Side of the window a step is measured over, metres (unset: the "
                                          "8 neighbours)")
    footprint_m: float | None = setting(None, help="Side of the roughness plane-fit window, metres (unset: 3x3 cells)")
    max_slope_percentile: float | None = setting(None, help="Slope limit as this percentile (0-100] of the map's own "
                                                 "slopes (replaces max_slope_deg)")
    rover: str | None = setting(None, help="Limits of a published rover profile (limits set beside it win)",
                                choices=lambda: ROVER_NAMES)

    def __post_init__(self) -> None:
        if not 0 < self.max_slope_deg < 90:
            raise FedmapError(f"max_slope_deg must be in (0, 90), got {self.max_slope_deg}")
        for name in ("max_step_m", "max_roughness_m", "rover_scale_max_px"):
            if not getattr(self, name) > 0:
                raise FedmapError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("step_window_m", "footprint_m"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
                raise FedmapError(f"{name} must be a positive number of metres, got {v!r}")
        p = self.max_slope_percentile
        if p is not None and not (isinstance(p, (int, float)) and 0 < p <= 100):
            raise FedmapError(f"max_slope_percentile must be in (0, 100], got {p!r}")
        if self.rover is not None and self.rover not in ROVER_NAMES:
            raise FedmapError(f"unknown rover {self.rover!r}; choose one of {', '.join(ROVER_NAMES)}")

    def to_dict(self) -> dict:
        """The limits as a plain dict; optional fields that are unset are left out."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    def describe(self, slope_limit_deg: float | None = None) -> str:
        """One line: the slope, step and roughness limits (and the rover)."""
        slope = f"{self.max_slope_deg:g} deg"
        if self.max_slope_percentile is not None:
            got = "" if slope_limit_deg is None else f" = {slope_limit_deg:.3g} deg"
            slope = f"p{self.max_slope_percentile:g} of the map's slopes{got}"
        rover = f"rover {self.rover}: " if self.rover else ""
        return (f"{rover}slope {slope}, step {self.max_step_m:.3g} m, roughness {self.max_roughness_m:.3g} m "
                f"(step and roughness only at pixels <= {self.rover_scale_max_px:.3g} m)")


# Rover profiles. Slope, step and size figures are the rovers' published capabilities
# (sources beside each value); the roughness limits are fedmap's choice, because no
# rover publishes one in these terms: GESTALT, the MER/MSL hazard-avoidance software,
# checks the plane-fit residual over the rover's footprint against its obstacle
# clearance (Goldberg, Maimone & Matthies, "Stereo vision and rover navigation software
# for planetary exploration", IEEE Aerospace 2002). fedmap's roughness is the residual's
# *standard deviation*, so the limit is a third of the step limit: a residual whose
# 3-sigma excursion reaches the step limit. ``rover_scale_max_px`` is half the
# footprint: below two cells across the rover a DEM cannot show rover-scale obstacles.
ROVER_PROFILES: dict[str, TraversabilityThresholds] = {
    # NASA/JPL CADRE (Cooperative Autonomous Distributed Robotic Exploration), three lunar
    # rovers "about the size of a carry-on suitcase" (JPL, PIA25666 caption, 2023), four
    # wheels without a rocker-bogie. JPL publishes no slope, step or wheel figure: the
    # values are estimates from that size class (footprint ~0.45 m, wheels ~0.1 m; a
    # rigid four-wheel chassis climbs about one wheel radius, 0.05 m; 20 deg slopes).
    "cadre": TraversabilityThresholds(max_slope_deg=20.0, max_step_m=0.05, max_roughness_m=0.05 / 3,
                                      rover_scale_max_px=0.45 / 2, step_window_m=0.10, footprint_m=0.45,
                                      rover="cadre"),
    # Mars Exploration Rovers Spirit and Opportunity (JPL MER mission pages): 26 cm wheels,
    # 1.6 m long x 2.3 m wide; NASA: the rovers "climb rocks up to ten inches high" (25 cm);
    # fedmap takes 0.20 m, the obstacle height MER's hazard avoidance planned around.
    # Built to survive 45 deg of tilt, driven within 30 deg (MER fault-protection tilt limit).
    "mer": TraversabilityThresholds(max_slope_deg=30.0, max_step_m=0.20, max_roughness_m=0.20 / 3,
                                    rover_scale_max_px=1.6 / 2, step_window_m=0.26, footprint_m=1.6, rover="mer"),
    # Mars Science Laboratory Curiosity (Perseverance is the same chassis): wheels "50
    # centimeters (20 inches) in diameter" (mars.nasa.gov/resources/3300); "can roll over
    # obstacles up to 65 centimeters (25 inches) high" (NASA MSL rover page); 3 m long x
    # 2.7 m wide; can withstand 45 deg of tilt, autonomous drives are limited to 30 deg.
    "msl": TraversabilityThresholds(max_slope_deg=30.0, max_step_m=0.65, max_roughness_m=0.65 / 3,
                                    rover_scale_max_px=3.0 / 2, step_window_m=0.50, footprint_m=3.0, rover="msl"),
}


def rover_profile(name: str) -> TraversabilityThresholds:
    """The limits of a named rover (``cadre``, ``mer``, ``msl``)."""
    if name not in ROVER_PROFILES:
        raise FedmapError(f"unknown rover {name!r}; choose one of {', '.join(ROVER_PROFILES)}")
    return ROVER_PROFILES[name]


def resolved_slope(thresholds: TraversabilityThresholds, truth: GridMap) -> TraversabilityThresholds:
    """``thresholds`` with a percentile slope limit resolved, once, into the degrees it gave on
    ``truth`` (``truth.meta["slope_limit_deg"]``, set by :func:`dem_to_traversability`).

    Every map derived later from part of the same terrain (a rover's few heights, a coarse
    orbital DEM, federated heights) must use those degrees: the percentile of a partial or
    resampled map's own slopes is another limit, and classifies the same slope differently.
    Limits given in degrees come back unchanged."""
    if thresholds.max_slope_percentile is None:
        return thresholds
    limit = truth.meta.get("slope_limit_deg")
    if limit is None:
        raise FedmapError(f"the slope limit p{thresholds.max_slope_percentile:g} is a percentile of the map's slopes, "
                          f"but map {truth.source!r} was not classified from a DEM: give the limit in degrees")
    return replace(thresholds, max_slope_deg=float(limit), max_slope_percentile=None)


def parse_slope_limit(text: str | float) -> dict:
    """``"25"`` -> ``{"max_slope_deg": 25.0}``; ``"p75"`` -> ``{"max_slope_percentile": 75.0}``."""
    raw = str(text).strip().lower()
    key = "max_slope_percentile" if raw.startswith("p") else "max_slope_deg"
    try:
        value = float(raw[1:] if raw.startswith("p") else raw)
    except ValueError:
        raise FedmapError(f"a slope limit is degrees (e.g. 25) or a percentile of the map's slopes (e.g. p75), "
                          f"got {text!r}") from None
    return {key: value}


def window_cells(metres: float | None, pixel_size: float, *, cap: int = 255) -> int:
    """Odd window side in cells covering about ``metres`` (at least 3, at most ``cap``)."""
    if metres is None:
        return 3
    k = int(round(metres / pixel_size))
    k = max(3, k + 1 - k % 2)  # odd, so the window is centred on its cell
    return min(k, cap)


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


def plane_fit(elevation: np.ndarray, size: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares plane over each ``size`` x ``size`` window: slopes along x (columns) and
    y (rows) in metres per cell, and the std of the residual in metres. Border replicated.

    Over a square window with offsets x, y in {-r..r} the basis 1, x, y is orthogonal, so
    the plane's slopes are ``b = sum(x z) / sum(x^2)`` and ``c = sum(y z) / sum(y^2)``, with
    ``sum(x^2) = size * r (r + 1) (2r + 1) / 3``, and the plane explains
    ``(b^2 + c^2) sum(x^2) / size^2`` of the window's variance (3x3: ``6 (b^2 + c^2) / 9``).
    """
    if size < 3 or size % 2 == 0:
        raise FedmapError(f"plane-fit window must be an odd number of cells >= 3, got {size}")
    r = size // 2
    z = elevation.astype(np.float64)
    mean = ndimage.uniform_filter(z, size=size, mode="nearest")
    mean_sq = ndimage.uniform_filter(z * z, size=size, mode="nearest")
    sxx = size * r * (r + 1) * (2 * r + 1) / 3.0
    offsets, ones = np.arange(-r, r + 1, dtype=np.float64), np.ones(size)
    # sum(x z) over the window, separably: offsets along the columns, a plain sum along the rows
    b = ndimage.correlate1d(ndimage.correlate1d(z, offsets, axis=1, mode="nearest"), ones, axis=0, mode="nearest") / sxx
    c = ndimage.correlate1d(ndimage.correlate1d(z, offsets, axis=0, mode="nearest"), ones, axis=1, mode="nearest") / sxx
    var = mean_sq - mean * mean - (b * b + c * c) * sxx / size**2
    return b, c, np.sqrt(np.maximum(var, 0.0))


def roughness(elevation: np.ndarray, size: int = 3) -> np.ndarray:
    """Std of the residual from the least-squares plane of each ``size`` x ``size`` window,
    in metres (:func:`plane_fit`)."""
    return plane_fit(elevation, size)[2]


def footprint_tilt(elevation: np.ndarray, pixel_size: float, size: int) -> np.ndarray:
    """Tilt in degrees of the plane fitted over a ``size`` x ``size`` footprint: the slope a
    rover standing there has (a rock's edge under one wheel is a step, not a slope)."""
    b, c, _ = plane_fit(elevation, size)
    return np.degrees(np.arctan(np.hypot(b, c) / pixel_size))


def window_steps(elevation: np.ndarray, pixel_size: float, size: int, max_step_m: float,
                 max_slope_deg: float) -> np.ndarray:
    """Cells with a step: some cell within the ``size`` x ``size`` window rises or drops more
    than ``max_step_m`` *and* more steeply than ``max_slope_deg`` over the distance between
    their centres (a smooth slope under the limit is never a step). Border replicated."""
    r = size // 2
    z = np.pad(elevation.astype(np.float64), r, mode="edge")
    h, w = elevation.shape
    centre = z[r:r + h, r:r + w]
    tan = math.tan(math.radians(max_slope_deg))
    out = np.zeros((h, w), dtype=bool)
    for dr in range(-r, r + 1):
        for dc in range(-r, r + 1):
            if dr or dc:
                rise = np.abs(z[r + dr:r + dr + h, r + dc:r + dc + w] - centre)
                out |= (rise > max_step_m) & (rise > tan * pixel_size * math.hypot(dr, dc))
    return out


#: Shares of the known cells above which a traversability map is flagged (:func:`class_balance_warning`).
MAX_IMPASSABLE, MAX_FREE = 0.80, 0.99


def class_balance_warning(grid: GridMap, thresholds: TraversabilityThresholds,
                          slope_limit_deg: float | None = None) -> str | None:
    """A one-line warning when the known cells are more than :data:`MAX_IMPASSABLE` impassable
    (a rover could go almost nowhere: its limits may not suit the pixel size) or more than
    :data:`MAX_FREE` free (nothing to avoid). Planetary maps are often 75-85 % free (the
    built-in terrains are), so a mostly free map alone is no warning."""
    known = grid.classes[grid.classes != UNKNOWN]
    if known.size == 0:
        return None
    for cls, name, most in ((FREE, "free", MAX_FREE), (IMPASSABLE, "impassable", MAX_IMPASSABLE)):
        frac = float((known == cls).mean())
        if frac > most:
            return (f"the traversability map is {frac:.1%} {name} at {grid.pixel_size:.3g} m pixels with "
                    f"{thresholds.describe(slope_limit_deg)}: these limits may not suit this pixel size "
                    f"(other limits: --rover NAME, --max-slope DEG, or --max-slope p75 for a coarse DEM)")
    return None


def dem_to_traversability(dem: Dem, thresholds: TraversabilityThresholds | None = None) -> GridMap:
    """Classify every DEM cell as FREE, IMPASSABLE or UNKNOWN (nodata).

    The map keeps the DEM's transform and CRS. ``meta`` records the thresholds, the slope
    limit used (``slope_limit_deg``, from the percentile when one is set) and, when the
    map is more than 99% one class, a one-line ``warning``.
    """
    t = thresholds or TraversabilityThresholds()
    key = (hashlib.blake2b(np.ascontiguousarray(dem.elevation).tobytes(), digest_size=16).digest(),
           dem.elevation.shape, str(dem.elevation.dtype), float(dem.pixel_size), t)
    if _LAST.get("key") != key:
        _LAST.clear()  # one entry: the built-in terrain classifies its DEM to calibrate it, then the truth
        _LAST.update(key=key, value=_classify(dem, t))
    classes, limit = _LAST["value"]
    meta = {"thresholds": t.to_dict(), "dem_source": dem.source, "slope_limit_deg": limit}
    grid = GridMap(classes.copy(), dem.pixel_size, f"traversability({dem.source})", meta, transform=dem.transform,
                   crs=dem.crs)
    warning = class_balance_warning(grid, t, limit)
    if warning is not None:
        grid.meta["warning"] = warning
    return grid


#: The last classification (its DEM's digest, shape, dtype, pixel size and thresholds): the
#: classes are a function of those alone, so a DEM classified twice is classified once.
_LAST: dict = {}


def _classify(dem: Dem, t: TraversabilityThresholds) -> tuple[np.ndarray, float]:
    """The classes of :func:`dem_to_traversability` and the slope limit used."""
    valid = dem.valid
    # Fill nodata with the nearest valid elevation so filters stay finite; the cells
    # touched by nodata are set UNKNOWN below anyway.
    z = dem.elevation
    if not valid.all():
        idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        z = z[tuple(idx)]
    near_nodata = ~ndimage.minimum_filter(valid, size=3, mode="nearest")
    if near_nodata.all():
        raise FedmapError(f"DEM {dem.source} has no cell with a defined slope: too much nodata")
    rover_scale = dem.pixel_size <= t.rover_scale_max_px
    footprint = window_cells(t.footprint_m, dem.pixel_size)
    if rover_scale and t.footprint_m is not None:
        slope = footprint_tilt(z, dem.pixel_size, footprint)  # the rover's tilt over its footprint
    else:
        slope = slope_degrees(z, dem.pixel_size)
    limit = t.max_slope_deg
    if t.max_slope_percentile is not None:
        # the percentile of the cells whose slope is defined; kept inside (0, 90) degrees
        limit = float(np.clip(np.percentile(slope[~near_nodata], t.max_slope_percentile), 1e-6, 89.999))
    bad = slope > limit
    if rover_scale:
        if t.step_window_m is None:
            steep = steepest_rise(z, dem.pixel_size) > np.tan(np.radians(limit))
            bad |= (step_height(z) > t.max_step_m) & steep
        else:
            steps = window_cells(t.step_window_m, dem.pixel_size, cap=31)  # the loop is O(cells^2)
            bad |= window_steps(z, dem.pixel_size, steps, t.max_step_m, limit)
        bad |= roughness(z, footprint) > t.max_roughness_m
    classes = np.where(bad, IMPASSABLE, FREE).astype(np.uint8)
    classes[near_nodata] = UNKNOWN
    return classes, float(limit)
