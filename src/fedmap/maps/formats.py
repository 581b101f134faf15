"""fedmap's own DEM reader for the one format GDAL has no driver for: RGB-packed heightmap
PNG tiles (``metres = R + 256 G + 65536 B - offset``, e.g. the GLD100 256p tiles).

Every other DEM format is read through rasterio (GDAL) by :func:`fedmap.maps.io.load_dem`,
which also calls this reader for ``.png`` files.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from fedmap._util import one_line as _one_line
from fedmap.errors import FedmapError


def _pil_errors() -> tuple[type[BaseException], ...]:
    """What Pillow raises for unreadable, truncated or corrupt images."""
    from PIL import Image, UnidentifiedImageError

    return (UnidentifiedImageError, ValueError, OSError, EOFError, SyntaxError, struct.error, zlib.error,
            Image.DecompressionBombError)


#: Elevation offset of RGB-packed heightmap tiles: ``metres = R + 256 G + 65536 B - offset``.
HEIGHTMAP_OFFSET_M: float = 10000.0


# --------------------------------------------------------------------------- heightmap PNG


def read_heightmap_png(path: Path, *, offset: float = HEIGHTMAP_OFFSET_M, zero_is_nodata: bool = True) -> np.ndarray:
    """Read an RGB-packed heightmap tile: ``metres = R + 256 G + 65536 B - offset``.

    A raw value of 0 (all channels 0, i.e. ``-offset`` m) is a gap in such tiles and is
    nodata unless ``zero_is_nodata=False``. Alpha is ignored. Grey or paletted PNGs are
    refused: they are maps or pictures, not packed elevations. Returns metres, (H, W)
    float64 with NaN gaps; the file holds no ground spacing.
    """
    from PIL import Image

    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            if mode not in ("RGB", "RGBA"):
                raise FedmapError(f"DEM {path} is a {mode} PNG: a heightmap PNG must be RGB-packed "
                                  f"(metres = R + 256 G + 65536 B - offset); load class maps with --map")
            rgb = np.asarray(img.convert("RGB"), dtype=np.int64)
    except _pil_errors() as exc:
        raise FedmapError(f"cannot read DEM {path}: not a valid PNG image ({_one_line(exc)})") from exc
    packed = rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2]
    metres = packed.astype(np.float64) - float(offset)
    if zero_is_nodata:
        metres[packed == 0] = np.nan
    return metres
