"""Maps out of a mission: each strategy's final global map (and each rover's final belief)
as a :class:`~fedmap.maps.grid.GridMap` in the truth's frame, and as files other tools open.

:func:`mission_maps` gives the maps, :func:`write_mission_maps` writes them under
``<folder>/maps/`` as ``<strategy>_global`` and ``<strategy>_rover<k>`` (k from 0, team
order) in each format of :data:`~fedmap.maps.export.EXPORT_FORMATS` asked for (the GeoTIFF
carries the truth's CRS and transform, so it overlays the DEM the mission ran on), and
:func:`reexport_mission_maps` converts every map of such a folder to another format
(``fedmap export <mission folder> --format ...``).

The maps are the last step's: a run keeps its last frame whatever ``frames`` bounds the
animation to (the step loop of :mod:`fedmap.mission.sim` always records step ``steps``).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from fedmap._util import make_dir
from fedmap.errors import FedmapError
from fedmap.maps.export import EXPORT_FORMATS, check_formats, export_map, export_maps
from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.maps.io import load_map
from fedmap.mission.results import MissionResult

#: The folder of a mission's output folder that holds its maps.
MAPS_DIR = "maps"
#: The formats :func:`write_mission_maps` writes unless told otherwise.
DEFAULT_FORMATS: tuple[str, ...] = ("png", "geotiff", "ros")
#: A map's source when a maps folder holds it in several formats, best first: the GeoTIFF
#: (classes, CRS, transform, pixel size), then the PNG (fedmap's carries the same in text
#: chunks), the ROS YAML (origin and resolution, no CRS), the ``.npy`` (classes only).
SOURCE_SUFFIXES: tuple[str, ...] = (".tif", ".tiff", ".png", ".yaml", ".yml", ".npy")


def _on_truth(truth: GridMap, classes: np.ndarray, source: str, meta: dict) -> GridMap:
    """``classes`` as a map in the truth's frame (pixel size, transform, CRS; no other layer)."""
    if np.shape(classes) != truth.shape:
        raise FedmapError(f"{source} is {np.shape(classes)}, the mission's truth {truth.shape}")
    return GridMap(np.asarray(classes, dtype=np.uint8).copy(), truth.pixel_size, source, meta,
                   transform=truth.transform, crs=truth.crs)


def mission_maps(result: MissionResult, *, beliefs: bool = False) -> dict[str, GridMap]:
    """Each strategy's final global map, and with ``beliefs`` every rover's final belief.

    Parameters
    ----------
    result : MissionResult
        A mission's result (:func:`~fedmap.mission.sim.run_mission`).
    beliefs : bool
        Also every rover's belief at the last step (what it plans on).

    Returns
    -------
    dict of str to GridMap
        ``"<strategy>_global"`` (the base station's map; on peers the lander's, or the cells
        every rover agrees on) and ``"<strategy>_rover<k>"`` (k from 0, team order), in the
        order the strategies ran. Each carries the truth's pixel size, transform and CRS.

    Notes
    -----
    A global map that holds no cell (all UNKNOWN) is left out: there is nothing to open.
    That is always so for ``none``, whose base station receives nothing, and for a
    strategy whose link delivered nothing by the last step. Its rovers' beliefs are still
    given with ``beliefs=True`` (a rover always knows what it observed).
    """
    truth = result.truth
    out: dict[str, GridMap] = {}
    for name, run in result.runs.items():
        if not run.frames:
            raise FedmapError(f"strategy {name!r} recorded no frame: no final map to give")
        last = run.frames[-1]
        end = run.series.step[-1]  # the mission's last step, or the step the stop rule ended the run at
        if last.step != end:
            raise FedmapError(f"strategy {name!r}'s last frame is step {last.step}, not its run's last step {end}")
        meta = {"strategy": name, "step": last.step}
        if (np.asarray(last.global_map) != UNKNOWN).any():
            out[f"{name}_global"] = _on_truth(truth, last.global_map, f"mission {name}: global map, step {last.step}",
                                              {**meta, "map": "global"})
        if beliefs:
            for k, belief in enumerate(last.beliefs):
                out[f"{name}_rover{k}"] = _on_truth(truth, belief, f"mission {name}: rover {k}'s belief, step "
                                                    f"{last.step}", {**meta, "map": "belief", "rover": k})
    return out


