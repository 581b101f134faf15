"""Payload codecs: round trips, error bounds, exact sizes, top-k selection, error feedback,
DGC momentum, corruption detection, spec parsing."""

import math

import numpy as np
import pytest
import torch

from fedmap.errors import FedmapError
from fedmap.federation.codecs import CodecSpec, Encoder, decode, dense_model_bytes, payload_header_bytes, scale_count
from fedmap.nets.model import build_model, get_weights

DENSE = ["fp32", "fp16", "bf16", "int8", "int8-tensor", "int4", "int4-tensor"]
ALL = DENSE + ["update-" + d for d in DENSE] + ["topk:0.05", "topk:0.05,values=fp32", "topk:0.05,values=int8", "topk:0.5"]


def small(seed: int = 0, scale: float = 1.0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    shapes = {"l0.weight": (8, 5), "l0.bias": (8,), "bn.weight": (8,), "l1.weight": (3, 8), "l1.bias": (3,)}
    return {k: (rng.normal(size=s) * scale).astype(np.float32) for k, s in shapes.items()}


def flat(w: dict[str, np.ndarray]) -> np.ndarray:
    return np.concatenate([np.asarray(v, dtype=np.float64).ravel() for v in w.values()])


def roundtrip(label: str, w, ref=None):
    data = Encoder(CodecSpec.parse(label)).encode(w, ref)
    return data, decode(data, ref)


# -- round trips ---------------------------------------------------------------------------

@pytest.mark.parametrize("label", ALL)
@pytest.mark.parametrize("zstd", ["", "+zstd"])
def test_every_codec_roundtrips_names_shapes_dtype(label: str, zstd: str) -> None:
    w, ref = small(0), small(1)
    data, out = roundtrip(label + zstd, w, ref)
    assert isinstance(data, bytes)
    assert list(out) == list(w)
    for k in w:
        assert out[k].shape == w[k].shape and out[k].dtype == np.float32 and out[k].flags.writeable
    # lossy codecs stay close; topk:0.5 sends half of the delta
    tol = {"fp32": 1e-6, "fp16": 1e-2, "bf16": 2e-2}.get(label.removeprefix("update-"), 0.3)
    if not label.startswith("topk"):
        assert max(np.abs(out[k] - w[k]).max() for k in w) < tol


@pytest.mark.parametrize("label", ALL)
def test_zstd_stage_is_lossless(label: str) -> None:
    w, ref = small(0), small(1)
    plain = Encoder(CodecSpec.parse(label)).encode(w, ref)
    packed = Encoder(CodecSpec.parse(label + "+zstd:19")).encode(w, ref)
    a, b = decode(plain, ref), decode(packed, ref)
    for k in w:
        assert np.array_equal(a[k].view(np.uint32), b[k].view(np.uint32))


def test_fp32_is_bit_exact() -> None:
    w = small(3)
    w["l0.bias"][:4] = [0.0, -0.0, 1e-45, -3.4e38]  # signed zero, subnormal, extreme
    for label in ("fp32", "fp32+zstd"):
        _, out = roundtrip(label, w)
        for k in w:
            assert np.array_equal(out[k].view(np.uint32), w[k].view(np.uint32))


def test_fp16_matches_numpy_cast() -> None:
    w = small(4, scale=100.0)
    _, out = roundtrip("fp16", w)
    for k in w:
        assert np.array_equal(out[k], w[k].astype(np.float16).astype(np.float32))


def bf16_reference(x: np.ndarray) -> np.ndarray:
    """Nearest of the two bf16 neighbours, ties to the even pattern (independent of the codec)."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    u = x.view(np.uint32)
    lo_bits = u & np.uint32(0xFFFF0000)
    lo = lo_bits.view(np.float32).astype(np.float64)
    hi = (lo_bits + np.uint32(0x10000)).view(np.float32).astype(np.float64)
    xd = x.astype(np.float64)
    dlo, dhi = np.abs(xd - lo), np.abs(hi - xd)
    pick_lo = (dlo < dhi) | ((dlo == dhi) & (((u >> 16) & 1) == 0))
    return np.where(pick_lo, lo, hi).astype(np.float32)


def test_bf16_rounds_to_nearest_even() -> None:
    w = small(5, scale=3.0)
    ties = np.array([0x3F808000, 0x3F818000, 0xBF808000, 0x3F807FFF, 0x3F808001, 0x00018000], dtype=np.uint32)
    w["l0.bias"] = ties.view(np.float32).copy().tolist() + [0.0, 1.0]
    w["l0.bias"] = np.asarray(w["l0.bias"], dtype=np.float32)
    _, out = roundtrip("bf16", w)
    for k in w:
        assert np.array_equal(out[k], bf16_reference(w[k]))
        assert np.array_equal(out[k], torch.from_numpy(w[k]).to(torch.bfloat16).float().numpy())
    # the ties went to the even neighbour
    assert out["l0.bias"][0].view(np.uint32) == 0x3F800000
    assert out["l0.bias"][1].view(np.uint32) == 0x3F820000


def expected_scales(w, qmax: int, per_channel: bool) -> dict[str, np.ndarray]:
    """Scale of every entry, broadcast to the tensor's shape, recomputed here."""
    out = {}
    for k, v in w.items():
        if per_channel and v.ndim >= 2:
            s = np.abs(v.reshape(v.shape[0], -1)).max(axis=1) / np.float32(qmax)
            out[k] = np.broadcast_to(s.astype(np.float32).reshape((-1,) + (1,) * (v.ndim - 1)), v.shape)
        else:
            out[k] = np.full(v.shape, np.float32(np.abs(v).max() / np.float32(qmax)), dtype=np.float32)
    return out


@pytest.mark.parametrize("kind,qmax", [("int8", 127), ("int4", 7)])
@pytest.mark.parametrize("per_channel", [True, False])
def test_int_quantisation_within_half_a_step(kind: str, qmax: int, per_channel: bool) -> None:
    w = small(6)
    w["l0.weight"] *= np.float32(10.0) ** np.arange(-2, 6, dtype=np.float32)[:, None]  # rows of very different size
    label = kind + ("" if per_channel else "-tensor")
    _, out = roundtrip(label, w)
    scales = expected_scales(w, qmax, per_channel)
    for k in w:
        s = scales[k]
        err = np.abs(out[k].astype(np.float64) - w[k])
        assert np.all(err <= s / 2 * (1 + 1e-6) + 1e-30), k
        q = out[k] / np.where(s > 0, s, 1)
        assert np.allclose(q, np.rint(q), atol=1e-3) and np.abs(q).max() <= qmax + 1e-3
    if not per_channel:  # the small rows are lost to the big row's scale...
        assert np.all(out["l0.weight"][0] == 0)
    else:  # ...but not with one scale per row
        assert np.abs(out["l0.weight"][0] - w["l0.weight"][0]).max() <= 0.51 / qmax * np.abs(w["l0.weight"][0]).max()


def test_int_quantisation_of_zero_empty_and_scalar_tensors() -> None:
    w = {"zeros": np.zeros((3, 4), np.float32), "empty": np.zeros((0, 4), np.float32),
         "scalar": np.array(2.5, np.float32), "v": np.array([1.0, -2.0], np.float32)}
    for label in ("int8", "int4", "int8-tensor", "topk:0.5,values=int8", "fp16+zstd"):
        _, out = roundtrip(label, w, {k: np.zeros_like(v) for k, v in w.items()})
        assert np.array_equal(out["zeros"], w["zeros"]) and out["empty"].shape == (0, 4)
        assert out["scalar"].shape == ()


# -- sizes ----------------------------------------------------------------------------------

def test_dense_model_bytes() -> None:
    assert [dense_model_bytes(199_683, k) for k in ("fp32", "fp16", "bf16", "int8", "int4")] == [
        798_732, 399_366, 399_366, 199_683, 99_842]
    with pytest.raises(FedmapError):
        dense_model_bytes(10, "topk")


@pytest.mark.parametrize("label", DENSE)
def test_dense_payload_size_is_values_plus_scales_plus_header(label: str) -> None:
    w = small(7)
    n = sum(v.size for v in w.values())
    kind, per_channel = label.split("-")[0], not label.endswith("-tensor")
    n_scales = sum(v.shape[0] if (per_channel and v.ndim >= 2) else 1 for v in w.values()) if kind in ("int8", "int4") else 0
    assert kind not in ("int8", "int4") or scale_count(w, per_channel) == n_scales
    data = Encoder(CodecSpec.parse(label)).encode(w)
    assert len(data) == dense_model_bytes(n, kind) + 4 * n_scales + payload_header_bytes(w)


def test_paper_network_fp16_payload_is_399366_plus_header() -> None:
    w = get_weights(build_model())
    n = sum(v.size for v in w.values())
    assert n == 199_683
    header = payload_header_bytes(w)
    assert header <= 300
    data = Encoder(CodecSpec("fp16")).encode(w)
    assert len(data) == 399_366 + header
    out = decode(data)
    assert all(np.array_equal(out[k], w[k].astype(np.float16).astype(np.float32)) for k in w)


# -- top-k ----------------------------------------------------------------------------------

def big(seed: int, n: int = 3000) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"a": rng.normal(size=(40, 50)).astype(np.float32), "b": rng.normal(size=n - 2000).astype(np.float32) * 3}


