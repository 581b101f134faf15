"""Reading and writing traversability maps and DEMs.

Maps (:func:`load_map`, :func:`save_map`)
-----------------------------------------
``.png``
    *RGB/RGBA* pixels go to the class of the nearest palette colour (green free, red
    impassable, grey unknown); alpha is ignored. *Grayscale* (L, I;16, LA, or a
    palette image whose used colours are all grey) must hold only the values 0, 1, 2,
    read as class indices; other grey values are an error, because a grey level has no
    meaningful nearest class colour (every grey is nearest to "unknown"). Other palette
    images are converted to RGB. :func:`save_map` writes the 8-bit RGB rendering, which
    reads back to exactly the same classes, and stores the pixel size in a PNG text
    chunk (``fedmap:pixel_size``) that :func:`load_map` uses when no ``pixel_size`` is
    passed.
``.npy``
    An integer ``(H, W)`` array of classes 0..2, a float ``(H, W, 3)`` RGB array in
    [0, 1], or a ``uint8`` ``(H, W, 3)`` RGB array in 0..255. There is no metadata, so
    the caller passes ``pixel_size``. :func:`save_map` writes the ``uint8`` class array.

Without a ``pixel_size`` argument (or PNG text chunk) a map's pixel size is 1.0 m.

DEMs (:func:`load_dem`)
-----------------------
``.tif`` / ``.tiff``
    The first page (first band if it has several samples), integer or float.

    * nodata: the ``nodata`` argument if given, else the ``GDAL_NODATA`` tag (42113)
      if present. Matching cells and non-finite values become NaN. GDAL's per-band
      ``scale``/``offset`` (in the ``GDAL_METADATA`` tag) are applied when present.
    * pixel size: the ``pixel_size`` argument if given, else from ``ModelPixelScaleTag``
      (33550) or ``ModelTransformationTag`` (34264), in the projection's linear unit
      (metres, feet, US survey feet, kilometres). If the GeoKeys (34735) say the raster
      is geographic (``GTModelTypeGeoKey`` = 2, angles), the angular spacing is
      converted to metres at the raster's centre latitude (from ``ModelTiepointTag``
      33922) on a sphere whose radius is the mean radius ``(2a + b) / 3`` of the
      ellipsoid the GeoKeys declare, or 6 371 000 m (Earth) when they declare none.
      For a geographic raster of another body whose file does not name its ellipsoid,
      pass ``pixel_size``.
    * non-square cells: a DEM has one pixel size, so when the ground spacing along x and
      y differs by more than 1% (any geographic raster away from the equator) the
      coarser axis is resampled by linear interpolation to the finer spacing, so that
      slopes computed with one pixel size are right. The shape then differs from the
      file's; ``meta["resampled"]`` records it. Passing ``pixel_size`` disables this.
    * without any georeferencing the pixel size is 1.0 m.
``.npy``
    A 2-D real array; ``pixel_size`` argument, default 1.0 m.
``.asc``
    ESRI ASCII grid (:func:`fedmap.maps.formats.read_ascii_grid`): header keys in any
    case, ``xllcorner``/``xllcenter``, ``cellsize`` or ``dx``/``dy`` (non-square cells
    are resampled as for GeoTIFF), ``NODATA_value``. The unit is not in the file:
    ``cellsize`` is taken as metres unless a ``.prj`` sidecar says geographic or the
    option ``geographic=True`` is given (degrees -> metres at the centre latitude on a
    sphere of ``radius_m``, default Earth); a degree-sized ``cellsize`` without either is
    refused. ``pixel_size`` overrides it all.
``.img`` / ``.raw``
    Raw PDS-style samples (:func:`fedmap.maps.formats.read_raw`), laid out by a PDS3
    label (attached, or a ``.lbl`` sidecar) or by the options ``shape=(rows, cols)``,
    ``dtype`` (default ``"int16"``), ``byteorder`` (``"big"``, default, or ``"little"``),
    ``header_bytes`` (default 0). The file size must match exactly. Pixel size from the
    label's ``MAP_SCALE``/``MAP_RESOLUTION``, else ``pixel_size``, default 1.0 m.
``.png``
    RGB-packed heightmap tile (:func:`fedmap.maps.formats.read_heightmap_png`):
    ``metres = R + 256 G + 65536 B - offset`` (option ``offset``, default 10000); raw 0
    is nodata unless ``zero_is_nodata=False``; the ``nodata`` argument compares metres.
    Grey or paletted PNGs are refused (those are class maps: :func:`load_map`). The file
    has no georeferencing: pass ``pixel_size`` (default 1.0 m).
    :func:`mosaic_tiles` joins a grid of tiles, :func:`mosaic_heightmap_tiles` GLD100-named
    ones (``256p+{lon}+{lat}.png``, 118.45 m pixels).

``nodata`` compares the stored values (before a file's scale/offset). ``Dem.meta``
records ``format``, ``nodata``, ``nodata_from`` ("argument", the format, or None),
``nodata_cells`` and ``pixel_size_from`` ("argument", the format, or "default").
:func:`resample_dem`, :func:`crop_dem` and :func:`centre_crop` (from
:mod:`fedmap.maps.regrid`) fit a DEM to a run's grid.

Every user-facing problem (missing file, unreadable or corrupt file, wrong shape,
unsupported suffix, DEM entirely nodata) raises :class:`~fedmap.errors.FedmapError`
with a one-line message naming the file. All writes are atomic
(:func:`atomic_write_bytes`).
"""

