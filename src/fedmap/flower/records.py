"""fedmap payloads inside Flower records, and Flower's own count of their size.

A payload (:mod:`fedmap.federation.codecs` bytes) travels as one 1-D ``uint8`` array under the key
``"payload"`` of an ``ArrayRecord``. Flower serialises an array with ``np.save``, so its
own count (``ArrayRecord.count_bytes()``) is the payload plus the ``.npy`` header plus the
key: :func:`flower_overhead` says exactly how much, and :func:`check_flower_count`
cross-checks the two accountings.
"""

from __future__ import annotations

import io

import numpy as np
from flwr.app import Array, ArrayRecord

from fedmap.errors import FedmapError

KEY = "payload"


def to_record(payload: bytes) -> ArrayRecord:
    """An ``ArrayRecord`` holding ``payload`` as a ``uint8`` array (empty bytes allowed)."""
    return ArrayRecord({KEY: Array(np.frombuffer(payload, dtype=np.uint8).copy())})


def from_record(record: ArrayRecord | None) -> bytes:
    """The payload bytes carried by :func:`to_record`."""
    if record is None or KEY not in record:
        raise FedmapError(f"message carries no fedmap payload (no {KEY!r} array)")
    arr = record[KEY].numpy()
    if arr.dtype != np.uint8 or arr.ndim != 1:
        raise FedmapError(f"fedmap payload must be a 1-D uint8 array, got {arr.dtype} {arr.shape}")
    return arr.tobytes()


def flower_overhead(n_bytes: int) -> int:
    """What Flower's ``count_bytes`` adds to an ``n_bytes`` payload: ``.npy`` header + key."""
    buf = io.BytesIO()
    np.save(buf, np.zeros(n_bytes, dtype=np.uint8), allow_pickle=False)
    return len(buf.getvalue()) - n_bytes + len(KEY)


def check_flower_count(record: ArrayRecord, n_bytes: int) -> int:
    """Flower's size of ``record``; raises when it disagrees with the fedmap payload size."""
    counted = record.count_bytes()
    if counted != n_bytes + flower_overhead(n_bytes):
        raise FedmapError(f"byte accounting mismatch: Flower counts {counted} B for a {n_bytes} B fedmap payload")
    return counted
