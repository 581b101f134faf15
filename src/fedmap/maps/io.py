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
``.tif`` / ``.tiff``
    A georeferenced class map (:mod:`fedmap.maps.geotiff`): uint8 class codes with a
    colour table, the CRS and the affine transform, so it overlays its DEM in QGIS.
``.yaml`` / ``.yml``
    A ROS map_server map (:mod:`fedmap.maps.ros`): the YAML plus its PGM image.
A ROS 2 bag (folder, ``.db3`` or ``.mcap``)
    A ``nav_msgs/OccupancyGrid`` message (:mod:`fedmap.maps.rosbag`): by default the last
    one of the bag's only OccupancyGrid topic (``topic=`` picks another topic). Read only:
    ``fedmap export --format rosbag2`` writes bags.

Without a ``pixel_size`` argument (or one stored in the file) a map's pixel size is 1.0 m.

DEMs (:func:`load_dem`)
-----------------------
Every raster format GDAL reads goes through rasterio: GeoTIFF and COG, ISIS3 and ISIS2
cubes, PDS3 (open the labelled ``.img``/``.lbl``) and PDS4 (open the ``.xml`` label),
VICAR, ESRI ASCII grids, JPEG 2000, netCDF, ... (the format follows the file's content,
not its suffix). GDAL's reading is honoured as it is:

* **nodata**: the band's mask (its nodata value, a per-dataset mask or the format's
  special values, e.g. ISIS3 NULL) becomes NaN, as do non-finite values; the ``nodata``
  argument replaces the file's nodata value (compared with the stored values).
* **scale/offset**: the band's scale and offset are applied (stored * scale + offset).
* **CRS and transform** are kept on the :class:`~fedmap.maps.dem.Dem`. A south-up (or
  east-to-west) grid is flipped to north-up, with its transform; a rotated or sheared
  geotransform is refused (warp it first).
* **pixel size** in metres from the CRS (:func:`fedmap.maps.georef.cell_size_m`):
  projected units are converted to metres; geographic degrees become metres on the
  ellipsoid of *that body*, taken from the CRS, at the grid's centre latitude. When the
  ground spacing along x and y differs by more than 1% (a geographic grid away from the
  equator) the coarser axis is resampled by linear interpolation to the finer spacing, so
  that slopes computed with one pixel size are right; ``meta["cells_resampled"]`` records it
  and ``meta["cells_note"]`` says it in one line.
  A grid with a transform but no CRS is taken to be in metres, unless its cell size and
  corner look like degrees, which is refused: pass ``crs`` (e.g. ``"EPSG:4326"``,
  ``"IAU_2015:30100"``) or ``pixel_size``. Without any georeferencing the pixel size is
  1.0 m. ``pixel_size`` overrides it all.

Options: ``band`` (1-based, default 1); ``crs`` assigns a CRS to a file that has none (or
replaces its own); raw samples without a label (e.g. the MOLA MEGDR ``.img``) are read
through a GDAL raw VRT with ``shape=(rows, cols)``, ``dtype`` (default ``"int16"``),
``byteorder`` (``"big"``, default, or ``"little"``) and ``header_bytes`` (default 0).

fedmap keeps its own reader only where GDAL has none:

``.png``
    RGB-packed heightmap tile (:func:`fedmap.maps.formats.read_heightmap_png`):
    ``metres = R + 256 G + 65536 B - offset`` (option ``offset``, default 10000); raw 0
    is nodata unless ``zero_is_nodata=False``; the ``nodata`` argument compares metres.
    Grey or paletted PNGs are refused (those are class maps: :func:`load_map`). The file
    has no georeferencing: pass ``pixel_size`` (default 1.0 m).
    :func:`mosaic_tiles` joins a grid of tiles, :func:`mosaic_heightmap_tiles` GLD100-named
    ones (``256p+{lon}+{lat}.png``, 118.45 m pixels, georeferenced in ``IAU_2015:30100``).
