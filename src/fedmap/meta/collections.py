"""Map collections: maps grouped into categories, each category one meta-learning task.

A :class:`MapCollection` holds ``size x size`` :class:`~fedmap.maps.grid.GridMap` s per
category, loaded eagerly (meta-training uses small maps; the network is a function of
coordinates in (0, 1), so a map's resolution only sets how finely it is sampled).

Sources
-------
``builtin``
    :func:`earth_like`: seeded Earth-like categories, ``urban`` (a road grid between
    building blocks), ``rural`` (fields with woods, hedgerows and tracks), ``highway``
    (wide curved roads with barriers through rough ground) and ``natural`` (a fractal
    hill DEM through :func:`~fedmap.maps.traversability.dem_to_traversability`).
Folders (:func:`load_collection`), ``layout`` one of:

``maps``      ``root/<category>/*.png|*.npy`` traversability maps (:func:`fedmap.maps.io.load_map`).
``kitti``     ``root/<category>/<drive>/*.png|*.npy`` maps, e.g. ``Residential/2011_09_26_drive_0019/
              000000.png``: the KITTI raw category/drive layout; the images must already be
              traversability maps in the map colours (bird's-eye occupancy), one per frame.
``domars``    ``root/[train|val|test]/<class>/*.jpg|*.png`` (DoMars16k): landform image crops,
              not maps. Rule: luminance, resized to ``size``; cells whose Sobel gradient
              magnitude is above the image's ``edge_quantile`` (default 0.8) quantile are
              IMPASSABLE (rims, ridges, scarps), the rest FREE. Category = class folder.
``dem``       ``root/<category>/*.tif|*.npy`` DEMs, or DEM files directly in ``root`` (then
              the category is the file's stem); every DEM is cut into non-overlapping
              ``size x size`` tiles at its native resolution, classified with the given
              thresholds; tiles with more than half nodata are dropped.

Maps whose side differs from ``size`` are resampled by nearest neighbour (classes).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, GridMap
from fedmap.maps.io import load_dem, load_map
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, slope_degrees

LAYOUTS = ("maps", "kitti", "domars", "dem")
BUILTIN_CATEGORIES = ("urban", "rural", "highway", "natural")
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class MapCollection:
    """Categories of equally sized maps. ``categories``: name -> list of maps."""
    name: str
    categories: dict[str, list[GridMap]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.categories = {k: list(v) for k, v in sorted(self.categories.items()) if len(v)}
        if not self.categories:
            raise FedmapError(f"collection {self.name!r} holds no maps")

    @property
    def n_maps(self) -> int:
        return sum(len(v) for v in self.categories.values())

    def maps(self) -> list[GridMap]:
        return [m for v in self.categories.values() for m in v]

    def sample(self, rng: np.random.Generator) -> GridMap:
        """A task (category, uniformly) and then one of its maps (uniformly)."""
        names = list(self.categories)
        maps = self.categories[names[int(rng.integers(len(names)))]]
        return maps[int(rng.integers(len(maps)))]

    def subset(self, names: list[str] | tuple[str, ...]) -> MapCollection:
        missing = [n for n in names if n not in self.categories]
        if missing:
            raise FedmapError(f"collection {self.name!r} has no category {missing[0]!r}; "
                              f"it has {', '.join(self.categories)}")
        return MapCollection(f"{self.name}[{','.join(names)}]", {n: self.categories[n] for n in names})

    def split(self, *, holdout: int, seed: int = 0) -> tuple[MapCollection, list[GridMap]]:
        """Hold ``holdout`` maps of every category out (for validation); the rest train.

        A category with ``holdout`` maps or fewer keeps all of them for training.
        """
        rng = np.random.default_rng(seed)
        train, held = {}, []
        for name, maps in self.categories.items():
            if len(maps) <= holdout:
                train[name] = maps
                continue
            order = rng.permutation(len(maps))
            held += [maps[i] for i in order[:holdout]]
            train[name] = [maps[i] for i in sorted(order[holdout:])]
        return MapCollection(self.name, train), held

    def summary(self) -> dict:
        return {"name": self.name, "maps": self.n_maps,
                "categories": {k: {"maps": len(v), **_mean_fractions(v)} for k, v in self.categories.items()}}


def _mean_fractions(maps: list[GridMap]) -> dict:
    f = [m.fractions() for m in maps]
    return {k: float(np.mean([x[k] for x in f])) for k in f[0]}


def resize_classes(classes: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resample of a class array to ``size x size`` (pixel centres)."""
    h, w = classes.shape
    rows = np.minimum(((np.arange(size) + 0.5) * h / size).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(size) + 0.5) * w / size).astype(np.int64), w - 1)
    return classes[np.ix_(rows, cols)]


def _sized(grid: GridMap, size: int) -> GridMap:
    if grid.shape == (size, size):
        return grid
    h, w = grid.shape
    px = grid.pixel_size * max(h, w) / size
    return GridMap(resize_classes(grid.classes, size), px, grid.source, dict(grid.meta))


