"""Fuzzing what crosses the link (hypothesis): every decoder gets random and mutated bytes
and must answer with a clean one-line FedmapError (or a well-formed result), never another
exception, an allocation past its bounds, or a hang.

Mutations keep a payload's trailing CRC-32 valid where it has one, so they reach the
parser behind the check. ``python benchmarks/fuzz_link.py`` runs the same targets for
100,000 cases.
"""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fedmap.errors import FedmapError
from fuzz_targets import TARGETS, mutate, run_case

FAST = settings(max_examples=400, deadline=2000, suppress_health_check=[HealthCheck.too_slow,
                                                                         HealthCheck.function_scoped_fixture])
#: Bytes a decoder may allocate for one fuzzed input (the largest legitimate payload here
#: decodes to a few MB; the declared bound of the map decoder is 16 Mcells).
ALLOC_BOUND = 64 << 20


@pytest.fixture(scope="module", autouse=True)
def _warm():
    """Import and run every decoder once on its valid sample (imports are not the decoder's
    time or memory), and check that the sample decodes."""
    for target in TARGETS.values():
        assert run_case(target, target.sample()) == "ok", target.name


@pytest.mark.parametrize("name", sorted(TARGETS))
@FAST
@given(data=st.data())
def test_a_decoder_answers_mutated_input_with_a_clean_error(name, data):
    target = TARGETS[name]
    seed = data.draw(st.integers(0, 2**32 - 1))
    payload = mutate(target.sample(), np.random.default_rng(seed), crc=target.crc)
    tracemalloc.start()
    try:
        outcome = run_case(target, payload)
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert outcome in ("ok", "rejected")
    assert peak < ALLOC_BOUND, f"{name} allocated {peak / 2**20:.0f} MB for a {len(payload)}-byte input"


@pytest.mark.parametrize("name", sorted(TARGETS))
@FAST
@given(raw=st.binary(max_size=300))
def test_a_decoder_answers_random_bytes_with_a_clean_error(name, raw):
    assert run_case(TARGETS[name], raw) in ("ok", "rejected")


def test_run_case_lets_only_one_line_fedmap_errors_through():
    class Boom:
        name = "boom"
        crc = False

        @staticmethod
        def decode(data):
            raise KeyError("names")

    with pytest.raises(AssertionError, match="KeyError"):
        run_case(Boom, b"x")  # type: ignore[arg-type]


def test_a_damaged_checkpoint_state_is_a_one_line_error(tmp_path: Path):
    from fedmap.flower.checkpoint import read_checkpoint
    from fuzz_targets import checkpoint_folder
    folder = checkpoint_folder(tmp_path)
    meta = json.loads((folder / "state.json").read_text())
    for key in ("names", "round", "shape", "history", "moments", "run_config"):
        broken = {k: v for k, v in meta.items() if k != key}
        (folder / "state.json").write_text(json.dumps(broken))
        with pytest.raises(FedmapError, match="checkpoint") as e:
            read_checkpoint(folder)
        assert "\n" not in str(e.value)


def test_a_table_declaring_more_scales_than_its_body_holds_is_refused_before_allocating():
    """Found by ``benchmarks/fuzz_link.py`` (case 75,536): a mutated int8 payload declared a
    tensor of shape (28,391,276,056, 0), zero entries but 28 billion per-channel scales, and
    the decoder tried to allocate 212 GiB for them."""
    target = TARGETS["payload int8+zstd"]
    rng = np.random.default_rng([0, 75536])
    rng.random()  # the benchmark's draw between random bytes and a mutation
    _assert_rejected_within_bound(target, mutate(target.sample(), rng, crc=target.crc))


def test_a_zstd_header_claiming_a_huge_size_is_not_allocated_before_decoding():
    """Found by this fuzzer: a 173-byte update-int4+zstd payload whose damaged zstd header
    claimed 1.5 GB made the one-shot decompressor allocate it all before failing."""
    target = TARGETS["payload update-int4+zstd"]
    _assert_rejected_within_bound(target, mutate(target.sample(), np.random.default_rng(1_030_443_533), crc=target.crc))


def _assert_rejected_within_bound(target, payload: bytes) -> None:
    tracemalloc.start()
    try:
        assert run_case(target, payload) == "rejected"
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < ALLOC_BOUND
