"""The bits-per-new-cell report's reference coders, against brute force."""

from __future__ import annotations

import math

import numpy as np

from conftest import maze
from fedmap.coding.mapcodec import ALPHA
from fedmap.experiments.cellstreams import TEMPLATE, cell_stream_report, quadtree_bytes, template_bits
from fedmap.maps.grid import UNKNOWN
from fedmap.mission import LinkConfig, MissionConfig


def _random_classes(shape, seed):
    rng = np.random.default_rng(seed)
    m = np.full(shape, UNKNOWN, np.uint8)
    m[2:9, 3:11] = rng.integers(0, 2, size=(7, 8))
    return m


def _quadtree_recursive(m: np.ndarray) -> int:
    """Inner nodes of the quadtree, by recursion (one byte each)."""
    if m.shape[0] == 1 or (m == m.flat[0]).all():
        return 0
    h = m.shape[0] // 2
    return 1 + sum(_quadtree_recursive(q) for q in (m[:h, :h], m[:h, h:], m[h:, :h], m[h:, h:]))


def test_quadtree_bytes_match_a_recursive_count():
    for seed in range(4):
        m = _random_classes((13, 11), seed)
        padded = np.full((16, 16), UNKNOWN, np.uint8)
        padded[:13, :11] = m
        assert quadtree_bytes(m) == _quadtree_recursive(padded)
    assert quadtree_bytes(np.full((8, 8), UNKNOWN, np.uint8)) == 0


def test_template_bits_match_a_sequential_adaptive_coder():
    m = _random_classes((12, 14), 7)
    h, w = m.shape
    counts: dict[int, list[float]] = {}
    bits = 0.0
    for r in range(h):  # raster order, the model updated after every cell
        for c in range(w):
            ctx = 0
            for dr, dc in TEMPLATE:
                rr, cc = r + dr, c + dc
                ctx = ctx * 3 + (int(m[rr, cc]) if 0 <= rr < h and 0 <= cc < w else UNKNOWN)
            n = counts.setdefault(ctx, [0.0, 0.0, 0.0])
            bits -= math.log2((n[m[r, c]] + ALPHA) / (sum(n) + 3 * ALPHA))
            n[m[r, c]] += 1
    assert math.isclose(template_bits(m), bits, rel_tol=1e-9)


def test_the_report_compares_every_coder_on_the_same_mission():
    config = MissionConfig(rovers=2, steps=40, sync_every=5, sensor_radius=4.0, eval_pairs=5,
                           link=LinkConfig(loss=0.2, seed=4))
    report = cell_stream_report(config, maze(48, 2, blocks=14))
    rows = {r["coder"]: r for r in report["rows"]}
    context = rows["context, per message (raw's body)"]
    full = rows["predictive (learned prior, derived mask, persistent)"]
    assert all(r["same_map"] for r in report["rows"] if r["coder"].startswith("predictive"))
    assert full["bytes"] < context["bytes"]
    # the generic coders all code raw's same messages
    assert len({(r["messages"], r["cells"]) for r in report["rows"] if not r["coder"].startswith("predictive")}) == 1
