"""The real terrains ``fedmap reproduce --data DIR`` maps, as :class:`~fedmap.maps.sources.TerrainSource` s.

``DIR`` is a folder laid out like the project's shared data folder (``mars/``, ``moon/``,
``ice/``; see its README). Nothing here is shipped: without the folder, ``reproduce``
uses the built-in terrains.

Traversability thresholds follow the ground size of a cell. At rover scale (Gale, 1–2 m
cells) the rover limits apply (15° slope, 0.3 m steps, 0.15 m roughness). At orbital
scale (hundreds of metres to kilometres per cell) a cell's mean slope is far gentler than
the slopes inside it, so the slope limit is lowered until the map is not trivially
free; each limit is stated here and in the report.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.maps.traversability import TraversabilityThresholds

GLD100_PX = 118.45  # metres: 1 degree of the 1737.4 km sphere over 256 px

#: name -> (description, source with paths relative to the data folder)
REAL_TERRAINS: dict[str, tuple[str, TerrainSource]] = {
    "mars-gale": ("Mars, Gale crater (HiRISE 1 m DEM, central 256 m), 15 deg slope",
                  TerrainSource(kind="dem", path="mars/missionDEM_gale_1m.tif", crop=256)),
    "mars-mola": ("Mars, Tharsis and Valles Marineris (MOLA MEGDR, 128x128 cells of 14.8 km), 2 deg slope",
                  TerrainSource(kind="dem", path="mars/mola_megt90n000cb.img", crop=(280, 408, 1100, 1228),
                                options={"shape": [720, 1440], "dtype": "int16", "byteorder": "big",
                                         "pixel_size": 14_818.0},
                                thresholds=TraversabilityThresholds(max_slope_deg=2.0))),
    "moon-hadley": ("Moon, Apollo 15 / Hadley Rille (LROC WAC GLD100, 8x8 tiles), 10 deg slope",
                    TerrainSource(kind="tiles", path="moon/gld100_256p", lon=0, lat=22, tiles=8,
                                  options={"pixel_size": GLD100_PX},
                                  thresholds=TraversabilityThresholds(max_slope_deg=10.0))),
    # the centred square leaves out column 0, an all-zero border
    "ice-columbia": ("Ice, Columbia Glacier, Alaska (OGGM 100 m DEM), 15 deg slope",
                     TerrainSource(kind="dem", path="ice/test-files_columbia_dem_Columbia.tif")),
}


def load_real(data: Path, name: str, size: int) -> GridMap:
    """Ground truth of the real terrain ``name`` from the data folder, resampled to ``size``."""
    if name not in REAL_TERRAINS:
        raise FedmapError(f"unknown real terrain {name!r}; choose from {', '.join(REAL_TERRAINS)}")
    desc, src = REAL_TERRAINS[name]
    assert src.path is not None  # every real terrain is a file or tile source
    path = Path(data) / src.path
    if not path.exists():
        raise FedmapError(f"{name}: {path} is missing from the data folder {data}")
    truth = load_truth(replace(src, path=str(path), size=size))
    truth.source = desc
    return truth
