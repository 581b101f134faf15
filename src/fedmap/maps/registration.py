"""Registration of traversability maps that share no frame, with a confidence gate.

Two rovers that started at unknown poses map in frames of their own. :func:`register`
estimates the rigid transform that carries map B's frame into map A's from the cells the
two maps both observed; :func:`merge` puts several maps into the first one's frame.

The transform (:class:`RigidTransform`) acts on cell coordinates ``(row, col)`` (cell
centres at integer coordinates): ``p_A = R(heading) p_B + (dy, dx)``, where ``R`` turns
counter-clockwise as the map is drawn (row 0 at the top), so ``dy`` is a shift down the
rows and ``dx`` along the columns, both in cells.

How the estimate is found
-------------------------
1. **Coarse search, every heading.** Both maps are reduced to about 64 cells a side
   (block means of "impassable" among the known cells; a block is known when half its
   cells are). For every heading on a grid (``heading_step``, default 2 deg, over the
   whole circle) B is turned about its centre and correlated with A at every shift by
   masked normalised cross-correlation (Padfield, "Masked object registration in the
   Fourier domain", IEEE TIP 2012; the statistic of
   ``skimage.registration.phase_cross_correlation(..., reference_mask=, moving_mask=)``),
   computed with FFTs for all shifts at once. Unknown cells take no part, so a shift is
   scored on the cells both maps know, and only shifts where those number at least
   ``min_overlap`` count. A shift's score is ``ncc ** SHARPNESS * sqrt(cells)``: more
   shared cells are more evidence, but neighbouring cells are far from independent, so a
   close fit on fewer cells must beat a loose fit on many (smooth blobs lying on other
   smooth blobs).
2. **Refinement.** The best headings (at least 10 deg apart) are screened at full
   resolution and the best few refined down the pyramid: at each level the heading is
   searched in half steps (turning about the middle of the overlap) and the shift in a
   small window, with the same score on the cells themselves; the shift is refined below
   a cell by a parabola through the scores beside the best.
3. **The gate (an independent check).** B is warped into A's frame with each placement
   the search kept (:meth:`RigidTransform.apply`, nearest neighbour) and the cells both
   maps know are compared (:func:`agreement`): the share that agree, against the share
   expected by chance from the two maps' class frequencies on that overlap, ``p_chance =
   sum_c pA(c) pB(c)``, gives Cohen's kappa, ``(agree - p_chance) / (1 - p_chance)`` --
   the *confidence*: 0 for maps that agree no more than chance, 1 for identical ones.
   The placement with the most evidence (``kappa ** EVIDENCE_POWER * sqrt(cells)``,
   :attr:`Agreement.evidence`; a power of 2, gentler than the search's 4, so a right
   placement on a large overlap of speckled or blobby maps is not beaten by a close fit on
   a sliver) is the estimate. It is *accepted* when the maps share at
   least ``min_overlap`` known cells (:data:`DEFAULT_MIN_OVERLAP`) with at least
   :data:`MIN_CLASS_CELLS` of each class in each map (kappa on a few impassable cells in
   a free overlap means little), kappa reaches ``gate`` (:data:`DEFAULT_GATE`) and its
   evidence beats that of every other placement the search found (another heading, or
   the overlap's middle elsewhere) by ``min_margin`` (:data:`DEFAULT_MARGIN`); otherwise
   it is *refused*, with the reason. Kappa alone is not enough: on maps of large smooth
   blobs a wrong placement can agree well with its overlap, and on finely speckled maps
   a right one agrees less than the noise suggests (nearest-neighbour resampling moves
   one-cell features); the margin refuses look-alike placements. Nothing refused is ever
   merged.

Merging (:func:`merge`): the first map's frame is the merged map's; each further map is
registered to the merged map so far (so it may overlap any map placed before it), and
maps refused in one pass are tried again after the others are placed. The canvas grows to
hold every placed map. Where two maps know a cell and disagree, IMPASSABLE wins: a
hazard is never overwritten with FREE.

Every step is deterministic: no random choice is made.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import fft, ndimage

from fedmap.errors import FedmapError
from fedmap.maps.georef import crop_transform
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap, check_classes

#: Cohen's kappa an estimate must reach on the overlap to be accepted.
DEFAULT_GATE: float = 0.4
#: Known cells the two maps must share under the estimate to be accepted.
DEFAULT_MIN_OVERLAP: int = 400
#: Cells of each class (free, impassable) each map must have on the overlap to be accepted.
MIN_CLASS_CELLS: int = 50
#: How much more evidence (:attr:`Agreement.evidence`) than any other placement found the estimate must have.
DEFAULT_MARGIN: float = 8.0
#: Placements further apart than this (heading, degrees; the overlap's middle, cells) are distinct.
DISTINCT_DEG, DISTINCT_CELLS = 4.0, 4.0
#: Power of the correlation in the search's score of a shift (``ncc ** SHARPNESS * sqrt(cells)``).
SHARPNESS: float = 4.0
#: Power of kappa in the gate's evidence of a placement (``kappa ** EVIDENCE_POWER * sqrt(cells)``).
EVIDENCE_POWER: float = 2.0
#: Fewer independent patches of terrain than this in the overlap (:attr:`Registration.patches`)
#: and a placement is weakly supported: said beside it, not refused.
FEW_PATCHES: float = 10.0
#: The longest lag (cells) :func:`correlation_area` sums the autocorrelation over.
MAX_LAG: int = 32
#: Side (cells) the coarse search reduces the larger map to, about.
COARSE_SIDE: int = 64
#: Headings of the coarse search screened at full resolution, at most.
CANDIDATES: int = 6
#: Of those, the ones refined.
REFINED: int = 3


# --------------------------------------------------------------------------- the transform


def _rotation(heading_deg: float) -> np.ndarray:
    """2x2 rotation on (row, col) coordinates, counter-clockwise as a map is drawn."""
    a = math.radians(heading_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


@dataclass(frozen=True)
class RigidTransform:
    """A rigid transform of cell coordinates: ``p_A = R(heading) p_B + (dy, dx)``.

    Parameters
    ----------
    dy : float
        Shift down the rows, in cells.
    dx : float
        Shift along the columns, in cells.
    heading_deg : float
        Counter-clockwise turn as the map is drawn (row 0 at the top), degrees in [0, 360).
    """

    dy: float = 0.0
    dx: float = 0.0
    heading_deg: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "heading_deg", float(self.heading_deg) % 360.0)

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> RigidTransform:
        """From a 3x3 homogeneous matrix on (row, col) (its rotation part must be a rotation)."""
        return cls(float(m[0, 2]), float(m[1, 2]), math.degrees(math.atan2(m[1, 0], m[0, 0])))

    def matrix(self) -> np.ndarray:
        """3x3 homogeneous matrix on (row, col) coordinates."""
        m = np.eye(3)
        m[:2, :2] = _rotation(self.heading_deg)
        m[:2, 2] = (self.dy, self.dx)
        return m

    def inverse(self) -> RigidTransform:
        """The transform from A's frame back into B's."""
        return RigidTransform.from_matrix(np.linalg.inv(self.matrix()))

    def compose(self, first: RigidTransform) -> RigidTransform:
        """``self`` after ``first``: ``p -> self(first(p))``."""
        return RigidTransform.from_matrix(self.matrix() @ first.matrix())

    def map_points(self, rc: np.ndarray) -> np.ndarray:
        """``(N, 2)`` (row, col) points of B -> the same points in A's frame."""
        rc = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
        return rc @ _rotation(self.heading_deg).T + np.array([self.dy, self.dx])

    def apply(self, classes: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Warp B's class grid into A's frame: a ``shape`` class grid, nearest neighbour
        (classes stay classes), UNKNOWN where B has no cell."""
        b = check_classes(classes, "map B")
        inv = np.linalg.inv(self.matrix())  # each output cell looks up the B cell it came from
        return ndimage.affine_transform(b, inv[:2, :2], offset=inv[:2, 2], output_shape=tuple(shape), order=0,
                                        mode="grid-constant", cval=UNKNOWN).astype(np.uint8)

    def describe(self) -> str:
        """``dx, dy, heading`` in a few words."""
        return f"dx {self.dx:+.1f}, dy {self.dy:+.1f} cells, heading {self.heading_deg:.1f} deg"


# --------------------------------------------------------------------------- the gate


@dataclass(frozen=True)
class Agreement:
    """How well two class grids in one frame agree on the cells both know.

    Parameters
    ----------
    overlap : int
        Cells known (FREE or IMPASSABLE) in both.
    agree : float
        Share of the overlap with the same class in both (0 on an empty overlap).
    chance : float
        The share expected by chance, ``sum_c pA(c) pB(c)`` over FREE and IMPASSABLE with
        each map's class frequencies on the overlap.
    kappa : float
        Cohen's kappa, ``(agree - chance) / (1 - chance)``; 0 where it is undefined (an
        empty overlap, or one class only in both maps).
    minority : int
        The fewest cells of one class in one map on the overlap: kappa rests on them (a
        few impassable cells in a free overlap say little, however well they agree).
    """

    overlap: int
    agree: float
    chance: float
    kappa: float
    minority: int = 0

    @property
    def evidence(self) -> float:
        """``kappa ** EVIDENCE_POWER * sqrt(overlap)`` (0 when kappa is not positive): how
        strongly the overlap supports the placement. Agreement on many cells is stronger
        evidence than the same agreement on a few, but neighbouring cells of a map are far
        from independent, so a large overlap of moderately similar maps (smooth blobs lying
        on smooth blobs) must not outweigh a smaller one that agrees closely: hence the
        power. A power of 4 (the search's) let slivers of 500-700 cells at kappa 0.7-0.9
        beat right placements on 4,000-6,000 cells at kappa 0.5-0.7; 2 keeps those right
        (benchmarks/registration.py).
        An overlap with fewer than :data:`MIN_CLASS_CELLS` cells of a class is no evidence (0)."""
        if self.minority < MIN_CLASS_CELLS:
            return 0.0
        return max(self.kappa, 0.0) ** EVIDENCE_POWER * math.sqrt(self.overlap)


def agreement(a: np.ndarray, b: np.ndarray) -> Agreement:
    """Agreement of two class grids of one shape on the cells both know (the gate's check)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        raise FedmapError(f"maps to compare must share a grid, got {a.shape} and {b.shape}")
    both = (a != UNKNOWN) & (b != UNKNOWN)
    n = int(both.sum())
    if n == 0:
        return Agreement(0, 0.0, 0.0, 0.0)
    ia, ib = a[both] == IMPASSABLE, b[both] == IMPASSABLE
    agree = float((ia == ib).mean())
    pa, pb = float(ia.mean()), float(ib.mean())
    chance = pa * pb + (1.0 - pa) * (1.0 - pb)
    kappa = 0.0 if chance >= 1.0 - 1e-12 else (agree - chance) / (1.0 - chance)
    minority = min(int(ia.sum()), n - int(ia.sum()), int(ib.sum()), n - int(ib.sum()))
    return Agreement(n, agree, chance, float(kappa), minority)


@dataclass(frozen=True)
class Registration:
    """An estimate of the transform from B's frame into A's, and the gate's verdict on it.

    Parameters
    ----------
    transform : RigidTransform
        The best estimate found (also when refused).
    check : Agreement
        The gate's independent check of ``transform``: the overlap, agreement and kappa.
    margin : float
        The estimate's :attr:`Agreement.evidence` minus that of the best placement the
        search found elsewhere (another heading, or the overlap's middle moved; 0 evidence
        when every candidate led to the same placement).
    accepted : bool
        True when the gate passed: see :func:`gate_verdict`.
    reason : str
        Why it was refused (empty when accepted).
    seconds : float
        Wall time of the registration.
    patches : float
        About how many independent patches of terrain the overlap holds: its cells over the
        two maps' :func:`correlation_area` (their geometric mean). Neighbouring cells of a
        smooth map say the same thing, so 4,000 shared cells of a map whose features span
        20 cells are a few patches, and a look-alike place can fit as well as the true one
        (a window of Hadley 118 m was placed on another window of it that it never met, at
        kappa 0.72 on 4,309 cells: 6.8 patches). Below :data:`FEW_PATCHES` the placement is
        flagged, not refused: most right placements on such maps are also there.
    """

    transform: RigidTransform
    check: Agreement
    margin: float
    accepted: bool
    reason: str = ""
    seconds: float = 0.0
    patches: float = math.inf

    @property
    def weak(self) -> bool:
        """True when the overlap holds fewer than :data:`FEW_PATCHES` independent patches."""
        return self.patches < FEW_PATCHES

    @property
    def confidence(self) -> float:
        """The gate's confidence: Cohen's kappa on the overlap."""
        return self.check.kappa


def correlation_area(classes: np.ndarray, max_lag: int = MAX_LAG) -> float:
    """The area (cells) over which a class map's known cells resemble each other: the sum
    of the autocorrelation of its impassable indicator (over its known cells) at every lag
    ``(dy, dx)`` closer than the first distance at which the autocorrelation's mean over a
    ring of lags falls to zero or below (at most ``max_lag``). White noise gives about 1; a
    map of blobs ``s`` cells across about ``s^2``. A sample of ``n`` cells of the map holds
    about ``n / area`` independent ones (the effective sample size of an autocorrelated
    field). A map with one class only, or nothing known, gives 1.

    The autocorrelation at a lag is the mean product of the centred indicator over the pairs
    of known cells that lag apart, over its variance (masked, by FFT: :mod:`scipy.fft`); lags
    with fewer than 50 such pairs count as 0."""
    classes = check_classes(classes, "map")
    known = (classes != UNKNOWN).astype(np.float64)
    n = known.sum()
    x = (classes == IMPASSABLE) * known
    p = x.sum() / n if n else 0.0
    if not 0.0 < p < 1.0:
        return 1.0
    centred = (x - p) * known
    h, w = classes.shape
    size = (2 * h, 2 * w)  # no wrap-around: every lag's pairs are real pairs
    f, m = fft.rfft2(centred, size), fft.rfft2(known, size)
    products = fft.irfft2(f * np.conj(f), size)
    pairs = fft.irfft2(m * np.conj(m), size)
    lag = min(max_lag, h - 1, w - 1)
    dy, dx = np.mgrid[-lag:lag + 1, -lag:lag + 1]
    prod, cnt = products[dy, dx], np.rint(pairs[dy, dx])  # negative lags wrap to the far end
    rho = np.where(cnt >= 50, prod / np.maximum(cnt, 1.0) / (p * (1.0 - p)), 0.0)
    ring = np.rint(np.hypot(dy, dx)).astype(int)
    means = ndimage.mean(rho, labels=ring, index=np.arange(lag + 1))
    below = np.nonzero(np.asarray(means) <= 0.0)[0]
    cut = int(below[0]) if below.size else lag + 1
    return max(float(rho[ring < cut].sum()), 1.0)


def gate_verdict(check: Agreement, margin: float = math.inf, *, gate: float = DEFAULT_GATE,
                 min_overlap: int = DEFAULT_MIN_OVERLAP, min_margin: float = DEFAULT_MARGIN) -> tuple[bool, str]:
    """``(accepted, reason)``: the gate passes when the maps share at least ``min_overlap``
    known cells holding at least :data:`MIN_CLASS_CELLS` cells of each class in each map,
    their kappa reaches ``gate`` and the placement's evidence exceeds that of any other
    placement the search found by ``min_margin``."""
    if check.overlap < min_overlap:
        return False, f"the maps share {check.overlap} known cells under the best estimate, fewer than {min_overlap}"
    if check.minority < MIN_CLASS_CELLS:
        return False, (f"the shared cells hold {check.minority} cells of one class in one map, fewer than "
                       f"{MIN_CLASS_CELLS}: too little to register on")
    if check.kappa < gate:
        return False, f"confidence {check.kappa:.2f} is below the gate {gate:.2f} ({check.overlap} shared cells)"
    if margin < min_margin:
        return False, (f"ambiguous: another placement fits almost as well (evidence margin {margin:.1f}, "
                       f"needs {min_margin:g})")
    return True, ""


def _check_options(gate: float, min_overlap: int, heading_step: float) -> None:
    if not (isinstance(gate, (int, float)) and -1.0 <= gate <= 1.0):
        raise FedmapError(f"the confidence gate must be in [-1, 1] (a kappa), got {gate!r}")
    if isinstance(min_overlap, bool) or not isinstance(min_overlap, (int, np.integer)) or min_overlap < 1:
        raise FedmapError(f"min_overlap must be a positive number of cells, got {min_overlap!r}")
    if not (isinstance(heading_step, (int, float)) and 0.1 <= heading_step <= 10.0):
        raise FedmapError(f"heading_step must be in [0.1, 10] degrees, got {heading_step!r}")


# --------------------------------------------------------------------------- the search


@dataclass
class _Level:
    """One pyramid level of a map: per block, the share of its cells that are impassable
    and that are known (both in [0, 1]); ``factor`` cells a side per block."""

    imp: np.ndarray  # (h, w) float32
    kn: np.ndarray  # (h, w) float32
    factor: int

    @property
    def mask(self) -> np.ndarray:
        return self.kn >= 0.5

    @property
    def value(self) -> np.ndarray:
        return np.where(self.kn > 0, self.imp / np.maximum(self.kn, 1e-9), 0.0)


def _level(classes: np.ndarray, factor: int) -> _Level:
    h, w = classes.shape
    H, W = -(-h // factor) * factor, -(-w // factor) * factor
    c = np.full((H, W), UNKNOWN, dtype=np.uint8)
    c[:h, :w] = classes
    shape = (H // factor, factor, W // factor, factor)
    imp = (c == IMPASSABLE).reshape(shape).mean(axis=(1, 3), dtype=np.float64)
    kn = (c != UNKNOWN).reshape(shape).mean(axis=(1, 3), dtype=np.float64)
    return _Level(imp.astype(np.float32), kn.astype(np.float32), factor)


@dataclass(frozen=True)
class _Geometry:
    """Where B's cells land on the square canvas B is turned on: canvas cell ``o`` holds B
    cell ``R(heading)^T (o - c_o) + c_b``, so B cell ``p`` lies at ``R (p - c_b) + c_o``."""

    side: int
    c_b: np.ndarray
    c_o: np.ndarray

    @classmethod
    def of(cls, shape: tuple[int, int]) -> _Geometry:
        side = int(math.ceil(math.hypot(*shape))) + 2  # holds B at any heading
        return cls(side, np.array([(shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0]), np.full(2, (side - 1) / 2.0))

    def transform(self, heading: float, shift: np.ndarray, factor: int) -> RigidTransform:
        """Full-resolution transform of the canvas at ``heading`` placed at ``shift`` (level
        cells: canvas cell o lands on A's level cell o + shift)."""
        r = _rotation(heading)
        t_level = self.c_o + shift - r @ self.c_b
        # level cell i covers full cells factor*i .. factor*i + factor - 1: p_full = factor p_level + (factor - 1)/2
        half = np.full(2, (factor - 1) / 2.0)
        t = factor * t_level + (np.eye(2) - r) @ half
        return RigidTransform(float(t[0]), float(t[1]), heading)

    def shift(self, transform: RigidTransform, heading: float, factor: int) -> np.ndarray:
        """The shift (level cells) of the canvas at ``heading`` that best matches ``transform``'s translation."""
        r = _rotation(heading)
        half = np.full(2, (factor - 1) / 2.0)
        t_level = (np.array([transform.dy, transform.dx]) - (np.eye(2) - r) @ half) / factor
        return t_level - self.c_o + r @ self.c_b


def _canvases(level: _Level, geo: _Geometry, headings) -> tuple[np.ndarray, np.ndarray]:
    """B's level turned by each heading: values and masks, ``(k, side, side)`` each."""
    headings = np.atleast_1d(np.asarray(headings, dtype=np.float64))
    o = np.mgrid[0:geo.side, 0:geo.side].reshape(2, -1) - geo.c_o[:, None]  # (2, side^2) about the canvas centre
    coords = np.concatenate([_rotation(h).T @ o + geo.c_b[:, None] for h in headings], axis=1)
    shape = (len(headings), geo.side, geo.side)
    if level.factor == 1:  # at full resolution classes stay classes: nearest neighbour, one lookup
        classes = np.where(level.kn > 0, np.where(level.imp > 0, IMPASSABLE, FREE), UNKNOWN).astype(np.uint8)
        c = ndimage.map_coordinates(classes, coords, order=0, mode="grid-constant", cval=UNKNOWN).reshape(shape)
        return (c == IMPASSABLE).astype(np.float32), c != UNKNOWN
    look = lambda a: ndimage.map_coordinates(a, coords, order=1, mode="grid-constant", cval=0.0).reshape(shape)
    imp, kn = look(level.imp), look(level.kn)
    mask = kn >= 0.5
    value = np.where(mask, imp / np.maximum(kn, 1e-6), 0.0).astype(np.float32)
    return value, mask


def _ncc_z(n, sa, sb, sab, sa2, sb2, n_min: float) -> np.ndarray:
    """``ncc * sqrt(n)`` from the overlap sums; -inf where the overlap is under ``n_min``
    or either side is (nearly) constant on it."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        nn = np.maximum(n, 1e-6)
        va = sa2 - sa * sa / nn
        vb = sb2 - sb * sb / nn
        ncc = (sab - sa * sb / nn) / np.sqrt(np.maximum(va * vb, 1e-12))
        z = np.sign(ncc) * np.abs(ncc) ** SHARPNESS * np.sqrt(nn)
    ok = (n >= n_min) & (va > 1e-3 * nn) & (vb > 1e-3 * nn)
    return np.where(ok, z, -np.inf)


class _Reference:
    """Map A at one level, with the spectra a dense masked correlation needs (computed once)."""

    def __init__(self, level: _Level, side: int) -> None:
        h, w = level.imp.shape
        self.shape = (h, w)
        self.pad = (fft.next_fast_len(h + side - 1, real=True), fft.next_fast_len(w + side - 1, real=True))
        m = level.mask.astype(np.float32)
        v = (level.value * m).astype(np.float32)
        self.fields = (m, v, v * v)
        self.binary = level.factor == 1
        self.spectra = [fft.rfft2(f, s=self.pad, workers=-1) for f in self.fields]

    def dense(self, value: np.ndarray, mask: np.ndarray, n_min: float) -> tuple[np.ndarray, np.ndarray]:
        """For each canvas of a stack, the best score over every shift and that shift
        (canvas cell o lands on A cell o + shift): ``(k,)`` and ``(k, 2)``."""
        m = mask.astype(np.float32)
        v = value * m
        fm, fv, fv2 = (np.conj(fft.rfft2(f, s=self.pad, axes=(-2, -1), workers=-1)) for f in (m, v, v * v))
        am, av, av2 = self.spectra
        corr = lambda x, y: fft.irfft2(x * y, s=self.pad, axes=(-2, -1), workers=-1)
        n = np.rint(corr(am, fm))
        z = _ncc_z(n, corr(av, fm), corr(am, fv), corr(av, fv), corr(av2, fm), corr(am, fv2), n_min)
        flat = z.reshape(len(z), -1)
        k = np.argmax(flat, axis=1)
        kr, kc = np.unravel_index(k, z.shape[1:])
        # circular index -> shift: indices past A's extent are negative shifts
        shifts = np.stack([np.where(kr < self.shape[0], kr, kr - self.pad[0]),
                           np.where(kc < self.shape[1], kc, kc - self.pad[1])], axis=1).astype(np.float64)
        return flat[np.arange(len(flat)), k], shifts

    def local(self, value: np.ndarray, mask: np.ndarray, centre: np.ndarray, radius: int,
              n_min: float) -> tuple[float, np.ndarray]:
        """Best score and shift within ``radius`` cells of ``centre`` (direct sums), the shift
        refined below a cell by a parabola through the scores beside the best."""
        a_m, a_v, a_v2 = self.fields
        b_m = mask.astype(np.float32)
        b_v = value * b_m
        h, w = self.shape
        side = mask.shape[0]
        c0 = np.rint(centre).astype(int)
        z = np.full((2 * radius + 1, 2 * radius + 1), -np.inf)
        for i, dr in enumerate(range(-radius, radius + 1)):
            for j, dc in enumerate(range(-radius, radius + 1)):
                sr, sc = int(c0[0] + dr), int(c0[1] + dc)
                r0, r1, q0, q1 = max(0, sr), min(h, sr + side), max(0, sc), min(w, sc + side)
                if r1 <= r0 or q1 <= q0:
                    continue
                wa = (slice(r0, r1), slice(q0, q1))
                wb = (slice(r0 - sr, r1 - sr), slice(q0 - sc, q1 - sc))
                bm, bv = b_m[wb], b_v[wb]
                sa, sb = np.sum(a_v[wa] * bm), np.sum(a_m[wa] * bv)  # at full resolution values are 0/1: squares too
                n, sab = (np.sum(a_m[wa] * bm), np.sum(a_v[wa] * bv))
                sa2, sb2 = (sa, sb) if self.binary else (np.sum(a_v2[wa] * bm), np.sum(a_m[wa] * bv * bv))
                z[i, j] = float(_ncc_z(n, sa, sb, sab, sa2, sb2, n_min))
        bi, bj = (int(k) for k in np.unravel_index(int(np.argmax(z)), z.shape))
        best = float(z[bi, bj])
        shift = np.array([c0[0] + bi - radius, c0[1] + bj - radius], dtype=np.float64)
        # below a cell: the vertex of the parabola through the best score and its two neighbours, per axis
        for axis, (lo, hi) in enumerate(((z[bi - 1, bj], z[bi + 1, bj]) if 0 < bi < 2 * radius else (None, None),
                                         (z[bi, bj - 1], z[bi, bj + 1]) if 0 < bj < 2 * radius else (None, None))):
            if lo is not None and hi is not None and np.isfinite(lo) and np.isfinite(hi) and lo - 2 * best + hi < 0:
                shift[axis] += float(np.clip(0.5 * (lo - hi) / (lo - 2 * best + hi), -0.5, 0.5))
        return best, shift


def _headings(step: float) -> np.ndarray:
    return np.arange(0.0, 360.0, step)


def _angle_gap(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def _turned(t: RigidTransform, heading: float, pivot: np.ndarray) -> RigidTransform:
    """``t`` turned to ``heading`` about B's cell ``pivot``, which stays where ``t`` puts it."""
    at = t.map_points(pivot)[0] - _rotation(heading) @ pivot
    return RigidTransform(float(at[0]), float(at[1]), heading)


def _pivot(a: np.ndarray, b: np.ndarray, t: RigidTransform) -> np.ndarray:
    """Centroid of B's known cells that ``t`` puts on A's known cells (B's centre if none)."""
    rc = np.argwhere(b != UNKNOWN)
    at = np.rint(t.map_points(rc)).astype(int)
    inside = (at[:, 0] >= 0) & (at[:, 0] < a.shape[0]) & (at[:, 1] >= 0) & (at[:, 1] < a.shape[1])
    on = np.zeros(len(rc), dtype=bool)
    on[inside] = a[at[inside, 0], at[inside, 1]] != UNKNOWN
    return rc[on].mean(axis=0) if on.any() else np.array([(b.shape[0] - 1) / 2.0, (b.shape[1] - 1) / 2.0])


def _refine(ref: _Reference, level_b: _Level, start: RigidTransform, pivot: np.ndarray, span: float, step: float,
            radius: int, n_min: float, rounds: int = 4) -> tuple[float, RigidTransform]:
    """Search headings ``start +- span`` by ``step`` (turning about ``pivot``, B's cell at the
    middle of the overlap) and shifts within ``radius`` at one level; while the best
    heading is at the edge of the span, search again around it (a few times)."""
    geo = _Geometry.of(level_b.imp.shape)
    best_z, best_t = -np.inf, start
    for _ in range(rounds):
        centre = best_t
        headings = centre.heading_deg + np.arange(-span, span + step / 2, step)
        values, masks = _canvases(level_b, geo, headings)
        for heading, value, mask in zip(headings, values, masks):
            guess = geo.shift(_turned(centre, float(heading), pivot), float(heading), level_b.factor)
            z, shift = ref.local(value, mask, guess, radius, n_min)
            if z > best_z:
                best_z, best_t = z, geo.transform(float(heading), shift, level_b.factor)
        if _angle_gap(best_t.heading_deg, centre.heading_deg) < span - step / 2:
            break
    return best_z, best_t


def _search(a: np.ndarray, b: np.ndarray, *, min_overlap: int = DEFAULT_MIN_OVERLAP,
            heading_step: float = 2.0) -> tuple[list[RigidTransform], list[RigidTransform]]:
    """The refined placements, best first, and the other candidates the search screened."""
    _check_options(DEFAULT_GATE, min_overlap, heading_step)
    factor = max(1, int(round(max(*a.shape, *b.shape) / COARSE_SIDE)))
    factors = [factor]
    while factors[-1] > 1:
        factors.append(max(1, factors[-1] // 2))
    levels_a = {f: _level(a, f) for f in factors}
    levels_b = {f: _level(b, f) for f in factors}
    refs = {f: _Reference(levels_a[f], _Geometry.of(levels_b[f].imp.shape).side) for f in factors}

    # 1. coarse: every heading, every shift
    geo = _Geometry.of(levels_b[factor].imp.shape)
    headings = _headings(heading_step)
    scores, shifts = [], []
    for chunk in np.array_split(headings, max(1, len(headings) // 24)):
        z, s = refs[factor].dense(*_canvases(levels_b[factor], geo, chunk), min_overlap / factor**2)
        scores.append(z)
        shifts.append(s)
    score, shift = np.concatenate(scores), np.concatenate(shifts)
    candidates: list[RigidTransform] = []
    for k in np.argsort(-score, kind="stable"):
        if not np.isfinite(score[k]):
            break
        if all(_angle_gap(headings[k], c.heading_deg) >= 10.0 for c in candidates):
            candidates.append(geo.transform(float(headings[k]), shift[k], factor))
        if len(candidates) == CANDIDATES:
            break
    if not candidates:  # no alignment shares min_overlap cells with two classes on each side
        return [RigidTransform()], []

    # 2. screen the candidates at full resolution (three headings, a small window), then
    # refine the best few down the pyramid, halving the heading step at each level
    screened = [_refine(refs[1], levels_b[1], t, _pivot(a, b, t), span=heading_step / 2, step=heading_step / 2,
                        radius=factor + 1, n_min=min_overlap, rounds=1) for t in candidates]
    screened.sort(key=lambda zt: -zt[0])
    refined = []
    for _, t in screened[:REFINED]:
        step = heading_step
        for f in factors[1:]:
            _, t = _refine(refs[f], levels_b[f], t, _pivot(a, b, t), span=1.5 * step, step=step / 2, radius=2,
                           n_min=min_overlap / f**2)
            step /= 2
        refined.append(_refine(refs[1], levels_b[1], t, _pivot(a, b, t), span=step / 2, step=step / 4, radius=1,
                               n_min=min_overlap))
    refined.sort(key=lambda zt: -zt[0])
    return [t for _, t in refined], [t for _, t in screened[REFINED:]]


def estimate_transform(a: np.ndarray, b: np.ndarray, *, min_overlap: int = DEFAULT_MIN_OVERLAP,
                       heading_step: float = 2.0) -> RigidTransform:
    """The rigid transform that best carries class grid ``b`` into ``a``'s frame (no gate:
    see :func:`register`). See the module docstring for the search.

    Parameters
    ----------
    a, b : ndarray (H, W) uint8
        Class grids (FREE, IMPASSABLE, UNKNOWN) with the same cell size.
    min_overlap : int
        Known cells an alignment must share to be considered.
    heading_step : float
        Heading grid of the coarse search, degrees.
    """
    return _search(check_classes(a, "map A"), check_classes(b, "map B"), min_overlap=min_overlap,
                   heading_step=heading_step)[0][0]


def _half_cell(ca: np.ndarray, cb: np.ndarray, check: Agreement,
               transform: RigidTransform) -> tuple[Agreement, RigidTransform]:
    """The estimate moved by half a cell along either axis where B's cells then land on A's
    better (more evidence). The search's shift can sit on a cell boundary: nearest-neighbour
    warping then rounds a whole map one cell either way (exact cuts turned by 90 or 180
    degrees were placed one cell off, kappa 0.6 where the true placement gives 1.0)."""
    best = (check, transform)
    for dy in (-0.5, 0.0, 0.5):
        for dx in (-0.5, 0.0, 0.5):
            if dy or dx:
                u = RigidTransform(transform.dy + dy, transform.dx + dx, transform.heading_deg)
                c = agreement(ca, u.apply(cb, ca.shape))
                if c.evidence > best[0].evidence:
                    best = (c, u)
    return best


def _distinct(t: RigidTransform, u: RigidTransform, pivot: np.ndarray) -> bool:
    """True when ``u`` places B elsewhere than ``t`` does: another heading (more than
    :data:`DISTINCT_DEG`) or the middle of the overlap more than :data:`DISTINCT_CELLS` away."""
    moved = float(np.linalg.norm(t.map_points(pivot) - u.map_points(pivot)))
    return _angle_gap(t.heading_deg, u.heading_deg) > DISTINCT_DEG or moved > DISTINCT_CELLS


def _classes(m, what: str) -> tuple[np.ndarray, float | None]:
    if isinstance(m, GridMap):
        return m.classes, m.pixel_size
    return check_classes(m, what), None


def register(a, b, *, gate: float = DEFAULT_GATE, min_overlap: int = DEFAULT_MIN_OVERLAP,
             min_margin: float = DEFAULT_MARGIN, heading_step: float = 2.0) -> Registration:
    """Estimate the transform from map ``b``'s frame into map ``a``'s and gate it.

    Parameters
    ----------
    a, b : GridMap or ndarray (H, W)
        Class maps; two GridMaps must have the same cell size (within 1 %).
    gate : float
        Cohen's kappa the estimate must reach on the overlap to be accepted.
    min_overlap : int
        Known cells the two maps must share under the estimate.
    min_margin : float
        How much more evidence (:attr:`Agreement.evidence`) than the best other placement
        the search found the estimate must have.
    heading_step : float
        Heading grid of the coarse search, degrees.

    Returns
    -------
    Registration
        The estimate, the gate's check of it and the verdict (refused with a reason below
        the gate: never merge a refused estimate).
    """
    t0 = time.perf_counter()
    (ca, pa), (cb, pb) = _classes(a, "map A"), _classes(b, "map B")
    if pa is not None and pb is not None and abs(pa - pb) > 0.01 * min(pa, pb):
        raise FedmapError(f"maps to register must have the same cell size, got {pa:g} m and {pb:g} m")
    _check_options(gate, min_overlap, heading_step)
    if not (isinstance(min_margin, (int, float)) and min_margin >= 0.0):
        raise FedmapError(f"min_margin must be a non-negative number, got {min_margin!r}")
    refined, screened = _search(ca, cb, min_overlap=min_overlap, heading_step=heading_step)
    # the gate's check: B warped into A's frame by each placement, compared cell by cell
    checks = [(agreement(ca, t.apply(cb, ca.shape)), t) for t in refined + screened]
    check, transform = max(checks[:len(refined)], key=lambda ct: ct[0].evidence)
    check, transform = _half_cell(ca, cb, check, transform)
    pivot = _pivot(ca, cb, transform)
    others = [c.evidence for c, t in checks if _distinct(transform, t, pivot)]
    margin = check.evidence - max(others, default=0.0)
    accepted, reason = gate_verdict(check, margin, gate=gate, min_overlap=min_overlap, min_margin=min_margin)
    patches = check.overlap / math.sqrt(correlation_area(ca) * correlation_area(cb))
    return Registration(transform, check, margin, accepted, reason, time.perf_counter() - t0, patches)


# --------------------------------------------------------------------------- merging


def combine(base: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Two class grids of one frame as one: a cell known in one map takes its class; a
    cell known in both is IMPASSABLE if either says so (FREE never covers a hazard)."""
    base, new = np.asarray(base), np.asarray(new)
    out = np.where(base == UNKNOWN, new, base)
    out[(base == IMPASSABLE) | (new == IMPASSABLE)] = IMPASSABLE
    return out.astype(np.uint8)


@dataclass(frozen=True)
class Placement:
    """What :func:`merge` did with one input map.

    Parameters
    ----------
    index : int
        Position of the map in the input.
    source : str
        The map's source (its file, for maps read from files).
    placed : bool
        True when the map is in the merged map.
    transform : RigidTransform or None
        From this map's frame into the first map's frame (identity for the first map);
        None when no estimate was made.
    registration : Registration or None
        The registration against the merged map (None for the first map).
    reason : str
        Why the map was refused (empty when placed).
    changed : int
        Cells the merged map knew before this map was placed whose class it changed (a free
        cell it says is impassable: impassable wins); 0 for the first map and refused ones.
    """

    index: int
    source: str
    placed: bool
    transform: RigidTransform | None
    registration: Registration | None = None
    reason: str = ""
    changed: int = 0

    @property
    def confidence(self) -> float | None:
        return None if self.registration is None else self.registration.confidence


@dataclass(frozen=True)
class MergeResult:
    """The merged map (in the first map's frame, grown to hold every placed map) and one
    :class:`Placement` per input map, in input order. ``origin`` is the (row, col) of the
    first map's cell (0, 0) on the merged grid."""

    grid: GridMap
    placements: tuple[Placement, ...]
    origin: tuple[int, int] = field(default=(0, 0))

    @property
    def n_placed(self) -> int:
        return sum(p.placed for p in self.placements)


def _footprint(transform: RigidTransform, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (min, max) of a ``shape`` grid's cell corners under ``transform``."""
    h, w = shape
    corners = np.array([[-0.5, -0.5], [-0.5, w - 0.5], [h - 0.5, -0.5], [h - 0.5, w - 0.5]])
    pts = transform.map_points(corners)
    return pts.min(axis=0), pts.max(axis=0)


def merge(maps, *, gate: float = DEFAULT_GATE, min_overlap: int = DEFAULT_MIN_OVERLAP,
          min_margin: float = DEFAULT_MARGIN, heading_step: float = 2.0) -> MergeResult:
    """Merge class maps in unknown frames into the first map's frame.

    Parameters
    ----------
    maps : sequence of GridMap
        Two or more maps of one cell size; the first one's frame is the merged map's.
    gate, min_overlap, min_margin, heading_step
        As in :func:`register`.

    Returns
    -------
    MergeResult
        The merged map, grown to hold every placed map (UNKNOWN where no map is), with
        the first map's georeferencing moved to the grown grid, and per input map its
        transform, confidence and whether it was placed or refused (and why).
    """
    maps = list(maps)
    if len(maps) < 2:
        raise FedmapError(f"merging needs at least two maps, got {len(maps)}")
    for i, m in enumerate(maps):
        if not isinstance(m, GridMap):
            raise FedmapError(f"map {i} is not a GridMap")
    first = maps[0]
    for i, m in enumerate(maps[1:], start=1):
        if abs(m.pixel_size - first.pixel_size) > 0.01 * min(m.pixel_size, first.pixel_size):
            raise FedmapError(f"map {i} ({m.source or 'unnamed'}) has {m.pixel_size:g} m cells, map 0 has "
                              f"{first.pixel_size:g} m: resample it first")
    _check_options(gate, min_overlap, heading_step)
    canvas = first.classes.copy()
    origin = np.zeros(2, dtype=int)  # (row, col) of map 0's cell (0, 0) on the canvas
    results: dict[int, Placement] = {0: Placement(0, first.source, True, RigidTransform())}
    pending = list(range(1, len(maps)))
    last: dict[int, Registration] = {}
    progress = True
    while pending and progress:  # a map refused now may overlap one placed later
        progress = False
        for i in list(pending):
            reg = register(canvas, maps[i].classes, gate=gate, min_overlap=min_overlap, min_margin=min_margin,
                           heading_step=heading_step)
            last[i] = reg
            if not reg.accepted:
                continue
            lo, hi = _footprint(reg.transform, maps[i].shape)  # the cells whose centres B covers
            grow_lo = np.maximum(0, -np.ceil(lo - 1e-9).astype(int))
            grow_hi = np.maximum(0, np.floor(hi + 1e-9).astype(int) + 1 - np.array(canvas.shape))
            if grow_lo.any() or grow_hi.any():
                bigger = np.full((canvas.shape[0] + grow_lo[0] + grow_hi[0], canvas.shape[1] + grow_lo[1] + grow_hi[1]),
                                 UNKNOWN, dtype=np.uint8)
                bigger[grow_lo[0]:grow_lo[0] + canvas.shape[0], grow_lo[1]:grow_lo[1] + canvas.shape[1]] = canvas
                canvas, origin = bigger, origin + grow_lo
            on_canvas = RigidTransform(reg.transform.dy + grow_lo[0], reg.transform.dx + grow_lo[1],
                                       reg.transform.heading_deg)
            merged = combine(canvas, on_canvas.apply(maps[i].classes, canvas.shape))
            changed = int(((canvas != UNKNOWN) & (merged != canvas)).sum())
            canvas = merged
            to_first = RigidTransform(on_canvas.dy - origin[0], on_canvas.dx - origin[1], on_canvas.heading_deg)
            results[i] = Placement(i, maps[i].source, True, to_first, reg, changed=changed)
            pending.remove(i)
            progress = True
    for i in pending:
        reg = last[i]
        t = RigidTransform(reg.transform.dy - origin[0], reg.transform.dx - origin[1], reg.transform.heading_deg)
        results[i] = Placement(i, maps[i].source, False, t, reg, reg.reason)
    meta = {"merged_from": [m.source for m in maps], "origin_of_first": [int(v) for v in origin]}
    grid = GridMap(canvas, first.pixel_size, "merge(" + ", ".join(m.source or "?" for m in maps) + ")", meta,
                   transform=crop_transform(first.transform, -int(origin[0]), -int(origin[1])), crs=first.crs)
    return MergeResult(grid, tuple(results[i] for i in range(len(maps))), (int(origin[0]), int(origin[1])))


__all__ = ["DEFAULT_GATE", "DEFAULT_MIN_OVERLAP", "FEW_PATCHES", "Agreement", "MergeResult",
           "Placement", "Registration", "RigidTransform", "agreement", "combine", "correlation_area", "estimate_transform",
           "gate_verdict", "merge", "register"]
