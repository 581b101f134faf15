"""Traversability grid maps in a shared global frame.

A :class:`GridMap` is an ``H x W`` array of classes (:data:`FREE`, :data:`IMPASSABLE`,
:data:`UNKNOWN`) plus metadata. Cells that are not UNKNOWN are *known*. For people and
as the network's target a map is rendered in the paper's colours (free = green,
impassable = red, unknown = grey 0.5); a network's RGB output goes back to classes by
nearest colour.

A map holds *named layers*, each declared once in :data:`LAYER_SPECS` (a
:class:`LayerSpec`: dtype, validation, the value of an unknown cell): the class array
``"classes"``, always, and optionally ``"elevation"`` (metres, NaN where unknown; see
:class:`GridMap`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np
from affine import Affine

from fedmap._util import suggest
from fedmap.errors import FedmapError

FREE: int = 0
IMPASSABLE: int = 1
UNKNOWN: int = 2
#: The largest map side a payload read from a link may claim (height payloads, a report's maps,
#: a height network's map): checked before anything of that size is allocated.
MAX_WIRE_SIDE = 8192
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


def check_heights(heights: np.ndarray, what: str = "layer 'elevation'") -> np.ndarray:
    """``heights`` as float32 metres (NaN = unknown); a one-line error names ``what`` when
    they are not real numbers or hold infinite heights."""
    a = np.asarray(heights)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise FedmapError(f"{what} must hold heights in metres, got {a.dtype}")
    a = a.astype(np.float32, copy=False)
    if np.isinf(a).any():
        raise FedmapError(f"{what} holds infinite heights (unknown cells must be NaN)")
    return a


@dataclass(frozen=True)
class LayerSpec:
    """What one layer of a :class:`GridMap` is: the one place a layer is declared.

    ``values(array, what)`` checks an array's values (a one-line :class:`FedmapError`
    naming ``what``, e.g. ``"layer 'elevation'"``) and returns it as ``dtype``; ``unknown``
    is the value of a cell nothing is known about (UNKNOWN for classes, NaN for heights).
    """

    name: str
    dtype: type[np.generic]
    unknown: float
    values: Callable[[np.ndarray, str], np.ndarray]

    def check(self, array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        """``array`` as this layer of a map of ``shape``; a one-line error when it has another
        shape or fails :attr:`values`."""
        a = np.asarray(array)
        if a.shape != tuple(shape):
            raise FedmapError(f"layer {self.name!r} has shape {_shape(a.shape)}, but the map is {_shape(shape)}")
        return self.values(a, f"layer {self.name!r}").astype(self.dtype, copy=False)


#: Every layer a :class:`GridMap` can hold, by name, canonical layer first: declaring a
#: layer here is all a map needs to hold, check and carry it.
LAYER_SPECS: dict[str, LayerSpec] = {spec.name: spec for spec in (
    LayerSpec("classes", np.uint8, UNKNOWN, check_classes),
    LayerSpec("elevation", np.float32, float("nan"), check_heights),
)}

#: Names of the layers a :class:`GridMap` can hold, canonical layer first.
LAYERS: tuple[str, ...] = tuple(LAYER_SPECS)


def check_layers(names: Iterable[str]) -> tuple[str, ...]:
    """``names`` as a tuple of layer names; a one-line error (with a suggestion) for one that
    is not in :data:`LAYER_SPECS`."""
    names = tuple(names)
    for name in names:
        if name not in LAYER_SPECS:
            raise FedmapError(f"unknown map layer {name!r}{suggest(name, tuple(LAYER_SPECS))}")
    return names


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
    layers : mapping, optional
        The map's other layers, name -> ``(H, W)`` array (e.g. ``{"elevation": z}``);
        each is checked against its :class:`LayerSpec` and stored as its dtype.

    Layers
    ------
    A map holds named ``(H, W)`` layers on one grid, all sharing ``pixel_size``,
    ``transform`` and ``crs``. Each name a map can hold is declared once, in
    :data:`LAYER_SPECS` (a :class:`LayerSpec`: dtype, checks, unknown value); a new layer
    needs no more than that entry here. ``"classes"`` (integer codes FREE, IMPASSABLE,
    UNKNOWN, stored as uint8) is always there, and the ``classes`` field stays its
    canonical accessor; the others, such as ``"elevation"`` (real heights in metres, NaN
    where unknown, never infinite, stored as float32), are optional and given as
    ``layers=``. After construction :attr:`layers` is a read-only mapping name -> array
    over every layer the map has, ``"classes"`` first and the rest in
    :data:`LAYER_SPECS` order, without copies (``grid.layers["classes"] is
    grid.classes``; ``grid.layers.get("elevation")`` is None on a map without heights).
    :meth:`layer` fetches one by name (a one-line :class:`FedmapError` names a missing
    layer and the available ones), :meth:`with_layer` returns a new map with one layer
    set, and :meth:`with_classes` carries every other layer along. An agent can derive
    its own classes from the elevation with its own rover profile
    (:func:`fedmap.maps.traversability.dem_to_traversability`).
    """

    classes: np.ndarray
    pixel_size: float = 1.0
    source: str = ""
    meta: dict = field(default_factory=dict)
    transform: Affine | None = None
    crs: str | None = None
    layers: Mapping[str, np.ndarray] = field(default_factory=dict)

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
        given = dict(self.layers)
        if "classes" in given:
            raise FedmapError("layers= holds a map's other layers; its classes are the first argument")
        check_layers(given)
        self.layers = _Layers({"classes": self.classes, **{
            name: spec.check(given[name], self.classes.shape) for name, spec in LAYER_SPECS.items() if name in given}})

    @property
    def shape(self) -> tuple[int, int]:
        return self.classes.shape

    def layer(self, name: str) -> np.ndarray:
        """The layer ``name``; a one-line error names it and the layers this map has."""
        if name not in self.layers:
            raise FedmapError(f"this map has no layer {name!r}; available layers: {', '.join(self.layers)}")
        return self.layers[name]

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
        """A copy with new classes, every other layer, and the same metadata and georeferencing."""
        return self._with({**self.layers, "classes": classes}, source)

    def with_layer(self, name: str, array: np.ndarray, source: str | None = None) -> GridMap:
        """A new map with layer ``name`` set to ``array`` and everything else kept.

        ``name`` must be one of :data:`LAYER_SPECS` and ``array`` must have the map's shape
        and pass the layer's checks (:meth:`LayerSpec.check`).
        """
        (name,) = check_layers([name])
        return self._with({**self.layers, name: LAYER_SPECS[name].check(array, self.shape)}, source)

    def _with(self, layers: Mapping[str, np.ndarray], source: str | None) -> GridMap:
        """A new map of ``layers`` (``"classes"`` among them) with this one's metadata."""
        others = {name: a for name, a in layers.items() if name != "classes"}
        return GridMap(layers["classes"], self.pixel_size, self.source if source is None else source,
                       dict(self.meta), transform=self.transform, crs=self.crs, layers=others)


class _Layers(Mapping[str, np.ndarray]):
    """A map's layers, name -> array, read-only (unlike a mappingproxy, it pickles)."""

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self._arrays = arrays

    def __getitem__(self, name: str) -> np.ndarray:
        return self._arrays[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._arrays)

    def __len__(self) -> int:
        return len(self._arrays)

    def __repr__(self) -> str:
        return f"layers({', '.join(self._arrays)})"


def beside_unknown(classes: np.ndarray) -> np.ndarray:
    """Cells with at least one UNKNOWN 4-neighbour (map edges are not unknown)."""
    unknown = np.asarray(classes) == UNKNOWN
    near = np.zeros_like(unknown)
    near[1:, :] |= unknown[:-1, :]
    near[:-1, :] |= unknown[1:, :]
    near[:, 1:] |= unknown[:, :-1]
    near[:, :-1] |= unknown[:, 1:]
    return near


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