# ------------------------------------------------------------------ built-in Earth-like

def _blobs(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """Smooth random field with zero mean and unit std, (n, n)."""
    f = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma, mode="wrap")
    return (f - f.mean()) / (f.std() + 1e-12)


def _line_mask(n: int, dist: np.ndarray, half_width: float) -> np.ndarray:
    return np.abs(dist) <= half_width


def _urban(rng: np.random.Generator, n: int) -> np.ndarray:
    """Building blocks (IMPASSABLE) between a jittered street grid (FREE), a few plazas."""
    out = np.full((n, n), IMPASSABLE, np.uint8)
    for axis in (0, 1):
        pos = rng.uniform(0, n * 0.15)
        while pos < n:
            width = int(rng.integers(2, 5))
            a = int(pos)
            if axis == 0:
                out[a : a + width, :] = FREE
            else:
                out[:, a : a + width] = FREE
            pos += rng.uniform(n * 0.12, n * 0.28)
    for _ in range(int(rng.integers(0, 3))):  # plazas / parks
        r, c = rng.integers(0, n, 2)
        h, w = rng.integers(n // 10, n // 4, 2)
        out[r : r + h, c : c + w] = FREE
    return out


def _rural(rng: np.random.Generator, n: int) -> np.ndarray:
    """Open fields (FREE) with woods, hedgerows (IMPASSABLE) and tracks cut through (FREE)."""
    woods = _blobs(rng, n, n / 10) > rng.uniform(0.6, 1.2)
    out = np.where(woods, IMPASSABLE, FREE).astype(np.uint8)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    for _ in range(int(rng.integers(2, 5))):  # hedgerows: straight lines
        ang = rng.uniform(0, np.pi)
        d = (xx - rng.uniform(0, n)) * np.sin(ang) - (yy - rng.uniform(0, n)) * np.cos(ang)
        out[_line_mask(n, d, 0.6)] = IMPASSABLE
    for _ in range(int(rng.integers(1, 3))):  # tracks: gentle sine curves
        amp, per, ph = rng.uniform(2, n / 6), rng.uniform(n / 2, 2 * n), rng.uniform(0, 2 * np.pi)
        base = rng.uniform(0.2, 0.8) * n
        d = (yy - base - amp * np.sin(2 * np.pi * xx / per + ph)) if rng.random() < 0.5 else \
            (xx - base - amp * np.sin(2 * np.pi * yy / per + ph))
        out[_line_mask(n, d, 1.0)] = FREE
    return out


def _highway(rng: np.random.Generator, n: int) -> np.ndarray:
    """Rough ground (about half IMPASSABLE) crossed by wide curved carriageways (FREE) with
    barriers (IMPASSABLE) along their edges."""
    out = np.where(_blobs(rng, n, n / 16) > rng.uniform(-0.3, 0.3), IMPASSABLE, FREE).astype(np.uint8)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    for _ in range(int(rng.integers(1, 3))):
        ang = rng.uniform(0, np.pi)
        cx, cy = rng.uniform(0.25, 0.75, 2) * n
        u = (xx - cx) * np.cos(ang) + (yy - cy) * np.sin(ang)
        v = -(xx - cx) * np.sin(ang) + (yy - cy) * np.cos(ang)
        d = v - rng.uniform(-1, 1) * u**2 / n  # gentle curve
        hw = rng.uniform(n / 24, n / 12)
        out[_line_mask(n, d, hw + 1.2) & ~_line_mask(n, d, hw)] = IMPASSABLE
        out[_line_mask(n, d, hw)] = FREE
    return out


def fractal_dem(rng: np.random.Generator, n: int, *, beta: float, pixel_size: float) -> Dem:
    """Power-law (1/f^beta) spectral noise DEM, unit-free then scaled to 100 m relief."""
    k = np.fft.fftfreq(n)
    kk = np.hypot(*np.meshgrid(k, k, indexing="ij"))
    kk[0, 0] = np.inf
    spec = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) * kk ** (-beta / 2)
    z = np.fft.ifft2(spec).real
    z = (z - z.min()) / (np.ptp(z) + 1e-12) * 100.0
    return Dem(z.astype(np.float32), pixel_size, "fractal hills")


def _natural(rng: np.random.Generator, n: int) -> np.ndarray:
    """Fractal hills; the slope limit is set so that 10-35% of the map is too steep."""
    dem = fractal_dem(rng, n, beta=rng.uniform(4.0, 5.0), pixel_size=30.0)
    slope = slope_degrees(dem.elevation, dem.pixel_size)
    limit = float(np.clip(np.quantile(slope, 1 - rng.uniform(0.10, 0.35)), 0.01, 89.0))
    return dem_to_traversability(dem, TraversabilityThresholds(max_slope_deg=limit)).classes


_GENERATORS = {"urban": _urban, "rural": _rural, "highway": _highway, "natural": _natural}


#: The smallest side of a built-in map (below 12 the generators cannot place their features).
MIN_BUILTIN_SIZE = 16