``.npy``
    A 2-D real array; ``pixel_size`` argument, default 1.0 m.

``Dem.meta`` records ``format`` (the GDAL driver, ``heightmap-png`` or ``npy``),
``nodata``, ``nodata_from``, ``nodata_cells``, ``pixel_size_from`` ("argument", "crs",
"transform (assumed metres)" or "default") and the CRS notes. :func:`resample_dem`,
:func:`crop_dem` and :func:`centre_crop` (from :mod:`fedmap.maps.regrid`) fit a DEM to a
run's grid and keep its transform right.

Every user-facing problem (missing file, unreadable or corrupt file, wrong shape,
unsupported option, DEM entirely nodata) raises :class:`~fedmap.errors.FedmapError`
with a one-line message naming the file. All writes are atomic
(:func:`atomic_write_bytes`).
"""

from __future__ import annotations

import io
import math
import pickle
import warnings
from pathlib import Path
from typing import SupportsInt, cast

import numpy as np
from affine import Affine

from fedmap._util import atomic_write_bytes  # noqa: F401  (part of this API)
from fedmap._util import one_line as _one_line
from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.formats import HEIGHTMAP_OFFSET_M, _pil_errors, read_heightmap_png
from fedmap.maps.georef import cell_size_m, crs_wkt, north_up
from fedmap.maps.geotiff import read_class_geotiff, write_class_geotiff
from fedmap.maps.grid import UNKNOWN, GridMap, classes_from_rgb, render_classes
from fedmap.maps.regrid import centre_crop, crop_dem, resample_dem  # noqa: F401  (part of this API)
from fedmap.maps.ros import read_ros_map, write_ros_map
from fedmap.maps.rosbag import is_bag, read_bag_map

MAP_SUFFIXES: tuple[str, ...] = (".png", ".npy", ".tif", ".tiff", ".yaml", ".yml")

#: Relative difference of x and y ground spacing above which a DEM is resampled.
SQUARE_TOLERANCE: float = 0.01

PNG_PIXEL_SIZE_KEY = "fedmap:pixel_size"
#: PNG text chunks that carry a map's place on its body (the affine transform, the CRS as WKT).
PNG_TRANSFORM_KEY, PNG_CRS_KEY = "fedmap:transform", "fedmap:crs"


def pam_sidecar(grid: GridMap) -> bytes | None:
    """GDAL's ``.aux.xml`` (PAM) for a georeferenced map saved as PNG: with it, GDAL, QGIS
    and rasterio place the PNG on its body (None for a map in a local frame)."""
    if grid.transform is None:
        return None
    t = grid.transform
    gt = ", ".join(repr(float(v)) for v in (t.c, t.a, t.b, t.f, t.d, t.e))  # GDAL's geotransform order
    srs = "" if not grid.crs else f"  <SRS>{_xml_escape(grid.crs)}</SRS>\n"
    return f"<PAMDataset>\n{srs}  <GeoTransform>{gt}</GeoTransform>\n</PAMDataset>\n".encode()


def _xml_escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")

#: Options of raw samples read through a GDAL raw VRT.
RAW_OPTIONS: tuple[str, ...] = ("shape", "dtype", "byteorder", "header_bytes")
#: Options of RGB-packed heightmap PNG tiles.
PNG_OPTIONS: tuple[str, ...] = ("offset", "zero_is_nodata")


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
    """Write a map atomically: ``.png`` (8-bit RGB rendering), ``.npy`` (uint8 classes),
    ``.tif`` (georeferenced class GeoTIFF) or ``.yaml`` (ROS map_server YAML + PGM)."""
    path = Path(path)
    suffix = _suffix(path, MAP_SUFFIXES, "map")
    if suffix in (".tif", ".tiff"):
        write_class_geotiff(grid, path)
        return
    if suffix in (".yaml", ".yml"):
        write_ros_map(grid, path)
        return
    buf = io.BytesIO()
    if suffix == ".png":
        from PIL import Image
        from PIL.PngImagePlugin import PngInfo

        rgb8 = np.rint(render_classes(grid.classes) * 255.0).astype(np.uint8)
        info = PngInfo()
        info.add_text(PNG_PIXEL_SIZE_KEY, repr(float(grid.pixel_size)))
        if grid.transform is not None:  # the map keeps its place on the body (and a GDAL sidecar)
            info.add_text(PNG_TRANSFORM_KEY, " ".join(repr(float(v)) for v in tuple(grid.transform)[:6]))
            if grid.crs:
                info.add_text(PNG_CRS_KEY, grid.crs)
        Image.fromarray(rgb8).save(buf, format="PNG", pnginfo=info)
        sidecar = pam_sidecar(grid)
        if sidecar is not None:
            atomic_write_bytes(path.with_name(path.name + ".aux.xml"), sidecar)
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
    meta: dict = {"png_mode": mode, "decoded_as": "classes" if kind == "gray" else "nearest colour"}
    if PNG_TRANSFORM_KEY in text:
        try:
            meta["_transform"] = Affine(*(float(v) for v in text[PNG_TRANSFORM_KEY].split()))
        except (TypeError, ValueError) as exc:
            raise FedmapError(f"cannot read map {path}: bad {PNG_TRANSFORM_KEY} text {text[PNG_TRANSFORM_KEY]!r}") from exc
        meta["_crs"] = text.get(PNG_CRS_KEY) or None
    return classes, meta, stored_px


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
        if dt == np.uint8 and arr.size and arr.max() <= UNKNOWN:  # a picture in 0..2 of 255 would be black
            raise FedmapError(f"map {path} is a {arr.shape} uint8 array holding only {arr.min()}..{arr.max()}: class "
                              "codes, not colours? A class map is 2-D (H, W); an RGB map holds colours 0..255")
        rgb = arr.astype(np.float32)
        if dt == np.uint8:
            rgb /= 255.0
        elif not np.isfinite(rgb).all() or rgb.min() < 0.0 or rgb.max() > 1.0:
            raise FedmapError(f"RGB map {path} must hold finite values in [0, 1]")
        return classes_from_rgb(rgb), {"decoded_as": "nearest colour"}
    raise FedmapError(
        f"map {path} has shape {arr.shape} and dtype {dt}: expected an integer (H, W) class array "
        f"or an (H, W, 3) RGB array (float in [0, 1] or uint8 in 0..255)"
    )


def load_map(path, *, pixel_size: float | None = None, topic: str | None = None) -> GridMap:
    """Read a traversability map from ``.png``, ``.npy``, ``.tif``, ROS ``.yaml`` or a ROS 2
    bag (see the module docstring).

    ``pixel_size`` (metres) defaults to the value stored in the file, else 1.0; ``topic``
    picks a bag's OccupancyGrid topic (other formats refuse it).
    """
    path = Path(path)
    if path.is_dir() or is_bag(path):  # a folder that is no bag is a one-line error
        grid = read_bag_map(path, topic=topic)
    else:
        if topic is not None:
            raise FedmapError(f"topic {topic!r} applies to ROS 2 bags only, not {path}")
        suffix = _suffix(path, MAP_SUFFIXES, "map")
        _check_exists(path)
        if suffix not in (".tif", ".tiff", ".yaml", ".yml"):
            return _load_image_map(path, suffix, pixel_size)
        grid = read_class_geotiff(path) if suffix in (".tif", ".tiff") else read_ros_map(path)
    if pixel_size is not None:
        grid = GridMap(grid.classes, float(pixel_size), grid.source, {**grid.meta, "pixel_size_from": "argument"},
                       transform=grid.transform, crs=grid.crs)
    return grid


def _load_image_map(path: Path, suffix: str, pixel_size: float | None) -> GridMap:
    """A ``.png`` or ``.npy`` class map (no transform unless fedmap's PNG text chunks hold one)."""
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
    transform, crs = meta.pop("_transform", None), meta.pop("_crs", None)  # a PNG fedmap georeferenced
    return GridMap(classes, px, str(path), meta, transform=transform, crs=crs)


# --------------------------------------------------------------------------- DEMs


_GDAL_TYPES = {"int8": "Int8", "uint8": "Byte", "int16": "Int16", "uint16": "UInt16", "int32": "Int32",
               "uint32": "UInt32", "int64": "Int64", "uint64": "UInt64", "float32": "Float32", "float64": "Float64"}
_BYTEORDERS = {"big": "MSB", "little": "LSB", ">": "MSB", "<": "LSB"}


def _raw_vrt(path: Path, shape=None, dtype=None, byteorder=None, header_bytes=None) -> str:
    """A GDAL VRT (XML text) that lays raw samples out as a raster: GDAL reads them."""
    if shape is None:
        raise FedmapError(f"cannot read raw DEM {path}: pass shape=(rows, cols) with dtype, byteorder, header_bytes")
    try:
        rows, cols = (int(v) for v in shape)
        dt = np.dtype(dtype or "int16")
    except (TypeError, ValueError) as exc:
        raise FedmapError(f"cannot read raw DEM {path}: bad shape/dtype ({_one_line(exc)})") from exc
    order = _BYTEORDERS.get(str(byteorder or "big").lower())
    if order is None:
        raise FedmapError(f"byteorder must be 'big' or 'little', got {byteorder!r}")
    if rows <= 0 or cols <= 0 or dt.name not in _GDAL_TYPES:
        raise FedmapError(f"cannot read raw DEM {path}: need a positive shape and an integer or float dtype, "
                          f"got {rows}x{cols} {dt}")
    offset = int(header_bytes or 0)
    need = offset + rows * cols * dt.itemsize
    size = path.stat().st_size
    if size != need:
        raise FedmapError(f"raw DEM {path} is {size:,} bytes but {offset} header + {rows} x {cols} x "
                          f"{dt.itemsize} B ({dt.name}) = {need:,} bytes: wrong shape, dtype or header_bytes?")
    src = str(path.resolve()).replace("&", "&amp;").replace("<", "&lt;")
    return (f'<VRTDataset rasterXSize="{cols}" rasterYSize="{rows}"><VRTRasterBand dataType="{_GDAL_TYPES[dt.name]}" '
            f'band="1" subClass="VRTRawRasterBand"><SourceFilename relativeToVRT="0">{src}</SourceFilename>'
            f"<ImageOffset>{offset}</ImageOffset><PixelOffset>{dt.itemsize}</PixelOffset>"
            f"<LineOffset>{cols * dt.itemsize}</LineOffset><ByteOrder>{order}</ByteOrder></VRTRasterBand></VRTDataset>")


#: Suffixes of raw sample files, which GDAL reads only with a label or shape=(rows, cols).
_RAW_SUFFIXES = ("", ".img", ".raw", ".dat", ".bin")


def _unrecognised(path: Path) -> str:
    """Why GDAL may not recognise ``path``, and what to do, in a few words."""
    try:
        head = path.read_bytes()[:4096]
    except OSError:
        head = b""
    if head:
        try:
            text = head.decode("utf-8")
        except UnicodeDecodeError:
            text = ""
        if text and sum(ch.isprintable() or ch.isspace() for ch in text) >= 0.95 * len(text):
            return "it is a text file, not a raster (the wrong file?)"
    if path.suffix.lower() in _RAW_SUFFIXES:
        return "GDAL does not recognise its format; raw samples without a label need shape=(rows, cols) " \
               "(and dtype, byteorder) in [terrain.options]"
    return f"GDAL does not recognise it as a raster (a damaged file, or not what its {path.suffix} name says)"


def _read_gdal(path: Path, band: int, raw: dict):
    """Stored values, GDAL's validity mask, scale/offset, transform, CRS and meta of one band."""
    import rasterio
    from rasterio._err import CPLE_BaseError  # GDAL errors that rasterio re-raises as they are
    from rasterio.errors import NotGeoreferencedWarning, RasterioError

    target = _raw_vrt(path, **raw) if raw else str(path)
    try:
        with warnings.catch_warnings():
            # a file without georeferencing is fine: its pixel size is the default or the argument
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(target) as src:
                if not 1 <= band <= src.count:
                    raise FedmapError(f"DEM {path} has {src.count} band(s); band {band} does not exist")
                values = src.read(band)
                valid = src.read_masks(band) != 0
                scale, offset = src.scales[band - 1], src.offsets[band - 1]
                georef = not (src.transform.is_identity and src.crs is None)
                transform = src.transform if georef else None
                crs = src.crs.to_wkt() if src.crs else None
                meta = {"format": "raw" if raw else src.driver.lower(), "driver": src.driver,
                        "bands": src.count, "file_nodata": src.nodatavals[band - 1]}
    except (RasterioError, CPLE_BaseError) as exc:
        if "not recognized" in str(exc):  # GDAL's message repeats the path: say what it means instead
            raise FedmapError(f"cannot read DEM {path}: {_unrecognised(path)}") from exc
        raise FedmapError(f"cannot read DEM {path}: {_one_line(exc)}") from exc
    return values, valid, (float(scale or 1.0), float(offset or 0.0)), transform, crs, meta


def _nodata_mask(arr: np.ndarray, nodata: float) -> np.ndarray:
    """Cells of ``arr`` equal to ``nodata`` (robust to float32 rounding of the lowest float)."""
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
        # e.g. -3.4028234663852886e+38 written for float32's lowest value
        return (np.sign(arr) == np.sign(nodata)) & (np.abs(arr) >= finfo.max * (1.0 - 1e-6))
    with np.errstate(over="ignore"):
        return arr == arr.dtype.type(nodata)


def _resample_axis(z: np.ndarray, axis: int, old_step: float, new_step: float) -> np.ndarray:
    """Linear resampling along one axis to a finer cell size over the same extent."""
    n_old = z.shape[axis]
    n_new = max(1, int(round(n_old * old_step / new_step)))
    x = (np.arange(n_new) + 0.5) * (n_old / n_new) - 0.5  # new cell centres in old cell units
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


#: The largest cell (in the file's units) taken to be degrees when the whole grid lies within
#: longitude/latitude bounds: 0.1 (about 11 km on Earth) covers every DEM of arc-seconds and
#: arc-minutes (2.5' = 0.0417 was taken as 4 cm); a metre grid of cells that small that also
#: sits within those bounds is refused too, and passing pixel_size says what was meant.
DEGREE_CELL_MAX = 0.1


def _looks_like_degrees(transform: Affine, shape: tuple[int, int]) -> bool:
    """Whether a grid's cells and its whole extent look like longitude/latitude degrees."""
    h, w = shape
    xs = (transform.c, transform.c + transform.a * w)
    ys = (transform.f, transform.f + transform.e * h)
    return (max(abs(transform.a), abs(transform.e)) <= DEGREE_CELL_MAX
            and -180 <= min(xs) and max(xs) <= 360 and -90 <= min(ys) and max(ys) <= 90)


def load_dem(path, *, pixel_size: float | None = None, nodata: float | None = None, band: int = 1, crs=None,
             shape=None, dtype=None, byteorder=None, header_bytes=None, offset: float | None = None,
             zero_is_nodata: bool | None = None) -> Dem:
    """Read a DEM: any format GDAL reads, an RGB-packed heightmap ``.png`` or a ``.npy``
    (see the module docstring).

    Parameters
    ----------
    path : str or Path
        The file (for PDS4, the ``.xml`` label).
    pixel_size : float, optional
        Metres per cell; overrides the file's georeferencing.
    nodata : float, optional
        Replaces the file's nodata value (compared with the stored values).
    band : int
        1-based band of a multi-band file.
    crs : optional
        A CRS (``"EPSG:4326"``, ``"IAU_2015:30100"``, WKT, PROJ) for a file that has none.
    shape, dtype, byteorder, header_bytes
        Layout of raw samples without a label (read through a GDAL raw VRT).
    offset, zero_is_nodata
        Heightmap ``.png`` packing: ``metres = R + 256 G + 65536 B - offset``; raw 0 is a gap.
    """
    path = Path(path)
    _check_exists(path)
    suffix = path.suffix.lower()
    raw = {k: v for k, v in (("shape", shape), ("dtype", dtype), ("byteorder", byteorder),
                             ("header_bytes", header_bytes)) if v is not None}
    png = {k: v for k, v in (("offset", offset), ("zero_is_nodata", zero_is_nodata)) if v is not None}
    if png and suffix != ".png":
        raise FedmapError(f"option(s) {', '.join(png)} apply to heightmap .png tiles only, not {path}")
    if raw and suffix in (".png", ".npy"):
        raise FedmapError(f"option(s) {', '.join(raw)} apply to raw sample files only, not {path}")
    transform: Affine | None = None
    file_crs: str | None = None
    if suffix == ".npy":
        arr = _load_npy(path, "DEM")
        valid, (scale, add) = None, (1.0, 0.0)
        meta: dict = {"format": "npy", "file_nodata": None}
    elif suffix == ".png":
        arr = read_heightmap_png(path, offset=float(png.get("offset", HEIGHTMAP_OFFSET_M)),
                                 zero_is_nodata=bool(png.get("zero_is_nodata", True)))
        valid, (scale, add) = None, (1.0, 0.0)
        meta = {"format": "heightmap-png", "file_nodata": None, **png}
    else:
        arr, valid, (scale, add), transform, file_crs, meta = _read_gdal(path, int(band), raw)
    if arr.ndim != 2:
        raise FedmapError(f"DEM {path} must be a 2-D grid, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)) or arr.dtype == bool:
        raise FedmapError(f"DEM {path} must hold integer or float elevations, got dtype {arr.dtype}")

    # nodata: the argument, else GDAL's mask (nodata value, mask band, format special values)
    nodata_from: str | None
    if nodata is not None:
        mask, nodata_from = _nodata_mask(arr, float(nodata)), "argument"
    else:
        mask = np.zeros(arr.shape, dtype=bool) if valid is None else ~valid
        nodata_from = str(meta["format"]) if mask.any() else None
    elev: np.ndarray = arr.astype(np.float64 if arr.dtype == np.float64 else np.float32)
    elev[mask | ~np.isfinite(elev)] = np.nan
    meta.update(nodata=float(nodata) if nodata is not None else meta.pop("file_nodata"), nodata_from=nodata_from,
                nodata_cells=int(np.isnan(elev).sum()))
    meta.pop("file_nodata", None)
    if (scale, add) != (1.0, 0.0):
        elev = elev * float(scale) + float(add)
        meta.update(scale=scale, offset=add)

    # georeferencing: north-up grid, the CRS (the argument assigns one), pixel size in metres
    the_crs = crs_wkt(crs) if crs is not None else file_crs
    meta["crs_from"] = "argument" if crs is not None else ("file" if file_crs else None)
    if transform is not None:
        elev, transform, flipped = north_up(elev, transform, f"DEM {path}")
        if flipped:
            meta["flipped"] = flipped
    if pixel_size is not None:
        px, meta["pixel_size_from"] = float(pixel_size), "argument"
    elif transform is None:
        if the_crs is not None:
            raise FedmapError(f"DEM {path} has a CRS but no geotransform; pass pixel_size")
        px, meta["pixel_size_from"] = 1.0, "default"
    else:
        if the_crs is not None:
            dx, dy, info = cell_size_m(the_crs, transform, elev.shape)
            if info["crs_kind"] == "projected" and _looks_like_degrees(transform, elev.shape):
                raise FedmapError(
                    f"DEM {path} has a projected CRS (metres) but cell size {abs(transform.a):g} with corner "
                    f"({transform.c:g}, {transform.f:g}), which looks like degrees; pass its real crs (e.g. "
                    "'EPSG:4326') or pixel_size")
            meta.update(info)
            meta["pixel_size_from"] = "crs"
        else:
            if _looks_like_degrees(transform, elev.shape):
                raise FedmapError(
                    f"DEM {path} has cell size {abs(transform.a):g} with corner ({transform.c:g}, {transform.f:g}) "
                    f"and no CRS, which looks like degrees; pass crs (e.g. 'EPSG:4326' or the body's CRS) or pixel_size")
            dx, dy = abs(transform.a), abs(transform.e)
            meta["pixel_size_from"] = "transform (assumed metres)"
        if abs(dx - dy) <= SQUARE_TOLERANCE * min(dx, dy):
            px = math.sqrt(dx * dy)
        else:
            px = min(dx, dy)
            axis = 0 if dy > dx else 1
            before = elev.shape
            elev = _resample_axis(elev, axis, max(dx, dy), px)
            transform = transform @ Affine.scale(before[1] / elev.shape[1], before[0] / elev.shape[0])
            meta["cells_resampled"] = {"axis": "rows" if axis == 0 else "columns",
                                       "from_shape": [int(v) for v in before],
                                       "to_shape": [int(v) for v in elev.shape], "reason": "non-square cells"}
            meta["cells_note"] = (f"the DEM's cells are {dx:.4g} m east-west by {dy:.4g} m north-south: its "
                                  f"{'rows' if axis == 0 else 'columns'} were resampled to square cells of {px:.4g} m "
                                  f"({before[0]}x{before[1]} -> {elev.shape[0]}x{elev.shape[1]} cells)")
    meta["pixel_size"] = float(px)
    return Dem(elev.astype(np.float32), px, str(path), meta, transform=transform, crs=the_crs)


# --------------------------------------------------------------------------- mosaics

#: Ground size of a GLD100 256p tile pixel: 1 degree of a 1737.4 km sphere / 256.
GLD100_PIXEL_SIZE_M: float = math.radians(1.0) * 1_737_400.0 / 256

#: The CRS of GLD100 tiles: longitude/latitude on the IAU 2015 Moon sphere (1737.4 km).
GLD100_CRS = "IAU_2015:30100"


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
    # the north-west tile's transform places the whole mosaic (the tiles are adjacent)
    return Dem(elev, first.pixel_size, f"mosaic of {len(rows)}x{len(rows[0])} tiles, north-west {first.source}", meta,
               transform=first.transform, crs=first.crs)


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
    256p spacing (118.45 m). The mosaic is georeferenced in :data:`GLD100_CRS`.
    """
    if np.isscalar(n):
        nr = nc = int(cast(SupportsInt, n))  # isscalar's TypeGuard also admits complex, which int() refuses
    else:
        nr, nc = (int(v) for v in n)
    if nr < 1 or nc < 1:
        raise FedmapError(f"mosaic needs at least 1x1 tiles, got {nr}x{nc}")
    grid = [[gld100_tile_path(folder, lon + j, lat + nr - 1 - i) for j in range(nc)] for i in range(nr)]
    dem = mosaic_tiles(grid, pixel_size=pixel_size, offset=offset, zero_is_nodata=zero_is_nodata)
    side = dem.shape[1] / nc  # cells per degree
    dem.transform = Affine(1.0 / side, 0.0, float(lon), 0.0, -1.0 / side, float(lat + nr))
    dem.crs = crs_wkt(GLD100_CRS)
    return dem
