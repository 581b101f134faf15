"""``fedmap bandwidth --layer elevation``: the rate-distortion of sharing an elevation layer.

For each terrain it codes the DEM (its known cells) with every way of sharing heights and
measures, on what the receiver decodes: bytes (exact, header included), bits per cell,
RMSE and max absolute error in metres, and the strict path F1 of the classes re-derived
from the decoded heights under the terrain's thresholds, against the classes of the true
heights.

* ``lossless`` float32 (exact) and at ``q`` = 1 cm; LERC at max errors of
  :data:`LERC_ERRORS` times the heights' std; JPEG XL at :data:`JXL_DISTANCES`; JPEG 2000
  at :data:`J2K_PSNR` dB (:mod:`fedmap.federation.heights`).
* ``neural``: the paper's Fourier network with one output (:mod:`fedmap.nets.heightfield`)
  at :data:`NEURAL_SIZES`, int8 weights (quantisation-aware) and zstd, its whole payload
  counted; and ``neural+residual``: the middle size with a residual that enforces each
  LERC max error (:func:`~fedmap.federation.heights.residual_encode`).

Three figures summarise a terrain:

* the question a planner asks, *how many bytes before the heights are good enough to plan
  on*: per codec family, the fewest bytes of a measured point whose re-derived classes
  reach path F1 >= :data:`F1_TARGET` (:func:`bytes_to_f1`; the smallest *measured* point,
  not an interpolation: F1 is not monotone in bytes, so the true threshold lies between
  that point and the family's next smaller one, also reported), and the family that
  needs the fewest;
* at a matched RMSE, the neural payload's bytes over JPEG XL's (JPEG XL's bytes
  interpolated log-log between its points at the neural RMSE);
* at a matched max error, neural+residual's bytes over LERC's (with both points' path F1,
  which says whether that error is one a planner can use).

The classes are re-derived with the terrain's thresholds; a slope limit given as a
percentile is resolved once, on the true heights' slopes, and those degrees classify every
decoded map (the percentile of a decoded map's own slopes would be another limit).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fedmap.errors import FedmapError
from fedmap.evaluation.paths import path_f1
from fedmap.federation.heights import HeightCodec, residual_apply, residual_encode
from fedmap.maps.dem import Dem
from fedmap.maps.sources import TerrainSource, load_source_dem
from fedmap.maps.traversability import TraversabilityThresholds, dem_to_traversability, resolved_slope
from fedmap.mission.results import F1_GOAL
from fedmap.nets.heightfield import HeightNetConfig, encode_heightnet, fit_heights, render_fit

#: LERC max errors, as multiples of the heights' standard deviation.
LERC_ERRORS: tuple[float, ...] = (0.003, 0.01, 0.03, 0.1)
JXL_DISTANCES: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
J2K_PSNR: tuple[float, ...] = (45.0, 55.0, 65.0, 75.0)
#: The neural payloads: (Fourier frequencies, hidden units); the middle one gets residuals.
NEURAL_SIZES: tuple[tuple[int, int], ...] = ((16, 16), (32, 32), (48, 48))
#: Codec families, in the order tables list them.
FAMILIES: tuple[str, ...] = ("lossless", "lerc", "jxl", "j2k", "neural", "neural+residual")
#: Path F1 of the re-derived classes at which heights are "good enough to plan on": the
#: missions' plannable-map goal (:data:`fedmap.mission.results.F1_GOAL`), one number for both.
F1_TARGET = F1_GOAL
#: Map side of every terrain unless the caller sets one.
DEFAULT_SIZE = 128
#: The six terrains of the benchmark: three built in, three from ``shared/data`` (path relative to it).
TERRAINS: dict[str, dict] = {
    "mars": {"kind": "builtin", "terrain": "mars", "size": 128},
    "moon": {"kind": "builtin", "terrain": "moon", "size": 128},
    "ice": {"kind": "builtin", "terrain": "ice", "size": 128},
    "gale": {"kind": "dem", "path": "mars/missionDEM_gale_1m.tif", "crop": 256, "size": 128},
    "hadley": {"kind": "tiles", "path": "moon/gld100_256p", "lon": 0, "lat": 22, "tiles": 8, "size": 128,
               "options": {"pixel_size": 118.45}},
    "columbia": {"kind": "dem", "path": "ice/test-files_columbia_dem_Columbia.tif", "size": 128},
}


@dataclass(frozen=True)
class Point:
    """One coded layer: what it is, its exact bytes, and what the receiver's heights score."""

    terrain: str
    codec: str  #: lossless, lerc, jxl, j2k, neural, neural+residual
    setting: str  #: its parameter, readable
    bytes: int
    bits_per_cell: float  #: per known cell
    rmse_m: float
    max_error_m: float
    path_f1: float  #: strict path F1 of the classes re-derived from the decoded heights

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def terrain_sources(data_dir: str | None, names: Sequence[str] | None = None, *, size: int | None = None,
                    thresholds: TraversabilityThresholds | None = None) -> dict[str, TerrainSource]:
    """The benchmark's terrains (``names`` of :data:`TERRAINS`; the real ones need ``data_dir``),
    each resampled to ``size`` cells (default: :data:`TERRAINS`' 128) and classified with
    ``thresholds`` (default: the generic rover's)."""
    out = {}
    for name in names or TERRAINS:
        spec = dict(TERRAINS[name])
        if spec["kind"] != "builtin":
            if data_dir is None:
                continue
            spec["path"] = f"{data_dir}/{spec['path']}"
        if size is not None:
            spec["size"] = size
        if thresholds is not None:
            spec["thresholds"] = thresholds
        out[name] = TerrainSource.from_dict(spec, where=f"terrain {name}")
    return out


