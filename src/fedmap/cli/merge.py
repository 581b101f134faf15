"""``fedmap merge``: class maps in frames of their own, put together in the first map's
frame by registration with a confidence gate (:mod:`fedmap.maps.registration`).

The library does the work; this module reads the maps, prints each map's transform and
confidence, lists what was refused and writes the merged map.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from fedmap.cli.ui import console, fit, fmt
from fedmap.errors import FedmapError
from fedmap.maps.io import MAP_SUFFIXES, load_map, save_map
from fedmap.maps.registration import DEFAULT_GATE, DEFAULT_MARGIN, DEFAULT_MIN_OVERLAP, MergeResult
from fedmap.maps.registration import merge as merge_maps


def _table(result: MergeResult, names: list[str]) -> Table:
    t = Table(title=f"maps placed in the frame of {names[0]}", header_style="bold")
    for col in ("map", "placed", "dx", "dy", "heading", "confidence", "shared cells", "margin", "patches"):
        t.add_column(col, justify="left" if col in ("map", "placed") else "right", no_wrap=True)
    for p, name in zip(result.placements, names):
        reg, tr = p.registration, p.transform
        if reg is None:  # the first map: the frame itself
            t.add_row(name, "frame", "0.0", "0.0", "0.0", "-", "-", "-", "-")
            continue
        assert tr is not None
        t.add_row(name, "yes" if p.placed else "refused", f"{tr.dx:+.1f}", f"{tr.dy:+.1f}", f"{tr.heading_deg:.1f}",
                  fmt(reg.confidence), f"{reg.check.overlap:,}", f"{reg.margin:.1f}", f"{reg.patches:.0f}")
    return fit(t)


def _load(path: Path, pixel_size: float | None):
    """A map with its stored cell size; ``--pixel-size`` only for a map that stores none (a
    stored size it contradicts is a one-line error, not silently replaced)."""
    grid = load_map(path)
    if pixel_size is None:
        return grid
    if grid.meta.get("pixel_size_from", "default") not in ("file", "crs"):  # none stored, or only guessed
        return load_map(path, pixel_size=pixel_size)
    if not math.isclose(grid.pixel_size, pixel_size, rel_tol=1e-9):
        raise FedmapError(f"{path} stores {grid.pixel_size:g} m cells but --pixel-size says {pixel_size:g}; "
                          "--pixel-size is for maps that store no cell size (.npy)")
    return grid


def merge(
    maps: list[Path] = typer.Argument(..., metavar="MAP...", help="Two or more class maps (.png, .npy, .tif, ROS .yaml "
                                      "or a ROS 2 bag) of one cell size; the first one's frame is the merged map's."),
    out: Path = typer.Option(..., "--out", "-o", help=f"The merged map; its suffix picks the format ({', '.join(MAP_SUFFIXES)})."),
    gate: float = typer.Option(DEFAULT_GATE, "--gate", help="Confidence (Cohen's kappa of the maps on the cells both know) a "
                               "map needs to be placed."),
    min_overlap: int = typer.Option(DEFAULT_MIN_OVERLAP, "--min-overlap", help="Known cells a map must share with the "
                                    "merged map to be placed."),
    min_margin: float = typer.Option(DEFAULT_MARGIN, "--min-margin", help="Evidence (kappa^2 x sqrt(shared cells)) by which a "
                                     "map's placement must beat any other placement found: refuses look-alike places."),
    pixel_size: Optional[float] = typer.Option(None, "--pixel-size", help="Metres per cell, for maps that do not store it (.npy)."),
) -> None:
    """Merge maps that share no frame: each map is registered (heading and shift) to the merged map so far, and placed
    only when the confidence gate passes; where two maps disagree on a cell, impassable wins.

    Prints each map's transform into the first map's frame (dx along the columns, dy down the rows, in cells; the
    heading counter-clockwise as the map is drawn) with its confidence and the independent patches of terrain the
    maps share (fewer than 10: a note), and one line per refused map. Exits 0 when at
    least one map was placed on the first (the refusals listed), and non-zero, writing nothing, when none was.
    """
    if len(maps) < 2:
        raise FedmapError(f"merging needs at least two maps, got {len(maps)}")
    if out.suffix.lower() not in MAP_SUFFIXES:
        raise FedmapError(f"cannot tell the format of {out}: use one of {', '.join(MAP_SUFFIXES)}")
    for m in maps:
        if m.exists() and out.exists() and out.resolve() == m.resolve():
            raise FedmapError(f"the merged map would overwrite its input {m}; choose another -o")
    grids = [_load(m, pixel_size) for m in maps]
    result = merge_maps(grids, gate=gate, min_overlap=min_overlap, min_margin=min_margin)
    names = [str(m) for m in maps]
    console.print(_table(result, names))
    for p, name in zip(result.placements, names):
        if not p.placed:
            console.print(f"refused {name}: {p.reason}", soft_wrap=True)
            continue
        if p.changed:  # what the maps placed before held, overruled (impassable wins)
            console.print(f"note: {name} changed {p.changed:,} known cell(s) of the maps placed before it (where they "
                          "disagree, impassable wins)", soft_wrap=True)
        if p.registration is not None and p.registration.weak:  # smooth maps: few independent patches shared
            reg = p.registration
            console.print(f"note: {name} was placed on about {reg.patches:.0f} independent patches of terrain "
                          f"({reg.check.overlap:,} shared cells of smooth maps, confidence {reg.confidence:.2f}): a "
                          "look-alike place can fit such maps almost as well, so check this placement (or raise "
                          "--gate)", soft_wrap=True)
    if result.n_placed < 2:
        raise FedmapError(f"no map could be placed on {names[0]}: nothing merged, {out} not written")
    save_map(result.grid, out)
    f = result.grid.fractions()
    console.print(f"{out}: {result.grid.shape[0]}x{result.grid.shape[1]} cells, {result.n_placed} of {len(maps)} maps; "
                  f"{f['free']:.1%} free, {f['impassable']:.1%} impassable, {f['unknown']:.1%} unknown", soft_wrap=True)