from __future__ import annotations

import io
import logging
import math
import pickle
import struct
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path
from typing import SupportsInt, cast

import numpy as np

from fedmap._util import atomic_write_bytes  # noqa: F401  (part of this API)
from fedmap._util import one_line as _one_line
from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.formats import EARTH_RADIUS_M, READERS, _pil_errors
from fedmap.maps.grid import UNKNOWN, GridMap, classes_from_rgb, render_classes
from fedmap.maps.regrid import centre_crop, crop_dem, resample_dem  # noqa: F401  (part of this API)

MAP_SUFFIXES: tuple[str, ...] = (".png", ".npy")
DEM_SUFFIXES: tuple[str, ...] = (".tif", ".tiff", ".npy", ".asc", ".img", ".raw", ".png")


#: Relative difference of x and y ground spacing above which a DEM is resampled.
SQUARE_TOLERANCE: float = 0.01

PNG_PIXEL_SIZE_KEY = "fedmap:pixel_size"

# GeoTIFF tags and keys.
_TAG_PIXEL_SCALE = 33550
_TAG_TIEPOINT = 33922
_TAG_TRANSFORMATION = 34264
_TAG_GEOKEYS = 34735
_TAG_GEODOUBLES = 34736
_TAG_GEOASCII = 34737
_TAG_GDAL_METADATA = 42112
_TAG_GDAL_NODATA = 42113
_KEY_MODEL_TYPE = 1024
_KEY_RASTER_TYPE = 1025
_KEY_ANGULAR_UNITS = 2054
_KEY_SEMI_MAJOR = 2057
_KEY_SEMI_MINOR = 2058
_KEY_INV_FLATTENING = 2059
_KEY_LINEAR_UNITS = 3076
_MODEL_PROJECTED, _MODEL_GEOGRAPHIC = 1, 2
_RASTER_PIXEL_IS_POINT = 2
_LINEAR_UNITS_M = {9001: 1.0, 9002: 0.3048, 9003: 1200.0 / 3937.0, 9030: 1852.0, 9036: 1000.0}
_ANGULAR_UNITS_DEG = {9101: 180.0 / math.pi, 9102: 1.0, 9103: 1.0 / 60.0, 9104: 1.0 / 3600.0, 9105: 0.9}


# --------------------------------------------------------------------------- helpers