def write_mission_maps(result: MissionResult, folder, *, beliefs: bool = False,
                       formats: Iterable[str] = DEFAULT_FORMATS) -> list[Path]:
    """Write :func:`mission_maps` as ``<folder>/maps/<name><suffix>`` in each format.

    ``png`` writes ``<name>.png`` (the paper's colours; a georeferenced map also gets a
    ``.png.aux.xml`` GDAL sidecar, not listed), ``geotiff`` ``<name>.tif`` (class codes,
    colour table, the truth's CRS and transform), ``ros`` ``<name>.yaml`` + ``<name>.pgm``
    (map_server), ``npy`` ``<name>.npy``. Each file is written atomically; an unknown
    format is a one-line error before anything is written. Returns the files written.
    """
    fmts = check_formats(formats)
    maps = mission_maps(result, beliefs=beliefs)
    if not fmts or not maps:
        return []
    target = make_dir(Path(folder) / MAPS_DIR)
    return export_maps(maps, target, fmts)


def mission_map_files(folder) -> dict[str, Path]:
    """The maps under ``<folder>/maps/``: name -> the file to read it from (one per name,
    the best of :data:`SOURCE_SUFFIXES`). A folder without maps is a one-line error."""
    folder = Path(folder)
    maps_dir = folder / MAPS_DIR
    if not maps_dir.is_dir():
        raise FedmapError(f"{folder} has no {MAPS_DIR}/ folder: give a map file, a ROS 2 bag, or a mission folder "
                          f"written with its maps")
    rank = {s: i for i, s in enumerate(SOURCE_SUFFIXES)}
    found: dict[str, Path] = {}
    for p in sorted(maps_dir.iterdir()):
        s = p.suffix.lower()
        if p.is_file() and s in rank and (p.stem not in found or rank[s] < rank[found[p.stem].suffix.lower()]):
            found[p.stem] = p
    if not found:
        raise FedmapError(f"{maps_dir} holds no map ({', '.join(SOURCE_SUFFIXES)})")
    return found


def reexport_mission_maps(folder, fmt: str, *, out=None,
                          pixel_size: float | None = None) -> list[tuple[GridMap, list[Path]]]:
    """Write every map of a mission folder (:func:`mission_map_files`) in format ``fmt``,
    into ``out`` (default: the folder's ``maps/``) as ``<name><suffix>``.

    Each map is read from its GeoTIFF where there is one, so the output keeps the CRS and
    transform. A map whose output would be its own source (``geotiff`` into ``maps/``) is a
    one-line error before anything is written. ``rosbag2`` writes every map into one bag,
    ``<out>/maps_bag``, a topic ``/<name>`` per map. Returns ``(map, files written)`` per map.
    """
    (fmt,) = check_formats([fmt])
    sources = mission_map_files(folder)
    out_dir = make_dir(Path(out) if out is not None else Path(folder) / MAPS_DIR)  # before anything is read
    if fmt == "rosbag2":
        maps = {name: load_map(src, pixel_size=pixel_size) for name, src in sources.items()}
        (bag,) = export_maps(maps, out_dir, [fmt])
        return [(grid, [bag]) for grid in maps.values()]
    targets = {name: out_dir / f"{name}{EXPORT_FORMATS[fmt]}" for name in sources}
    for name, src in sources.items():
        if targets[name].resolve() == src.resolve():
            raise FedmapError(f"exporting {src} as {fmt} would overwrite it; pass -o DIR")
    done = []
    for name, src in sources.items():
        grid = load_map(src, pixel_size=pixel_size)
        done.append((grid, export_map(grid, targets[name], fmt)))
    return done


__all__ = ["DEFAULT_FORMATS", "MAPS_DIR", "SOURCE_SUFFIXES", "mission_map_files", "mission_maps",
           "reexport_mission_maps", "write_mission_maps"]
