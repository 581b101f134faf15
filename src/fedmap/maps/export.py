"""Writing class maps in the formats other tools open: GeoTIFF (QGIS, GDAL), ROS
map_server (YAML + PGM), PNG (the paper's colours), ``.npy`` (class codes) and ROS 2 bags
(``nav_msgs/OccupancyGrid``, :mod:`fedmap.maps.rosbag`).

:func:`export_map` writes one map in one format; :func:`export_maps` writes a set of maps
that share a frame (a run's truth, local, global and refined maps), giving each map
without georeferencing of its own the frame's transform and CRS, so that every output
overlays the DEM it came from.

A bag is a folder: ``rosbag2`` has no suffix. One map is a bag with one message on
``/map``; a set of maps is one bag, :data:`BAG_NAME`, with a topic ``/<name>`` per map.
"""

from __future__ import annotations

from pathlib import Path

from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.rosbag import write_map_bag, write_maps_bag

#: Export format -> file suffix (``ros`` also writes a ``.pgm`` beside the ``.yaml``; a
#: ``rosbag2`` bag is a folder, named as given, without a suffix).
EXPORT_FORMATS: dict[str, str] = {"geotiff": ".tif", "ros": ".yaml", "png": ".png", "npy": ".npy", "rosbag2": ""}
#: What each format keeps of a map's georeferencing (None: nothing; a .png keeps it in its
#: ``.aux.xml`` sidecar).
KEEPS_GEOREF: dict[str, str | None] = {"geotiff": "transform and CRS", "ros": "origin only, no CRS",
                                       "png": "transform and CRS in its .aux.xml sidecar", "npy": None,
                                       "rosbag2": "origin only, no CRS"}
#: The bag :func:`export_maps` writes a set of maps into (a folder in the output folder).
BAG_NAME = "maps_bag"


def check_formats(formats) -> tuple[str, ...]:
    """The formats as a tuple; an unknown one is a one-line error listing the known ones."""
    out = tuple(str(f).strip().lower() for f in (formats or ()))
    for f in out:
        if f not in EXPORT_FORMATS:
            raise FedmapError(f"unknown export format {f!r}; choose one of {', '.join(EXPORT_FORMATS)}")
    return out


def export_map(grid: GridMap, path, fmt: str | None = None) -> list[Path]:
    """Write ``grid`` to ``path`` in ``fmt`` (default: from the suffix); returns the files written.

    The suffix is set to the format's when ``fmt`` is given.
    """
    from fedmap.maps.io import save_map  # io reads and writes every format; this module picks one

    path = Path(path)
    if fmt is not None and check_formats([fmt]) == ("rosbag2",):  # a folder, named as given
        return [write_map_bag(grid, path)]
    if fmt is None:
        by_suffix = {v: k for k, v in EXPORT_FORMATS.items() if v} | {".tiff": "geotiff", ".yml": "ros"}
        if path.suffix.lower() not in by_suffix:
            raise FedmapError(f"cannot tell the export format of {path}; use one of {', '.join(EXPORT_FORMATS)}")
        fmt = by_suffix[path.suffix.lower()]
    (fmt,) = check_formats([fmt])
    if path.suffix.lower() != EXPORT_FORMATS[fmt] and not (fmt == "geotiff" and path.suffix.lower() == ".tiff"):
        path = path.with_suffix(EXPORT_FORMATS[fmt])
    save_map(grid, path)
    return [path, path.with_suffix(".pgm")] if fmt == "ros" else [path]


def in_frame(grid: GridMap, frame: GridMap | None) -> GridMap:
    """``grid`` with the ``frame``'s transform and CRS when it has none of its own."""
    if frame is None or grid.transform is not None or frame.transform is None:
        return grid
    if grid.shape != frame.shape:
        raise FedmapError(f"map {grid.source} is {grid.shape[0]}x{grid.shape[1]}, its frame "
                          f"{frame.shape[0]}x{frame.shape[1]}")
    return GridMap(grid.classes, grid.pixel_size, grid.source, dict(grid.meta), transform=frame.transform,
                   crs=frame.crs)


def export_maps(maps: dict[str, GridMap], folder, formats, *, frame: GridMap | None = None) -> list[Path]:
    """Write each map as ``folder/<name><suffix>`` in each format (``rosbag2``: all maps in
    one bag ``folder/maps_bag``, a topic ``/<name>`` each); returns the files written."""
    folder = Path(folder)
    written: list[Path] = []
    for fmt in check_formats(formats):
        if fmt == "rosbag2":
            written.append(write_maps_bag({n: in_frame(g, frame) for n, g in maps.items()}, folder / BAG_NAME))
            continue
        for name, grid in maps.items():
            written += export_map(in_frame(grid, frame), folder / f"{name}{EXPORT_FORMATS[fmt]}", fmt)
    return written
