"""Seeded built-in terrain generators: synthetic DEMs for Mars, the Moon and glacier ice.

Each generator builds a digital elevation model (:class:`~fedmap.maps.dem.Dem`) at rover
scale whose traversability map (:func:`~fedmap.maps.traversability.dem_to_traversability`
with default thresholds) looks like its namesake:

* ``mars``: a smooth fractal plain with craters (raised rims, ejecta aprons, power-law
  sizes, fresh and degraded), clustered boulder fields and transverse dune fields with a
  dominant wind direction.
* ``moon``: crater-saturated regolith built epoch by epoch: each epoch adds a population
  of craters and is then smoothed by diffusion, so old craters are soft and small old
  ones are erased, as on real lunar terrain; sparse boulders lie around fresh craters.
* ``ice``: a gently sloping glacier with bands of transverse crevasse fields, chevron
  crevasses and serac blocks toward the margins, a lateral moraine beyond them, and
  medial moraines strewn with debris.

All lengths are in metres and all feature sizes are physical, so a larger map shows
more features rather than bigger ones, and a coarser ``pixel_size`` blurs away features
smaller than a pixel. Every random draw comes from one ``numpy.random.default_rng(seed)``
in a fixed order, so the same arguments always give a bit-identical DEM.

A last step (:func:`_calibrate_relief`) keeps the impassable fraction inside
``_TARGET_IMPASSABLE`` by a vertical exaggeration factor, needed mainly for small maps
where a few large features dominate and for non-default pixel sizes. The factor is
recorded as ``meta["relief_scale"]`` (1.0 for most maps at the default pixel size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import IMPASSABLE
from fedmap.maps.traversability import dem_to_traversability

TERRAIN_KINDS: tuple[str, ...] = ("mars", "moon", "ice")

#: Allowed map sizes in cells per side.
_MIN_SIZE: int = 64
_MAX_SIZE: int = 4096

#: Default ground size of one cell, metres: rover scale, so boulders and steps count.
_DEFAULT_PIXEL_SIZE: dict[str, float] = {"mars": 1.0, "moon": 1.0, "ice": 1.0}

#: Impassable fraction (default thresholds) the relief calibration keeps the map inside.
_TARGET_IMPASSABLE: tuple[float, float] = (0.10, 0.27)

# Most elements handed to one np.bincount when stamping features; bounds peak memory.
_STAMP_CHUNK = 6_000_000


def generate_dem(kind: str, size: int, *, seed: int = 0, pixel_size: float | None = None) -> Dem:
    """Generate a seeded synthetic DEM of a built-in terrain kind.

    Parameters
    ----------
    kind : str
        One of :data:`TERRAIN_KINDS`.
    size : int
        Cells per side, in ``[64, 4096]``; the DEM is ``size x size``.
    seed : int
        Non-negative seed; the output is a pure function of ``(kind, size, seed,
        pixel_size)``.
    pixel_size : float, optional
        Metres per cell; defaults to 1 m for every kind (rover scale).

    Returns
    -------
    Dem
        float32 elevation in metres without NaNs. ``meta`` holds ``kind``, ``seed``,
        ``size``, ``pixel_size``, ``relief_scale`` and kind-specific entries:

        * ``mars`` and ``moon``: ``craters``, a list of ``(row, col, radius_px)`` of
          the craters centred inside the map, largest first, and ``fresh_craters``,
          the subset stamped last with sharp rims;
        * ``mars``: ``wind_direction_deg``, the direction the dune-forming wind blows;
        * ``ice``: ``flow_direction_deg``, the downhill ice-flow direction.

        Directions are in degrees from the +column axis towards +row.

    Raises
    ------
    FedmapError
        For an unknown kind, a size outside the allowed range, a bad seed or a
        non-positive pixel size.
    """
    px = _check_args(kind, size, seed, pixel_size)
    rng = np.random.default_rng(int(seed))
    z, meta = _GENERATORS[kind](rng, int(size), px)
    z, k = _calibrate_relief(z, px)
    meta = {"kind": kind, "seed": int(seed), "size": int(size), "pixel_size": px, "relief_scale": k, **meta}
    return Dem(z, px, f"builtin:{kind}(size={int(size)},seed={int(seed)})", meta)


# --------------------------------------------------------------------------- arguments


def _check_args(kind: object, size: object, seed: object, pixel_size: object) -> float:
    """Validate the public arguments; return the pixel size in metres."""
    if kind not in TERRAIN_KINDS:
        raise FedmapError(f"unknown terrain kind {kind!r}: choose one of {', '.join(TERRAIN_KINDS)}")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not _MIN_SIZE <= size <= _MAX_SIZE:
        raise FedmapError(f"terrain size must be an integer in [{_MIN_SIZE}, {_MAX_SIZE}], got {size!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise FedmapError(f"terrain seed must be a non-negative integer, got {seed!r}")
    if pixel_size is None:
        return _DEFAULT_PIXEL_SIZE[str(kind)]
    try:
        px = float(pixel_size)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        px = float("nan")
    if not math.isfinite(px) or px <= 0:
        raise FedmapError(f"pixel size must be a positive number of metres, got {pixel_size!r}")
    return px


# --------------------------------------------------------------------------- fields


def _spectral_noise(rng: np.random.Generator, n: int, px: float, beta: float, corner_m: float) -> np.ndarray:
    """Zero-mean, unit-std fractal field by spectral synthesis.

    The power spectrum falls as ``(k^2 + k0^2)^(-beta/2)`` with ``k0 = 1/corner_m``: a
    1/f^beta surface that flattens out beyond ``corner_m``, so big maps do not grow
    ever larger hills. Synthesised on a grid 1/8 larger than needed and cropped, so the
    FFT's periodicity does not show as matching opposite edges.
    """
    m = _fft_size(n + n // 8)
    ky = np.fft.fftfreq(m, d=px)[:, None]
    kx = np.fft.rfftfreq(m, d=px)[None, :]
    amp = (kx * kx + ky * ky + corner_m**-2) ** (-beta / 4.0)
    amp[0, 0] = 0.0
    spec = (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape)) * amp
    field = np.fft.irfft2(spec, s=(m, m))[:n, :n]
    field -= field.mean()
    return field / max(float(field.std()), 1e-12)


def _fft_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n, a size numpy's FFT handles fast."""
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p = p35
            while p < n:
                p *= 2
            best = min(best, p)
            p35 *= 3
        p5 *= 5
    return best


