"""Readers for the DEM formats besides GeoTIFF and ``.npy``: ESRI ASCII grids, raw
PDS-style images and RGB-packed heightmap PNG tiles.

Each reader returns a :class:`RawRaster` (the stored values plus what the file says
about nodata, scale/offset and ground spacing); :func:`fedmap.maps.io.load_dem` turns it
into a :class:`~fedmap.maps.dem.Dem` with the same nodata and pixel-size rules for every
format. Use :func:`~fedmap.maps.io.load_dem`; these functions are its parts.
"""

from __future__ import annotations

import math
import re
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fedmap._util import one_line as _one_line
from fedmap.errors import FedmapError

#: Sphere radius used for geographic rasters whose GeoKeys declare no ellipsoid (Earth).
EARTH_RADIUS_M: float = 6_371_000.0


def _pil_errors() -> tuple[type[BaseException], ...]:
    """What Pillow raises for unreadable, truncated or corrupt images."""
    from PIL import Image, UnidentifiedImageError

    return (UnidentifiedImageError, ValueError, OSError, EOFError, SyntaxError, struct.error, zlib.error,
            Image.DecompressionBombError)

#: Elevation offset of RGB-packed heightmap tiles: ``metres = R + 256 G + 65536 B - offset``.
HEIGHTMAP_OFFSET_M: float = 10000.0


@dataclass
class RawRaster:
    """What a reader found: stored values and the file's own metadata.

    ``nodata`` compares the stored values (before ``scale``/``offset``); ``spacing`` is
    the ground size of a cell along x and y in metres, or None when the file does not say.
    """

    values: np.ndarray
    nodata: float | None = None
    scale: float = 1.0
    offset: float = 0.0
    spacing: tuple[float, float] | None = None
    meta: dict = field(default_factory=dict)


def _degrees_to_metres(dx_deg: float, dy_deg: float, lat_deg: float, radius_m: float) -> tuple[float, float]:
    """Ground spacing of a (dx, dy) degree cell at latitude ``lat_deg`` on a sphere."""
    m_per_deg = math.radians(1.0) * radius_m
    return dx_deg * m_per_deg * math.cos(math.radians(lat_deg)), dy_deg * m_per_deg


# --------------------------------------------------------------------------- ESRI ASCII grid

_ASC_KEYS = ("ncols", "nrows", "xllcorner", "xllcenter", "yllcorner", "yllcenter", "cellsize", "dx", "dy",
             "nodata_value")


def _prj_is_geographic(path: Path) -> bool | None:
    """True/False from a ``.prj`` sidecar (WKT), None when there is none."""
    prj = path.with_suffix(".prj")
    if not prj.is_file():
        return None
    wkt = prj.read_text(errors="replace").lstrip().upper()
    return wkt.startswith("GEOGCS") or wkt.startswith("GEOGCRS")


