"""``fedmap export``: a class map in another format (GeoTIFF, ROS map_server, PNG, .npy).

The library does the work (:mod:`fedmap.maps.export`); this module wires the options.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from fedmap.cli.ui import console
from fedmap.errors import FedmapError
from fedmap.maps.export import EXPORT_FORMATS, check_formats, export_map
from fedmap.maps.io import load_map


def export(
    map_: Path = typer.Argument(..., metavar="MAP", help="Class map: .png, .npy, .tif (GeoTIFF) or .yaml (ROS map_server)."),
    format_: str = typer.Option(..., "--format", "-f", help=f"Output format: {', '.join(EXPORT_FORMATS)}."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output file [MAP with the format's suffix]; ros also writes a .pgm beside it."),
    pixel_size: Optional[float] = typer.Option(None, "--pixel-size", help="Metres per cell, when MAP does not store it (.npy)."),
) -> None:
    """Write a class map as a GeoTIFF (classes + colour table + CRS + transform), a ROS map_server map, a PNG or a .npy."""
    (fmt,) = check_formats([format_])
    grid = load_map(map_, pixel_size=pixel_size)
    target = out if out is not None else map_.with_suffix(EXPORT_FORMATS[fmt])
    if target.resolve() == map_.resolve():
        raise FedmapError(f"exporting {map_} as {fmt} would overwrite it; pass -o")
    written = export_map(grid, target, fmt)
    f = grid.fractions()
    georef = "no georeferencing (a local metric frame)" if grid.transform is None else (
        "georeferenced" + ("" if grid.crs else ", no CRS"))
    console.print(f"{', '.join(str(p) for p in written)}: {grid.shape[0]}x{grid.shape[1]} cells of {grid.pixel_size:.4g} m, "
                  f"{georef}; {f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown",
                  soft_wrap=True)
