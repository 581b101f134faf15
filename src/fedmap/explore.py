"""Agents' exploration: which part of the global frame each agent observes.

Every local map lives in the **global frame** (same grid as the ground truth): observed
cells keep their true class, everything else is UNKNOWN.

Modes
-----
``quadrants``  4 agents, one image quadrant each (the paper's setup).
``strips``     N vertical strips of (nearly) equal width.
``grid``       N agents on a near-square tiling (rows x cols blocks, row-major).
``traverse``   each agent drives a path through free space inside its own block of the
               ``grid`` tiling, through seeded random waypoints planned with A*, and
               observes every cell within ``sensor_radius`` cells of its path.

``overlap`` (cells) widens each block of the partition modes on every side, so
neighbouring agents see a shared margin.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fedmap._schema import setting
from fedmap.errors import FedmapError
from fedmap.maps.grid import LAYER_SPECS, LAYERS, UNKNOWN, GridMap, check_layers
from fedmap.maps.planning import astar, passable_mask
from fedmap.maps.sources import needs_dem

EXPLORE_MODES = ("quadrants", "strips", "grid", "traverse")


@dataclass(frozen=True)
class ExploreConfig:
    """Who observes what in a one-shot run: the ``[explore]`` section of a run config."""

    agents: int = setting(4, help="Number of rovers")
    mode: str = setting("quadrants", help="Exploration", choices=EXPLORE_MODES, cli="--explore")
    overlap: int = setting(0, help="Cells of overlap between neighbouring rovers' blocks")
    sensor_radius: float = setting(12.0, help="traverse: cells a rover observes around its path")
    layers: tuple[str, ...] = setting(("classes",), help="Map layers the rovers observe and share, comma-separated: "
                                      "classes, or classes,elevation (the heights, federated as a height grid)",
                                      choices=LAYERS)

    def __post_init__(self) -> None:
        # classes are always observed; "elevation" adds the heights
        object.__setattr__(self, "layers", check_layers(self.layers))
        if isinstance(self.agents, bool) or not isinstance(self.agents, int) or self.agents < 1:
            raise FedmapError(f"agents must be an integer >= 1, got {self.agents!r}")
        if self.mode not in EXPLORE_MODES:
            raise FedmapError(f"unknown exploration mode {self.mode!r}; choose one of {', '.join(EXPLORE_MODES)}")
        if self.overlap < 0 or not self.sensor_radius > 0:
            raise FedmapError(f"overlap must be >= 0 and sensor_radius positive, got {self.overlap}, {self.sensor_radius}")

    def local_maps(self, truth: GridMap, *, seed: int) -> list[GridMap]:
        """One local map per rover (:func:`explore`) with these settings; each other layer
        of ``layers`` carries the truth's values of the cells the rover observed and the
        layer's unknown value elsewhere (an elevation layer: the heights, NaN elsewhere)."""
        maps = explore(truth, self.agents, self.mode, seed=seed, overlap=self.overlap, sensor_radius=self.sensor_radius)
        if "elevation" in self.layers and "elevation" not in truth.layers:
            raise needs_dem("an elevation layer")
        for name in self.layers:
            if name != "classes":
                unknown = LAYER_SPECS[name].unknown
                maps = [m.with_layer(name, np.where(m.known, truth.layer(name), unknown)) for m in maps]
        return maps


def _grid_shape(n: int) -> tuple[int, int]:
    rows = int(math.floor(math.sqrt(n)))
    while n % rows:
        rows -= 1
    return rows, n // rows


