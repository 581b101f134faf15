"""Traversability grid maps in a shared global frame.

A :class:`GridMap` is an ``H x W`` array of classes (:data:`FREE`, :data:`IMPASSABLE`,
:data:`UNKNOWN`) plus metadata. Cells that are not UNKNOWN are *known*. For people and
as the network's target a map is rendered in the paper's colours (free = green,
impassable = red, unknown = grey 0.5); a network's RGB output goes back to classes by
nearest colour.

A map holds *named layers* (:data:`LAYERS`): the class array ``"classes"``, always, and
optionally ``"elevation"`` (metres, NaN where unknown; see :class:`GridMap`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
from affine import Affine

from fedmap._util import suggest
from fedmap.errors import FedmapError

FREE: int = 0
IMPASSABLE: int = 1
UNKNOWN: int = 2
CLASS_NAMES: tuple[str, ...] = ("free", "impassable", "unknown")

#: RGB colour of each class, indexed by class value, in [0, 1].
PALETTE = np.array(
    [
        [0.0, 1.0, 0.0],  # FREE: green
        [1.0, 0.0, 0.0],  # IMPASSABLE: red
        [0.5, 0.5, 0.5],  # UNKNOWN: grey
    ],
    dtype=np.float32,
)

#: Names of the layers a :class:`GridMap` can hold, canonical layer first.
LAYERS: tuple[str, ...] = ("classes", "elevation")


@dataclass
class GridMap:
    """A traversability map on a grid in the global frame.

    Parameters
    ----------
    classes : ndarray (H, W) uint8
        One of FREE, IMPASSABLE, UNKNOWN per cell.
    pixel_size : float
        Ground size of one cell in metres.
    source : str
        Where the map came from (file path, generator settings, agent id...).
    meta : dict
        Free-form notes (reader, thresholds, warnings).
    transform : affine.Affine, optional
        Cell (col, row) -> CRS (x, y), north-up (see :mod:`fedmap.maps.georef`); None for
        a grid without georeferencing (generated terrain).
    crs : str, optional
        The CRS as WKT, or None.

    Layers
    ------
    A map holds named ``(H, W)`` layers on one grid, all sharing ``pixel_size``,
    ``transform`` and ``crs``; :data:`LAYERS` lists the names a map can hold. ``"classes"``
    is stored in the ``classes`` field, which stays the canonical accessor; the optional
    ``"elevation"`` (metres, float32, NaN = unknown) in the keyword field ``elevation``.
    :attr:`layers` is a read-only mapping name -> array over the
    same arrays (no copies: ``grid.layers["classes"] is grid.classes``),
    :meth:`layer` fetches one by name (a one-line :class:`FedmapError` names a missing
    layer and the available ones) and :meth:`with_layer` returns a new map with one
    layer replaced, after checking its shape matches the map's and the layer's own
    rules (``classes``: integer codes FREE, IMPASSABLE, UNKNOWN, stored as uint8;
    ``elevation``: real heights, NaN where unknown, never infinite, stored as float32).
    :meth:`with_classes` carries the elevation along. An agent can derive its own classes
    from the elevation with its own rover profile
    (:func:`fedmap.maps.traversability.dem_to_traversability`).
    """

    classes: np.ndarray
    pixel_size: float = 1.0
    source: str = ""
    meta: dict = field(default_factory=dict)
    transform: Affine | None = None
    crs: str | None = None
    elevation: np.ndarray | None = None

    def __post_init__(self) -> None:
        c = np.asarray(self.classes)
        if c.ndim != 2:
            raise FedmapError(f"a map must be 2-D, got shape {c.shape}")
        if c.shape[0] <= 0 or c.shape[1] <= 0:
            raise FedmapError(f"a map must not be empty, got shape {c.shape}")
        if c.size and (c.min() < 0 or c.max() > UNKNOWN):
            raise FedmapError(f"map classes must be 0..{UNKNOWN}, got values {c.min()}..{c.max()}")
        self.classes = c.astype(np.uint8, copy=False)
        if not np.isfinite(self.pixel_size) or self.pixel_size <= 0:
            raise FedmapError(f"pixel size must be a positive number of metres, got {self.pixel_size}")
        if self.elevation is not None:
            self.elevation = check_elevation(self.elevation, self.classes.shape)

    @property
    def shape(self) -> tuple[int, int]:
        return self.classes.shape

    @property
    def layers(self) -> Mapping[str, np.ndarray]:
        """The map's layers, name -> ``(H, W)`` array, read-only; the arrays are the
        map's own (``layers["classes"] is classes``)."""
        out = {"classes": self.classes}
        if self.elevation is not None:
            out["elevation"] = self.elevation
        return MappingProxyType(out)

    def layer(self, name: str) -> np.ndarray:
        """The layer ``name``; a one-line error names it and the layers this map has."""
        layers = self.layers
        if name not in layers:
            raise FedmapError(f"this map has no layer {name!r}; available layers: {', '.join(layers)}")
        return layers[name]

    @property
    def known(self) -> np.ndarray:
        """Boolean mask of observed cells, (H, W)."""
        return self.classes != UNKNOWN

    @property
    def n_known(self) -> int:
        return int(self.known.sum())

    def to_rgb(self) -> np.ndarray:
        """Render in the paper's colours: (H, W, 3) float32 in [0, 1]."""
        return render_classes(self.classes)

    def fractions(self) -> dict[str, float]:
        counts = np.bincount(self.classes.ravel(), minlength=3) / self.classes.size
        return {name: float(counts[i]) for i, name in enumerate(CLASS_NAMES)}

    def with_classes(self, classes: np.ndarray, source: str | None = None) -> GridMap:
        """A copy with new classes and the same metadata and georeferencing."""
        return GridMap(classes, self.pixel_size, self.source if source is None else source, dict(self.meta),
                       transform=self.transform, crs=self.crs, elevation=self.elevation)

    def with_layer(self, name: str, array: np.ndarray, source: str | None = None) -> GridMap:
        """A new map with layer ``name`` set to ``array`` and everything else kept.

        ``name`` must be one of :data:`LAYERS` and ``array`` must have the map's shape;
        a ``classes`` layer must hold integer class codes (stored as uint8).
        """
        check_layers([name])
        a = np.asarray(array)
        if a.shape != self.shape:
            raise FedmapError(f"layer {name!r} has shape {_shape(a.shape)}, but the map is {_shape(self.shape)}")
        if name == "elevation":
            out = self.with_classes(self.classes, source)
            out.elevation = check_elevation(a, self.shape)
            return out
        return self.with_classes(check_classes(a, f"layer {name!r}"), source)