def read_ascii_grid(path: Path, *, geographic: bool | None = None, radius_m: float = EARTH_RADIUS_M) -> RawRaster:
    """Read an ESRI ASCII grid (``.asc``).

    The header holds ``ncols``, ``nrows``, ``xllcorner``/``xllcenter``,
    ``yllcorner``/``yllcenter``, ``cellsize`` (or ``dx`` and ``dy``) and optionally
    ``NODATA_value``, one per line, keys in any case. Rows follow north first.

    The grid's unit is not in the file. ``geographic=None`` reads it from a ``.prj``
    sidecar when there is one and otherwise takes ``cellsize`` as metres; but a
    ``cellsize`` under 0.01 with corner coordinates inside longitude/latitude ranges looks
    like degrees and is refused (pass ``geographic=True`` or ``pixel_size``).
    ``geographic=True`` converts degrees to metres at the centre latitude on a sphere of
    ``radius_m`` (Earth's by default).
    """
    try:
        text = path.read_bytes().decode("ascii")
    except UnicodeDecodeError as exc:
        raise FedmapError(f"cannot read DEM {path}: not an ASCII grid (non-text byte at {exc.start})") from exc
    lines = text.splitlines()
    header: dict[str, float] = {}
    n_header = 0
    for line in lines:
        parts = line.split()
        if not parts:
            n_header += 1
            continue
        key = parts[0].lower()
        if key not in _ASC_KEYS:
            break
        if len(parts) != 2:
            raise FedmapError(f"cannot read DEM {path}: bad ASCII grid header line {line.strip()!r}")
        try:
            header[key] = float(parts[1])
        except ValueError:
            raise FedmapError(f"cannot read DEM {path}: header {parts[0]} has non-numeric value {parts[1]!r}") from None
        n_header += 1
    missing = [k for k in ("ncols", "nrows") if k not in header]
    if "cellsize" not in header and not ("dx" in header and "dy" in header):
        missing.append("cellsize")
    if missing:
        raise FedmapError(f"cannot read DEM {path}: ASCII grid header lacks {', '.join(missing)}")
    ncols, nrows = header["ncols"], header["nrows"]
    if not (ncols == int(ncols) and nrows == int(nrows) and ncols > 0 and nrows > 0):
        raise FedmapError(f"cannot read DEM {path}: ncols/nrows must be positive integers, got {ncols}, {nrows}")
    ncols, nrows = int(ncols), int(nrows)
    dx = header.get("dx", header.get("cellsize"))
    dy = header.get("dy", header.get("cellsize"))
    assert dx is not None and dy is not None  # the header check above guarantees dx/dy or cellsize
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise FedmapError(f"cannot read DEM {path}: cell size must be positive, got {dx}, {dy}")
    try:
        values = np.array(" ".join(lines[n_header:]).split(), dtype=np.float64)
    except ValueError as exc:
        raise FedmapError(f"cannot read DEM {path}: non-numeric value in the grid ({_one_line(exc)})") from exc
    if values.size != nrows * ncols:
        what = "truncated?" if values.size < nrows * ncols else "extra values"
        raise FedmapError(f"cannot read DEM {path}: {values.size} values but the header says "
                          f"{nrows} x {ncols} = {nrows * ncols} ({what})")

    # Lower-left corner of the grid (xllcenter/yllcenter give the centre of that cell).
    x0 = header["xllcorner"] if "xllcorner" in header else header.get("xllcenter", 0.0) - dx / 2
    y0 = header["yllcorner"] if "yllcorner" in header else header.get("yllcenter", 0.0) - dy / 2
    meta = {"format": "esri-ascii", "xll_corner": x0, "yll_corner": y0, "cell_x": dx, "cell_y": dy}
    if geographic is None:
        geographic = _prj_is_geographic(path)
        meta["crs_from"] = ".prj" if geographic is not None else "assumed metres"
        if geographic is None:
            looks_angular = max(dx, dy) < 0.01 and -180 <= x0 <= 360 and -90 <= y0 <= 90
            if looks_angular:
                raise FedmapError(
                    f"DEM {path} has cellsize {dx:g} with corner ({x0:g}, {y0:g}), which looks like degrees; "
                    f"pass geographic=True (sphere radius radius_m, default Earth) or pixel_size"
                )
            geographic = False
    if geographic:
        lat_c = y0 + nrows * dy / 2
        spacing = _degrees_to_metres(dx, dy, lat_c, radius_m)
        meta.update(crs="geographic", centre_lat_deg=lat_c, radius_m=radius_m)
    else:
        spacing = (dx, dy)
        meta["crs"] = "projected (metres)"
    return RawRaster(values.reshape(nrows, ncols), header.get("nodata_value"), spacing=spacing, meta=meta)


# --------------------------------------------------------------------------- raw / PDS3

_PDS_TYPES = {  # SAMPLE_TYPE -> (numpy kind, byte order)
    "MSB_INTEGER": ("i", ">"), "SUN_INTEGER": ("i", ">"), "MAC_INTEGER": ("i", ">"), "INTEGER": ("i", ">"),
    "MSB_UNSIGNED_INTEGER": ("u", ">"), "SUN_UNSIGNED_INTEGER": ("u", ">"), "MAC_UNSIGNED_INTEGER": ("u", ">"),
    "UNSIGNED_INTEGER": ("u", ">"),
    "LSB_INTEGER": ("i", "<"), "PC_INTEGER": ("i", "<"), "VAX_INTEGER": ("i", "<"),
    "LSB_UNSIGNED_INTEGER": ("u", "<"), "PC_UNSIGNED_INTEGER": ("u", "<"), "VAX_UNSIGNED_INTEGER": ("u", "<"),
    "IEEE_REAL": ("f", ">"), "MAC_REAL": ("f", ">"), "SUN_REAL": ("f", ">"), "PC_REAL": ("f", "<"),
}
_BYTEORDERS = {"big": ">", "little": "<", ">": ">", "<": "<"}


