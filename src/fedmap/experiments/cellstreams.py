"""Bits per new cell: what each way of coding a rover's newly observed cells costs, on the
stream of uplink messages of a real mission.

The stream is ``raw``'s: every uplink message ``raw`` delivered in the mission, each a
class map of the cells the rover observed since its last delivered message (UNKNOWN
elsewhere). On those same messages, each codec codes every message on its own:

* ``zstd`` / ``lzma`` of the 2-bit class codes of the whole map (4 cells per byte);
* ``quadtree``: the OctoMap binary scheme, 2 bits per child of every inner node (unknown,
  free, impassable, or inner), over the map padded to a power of two;
* ``JBIG-style template``: an adaptive model of each cell in raster order given its 10
  causal neighbours (2 above-above, 5 above, 2 left, as JBIG's three-line template), 3
  classes, counts restarted per message. Its ideal code length (computed exactly from
  the final counts; an arithmetic coder adds at most 2 bytes), not real bytes;
* ``context``: the body of ``raw``'s real message (fedmap's ``context`` codec, its own
  18-byte header and CRC included, the 16-byte position header not).

Then the ``predictive`` strategy on the same mission, in full and with each part
switched off (``[strategies.predictive]``: its learned prior, its derived mask, its
persistent state): its real uplink bytes, every header, trail, target and check byte
included. It does not resend cells the rover received from the others, so it carries
fewer cells; the last column divides every row by the same count (the cells of the
base's final map), so the rows compare as totals.
"""

from __future__ import annotations

import lzma
import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import zstandard
from scipy.special import gammaln

from fedmap.coding.mapcodec import ALPHA, decode_map
from fedmap.experiments.bandwidth import pack_2bit
from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.mission.ends.predictive import PredictiveRover
from fedmap.mission.ends.protocol import unpack_up
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import run_mission

#: The JBIG-style template: (drow, dcol) of the 10 causal neighbours of a cell.
TEMPLATE = ((-2, -1), (-2, 0), (-2, 1), (-1, -2), (-1, -1), (-1, 0), (-1, 1), (-1, 2), (0, -2), (0, -1))
#: The predictive variants measured: label -> ``[strategies.predictive]`` options.
VARIANTS: dict[str, dict[str, str]] = {
    "predictive (learned prior, derived mask, persistent)": {},
    "predictive, no learned prior": {"prior": "none"},
    "predictive, state restarted per message": {"state": "per-message"},
    "predictive, mask coded (not derived)": {"mask": "coded"},
}


