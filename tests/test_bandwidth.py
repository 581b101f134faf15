"""Tests for fedmap.experiments.bandwidth: the paper's Table III arithmetic and the image codecs.

References: Table III of the paper as printed (the numbers in ``PRINTED`` below, typed
from the paper, not from the module), 199,683 parameters x 2 B (fp16); bit layouts and
grey-level snapping worked out by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import features

from fedmap.errors import FedmapError
from fedmap.experiments.bandwidth import (
    ImageCodec,
    classes_to_gray,
    compare_image_codecs,
    gray_to_classes,
    image_codecs,
    markdown_table,
    pack_2bit,
    paper_table3,
    rd_figure,
    unpack_2bit,
)
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.terrain import generate_dem
from fedmap.maps.traversability import dem_to_traversability

# (data size, model size, reduction) exactly as printed in the paper's Table III.
PRINTED = [
    ("3.81 MB", "399 KB", "89.53 %"),
    ("402 KB", "399 KB", "0.7 %"),
    ("960 KB", "399 KB", "58.4 %"),
    ("2.16 MB", "399 KB", "81.5 %"),
    ("2.88 MB", "399 KB", "86.1 %"),
    ("6.48 MB", "399 KB", "93.8 %"),
]
LOSSLESS = ["raw-gray", "png-gray", "png-palette", "zstd-2bit", "zstd-uint8"] + (
    ["webp-lossless"] if features.check("webp") else [])
needs_webp = pytest.mark.skipif(not features.check("webp"), reason="Pillow built without WebP")


@pytest.fixture(scope="module")
def mars() -> GridMap:
    """A real-looking built-in map (128 x 128: big enough for JPEG to behave as on photos
    of terrain, small enough for fast tests)."""
    return dem_to_traversability(generate_dem("mars", 128, seed=0))


@pytest.fixture(scope="module")
def mixed() -> np.ndarray:
    """37x53 (not a multiple of 4 cells) with all three classes: random cells and blocks."""
    rng = np.random.default_rng(3)
    c = rng.choice([FREE, IMPASSABLE, UNKNOWN], size=(37, 53), p=[0.6, 0.3, 0.1]).astype(np.uint8)
    c[5:15, 10:30] = UNKNOWN
    c[20:30, 0:20] = IMPASSABLE
    return c


# -- Table III ---------------------------------------------------------------------------

def test_table3_displayed_numbers_reproduced():
    rows = paper_table3()
    assert len(rows) == len(PRINTED)
    for row, (data, model, red) in zip(rows, PRINTED):
        assert row["data_display"] == data
        assert row["model_display"] == model
        assert row["reduction_paper_display"] == red
        assert row["paper_printed"] == {"data": data, "model": model, "reduction": red}


def test_table3_bytes_from_first_principles():
    rows = paper_table3()
    assert all(r["model_bytes"] == 199_683 * 2 == 399_366 for r in rows)
    expected = [2000 * 2000 * 1, 402_000, 400 * 400 * 6, 600 * 600 * 6, 400 * 400 * 18, 600 * 600 * 18]
    assert [r["data_bytes"] for r in rows] == expected
    assert [r["bytes_per_cell"] for r in rows] == [1, None, 6, 6, 18, 18]
    # the paper's way: 1 - 399/3810, 1 - 399/402, 1 - 399/960 ...
    for r, k in zip(rows, [3810, 402, 960, 2160, 2880, 6480]):
        assert r["reduction_paper"] == pytest.approx(1 - 399 / k, abs=1e-12)
        assert r["reduction_bytes"] == pytest.approx(1 - 399_366 / r["data_bytes"], abs=1e-12)


def test_table3_unit_mix_only_matters_for_grayscale():
    rows = paper_table3()
    gray = rows[0]
    assert 4_000_000 / 2**20 == pytest.approx(3.8147, abs=1e-4)  # "3.81 MB" is MiB
    assert gray["reduction_bytes_display"] == "90.02 %"  # consistent bytes
    assert gray["reduction_paper_display"] == "89.53 %"
    assert "MiB" in gray["data_display_unit"] and "90.02 %" in gray["note"]
    for r in rows[1:]:  # decimal throughout: both ways agree to the shown decimal
        assert r["reduction_bytes_display"] == r["reduction_paper_display"]


def test_table3_other_model_size_and_bad_input():
    rows = paper_table3(model_bytes=100_000)
    assert rows[0]["model_display"] == "100 KB"
    assert rows[0]["reduction_paper"] == pytest.approx(1 - 100 / 3810)
    for bad in (0, -5, 1.5, True):
        with pytest.raises(FedmapError):
            paper_table3(model_bytes=bad)
    md = markdown_table(paper_table3())
    assert "89.53 %" in md and "90.02 %" in md and "4,000,000" in md


# -- grey levels and 2-bit packing ---------------------------------------------------------

def test_grey_levels_and_snapping():
    np.testing.assert_array_equal(classes_to_gray(np.array([[FREE, IMPASSABLE, UNKNOWN]])), [[255, 0, 128]])
    g = np.array([0, 63, 64, 65, 128, 191, 192, 255], dtype=np.uint8)
    # 64 is equidistant from 0 (impassable) and 128 (unknown): lower class value wins
    np.testing.assert_array_equal(gray_to_classes(g),
                                  [IMPASSABLE, IMPASSABLE, IMPASSABLE, UNKNOWN, UNKNOWN, UNKNOWN, FREE, FREE])
    with pytest.raises(FedmapError):
        gray_to_classes(g.astype(np.int16))


def test_pack_2bit_layout_by_hand():
    c = np.array([[0, 1, 2, 0, 1]], dtype=np.uint8)
    # 00 01 10 00 -> 0x18; 01 + three zero pad codes -> 0x40
    assert pack_2bit(c) == bytes([0x18, 0x40])
    np.testing.assert_array_equal(unpack_2bit(bytes([0x18, 0x40]), (1, 5)), c)
    with pytest.raises(FedmapError, match="padding"):
        unpack_2bit(bytes([0x18, 0x41]), (1, 5))
    with pytest.raises(FedmapError, match="code 3"):
        unpack_2bit(bytes([0xC0, 0x40]), (1, 5))
    with pytest.raises(FedmapError):
        unpack_2bit(bytes([0x18]), (1, 5))


# -- codecs --------------------------------------------------------------------------------

@pytest.mark.parametrize("name", LOSSLESS)
def test_lossless_roundtrip_exact(name, mixed, mars):
    codec = ImageCodec(name)
    assert codec.lossless
    for c in (mixed, mars.classes[:64, :80]):
        payload, decoded = codec.roundtrip(c)
        assert isinstance(payload, bytes)
        assert decoded.dtype == np.uint8 and decoded.shape == c.shape
        np.testing.assert_array_equal(decoded, c)
        assert codec.encode(c) == payload  # deterministic


def test_raw_gray_is_one_byte_per_cell(mixed):
    assert len(ImageCodec("raw-gray").encode(mixed)) == mixed.size
    assert len(pack_2bit(mixed)) == math.ceil(mixed.size / 4)


def test_rows_bytes_are_payload_lengths(mars):
    codecs = image_codecs((10, 50))
    rows = compare_image_codecs(mars, codecs=codecs, n_pairs=5)
    assert [r["codec"] for r in rows] == [c.label for c in codecs]
    for codec, r in zip(codecs, rows):
        n = len(codec.encode(mars.classes))
        assert r["bytes"] == n
        assert r["bits_per_cell"] == pytest.approx(8 * n / mars.classes.size)
        assert r["seconds"] == pytest.approx(r["encode_s"] + r["decode_s"])
        if r["lossless"]:
            assert r["exact"] and r["psnr"] == math.inf and r["ssim"] == 1.0 and r["f1"] == 1.0
    assert next(r for r in rows if r["codec"] == "raw-gray")["bytes"] == 128 * 128


def test_jpeg_bytes_shrink_with_quality(mars):
    sizes = [len(ImageCodec("jpeg", q).encode(mars.classes)) for q in (90, 75, 50, 26, 10)]
    assert all(a > b for a, b in zip(sizes, sizes[1:])), sizes


@needs_webp
def test_webp_bytes_shrink_with_quality(mars):
    sizes = [len(ImageCodec("webp", q).encode(mars.classes)) for q in (90, 50, 10)]
    assert all(a > b for a, b in zip(sizes, sizes[1:])), sizes


def test_lossy_scores_below_lossless(mars):
    codecs = [ImageCodec("png-palette"), ImageCodec("jpeg", 10), ImageCodec("jpeg", 26)]
    rows = {r["codec"]: r for r in compare_image_codecs(mars, codecs=codecs, n_pairs=5)}
    assert rows["png-palette"]["psnr"] == math.inf
    for label in ("jpeg q10", "jpeg q26"):
        r = rows[label]
        assert not r["exact"] and not r["lossless"]
        assert math.isfinite(r["psnr"]) and r["psnr"] < rows["png-palette"]["psnr"]
        assert r["ssim"] < 1 and r["accuracy"] < 1 and math.isfinite(r["psnr_gray"])
    assert rows["jpeg q10"]["psnr"] < rows["jpeg q26"]["psnr"]
    # decoded lossy maps hold only classes
    payload, decoded = ImageCodec("jpeg", 10).roundtrip(mars.classes)
    assert set(np.unique(decoded)) <= {FREE, IMPASSABLE, UNKNOWN}


def test_two_level_snapping(mars, mixed):
    c = mars.classes
    assert not (c == UNKNOWN).any()
    three, two = ImageCodec("jpeg", 26), ImageCodec("jpeg", 26, two_level=True)
    assert two.label == "jpeg q26 2-level" and two.family == "jpeg 2-level"
    p = three.encode(c)
    assert two.encode(c) == p  # same bytes, only the receiver's snapping differs
    gray = three.decode_gray(p, c.shape)
    np.testing.assert_array_equal(two.decode(p, c.shape), np.where(gray >= 128, FREE, IMPASSABLE))
    assert set(np.unique(two.decode(p, c.shape))) <= {FREE, IMPASSABLE}
    assert (two.decode(p, c.shape) != c).sum() <= (three.decode(p, c.shape) != c).sum()
    with pytest.raises(FedmapError, match="unknown cells"):
        two.encode(mixed)
    with pytest.raises(FedmapError):
        ImageCodec("png-gray", two_level=True)
    labels = [k.label for k in image_codecs((10,), webp=False, two_level=True)]
    assert labels[-2:] == ["jpeg q10", "jpeg q10 2-level"]


def test_path_scores_optional(mixed):
    rows = compare_image_codecs(mixed, codecs=[ImageCodec("zstd-2bit")], path_scores=False)
    assert rows[0]["f1"] is None and rows[0]["psnr"] == math.inf


# -- corrupted payloads ------------------------------------------------------------------

def _flip(payload: bytes, i: int) -> bytes:
    b = bytearray(payload)
    b[i] ^= 0x55
    return bytes(b)


@pytest.mark.parametrize("codec", [ImageCodec("jpeg", 26), ImageCodec("png-gray"), ImageCodec("png-palette"),
                                   ImageCodec("zstd-2bit"), ImageCodec("zstd-uint8")], ids=lambda c: c.label)
def test_corrupted_payload_raises(codec, mars):
    c = mars.classes
    p = codec.encode(c)
    bad = [p[: len(p) // 2], p[:10], b"", b"XXXX" + p[4:], b"not an image at all"]
    if codec.lossless:  # PNG's zlib check and zstd's checksum catch a flipped byte
        bad.append(_flip(p, len(p) // 2))
    for q in bad:
        with pytest.raises(FedmapError, match="malformed payload"):
            codec.decode(q, c.shape)


@pytest.mark.parametrize("name", ["jpeg", "png-gray", "png-palette", "zstd-2bit", "zstd-uint8", "raw-gray"])
def test_wrong_shape_raises(name, mixed):
    codec = ImageCodec(name, 50 if name == "jpeg" else None)
    p = codec.encode(mixed)
    h, w = mixed.shape
    for shape in ((w, h), (h, w + 4), (h - 1, w)):  # payloads without a header only know the cell count
        if not codec.name.startswith(("png", "jpeg")) and shape[0] * shape[1] == h * w:
            continue
        with pytest.raises(FedmapError):
            codec.decode(p, shape)


def test_raw_and_uint8_reject_non_class_values(mixed):
    raw = bytearray(ImageCodec("raw-gray").encode(mixed))
    raw[0] = 7
    with pytest.raises(FedmapError, match="no class level"):
        ImageCodec("raw-gray").decode(bytes(raw), mixed.shape)
    import zstandard

    bad = zstandard.ZstdCompressor(level=3, write_checksum=True).compress(np.full(mixed.size, 3, np.uint8).tobytes())
    with pytest.raises(FedmapError, match="no class"):
        ImageCodec("zstd-uint8").decode(bad, mixed.shape)


def test_codec_arguments_checked(mixed):
    for kwargs in ({"name": "gif"}, {"name": "jpeg"}, {"name": "jpeg", "quality": 0}, {"name": "jpeg", "quality": 101},
                   {"name": "png-gray", "quality": 50}):
        with pytest.raises(FedmapError):
            ImageCodec(**kwargs)
    with pytest.raises(FedmapError):
        ImageCodec("png-gray").encode(np.full((4, 4), 3, np.uint8))


# -- figure and table ----------------------------------------------------------------------

def test_rd_figure_and_markdown(tmp_path, mars):
    rows = compare_image_codecs(mars.classes[:64, :64], codecs=image_codecs((10, 90)), n_pairs=3)
    out = tmp_path / "rd.png"
    rd_figure(rows, out, model_points=[{"label": "model fp16", "bytes": 399_366, "psnr": None, "f1": None},
                                       {"label": "model int8", "bytes": 200_000, "psnr": 21.0, "f1": 0.8}])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = markdown_table(rows)
    assert md.count("\n") == len(rows) + 2
    assert "jpeg q10" in md and "zstd-2bit (lossless)" in md and "| inf |" in md
    with pytest.raises(FedmapError):
        rd_figure(rows, tmp_path / "x.png", model_points=[{"label": "no bytes"}])