def _suffix(path: Path, supported: tuple[str, ...], what: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in supported:
        raise FedmapError(
            f"unsupported {what} file type {suffix or '(no suffix)'!r} for {path}: supported are {', '.join(supported)}"
        )
    return suffix


def _check_exists(path: Path) -> None:
    if not path.exists():
        raise FedmapError(f"no such file: {path}")
    if not path.is_file():
        raise FedmapError(f"not a file: {path}")


_NPY_ERRORS = (ValueError, OSError, EOFError, pickle.UnpicklingError)


def _load_npy(path: Path, what: str) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except _NPY_ERRORS as exc:
        raise FedmapError(f"cannot read {what} {path}: not a valid .npy file ({_one_line(exc)})") from exc
    if not isinstance(arr, np.ndarray):  # an .npz archive under a .npy name
        if hasattr(arr, "close"):
            arr.close()
        raise FedmapError(f"cannot read {what} {path}: expected a single array (.npy), got an archive")
    return arr


# --------------------------------------------------------------------------- writing


def save_map(grid: GridMap, path) -> None:
    """Write a map as ``.png`` (8-bit RGB rendering) or ``.npy`` (uint8 classes), atomically."""
    path = Path(path)
    suffix = _suffix(path, MAP_SUFFIXES, "map")
    buf = io.BytesIO()
    if suffix == ".png":
        from PIL import Image
        from PIL.PngImagePlugin import PngInfo

        rgb8 = np.rint(render_classes(grid.classes) * 255.0).astype(np.uint8)
        info = PngInfo()
        info.add_text(PNG_PIXEL_SIZE_KEY, repr(float(grid.pixel_size)))
        Image.fromarray(rgb8).save(buf, format="PNG", pnginfo=info)
    else:
        np.save(buf, np.ascontiguousarray(grid.classes, dtype=np.uint8), allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


# --------------------------------------------------------------------------- maps


def _classes_from_gray(gray: np.ndarray, path: Path) -> np.ndarray:
    values = np.unique(gray)
    if values.min() < 0 or values.max() > UNKNOWN:
        shown = ", ".join(str(v) for v in values[:6]) + (", ..." if values.size > 6 else "")
        raise FedmapError(
            f"grayscale map {path} holds values {shown}: a grayscale map must hold class indices "
            f"0 (free), 1 (impassable), 2 (unknown); save other maps as RGB in the map colours"
        )
    return gray.astype(np.uint8)


def _read_png_map(path: Path) -> tuple[np.ndarray, dict, float | None]:
    from PIL import Image

    errors = _pil_errors()
    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            text = dict(getattr(img, "text", {}) or {})
            if mode in ("P", "PA"):
                idx = np.asarray(img.convert("P") if mode == "PA" else img)
                palette = img.getpalette() or []
                pal = np.asarray(palette, dtype=np.int64).reshape(-1, 3) if palette else np.zeros((0, 3), np.int64)
                used = np.unique(idx)
                if used.size and used.max() < len(pal) and (pal[used, 0] == pal[used, 1]).all() and (
                    pal[used, 1] == pal[used, 2]
                ).all():
                    arr, kind = pal[idx, 0], "gray"
                else:
                    arr, kind = np.asarray(img.convert("RGB")), "rgb"
            elif mode in ("L", "I", "I;16", "I;16B", "I;16L", "LA"):
                arr = np.asarray(img.getchannel(0) if mode == "LA" else img)
                kind = "gray"
            elif mode == "1":
                arr, kind = np.asarray(img.convert("L")), "gray"
            else:
                arr, kind = np.asarray(img.convert("RGB")), "rgb"
    except errors as exc:
        raise FedmapError(f"cannot read map {path}: not a valid PNG image ({_one_line(exc)})") from exc

    if kind == "gray":
        classes = _classes_from_gray(np.asarray(arr, dtype=np.int64), path)
    else:
        classes = classes_from_rgb(np.asarray(arr, dtype=np.float32) / 255.0)
    stored_px = None
    if PNG_PIXEL_SIZE_KEY in text:
        try:
            stored_px = float(text[PNG_PIXEL_SIZE_KEY])
        except ValueError as exc:
            raise FedmapError(
                f"cannot read map {path}: bad {PNG_PIXEL_SIZE_KEY} text {text[PNG_PIXEL_SIZE_KEY]!r}"
            ) from exc
    return classes, {"png_mode": mode, "decoded_as": "classes" if kind == "gray" else "nearest colour"}, stored_px


def _read_npy_map(path: Path) -> tuple[np.ndarray, dict]:
    arr = _load_npy(path, "map")
    dt = arr.dtype
    if arr.ndim == 2 and np.issubdtype(dt, np.integer):
        if arr.size and (arr.min() < 0 or arr.max() > UNKNOWN):
            raise FedmapError(
                f"map {path} holds values {arr.min()}..{arr.max()}: a class map must hold 0 (free), "
                f"1 (impassable), 2 (unknown)"
            )
        return arr.astype(np.uint8), {"decoded_as": "classes"}
    if arr.ndim == 3 and arr.shape[2] == 3 and (np.issubdtype(dt, np.floating) or dt == np.uint8):
        rgb = arr.astype(np.float32)
        if dt == np.uint8:
            rgb /= 255.0
        elif not np.isfinite(rgb).all() or rgb.min() < 0.0 or rgb.max() > 1.0:
            raise FedmapError(f"RGB map {path} must hold finite values in [0, 1]")
        return classes_from_rgb(rgb), {"decoded_as": "nearest colour"}
    raise FedmapError(
        f"map {path} has shape {arr.shape} and dtype {dt}: expected an integer (H, W) class array "
        f"or a float (H, W, 3) RGB array in [0, 1]"
    )


def load_map(path, *, pixel_size: float | None = None) -> GridMap:
    """Read a traversability map from ``.png`` or ``.npy`` (see the module docstring).

    ``pixel_size`` (metres) defaults to the value stored by :func:`save_map` in a PNG,
    else 1.0.
    """
    path = Path(path)
    suffix = _suffix(path, MAP_SUFFIXES, "map")
    _check_exists(path)
    stored_px = None
    if suffix == ".png":
        classes, meta, stored_px = _read_png_map(path)
    else:
        classes, meta = _read_npy_map(path)
    meta["format"] = suffix[1:]
    if pixel_size is not None:
        px, meta["pixel_size_from"] = float(pixel_size), "argument"
    elif stored_px is not None:
        px, meta["pixel_size_from"] = stored_px, "file"
    else:
        px, meta["pixel_size_from"] = 1.0, "default"
    if classes.ndim != 2 or min(classes.shape) <= 0:
        raise FedmapError(f"map {path} must be a non-empty 2-D grid, got shape {classes.shape}")
    return GridMap(classes, px, str(path), meta)


# --------------------------------------------------------------------------- DEMs


def _parse_geokeys(tags) -> dict[int, object]:
    """GeoKeyDirectoryTag -> {key id: value} (ints, floats, tuples or strings)."""
    directory = tags.get(_TAG_GEOKEYS)
    if directory is None:
        return {}
    d = [int(v) for v in np.asarray(directory).ravel()]
    doubles_raw, ascii_raw = tags.get(_TAG_GEODOUBLES), tags.get(_TAG_GEOASCII)
    doubles = [float(v) for v in np.asarray(doubles_raw).ravel()] if doubles_raw is not None else []
    ascii_ = str(ascii_raw) if ascii_raw is not None else ""
    keys: dict[int, object] = {}
    if len(d) < 4:
        return keys
    for k in range(d[3]):
        entry = d[4 + 4 * k: 8 + 4 * k]
        if len(entry) < 4:
            break
        key, location, count, offset = entry
        if location == 0:
            keys[key] = offset
        elif location == _TAG_GEODOUBLES and offset + count <= len(doubles):
            vals = doubles[offset:offset + count]
            keys[key] = vals[0] if count == 1 else tuple(vals)
        elif location == _TAG_GEOASCII:
            keys[key] = ascii_[offset:offset + count].rstrip("|\x00")
        elif location == _TAG_GEOKEYS and offset + count <= len(d):
            ints = d[offset:offset + count]
            keys[key] = ints[0] if count == 1 else tuple(ints)
    return keys


def _tag_floats(tags, code: int) -> list[float] | None:
    value = tags.get(code)
    if value is None:
        return None
    return [float(v) for v in np.asarray(value, dtype=np.float64).ravel()]


def _geotiff_pixel_size(tags, shape: tuple[int, int], path: Path) -> dict | None:
    """Ground spacing (dx, dy) in metres from the GeoTIFF tags, or None without georeferencing."""
    scale = _tag_floats(tags, _TAG_PIXEL_SCALE)
    transform = _tag_floats(tags, _TAG_TRANSFORMATION)
    tie = _tag_floats(tags, _TAG_TIEPOINT)
    keys = _parse_geokeys(tags)
    if scale is not None and len(scale) >= 2:
        sx, sy = abs(scale[0]), abs(scale[1])
        origin = (tie[0], tie[1], tie[3], tie[4]) if tie is not None and len(tie) >= 6 else None
        y_step = -scale[1]  # model y per row (north-up: y decreases downwards)
    elif transform is not None and len(transform) >= 16:
        m = transform
        sx, sy = math.hypot(m[0], m[4]), math.hypot(m[1], m[5])
        origin = (0.0, 0.0, m[3], m[7])
        y_step = m[5]
    else:
        return None
    if not (np.isfinite([sx, sy]).all() and sx > 0 and sy > 0):
        raise FedmapError(f"DEM {path} has an unusable pixel scale ({sx}, {sy}); pass pixel_size")

    model = keys.get(_KEY_MODEL_TYPE)
    info: dict = {}
    if model == _MODEL_GEOGRAPHIC:
        unit = keys.get(_KEY_ANGULAR_UNITS, 9102)
        if unit not in _ANGULAR_UNITS_DEG:
            raise FedmapError(f"DEM {path} uses angular unit code {unit}, which fedmap does not know; pass pixel_size")
        to_deg = _ANGULAR_UNITS_DEG[unit]
        if origin is None:
            raise FedmapError(f"geographic DEM {path} has no tiepoint, so its latitude is unknown; pass pixel_size")
        i0, j0, _x0, lat0 = origin
        centre_row = shape[0] / 2.0 - (0.5 if keys.get(_KEY_RASTER_TYPE) == _RASTER_PIXEL_IS_POINT else 0.0)
        lat_c = (lat0 + (centre_row - j0) * y_step) * to_deg
        if not -90.0 <= lat_c <= 90.0:
            raise FedmapError(f"geographic DEM {path} has centre latitude {lat_c:.3f} deg; pass pixel_size")
        a = keys.get(_KEY_SEMI_MAJOR)
        if isinstance(a, (int, float)) and a > 0:
            b = keys.get(_KEY_SEMI_MINOR)
            if not (isinstance(b, (int, float)) and b > 0):
                inv_f = keys.get(_KEY_INV_FLATTENING)
                b = a * (1.0 - 1.0 / inv_f) if isinstance(inv_f, (int, float)) and inv_f > 0 else a
            radius, radius_from = (2.0 * a + b) / 3.0, "geotiff ellipsoid"
        else:
            radius, radius_from = EARTH_RADIUS_M, "earth default"
        m_per_deg = math.radians(1.0) * radius
        dx = sx * to_deg * m_per_deg * math.cos(math.radians(lat_c))
        dy = sy * to_deg * m_per_deg
        info.update(crs="geographic", centre_lat_deg=float(lat_c), radius_m=float(radius), radius_from=radius_from)
    elif model in (None, _MODEL_PROJECTED):
        unit = keys.get(_KEY_LINEAR_UNITS, 9001)
        if unit not in _LINEAR_UNITS_M:
            raise FedmapError(f"DEM {path} uses linear unit code {unit}, which fedmap does not know; pass pixel_size")
        dx, dy = sx * _LINEAR_UNITS_M[unit], sy * _LINEAR_UNITS_M[unit]
        info["crs"] = "projected" if model == _MODEL_PROJECTED else "unknown (assumed metres)"
    else:
        raise FedmapError(f"DEM {path} has GeoTIFF model type {model} (not projected or geographic); pass pixel_size")
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise FedmapError(f"DEM {path} gives an unusable ground spacing ({dx}, {dy}) m; pass pixel_size")
    info.update(pixel_size_x_m=float(dx), pixel_size_y_m=float(dy))
    return info


def _gdal_scale_offset(tags) -> tuple[float, float]:
    value = tags.get(_TAG_GDAL_METADATA)
    if value is None:
        return 1.0, 0.0
    scale, offset = 1.0, 0.0
    try:
        root = ET.fromstring(str(value))
    except ET.ParseError:
        return 1.0, 0.0
    for item in root.iter("Item"):
        if item.get("sample", "0") != "0":
            continue
        role = (item.get("role") or "").lower()
        try:
            if role == "scale":
                scale = float(item.text or "1")
            elif role == "offset":
                offset = float(item.text or "0")
        except ValueError:
            continue
    return scale, offset


class _DropGdalNodataNotes(logging.Filter):
    """tifffile logs a spurious warning for e.g. GDAL_NODATA 32767 on int16; we parse it ourselves."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "GDAL_NODATA" not in record.getMessage()


def _read_tiff(path: Path):
    import tifffile

    errors = (tifffile.TiffFileError, ValueError, OSError, EOFError, struct.error, zlib.error, KeyError,
              IndexError, NotImplementedError, RuntimeError, MemoryError)
    log = logging.getLogger("tifffile")
    filt = _DropGdalNodataNotes()
    log.addFilter(filt)
    try:
        with tifffile.TiffFile(path) as tf:
            if not tf.pages:
                raise FedmapError(f"cannot read DEM {path}: the TIFF holds no image")
            page = tf.pages.first  # always a TiffPage (tf.pages[0] is typed TiffPage | TiffFrame)
            arr = page.asarray()
            axes = getattr(page, "axes", "")
            # Tag values are read lazily: copy them while the file is open.
            tags = {t.code: t.value for t in page.tags.values()}
    except errors as exc:
        if "imagecodecs" in str(exc):
            raise FedmapError(
                f"cannot read DEM {path}: its compression needs the 'imagecodecs' package "
                f"(pip install imagecodecs) ({_one_line(exc)})"
            ) from exc
        raise FedmapError(f"cannot read DEM {path}: not a valid TIFF ({_one_line(exc)})") from exc
    finally:
        log.removeFilter(filt)
    if "S" in axes and arr.ndim == len(axes):
        arr = np.take(arr, 0, axis=axes.index("S"))  # first band
    arr = np.squeeze(arr) if arr.ndim > 2 and sum(n > 1 for n in arr.shape) <= 2 else arr
    return arr, tags


def _nodata_mask(arr: np.ndarray, nodata: float) -> np.ndarray:
    if math.isnan(nodata):
        return np.zeros(arr.shape, dtype=bool)  # NaN cells are caught as non-finite
    if np.issubdtype(arr.dtype, np.integer):
        info = np.iinfo(arr.dtype)
        if not (math.isfinite(nodata) and nodata == int(nodata) and info.min <= nodata <= info.max):
            return np.zeros(arr.shape, dtype=bool)  # no cell of this type can hold it
        return arr == arr.dtype.type(int(nodata))
    if math.isinf(nodata):
        return np.zeros(arr.shape, dtype=bool)
    finfo = np.finfo(arr.dtype)
    if abs(nodata) >= float(finfo.max) * (1.0 - 1e-6):
        # e.g. -3.4028234663852886e+38 written for float32's lowest value; rounding may
        # push it just past the type's range.
        return (np.sign(arr) == np.sign(nodata)) & (np.abs(arr) >= finfo.max * (1.0 - 1e-6))
    with np.errstate(over="ignore"):
        return arr == arr.dtype.type(nodata)


def _resample_axis(z: np.ndarray, axis: int, old_step: float, new_step: float) -> np.ndarray:
    """Linear resampling along one axis to a finer cell size, cell centres aligned at the edge."""
    n_old = z.shape[axis]
    n_new = max(1, int(round(n_old * old_step / new_step)))
    x = (np.arange(n_new) + 0.5) * (new_step / old_step) - 0.5
    x = np.clip(x, 0.0, n_old - 1.0)
    i0 = np.minimum(np.floor(x).astype(np.intp), max(n_old - 2, 0))
    i1 = np.minimum(i0 + 1, n_old - 1)
    w = (x - i0).astype(np.float64)
    shape = [1] * z.ndim
    shape[axis] = n_new
    w = w.reshape(shape)
    z0, z1 = np.take(z, i0, axis=axis), np.take(z, i1, axis=axis)
    blend = z0 * (1.0 - w) + z1 * w  # NaN if either neighbour is nodata
    out = np.where(w <= 0.0, z0, np.where(w >= 1.0, z1, blend))
    return out.astype(np.float32)


def _read_dem_values(path: Path, suffix: str, options: dict, pixel_size: float | None):
    """Stored values, file nodata, scale/offset, (dx, dy) spacing or None, and meta, per format."""
    if suffix in (".npy", ".tif", ".tiff"):
        if options:
            raise FedmapError(f"unknown option(s) {', '.join(sorted(options))} for {suffix} DEMs "
                              f"(only pixel_size and nodata apply)")
        if suffix == ".npy":
            return _load_npy(path, "DEM"), None, (1.0, 0.0), None, {"format": "npy"}
        arr, tags = _read_tiff(path)
        file_nodata = None
        if _TAG_GDAL_NODATA in tags:
            raw = str(tags[_TAG_GDAL_NODATA]).strip().rstrip("\x00").replace(",", ".")
            try:
                file_nodata = float(raw)
            except ValueError as exc:
                raise FedmapError(f"DEM {path} has an unreadable GDAL_NODATA tag {raw!r}; pass nodata") from exc
        meta: dict = {"format": "geotiff"}
        # The georeferencing is only interpreted when it is needed, so that pixel_size can
        # stand in for tags fedmap cannot use.
        geo = _geotiff_pixel_size(tags, arr.shape, path) if tags and pixel_size is None else None
        if geo is not None:
            meta.update(geo)
        spacing = (geo["pixel_size_x_m"], geo["pixel_size_y_m"]) if geo is not None else None
        scale_offset = _gdal_scale_offset(tags) if tags else (1.0, 0.0)
        return arr, file_nodata, scale_offset, spacing, meta

    reader, accepted = READERS[suffix]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise FedmapError(f"unknown option(s) {', '.join(unknown)} for {suffix} DEMs; "
                          f"accepted: pixel_size, nodata, {', '.join(accepted)}")
    if pixel_size is not None and suffix == ".asc":
        options = {"geographic": False, **options}  # the grid's unit does not matter then
    try:
        raster = reader(path, **options)
    except OSError as exc:
        raise FedmapError(f"cannot read DEM {path}: {_one_line(exc)}") from exc
    spacing = raster.spacing if pixel_size is None else None
    return raster.values, raster.nodata, (raster.scale, raster.offset), spacing, raster.meta


def load_dem(path, *, pixel_size: float | None = None, nodata: float | None = None, **options) -> Dem:
    """Read a DEM; the format follows the suffix (see the module docstring).

    ``pixel_size`` (metres) overrides the file's georeferencing; ``nodata`` overrides
    the file's own nodata value. Nodata and non-finite cells become NaN. ``options`` are
    format-specific (``.asc``: ``geographic``, ``radius_m``; ``.img``/``.raw``:
    ``shape``, ``dtype``, ``byteorder``, ``header_bytes``; ``.png``: ``offset``,
    ``zero_is_nodata``); an option the format does not take is an error.
    """
    path = Path(path)
    suffix = _suffix(path, DEM_SUFFIXES, "DEM")
    _check_exists(path)
    arr, file_nodata, (scale, offset), spacing, meta = _read_dem_values(path, suffix, options, pixel_size)
    if arr.ndim != 2:
        raise FedmapError(f"DEM {path} must be a 2-D grid, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)) or arr.dtype == bool:
        raise FedmapError(f"DEM {path} must hold integer or float elevations, got dtype {arr.dtype}")

    # nodata (compared with the stored values, before scale/offset)
    if nodata is not None:
        nd, nodata_from = float(nodata), "argument"
    elif file_nodata is not None:
        nd, nodata_from = float(file_nodata), meta["format"]
    else:
        nd, nodata_from = None, None
    mask = _nodata_mask(arr, nd) if nd is not None else np.zeros(arr.shape, dtype=bool)
    elev = arr.astype(np.float64 if arr.dtype == np.float64 else np.float32)
    elev[mask] = np.nan
    elev[~np.isfinite(elev)] = np.nan
    meta.update(nodata=nd, nodata_from=nodata_from, nodata_cells=int(np.isnan(elev).sum()))

    if (scale, offset) != (1.0, 0.0):
        elev = elev * scale + offset
        meta.update(scale=scale, offset=offset)

    # pixel size
    if pixel_size is not None:
        px, meta["pixel_size_from"] = float(pixel_size), "argument"
    elif spacing is not None:
        dx, dy = spacing
        meta["pixel_size_from"] = meta["format"]
        if abs(dx - dy) <= SQUARE_TOLERANCE * min(dx, dy):
            px = math.sqrt(dx * dy)
        else:
            px = min(dx, dy)
            axis = 0 if dy > dx else 1
            before = elev.shape
            elev = _resample_axis(elev, axis, max(dx, dy), px)
            meta["resampled"] = {
                "axis": "rows" if axis == 0 else "columns",
                "from_shape": [int(before[0]), int(before[1])],
                "to_shape": [int(elev.shape[0]), int(elev.shape[1])],
                "reason": "non-square cells",
            }
    else:
        px, meta["pixel_size_from"] = 1.0, "default"
    meta["pixel_size"] = float(px)
    return Dem(elev.astype(np.float32), px, str(path), meta)


# --------------------------------------------------------------------------- mosaics

#: Ground size of a GLD100 256p tile pixel: 1 degree of a 1737.4 km sphere / 256.
GLD100_PIXEL_SIZE_M: float = math.radians(1.0) * 1_737_400.0 / 256


def mosaic_tiles(paths, *, pixel_size: float | None = None, **options) -> Dem:
    """Join a grid of adjacent DEM tiles into one DEM.

    ``paths`` is a list of rows, north row first, each row west to east. Every tile is
    read with :func:`load_dem` (``pixel_size`` and ``options`` apply to all) and must
    have the same shape and pixel size.
    """
    rows = [list(r) for r in paths]
    if not rows or not rows[0] or any(len(r) != len(rows[0]) for r in rows):
        raise FedmapError("mosaic tiles must be a non-empty rectangular grid of paths (rows north first)")
    for r in rows:
        for p in r:
            if not Path(p).is_file():
                raise FedmapError(f"mosaic tile missing: {p}")
    dems = [[load_dem(p, pixel_size=pixel_size, **options) for p in r] for r in rows]
    first = dems[0][0]
    for r in dems:
        for d in r:
            if d.shape != first.shape:
                raise FedmapError(f"mosaic tile {d.source} is {d.shape[0]}x{d.shape[1]}, "
                                  f"{first.source} is {first.shape[0]}x{first.shape[1]}")
            if abs(d.pixel_size - first.pixel_size) > 1e-6 * first.pixel_size:
                raise FedmapError(f"mosaic tile {d.source} has pixel size {d.pixel_size} m, "
                                  f"{first.source} has {first.pixel_size} m")
    elev = np.block([[d.elevation for d in r] for r in dems])
    meta = {"format": "mosaic", "tiles": [[d.source for d in r] for r in dems], "tile_shape": list(first.shape),
            "pixel_size": first.pixel_size, "pixel_size_from": first.meta.get("pixel_size_from")}
    return Dem(elev, first.pixel_size, f"mosaic of {len(rows)}x{len(rows[0])} tiles, north-west {first.source}", meta)


def gld100_tile_path(folder, lon: int, lat: int) -> Path:
    """``folder/256p+{lon}+{lat}.png``: the GLD100 tile whose south-west corner is (lon E, lat N)."""
    return Path(folder) / f"256p+{int(lon)}+{int(lat)}.png"


def mosaic_heightmap_tiles(folder, *, lon: int, lat: int, n=1, pixel_size: float = GLD100_PIXEL_SIZE_M,
                           offset: float = 10000.0, zero_is_nodata: bool = True) -> Dem:
    """Mosaic GLD100-named RGB-packed tiles: ``n`` (or ``(rows, cols)``) 1-degree tiles
    whose south-west tile is (``lon``, ``lat``).

    Tile ``256p+{lon}+{lat}.png`` covers longitudes ``lon..lon+1`` east and latitudes
    ``lat..lat+1`` north, north at the top, so tile (lon, lat + 1) lies above tile
    (lon, lat) and (lon + 1, lat) to its right. ``pixel_size`` defaults to the GLD100
    256p spacing (118.45 m).
    """
    if np.isscalar(n):
        nr = nc = int(cast(SupportsInt, n))  # isscalar's TypeGuard also admits complex, which int() refuses
    else:
        nr, nc = (int(v) for v in n)
    if nr < 1 or nc < 1:
        raise FedmapError(f"mosaic needs at least 1x1 tiles, got {nr}x{nc}")
    grid = [[gld100_tile_path(folder, lon + j, lat + nr - 1 - i) for j in range(nc)] for i in range(nr)]
    return mosaic_tiles(grid, pixel_size=pixel_size, offset=offset, zero_is_nodata=zero_is_nodata)
