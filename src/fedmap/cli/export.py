"""``fedmap export``: a class map in another format (GeoTIFF, ROS map_server, PNG, .npy,
ROS 2 bag), or every map of a mission folder's ``maps/``.

The library does the work (:mod:`fedmap.maps.export`, :mod:`fedmap.mission.outputs.maps_out`);
this module wires the options.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from fedmap.cli.ui import console
from fedmap.errors import FedmapError
from fedmap.maps.export import EXPORT_FORMATS, KEEPS_GEOREF, check_formats, export_map
from fedmap.maps.grid import GridMap
from fedmap.maps.io import load_map
from fedmap.maps.rosbag import is_bag
from fedmap.mission.outputs.maps_out import reexport_mission_maps


def _line(grid: GridMap, written: list[Path], fmt: str, topic: str = "") -> None:
    """One line per map written: its size and classes, and what the written file holds of its georeferencing."""
    f = grid.fractions()
    keeps = KEEPS_GEOREF[fmt]
    if grid.transform is None:
        georef = "no georeferencing (a local metric frame)"
    elif keeps is None:
        georef = f"not georeferenced: {fmt} holds no georeferencing (the map's is lost; geotiff keeps it)"
    else:
        georef = f"georeferenced ({keeps})" + ("" if grid.crs or "no CRS" in keeps else ", the map has no CRS")
    console.print(f"{', '.join(str(p) for p in written)}{topic}: {grid.shape[0]}x{grid.shape[1]} cells of {grid.pixel_size:.4g} m, "
                  f"{georef}; {f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown",
                  soft_wrap=True)


def export(
    map_: Path = typer.Argument(..., metavar="MAP", help="Class map: .png, .npy, .tif (GeoTIFF), .yaml (ROS map_server) or a "
                                "ROS 2 bag (folder, .db3, .mcap: its last OccupancyGrid); or a mission folder: every map "
                                "under its maps/."),
    format_: str = typer.Option(..., "--format", "-f", help=f"Output format: {', '.join(EXPORT_FORMATS)}."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output file [MAP with the format's suffix]; ros also writes a "
                                       ".pgm beside it; rosbag2 writes a bag folder [MAP without its suffix]. With a mission "
                                       "folder: the output folder (default: its maps/; rosbag2: one bag maps_bag/ in it, a "
                                       "topic per map)."),
    pixel_size: Optional[float] = typer.Option(None, "--pixel-size", help="Metres per cell, when MAP does not store it (.npy)."),
) -> None:
    """Write a class map as a GeoTIFF (classes + colour table + CRS + transform), a ROS map_server map, a PNG, a .npy
    or a ROS 2 bag (one nav_msgs/OccupancyGrid on /map, frame map, sqlite3 storage, for ros2 bag play).

    MAP may be a mission folder: every map under its maps/ is re-exported, each read from its GeoTIFF where there is one.
    """
    (fmt,) = check_formats([format_])
    if map_.is_dir() and not is_bag(map_):  # a mission folder: its maps/, each read from its GeoTIFF where there is one
        for grid, written in reexport_mission_maps(map_, fmt, out=out, pixel_size=pixel_size):
            _line(grid, written, fmt, f" /{Path(grid.source).stem}" if fmt == "rosbag2" else "")
        return
    grid = load_map(map_, pixel_size=pixel_size)
    target = out if out is not None else map_.with_suffix(EXPORT_FORMATS[fmt])
    if target.resolve() == map_.resolve():
        raise FedmapError(f"exporting {map_} as {fmt} would overwrite it; pass -o")
    _line(grid, export_map(grid, target, fmt), fmt, " /map" if fmt == "rosbag2" else "")