def dem_source(path: str | Path, *, size: int | None = DEFAULT_SIZE, pixel_size: float | None = None,
               thresholds: TraversabilityThresholds | None = None) -> dict[str, TerrainSource]:
    """A user's DEM file as the only terrain, named after the file: its centred square,
    resampled to ``size`` cells (None: kept at its resolution), read like every ``dem``
    source (:func:`~fedmap.maps.sources.load_source_dem`). A missing path is a one-line error
    here, before any work."""
    p = Path(path)
    if not p.is_file():
        raise FedmapError(f"--dem {path}: {'not a file' if p.exists() else 'no such file'}")
    src = TerrainSource(kind="dem", path=str(p.resolve()), size=size,
                        options={} if pixel_size is None else {"pixel_size": pixel_size},
                        thresholds=thresholds or TraversabilityThresholds())
    return {p.stem: src}


def _score(name: str, dem: Dem, truth_classes: np.ndarray, thresholds: TraversabilityThresholds,
           decoded: np.ndarray, codec: str, setting: str, n_bytes: int, pairs: int, seed: int) -> Point:
    z = dem.elevation.astype(np.float64)
    known = np.isfinite(z)
    err = np.abs(decoded[known] - z[known])
    derived = dem_to_traversability(Dem(decoded.astype(np.float32), dem.pixel_size), thresholds).classes
    f1 = path_f1(truth_classes, derived, n_pairs=pairs, seed=seed).f1
    return Point(name, codec, setting, n_bytes, 8 * n_bytes / int(known.sum()), float(np.sqrt(np.mean(err**2))),
                 float(err.max()), float(f1))


