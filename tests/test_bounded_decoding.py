"""Every decoder of network bytes is bounded by what its header announces and by a sane limit:
a payload that lies is refused in one line before anything large is allocated.

The bombs are real zstd/zlib streams whose frames declare their (huge) content size, made
chunk by chunk so the test itself never holds what they expand to."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest
import zstandard

from fedmap._util import inflate_zlib, inflate_zstd
from fedmap.errors import RejectedUpdate
from fedmap.mission.network.nodelog import MAX_ENTRY_MAPS, RoverEntry
from fedmap.mission.network.remote import CorruptMessage, Report, pack_frame


def zstd_bomb(size: int, *, declare: bool = True) -> bytes:
    """A zstd frame of ``size`` zero bytes (its header declaring the size when ``declare``)."""
    c = zstandard.ZstdCompressor(level=1).compressobj(size=size if declare else -1)
    chunk, out, left = bytes(1 << 20), [], size
    while left > 0:
        out.append(c.compress(chunk[:min(left, len(chunk))]))
        left -= min(left, len(chunk))
    out.append(c.flush())
    return b"".join(out)


def hostile_entry(n: int, h: int, w: int, maps: bytes) -> bytes:
    """A rover's log entry (what ``fedmap score`` reads from a run folder) announcing ``n``
    steps of ``h`` x ``w`` maps, its maps ``maps``."""
    state = [1, [0, 0], None, 0.0, 0]
    header = {"kind": "rover-log", "strategy": "raw", "rover": 0, "mission": "m", "step": n, "trail": [],
              "states": [state] * n}
    return pack_frame(header, [struct.pack("<II", h, w) + maps])


def test_inflate_stops_at_the_limit_it_is_given():
    small = zstandard.ZstdCompressor().compress(b"abc" * 100)
    assert inflate_zstd(small, 300) == b"abc" * 100
    with pytest.raises(ValueError, match="more than the 299 bytes"):
        inflate_zstd(small, 299)
    with pytest.raises(ValueError, match="zstd"):
        inflate_zstd(b"not zstd at all", 1000)
    z = zlib.compress(b"x" * 5000)
    assert inflate_zlib(z, 5000) == b"x" * 5000
    with pytest.raises(ValueError, match="more than"):
        inflate_zlib(z, 4999)


def test_a_log_that_announces_a_gigabyte_is_refused_in_one_line_with_little_memory(tmp_path):
    """A 1 GiB announcement (6 steps of 8192x8192 maps, a frame declaring 1 GiB) is refused
    before decoding; a log entry whose maps decode beyond what it announces is refused as
    soon as they do. A fresh process's peak RSS grows by less than 100 MB either way."""
    announced = hostile_entry(6, 8192, 8192, zstd_bomb(1 << 30))
    assert len(announced) < 100_000
    lying = hostile_entry(1, 2048, 2048, zstd_bomb(1 << 30))  # announces 12 MiB, decodes to 1 GiB
    for name, raw in (("announced", announced), ("lying", lying)):
        (tmp_path / name).write_bytes(raw)
    code = f"""
import resource, sys
from pathlib import Path
from fedmap.mission.network.nodelog import RoverEntry
from fedmap.mission.network.wire import CorruptMessage
for name in ("announced", "lying"):
    raw = Path({str(tmp_path)!r}, name).read_bytes()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    try:
        RoverEntry.from_bytes(raw)
        print(name, "ACCEPTED")
    except CorruptMessage as e:
        print(name, "refused:", e)
    print(name, "peak+", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = dict(line.split(" ", 1) for line in r.stdout.splitlines())
    out = r.stdout
    assert "ACCEPTED" not in out, out
    assert "more than an entry may hold" in out and "more than the 12582912 bytes announced" in out, out
    for name in ("announced", "lying"):
        extra_kib = int([ln for ln in out.splitlines() if ln.startswith(f"{name} peak+")][0].split("+ ")[1])
        assert extra_kib < 100 * 1024, (name, extra_kib, lines)


def test_a_log_of_another_maps_shape_is_refused_where_the_mission_is_known():
    raw = hostile_entry(1, 64, 64, zstandard.ZstdCompressor().compress(bytes(3 * 64 * 64)))
    assert len(RoverEntry.from_bytes(raw).states) == 1
    with pytest.raises(CorruptMessage, match="64x64, the mission's are 128x128"):
        RoverEntry.from_bytes(raw, shape=(128, 128))
    assert 3 * 8192 * 8192 * 2 > MAX_ENTRY_MAPS  # the limit is below what the largest sides allow


@pytest.mark.parametrize("header", [{"kind": "report"}, {"kind": "report", "uplink": 5},
                                    {"kind": "report", "pos": [1], "uplink": None}, {"kind": "rover-log"},
                                    {"kind": "rover-log", "states": 5}, {"kind": "rover-log", "states": [[1]]},
                                    {"kind": "base-log", "held": [0]}])
def test_a_header_of_the_wrong_layout_is_a_corrupt_message_not_a_crash(header):
    from fedmap.mission.network.nodelog import BaseRecord

    kind = {"report": Report, "rover-log": RoverEntry, "base-log": BaseRecord}[header["kind"]]
    with pytest.raises(CorruptMessage):
        kind.from_bytes(pack_frame(header, [b""] * (2 if kind is BaseRecord else 1)))


def test_a_weights_payload_whose_zstd_frame_lies_about_its_size_is_rejected():
    from fedmap.federation.codecs import Encoder, decode

    w = {"a": np.linspace(-1, 1, 4000, dtype=np.float32)}
    payload = bytearray(Encoder("fp32+zstd").encode(w))
    # the frame after the prefix: swap it for a bomb declaring the same size but decoding to 64 MiB
    from fedmap.federation import codecs

    content = bytes(payload[codecs._PREFIX:-4])
    size = zstandard.frame_content_size(content)
    assert size > 0
    c = zstandard.ZstdCompressor().compressobj(size=-1)  # no declared size: refused as implausible
    bomb = c.compress(bytes(64 << 20)) + c.flush()
    forged = bytes(payload[:codecs._PREFIX]) + bomb
    forged += struct.pack("<I", zlib.crc32(forged))
    with pytest.raises(RejectedUpdate, match="malformed payload"):
        decode(forged)
    assert np.array_equal(decode(bytes(payload))["a"], w["a"])


def test_a_rosgrid_zlib_bomb_is_not_a_grid():
    from fedmap.mission.ends.rosgrid import GridCodec

    codec = GridCodec((32, 32), resolution=1.0, origin=(0.0, 0.0), sync_every=1, level=9)
    classes = np.zeros((32, 32), np.uint8)
    assert codec.decode(codec.encode(classes, 3)) is not None
    d = zlib.compressobj(9)
    bomb = b"".join(d.compress(bytes(1 << 20)) for _ in range(64)) + d.flush()
    assert codec.decode(bomb) is None


def test_a_height_network_payload_claiming_a_huge_network_or_map_is_rejected_before_it_is_built():
    from fedmap.nets.heightfield import decode_heightnet

    for config, shape in (({"mapping": 32, "hidden": 1 << 20, "layers": 3}, [64, 64]),
                          ({"mapping": 32, "hidden": 32, "layers": 3}, [1 << 20, 1 << 20])):
        head = json.dumps({"config": config, "mean": 0.0, "std": 1.0, "shape": shape}).encode()
        with pytest.raises(RejectedUpdate, match="beyond the limits"):
            decode_heightnet(struct.pack("<I", len(head)) + head + zstandard.ZstdCompressor().compress(b"\0" * 10))


def test_an_update_whose_table_declares_a_huge_tensor_is_refused_before_it_is_made():
    """A top-k update names the tensors it updates; one whose table declares a tensor of 13.7
    billion entries (51 GiB of float32, found by the link fuzzer) is checked against the
    model it updates and refused in one line, before anything of that size is allocated."""
    import zlib

    from fedmap.federation.codecs import Encoder, decode

    def weights(seed):
        return {"a.bias": np.random.default_rng(seed).normal(size=6).astype(np.float32)}

    raw = Encoder("topk:0.5,values=int8").encode(weights(1), weights(0))
    assert decode(raw, weights(0))["a.bias"].shape == (6,)
    table = bytes([1, 0, 6]) + b"a.bias" + bytes([1, 6])  # one tensor "a.bias" of shape (6,), by hand
    assert raw[7:7 + len(table)] == table
    huge, n = bytearray(), 13_705_992_032
    while True:  # the dimension as a LEB128 varint
        huge.append((n & 0x7F) | (0x80 if n >> 7 else 0))
        n >>= 7
        if not n:
            break
    body = raw[:7] + table[:-1] + bytes(huge) + raw[7 + len(table):-4]
    hostile = body + struct.pack("<I", zlib.crc32(body))
    with pytest.raises(RejectedUpdate, match=r"'a.bias' has shape \(6,\), expected \(13705992032,\)"):
        decode(hostile, weights(0))
