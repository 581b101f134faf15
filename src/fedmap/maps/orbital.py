"""An orbital prior: what an orbiter's coarse DEM says about traversability before any
rover has looked.

:func:`orbital_prior` block-averages the site's DEM ``factor`` times (the area mean of
:func:`~fedmap.maps.regrid.resample_dem`), classifies it with the rover's thresholds at
that resolution (:func:`~fedmap.maps.traversability.dem_to_traversability`, which sees
the coarser cell size), and spreads each coarse class back over the cells it covers. At
a coarse resolution slopes are averaged out, so the prior misses small hazards; it is a
guess to plan with, never an observation.
"""

from __future__ import annotations

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.regrid import resample_dem
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability


def orbital_prior(dem: Dem, thresholds: TraversabilityThresholds | None, factor: int) -> np.ndarray:
    """``dem.shape`` classes: the traversability of the DEM block-averaged ``factor`` times,
    upsampled (nearest) back to the DEM's grid."""
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 2:
        raise FedmapError(f"the orbital prior's factor must be an integer >= 2, got {factor!r}")
    h, w = dem.shape
    ch, cw = -(-h // factor), -(-w // factor)
    if min(ch, cw) < 4:
        raise FedmapError(f"an orbital prior {factor}x coarser than a {h}x{w} map has fewer than 4 cells a side")
    coarse = dem_to_traversability(resample_dem(dem, (ch, cw), method="area"), thresholds).classes
    rows = np.minimum(((np.arange(h) + 0.5) * ch / h).astype(np.intp), ch - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * cw / w).astype(np.intp), cw - 1)
    return coarse[np.ix_(rows, cols)].astype(np.uint8)