def terrain_rd(name: str, dem: Dem, *, thresholds: TraversabilityThresholds | None = None, pairs: int = 40,
               seed: int = 0, neural_steps: int = 1500,
               on_point: Callable[[str], None] | None = None) -> list[Point]:
    """Every codec's points on one terrain (see the module docstring); classes under
    ``thresholds`` (default: the generic rover's), a percentile slope limit resolved on ``dem``."""
    z = dem.elevation.astype(np.float64)
    known = np.isfinite(z)
    std = float(z[known].std()) or 1.0
    truth_map = dem_to_traversability(dem, thresholds)
    truth = truth_map.classes
    t_deg = resolved_slope(thresholds or TraversabilityThresholds(), truth_map)
    points = []

    def score(decoded: np.ndarray, family: str, setting: str, n_bytes: int) -> Point:
        return _score(name, dem, truth, t_deg, decoded, family, setting, n_bytes, pairs, seed)

    def coded(codec: HeightCodec, family: str, setting: str) -> None:
        payload = codec.encode(z)
        points.append(score(HeightCodec.decode(payload), family, setting, len(payload)))
        if on_point is not None:
            on_point(f"{name}: {codec.label}")

    coded(HeightCodec("lossless", 0), "lossless", "float32")
    coded(HeightCodec("lossless", 0.01), "lossless", "q 0.01 m")
    errors = [round_sig(f * std) for f in LERC_ERRORS]
    for e in errors:
        coded(HeightCodec("lerc", e), "lerc", f"max err {e:g} m")
    for d in JXL_DISTANCES:
        coded(HeightCodec("jxl", d), "jxl", f"distance {d:g}")
    for p in J2K_PSNR:
        coded(HeightCodec("j2k", p), "j2k", f"{p:g} dB")
    for i, (mapping, hidden) in enumerate(NEURAL_SIZES):
        fit = fit_heights(z, HeightNetConfig(mapping=mapping, hidden=hidden), steps=neural_steps, seed=seed)
        payload = encode_heightnet(fit)
        pred = render_fit(fit)
        points.append(score(np.where(known, pred, np.nan), "neural", f"{mapping} freq, {hidden} units", len(payload)))
        if on_point is not None:
            on_point(f"{name}: neural {mapping}x{hidden}")
        if i == len(NEURAL_SIZES) // 2:
            for e in errors:
                res = residual_encode(z, pred, e)
                fixed = residual_apply(pred, res, e)
                points.append(score(np.where(known, fixed, np.nan), "neural+residual",
                                    f"{mapping}x{hidden}, max err {e:g} m", len(payload) + len(res)))
    return points


def round_sig(x: float, digits: int = 2) -> float:
    """``x`` to ``digits`` significant digits (readable max errors)."""
    return float(f"{x:.{digits}g}") if x > 0 else x


def _interp_loglog(x: float, xs: np.ndarray, ys: np.ndarray) -> float | None:
    """y at x on the log-log polyline through (xs, ys), or None outside its range."""
    order = np.argsort(xs)
    xs, ys = np.log(xs[order]), np.log(ys[order])
    lx = math.log(x)
    if not xs[0] <= lx <= xs[-1]:
        return None
    return float(math.exp(np.interp(lx, xs, ys)))


@dataclass(frozen=True)
class Reach:
    """Where one codec family first gives heights good enough to plan on."""

    codec: str
    bytes: int  #: the fewest bytes of a measured point with path F1 >= the target
    setting: str  #: that point's setting
    path_f1: float  #: that point's path F1
    below: int | None  #: bytes of the family's next smaller point (which misses), if any

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def bytes_to_f1(points: Sequence[Point], *, target: float = F1_TARGET) -> dict[str, Reach | None]:
    """Per codec family of ``points`` (one terrain's), the smallest measured point whose
    re-derived classes reach path F1 >= ``target``; None when no point of the family does.

    It is a measured point, not a log-log interpolation: path F1 is not monotone in bytes
    (a tighter setting can flip a cell on a path a looser one left alone), so a
    curve between two points would claim a rate no codec setting gave. The threshold lies
    between ``below`` (the family's largest point under it, which misses) and ``bytes``.
    """
    out: dict[str, Reach | None] = {}
    for family in dict.fromkeys(p.codec for p in points):
        mine = sorted((p for p in points if p.codec == family), key=lambda p: p.bytes)
        hit = next((p for p in mine if p.path_f1 >= target), None)
        if hit is None:
            out[family] = None
            continue
        smaller = [p.bytes for p in mine if p.bytes < hit.bytes]
        out[family] = Reach(family, hit.bytes, hit.setting, hit.path_f1, smaller[-1] if smaller else None)
    return out