def quadtree_bytes(classes: np.ndarray) -> int:
    """Bytes of the OctoMap-style binary quadtree of a class map (2 bits per child of every
    inner node; a block is a leaf when all its cells hold one class, padding UNKNOWN)."""
    h, w = classes.shape
    side = 1 << max(0, (max(h, w) - 1).bit_length())
    m = np.full((side, side), UNKNOWN, dtype=np.int16)
    m[:h, :w] = classes
    lo, hi = m.copy(), m.copy()
    inner = 0
    s = 1
    while s < side:  # blocks of 2s: uniform when min == max over the block
        lo = lo.reshape(side // (2 * s), 2, side // (2 * s), 2).min(axis=(1, 3))
        hi = hi.reshape(side // (2 * s), 2, side // (2 * s), 2).max(axis=(1, 3))
        s *= 2
        inner += int((lo != hi).sum())
    return inner  # 4 children x 2 bits = 1 byte per inner node


def template_bits(classes: np.ndarray) -> float:
    """Ideal code length (bits) of a class map in raster order with an adaptive model of
    the :data:`TEMPLATE` context (outside the map reads UNKNOWN), additive prior ALPHA.

    For a sequential additive estimator the total code length depends only on each
    context's final counts: sum over contexts of ``lgamma(n + 3a) - lgamma(3a) -
    sum_s (lgamma(n_s + a) - lgamma(a))``, in nats."""
    h, w = classes.shape
    pad = np.full((h + 2, w + 4), UNKNOWN, dtype=np.int64)
    pad[2:, 2:-2] = classes
    ctx = np.zeros((h, w), dtype=np.int64)
    for dr, dc in TEMPLATE:
        ctx = ctx * 3 + pad[2 + dr:2 + dr + h, 2 + dc:2 + dc + w]
    counts = np.zeros((3**len(TEMPLATE), 3), dtype=np.int64)
    np.add.at(counts, (ctx.ravel(), classes.ravel().astype(np.int64)), 1)
    used = counts[counts.sum(axis=1) > 0]
    nats = (gammaln(used.sum(axis=1) + 3 * ALPHA) - gammaln(3 * ALPHA)
            - (gammaln(used + ALPHA) - gammaln(ALPHA)).sum(axis=1)).sum()
    return float(nats / math.log(2))


def _lzma(data: bytes) -> bytes:
    return lzma.compress(data, format=lzma.FORMAT_RAW, filters=[{"id": lzma.FILTER_LZMA2, "preset": 9}])


def cell_stream_report(config: MissionConfig, truth: GridMap, *, elevation: np.ndarray | None = None,
                       prior: np.ndarray | None = None, on_stage: Callable[[str], None] | None = None) -> dict:
    """The bits-per-new-cell table of one mission (see the module docstring)."""
    say = on_stage or (lambda _s: None)
    say("raw")
    raw = run_mission(replace(config, strategies=("raw",)), truth, elevation=elevation, prior=prior,
                      frames=1).runs["raw"].sharing
    received = raw.journal.received  # what the base merged, as it got it
    messages = [decode_map(unpack_up(p)[3], expected_shape=truth.shape) for _, _, p in received]
    bodies = [len(unpack_up(p)[3]) for _, _, p in received]
    carried = int(sum((m != UNKNOWN).sum() for m in messages))
    final = int((raw.global_map() != UNKNOWN).sum())
    say("generic codecs")
    zc = zstandard.ZstdCompressor(level=19)
    sizes = {
        "zstd of 2-bit codes": sum(len(zc.compress(pack_2bit(m))) for m in messages),
        "lzma of 2-bit codes": sum(len(_lzma(pack_2bit(m))) for m in messages),
        "quadtree (OctoMap binary)": sum(quadtree_bytes(m) for m in messages),
        "JBIG-style 10-cell template (ideal)": sum(math.ceil(template_bits(m) / 8) for m in messages),
        "context, per message (raw's body)": sum(bodies),
    }
    rows: list[dict] = [{"coder": k, "messages": len(messages), "cells": carried, "bytes": v} for k, v in sizes.items()]
    for label, opts in VARIANTS.items():
        say(label)
        c = replace(config, strategies=("predictive",), methods={**config.methods, "predictive": opts})
        run = run_mission(c, truth, elevation=elevation, prior=prior, frames=1).runs["predictive"]
        s = run.sharing
        assert all(isinstance(r, PredictiveRover) for r in s.rovers)
        up = [m for m in run.ledger if m.direction == "up" and m.status == "delivered"]
        cells = int(sum(r.delivered_cells.sum() for r in s.rovers))
        rows.append({"coder": label, "messages": len(up), "cells": cells, "bytes": sum(m.bytes for m in up),
                     "same_map": bool(np.array_equal(s.global_map(), raw.global_map()))})
    for r in rows:
        r["bits_per_cell"] = 8 * r["bytes"] / max(r["cells"], 1)
        r["bits_per_map_cell"] = 8 * r["bytes"] / max(final, 1)
    return {"final_map_cells": final, "rows": rows}


def markdown(report: dict, title: str) -> str:
    """The report as a markdown table."""
    lines = [f"**{title}** (uplink messages delivered; the base's final map has {report['final_map_cells']:,} "
             "cells)", "", "| coder | messages | cells carried | bytes | bits per carried cell | "
             "bits per cell of the final map |", "|---|---:|---:|---:|---:|---:|"]
    for r in report["rows"]:
        lines.append(f"| {r['coder']} | {r['messages']} | {r['cells']:,} | {r['bytes']:,} | "
                     f"{r['bits_per_cell']:.3f} | {r['bits_per_map_cell']:.3f} |")
    return "\n".join(lines) + "\n"