def parse_pds3_label(text: str) -> dict[str, str]:
    """``KEY = VALUE`` pairs of a PDS3 label (first occurrence wins), comments removed."""
    out: dict[str, str] = {}
    for line in re.sub(r"/\*.*?\*/", "", text, flags=re.S).splitlines():
        if line.strip() == "END":
            break
        if "=" in line:
            key, value = line.split("=", 1)
            out.setdefault(key.strip().upper(), value.strip())
    return out


def _label_number(label: dict, key: str, path: Path) -> tuple[float, str] | None:
    """A numeric label value and its unit (``"12.5 <KM/PIXEL>"`` -> (12.5, "KM/PIXEL"))."""
    if key not in label:
        return None
    m = re.match(r'^"?\s*([-+0-9.eE]+)\s*"?\s*(?:<([^>]*)>)?', label[key])
    try:
        return float(m.group(1)), (m.group(2) or "").strip().upper()  # type: ignore[union-attr]
    except (AttributeError, ValueError):
        raise FedmapError(f"cannot read DEM {path}: PDS label {key} = {label[key]!r} is not a number") from None


def _find_label(path: Path) -> tuple[dict, str, bool] | None:
    """The PDS3 label (dict, where, attached?): attached at the file start or a .lbl sidecar."""
    with open(path, "rb") as f:
        head = f.read(65536)
    if head.startswith(b"PDS_VERSION_ID") or head.startswith(b"CCSD"):
        return parse_pds3_label(head.decode("latin-1")), "attached", True
    for suffix in (".lbl", ".LBL"):
        sidecar = path.with_suffix(suffix)
        if sidecar.is_file():
            return parse_pds3_label(sidecar.read_text(errors="replace")), str(sidecar), False
    return None


def _label_layout(label: dict, attached: bool, path: Path) -> dict:
    """shape, dtype, header bytes, nodata, scale/offset and spacing from a PDS3 label."""
    out: dict = {}
    lines, samples = _label_number(label, "LINES", path), _label_number(label, "LINE_SAMPLES", path)
    if lines and samples:
        out["shape"] = (int(lines[0]), int(samples[0]))
    stype, bits = label.get("SAMPLE_TYPE", "").strip('"').upper(), _label_number(label, "SAMPLE_BITS", path)
    if stype:
        if stype not in _PDS_TYPES:
            raise FedmapError(f"cannot read DEM {path}: PDS SAMPLE_TYPE {stype} is not supported")
        kind, order = _PDS_TYPES[stype]
        nbytes = int(bits[0]) // 8 if bits else 2
        out["dtype"], out["byteorder"] = f"{kind}{nbytes}", order
    record = _label_number(label, "RECORD_BYTES", path)
    pointer = label.get("^IMAGE")
    if pointer is not None:
        m = re.search(r"(\d+)\s*(<BYTES>)?\s*\)?\s*$", pointer.upper())
        if m is None:
            raise FedmapError(f"cannot read DEM {path}: unreadable PDS pointer ^IMAGE = {pointer}")
        n = int(m.group(1))
        out["header_bytes"] = n - 1 if m.group(2) else (n - 1) * int(record[0] if record else 0)
    elif attached and record and "LABEL_RECORDS" in label:
        out["header_bytes"] = int(_label_number(label, "LABEL_RECORDS", path)[0] * record[0])  # type: ignore[index]
    for key in ("MISSING_CONSTANT", "CORE_NULL"):
        v = _label_number(label, key, path)
        if v is not None:
            out["nodata"] = v[0]
            break
    for key, name in (("SCALING_FACTOR", "scale"), ("OFFSET", "offset")):
        v = _label_number(label, key, path)
        if v is not None:
            out[name] = v[0]
    scale = _label_number(label, "MAP_SCALE", path)
    res = _label_number(label, "MAP_RESOLUTION", path)
    if scale is not None and scale[0] > 0:
        out["pixel_size"] = scale[0] * (1.0 if scale[1].startswith("M") else 1000.0)  # KM/PIXEL unless METERS
    elif res is not None and res[0] > 0:
        radius = _label_number(label, "A_AXIS_RADIUS", path)
        if radius is not None:
            out["pixel_size"] = math.radians(1.0) * radius[0] * 1000.0 / res[0]
    return out