def winner(reach: dict[str, Reach | None]) -> str | None:
    """The family that reaches the F1 target in the fewest bytes (None: no family does)."""
    hits = [r for r in reach.values() if r is not None]
    return min(hits, key=lambda r: r.bytes).codec if hits else None


def summarise(points: list[Point], *, target: float = F1_TARGET) -> dict:
    """Per terrain: the fewest bytes to path F1 >= ``target`` per family and the family that
    needs the fewest (:func:`bytes_to_f1`); neural / JPEG XL bytes at matched RMSE (each
    neural point, and the best); and neural+residual / LERC bytes at each max error (and
    the best), with both points' path F1."""
    out: dict = {}
    for name in dict.fromkeys(p.terrain for p in points):
        mine = [p for p in points if p.terrain == name]
        jxl = [p for p in mine if p.codec == "jxl" and p.rmse_m > 0]
        xs = np.array([p.rmse_m for p in jxl])
        ys = np.array([p.bytes for p in jxl], dtype=np.float64)
        vs_jxl: list[dict[str, Any]] = []
        for p in (q for q in mine if q.codec == "neural"):
            ref = _interp_loglog(p.rmse_m, xs, ys)
            vs_jxl.append({"setting": p.setting, "rmse_m": p.rmse_m, "bytes": p.bytes, "jxl_bytes": ref,
                           "ratio": None if ref is None else p.bytes / ref})
        lerc = {p.setting.removeprefix("max err "): p for p in mine if p.codec == "lerc"}
        vs_lerc: list[dict[str, Any]] = []
        for p in (q for q in mine if q.codec == "neural+residual"):
            e = p.setting.split("max err ")[1]
            vs_lerc.append({"max_error": e, "bytes": p.bytes, "lerc_bytes": lerc[e].bytes,
                            "ratio": p.bytes / lerc[e].bytes, "path_f1": p.path_f1, "lerc_path_f1": lerc[e].path_f1})
        ratios: list[float] = [v["ratio"] for v in vs_jxl if v["ratio"] is not None]
        lerc_ratios: list[float] = [v["ratio"] for v in vs_lerc]
        reach = bytes_to_f1(mine, target=target)
        out[name] = {"f1_target": target,
                     "bytes_to_f1": {k: None if r is None else r.to_dict() for k, r in reach.items()},
                     "winner_at_f1": winner(reach),
                     "neural_vs_jxl": vs_jxl, "best_neural_vs_jxl": min(ratios) if ratios else None,
                     "neural_residual_vs_lerc": vs_lerc,
                     "best_neural_residual_vs_lerc": min(lerc_ratios) if lerc_ratios else None}
    return out


def elevation_rd(sources: dict[str, TerrainSource], *, pairs: int = 40, seed: int = 0, neural_steps: int = 1500,
                 on_point: Callable[[str], None] | None = None) -> dict:
    """The rate-distortion points and summary of every terrain in ``sources``."""
    t0 = time.perf_counter()
    points: list[Point] = []
    for name, src in sources.items():
        points += terrain_rd(name, load_source_dem(src, seed=seed), thresholds=src.thresholds, pairs=pairs,
                             seed=seed, neural_steps=neural_steps, on_point=on_point)
    return {"points": [p.to_dict() for p in points], "summary": summarise(points),
            "seconds": time.perf_counter() - t0}


_STYLE = {"lossless": ("black", "*"), "lerc": ("tab:blue", "o"), "jxl": ("tab:orange", "s"),
          "j2k": ("tab:green", "^"), "neural": ("tab:red", "D"), "neural+residual": ("tab:purple", "v")}


