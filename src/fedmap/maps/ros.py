"""Class maps in the ROS map_server format: a YAML file plus an image (PGM).

Writing (:func:`write_ros_map`) gives a *trinary* map: ``map.pgm`` holds 254 for free,
0 for occupied (impassable) and 205 for unknown cells, row 0 at the top (largest y), and
``map.yaml`` holds::

    image: map.pgm
    mode: trinary
    resolution: 0.5           # metres per cell
    origin: [x, y, 0.0]       # pose of the lower-left corner of the lower-left cell
    negate: 0
    occupied_thresh: 0.65
    free_thresh: 0.196

``free_thresh`` is 0.196, not map_server's 0.25 default: the unknown grey 205 has
occupancy (255 - 205) / 255 = 0.196, so with 0.25 every unknown cell would load as free.
ROS 1's map_saver writes 0.196 for the same reason, and Nav2 does since
ros-navigation/navigation2#5278 (see also SteveMacenski/slam_toolbox#587).
``origin`` is the map's lower-left corner in its CRS when that CRS is metric (projected
in metres, or a local frame), else (0, 0).

Reading (:func:`read_ros_map`) follows map_server: the image's grey level ``v`` (the
mean of R, G, B for a colour image) gives the occupancy ``p = (255 - v) / 255``, or
``v / 255`` with ``negate: 1``. In ``trinary`` and ``scale`` mode a cell is IMPASSABLE
when ``p > occupied_thresh``, FREE when ``p < free_thresh`` and UNKNOWN otherwise (scale
mode's graded costs between the thresholds have no fedmap class, so they are unknown).
In ``raw`` mode ``v`` is the occupancy in percent, 0..100, and anything above 100 (e.g.
255, map_server's -1) is unknown; the thresholds then apply to ``v / 100``.

The YAML is small and flat, so it is written by hand and read by :func:`parse_map_yaml`,
a minimal safe reader of ``key: value`` lines, flow lists ``[a, b]`` and block lists.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
from affine import Affine

from fedmap._util import atomic_write_bytes
from fedmap._util import one_line as _one_line
from fedmap.errors import FedmapError
from fedmap.maps.georef import is_metric
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap

#: PGM grey level of each class in a trinary map.
TRINARY_VALUES: dict[int, int] = {FREE: 254, IMPASSABLE: 0, UNKNOWN: 205}
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
MODES = ("trinary", "scale", "raw")


def occupancy_classes(p: np.ndarray, *, occupied_thresh: float = OCCUPIED_THRESH,
                      free_thresh: float = FREE_THRESH) -> np.ndarray:
    """map_server's trinary rule on occupancy probabilities ``p`` (0..1): IMPASSABLE above
    ``occupied_thresh``, FREE below ``free_thresh``, UNKNOWN between (uint8 classes)."""
    return np.where(p > occupied_thresh, IMPASSABLE, np.where(p < free_thresh, FREE, UNKNOWN)).astype(np.uint8)


def classes_from_occupancy(values: np.ndarray, *, occupied_thresh: float = OCCUPIED_THRESH,
                           free_thresh: float = FREE_THRESH) -> np.ndarray:
    """Classes of occupancy in percent (an OccupancyGrid's values, a ``raw`` map image's grey
    levels) by map_server's thresholds on ``p = value / 100``; a value outside 0..100 (an
    OccupancyGrid's -1, a raw image's 255) is UNKNOWN."""
    v = np.asarray(values, dtype=np.float64)
    classes = occupancy_classes(v / 100.0, occupied_thresh=occupied_thresh, free_thresh=free_thresh)
    classes[(v < 0) | (v > 100)] = UNKNOWN
    return classes


def _fmt(v: float) -> str:
    return repr(float(v))


def lower_left_origin(grid: GridMap) -> tuple[float, float]:
    """The lower-left corner of ``grid`` in its CRS when that CRS is metric (north-up: the
    transform's ``e`` < 0), else (0, 0): a map_server ``origin``, an OccupancyGrid's
    ``info.origin``, a recording's ``map`` frame."""
    t = grid.transform
    if t is None or not is_metric(grid.crs):
        return 0.0, 0.0
    return float(t.c), float(t.f + t.e * grid.shape[0])


def map_yaml_text(grid: GridMap, image: str, *, occupied_thresh: float = OCCUPIED_THRESH,
                  free_thresh: float = FREE_THRESH) -> str:
    """The map_server YAML of ``grid`` whose image file is ``image``."""
    x0, y0 = lower_left_origin(grid)
    if any(c in image for c in ":#\n'\"[]{}") or image != image.strip():
        raise FedmapError(f"ROS map image name {image!r} must be a plain file name")
    return (f"image: {image}\nmode: trinary\nresolution: {_fmt(grid.pixel_size)}\n"
            f"origin: [{_fmt(x0)}, {_fmt(y0)}, 0.0]\nnegate: 0\noccupied_thresh: {_fmt(occupied_thresh)}\n"
            f"free_thresh: {_fmt(free_thresh)}\n")


def write_ros_map(grid: GridMap, yaml_path, *, occupied_thresh: float = OCCUPIED_THRESH,
                  free_thresh: float = FREE_THRESH) -> tuple[Path, Path]:
    """Write ``yaml_path`` and the trinary PGM beside it (same stem, ``.pgm``), each atomically.

    Returns the YAML and PGM paths.
    """
    from PIL import Image

    yaml_path = Path(yaml_path)
    pgm_path = yaml_path.with_suffix(".pgm")
    if not 0.0 <= free_thresh < occupied_thresh <= 1.0:
        raise FedmapError(f"ROS thresholds need 0 <= free_thresh < occupied_thresh <= 1, got {free_thresh}, "
                          f"{occupied_thresh}")
    lut = np.zeros(3, dtype=np.uint8)
    for c, v in TRINARY_VALUES.items():
        lut[c] = v
    buf = io.BytesIO()
    Image.fromarray(lut[grid.classes], mode="L").save(buf, format="PPM")  # an L image saves as binary PGM (P5)
    atomic_write_bytes(pgm_path, buf.getvalue())
    text = map_yaml_text(grid, pgm_path.name, occupied_thresh=occupied_thresh, free_thresh=free_thresh)
    atomic_write_bytes(yaml_path, text.encode("utf-8"))
    return yaml_path, pgm_path


# --------------------------------------------------------------------------- reading


def _scalar(text: str):
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def _strip_comment(line: str) -> str:
    out, quote = [], ""
    for i, ch in enumerate(line):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            break
        out.append(ch)
    return "".join(out).rstrip()


def parse_map_yaml(text: str, where: str = "map YAML") -> dict:
    """Read the flat YAML of a map_server map: ``key: value`` lines whose values are
    numbers, strings or lists (``[a, b, c]`` or ``- a`` lines under an empty key)."""
    out: dict = {}
    block: str | None = None
    for n, raw_line in enumerate(text.splitlines(), start=1):
        line = _strip_comment(raw_line)
        if not line.strip() or line.strip() in ("---", "..."):
            continue
        stripped = line.strip()
        if stripped.startswith("- ") or stripped == "-":
            if block is None:
                raise FedmapError(f"{where} line {n}: a list item without a key")
            out[block].append(_scalar(stripped[1:]))
            continue
        if ":" not in stripped:
            raise FedmapError(f"{where} line {n}: expected 'key: value', got {stripped!r}")
        key, value = (s.strip() for s in stripped.split(":", 1))
        if value == "":
            out[key], block = [], key
            continue
        block = None
        if value.startswith("["):
            if not value.endswith("]"):
                raise FedmapError(f"{where} line {n}: unclosed list {value!r}")
            inner = value[1:-1].strip()
            out[key] = [_scalar(v) for v in inner.split(",")] if inner else []
        else:
            out[key] = _scalar(value)
    return out


def _number(data: dict, key: str, default: float | None, where: str) -> float:
    v = data.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise FedmapError(f"{where}: {key} must be a number, got {v!r}")
    return float(v)


def _grey_levels(image_path: Path, where: str) -> np.ndarray:
    """The image's grey level per pixel (mean of R, G, B for colour), (H, W) float64 0..255."""
    from PIL import Image

    from fedmap.maps.formats import _pil_errors

    if not image_path.is_file():
        raise FedmapError(f"{where}: image {image_path} not found")
    try:
        with Image.open(image_path) as img:
            img.load()
            if img.mode in ("L", "P", "1", "LA", "PA"):
                a = np.asarray(img.convert("L"), dtype=np.float64)
            elif img.mode.startswith("I"):
                a = np.asarray(img, dtype=np.float64)
            else:
                a = np.asarray(img.convert("RGB"), dtype=np.float64).mean(axis=2)
    except _pil_errors() as exc:
        raise FedmapError(f"{where}: cannot read image {image_path} ({_one_line(exc)})") from exc
    return a


def read_ros_map(yaml_path) -> GridMap:
    """Read a map_server map (YAML + image) as classes (see the module docstring).

    The grid's transform puts its lower-left corner at ``origin`` with ``resolution``
    metres per cell (no CRS); a non-zero yaw (rotated map) leaves the transform unset and
    is noted in ``meta["yaw"]``.
    """
    yaml_path = Path(yaml_path)
    where = f"ROS map {yaml_path}"
    try:
        text = yaml_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FedmapError(f"cannot read {where}: {_one_line(exc)}") from exc
    data = parse_map_yaml(text, where)
    if "image" not in data or not isinstance(data["image"], str):
        raise FedmapError(f"{where} has no image")
    res = _number(data, "resolution", None, where)
    if res <= 0:
        raise FedmapError(f"{where}: resolution must be positive, got {res}")
    occ = _number(data, "occupied_thresh", OCCUPIED_THRESH, where)
    free = _number(data, "free_thresh", FREE_THRESH, where)
    negate = _number(data, "negate", 0, where)
    mode = str(data.get("mode", "trinary")).lower()
    if mode not in MODES:
        raise FedmapError(f"{where}: mode must be one of {', '.join(MODES)}, got {mode!r}")
    origin = data.get("origin", [0.0, 0.0, 0.0])
    if not (isinstance(origin, list) and len(origin) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in origin)):
        raise FedmapError(f"{where}: origin must be [x, y, yaw], got {origin!r}")
    image = Path(data["image"])
    image = image if image.is_absolute() else yaml_path.parent / image
    v = _grey_levels(image, where)
    if mode == "raw":
        classes = classes_from_occupancy(v, occupied_thresh=occ, free_thresh=free)
    else:
        p = v / 255.0 if negate else (255.0 - v) / 255.0
        classes = occupancy_classes(p, occupied_thresh=occ, free_thresh=free)
    x0, y0, yaw = (float(o) for o in origin)
    h = v.shape[0]
    transform = Affine(res, 0.0, x0, 0.0, -res, y0 + h * res) if yaw == 0 else None
    meta = {"format": "ros", "mode": mode, "negate": int(negate), "occupied_thresh": occ, "free_thresh": free,
            "origin": [x0, y0, yaw], "image": str(image), "pixel_size_from": "file"}
    if yaw != 0:
        meta["yaw"] = yaw
    return GridMap(classes.astype(np.uint8), res, str(yaml_path), meta, transform=transform)
