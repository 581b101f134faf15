"""Sharing an elevation layer: the height codecs' error contracts, the residual that enforces
a max error, the neural height field, the rate-distortion summary, and classes re-derived
from a lossless share against the truth's under every rover profile."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.experiments.elevation import Point, summarise
from fedmap.federation.heights import HeightCodec, residual_apply, residual_encode
from fedmap.maps.dem import Dem
from fedmap.maps.terrain import generate_dem
from fedmap.maps.traversability import ROVER_NAMES, dem_to_traversability, rover_profile
from fedmap.nets.heightfield import HeightNetConfig, decode_heightnet, encode_heightnet, fit_heights

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _surface(seed: int = 0, shape=(40, 52)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[: shape[0], : shape[1]]
    z = 30 + 0.2 * r - 0.1 * c + 3 * np.sin(r / 7) * np.cos(c / 5) + rng.normal(0, 0.05, shape)
    z[rng.random(shape) < 0.02] = np.nan  # nodata
    return z.astype(np.float32)


@pytest.mark.parametrize("seed", range(3))
def test_every_codec_keeps_its_error_contract_and_the_unknown_cells(seed):
    z = _surface(seed)
    known = np.isfinite(z)
    for codec, bound in [(HeightCodec("lossless", 0), 0.0), (HeightCodec("lossless", 0.01), 0.005),
                         (HeightCodec("lerc", 0.05), 0.05), (HeightCodec("lerc", 0.5), 0.5)]:
        d = HeightCodec.decode(codec.encode(z))
        assert (np.isnan(d) == ~known).all(), codec.label
        assert np.abs(d[known] - z[known]).max() <= bound + 1e-6, codec.label
    exact = HeightCodec.decode(HeightCodec("lossless", 0).encode(z))
    assert np.array_equal(exact[known].astype(np.float32), z[known])  # bit for bit
    # JPEG XL at distance 0 is lossless on the 16-bit quantisation of the range
    step = (np.nanmax(z) - np.nanmin(z)) / 65535
    d = HeightCodec.decode(HeightCodec("jxl", 0).encode(z))
    assert np.abs(d[known] - z[known]).max() <= step / 2 + 1e-6
    # lossy JPEG XL and JPEG 2000: fewer bytes as the distance grows / the PSNR drops
    sizes = [len(HeightCodec("jxl", dist).encode(z)) for dist in (0.5, 2, 8)]
    assert sizes[0] > sizes[1] > sizes[2]
    sizes = [len(HeightCodec("j2k", p).encode(z)) for p in (75, 55, 40)]
    assert sizes[0] > sizes[1] > sizes[2]


def test_bad_heights_and_damaged_payloads_are_one_line_errors():
    with pytest.raises(FedmapError, match="infinite"):
        HeightCodec("lossless", 0.01).encode(np.array([[1.0, np.inf]]))
    with pytest.raises(FedmapError, match="unknown height codec"):
        HeightCodec("png", 1)
    z = _surface(1)
    rng = np.random.default_rng(0)
    for codec in (HeightCodec("lossless", 0.01), HeightCodec("lossless", 0), HeightCodec("lerc", 0.1),
                  HeightCodec("jxl", 1), HeightCodec("j2k", 50)):
        p = codec.encode(z)
        with pytest.raises(RejectedUpdate):
            HeightCodec.decode(p[: len(p) // 2])
        for _ in range(20):  # a flipped byte: a clean refusal or heights of the right shape, never a crash
            b = bytearray(p)
            b[int(rng.integers(0, len(b)))] ^= 0xFF
            try:
                d = HeightCodec.decode(bytes(b))
            except RejectedUpdate:
                continue
            assert d.shape == z.shape


def test_the_residual_enforces_the_max_error():
    rng = np.random.default_rng(4)
    z = _surface(2).astype(np.float64)
    for e in (0.01, 0.1, 1.0):
        pred = z + rng.normal(0, 3 * e, z.shape)
        fixed = residual_apply(np.nan_to_num(pred), residual_encode(z, np.nan_to_num(pred), e), e)
        known = np.isfinite(z)
        assert np.abs(fixed[known] - z[known]).max() <= e + 1e-9


def test_the_height_field_fits_a_smooth_surface_and_its_int8_payload_decodes_to_it():
    z = _surface(0).astype(np.float64)
    fit = fit_heights(z, HeightNetConfig(mapping=16, hidden=32, scale=3.0), steps=600, qat_steps=150)
    payload = encode_heightnet(fit)
    got = decode_heightnet(payload)
    known = np.isfinite(z)
    rmse = math.sqrt(np.mean((got[known] - z[known]) ** 2))
    assert rmse < 0.1 * np.nanstd(z)
    # the payload is the int8 weights: one byte per weight and a 4-byte scale per tensor, then zstd
    n = sum(p.numel() for p in fit.net.mlp.parameters())
    assert len(payload) < n + 4 * 6 + 200
    with pytest.raises(RejectedUpdate):
        decode_heightnet(payload[:10])


def test_matched_rmse_and_max_error_ratios_by_hand():
    pts = [Point("t", "jxl", "d1", 1000, 1.0, 0.1, 0.5, 1.0), Point("t", "jxl", "d2", 400, 1.0, 0.4, 1.0, 1.0),
           Point("t", "neural", "n", 500, 1.0, 0.2, 1.0, 1.0), Point("t", "neural", "far", 50, 1.0, 3.0, 9.0, 1.0),
           Point("t", "lerc", "max err 0.5 m", 800, 1.0, 0.2, 0.5, 1.0),
           Point("t", "neural+residual", "n, max err 0.5 m", 600, 1.0, 0.2, 0.5, 1.0)]
    s = summarise(pts)["t"]
    # log-log: at rmse 0.2 between (0.1, 1000) and (0.4, 400): log b = log 1000 + (log 2 / log 4) log(0.4)
    want = math.exp(math.log(1000) + 0.5 * math.log(400 / 1000))
    assert s["neural_vs_jxl"][0]["jxl_bytes"] == pytest.approx(want)
    assert s["best_neural_vs_jxl"] == pytest.approx(500 / want)
    assert s["neural_vs_jxl"][1]["ratio"] is None  # outside JPEG XL's measured range: no ratio
    assert s["best_neural_residual_vs_lerc"] == pytest.approx(600 / 800)


def _terrains():
    out = [generate_dem(k, 64, seed=3) for k in ("mars", "moon", "ice")]
    gale = DATA / "mars" / "missionDEM_gale_1m.tif"
    if gale.exists():
        from fedmap.maps.io import load_dem
        d = load_dem(gale)
        out.append(Dem(d.elevation[:96, :96], d.pixel_size))
    return out


def test_classes_rederived_from_a_lossless_share_are_the_truths_under_every_profile():
    for dem in _terrains():
        shared = HeightCodec.decode(HeightCodec("lossless", 0).encode(dem.elevation))
        received = Dem(shared.astype(np.float32), dem.pixel_size)
        for profile in (None, *(rover_profile(n) for n in ROVER_NAMES)):
            want = dem_to_traversability(dem, profile).classes
            got = dem_to_traversability(received, profile).classes
            assert np.array_equal(got, want), (dem.source, profile)


def test_federated_height_grids_merge_into_the_union_of_what_the_rovers_saw():
    from fedmap.federation.heightfed import federate_heights, grid_resolutions
    from fedmap.maps.grid import GridMap

    z = _surface(3, shape=(32, 32)).astype(np.float64)
    z = np.where(np.isfinite(z), z, 30.0)
    halves = [np.zeros(z.shape, bool), np.zeros(z.shape, bool)]
    halves[0][:, :16], halves[1][:, 16:] = True, True
    maps = [GridMap(np.where(m, 0, 2).astype(np.uint8), 1.0).with_layer("elevation", np.where(m, z, np.nan))
            for m in halves]
    hf = federate_heights(maps, steps=300)
    assert hf.resolutions == grid_resolutions(32) == (32,)
    err = np.abs(hf.heights - z)
    # fp16 of heights normalised by the team's std: a few mm at ~30 m
    assert err.max() < 0.02
    assert hf.uplink_bytes > 2 * 32 * 16 and hf.downlink_bytes > 0 and hf.reference_bytes > 0
    with pytest.raises(FedmapError, match="elevation layer"):
        federate_heights([GridMap(np.zeros((8, 8), np.uint8), 1.0)])


def test_a_run_with_an_elevation_layer_reports_its_heights():
    from fedmap.config import method_config
    from fedmap.maps.grid import GridMap
    from fedmap.pipeline import run_pipeline

    cfg = method_config("fedmap", size=64, **{"explore.layers": ["classes", "elevation"], "evaluate.central": False})
    res = run_pipeline(cfg)
    e = res.metrics["elevation"]
    assert e["observed"]["rmse_m"] < 0.01 and e["bytes"]["uplink"] > 0
    assert e["rederived_classes"]["path"]["f1"] >= 0.95
    # a class map has no heights: a one-line error, before any work
    with pytest.raises(FedmapError, match="elevation"):
        run_pipeline(cfg, truth=GridMap(res.truth.classes, res.truth.pixel_size))