@pytest.mark.parametrize("fraction", [0.01, 0.003, 1e-6, 0.4])
def test_topk_sends_exactly_the_k_largest(fraction: float) -> None:
    w, ref = big(0), big(1)
    delta = flat(w) - flat(ref)
    n = delta.size
    k = max(1, round(fraction * n))
    zero = {key: np.zeros_like(v) for key, v in w.items()}
    enc = Encoder(CodecSpec("topk", fraction=fraction, values="fp32"))
    # with a zero reference the decoded weights are the sent values themselves
    sent = flat(decode(enc.encode({key: w[key] - ref[key] for key in w}, zero), zero))
    idx = np.flatnonzero(sent)
    assert idx.size == k
    assert set(idx) == set(np.argpartition(-np.abs(delta), k - 1)[:k])
    assert np.allclose(sent[idx], delta[idx], rtol=1e-6)
    # and with the real reference: reference + sparse delta
    out = flat(decode(Encoder(CodecSpec("topk", fraction=fraction, values="fp32")).encode(w, ref), ref))
    expect = flat(ref)
    expect[idx] += delta[idx]
    assert np.allclose(out, expect, rtol=1e-6, atol=1e-6)


def test_topk_ties_go_to_the_lower_index_and_payload_is_deterministic() -> None:
    w = {"a": np.ones((10, 10), np.float32), "b": -np.ones(100, np.float32)}
    zero = {k: np.zeros_like(v) for k, v in w.items()}
    data = Encoder(CodecSpec.parse("topk:0.1")).encode(w, zero)
    sent = flat(decode(data, zero))
    assert np.array_equal(np.flatnonzero(sent), np.arange(20))
    assert data == Encoder(CodecSpec.parse("topk:0.1")).encode(w, zero)


