"""Class maps as GeoTIFF: uint8 class codes with a colour table, the CRS and the transform.

A map written here opens in QGIS (or any GIS) in the paper's colours, on top of the DEM
it came from: it carries the DEM's CRS and affine transform (a cropped or resampled
grid's transform is moved with it, :mod:`fedmap.maps.regrid`). A map without
georeferencing (generated terrain) gets a local metric frame with its lower-left corner
at (0, 0) and no CRS. The pixel size in metres is also stored as the dataset tag
``FEDMAP_PIXEL_SIZE`` so that a geographic map reads back with its exact pixel size.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from fedmap._util import atomic_write_bytes
from fedmap._util import one_line as _one_line
from fedmap.errors import FedmapError
from fedmap.maps.georef import cell_size_m, local_transform, north_up
from fedmap.maps.grid import FREE, IMPASSABLE, PALETTE, UNKNOWN, GridMap, check_classes

#: Colour table of the class codes (RGBA 0..255): the paper's colours.
CLASS_COLORMAP: dict[int, tuple[int, int, int, int]] = {
    c: (*(int(round(v * 255)) for v in PALETTE[c]), 255) for c in (FREE, IMPASSABLE, UNKNOWN)  # type: ignore[misc]
}

PIXEL_SIZE_TAG = "FEDMAP_PIXEL_SIZE"


def class_geotiff_bytes(grid: GridMap) -> bytes:
    """The GeoTIFF file of a class map (deflate-compressed, one uint8 band, colour table)."""
    from rasterio.io import MemoryFile

    h, w = grid.shape
    transform = grid.transform if grid.transform is not None else local_transform(grid.pixel_size, grid.shape)
    with MemoryFile() as mem:
        with mem.open(driver="GTiff", height=h, width=w, count=1, dtype="uint8", crs=grid.crs, transform=transform,
                      compress="deflate", photometric="palette") as dst:
            dst.write(np.ascontiguousarray(grid.classes, dtype=np.uint8), 1)
            dst.write_colormap(1, CLASS_COLORMAP)
            dst.set_band_description(1, "traversability class: 0 free, 1 impassable, 2 unknown")
            dst.update_tags(**{PIXEL_SIZE_TAG: repr(float(grid.pixel_size)), "FEDMAP_SOURCE": grid.source[:200]})
        return mem.read()


def write_class_geotiff(grid: GridMap, path) -> None:
    """Write ``grid`` as a class GeoTIFF at ``path``, atomically."""
    atomic_write_bytes(Path(path), class_geotiff_bytes(grid))


def read_class_geotiff(path) -> GridMap:
    """Read a class GeoTIFF (band 1 holds 0 free, 1 impassable, 2 unknown) with its CRS and
    transform. Pixel size: the ``FEDMAP_PIXEL_SIZE`` tag, else from the CRS, else the
    transform's cell size taken as metres, else 1.0."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioError

    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as src:
                classes = src.read(1)
                georef = not (src.transform.is_identity and src.crs is None)
                transform = src.transform if georef else None
                crs = src.crs.to_wkt() if src.crs else None
                tag = src.tags().get(PIXEL_SIZE_TAG)
    except RasterioError as exc:
        raise FedmapError(f"cannot read map {path}: {_one_line(exc)}") from exc
    classes = check_classes(classes, f"map {path}")
    meta: dict = {"format": "geotiff"}
    if transform is not None:
        classes, transform, flipped = north_up(classes, transform, f"map {path}")
        if flipped:
            meta["flipped"] = flipped
    if tag is not None:
        try:
            px, meta["pixel_size_from"] = float(tag), "file"
        except ValueError:
            raise FedmapError(f"cannot read map {path}: bad {PIXEL_SIZE_TAG} tag {tag!r}") from None
    elif transform is not None and crs is not None:
        dx, dy, _info = cell_size_m(crs, transform, classes.shape)
        px, meta["pixel_size_from"] = float(np.sqrt(dx * dy)), "crs"
    elif transform is not None:
        px, meta["pixel_size_from"] = float(np.sqrt(abs(transform.a * transform.e))), "transform (assumed metres)"
    else:
        px, meta["pixel_size_from"] = 1.0, "default"
    return GridMap(classes, px, str(path), meta, transform=transform, crs=crs)