def read_raw(path: Path, *, shape=None, dtype=None, byteorder=None, header_bytes=None) -> RawRaster:
    """Read a raw PDS-style image (``.img``/``.raw``): rows of samples, no compression.

    Layout comes from the options, else from a PDS3 label (attached at the start of the
    file, or a ``.lbl`` sidecar with the same stem): ``LINES``, ``LINE_SAMPLES``,
    ``SAMPLE_TYPE``, ``SAMPLE_BITS``, ``^IMAGE``/``RECORD_BYTES``/``LABEL_RECORDS``,
    ``MISSING_CONSTANT``, ``SCALING_FACTOR``/``OFFSET`` and ``MAP_SCALE`` (km/pixel) or
    ``MAP_RESOLUTION`` (pixels/degree, with ``A_AXIS_RADIUS``). Options win over the
    label. Without a label: ``shape=(rows, cols)`` is required; ``dtype`` defaults to
    ``"int16"``, ``byteorder`` to ``"big"`` (PDS's MSB), ``header_bytes`` to 0. The file
    size must be exactly ``header_bytes + rows * cols * itemsize`` (a labelled file may
    carry less than one record of padding).
    """
    found = _find_label(path)
    layout = _label_layout(found[0], found[2], path) if found else {}
    record = _label_number(found[0], "RECORD_BYTES", path) if found else None
    if shape is not None:
        layout["shape"] = shape
    if dtype is not None:
        layout["dtype"] = dtype
    if byteorder is not None:
        if str(byteorder).lower() not in _BYTEORDERS:
            raise FedmapError(f"byteorder must be 'big' or 'little', got {byteorder!r}")
        layout["byteorder"] = _BYTEORDERS[str(byteorder).lower()]
    if header_bytes is not None:
        layout["header_bytes"] = header_bytes
    if "shape" not in layout:
        raise FedmapError(f"cannot read raw DEM {path}: no PDS label found; pass shape=(rows, cols) "
                          f"(and dtype, byteorder, header_bytes if not int16 big-endian without header)")
    try:
        rows, cols = (int(v) for v in layout["shape"])
        dt = np.dtype(layout.get("dtype", "int16")).newbyteorder(layout.get("byteorder", ">"))
    except (TypeError, ValueError) as exc:
        raise FedmapError(f"cannot read raw DEM {path}: bad shape/dtype ({_one_line(exc)})") from exc
    if rows <= 0 or cols <= 0 or dt.kind not in "iuf":
        raise FedmapError(f"cannot read raw DEM {path}: need a positive shape and an integer or float dtype, "
                          f"got {rows}x{cols} {dt}")
    offset = int(layout.get("header_bytes", 0))
    need = offset + rows * cols * dt.itemsize
    size = path.stat().st_size
    slack = int(record[0]) - 1 if (found and record) else 0
    if not need <= size <= need + slack:
        raise FedmapError(f"raw DEM {path} is {size:,} bytes but {offset} header + {rows} x {cols} x "
                          f"{dt.itemsize} B ({dt.name}) = {need:,} bytes: wrong shape, dtype or header_bytes?")
    values = np.fromfile(path, dtype=dt, count=rows * cols, offset=offset).reshape(rows, cols)
    px = layout.get("pixel_size")
    meta = {"format": "raw", "label": found[1] if found else None, "shape_in_file": [rows, cols],
            "dtype_in_file": dt.str, "header_bytes": offset}
    return RawRaster(values.astype(dt.newbyteorder("=")), layout.get("nodata"), layout.get("scale", 1.0),
                     layout.get("offset", 0.0), (px, px) if px else None, meta)


# --------------------------------------------------------------------------- heightmap PNG


def read_heightmap_png(path: Path, *, offset: float = HEIGHTMAP_OFFSET_M, zero_is_nodata: bool = True) -> RawRaster:
    """Read an RGB-packed heightmap tile: ``metres = R + 256 G + 65536 B - offset``.

    A raw value of 0 (all channels 0, i.e. ``-offset`` m) is a gap in such tiles and is
    nodata unless ``zero_is_nodata=False``. Alpha is ignored. Grey or paletted PNGs are
    refused: they are maps or pictures, not packed elevations. The values returned are
    already metres; the file holds no ground spacing.
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
    meta = {"format": "heightmap-png", "offset": float(offset), "zero_is_nodata": bool(zero_is_nodata)}
    return RawRaster(metres, None, meta=meta)


#: Reader and accepted keyword options per suffix.
READERS: dict[str, tuple[Callable[..., RawRaster], tuple[str, ...]]] = {
    ".asc": (read_ascii_grid, ("geographic", "radius_m")),
    ".img": (read_raw, ("shape", "dtype", "byteorder", "header_bytes")),
    ".raw": (read_raw, ("shape", "dtype", "byteorder", "header_bytes")),
    ".png": (read_heightmap_png, ("offset", "zero_is_nodata")),
}