def test_topk_payload_sizes_count_indices_and_values() -> None:
    w, ref = big(0), big(1)
    sizes = {v: len(Encoder(CodecSpec("topk", fraction=0.01, values=v)).encode(w, ref)) for v in ("fp32", "fp16", "int8")}
    k = 30
    assert sizes["fp32"] - sizes["fp16"] == 2 * k
    assert sizes["fp16"] - sizes["int8"] == k - 4 * len(w)
    assert sizes["fp16"] < payload_header_bytes(w) + 3 * k + 16  # ~1-2 B per index, 2 B per value


def test_error_feedback_delivers_small_entries_eventually() -> None:
    delta = np.full(100, 0.3, np.float32)
    delta[:5] = 1.0  # k = 5: without feedback only these are ever sent
    zero = {"d": np.zeros(100, np.float32)}
    for ef, expect_small in ((False, False), (True, True)):
        enc = Encoder(CodecSpec("topk", fraction=0.05, values="fp32", error_feedback=ef))
        got = np.zeros(100)
        for _ in range(20):
            got += flat(decode(enc.encode({"d": delta}, zero), zero))
        assert (got[5:] != 0).any() == expect_small
        if ef:
            assert (got[5:] != 0).sum() >= 50
            assert np.allclose(got + enc.residual()["d"], 20 * delta.astype(np.float64))
        else:
            assert np.allclose(got[:5], 20.0) and enc.residual() is not None and not enc.residual()["d"].any()


@pytest.mark.parametrize("label", ["topk:0.02", "topk:0.02,values=int8", "topk:0.02,values=fp32",
                                   "update-int8", "update-int4-tensor", "update-fp16", "update-bf16"])
