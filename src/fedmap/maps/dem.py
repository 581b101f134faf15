"""Digital elevation models: elevation in metres with NaN as nodata."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from affine import Affine

from fedmap.errors import FedmapError


@dataclass
class Dem:
    """Elevation grid in metres.

    Parameters
    ----------
    elevation : ndarray (H, W) float32
        Metres; NaN marks nodata.
    pixel_size : float
        Ground size of one cell in metres.
    source : str
        File path or generator settings.
    meta : dict
        What the reader found (format, nodata, CRS notes, ...).
    transform : affine.Affine, optional
        Cell (col, row) -> CRS (x, y), north-up (:mod:`fedmap.maps.georef`); None for
        generated terrain.
    crs : str, optional
        The CRS as WKT, or None.
    """

    elevation: np.ndarray
    pixel_size: float
    source: str = ""
    meta: dict = field(default_factory=dict)
    transform: Affine | None = None
    crs: str | None = None

    def __post_init__(self) -> None:
        e = np.asarray(self.elevation, dtype=np.float32)
        if e.ndim != 2:
            raise FedmapError(f"a DEM must be 2-D, got shape {e.shape}")
        if min(e.shape) < 3:
            raise FedmapError(f"a DEM must be at least 3x3, got {e.shape[0]}x{e.shape[1]}")
        e = np.where(np.isinf(e), np.nan, e).astype(np.float32)
        if not np.isfinite(e).any():
            raise FedmapError(f"DEM {self.source or ''} holds no valid elevation: every cell is nodata".replace("  ", " "))
        self.elevation = e
        if not np.isfinite(self.pixel_size) or self.pixel_size <= 0:
            raise FedmapError(f"DEM pixel size must be a positive number of metres, got {self.pixel_size}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.elevation.shape

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.elevation)
