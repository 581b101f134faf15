"""Image metrics of a learned map against ground truth.

PSNR and SSIM are computed on the **RGB renderings in the paper's colours** (free green,
impassable red, unknown grey), float in [0, 1], with ``data_range=1``; SSIM uses
scikit-image's defaults (7x7 uniform window) over the 3 channels (``channel_axis=-1``).
A raw network output can be scored directly (:func:`psnr`, :func:`ssim`) or after it is
snapped to classes (:func:`image_scores`, what a planner uses and every run reports), which
computes the renderings' figures from the classes without rendering them.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from fedmap._util import compiled_once, cpu_cores
from fedmap.errors import FedmapError
from fedmap.maps.grid import PALETTE


def _check(truth_rgb: np.ndarray, pred_rgb: np.ndarray) -> None:
    if truth_rgb.shape != pred_rgb.shape:
        raise FedmapError(f"learned map {pred_rgb.shape[:2]} and ground truth {truth_rgb.shape[:2]} differ in size")
    if not np.isfinite(pred_rgb).all():
        raise FedmapError("learned map contains NaN or infinite values")
    if not np.isfinite(truth_rgb).all():
        raise FedmapError("ground truth contains NaN or infinite values")


def psnr(truth_rgb: np.ndarray, pred_rgb: np.ndarray) -> float:
    """PSNR in dB with data range 1 (``inf`` for identical maps)."""
    truth_rgb = np.asarray(truth_rgb, dtype=np.float64)
    pred_rgb = np.asarray(pred_rgb, dtype=np.float64)
    _check(truth_rgb, pred_rgb)
    if np.array_equal(truth_rgb, pred_rgb):
        return float("inf")
    from skimage.metrics import peak_signal_noise_ratio  # here: it imports scipy.stats (0.6 s of every command)

    return float(peak_signal_noise_ratio(truth_rgb, pred_rgb, data_range=1.0))


def ssim(truth_rgb: np.ndarray, pred_rgb: np.ndarray) -> float:
    """Mean SSIM over the RGB channels with data range 1."""
    truth_rgb = np.asarray(truth_rgb, dtype=np.float64)
    pred_rgb = np.asarray(pred_rgb, dtype=np.float64)
    _check(truth_rgb, pred_rgb)
    _check_window(*truth_rgb.shape[:2])
    from skimage.metrics import structural_similarity  # here: see psnr

    return float(structural_similarity(truth_rgb, pred_rgb, data_range=1.0, channel_axis=-1))


def class_scores(truth: np.ndarray, pred: np.ndarray) -> dict:
    """Cell accuracy and per-class IoU of two class maps."""
    return _class_scores(_confusion(*_class_maps(truth, pred)))


def image_scores(truth_classes: np.ndarray, pred_classes: np.ndarray) -> dict:
    """PSNR, SSIM (on renderings) and class scores of a class map against the truth.

    The same figures as :func:`psnr` and :func:`ssim` of the two :func:`render_classes`
    renderings (to rounding: equal within 1e-12), computed from the classes: PSNR from the
    3x3 confusion counts, SSIM by :func:`_ssim_rows` from exact integer window sums, with
    no rendering made: 0.67 s for a 4096² map on 2 cores, against 17.3 s for the renderings'.
    """
    t, p = _class_maps(truth_classes, pred_classes)
    counts = _confusion(t, p)
    d2 = ((PALETTE[:, None, :].astype(np.float64) - PALETTE[None, :, :].astype(np.float64)) ** 2).sum(-1)
    mse = float((counts * d2).sum()) / (t.size * 3)
    value = float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))
    return {"psnr": value, "ssim": _ssim_classes(t, p), **_class_scores(counts)}


def _class_maps(truth: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    truth, pred = np.asarray(truth), np.asarray(pred)
    if truth.shape != pred.shape:
        raise FedmapError(f"learned map {pred.shape} and ground truth {truth.shape} differ in size")
    out = []
    for name, m in (("ground truth", truth), ("learned map", pred)):
        if m.ndim != 2:
            raise FedmapError(f"the {name} must be a (H, W) class map, got shape {m.shape}")
        if m.size and (m.min() < 0 or m.max() >= len(PALETTE)):
            raise FedmapError(f"the {name} holds values other than the classes 0..{len(PALETTE) - 1}")
        out.append(np.ascontiguousarray(m, dtype=np.uint8))
    return out[0], out[1]


def _confusion(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """counts[k, l]: cells of class k in the truth and l in the learned map."""
    k = len(PALETTE)
    return np.bincount((t.astype(np.intp) * k + p).ravel(), minlength=k * k).reshape(k, k)


def _class_scores(counts: np.ndarray) -> dict:
    out = {"accuracy": float(np.trace(counts) / counts.sum())}
    for value, name in ((0, "free"), (1, "impassable")):
        inter = counts[value, value]
        union = counts[value, :].sum() + counts[:, value].sum() - inter
        out[f"iou_{name}"] = float(inter / union) if union else 1.0
    return out


def _ssim_classes(t: np.ndarray, p: np.ndarray) -> float:
    """:func:`ssim` of the renderings of class maps ``t`` and ``p`` (uint8, same shape)."""
    h, w = t.shape
    _check_window(h, w)
    twice = _TWICE_COLOUR
    rows = h - SSIM_WINDOW + 1
    sums = np.zeros((3, rows))
    kernel = _ssim_kernel()
    parts = max(1, min(cpu_cores(), rows // 64))
    bounds = np.linspace(0, rows, parts + 1).astype(int)
    if parts == 1:
        kernel(t, p, twice, 0, rows, sums)
    else:
        with ThreadPoolExecutor(parts) as pool:
            list(pool.map(lambda k: kernel(t, p, twice, bounds[k], bounds[k + 1], sums), range(parts)))
    return float(np.mean(sums.sum(axis=1) / (rows * (w - SSIM_WINDOW + 1))))


#: SSIM's window side (scikit-image's default uniform window).
SSIM_WINDOW = 7

#: Twice each class's colour, channel x class: integers, as :func:`_ssim_rows` needs.
_TWICE_COLOUR = np.rint(2 * PALETTE.T.astype(np.float64)).astype(np.int64)
assert np.array_equal(_TWICE_COLOUR, 2 * PALETTE.T.astype(np.float64)), "SSIM from classes needs colours in halves"


def _check_window(h: int, w: int) -> None:
    if min(h, w) < SSIM_WINDOW:
        raise FedmapError(f"SSIM needs maps of at least {SSIM_WINDOW}x{SSIM_WINDOW} cells (its window), got {h}x{w}")


@compiled_once
def _ssim_kernel():
    """:func:`_ssim_rows` compiled with numba (cached on disk), releasing the GIL."""
    from numba import njit

    kernel = njit(cache=True, nogil=True)(_ssim_rows)
    tiny = np.zeros((7, 7), np.uint8)  # compiled (or loaded) here, once, not by threads racing to do it
    kernel(tiny, tiny, np.zeros((3, 3), np.int64), 0, 1, np.zeros((3, 1)))
    return kernel


def _ssim_rows(t: np.ndarray, p: np.ndarray, twice: np.ndarray, r0: int, r1: int, sums: np.ndarray) -> None:
    """Per-channel sums of the SSIM map of the renderings of ``t`` and ``p``, for the
    windows whose top row is in ``[r0, r1)``, into ``sums[channel, row]``.

    scikit-image's SSIM on the renderings, from classes: ``twice[c, k]`` is twice class
    ``k``'s colour in channel ``c`` (an integer), so every 7x7 window's sums of x, y, x²,
    y² and xy are exact integers, kept as running column and row sums; the means,
    (co)variances (sample: times 49/48), constants (K1 = 0.01, K2 = 0.03, data range 1)
    and the SSIM formula are scikit-image's. Only windows wholly inside the map (its crop).
    """
    h, w = t.shape
    n = 7
    c1 = 0.01 ** 2
    c2 = 0.03 ** 2
    norm = 49.0 / 48.0
    cols = np.zeros((3, 5, w), np.int64)  # per channel: x, y, xx, yy, xy sums of rows r..r+6
    for r in range(r0, r0 + n - 1):
        for x in range(w):
            for c in range(3):
                a, b = twice[c, t[r, x]], twice[c, p[r, x]]
                cols[c, 0, x] += a
                cols[c, 1, x] += b
                cols[c, 2, x] += a * a
                cols[c, 3, x] += b * b
                cols[c, 4, x] += a * b
    run = np.zeros((3, 5), np.int64)
    for r in range(r0, r1):
        for x in range(w):  # bring row r + 6 in, row r - 1 out
            for c in range(3):
                a, b = twice[c, t[r + n - 1, x]], twice[c, p[r + n - 1, x]]
                cols[c, 0, x] += a
                cols[c, 1, x] += b
                cols[c, 2, x] += a * a
                cols[c, 3, x] += b * b
                cols[c, 4, x] += a * b
                if r > r0:
                    a, b = twice[c, t[r - 1, x]], twice[c, p[r - 1, x]]
                    cols[c, 0, x] -= a
                    cols[c, 1, x] -= b
                    cols[c, 2, x] -= a * a
                    cols[c, 3, x] -= b * b
                    cols[c, 4, x] -= a * b
        for c in range(3):
            total = 0.0
            for q in range(5):
                run[c, q] = 0
                for x in range(n - 1):
                    run[c, q] += cols[c, q, x]
            for x in range(w - n + 1):
                for q in range(5):
                    run[c, q] += cols[c, q, x + n - 1]
                ux = run[c, 0] / 98.0
                uy = run[c, 1] / 98.0
                uxx = run[c, 2] / 196.0
                uyy = run[c, 3] / 196.0
                uxy = run[c, 4] / 196.0
                vx = norm * (uxx - ux * ux)
                vy = norm * (uyy - uy * uy)
                vxy = norm * (uxy - ux * uy)
                a1 = 2 * ux * uy + c1
                a2 = 2 * vxy + c2
                b1 = ux ** 2 + uy ** 2 + c1
                b2 = vx + vy + c2
                total += (a1 * a2) / (b1 * b2)
                for q in range(5):
                    run[c, q] -= cols[c, q, x]
            sums[c, r] = total


#: Equal-width bins of the expected calibration error (:func:`prediction_scores`).
CALIBRATION_BINS = 10


def prediction_scores(p_impassable: np.ndarray, impassable: np.ndarray) -> dict:
    """How well guesses ``p_impassable`` (P(impassable) of some cells) match the truth
    ``impassable`` (bool, the same cells): ``cells``, the truth's impassable share, accuracy
    (a guess is impassable above 1/2), impassable IoU, Brier score, expected calibration
    error over :data:`CALIBRATION_BINS` equal bins (count-weighted |frequency - mean P|),
    and an "all free" guess's accuracy beside them."""
    p = np.asarray(p_impassable, dtype=np.float64).ravel()
    y = np.asarray(impassable, dtype=bool).ravel()
    if p.shape != y.shape:
        raise FedmapError(f"{p.size} guesses for {y.size} cells")
    if not len(p):
        raise FedmapError("no cells to score the guesses on")
    guess = p > 0.5
    edges = np.linspace(0, 1, CALIBRATION_BINS + 1)
    which = np.clip(np.digitize(p, edges[1:-1]), 0, CALIBRATION_BINS - 1)
    ece = 0.0
    for i in range(CALIBRATION_BINS):
        sel = which == i
        if sel.any():
            ece += sel.mean() * abs(float(y[sel].mean()) - float(p[sel].mean()))
    union = int((guess | y).sum())
    return {"cells": int(len(p)), "impassable": float(y.mean()), "accuracy": float((guess == y).mean()),
            "iou_impassable": float((guess & y).sum() / union) if union else 1.0,
            "brier": float(np.mean((p - y) ** 2)), "ece": float(ece), "accuracy_all_free": float((~y).mean())}