def earth_like(*, size: int = 64, per_category: int = 32, seed: int = 0,
               categories: tuple[str, ...] = BUILTIN_CATEGORIES) -> MapCollection:
    """The built-in Earth-like collection: ``per_category`` seeded maps per category, of at
    least :data:`MIN_BUILTIN_SIZE` cells a side (the generators' streets and blocks need room)."""
    if size < MIN_BUILTIN_SIZE or per_category < 1:
        raise FedmapError(f"need maps of at least {MIN_BUILTIN_SIZE}x{MIN_BUILTIN_SIZE} and one map per category, "
                          f"got size {size} and {per_category} per category")
    cats = {}
    for ci, name in enumerate(categories):
        if name not in _GENERATORS:
            raise FedmapError(f"unknown built-in category {name!r}; choose from {', '.join(_GENERATORS)}")
        maps = []
        for i in range(per_category):
            rng = np.random.default_rng([seed, ci, i])
            maps.append(GridMap(_GENERATORS[name](rng, size), 1.0, f"builtin:{name}#{i}"))
        cats[name] = maps
    return MapCollection(f"builtin(seed={seed},size={size},n={per_category})", cats)


# ------------------------------------------------------------------ folders

def _files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)


def _dirs(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))


def dem_tiles(dem: Dem, size: int, thresholds: TraversabilityThresholds | None = None,
              *, max_nodata: float = 0.5, stride: int | None = None) -> list[GridMap]:
    """``size x size`` tiles of a DEM as traversability maps (row-major), every ``stride``
    cells (default ``size``: non-overlapping); tiles over ``max_nodata`` nodata are dropped."""
    h, w = dem.shape
    step = stride or size
    out = []
    for r in range(0, h - size + 1, step):
        for c in range(0, w - size + 1, step):
            z = dem.elevation[r : r + size, c : c + size]
            if np.isnan(z).mean() > max_nodata:
                continue
            tile = Dem(z, dem.pixel_size, f"{dem.source}[{r}:{r + size},{c}:{c + size}]")
            out.append(dem_to_traversability(tile, thresholds))
    return out


def domars_map(path: Path, size: int, *, edge_quantile: float = 0.8) -> GridMap:
    """A DoMars16k-style landform image as a map (see the module docstring for the rule)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            grey = np.asarray(img.convert("L").resize((size, size), Image.Resampling.BILINEAR), dtype=np.float64) / 255.0
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise FedmapError(f"cannot read image {path}: {type(e).__name__}") from e
    mag = np.hypot(ndimage.sobel(grey, 0), ndimage.sobel(grey, 1))
    impassable = mag > np.quantile(mag, edge_quantile)
    return GridMap(np.where(impassable, IMPASSABLE, FREE).astype(np.uint8), 1.0, str(path),
                   {"rule": f"sobel > q{edge_quantile}"})


def load_collection(root: str | Path, *, layout: str = "maps", size: int = 64, max_per_category: int | None = None,
                    thresholds: TraversabilityThresholds | None = None, seed: int = 0) -> MapCollection:
    """Load a folder as a collection (``layout``: maps, kitti, domars or dem; see module doc).

    ``max_per_category`` keeps a seeded random subset of each category.
    """
    root = Path(root)
    if layout not in LAYOUTS:
        raise FedmapError(f"unknown collection layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    if not root.is_dir():
        raise FedmapError(f"collection folder {root} does not exist")
    cats: dict[str, list[GridMap]] = {}
    if layout == "maps":
        for d in _dirs(root):
            cats[d.name] = [_sized(load_map(p), size) for p in _files(d, (".png", ".npy"))]
    elif layout == "kitti":
        for d in _dirs(root):
            cats[d.name] = [_sized(load_map(p), size) for drive in _dirs(d) for p in _files(drive, (".png", ".npy"))]
    elif layout == "domars":
        splits = [root / s for s in ("train", "val", "test") if (root / s).is_dir()]
        if not splits:
            raise FedmapError(f"{root} has no train/, val/ or test/ folder (DoMars16k layout)")
        for s in splits:
            for d in _dirs(s):
                cats.setdefault(d.name, []).extend(domars_map(p, size) for p in _files(d, _IMAGE_SUFFIXES))
    else:  # dem
        dem_suffixes = (".tif", ".tiff", ".npy")
        groups = {d.name: _files(d, dem_suffixes) for d in _dirs(root)}
        groups.update({p.stem: [p] for p in _files(root, dem_suffixes)})
        for name, files in groups.items():
            cats[name] = [t for p in files for t in dem_tiles(load_dem(p), size, thresholds)]
    if max_per_category is not None:
        rng = np.random.default_rng(seed)
        cats = {k: [v[i] for i in sorted(rng.choice(len(v), max_per_category, replace=False))]
                if len(v) > max_per_category else v for k, v in cats.items()}
    if not any(cats.values()):
        raise FedmapError(f"no maps found in {root} for layout {layout!r} (see fedmap.meta.collections)")
    return MapCollection(f"{layout}:{root}", cats)
