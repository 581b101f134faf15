"""The ``context`` class-map codec: exact round trips, its model checked against a slow
reference, references, and malformed payloads."""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np
import pytest

from fedmap._util import varint
from fedmap.coding import mapcodec
from fedmap.coding.mapcodec import decode_map, encode_map
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.experiments.bandwidth import ImageCodec
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.sources import TerrainSource, load_truth

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
HEAD = mapcodec._HEADER.size + 4  # header + trailing CRC (a payload of the whole grid: no window fields)


def _window_fields(data: bytes) -> int:
    """Bytes of the window's varints (0 without a window)."""
    if not data[5] & mapcodec._F_WINDOW:
        return 0
    off = mapcodec._HEADER.size
    for _ in range(4):
        while data[off] & 0x80:
            off += 1
        off += 1
    return off - mapcodec._HEADER.size


def _roundtrip(m: np.ndarray, reference: np.ndarray | None = None) -> bytes:
    data = encode_map(m, reference=reference)
    back = decode_map(data, reference=reference)
    assert back.dtype == np.uint8 and back.shape == m.shape
    np.testing.assert_array_equal(back, m)
    return data


def _blobs(shape: tuple[int, int], seed: int, block: int = 8) -> np.ndarray:
    """Blocky random terrain: classes constant on ``block``-sized squares, some noise."""
    rng = np.random.default_rng(seed)
    coarse = rng.choice(3, p=[0.7, 0.2, 0.1], size=(-(-shape[0] // block), -(-shape[1] // block)))
    m = np.kron(coarse, np.ones((block, block), dtype=np.int64))[: shape[0], : shape[1]]
    flip = rng.random(shape) < 0.01
    m[flip] = rng.integers(0, 3, size=int(flip.sum()))
    return m.astype(np.uint8)


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_maps_round_trip(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(v) for v in rng.integers(1, 90, size=2))
    _roundtrip(rng.integers(0, 3, size=shape).astype(np.uint8))
    _roundtrip(_blobs((97, 131), seed))


@pytest.mark.parametrize("value", [FREE, IMPASSABLE, UNKNOWN])
def test_single_class_maps_cost_almost_nothing(value):
    m = np.full((256, 256), value, dtype=np.uint8)
    data = _roundtrip(m)
    assert len(data) - HEAD <= 32  # 65,536 cells of one class (16,384 B packed): a few coder words


@pytest.mark.parametrize("shape", [(1, 1), (1, 2), (2, 1), (1, 3), (1, 17), (17, 1), (1, 1000), (1000, 1), (3, 700)])
def test_strips_round_trip(shape):
    rng = np.random.default_rng(shape[0] * 7919 + shape[1])
    _roundtrip(rng.integers(0, 3, size=shape).astype(np.uint8))


@pytest.mark.parametrize("terrain", ["mars", "moon", "ice"])
def test_builtin_terrain_round_trips_and_beats_zstd(terrain):
    m = load_truth(TerrainSource(terrain=terrain, size=128)).classes
    data = _roundtrip(m)
    assert len(data) < len(ImageCodec("zstd-2bit").encode(m))


def test_large_map_round_trips():
    _roundtrip(_blobs((2048, 2048), seed=5, block=16))


@pytest.mark.skipif(not (DATA / "mars" / "missionDEM_gale_1m.tif").exists(), reason="needs ../shared/data")
def test_real_terrain_round_trips():
    m = load_truth(TerrainSource(kind="dem", path=str(DATA / "mars" / "missionDEM_gale_1m.tif"), crop=320)).classes
    assert (m == IMPASSABLE).any() and (m == FREE).any()
    _roundtrip(m)


def test_same_input_same_bytes():
    m = _blobs((64, 80), seed=3)
    assert encode_map(m) == encode_map(m.copy()) == encode_map(m.astype(np.int64))


# ----------------------------------------------------------------------------- the model


def _reference_bits(m: np.ndarray) -> float:
    """Ideal code length of the documented model, written out cell by cell (slow, plain
    Python): coarse-to-fine phases A/B/C, four neighbours at distance s (outside: the
    opposite neighbour, else 3), one count table per (phase, level); within a phase the
    k-th cell of each context is coded with the counts left by the cells of that context
    that came in earlier rounds (round = k.bit_length())."""
    h, w = m.shape
    alpha = mapcodec.ALPHA
    tables: dict[tuple, dict[tuple, list[int]]] = {}

    def cost(cells: list[tuple[int, int]], table: tuple, ctx_of) -> float:
        counts = tables.setdefault(table, {})
        groups: dict[tuple, list[int]] = {}
        for r, c in cells:  # raster order within a context
            groups.setdefault(ctx_of(r, c), []).append(int(m[r, c]))
        bits = 0.0
        for key, symbols in groups.items():
            prior = list(counts.get(key, [0, 0, 0]))
            for k, y in enumerate(symbols):
                n = list(prior)
                for j in range(k):  # earlier cells of this context in earlier rounds
                    if j.bit_length() < k.bit_length():
                        n[symbols[j]] += 1
                bits -= math.log2((n[y] + alpha) / (sum(n) + 3 * alpha))
            for y in symbols:
                prior[y] += 1
            counts[key] = prior
        return bits

    def at(r: int, c: int, dr: int, dc: int) -> int:
        for rr, cc in ((r + dr, c + dc), (r - dr, c - dc)):  # outside: the mirrored neighbour
            if 0 <= rr < h and 0 <= cc < w:
                return int(m[rr, cc])
        return 3

    bits = cost([(0, 0)], ("root",), lambda r, c: 0)
    s = 1
    while s < max(h, w):
        s *= 2
    s //= 2
    while s >= 1:
        level = 0 if s == 1 else 1 if s == 2 else 2
        offsets = {"A": [(-s, -s), (-s, s), (s, -s), (s, s)], "B": [(0, -s), (0, s), (-s, 0), (s, 0)],
                   "C": [(-s, 0), (s, 0), (0, -s), (0, s)]}
        starts = {"A": (s, s), "B": (0, s), "C": (s, 0)}
        for kind in "ABC":
            r0, c0 = starts[kind]
            cells = [(r, c) for r in range(r0, h, 2 * s) for c in range(c0, w, 2 * s)]

            def ctx_of(r, c, offs=offsets[kind]):
                return tuple(at(r, c, dr, dc) for dr, dc in offs)

            bits += cost(cells, (kind, level), ctx_of)
        s //= 2
    return bits


@pytest.mark.parametrize("shape, seed", [((37, 53), 0), ((64, 64), 1), ((1, 200), 2)])
def test_payload_size_is_the_models_ideal_code_length(shape, seed):
    """The range coder spends within a few bytes of -sum log2 p under the documented model."""
    m = _blobs(shape, seed, block=4)
    data = encode_map(m)
    body = len(data) - HEAD - _window_fields(data)
    top, left, h, w = mapcodec.changed_window(m, None)
    ideal = _reference_bits(m[top:top + h, left:left + w]) / 8  # only the window that differs from UNKNOWN
    assert ideal - 1 <= body <= ideal + 8, (body, ideal)


# ----------------------------------------------------------------------------- references


def test_a_reference_makes_an_update_cheap():
    """A rover's map given the global map the receiver holds: only the new ground costs."""
    truth = load_truth(TerrainSource(terrain="mars", size=256)).classes
    before = truth.copy()
    before[128:, 128:] = UNKNOWN  # the quadrant nobody had seen
    after = before.copy()
    after[128:200, 128:200] = truth[128:200, 128:200]  # a rover observed part of it
    with_ref = _roundtrip(after, reference=before)
    alone = _roundtrip(after)
    new_only = _roundtrip(np.where(np.arange(256)[:, None] >= 128, after, UNKNOWN).astype(np.uint8))
    assert len(with_ref) < len(alone) / 2
    assert len(with_ref) <= len(new_only) * 1.25  # about what the new cells cost on their own
    assert len(_roundtrip(before, reference=before)) <= HEAD + 40  # nothing new: next to nothing


def test_reference_mistakes():
    m = _blobs((40, 40), seed=1)
    ref = _blobs((40, 40), seed=2)
    data = encode_map(m, reference=ref)
    with pytest.raises(RejectedUpdate, match="coded against a reference map; pass the same reference"):
        decode_map(data)
    with pytest.raises(RejectedUpdate, match="^malformed map payload: the reference map differs from the encoder's"):
        decode_map(data, reference=_blobs((40, 40), seed=3))
    with pytest.raises(RejectedUpdate, match="it is 40x40, the reference is 40x41"):
        decode_map(data, reference=np.zeros((40, 41), np.uint8))
    with pytest.raises(FedmapError, match="reference map is 3x3, the map is 40x40"):
        encode_map(m, reference=np.zeros((3, 3), np.uint8))


# ----------------------------------------------------------------------------- bad input


def test_malformed_payloads_are_rejected_in_one_line():
    m = _blobs((50, 60), seed=4)
    data = encode_map(m)
    cases = {
        "shorter than the header": data[:10],
        "CRC mismatch": data[:-9] + data[-8:],  # a byte lost
        "bad magic": b"XXXX" + data[4:],
        "format version": data[:4] + bytes([9]) + data[5:],
    }
    for i in range(len(data)):  # every single flipped byte is caught
        bad = bytearray(data)
        bad[i] ^= 0x10
        with pytest.raises(RejectedUpdate, match="^malformed map payload: "):
            decode_map(bytes(bad))
    for why, bad in cases.items():
        with pytest.raises(RejectedUpdate, match=why) as e:
            decode_map(bad)
        assert "\n" not in str(e.value)
    # a payload with a valid CRC but an impossible header
    head = mapcodec._HEADER.pack(mapcodec.MAGIC, mapcodec.VERSION, 0, 1 << 20, 1 << 20, 0)
    forged = head + struct_crc(head)
    with pytest.raises(RejectedUpdate, match="bad header"):
        decode_map(forged)
    # within the limit, a receiver that knows its grid refuses another shape before decoding
    head = mapcodec._HEADER.pack(mapcodec.MAGIC, mapcodec.VERSION, 0, 4096, 4096, 0)
    with pytest.raises(RejectedUpdate, match="a 4096x4096 map, expected 50x60"):
        decode_map(head + struct_crc(head), expected_shape=(50, 60))


def struct_crc(b: bytes) -> bytes:
    return zlib.crc32(b).to_bytes(4, "little")


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 4), np.uint8), "non-empty 2-D"),
    (np.zeros((2, 2, 2), np.uint8), "non-empty 2-D"),
    (np.full((3, 3), 0.5), "integer classes"),
    (np.full((3, 3), 3, np.uint8), "classes 0, 1, 2"),
    (np.full((3, 3), -1, np.int64), "classes 0, 1, 2"),
])
def test_bad_maps_are_refused(bad, message):
    with pytest.raises(FedmapError, match=message):
        encode_map(bad)