def _shape(shape: tuple[int, ...]) -> str:
    return "x".join(str(n) for n in shape) or "()"


def check_classes(classes: np.ndarray, what: str = "class map") -> np.ndarray:
    """``classes`` as a ``(H, W)`` uint8 class map; a one-line error names ``what`` when it
    is not a non-empty 2-D array of integer classes FREE, IMPASSABLE or UNKNOWN."""
    a = np.asarray(classes)
    if a.ndim != 2 or a.size == 0:
        raise FedmapError(f"{what} must be a non-empty 2-D class map, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.integer):
        raise FedmapError(f"{what} must hold integer classes, got {a.dtype}")
    if a.min() < 0 or a.max() > UNKNOWN:
        raise FedmapError(f"{what} must hold classes 0, 1, 2 (free, impassable, unknown), got {a.min()}..{a.max()}")
    return a.astype(np.uint8, copy=False)


def check_layers(names) -> tuple[str, ...]:
    """``names`` as a tuple of layer names; a one-line error (with a suggestion) for one that
    is not in :data:`LAYERS`."""
    names = tuple(names)
    for name in names:
        if name not in LAYERS:
            raise FedmapError(f"unknown map layer {name!r}{suggest(name, LAYERS)}")
    return names


def check_elevation(elevation: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``elevation`` as a float32 layer of ``shape`` (metres, NaN = unknown); a one-line
    error when it has another shape, is not real, or holds infinite heights."""
    a = np.asarray(elevation)
    if a.shape != shape:
        raise FedmapError(f"layer 'elevation' has shape {_shape(a.shape)}, but the map is {_shape(shape)}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise FedmapError(f"layer 'elevation' must hold heights in metres, got {a.dtype}")
    a = a.astype(np.float32, copy=False)
    if np.isinf(a).any():
        raise FedmapError("layer 'elevation' holds infinite heights (unknown cells must be NaN)")
    return a


def render_classes(classes: np.ndarray) -> np.ndarray:
    """Class array (H, W) -> RGB (H, W, 3) float32 in the paper's colours."""
    return PALETTE[np.asarray(classes, dtype=np.intp)]


def classes_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """Nearest palette colour for each pixel: (H, W, 3) in [0, 1] -> (H, W) uint8 classes.

    Ties (exactly equidistant colours) go to the lower class value.
    """
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise FedmapError(f"an RGB map must have shape (H, W, 3), got {rgb.shape}")
    d2 = ((rgb[:, :, None, :] - PALETTE[None, None, :, :]) ** 2).sum(axis=-1)  # (H, W, 3)
    return np.argmin(d2, axis=-1).astype(np.uint8)


def check_same_frame(maps: list[GridMap]) -> tuple[int, int]:
    """All maps must share one global grid; returns its shape."""
    if not maps:
        raise FedmapError("no maps given")
    shape = maps[0].shape
    for i, m in enumerate(maps[1:], start=1):
        if m.shape != shape:
            raise FedmapError(f"map {i} has grid {m.shape[0]}x{m.shape[1]}, but map 0 has {shape[0]}x{shape[1]}: "
                              "all agents must share one global grid")
    return shape