def plot_rd(report: dict) -> bytes:
    """Bits per cell against RMSE (top row) and against max error (bottom), one column per
    terrain, log-log, every codec."""
    import io

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = report["points"]
    names = list(dict.fromkeys(p["terrain"] for p in points))
    fig, axes = plt.subplots(2, len(names), figsize=(3.2 * len(names), 6.4), squeeze=False)
    for j, name in enumerate(names):
        for i, metric in enumerate(("rmse_m", "max_error_m")):
            ax = axes[i][j]
            for codec, (colour, marker) in _STYLE.items():
                pts = sorted((p for p in points if p["terrain"] == name and p["codec"] == codec and p[metric] > 0),
                             key=lambda p: p[metric])
                if pts:
                    ax.plot([p[metric] for p in pts], [p["bits_per_cell"] for p in pts], marker=marker, color=colour,
                            label=codec, lw=1, ms=4)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            if i == 0:
                ax.set_title(name)
            ax.set_xlabel("RMSE, m" if i == 0 else "max abs error, m")
            if j == 0:
                ax.set_ylabel("bits per cell")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _f(v, nd: int = 2) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def reach_cell(r: dict | None) -> str:
    """A ``bytes_to_f1`` entry for a table: its bytes (``4,353``), or ``not reached``."""
    return "not reached" if r is None else f"{r['bytes']:,}"


def reach_rows(report: dict) -> list[list[str]]:
    """The "fewest bytes to path F1 >= target" table, one row per terrain: the terrain, a
    cell per family of :data:`FAMILIES` (``-`` when the family has no point there), and the
    winning family."""
    rows = []
    for name, sm in report["summary"].items():
        reach = sm["bytes_to_f1"]
        rows.append([name, *("-" if f not in reach else reach_cell(reach[f]) for f in FAMILIES),
                     sm["winner_at_f1"] or "none"])
    return rows


def elevation_markdown(report: dict) -> str:
    """``report.md``: bytes to plannable heights per terrain, the neural ratios, then every point."""
    first: dict = next(iter(report["summary"].values()), {})
    target = first.get("f1_target", F1_TARGET)
    lines = ["# Sharing an elevation layer: rate and distortion", "",
             "Bytes are exact payloads, headers included. RMSE and max error are in metres on the known cells; "
             "*path F1* scores the classes re-derived from the decoded heights against the true heights' classes "
             "(strict A*, seeded pairs).", "",
             f"## Bytes before the heights are good enough to plan on (path F1 >= {target:g})", "",
             f"Per codec, the smallest *measured* point whose re-derived classes reach path F1 >= {target:g} (not "
             "an interpolation: F1 is not monotone in bytes); *not reached* when no point of the codec does. "
             "*wins*: the codec that needs the fewest bytes.", "",
             "| terrain | " + " | ".join(FAMILIES) + " | wins |", "|---|" + "---:|" * len(FAMILIES) + "---|"]
    lines += ["| " + " | ".join(row) + " |" for row in reach_rows(report)]
    lines += ["", "## Neural against the standard codecs", "",
              "Ratios below 1 mean the neural payload is smaller at the same error. *path F1 at the best*: the "
              "path F1 of the neural+residual point with the best ratio, i.e. whether a planner could use it.", "",
              "| terrain | best neural / JPEG XL bytes, matched RMSE | best neural+residual / LERC bytes, matched max "
              "error | path F1 at the best |", "|---|---:|---:|---:|"]
    for name, sm in report["summary"].items():
        vs = sm.get("neural_residual_vs_lerc") or []
        best = min(vs, key=lambda v: v["ratio"]) if vs else None
        lines.append(f"| {name} | {_f(sm['best_neural_vs_jxl'])} | {_f(sm['best_neural_residual_vs_lerc'])} | "
                     f"{_f(None if best is None else best.get('path_f1'))} |")
    lines += ["", "## Every point", "", "| terrain | codec | setting | bytes | bits/cell | RMSE m | max err m | path F1 |",
              "|---|---|---|---:|---:|---:|---:|---:|"]
    for p in report["points"]:
        lines.append(f"| {p['terrain']} | {p['codec']} | {p['setting']} | {p['bytes']:,} | {p['bits_per_cell']:.3f} | "
                     f"{p['rmse_m']:.4g} | {p['max_error_m']:.4g} | {p['path_f1']:.2f} |")
    return "\n".join(lines) + "\n"