def test_context_is_an_image_codec_row():
    """Table III and the rate-distortion figure list it with the other lossless codecs."""
    m = load_truth(TerrainSource(terrain="moon", size=64)).classes
    codec = ImageCodec("context")
    payload, back = codec.roundtrip(m)
    np.testing.assert_array_equal(back, m)
    assert codec.lossless and payload == encode_map(m)
    with pytest.raises(RejectedUpdate, match="a 64x64 map, expected 64x65"):
        codec.decode(payload, (64, 65))


# ----------------------------------------------------------------------------- windows


def _brute_window(m: np.ndarray, background) -> tuple[int, int, int, int]:
    cells = [(r, c) for r in range(m.shape[0]) for c in range(m.shape[1])
             if m[r, c] != (background if np.isscalar(background) else background[r, c])]
    if not cells:
        return 0, 0, 0, 0
    rs, cs = [r for r, _ in cells], [c for _, c in cells]
    return min(rs), min(cs), max(rs) - min(rs) + 1, max(cs) - min(cs) + 1


@pytest.mark.parametrize("seed", range(6))
def test_the_window_is_every_changed_cell_and_no_more(seed):
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(1, 40, size=2))
    ref = rng.integers(0, 3, size=(h, w)).astype(np.uint8)
    m = np.full((h, w), UNKNOWN, np.uint8)
    new = ref.copy()
    for _ in range(int(rng.integers(0, 4))):  # a few changed patches (none: nothing differs)
        r, c = int(rng.integers(0, h)), int(rng.integers(0, w))
        m[r:r + 3, c:c + 5] = rng.integers(0, 2, size=m[r:r + 3, c:c + 5].shape)
        new[r:r + 2, c:c + 2] = (new[r:r + 2, c:c + 2] + 1) % 3
    assert mapcodec.changed_window(m, None) == _brute_window(m, UNKNOWN)
    assert mapcodec.changed_window(new, ref) == _brute_window(new, ref)
    _roundtrip(m)
    _roundtrip(new, reference=ref)


