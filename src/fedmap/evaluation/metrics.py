"""Image metrics of a learned map against ground truth.

PSNR and SSIM are computed on the **RGB renderings in the paper's colours** (free green,
impassable red, unknown grey), float in [0, 1], with ``data_range=1``; SSIM uses
scikit-image's defaults (7x7 uniform window) over the 3 channels (``channel_axis=-1``).
A raw network output can be scored directly (``pred_rgb``) or after it is snapped to
classes; :func:`evaluate_map` reports the class map, which is what a planner uses.
"""

from __future__ import annotations

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from fedmap.errors import FedmapError
from fedmap.maps.grid import render_classes


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
    return float(peak_signal_noise_ratio(truth_rgb, pred_rgb, data_range=1.0))


def ssim(truth_rgb: np.ndarray, pred_rgb: np.ndarray) -> float:
    """Mean SSIM over the RGB channels with data range 1."""
    truth_rgb = np.asarray(truth_rgb, dtype=np.float64)
    pred_rgb = np.asarray(pred_rgb, dtype=np.float64)
    _check(truth_rgb, pred_rgb)
    if min(truth_rgb.shape[:2]) < 7:
        raise FedmapError("SSIM needs maps of at least 7x7 cells (its window), "
                          f"got {truth_rgb.shape[0]}x{truth_rgb.shape[1]}")
    return float(structural_similarity(truth_rgb, pred_rgb, data_range=1.0, channel_axis=-1))


def class_scores(truth: np.ndarray, pred: np.ndarray) -> dict:
    """Cell accuracy and per-class IoU of two class maps."""
    truth, pred = np.asarray(truth), np.asarray(pred)
    if truth.shape != pred.shape:
        raise FedmapError(f"learned map {pred.shape} and ground truth {truth.shape} differ in size")
    out = {"accuracy": float((truth == pred).mean())}
    for value, name in ((0, "free"), (1, "impassable")):
        inter = np.logical_and(truth == value, pred == value).sum()
        union = np.logical_or(truth == value, pred == value).sum()
        out[f"iou_{name}"] = float(inter / union) if union else 1.0
    return out


def image_scores(truth_classes: np.ndarray, pred_classes: np.ndarray) -> dict:
    """PSNR, SSIM (on renderings) and class scores of a class map against the truth."""
    t, p = render_classes(truth_classes), render_classes(pred_classes)
    return {"psnr": psnr(t, p), "ssim": ssim(t, p), **class_scores(truth_classes, pred_classes)}


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