def test_residual_telescopes(label: str) -> None:
    """sum of what was delivered + final residual == sum of the true deltas."""
    rng = np.random.default_rng(2)
    shapes = big(0)
    zero = {k: np.zeros_like(v) for k, v in shapes.items()}
    enc = Encoder(CodecSpec.parse(label))
    total_true, total_sent = 0.0, 0.0
    for t in range(8):
        delta = {k: (rng.normal(size=v.shape) * (1 + t) * 1e-2).astype(np.float32) for k, v in shapes.items()}
        total_true = total_true + flat(delta)
        total_sent = total_sent + flat(decode(enc.encode(delta, zero), zero))
    residual = flat(enc.residual())
    assert np.abs(residual).max() > 0
    assert np.allclose(total_sent + residual, total_true, rtol=0, atol=1e-9)


def test_momentum_correction_follows_dgc() -> None:
    """Compare with a direct transcription of DGC (Lin et al. 2018, Alg. 1 + momentum masking)."""
    rng = np.random.default_rng(3)
    n, k, m = 500, 10, 0.9
    zero = {"d": np.zeros(n, np.float32)}
    deltas = [(rng.normal(size=n) * rng.uniform(0.1, 3, size=n)).astype(np.float32) for _ in range(6)]
    sent_idx = {}
    for mom in (0.0, m):
        enc = Encoder(CodecSpec("topk", fraction=k / n, values="fp32", momentum=mom))
        u, v = np.zeros(n), np.zeros(n)
        sent_idx[mom] = []
        for d in deltas:
            u = mom * u + d
            v = v + u
            idx = np.sort(np.argsort(-np.abs(v), kind="stable")[:k])
            vals = v[idx].astype(np.float32)
            v[idx] -= vals
            u[idx] = 0.0
            got = flat(decode(enc.encode({"d": d}, zero), zero))
            assert np.array_equal(np.flatnonzero(got), idx)
            assert np.array_equal(got[idx], vals.astype(np.float64))
            sent_idx[mom].append(tuple(idx))
        assert np.allclose(flat(enc.residual()), v)
    assert sent_idx[0.0][0] == sent_idx[m][0]  # same first round
    assert sent_idx[0.0] != sent_idx[m]  # momentum changes what is sent later


def test_update_mode_decodes_against_the_reference() -> None:
    w, ref = small(0), small(1)
    data = Encoder(CodecSpec.parse("update-fp32")).encode(w, ref)
    out = decode(data, ref)
    assert all(np.allclose(out[k], w[k], atol=1e-6) for k in w)
    with pytest.raises(FedmapError, match="reference"):
        decode(data)


# -- bad input ------------------------------------------------------------------------------

CORRUPT = ["fp32", "fp16+zstd", "bf16", "int8", "int4-tensor+zstd", "update-int8", "topk:0.2", "topk:0.2,values=int8+zstd",
           "topk:0.9"]


@pytest.mark.parametrize("label", CORRUPT)
def test_every_truncation_and_byte_flip_is_rejected(label: str) -> None:
    w, ref = small(0), small(1)
    data = Encoder(CodecSpec.parse(label)).encode(w, ref)
    decode(data, ref)
    for cut in range(len(data)):
        with pytest.raises(FedmapError, match="^malformed payload: "):
            decode(data[:cut], ref)
    with pytest.raises(FedmapError, match="^malformed payload: "):
        decode(data + b"\x00", ref)
    rng = np.random.default_rng(0)
    for trial in range(300):
        bad = bytearray(data)
        for pos in rng.choice(len(data), size=1 + trial % 3, replace=False):
            bad[pos] ^= int(rng.integers(1, 256))
        with pytest.raises(FedmapError, match="^malformed payload: "):
            decode(bytes(bad), ref)


def test_decode_accepts_buffers() -> None:
    w = small(0)
    data = Encoder(CodecSpec("int8")).encode(w)
    for buf in (bytearray(data), memoryview(data)):
        assert all(np.array_equal(decode(buf)[k], decode(data)[k]) for k in w)


@pytest.mark.parametrize("label", ["topk:0.1", "update-int8"])
def test_reference_mismatch_and_missing_reference(label: str) -> None:
    w, ref = small(0), small(1)
    wrong_shape = dict(ref, **{"l1.weight": ref["l1.weight"].T.copy()})
    missing = {k: v for k, v in ref.items() if k != "l0.bias"}
    for bad in (wrong_shape, missing):
        with pytest.raises(FedmapError, match="reference"):
            Encoder(CodecSpec.parse(label)).encode(w, bad)
    with pytest.raises(FedmapError, match="reference"):
        Encoder(CodecSpec.parse(label)).encode(w)
    data = Encoder(CodecSpec.parse(label)).encode(w, ref)
    for bad in (wrong_shape, missing, None):
        with pytest.raises(FedmapError, match="reference"):
            decode(data, bad)