def test_a_small_update_on_a_large_grid_codes_its_window():
    """A rover's few new cells on a 2048x2048 grid: the payload is the window coded alone,
    plus the window's place (a few bytes)."""
    truth = _blobs((2048, 2048), seed=7, block=16)
    update = np.full(truth.shape, UNKNOWN, np.uint8)
    update[1500:1540, 300:364] = truth[1500:1540, 300:364]
    data = _roundtrip(update)
    alone = encode_map(truth[1500:1540, 300:364])
    assert data[5] & mapcodec._F_WINDOW
    assert len(data) - _window_fields(data) == len(alone)
    assert data[-len(alone) + mapcodec._HEADER.size:-4] == alone[mapcodec._HEADER.size:-4]  # the same coder words
    nothing = _roundtrip(np.full((300, 200), UNKNOWN, np.uint8))  # nothing to say: no coder words
    assert len(nothing) == HEAD + _window_fields(nothing) == HEAD + 4


def test_the_whole_grid_ablation_decodes_to_the_same_map_for_more_bytes():
    """``window=False`` (the ablation benchmarks/codec_window.py measures) codes every cell: the
    same map decodes, the payload carries no window and costs more than the windowed one."""
    truth = _blobs((256, 256), seed=3, block=8)
    update = np.full(truth.shape, UNKNOWN, np.uint8)
    update[100:140, 30:94] = truth[100:140, 30:94]
    whole, windowed = encode_map(update, window=False), encode_map(update)
    assert not whole[5] & mapcodec._F_WINDOW and windowed[5] & mapcodec._F_WINDOW
    assert np.array_equal(decode_map(whole), update) and np.array_equal(decode_map(windowed), update)
    assert len(whole) > len(windowed)


