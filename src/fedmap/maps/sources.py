"""Where a run's ground-truth map comes from: a built-in terrain, a DEM file, a class
map, or a mosaic of heightmap tiles.

A :class:`TerrainSource` says what to read and how to fit it to the run's grid;
:func:`load_truth` turns it into the traversability :class:`~fedmap.maps.grid.GridMap`
(and :func:`load_source_dem` gives the prepared DEM). ``fedmap run`` and
``fedmap reproduce`` both use these.

Preparing a DEM: read -> ``crop`` -> a centred square crop if it is not square (the
networks and the exploration split a square map) -> resample to ``size`` cells ->
traversability with ``thresholds`` at the resulting pixel size. A class map is cropped
the same way and resampled by nearest neighbour.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from fedmap._schema import setting, wiring
from fedmap._util import check_keys
from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.georef import crop_transform, scale_transform
from fedmap.maps.grid import GridMap
from fedmap.maps.io import crop_dem, load_dem, load_map, mosaic_heightmap_tiles, resample_dem
from fedmap.maps.regrid import RESAMPLE_METHODS
from fedmap.maps.terrain import TERRAIN_KINDS, generate_dem
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability

SOURCE_KINDS: tuple[str, ...] = ("builtin", "dem", "map", "tiles")

#: Options that :func:`fedmap.maps.io.load_dem` (and ``load_map``: pixel_size) accepts.
READER_OPTIONS: dict[str, tuple[type, ...]] = {
    "pixel_size": (float, int), "nodata": (float, int), "band": (int,), "crs": (str,),
    "shape": (list,), "dtype": (str,), "byteorder": (str,), "header_bytes": (int,), "offset": (float, int),
    "zero_is_nodata": (bool,), "topic": (str,),
}

#: Built-in terrain side when a builtin source gives no ``size``.
DEFAULT_BUILTIN_SIZE = 128


@dataclass(frozen=True)
class TerrainSource:
    """What terrain a run maps and how it is fitted to the run's grid.

    Parameters
    ----------
    kind : str
        ``builtin`` (seeded synthetic terrain), ``dem`` (a DEM file: anything GDAL reads,
        e.g. .tif, .cub, .img, .xml (PDS4), .asc; a .png heightmap; .npy), ``map`` (a class
        map: .png, .npy, .tif, ROS .yaml, or a ROS 2 bag: its folder, .db3 or .mcap) or ``tiles`` (RGB-packed
        GLD100-named tiles ``256p+{lon}+{lat}.png`` in the folder ``path``).
    path : str, optional
        The file (dem, map) or the tile folder (tiles).
    terrain : str
        The built-in terrain kind (mars, moon, ice); also the label of built-in runs.
    lon, lat, tiles : int
        ``tiles``: south-west tile and the number of tiles per side.
    crop : int or [row0, row1, col0, col1], optional
        Centred square of this side, or a box in cells, cut before resampling.
    size : int, optional
        Resample the (square) map to ``size x size`` cells; built-in terrain is generated
        at this size (default 128). Without it a file keeps its resolution.
    resample : str
        ``area`` or ``bilinear`` for DEMs (class maps always use nearest).
    options : dict
        Reader options (``pixel_size``, ``nodata``, ``band``, ``crs``, ``shape``, ``dtype``,
        ``byteorder``, ``header_bytes``, ``offset``, ``zero_is_nodata``; ``topic``: a ROS 2
        bag's OccupancyGrid topic).
    thresholds : TraversabilityThresholds
        Rover limits for DEM -> traversability.
    """

    kind: str = setting("builtin", help="Terrain source", choices=lambda: SOURCE_KINDS)
    path: str | None = setting(None, help="The DEM or map file, or the tile folder", path=True)
    terrain: str = setting("mars", help="Built-in terrain", choices=lambda: TERRAIN_KINDS)
    lon: int | None = setting(None, help="tiles: longitude of the south-west tile")
    lat: int | None = setting(None, help="tiles: latitude of the south-west tile")
    tiles: int = setting(8, help="tiles: tiles per side")
    crop: int | tuple[int, int, int, int] | None = setting(
        None, help="Centred square crop in cells, or [row0, row1, col0, col1], before resampling")
    size: int | None = setting(None, help="Resample the terrain to size x size cells (built-in: generated at this "
                               f"size, default {DEFAULT_BUILTIN_SIZE})")
    resample: str = setting("area", help="DEM resampling", choices=lambda: RESAMPLE_METHODS)
    options: dict = setting(default_factory=dict, help="Reader options (pixel_size, nodata, band, crs, shape, dtype, "
                            "byteorder, header_bytes, offset, zero_is_nodata; topic: a bag's map topic)")
    thresholds: TraversabilityThresholds = wiring(default_factory=TraversabilityThresholds)

    def __post_init__(self) -> None:
        if self.kind not in SOURCE_KINDS:
            raise FedmapError(f"unknown terrain source kind {self.kind!r}; choose one of {', '.join(SOURCE_KINDS)}")
        if self.kind != "builtin" and not self.path:
            raise FedmapError(f"a {self.kind!r} terrain source needs a path")
        if self.kind == "tiles" and (self.lon is None or self.lat is None):
            raise FedmapError("a 'tiles' terrain source needs lon and lat (its south-west tile)")
        if self.kind == "tiles" and self.tiles < 1:
            raise FedmapError(f"tiles must be >= 1, got {self.tiles}")
        if self.crop is not None:
            crop = self.crop
            ok = (isinstance(crop, int) and crop > 0) or (
                isinstance(crop, (list, tuple)) and len(crop) == 4 and all(isinstance(v, int) for v in crop))
            if not ok:
                raise FedmapError(f"crop must be a side in cells or [row0, row1, col0, col1], got {crop!r}")
            if isinstance(crop, list):
                object.__setattr__(self, "crop", tuple(crop))
        if self.size is not None and (isinstance(self.size, bool) or not isinstance(self.size, int) or self.size < 3):
            raise FedmapError(f"terrain size must be at least 3 cells (the side the map is resampled to), "
                              f"got {self.size!r}")
        if self.resample not in RESAMPLE_METHODS:
            raise FedmapError(f"unknown resample method {self.resample!r}; choose one of {', '.join(RESAMPLE_METHODS)}")
        unknown = sorted(set(self.options) - set(READER_OPTIONS))
        if unknown:
            raise FedmapError(f"unknown reader option {unknown[0]!r}; known: {', '.join(READER_OPTIONS)}")
        if self.kind == "builtin" and self.crop is not None:
            raise FedmapError("crop does not apply to built-in terrain (set size instead)")
        if self.kind == "builtin" and self.size is None:
            object.__setattr__(self, "size", DEFAULT_BUILTIN_SIZE)
        if isinstance(self.thresholds, dict):
            object.__setattr__(self, "thresholds", TraversabilityThresholds(**self.thresholds))

    # ------------------------------------------------------------------ dict form

    def to_dict(self) -> dict:
        """Plain dict (TOML/JSON-ready): None entries, empty options and keys the kind
        does not use are left out."""
        d = asdict(self)
        if isinstance(d["crop"], tuple):
            d["crop"] = list(d["crop"])
        unused = {"builtin": ("path", "lon", "lat", "tiles", "crop", "resample"), "dem": ("terrain", "lon", "lat", "tiles"),
                  "map": ("terrain", "lon", "lat", "tiles", "resample"), "tiles": ("terrain",)}[self.kind]
        return {k: v for k, v in d.items() if v is not None and k not in unused and v != {}}

    @classmethod
    def from_dict(cls, data: dict, *, where: str = "terrain source") -> TerrainSource:
        """Build from a dict (e.g. a TOML ``[terrain]`` table plus ``thresholds``);
        unknown keys raise a :class:`FedmapError` naming the key and ``where``."""
        names = [f.name for f in fields(cls)]
        check_keys(data, names, where)
        return cls(**data)

    @property
    def label(self) -> str:
        """A short name for titles: the built-in kind or the file/tile name."""
        if self.kind == "builtin":
            return self.terrain
        name = Path(self.path or "").name
        if self.kind == "tiles":
            return f"{name} {self.tiles}x{self.tiles} tiles from ({self.lon}E, {self.lat}N)"
        return name


# --------------------------------------------------------------------------- loading


def _square_box(shape: tuple[int, int], crop) -> tuple[tuple[int, int], tuple[int, int]]:
    """Rows and cols of the window: the ``crop`` box or centred square, then squared."""
    h, w = shape
    if isinstance(crop, tuple):
        r0, r1, c0, c1 = crop
    else:
        side = min(h, w) if crop is None else crop
        if side > min(h, w):
            raise FedmapError(f"crop {side} is larger than the {h}x{w} terrain")
        r0, c0 = (h - side) // 2, (w - side) // 2
        r1, c1 = r0 + side, c0 + side
    if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
        raise FedmapError(f"crop box [{r0}, {r1}, {c0}, {c1}] is outside the {h}x{w} terrain")
    side = min(r1 - r0, c1 - c0)  # centred square inside the box
    r0 += (r1 - r0 - side) // 2
    c0 += (c1 - c0 - side) // 2
    return (r0, r0 + side), (c0, c0 + side)


def load_source_dem(source: TerrainSource, *, seed: int = 0) -> Dem:
    """The DEM of a builtin, dem or tiles source, cropped square and resampled to ``size``."""
    if source.kind == "builtin":
        assert source.size is not None  # __post_init__ sets the default size of built-in terrain
        px = source.options.get("pixel_size")
        return generate_dem(source.terrain, source.size, seed=seed,
                            pixel_size=None if px is None else float(px))
    if source.kind == "map":
        raise FedmapError("a 'map' terrain source has no DEM")
    if "topic" in source.options:
        raise FedmapError("reader option topic applies to a 'map' source read from a ROS 2 bag only")
    opts = dict(source.options)
    if isinstance(opts.get("shape"), list):
        opts["shape"] = tuple(opts["shape"])
    if source.kind == "tiles":
        extra = {k: v for k, v in opts.items() if k not in ("pixel_size", "offset", "zero_is_nodata")}
        if extra:
            raise FedmapError(f"reader option(s) {', '.join(sorted(extra))} do not apply to heightmap tiles")
        assert source.lon is not None and source.lat is not None  # __post_init__ refuses tiles without them
        dem = mosaic_heightmap_tiles(source.path, lon=source.lon, lat=source.lat, n=source.tiles, **opts)
    else:
        dem = load_dem(source.path, **opts)
    rows, cols = _square_box(dem.shape, source.crop)
    squared = square_note(dem.shape, rows, cols, source.crop)
    if (rows, cols) != ((0, dem.shape[0]), (0, dem.shape[1])):
        dem = crop_dem(dem, rows, cols)
    if squared:
        dem.meta["squared"] = squared
    if source.size is not None and source.size != dem.shape[0]:
        before = (dem.shape[0], dem.pixel_size)
        dem = resample_dem(dem, source.size, method=source.resample)
        dem.meta["resampled"] = resample_note(before, (dem.shape[0], dem.pixel_size), source.resample)
    return dem


def square_note(shape: tuple[int, int], rows: tuple[int, int], cols: tuple[int, int], crop) -> str | None:
    """One line when a map that is not square was cut to its centred square without a ``crop``
    asking for it (the networks and the exploration need a square map), else None."""
    if crop is not None or shape[0] == shape[1]:
        return None
    side = rows[1] - rows[0]
    return (f"the map is {shape[0]}x{shape[1]} cells; the run uses its centred {side}x{side} square (rows "
            f"{rows[0]}..{rows[1] - 1}, columns {cols[0]}..{cols[1] - 1}): set the terrain's crop to choose another")


def _metres(v: float) -> str:
    return f"{v / 1000:.3g} km" if v >= 1000 else f"{v:.3g} m"


def resample_note(before: tuple[int, float], after: tuple[int, float], method: str) -> str:
    """One line: the DEM was resampled, from what side and cell size to what."""
    return (f"the DEM was resampled ({method}) from {before[0]}x{before[0]} cells of {_metres(before[1])} to "
            f"{after[0]}x{after[0]} cells of {_metres(after[1])} (the terrain's size, from --size, the mission file or "
            f"its preset: size {before[0]} keeps its cells)")


def _nearest_classes(classes: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resampling of a square class grid: target cell centre -> source cell."""
    n = classes.shape[0]
    idx = np.minimum(((np.arange(size) + 0.5) * n / size).astype(np.intp), n - 1)
    return classes[np.ix_(idx, idx)]


def needs_dem(what: str) -> FedmapError:
    """The one-line error for a feature that needs the terrain's elevation on a class map."""
    return FedmapError(f"{what} needs the terrain's elevation (a DEM, tiles or built-in source, not a class map)")


def load_truth(source: TerrainSource, *, seed: int = 0, elevation: bool = False) -> GridMap:
    """The ground-truth traversability map of a source (see the module docstring); with
    ``elevation``, carrying the DEM it was classified from as its ``elevation`` layer."""
    truth, dem = load_terrain(source, seed=seed, with_dem=elevation)
    if not elevation:
        return truth
    if dem is None:
        raise needs_dem("an elevation layer")
    return truth.with_layer("elevation", dem.elevation)


#: What reading a DEM has to tell the user, each one line in its ``meta``, carried to the
#: truth made from it, in the order they are said.
DEM_NOTES = ("latitude_note", "cells_note", "squared", "resampled")


def terrain_notes(truth: GridMap) -> list[str]:
    """Every line loading ``truth`` has to tell the user: the DEM's notes, then its
    classification's warning (:func:`~fedmap.maps.traversability.dem_to_traversability`)."""
    return [str(truth.meta[k]) for k in (*DEM_NOTES, "warning") if truth.meta.get(k)]


def load_terrain(source: TerrainSource, *, seed: int = 0, with_dem: bool = True) -> tuple[GridMap, Dem | None]:
    """``(truth, dem)``: the truth as :func:`load_truth` gives it and, with ``with_dem``, the
    DEM it was classified from (None for a ``map`` source, or without ``with_dem``), read once."""
    if source.kind == "map":
        grid = load_map(source.path, pixel_size=source.options.get("pixel_size"), topic=source.options.get("topic"))
        (r0, r1), (c0, c1) = _square_box(grid.shape, source.crop)
        squared = square_note(grid.shape, (r0, r1), (c0, c1), source.crop)
        classes, px = grid.classes[r0:r1, c0:c1], grid.pixel_size
        transform = crop_transform(grid.transform, r0, c0)
        if source.size is not None and source.size != classes.shape[0]:
            px = px * classes.shape[0] / source.size
            transform = scale_transform(transform, classes.shape, (source.size, source.size))
            classes = _nearest_classes(classes, source.size)
        meta = {**grid.meta, "crop": [r0, r1, c0, c1], **({"squared": squared} if squared else {})}
        return GridMap(classes, px, grid.source, meta, transform=transform, crs=grid.crs), None
    dem = load_source_dem(source, seed=seed)
    truth = dem_to_traversability(dem, source.thresholds)
    for key in DEM_NOTES:  # said once, beside the truth (terrain_notes)
        if key in dem.meta:
            truth.meta[key] = dem.meta[key]
    return truth, dem if with_dem else None
