"""Georeferencing of grids: the affine transform and CRS a map or DEM carries, and the
ground size of its cells in metres.

A grid's ``transform`` maps (column, row) cell coordinates to the CRS's (x, y), with
(0, 0) the top-left corner of the top-left cell, as in GDAL and rasterio
(:class:`affine.Affine`). fedmap keeps grids north-up: row 0 is the top (largest y), so
``transform.e < 0`` and there is no rotation. The ``crs`` is kept as WKT text (None for
generated terrain), so maps stay plain data that pickles and prints.

Cell sizes in metres (:func:`cell_size_m`): a projected CRS's linear unit is converted to
metres; a geographic CRS's degrees are converted on *that body's* ellipsoid, read from
the CRS (the Moon's 1,737.4 km sphere, Mars's 3,396.19 km ellipsoid, ...) at the grid's
centre latitude, with the meridional radius for north-south and the prime-vertical
radius times cos(latitude) for east-west spacing.
"""

from __future__ import annotations

import math
import re

import numpy as np
from affine import Affine

from fedmap.errors import FedmapError


def crs_wkt(crs) -> str | None:
    """WKT text of anything rasterio reads as a CRS (a CRS object, ``"EPSG:4326"``,
    ``"IAU_2015:30100"``, a PROJ string, WKT), or None for None/empty."""
    if crs is None or crs == "":
        return None
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    try:
        c = crs if isinstance(crs, CRS) else CRS.from_user_input(crs)
    except (CRSError, ValueError, TypeError) as exc:
        raise FedmapError(f"not a coordinate reference system: {str(crs)[:80]!r} ({' '.join(str(exc).split())})") from exc
    return c.to_wkt()


def crop_transform(transform: Affine | None, row0: int, col0: int) -> Affine | None:
    """The transform of a window whose top-left cell is (row0, col0) of the original grid."""
    return None if transform is None else transform @ Affine.translation(col0, row0)


def scale_transform(transform: Affine | None, old_shape: tuple[int, int], new_shape: tuple[int, int]) -> Affine | None:
    """The transform after resampling the same extent from ``old_shape`` to ``new_shape`` cells."""
    if transform is None:
        return None
    return transform @ Affine.scale(old_shape[1] / new_shape[1], old_shape[0] / new_shape[0])


def cell_centre(transform: Affine, row: float, col: float) -> tuple[float, float]:
    """CRS (x, y) of the centre of cell (row, col)."""
    x, y = transform @ (col + 0.5, row + 0.5)
    return float(x), float(y)


def cell_of(transform: Affine, x: float, y: float) -> tuple[int, int]:
    """The cell (row, col) that CRS point (x, y) falls in (the inverse of :func:`cell_centre`;
    it may lie outside the grid)."""
    col, row = ~transform @ (x, y)
    return math.floor(row), math.floor(col)


def local_transform(pixel_size: float, shape: tuple[int, int]) -> Affine:
    """A metric north-up transform with the map's lower-left corner at (0, 0): the frame of a
    grid that has no georeferencing of its own (generated terrain)."""
    return Affine(pixel_size, 0.0, 0.0, 0.0, -pixel_size, shape[0] * pixel_size)


def check_north_up(transform: Affine, what: str) -> None:
    """Refuse rotated or sheared transforms: a fedmap grid has rows along x and columns along y."""
    if transform.b != 0 or transform.d != 0:
        raise FedmapError(f"{what} has a rotated geotransform ({transform.b:g}, {transform.d:g} rotation terms); "
                          f"fedmap needs north-up rows: warp it first (e.g. gdalwarp)")
    if transform.a == 0 or transform.e == 0:
        raise FedmapError(f"{what} has a degenerate geotransform (zero cell size)")


def north_up(grid: np.ndarray, transform: Affine, what: str) -> tuple[np.ndarray, Affine, list[str]]:
    """Flip a south-up or east-to-west grid (and its transform) so that row 0 is north and
    column 0 is west; a rotated transform is refused. Returns the grid, its transform and
    what was flipped."""
    check_north_up(transform, what)
    flipped = []
    h, w = grid.shape[:2]
    if transform.e > 0:
        grid, transform = grid[::-1], transform @ Affine.translation(0, h) @ Affine.scale(1, -1)
        flipped.append("rows (south-up file)")
    if transform.a < 0:
        grid, transform = grid[:, ::-1], transform @ Affine.translation(w, 0) @ Affine.scale(-1, 1)
        flipped.append("columns (east-to-west file)")
    return np.ascontiguousarray(grid), transform, flipped


