"""What the link fuzzer feeds: one :class:`Target` per decoder of bytes that cross a link
or a disk (payload codecs, the map codec, the predictive coder, checkpoints, the ROS map
YAML and TOML readers), each with a valid sample to mutate. Shared by
``tests/test_fuzz_link.py`` and ``benchmarks/fuzz_link.py``.
"""

from __future__ import annotations

import tempfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from fedmap.errors import FedmapError


@dataclass(frozen=True)
class Target:
    """A decoder under fuzzing: ``decode(bytes)`` and a valid ``sample()``; ``crc``: the
    format ends with a CRC-32 of everything before it (mutations then keep it valid)."""

    name: str
    decode: Callable[[bytes], object]
    sample: Callable[[], bytes]
    crc: bool = False


def mutate(data: bytes, rng: np.random.Generator, *, crc: bool = False) -> bytes:
    """Flip, overwrite, insert, delete or truncate a few bytes (and fix a trailing CRC-32)."""
    b = bytearray(data[:-4] if crc and len(data) >= 4 else data)
    for _ in range(int(rng.integers(1, 5))):
        op = int(rng.integers(5))
        i = int(rng.integers(len(b) + 1))
        if op == 0 and b and i < len(b):
            b[i] ^= 1 << int(rng.integers(8))
        elif op == 1 and b and i < len(b):
            b[i] = int(rng.integers(256))
        elif op == 2:
            b[i:i] = rng.integers(0, 256, size=int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
        elif op == 3 and b:
            del b[i:i + int(rng.integers(1, 9))]
        else:
            b = b[:i]
    out = bytes(b)
    return out + zlib.crc32(out).to_bytes(4, "little") if crc else out


def run_case(target: Target, data: bytes) -> str:
    """``"ok"`` (decoded) or ``"rejected"`` (a one-line FedmapError); anything else fails."""
    try:
        target.decode(data)
    except FedmapError as e:
        assert "\n" not in str(e), f"{target.name}: a multi-line error: {e!r}"
        return "rejected"
    except Exception as e:  # noqa: BLE001 - the point: no other exception may escape
        raise AssertionError(f"{target.name}: {type(e).__name__}: {e}") from e
    return "ok"


# -- samples -----------------------------------------------------------------------------

def _weights(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"a.weight": rng.normal(size=(8, 6)).astype(np.float32), "a.bias": rng.normal(size=6).astype(np.float32),
            "grid": rng.normal(size=(2, 16, 16)).astype(np.float32)}


def _classes(seed: int = 0, n: int = 24) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.zeros((n, n), np.uint8)
    m[rng.random((n, n)) < 0.2] = 1
    m[: n // 3] = 2
    return m


def _payload(spec: str, update: bool) -> Callable[[], bytes]:
    def sample() -> bytes:
        from fedmap.federation.codecs import Encoder
        ref = _weights(0)
        return Encoder(spec).encode(_weights(1), ref if update else None)
    return sample


def _decode_payload(data: bytes) -> object:
    from fedmap.federation.codecs import decode
    return decode(data, _weights(0))


def _decode_map(data: bytes) -> object:
    from fedmap.coding.mapcodec import decode_map
    return decode_map(data, expected_shape=(24, 24))


def _decode_map_ref(data: bytes) -> object:
    from fedmap.coding.mapcodec import decode_map
    return decode_map(data, reference=_classes(1), expected_shape=(24, 24))


def _stream_kwargs() -> dict:
    from fedmap.coding.streamcodec import MOVES  # noqa: F401 - the module under test
    known = np.full((24, 24), 2, np.uint8)
    known[:4] = 0

    def candidates(tracks):
        out = np.zeros((24, 24), bool)
        for t in tracks:
            for r, c in t:
                out[max(r - 3, 0):r + 4, max(c - 3, 0):c + 4] = True
        return out
    return {"anchors": [(12, 12)], "mark_refs": [None], "known": known, "candidates": candidates}


def _stream_sample() -> bytes:
    from fedmap.coding import streamcodec as sc
    kw = _stream_kwargs()
    track = [(12, 13), (13, 14), (14, 14), (15, 13)]
    cand = kw["candidates"]([track]) & (kw["known"] == 2)
    cells = np.where(cand, _classes(2) % 2, 2).astype(np.uint8)
    return sc.encode(sc.Content([track], [(3, 3)], cells), state=sc.blank_state(), **kw)[0]


def _decode_stream(data: bytes) -> object:
    from fedmap.coding import streamcodec as sc
    return sc.decode(data, state=sc.blank_state(), **_stream_kwargs())


@cache
def _scratch() -> Path:
    """A scratch folder for the file readers' inputs, removed when the process ends."""
    import atexit
    import shutil
    path = Path(tempfile.mkdtemp(prefix="fedmap-fuzz-"))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


def checkpoint_folder(root: Path) -> Path:
    """A small valid base-station checkpoint in ``root``."""
    from fedmap.federation.runner import RoundRecord  # noqa: F401 - history entries
    from fedmap.flower.checkpoint import BaseState, write_checkpoint
    state = BaseState(2, _weights(0), {}, None, [], (24, 24), {"rounds": 3})
    return write_checkpoint(Path(root), state)


def _checkpoint_state_sample() -> bytes:
    return (checkpoint_folder(_scratch() / "sample") / "state.json").read_bytes()


def _checkpoint_copy() -> Path:
    """A fresh copy of the sample checkpoint to damage."""
    import shutil
    src = checkpoint_folder(_scratch() / "sample")
    dst = _scratch() / "case" / src.name
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst)
    return dst


def _read_checkpoint_state(data: bytes) -> object:
    from fedmap.flower.checkpoint import read_checkpoint
    dst = _checkpoint_copy()
    (dst / "state.json").write_bytes(data)
    return read_checkpoint(dst)


def _read_checkpoint_arrays(data: bytes) -> object:
    import hashlib
    import json

    from fedmap.flower.checkpoint import read_checkpoint
    dst = _checkpoint_copy()
    (dst / "arrays.npz").write_bytes(data)
    meta = json.loads((dst / "state.json").read_text())
    meta["arrays_sha256"] = hashlib.sha256(data).hexdigest()  # past the hash, into the reader
    (dst / "state.json").write_text(json.dumps(meta))
    return read_checkpoint(dst)


def _arrays_sample() -> bytes:
    return (checkpoint_folder(_scratch() / "sample") / "arrays.npz").read_bytes()


def _chain_sample() -> bytes:
    from fedmap.federation.codecs import Encoder
    from fedmap.federation.runner import pack_chain
    a, b, c = _weights(0), _weights(1), _weights(2)
    enc = Encoder("update-int8+zstd")
    return pack_chain([enc.encode(b, reference=a), Encoder("update-int8+zstd").encode(c, reference=b)])


def _apply_chain(data: bytes) -> object:
    from fedmap.federation.runner import apply_downlink, model_version
    held = _weights(0)
    return apply_downlink(held, "chain", data, model_version(held))


_ROS_YAML = b"image: map.pgm\nresolution: 0.05\norigin: [-10.0, -10.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n" \
            b"free_thresh: 0.196\nmode: trinary\n"


def _parse_ros(data: bytes) -> object:
    from fedmap.maps.ros import parse_map_yaml
    return parse_map_yaml(data.decode("utf-8", errors="replace"))


_MISSION_TOML = b'seed = 0\n[terrain]\nkind = "builtin"\nterrain = "mars"\nsize = 64\n[mission]\nrovers = 3\n' \
                b'steps = 40\n[link]\nloss = 0.1\nuplink_bytes = 2000\n[strategies.predictive]\nprior = "none"\n'


def _read_mission_toml(data: bytes) -> object:
    from fedmap.mission.settings import load_mission
    path = _scratch() / "mission.toml"
    path.write_bytes(data)
    return load_mission(path)


TARGETS: dict[str, Target] = {t.name: t for t in (
    Target("payload fp32", _decode_payload, _payload("fp32", False), crc=True),
    Target("payload int8+zstd", _decode_payload, _payload("int8+zstd", False), crc=True),
    Target("payload update-int4+zstd", _decode_payload, _payload("update-int4+zstd", True), crc=True),
    Target("payload topk", _decode_payload, _payload("topk:0.1,values=int8", True), crc=True),
    Target("map codec", _decode_map, lambda: __import__("fedmap.coding.mapcodec", fromlist=["x"]).encode_map(
        _classes(0)), crc=True),
    Target("map codec with a reference", _decode_map_ref,
           lambda: __import__("fedmap.coding.mapcodec", fromlist=["x"]).encode_map(_classes(0),
                                                                                       reference=_classes(1)),
           crc=True),
    Target("predictive message", _decode_stream, _stream_sample),
    Target("chain of broadcasts", _apply_chain, _chain_sample),
    Target("checkpoint state.json", _read_checkpoint_state, _checkpoint_state_sample),
    Target("checkpoint arrays.npz", _read_checkpoint_arrays, _arrays_sample),
    Target("ROS map YAML", _parse_ros, lambda: _ROS_YAML),
    Target("mission TOML", _read_mission_toml, lambda: _MISSION_TOML),
)}