def region_masks(shape: tuple[int, int], n_agents: int, mode: str = "quadrants", *, overlap: int = 0) -> list[np.ndarray]:
    """Boolean (H, W) mask of each agent's block for the partition modes."""
    h, w = shape
    if n_agents < 1:
        raise FedmapError(f"number of agents must be >= 1, got {n_agents}")
    if overlap < 0:
        raise FedmapError(f"overlap must be >= 0 cells, got {overlap}")
    if mode == "quadrants":
        if n_agents != 4:
            raise FedmapError(f"'quadrants' exploration needs exactly 4 agents, got {n_agents}; use 'strips' or 'grid'")
        rows, cols = 2, 2
    elif mode == "strips":
        rows, cols = 1, n_agents
    elif mode in ("grid", "traverse"):
        rows, cols = _grid_shape(n_agents)
    else:
        raise FedmapError(f"unknown exploration mode {mode!r}; choose one of {', '.join(EXPLORE_MODES)}")
    if rows > h or cols > w:
        raise FedmapError(f"cannot split a {h}x{w} map among {n_agents} agents")
    rb = np.linspace(0, h, rows + 1).round().astype(int)
    cb = np.linspace(0, w, cols + 1).round().astype(int)
    masks = []
    for i in range(rows):
        for j in range(cols):
            m = np.zeros(shape, dtype=bool)
            m[max(rb[i] - overlap, 0) : rb[i + 1] + overlap, max(cb[j] - overlap, 0) : cb[j + 1] + overlap] = True
            masks.append(m)
    return masks


def traverse_mask(
    truth: GridMap, region: np.ndarray, *, sensor_radius: float, waypoints: int, rng: np.random.Generator
) -> np.ndarray:
    """Cells seen by a rover driving through ``waypoints`` random free cells of ``region``."""
    passable = passable_mask(truth.classes)
    labels, _ = ndimage.label(passable)
    cand = np.argwhere(passable & region)
    if len(cand) == 0:
        raise FedmapError("an agent's region holds no free cell to drive on")
    # Drive inside the largest free component touching the region so waypoints connect.
    comp_sizes = np.bincount(labels[passable & region])
    comp_sizes[0] = 0
    comp = int(np.argmax(comp_sizes))
    cand = np.argwhere((labels == comp) & region)
    route = np.zeros(truth.shape, dtype=bool)
    r, c = cand[rng.integers(len(cand))]
    pos = (int(r), int(c))
    route[pos] = True
    for _ in range(waypoints):
        r, c = cand[rng.integers(len(cand))]
        nxt = (int(r), int(c))
        path = astar(passable, pos, nxt)
        if path:
            rr, cc = zip(*path)
            route[list(rr), list(cc)] = True
            pos = nxt
    dist = ndimage.distance_transform_edt(~route)
    return dist <= sensor_radius


def _per_agent(value, n: int, name: str) -> list:
    if np.ndim(value) == 0:
        return [value] * n
    values = list(value)
    if len(values) != n:
        raise FedmapError(f"{name} needs one value or one per agent ({n}), got {len(values)}")
    return values


def explore(
    truth: GridMap,
    n_agents: int = 4,
    mode: str = "quadrants",
    *,
    seed: int = 0,
    overlap: int = 0,
    sensor_radius: float | Sequence[float] = 12.0,
    waypoints: int | Sequence[int] = 6,
) -> list[GridMap]:
    """One local map per agent, in the global frame.

    ``sensor_radius`` and ``waypoints`` (traverse mode) may be one value for all agents
    or one per agent, for heterogeneous teams (different sensors, different amounts of
    driving).
    """
    if mode not in EXPLORE_MODES:
        raise FedmapError(f"unknown exploration mode {mode!r}; choose one of {', '.join(EXPLORE_MODES)}")
    regions = region_masks(truth.shape, n_agents, mode, overlap=overlap)
    if mode == "traverse":
        radii = _per_agent(sensor_radius, n_agents, "sensor_radius")
        wps = _per_agent(waypoints, n_agents, "waypoints")
        if min(radii) <= 0 or min(wps) < 0:
            raise FedmapError(f"sensor radius must be positive and waypoints >= 0, got {radii} and {wps}")
        rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n_agents)]
        seen = [traverse_mask(truth, reg, sensor_radius=r, waypoints=int(w), rng=g)
                for reg, r, w, g in zip(regions, radii, wps, rngs)]
    else:
        seen = regions
    local = []
    for k, mask in enumerate(seen):
        classes = np.where(mask, truth.classes, UNKNOWN).astype(np.uint8)
        m = GridMap(classes, truth.pixel_size, f"agent{k}:{mode}", {"agent": k, "mode": mode},
                    transform=truth.transform, crs=truth.crs)  # in the global frame: the truth's place
        if m.n_known == 0:
            raise FedmapError(f"agent {k} observed nothing (its region is all nodata)")
        local.append(m)
    return local