#: Payloads of format version 1 (whole grid, no window), written by fedmap before windows:
#: a 9x13 map, and the same map against a reference; both still decode.
V1_PLAIN = bytes.fromhex("464d434d0100090000000d00000079babefc1350811615fe03a37ee2d65b0c724cd72fe9557299020a1ee29eb4de")
V1_REFERENCE = bytes.fromhex("464d434d0101090000000d00000079babefca1dc3217d44f7b735d5791bafb995800aa4e25e5")


def test_version_1_payloads_still_decode():
    rng = np.random.default_rng(11)  # the maps they were made from
    m = rng.choice(3, p=[0.6, 0.3, 0.1], size=(9, 13)).astype(np.uint8)
    ref = m.copy()
    ref[2:5, 3:8] = UNKNOWN
    assert V1_PLAIN[4] == 1 and V1_REFERENCE[4] == 1
    np.testing.assert_array_equal(decode_map(V1_PLAIN), m)
    np.testing.assert_array_equal(decode_map(V1_REFERENCE, reference=ref), m)
    # a version-1 payload with the window bit is not one fedmap wrote
    bad = V1_PLAIN[:5] + bytes([mapcodec._F_WINDOW]) + V1_PLAIN[6:-4]
    with pytest.raises(RejectedUpdate, match="bad header"):
        decode_map(bad + struct_crc(bad))


@pytest.mark.parametrize("window, why", [
    ((0, 0, 3, 0), "bad window"),  # a height without a width
    ((5, 0, 6, 4), "bad window"),  # past the bottom of a 10x10 map
    ((0, 0, 10, 10), "bad window"),  # the whole grid is not a window
])
def test_a_bad_window_is_refused_in_one_line(window, why):
    head = mapcodec._HEADER.pack(mapcodec.MAGIC, mapcodec.VERSION, mapcodec._F_WINDOW, 10, 10, 0)
    head += b"".join(varint(v) for v in window) + bytes(4)
    with pytest.raises(RejectedUpdate, match=f"^malformed map payload: {why}"):
        decode_map(head + struct_crc(head))
    cut = mapcodec._HEADER.pack(mapcodec.MAGIC, mapcodec.VERSION, mapcodec._F_WINDOW, 10, 10, 0) + b"\x80\x80"
    with pytest.raises(RejectedUpdate, match="window is cut short"):
        decode_map(cut + struct_crc(cut))