def _ellipsoid(wkt: str) -> tuple[float, float]:
    """(semi-major axis, inverse flattening) of the first ELLIPSOID/SPHEROID in a WKT."""
    m = re.search(r'(?:SPHEROID|ELLIPSOID)\["[^"]*",\s*([-+0-9.eE]+),\s*([-+0-9.eE]+)', wkt)
    if m is None:
        raise FedmapError("the CRS names no ellipsoid, so degrees cannot be turned into metres; pass pixel_size")
    return float(m.group(1)), float(m.group(2))


def body_radii(crs, lat_deg: float) -> tuple[float, float]:
    """(meridional, prime-vertical) radius of curvature in metres of the CRS's ellipsoid at
    ``lat_deg``: the metres per radian north-south and, times cos(lat), east-west."""
    a, inv_f = _ellipsoid(crs_wkt(crs) or "")
    f = 0.0 if inv_f == 0 else 1.0 / inv_f
    e2 = f * (2.0 - f)
    s2 = math.sin(math.radians(lat_deg)) ** 2
    w = math.sqrt(1.0 - e2 * s2)
    return a * (1.0 - e2) / w**3, a / w


#: How far (a ratio) a geographic grid's east-west cell size may drift from the one used
#: (its centre latitude's) across the grid before the user is told.
LATITUDE_SPREAD = 1.05


def cell_size_m(crs, transform: Affine, shape: tuple[int, int]) -> tuple[float, float, dict]:
    """Ground size (dx, dy) of a cell in metres and how it was found.

    Projected CRS: the transform's cell size times the linear unit in metres.
    Geographic CRS: degrees on the CRS's own ellipsoid at the grid's centre latitude.
    """
    from rasterio.crs import CRS

    c = CRS.from_wkt(crs_wkt(crs) or "")
    sx, sy = abs(transform.a), abs(transform.e)
    if c.is_geographic:
        _unit, rad_per_unit = c.units_factor
        _x, lat_c = transform @ (shape[1] / 2.0, shape[0] / 2.0)
        lat_deg = math.degrees(lat_c * rad_per_unit)
        if not -90.0 <= lat_deg <= 90.0:
            raise FedmapError(f"geographic grid has centre latitude {lat_deg:.3f} deg; pass pixel_size")
        m_rad, n_rad = body_radii(c, lat_deg)
        dx = sx * rad_per_unit * n_rad * math.cos(math.radians(lat_deg))
        dy = sy * rad_per_unit * m_rad
        info = {"crs_kind": "geographic", "centre_lat_deg": lat_deg, "radius_m": n_rad}
        # one cell size serves the whole grid: say so where it is far from true (a wide span of latitude)
        _x0, lat_a = transform @ (0.0, 0.0)
        _x1, lat_b = transform @ (0.0, float(shape[0]))
        lats = sorted(math.degrees(v * rad_per_unit) for v in (lat_a, lat_b))
        if -90.0 <= lats[0] and lats[1] <= 90.0:
            ew = [sx * rad_per_unit * body_radii(c, la)[1] * math.cos(math.radians(la)) for la in lats]
            if max(ew) > LATITUDE_SPREAD * dx or min(ew) * LATITUDE_SPREAD < dx:
                info["latitude_note"] = (
                    f"the DEM spans latitudes {lats[0]:.2f} to {lats[1]:.2f} deg: its cells are {min(ew):,.0f} to "
                    f"{max(ew):,.0f} m east-west across it, and the run takes them all as {dx:,.0f} m (true at its "
                    "centre latitude): crop it, or reproject it to an equal-area or local projection first")
    else:
        _unit, factor = c.linear_units_factor
        dx, dy = sx * factor, sy * factor
        info = {"crs_kind": "projected", "linear_unit_m": factor}
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise FedmapError(f"unusable ground spacing ({dx}, {dy}) m from the CRS; pass pixel_size")
    return dx, dy, info


def is_metric(crs) -> bool:
    """True when the CRS is None (a local metric frame) or projected in metres."""
    if crs is None:
        return True
    from rasterio.crs import CRS

    c = CRS.from_wkt(crs_wkt(crs) or "")
    return bool(c.is_projected and abs(c.linear_units_factor[1] - 1.0) < 1e-12)