def test_encoder_state_is_tied_to_its_tensors() -> None:
    enc = Encoder(CodecSpec.parse("topk:0.1"))
    w, ref = small(0), small(1)
    enc.encode(w, ref)
    enc.encode({k: w[k] for k in reversed(list(w))}, ref)  # same tensors, other order: fine
    with pytest.raises(FedmapError, match="different set of tensors"):
        enc.encode(big(0), big(1))
    enc.reset()
    enc.encode(big(0), big(1))


def test_non_finite_and_out_of_range_values_are_refused() -> None:
    w = small(0)
    w["l0.bias"][2] = np.nan
    with pytest.raises(FedmapError, match="NaN"):
        Encoder(CodecSpec("fp32")).encode(w)
    w = small(0)
    w["l0.bias"][2] = 1e6
    with pytest.raises(FedmapError, match="fp16 range"):
        Encoder(CodecSpec("fp16")).encode(w)
    assert decode(Encoder(CodecSpec("bf16")).encode(w))["l0.bias"][2] == pytest.approx(1e6, rel=1e-2)


# -- spec text ------------------------------------------------------------------------------

CANONICAL = ["fp32", "fp16", "bf16", "fp16+zstd", "int8", "int8-tensor", "int4+zstd", "int4-tensor+zstd:19",
             "topk:0.01", "topk:0.005+zstd", "update-int8+zstd", "update-int4-tensor,noef", "update-bf16",
             "topk:0.002,values=int8,momentum=0.9,noef+zstd:9", "topk:1.0,values=fp32"]


@pytest.mark.parametrize("text", CANONICAL)
def test_parse_label_roundtrip(text: str) -> None:
    spec = CodecSpec.parse(text)
    assert spec.label() == text
    assert CodecSpec.parse(spec.label()) == spec


def test_parse_fields_and_spec_normalisation() -> None:
    assert CodecSpec.parse("fp16+zstd") == CodecSpec("fp16", zstd=3)
    assert CodecSpec.parse("int8-tensor") == CodecSpec("int8", per_channel=False)
    assert CodecSpec.parse("topk:0.005") == CodecSpec("topk", fraction=0.005, update=True)
    assert CodecSpec.parse(" TOPK ") == CodecSpec("topk") == CodecSpec.parse("update-topk:0.01")
    assert CodecSpec.parse("update-int8+zstd") == CodecSpec("int8", update=True, zstd=3)
    assert CodecSpec.parse("topk:0.01,momentum=0.5,values=int8").momentum == 0.5
    specs = [CodecSpec("fp16", per_channel=False, fraction=0.3, momentum=0.9, error_feedback=False),
             CodecSpec("int4", per_channel=False, update=True, error_feedback=False, zstd=22),
             CodecSpec("topk", fraction=1, values="fp32", momentum=0.99, error_feedback=False, per_channel=False)]
    for spec in specs:
        assert CodecSpec.parse(spec.label()) == spec
    assert specs[0] == CodecSpec("fp16")  # fields that do not apply are reset


@pytest.mark.parametrize("text", ["", "fp8", "fp16+gzip", "fp16+zstd+zstd", "fp16+zstd:0", "fp16+zstd:99", "topk:abc",
                                  "topk:0", "topk:1.5", "topk:nan", "topk:", "int8-tensor:0.1", "fp16-tensor",
                                  "fp16:0.1", "fp16,noef", "int8,", "topk:0.01,values=int16", "topk:0.01,momentum=1.0",
                                  "topk:0.01,noef,noef", "topk:0.01,values", "update-", "update-fp16,momentum=0.9"])
def test_parse_rejects_bad_text_with_the_grammar(text: str) -> None:
    with pytest.raises(FedmapError, match="expected .*topk") as e:
        CodecSpec.parse(text)
    assert "\n" not in str(e.value)


def test_spec_validation() -> None:
    for kw in ({"kind": "fp64"}, {"kind": "topk", "fraction": 0.0}, {"kind": "topk", "momentum": -0.1},
               {"kind": "topk", "values": "bf16"}, {"zstd": 0}, {"zstd": True}, {"zstd": 1.5}):
        with pytest.raises(FedmapError):
            CodecSpec(**kw)
    assert Encoder("int8-tensor").spec == CodecSpec("int8", per_channel=False)
    assert math.isclose(CodecSpec.parse("topk:1e-05").fraction, 1e-5)