def _smooth_field(rng: np.random.Generator, n: int, px: float, scale_m: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field with features about ``scale_m`` across.

    Used for zone masks and coordinate warps. Drawn on a coarse grid (about six cells
    per feature) and upsampled by separable cubic convolution, written as two small
    matrix products: at 2048 cells a full-resolution FFT, or ``ndimage.zoom``, per
    mask would dominate the run time for no visible gain.
    """
    cell = max(scale_m / 6.0, px)
    nc = int(math.ceil(n * px / cell)) + 4
    coarse = _spectral_noise(rng, nc, cell, 4.0, scale_m)
    w = _cubic_upsample_matrix(n, px / cell, nc)
    fine = w @ coarse @ w.T
    fine -= fine.mean()
    return fine / max(float(fine.std()), 1e-12)


def _cubic_upsample_matrix(n: int, step: float, m: int) -> np.ndarray:
    """``(n, m)`` weights of Keys cubic convolution sampling a coarse axis at ``1 + i*step``.

    ``m`` must exceed ``2 + (n - 1) * step + 1`` so every sample has its four nodes.

    The kernel is C1-continuous, so warps built from it bend stripes smoothly instead
    of kinking them at coarse-grid nodes as linear interpolation would.
    """
    pos = 1.0 + np.arange(n) * step
    base = np.floor(pos).astype(np.int64)
    frac = pos - base
    w = np.zeros((n, m))
    rows = np.arange(n)
    for off in (-1, 0, 1, 2):
        t = np.abs(frac - off)
        k = np.where(t <= 1, 1.5 * t**3 - 2.5 * t**2 + 1, -0.5 * t**3 + 2.5 * t**2 - 4 * t + 2)
        np.add.at(w, (rows, base + off), k)
    return w


def _rms_slope_normalise(z: np.ndarray, px: float, slope_deg: float) -> np.ndarray:
    """Scale ``z`` so that its RMS gradient is ``tan(slope_deg)``.

    Normalising the slope rather than the height keeps the background equally gentle
    at every map size and pixel size, because slope is what the classifier tests.
    """
    return _gradient_normalise(z, px, math.tan(math.radians(slope_deg)))


def _gradient_normalise(z: np.ndarray, px: float, rms_gradient: float, stride: int = 1) -> np.ndarray:
    """Scale ``z`` so that its RMS gradient (units of z per metre) is ``rms_gradient``.

    Also used for coordinate warps: a warp's gradient, not its amplitude, decides how
    much it bends and squeezes the stripes it displaces. ``stride > 1`` estimates the
    gradient on every ``stride``-th cell, accurate for fields smooth at that scale.
    """
    sub = z[::stride, ::stride]
    gy, gx = np.gradient(sub, px * stride) if min(sub.shape) > 2 else np.gradient(z, px)
    rms = float(np.sqrt(np.mean(gx * gx + gy * gy)))
    return z * (rms_gradient / max(rms, 1e-12))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """Cubic smoothstep clipped to [0, 1]: C1-continuous soft masks and tapers."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _zone_mask(field: np.ndarray, area: float, softness: float = 0.35) -> np.ndarray:
    """Soft mask in [0, 1] covering about ``area`` of the map where ``field`` is highest.

    The threshold is the field's own quantile, so every map (even a 64-cell one that
    sees only a sliver of one zone) gets the intended share of zone area.
    """
    thr = float(np.quantile(field[::4, ::4], 1.0 - area))
    return _smoothstep((field - thr) / softness + 0.5)


def _coords(n: int, px: float) -> tuple[np.ndarray, np.ndarray]:
    """Column (x) and row (y) coordinates in metres, centred on the map, broadcastable."""
    c = (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * px
    return c[None, :], c[:, None]


# --------------------------------------------------------------------------- stamping


class _Accumulator:
    """Adds many small windows of values into an ``n x n`` grid via chunked bincount.

    ``np.add.at`` with random indices is an order of magnitude slower than
    ``np.bincount`` here, and bincount per small group would re-allocate the whole
    grid each time, so flat indices and values are buffered and flushed in chunks.
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.total = np.zeros(n * n, dtype=np.float64)
        self._idx: list[np.ndarray] = []
        self._val: list[np.ndarray] = []
        self._count = 0

    def add(self, idx: np.ndarray, val: np.ndarray) -> None:
        self._idx.append(idx)
        self._val.append(val)
        self._count += idx.size
        if self._count >= _STAMP_CHUNK:
            self.flush()

    def flush(self) -> None:
        if self._count:
            idx = np.concatenate(self._idx)
            val = np.concatenate(self._val)
            self.total += np.bincount(idx, weights=val, minlength=self.n * self.n)
        self._idx, self._val, self._count = [], [], 0

    def result(self) -> np.ndarray:
        self.flush()
        return self.total.reshape(self.n, self.n)


def _window_indices(n: int, rows: np.ndarray, cols: np.ndarray, hw: int):
    """Offsets of ``(2hw+1)^2`` windows around each centre, clipped to the map.

    Returns the sub-pixel offsets ``dy, dx`` (N, w, w) in cells, the flat indices of
    the in-map cells and the boolean mask selecting them.
    """
    off = np.arange(-hw, hw + 1)
    r0 = np.rint(rows).astype(np.int64)
    c0 = np.rint(cols).astype(np.int64)
    rr = r0[:, None, None] + off[None, :, None]
    cc = c0[:, None, None] + off[None, None, :]
    inside = (rr >= 0) & (rr < n) & (cc >= 0) & (cc < n)
    dy = (rr - rows[:, None, None]).astype(np.float32)
    dx = (cc - cols[:, None, None]).astype(np.float32)
    flat = (rr * n + cc)[inside]
    return dy, dx, flat, inside


@dataclass
class _Craters:
    """A crater population, one entry per crater.

    Attributes
    ----------
    row, col : centre in cells (may lie outside the map; only overlapping ones count).
    radius : rim radius in cells.
    depth : floor depth below the surrounding surface, metres.
    rim : rim height above the surrounding surface, metres.
    floor : flat-floor radius as a fraction of the rim radius.
    tilt, tilt_dir : first azimuthal harmonic of the wall relief (0 = symmetric); a
        large tilt lowers one side of the rim so the crater has an entrance.
    ellip, ellip_dir : second harmonic of the radius: slightly elliptical outlines.
    """

    row: np.ndarray
    col: np.ndarray
    radius: np.ndarray
    depth: np.ndarray
    rim: np.ndarray
    floor: np.ndarray
    tilt: np.ndarray
    tilt_dir: np.ndarray
    ellip: np.ndarray
    ellip_dir: np.ndarray

    def __len__(self) -> int:
        return int(self.row.size)

    def subset(self, keep: np.ndarray) -> _Craters:
        return _Craters(**{k: v[keep] for k, v in vars(self).items()})


#: Ejecta reach in rim radii: beyond it a crater leaves the surface untouched.
_EJECTA_REACH = 2.2


def _crater_profile(dy, dx, c: _Craters) -> np.ndarray:
    """Elevation change (metres) of a batch of craters at offsets ``dy, dx`` (N, w, w).

    Inside the rim a flat floor of radius ``floor * R`` rises to the rim along a
    parabola, ``z = -d + (d + h) m t^2``, so the wall is steepest at the rim (a sharp
    crest) and meets the floor smoothly; ``m`` tilts the relief with azimuth. Outside,
    the ejecta apron decays like ``q^-3`` (the classic ejecta thickness law) and is
    tapered to zero at ``_EJECTA_REACH`` so the window edge leaves no seam.
    """
    def per(a):
        return a.astype(np.float32)[:, None, None]

    dist = np.sqrt(dy * dy + dx * dx)
    inv = 1.0 / np.maximum(dist, np.float32(1e-6))
    cos_t, sin_t = dx * inv, dy * inv
    tdir, edir = per(c.tilt_dir), per(c.ellip_dir)
    m = 1.0 + per(c.tilt) * (cos_t * np.cos(tdir) + sin_t * np.sin(tdir))
    cos2 = (cos_t * cos_t - sin_t * sin_t) * np.cos(2 * edir) + 2 * sin_t * cos_t * np.sin(2 * edir)
    q = dist / (per(c.radius) * (1.0 + per(c.ellip) * cos2))
    d, h, f = per(c.depth), per(c.rim), per(c.floor)
    t = np.clip((q - f) / (1.0 - f), 0.0, 1.0)
    inside = -d + (d + h) * m * t * t
    rim_z = -d + (d + h) * m
    s = np.clip((q - 1.0) / (_EJECTA_REACH - 1.0), 0.0, 1.0)
    outside = rim_z * np.maximum(q, 1.0) ** -3 * (1.0 - s * s) ** 2
    return np.where(q < 1.0, inside, outside)


def _stamp_craters(n: int, c: _Craters, factor: int = 1) -> np.ndarray:
    """Sum the relief of all craters into an ``n x n`` grid.

    Craters are grouped by window half-width so each group is one vectorised batch of
    equal-sized windows; only cells inside the map are kept. With ``factor > 1`` the
    craters are stamped on a grid ``factor`` times coarser and upsampled: for craters
    that will be diffused by more than a cell anyway this loses nothing visible and
    cuts the work by ``factor^2``.
    """
    if factor == 1:
        return _stamp_windows(n, c)
    # Coarse node j sits at fine position (j - 1) * factor; see _cubic_upsample_matrix.
    m = int(math.ceil((n - 1) / factor)) + 4
    scaled = _Craters(**{**vars(c), "row": c.row / factor + 1, "col": c.col / factor + 1, "radius": c.radius / factor})
    w = _cubic_upsample_matrix(n, 1.0 / factor, m)
    return w @ _stamp_windows(m, scaled) @ w.T


def _stamp_windows(n: int, c: _Craters) -> np.ndarray:
    """Crater relief on an ``n x n`` grid at full resolution (see :func:`_stamp_craters`)."""
    acc = _Accumulator(n)
    hw_all = np.ceil(c.radius * _EJECTA_REACH * (1.0 + c.ellip)).astype(np.int64) + 1
    for hw in np.unique(hw_all):
        sel = np.flatnonzero(hw_all == hw)
        # Batches of a few million elements keep the temporary (N, w, w) arrays small.
        step = max(1, 2_000_000 // (2 * int(hw) + 1) ** 2)
        for start in range(0, sel.size, step):
            g = c.subset(sel[start : start + step])
            dy, dx, flat, inside = _window_indices(n, g.row, g.col, int(hw))
            acc.add(flat, _crater_profile(dy, dx, g)[inside])
    return acc.result()


#: Gaussian widths (cells) boulders are rounded to: one blur per class, not per boulder.
_BOULDER_SIGMAS = np.array([0.6, 0.9, 1.35, 2.0, 3.0])


def _stamp_boulders(n: int, px: float, rows: np.ndarray, cols: np.ndarray, height: np.ndarray,
                    radius_m: np.ndarray) -> np.ndarray:
    """Boulders as Gaussian bumps, by depositing them on cells and blurring per size class.

    A boulder's footprint follows its radius (a few width classes, so a 3 m boulder
    blocks more cells than a 1 m one). A boulder narrower than a cell is averaged over
    the cell (its volume spread over ``px^2``), so coarse maps lose small boulders as a
    real coarse DEM would.
    """
    r = np.rint(rows).astype(np.int64)
    c = np.rint(cols).astype(np.int64)
    keep = (r >= 0) & (r < n) & (c >= 0) & (c < n)
    flat = r[keep] * n + c[keep]
    h_eff = (height * np.minimum(1.0, (radius_m / px) ** 2 * math.pi / 2.0))[keep]
    sigma_px = np.maximum(radius_m[keep] / (1.5 * px), _BOULDER_SIGMAS[0])
    cls = np.argmin(np.abs(np.log(sigma_px[:, None] / _BOULDER_SIGMAS[None, :])), axis=1)
    out = np.zeros((n, n))
    for i in np.unique(cls):
        sigma = float(_BOULDER_SIGMAS[i])
        half = int(math.ceil(3.5 * sigma))
        # Peak of the normalised discrete kernel: deposit h / peak so the bump tops at h.
        g = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
        peak = (1.0 / g.sum()) ** 2
        sel = cls == i
        grid = np.bincount(flat[sel], weights=h_eff[sel] / peak, minlength=n * n).reshape(n, n)
        out += ndimage.gaussian_filter(grid, sigma, radius=half, mode="constant")
    return out


def _boulder_sizes(rng: np.random.Generator, count: int, h_min: float, h_max: float, exponent: float):
    """Power-law boulder heights (metres) and radii (boulders about twice as wide as high)."""
    u = rng.random(count)
    h = np.minimum(h_min * (1.0 - u) ** (-1.0 / exponent), h_max)
    return h, h * (0.8 + 0.4 * rng.random(count))


# --------------------------------------------------------------------------- craters


def _power_law_radii(rng: np.random.Generator, count: int, r_min: float, r_max: float, b: float) -> np.ndarray:
    """Truncated Pareto radii: cumulative number of craters larger than R falls as R^-b."""
    u = rng.random(count)
    lo = 1.0 - (r_min / r_max) ** b
    return r_min * (1.0 - u * lo) ** (-1.0 / b)


def _crater_count(rng: np.random.Generator, area_m2: float, density: float, r_min: float, r_ref: float, b: float) -> int:
    """Poisson number of craters with radius >= r_min on ``area_m2``.

    ``density`` is craters per m^2 larger than the reference radius ``r_ref``; the
    cumulative power law gives the count above ``r_min``. Fixing a physical density
    (not a count per map) is what makes a bigger map show more craters.
    """
    return int(rng.poisson(area_m2 * density * (r_ref / r_min) ** b))


def _place_craters(rng: np.random.Generator, n: int, px: float, count: int, r_min: float, r_max: float,
                   b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sizes (cells) and uniform centres over the map plus a margin of the largest reach.

    The margin lets craters centred just outside the map show their rims and ejecta at
    the edges, so the edges are not visibly emptier than the middle.
    """
    radius = _power_law_radii(rng, count, r_min, r_max, b) / px
    pad = r_max / px * _EJECTA_REACH
    row = rng.uniform(-pad, n - 1 + pad, count)
    col = rng.uniform(-pad, n - 1 + pad, count)
    return row, col, radius


def _visible(n: int, c: _Craters) -> _Craters:
    """Drop craters whose reach does not touch the map (they were sampled in the margin)."""
    reach = c.radius * _EJECTA_REACH * (1.0 + c.ellip) + 1
    keep = (c.row + reach >= 0) & (c.row - reach <= n - 1) & (c.col + reach >= 0) & (c.col - reach <= n - 1)
    return c.subset(keep)


def _crater_list(n: int, c: _Craters) -> list[tuple[float, float, float]]:
    """``(row, col, radius_px)`` of craters centred inside the map, largest first."""
    inside = (c.row >= 0) & (c.row <= n - 1) & (c.col >= 0) & (c.col <= n - 1)
    order = np.argsort(-c.radius[inside], kind="stable")
    rows, cols, rad = c.row[inside][order], c.col[inside][order], c.radius[inside][order]
    return [(float(r), float(q), float(s)) for r, q, s in zip(rows, cols, rad)]


def _r_min(px: float, metres: float) -> float:
    """Smallest crater radius worth stamping: ``metres`` but at least 1.5 cells."""
    return max(metres, 1.5 * px)


def _r_max(n: int, px: float, metres: float) -> float:
    """Largest crater radius: ``metres``, but at most a fifth of the map extent.

    Without the cap one big crater could fill a small map; the cap keeps small maps
    a fair sample of the terrain.
    """
    return min(metres, 0.2 * n * px)


# --------------------------------------------------------------------------- mars


def _mars(rng: np.random.Generator, n: int, px: float) -> tuple[np.ndarray, dict]:
    """Mars plains: fractal background, craters, dune fields and boulder fields."""
    z = _rms_slope_normalise(_spectral_noise(rng, n, px, 3.2, 300.0), px, 3.5)
    craters = _mars_craters(rng, n, px)
    # Two epochs: old craters are stamped and diffused (soft rims, shallow walls) before
    # the fresh ones, which keep sharp rims.
    old = craters.subset(np.arange(len(craters)) < len(craters) * 0.55)
    fresh = craters.subset(np.arange(len(craters)) >= len(craters) * 0.55)
    z += _diffuse(_stamp_craters(n, old, max(1, int(2.5 / px))), 2.5 / px)
    z += _stamp_craters(n, fresh)
    dunes, wind = _dunes(rng, n, px)
    z += dunes
    z += _mars_boulders(rng, n, px, fresh)
    return z, {"craters": _crater_list(n, craters), "fresh_craters": _crater_list(n, fresh), "wind_direction_deg": wind}


def _diffuse(z: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur standing in for ages of hillslope diffusion (sigma in cells)."""
    return ndimage.gaussian_filter(z, sigma_px, mode="nearest") if sigma_px > 0.3 else z


def _mars_craters(rng: np.random.Generator, n: int, px: float) -> _Craters:
    """A production population with a steep power law (cumulative slope -2.8)."""
    b = 2.8
    r_min, r_max = _r_min(px, 1.5), _r_max(n, px, 120.0)
    pad = r_max * _EJECTA_REACH
    area = (n * px + 2 * pad) ** 2
    count = _crater_count(rng, area, 6.0e-3, r_min, 1.5, b)
    row, col, radius = _place_craters(rng, n, px, count, r_min, r_max, b)
    depth_ratio = rng.uniform(0.12, 0.32, count)
    c = _Craters(
        row=row,
        col=col,
        radius=radius,
        depth=depth_ratio * radius * px,
        rim=depth_ratio * radius * px * rng.uniform(0.15, 0.3, count),
        floor=rng.uniform(0.3, 0.6, count),
        tilt=rng.uniform(0.0, 0.35, count),
        tilt_dir=rng.uniform(0.0, 2 * math.pi, count),
        ellip=rng.uniform(0.0, 0.08, count),
        ellip_dir=rng.uniform(0.0, math.pi, count),
    )
    return _visible(n, c)


def _dunes(rng: np.random.Generator, n: int, px: float) -> tuple[np.ndarray, float]:
    """Transverse dune fields: asymmetric ridges across a dominant wind, in some zones.

    Each ridge has a long gentle stoss side (~8 deg) and a short steep lee side (slip
    face ~25 deg) downwind. The ridge phase is warped by a smooth field so crests curve
    and wavelengths vary; crest height varies along the crest, and a zone mask keeps
    the dunes to patches (about a fifth of the plain).

    Returns the relief and the wind direction (degrees from +column towards +row).
    """
    wind = rng.uniform(0.0, 2 * math.pi)
    wavelength = rng.uniform(20.0, 32.0)
    x, y = _coords(n, px)
    # The warp's gradient is a fraction of the ridge frequency: crests bend and
    # wavelengths vary by ~20% but ridges stay roughly across the wind.
    warp = _gradient_normalise(_smooth_field(rng, n, px, 250.0), px, 0.2 / wavelength, stride=4)
    phase = (x * math.cos(wind) + y * math.sin(wind)) / wavelength + warp
    p = phase - np.floor(phase)
    lee = 0.2
    # Stoss: half cosine from trough (p=0) up to crest (p=1-lee); lee: back down.
    stoss = 0.5 - 0.5 * np.cos(np.pi * np.minimum(p / (1 - lee), 1.0))
    down = 0.5 + 0.5 * np.cos(np.pi * np.clip((p - (1 - lee)) / lee, 0.0, 1.0))
    profile = np.where(p < 1 - lee, stoss, down)
    height = wavelength * rng.uniform(0.07, 0.085) * (1.0 + 0.2 * _smooth_field(rng, n, px, 60.0))
    zone = _zone_mask(_smooth_field(rng, n, px, 250.0), rng.uniform(0.25, 0.35), softness=0.6)
    # A coarse DEM cannot resolve ridges only a few cells apart: fade them out.
    resolve = float(np.clip((wavelength / px - 3.0) / 3.0, 0.0, 1.0))
    return profile * np.maximum(height, 0.0) * zone * resolve, math.degrees(wind) % 360.0


def _mars_boulders(rng: np.random.Generator, n: int, px: float, fresh: _Craters) -> np.ndarray:
    """Clustered boulder fields (a Thomas process) plus ejecta boulders around fresh craters."""
    ext = n * px
    n_fields = max(1, int(rng.poisson((ext + 100.0) ** 2 / 140.0**2)))
    fr = rng.uniform(-50.0, ext + 50.0, n_fields) / px
    fc = rng.uniform(-50.0, ext + 50.0, n_fields) / px
    spread = rng.uniform(8.0, 25.0, n_fields)
    per_field = rng.poisson(0.4 * spread**2)
    parent = np.repeat(np.arange(n_fields), per_field)
    k = parent.size
    rows = fr[parent] + rng.standard_normal(k) * spread[parent] / px
    cols = fc[parent] + rng.standard_normal(k) * spread[parent] / px
    h, a = _boulder_sizes(rng, k, 0.4, 2.5, 2.0)
    er, ec, eh, ea = _ejecta_boulders(rng, px, fresh, 0.02)
    return _stamp_boulders(n, px, np.concatenate([rows, er]), np.concatenate([cols, ec]), np.concatenate([h, eh]),
                           np.concatenate([a, ea]))


def _ejecta_boulders(rng: np.random.Generator, px: float, craters: _Craters, per_m2: float):
    """Boulders thrown onto the ejecta apron (1 to 2.2 rim radii) of craters > 3 m."""
    big = craters.radius * px > 3.0
    r_m = craters.radius[big] * px
    counts = rng.poisson(per_m2 * math.pi * r_m**2)
    owner = np.repeat(np.arange(r_m.size), counts)
    k = owner.size
    dist = r_m[owner] * rng.uniform(0.95, 2.2, k) / px
    ang = rng.uniform(0.0, 2 * math.pi, k)
    rows = craters.row[big][owner] + dist * np.sin(ang)
    cols = craters.col[big][owner] + dist * np.cos(ang)
    h, a = _boulder_sizes(rng, k, 0.4, 2.0, 2.2)
    return rows, cols, h, a


# --------------------------------------------------------------------------- moon


#: Moon crater epochs, oldest first: (density of craters > 1.5 m per m^2, range of
#: depth/radius, range of flat-floor fraction, diffusion sigma in metres applied after
#: the epoch). Older craters are shallower bowls with gentle walls (topographic
#: diffusion lowers depth/diameter and widens the walls with age) and the blurs
#: accumulate, so old craters are soft and small old ones vanish, as in lunar
#: equilibrium terrain; only the last, sparse epoch keeps sharp fresh rims.
_MOON_EPOCHS: tuple[tuple[float, tuple[float, float], tuple[float, float], float], ...] = (
    (0.050, (0.03, 0.06), (0.0, 0.2), 3.0),
    (0.035, (0.04, 0.08), (0.1, 0.3), 2.0),
    (0.018, (0.06, 0.11), (0.2, 0.4), 1.0),
    (0.005, (0.16, 0.28), (0.3, 0.5), 0.0),
)


def _moon(rng: np.random.Generator, n: int, px: float) -> tuple[np.ndarray, dict]:
    """Crater-saturated regolith: epochs of cratering and diffusion, then boulders."""
    z = _rms_slope_normalise(_spectral_noise(rng, n, px, 3.6, 400.0), px, 2.5)
    b = 2.6
    r_max = _r_max(n, px, 100.0)
    pad = r_max * _EJECTA_REACH
    area = (n * px + 2 * pad) ** 2
    relief = np.zeros((n, n))
    epochs: list[_Craters] = []
    sigmas = [e[3] for e in _MOON_EPOCHS]
    for e, (density, depth_ratio, floor, sigma) in enumerate(_MOON_EPOCHS):
        # Craters smaller than what the remaining diffusion erases are not worth stamping.
        remaining = math.sqrt(sum(v * v for v in sigmas[e:]))
        r_min = max(_r_min(px, 1.5), 1.2 * remaining)
        count = _crater_count(rng, area, density, r_min, 1.5, b)
        c = _moon_crater_params(rng, n, px, count, r_min, r_max, b, depth_ratio, floor)
        factor = max(1, int(remaining / px))
        relief = _diffuse(relief + _stamp_craters(n, c, factor), sigma / px)
        epochs.append(c)
    z += relief
    er, ec, eh, ea = _ejecta_boulders(rng, px, epochs[-1], 0.03)
    z += _stamp_boulders(n, px, er, ec, eh, ea)
    merged = _Craters(**{k: np.concatenate([getattr(c, k) for c in epochs]) for k in vars(epochs[0])})
    return z, {"craters": _crater_list(n, merged), "fresh_craters": _crater_list(n, epochs[-1])}


def _moon_crater_params(
    rng: np.random.Generator,
    n: int,
    px: float,
    count: int,
    r_min: float,
    r_max: float,
    b: float,
    depth_ratio: tuple[float, float],
    floor: tuple[float, float],
) -> _Craters:
    """Simple-crater shapes (bowls with rims) of the given depth/radius range."""
    row, col, radius = _place_craters(rng, n, px, count, r_min, r_max, b)
    ratio = rng.uniform(depth_ratio[0], depth_ratio[1], count)
    c = _Craters(
        row=row,
        col=col,
        radius=radius,
        depth=ratio * radius * px,
        rim=ratio * radius * px * rng.uniform(0.18, 0.3, count),
        floor=rng.uniform(floor[0], floor[1], count),
        tilt=rng.uniform(0.0, 0.3, count),
        tilt_dir=rng.uniform(0.0, 2 * math.pi, count),
        ellip=rng.uniform(0.0, 0.06, count),
        ellip_dir=rng.uniform(0.0, math.pi, count),
    )
    return _visible(n, c)


# --------------------------------------------------------------------------- ice


def _ice(rng: np.random.Generator, n: int, px: float) -> tuple[np.ndarray, dict]:
    """Glacier: sloping smooth ice, crevasse fields, marginal seracs, moraines.

    Across the flow the glacier is zoned from its centre line outwards: transverse
    crevasse fields, then a band of chevron crevasses, then a band of serac blocks,
    then the lateral moraine and debris-covered ground beyond the ice. The glacier is
    wider than small maps (a 256 m map is usually all interior) and its margins come
    into view at the sides of maps about a kilometre or more across.
    """
    flow = rng.uniform(0.0, 2 * math.pi)
    x, y = _coords(n, px)
    s = x * math.cos(flow) + y * math.sin(flow)  # downstream distance, m
    u = -x * math.sin(flow) + y * math.cos(flow)  # across-flow distance, m
    surface_slope = math.tan(math.radians(rng.uniform(2.0, 5.0)))
    z = -surface_slope * s
    z = z + _rms_slope_normalise(_spectral_noise(rng, n, px, 3.8, 200.0), px, 1.5)
    ext = n * px
    serac_band = rng.uniform(50.0, 100.0)
    chevron_band = rng.uniform(80.0, 160.0)
    half_width = serac_band + chevron_band + 80.0 + rng.uniform(0.25, 0.4) * ext
    # Across-flow distance from the centre line, warped so the margins wander.
    u = u - rng.uniform(-0.1, 0.1) * ext + _gradient_normalise(_smooth_field(rng, n, px, 300.0), px, 0.1, stride=4)
    lateral = np.abs(u)
    outside = _smoothstep((lateral - half_width) / 10.0 + 0.5)
    serac_zone = _smoothstep((lateral - (half_width - serac_band)) / 10.0 + 0.5)
    near_margin = _smoothstep((lateral - (half_width - serac_band - chevron_band)) / 20.0 + 0.5) - serac_zone
    z += _transverse_crevasses(rng, n, px, s, u, half_width, 1.0 - serac_zone - near_margin)
    z += _chevron_crevasses(rng, n, px, s, u, near_margin)
    z += _seracs(rng, n, px, s, u, serac_zone - outside)
    z += _medial_moraines(rng, n, px, u, half_width)
    z += _lateral_moraine(rng, n, px, lateral, half_width, outside)
    return z, {"flow_direction_deg": math.degrees(flow) % 360.0}


def _region(weight: np.ndarray) -> np.ndarray:
    """Flat indices of the cells where ``weight > 0``.

    Zonal features (crevasse fields, seracs) are evaluated only there: on large maps
    each zone covers a fraction of the grid, and on small maps often none of it.
    """
    return np.flatnonzero(weight.ravel() > 0.0)


def _scatter(n: int, sel: np.ndarray, values: np.ndarray) -> np.ndarray:
    """An ``n x n`` grid that is ``values`` at flat indices ``sel`` and 0 elsewhere."""
    out = np.zeros(n * n)
    out[sel] = values
    return out.reshape(n, n)


def _crevasse_set(rng: np.random.Generator, px: float, along: np.ndarray, across: np.ndarray, spacing: float,
                  zone: np.ndarray) -> np.ndarray:
    """A family of parallel crevasses: narrow deep trenches along lines ``along = const``.

    Works on flat arrays of selected cells. ``along`` is the coordinate across the
    crevasses (metres), ``across`` the one along them, ``zone`` the weight in [0, 1].
    Crevasse ``k`` lies at ``along = k * spacing`` and is broken into lens-shaped
    segments along its length, each tapering in depth and width toward its tips, with
    gaps a rover can cross. Every crevasse draws its own depth, width and segment
    pattern from per-index tables. On cells wider than a crevasse the trench is
    widened to a cell and made shallower in proportion (its cross-section kept), as a
    coarse DEM would average it, instead of being hit or missed cell by cell.
    """
    phase = along / spacing
    k = np.rint(phase)
    dist = (phase - k) * spacing  # metres from the crevasse axis
    k_lo = int(k.min()) if k.size else 0
    n_k = (int(k.max()) - k_lo + 1) if k.size else 1
    ki = (k - k_lo).astype(np.int64)
    half_width = rng.uniform(0.4, 0.9, n_k)[ki]
    wide = np.maximum(half_width, 0.75 * px)
    depth = rng.uniform(3.0, 8.0, n_k)[ki] * half_width / wide
    half_width = wide
    seg_len = rng.uniform(20.0, 60.0, n_k)[ki]
    seg_off = rng.uniform(0.0, 1.0, n_k)[ki]
    duty = rng.uniform(0.5, 0.85, n_k)[ki]
    # Lens-shaped segments: cos above a cut-off, rescaled to [0, 1].
    cut = np.cos(np.pi * duty)
    wave = np.cos(2 * np.pi * (across / seg_len + seg_off))
    seg = np.sqrt(np.clip((wave - cut) / (1.0 - cut), 0.0, 1.0) * zone)
    trench = np.clip(1.0 - (dist / (half_width * seg + 1e-6)) ** 2, 0.0, 1.0)
    return -depth * seg * trench


def _transverse_crevasses(rng: np.random.Generator, n: int, px: float, s: np.ndarray, u: np.ndarray,
                          half_width: float, weight: np.ndarray) -> np.ndarray:
    """Crevasse fields across the flow where the ice accelerates, times ``weight``.

    The crevasses arc downstream toward the centre line (the centre flows fastest).
    The fields are bands crossing the glacier (where the bed steepens), a few hundred
    metres apart along the flow, together covering about half of the surface.
    """
    spacing = rng.uniform(8.0, 13.0)
    # Parabolic arcs lagging by up to 0.4 half-widths at the margins, where the
    # crevasses then meet the flow at no less than ~50 degrees.
    arc = rng.uniform(0.0, 0.4) / half_width
    # The warp's gradient is a small fraction of the crevasse frequency: lines bend a
    # little and spacing varies by ~10%, but crevasses never cross.
    warp = _gradient_normalise(_smooth_field(rng, n, px, 200.0), px, 0.12, stride=4)
    bands = _random_waves(rng, s, 250.0) + 0.4 * _smooth_field(rng, n, px, 300.0)
    zone = _zone_mask(bands, rng.uniform(0.5, 0.65), softness=0.25) * weight
    sel = _region(zone)
    ss, uu = s.ravel()[sel], u.ravel()[sel]
    along = ss - arc * uu * uu + warp.ravel()[sel]
    return _scatter(n, sel, _crevasse_set(rng, px, along, uu, spacing, zone.ravel()[sel]))


def _chevron_crevasses(rng: np.random.Generator, n: int, px: float, s: np.ndarray, u: np.ndarray,
                       weight: np.ndarray) -> np.ndarray:
    """Marginal (chevron) crevasses at ~45 deg to the margin, pointing up-glacier.

    Shear at a margin opens crevasses at about 45 degrees to the flow; mirrored on the
    two sides of the centre line they form chevrons.
    """
    angle = math.radians(rng.uniform(35.0, 55.0))
    spacing = rng.uniform(10.0, 18.0)
    warp = _gradient_normalise(_smooth_field(rng, n, px, 200.0), px, 0.12, stride=4)
    sel = _region(weight)
    ss, uu = s.ravel()[sel], u.ravel()[sel]
    side = np.where(uu >= 0.0, 1.0, -1.0)
    along = ss * math.cos(angle) + side * uu * math.sin(angle) + warp.ravel()[sel]
    across = -ss * math.sin(angle) + side * uu * math.cos(angle)
    return _scatter(n, sel, _crevasse_set(rng, px, along, across, spacing, weight.ravel()[sel]))


def _random_waves(rng: np.random.Generator, coord: np.ndarray, scale_m: float, count: int = 4) -> np.ndarray:
    """Unit-variance sum of a few random sinusoids of ``coord`` with wavelengths near ``scale_m``.

    A cheap 1-D random profile: it varies only along ``coord``, which makes bands.
    Evaluated on a fine 1-D grid and interpolated, so its cost does not grow with the
    number of sinusoids.
    """
    lo, hi = float(coord.min()), float(coord.max())
    grid = np.linspace(lo, hi, max(2, int((hi - lo) / (scale_m / 200.0)) + 2))
    prof = np.zeros_like(grid)
    for wavelength, phase in zip(scale_m * rng.uniform(0.6, 1.6, count), rng.uniform(0.0, 2 * math.pi, count)):
        prof += np.cos(2 * math.pi * grid / wavelength + phase)
    return np.interp(coord, grid, prof * math.sqrt(2.0 / count))


def _seracs(rng: np.random.Generator, n: int, px: float, s: np.ndarray, u: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Serac blocks, times ``weight``: ice towers separated by intersecting crevasses.

    Blocks sit on a grid aligned with the flow and gently warped; each has its own
    height and a slight tilt, and its sides drop steeply into the gaps.
    """
    a_s, a_u = rng.uniform(10.0, 16.0), rng.uniform(12.0, 20.0)
    warp_s = _gradient_normalise(_smooth_field(rng, n, px, 100.0), px, 0.15 / a_s, stride=4)
    warp_u = _gradient_normalise(_smooth_field(rng, n, px, 100.0), px, 0.15 / a_u, stride=4)
    sel = _region(weight)
    ps = s.ravel()[sel] / a_s + warp_s.ravel()[sel]
    pu = u.ravel()[sel] / a_u + warp_u.ravel()[sel]
    i, j = np.floor(ps), np.floor(pu)
    fs, fu = ps - i, pu - j
    i0 = int(i.min()) if i.size else 0
    j0 = int(j.min()) if j.size else 0
    ni = (int(i.max()) - i0 + 1) if i.size else 1
    nj = (int(j.max()) - j0 + 1) if j.size else 1
    heights = rng.uniform(1.0, 5.0, (ni, nj))
    tilt = rng.uniform(-0.15, 0.15, (ni, nj))
    ii, jj = (i - i0).astype(np.int64), (j - j0).astype(np.int64)
    edge = np.minimum(np.minimum(fs, 1 - fs), np.minimum(fu, 1 - fu))
    block = _smoothstep(edge / 0.1)
    values = block * (heights[ii, jj] + tilt[ii, jj] * (fs - 0.5) * a_s) * weight.ravel()[sel]
    return _scatter(n, sel, values)


def _medial_moraines(rng: np.random.Generator, n: int, px: float, u: np.ndarray, half_width: float) -> np.ndarray:
    """Medial moraines: low debris ridges along the flow, strewn with boulders.

    About one ridge per 300 m across the glacier, placed physically: a small map sees
    a moraine only sometimes, a large one several. Ridges depend on the across-flow
    distance only, so they are built as 1-D profiles and interpolated.
    """
    count = int(rng.poisson(2 * half_width / 300.0))
    centres = rng.uniform(-0.8 * half_width, 0.8 * half_width, count)
    # Broad, low ridges (flanks ~5 deg): the debris, not the ridge, is the obstacle.
    widths = rng.uniform(10.0, 20.0, count)
    heights = rng.uniform(1.0, 2.0, count)
    lo, hi = float(u.min()), float(u.max())
    grid = np.linspace(lo, hi, max(2, int((hi - lo) / 0.25) + 2))
    ridge = np.zeros_like(grid)
    debris = np.zeros_like(grid)
    for c, w, h in zip(centres, widths, heights):
        bump = np.exp(-0.5 * ((grid - c) / w) ** 2)
        ridge += h * bump
        debris = np.maximum(debris, bump)
    return np.interp(u, grid, ridge) + _scatter_boulders(rng, n, px, 0.02 * np.interp(u, grid, debris))


def _lateral_moraine(rng: np.random.Generator, n: int, px: float, lateral: np.ndarray, half_width: float,
                     outside: np.ndarray) -> np.ndarray:
    """A steep-flanked lateral moraine ridge just off the ice, and bouldery ground beyond."""
    height, width = rng.uniform(3.0, 6.0), rng.uniform(6.0, 10.0)
    d = (lateral - half_width - 1.5 * width) / width
    ridge = height * np.exp(-0.5 * d * d)
    return ridge + _scatter_boulders(rng, n, px, 0.008 * outside + 0.02 * ridge / height)


def _scatter_boulders(rng: np.random.Generator, n: int, px: float, per_m2: np.ndarray) -> np.ndarray:
    """Boulders with a spatially varying density (per m^2), by rejection sampling.

    Uniform proposals at the peak density are thinned by ``per_m2 / peak``, which
    is exact and needs no per-cell Poisson draws.
    """
    peak = float(per_m2.max())
    k = int(rng.poisson(peak * (n * px) ** 2))
    rows = rng.uniform(-0.5, n - 0.5, k)
    cols = rng.uniform(-0.5, n - 0.5, k)
    r = np.clip(np.rint(rows).astype(np.int64), 0, n - 1)
    c = np.clip(np.rint(cols).astype(np.int64), 0, n - 1)
    accept = rng.random(k) * peak < per_m2[r, c]
    h, a = _boulder_sizes(rng, k, 0.4, 2.0, 2.0)
    return _stamp_boulders(n, px, rows[accept], cols[accept], h[accept], a[accept])


# --------------------------------------------------------------------------- calibration


def _calibrate_relief(z: np.ndarray, px: float) -> tuple[np.ndarray, float]:
    """Scale relief so the impassable fraction lies inside ``_TARGET_IMPASSABLE``.

    The fraction is measured with :func:`dem_to_traversability` itself (default
    thresholds), treated as a black box, so the calibration stays right if the
    classifier's tests change. Its tests grow with the relief, so the fraction rises
    monotonically with a vertical scale factor ``k``; when the unscaled map is outside
    the band, ``k`` is found by a power-law first guess and then bisection in
    ``log k`` within ``[1/4, 4]``, stopping as soon as the fraction is in the band.
    Most maps need no scaling and cost a single classification.

    Returns the float32 DEM and the factor used (1.0 when already inside the band).
    """
    z = z - float(z.mean())
    lo, hi = _TARGET_IMPASSABLE
    z32 = z.astype(np.float32)
    frac = _impassable_fraction(z32, px)
    if lo <= frac <= hi:
        return z32, 1.0
    k_lo, k_hi = (1.0, 4.0) if frac < lo else (0.25, 1.0)
    target = lo + 0.03 if frac < lo else hi - 0.03
    # Fractions grow roughly like k^1.5 near the band: a good first guess.
    k = float(np.clip((target / max(frac, 1e-3)) ** (1 / 1.5), k_lo, k_hi))
    best = (abs(frac - target), 1.0, z32)
    for _ in range(10):
        scaled = (z * k).astype(np.float32)
        frac = _impassable_fraction(scaled, px)
        best = min(best, (abs(frac - target), k, scaled), key=lambda b: b[0])
        if lo <= frac <= hi:
            return scaled, k
        if frac < lo:
            k_lo = k
        else:
            k_hi = k
        k = math.sqrt(k_lo * k_hi)
    return best[2], best[1]


def _impassable_fraction(z: np.ndarray, px: float) -> float:
    """Share of cells the default traversability classifier marks impassable."""
    grid = dem_to_traversability(Dem(z, px))
    return float(np.mean(grid.classes == IMPASSABLE))


_GENERATORS = {"mars": _mars, "moon": _moon, "ice": _ice}
