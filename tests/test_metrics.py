"""Tests for fedmap.evaluation.metrics: PSNR, SSIM, class scores.

References:
* PSNR: the textbook formula 10*log10(R^2 / MSE) with R = 1, evaluated here with numpy,
  plus values worked out by hand.
* SSIM: ``ref_ssim`` below, written from Wang et al. (2004) with the choices
  scikit-image's ``structural_similarity`` makes by default (which fedmap documents it
  uses): a 7x7 uniform window (``scipy.ndimage.uniform_filter``, its default 'reflect'
  border), K1 = 0.01, K2 = 0.03, data range 1, sample (co)variances (the population
  values times N/(N-1), N = 49), the SSIM map averaged over the interior only (a crop of
  (7-1)//2 = 3 cells on every side), and the mean over the 3 colour channels.
* Class scores: counted by hand on a 2x3 map.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import class_scores, image_scores, psnr, ssim
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, render_classes


def ref_ssim_channel(x: np.ndarray, y: np.ndarray, win: int = 7, data_range: float = 1.0) -> float:
    x = x.astype(np.float64)
    y = y.astype(np.float64)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    n = win * win
    norm = n / (n - 1)  # sample covariance
    mx, my = uniform_filter(x, win), uniform_filter(y, win)
    vx = norm * (uniform_filter(x * x, win) - mx * mx)
    vy = norm * (uniform_filter(y * y, win) - my * my)
    vxy = norm * (uniform_filter(x * y, win) - mx * my)
    s = ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    pad = (win - 1) // 2
    return float(s[pad:-pad, pad:-pad].mean())


def ref_ssim(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.mean([ref_ssim_channel(x[..., k], y[..., k]) for k in range(x.shape[-1])]))


def ref_psnr(x: np.ndarray, y: np.ndarray) -> float:
    mse = np.mean((np.asarray(x, np.float64) - np.asarray(y, np.float64)) ** 2)
    return 10 * math.log10(1.0 / mse)


# ----------------------------------------------------------------------------- PSNR


def test_psnr_hand_value():
    t = np.zeros((4, 4, 3))
    p = t.copy()
    p[1, 2, 0] = 0.5
    # hand: MSE = 0.5^2 / 48 = 1/192 -> PSNR = 10 log10(192) = 22.8330 dB
    assert psnr(t, p) == pytest.approx(10 * math.log10(192), abs=1e-9)
    assert psnr(t, p) == pytest.approx(22.8330, abs=1e-4)


@pytest.mark.parametrize("seed", range(3))
def test_psnr_matches_formula_on_random_images(seed):
    rng = np.random.default_rng(seed)
    t = rng.random((9, 11, 3))
    p = np.clip(t + rng.normal(0, 0.1, t.shape), 0, 1)
    assert psnr(t, p) == pytest.approx(ref_psnr(t, p), rel=1e-12)
    # float32 input gives the same value as its float64 copy
    assert psnr(t.astype(np.float32), p.astype(np.float32)) == pytest.approx(
        ref_psnr(t.astype(np.float32), p.astype(np.float32)), rel=1e-9)


def test_psnr_identical_is_inf():
    t = render_classes(np.random.default_rng(0).integers(0, 3, (8, 8)))
    assert psnr(t, t.copy()) == math.inf


# ----------------------------------------------------------------------------- SSIM


def test_ref_ssim_hand_values():
    # Sanity checks of the reference: identical images give exactly 1 (numerator equals
    # denominator); two different constant images x=a, y=b have zero variances, so
    # SSIM = (2ab + C1) / (a^2 + b^2 + C1) (hand, C1 = 1e-4).
    x = np.random.default_rng(1).random((10, 12, 3))
    assert ref_ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    a, b, c1 = 0.2, 0.6, 1e-4
    hand = (2 * a * b + c1) / (a * a + b * b + c1)
    assert ref_ssim(np.full((9, 9, 3), a), np.full((9, 9, 3), b)) == pytest.approx(hand, rel=1e-9)
    assert ssim(np.full((9, 9, 3), a), np.full((9, 9, 3), b)) == pytest.approx(hand, rel=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_ssim_matches_reference_on_random_images(seed):
    rng = np.random.default_rng(seed)
    t = rng.random((16, 20, 3))
    p = np.clip(t + rng.normal(0, 0.2, t.shape), 0, 1)
    assert ssim(t, p) == pytest.approx(ref_ssim(t, p), rel=1e-9, abs=1e-12)


def test_ssim_matches_reference_on_class_renderings():
    rng = np.random.default_rng(4)
    truth = rng.integers(0, 3, (24, 21))
    pred = truth.copy()
    flip = rng.random(truth.shape) < 0.15
    pred[flip] = rng.integers(0, 3, flip.sum())
    t, p = render_classes(truth), render_classes(pred)
    value = ssim(t, p)
    assert value == pytest.approx(ref_ssim(t, p), rel=1e-9, abs=1e-12)
    assert value < 1.0
    assert ssim(t, t.copy()) == pytest.approx(1.0, abs=1e-12)


def test_ssim_uses_per_channel_mean():
    # Only the red channel differs: hand, SSIM = (s_red + 1 + 1) / 3.
    rng = np.random.default_rng(5)
    t = rng.random((12, 12, 3))
    p = t.copy()
    p[..., 0] = rng.random((12, 12))
    s_red = ref_ssim_channel(t[..., 0], p[..., 0])
    assert ssim(t, p) == pytest.approx((s_red + 2.0) / 3.0, rel=1e-9)


def test_small_map_gives_a_user_error_not_a_crash():
    # A 5x5 map is a valid GridMap, but the 7x7 SSIM window does not fit. Scoring it must
    # either work or raise the one-line FedmapError the package promises for user
    # mistakes, never a raw ValueError from scikit-image.
    c = np.full((5, 5), FREE, np.uint8)
    c[2, 2] = IMPASSABLE
    t = render_classes(c)
    try:
        value = ssim(t, t.copy())
    except FedmapError:
        return
    assert math.isfinite(value)


# ----------------------------------------------------------------------------- errors


def test_shape_mismatch_raises():
    a = np.zeros((8, 8, 3))
    b = np.zeros((8, 9, 3))
    for fn in (psnr, ssim):
        with pytest.raises(FedmapError, match="differ in size"):
            fn(a, b)
    with pytest.raises(FedmapError, match="differ in size"):
        image_scores(np.zeros((8, 8), np.uint8), np.zeros((9, 8), np.uint8))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_prediction_raises(bad):
    a = np.zeros((8, 8, 3))
    b = a.copy()
    b[3, 4, 1] = bad
    for fn in (psnr, ssim):
        with pytest.raises(FedmapError, match="NaN or infinite"):
            fn(a, b)


def test_non_finite_truth_raises():
    # A NaN in the reference image must not silently yield a NaN score.
    a = np.zeros((8, 8, 3))
    b = a.copy()
    a[0, 0, 0] = np.nan
    for fn in (psnr, ssim):
        with pytest.raises(FedmapError):
            fn(a, b)


def test_class_scores_shape_mismatch_raises():
    # (4,4) vs (1,4) would broadcast silently; (4,4) vs (3,3) would raise numpy's
    # ValueError. Either way the user must get a FedmapError.
    t = np.zeros((4, 4), np.uint8)
    for p in (np.zeros((1, 4), np.uint8), np.zeros((3, 3), np.uint8)):
        with pytest.raises(FedmapError):
            class_scores(t, p)


# ----------------------------------------------------------------------------- class scores


def test_class_scores_by_hand():
    truth = np.array([[FREE, FREE, IMPASSABLE], [IMPASSABLE, UNKNOWN, FREE]], np.uint8)
    pred = np.array([[FREE, IMPASSABLE, IMPASSABLE], [UNKNOWN, UNKNOWN, FREE]], np.uint8)
    out = class_scores(truth, pred)
    # hand: equal at (0,0), (0,2), (1,1), (1,2) -> 4/6
    assert out["accuracy"] == pytest.approx(4 / 6)
    # free: truth {(0,0),(0,1),(1,2)}, pred {(0,0),(1,2)} -> 2 / 3
    assert out["iou_free"] == pytest.approx(2 / 3)
    # impassable: truth {(0,2),(1,0)}, pred {(0,1),(0,2)} -> 1 / 3
    assert out["iou_impassable"] == pytest.approx(1 / 3)


def test_class_scores_absent_class_counts_as_perfect():
    # Neither map has an IMPASSABLE cell: the union is empty and the IoU is 1 by
    # convention; FREE matches exactly.
    truth = np.array([[FREE, UNKNOWN]], np.uint8)
    out = class_scores(truth, truth.copy())
    assert out == {"accuracy": 1.0, "iou_free": 1.0, "iou_impassable": 1.0}


def test_image_scores_by_hand():
    truth = np.full((8, 8), FREE, np.uint8)
    pred = truth.copy()
    pred[4, 4] = IMPASSABLE
    out = image_scores(truth, pred)
    # hand: green (0,1,0) vs red (1,0,0) differ by 1 in two of 8*8*3 = 192 values:
    # MSE = 2/192, PSNR = 10 log10(96) = 19.8227 dB
    assert out["psnr"] == pytest.approx(10 * math.log10(96), abs=1e-9)
    assert out["ssim"] == pytest.approx(ref_ssim(render_classes(truth), render_classes(pred)), rel=1e-9)
    assert out["accuracy"] == pytest.approx(63 / 64)
    assert out["iou_free"] == pytest.approx(63 / 64)
    assert out["iou_impassable"] == 0.0


@pytest.mark.parametrize("seed", range(8))
def test_image_scores_from_classes_equal_the_renderings_scores(seed):
    """image_scores computes PSNR and SSIM from the classes (confusion counts, integer
    window sums, threads over row blocks), never rendering: the same figures as the
    reference SSIM and PSNR of the two renderings, to rounding."""
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(7, 160)), int(rng.integers(7, 160)))
    truth = rng.integers(0, 3, shape).astype(np.uint8)
    pred = truth.copy()
    flip = rng.random(shape) < rng.uniform(0.01, 0.6)
    pred[flip] = rng.integers(0, 3, int(flip.sum()))
    t, p = render_classes(truth), render_classes(pred)
    out = image_scores(truth, pred.astype(np.int64))
    assert out["ssim"] == pytest.approx(ref_ssim(t, p), rel=1e-12, abs=1e-14)
    assert out["psnr"] == pytest.approx(ref_psnr(t, p), rel=1e-12)
    assert out["accuracy"] == (truth == pred).mean()
    same = image_scores(truth, truth.copy())
    assert same["psnr"] == math.inf and same["ssim"] == pytest.approx(1.0, abs=1e-14)


def test_image_scores_name_a_value_that_is_not_a_class():
    truth = np.zeros((9, 9), np.uint8)
    bad = truth.copy()
    bad[2, 2] = 3
    with pytest.raises(FedmapError, match="learned map holds values other than the classes"):
        image_scores(truth, bad)
    with pytest.raises(FedmapError, match="ground truth holds values other than the classes"):
        image_scores(bad - 4, truth)
