"""The ``predictive`` coder's learned initial state: the meta-initialisation idea applied
to the coder.

:func:`learn_coder_prior` runs a ``predictive`` mission on every map of a collection (by
default the built-in Earth-like collection of the meta-initialisation, never a test
site), sums what every link's coder state learned (its counts at the end minus a blank
state's), and scales each context down to at most ``total`` counts, so the shipped state
predicts from the first message and still adapts quickly to a new site.
:func:`save_coder_prior` writes it where :func:`fedmap.coding.streamcodec.initial_state`
reads it (``fedmap/weights/cell_prior.npz``); ``fedmap meta coder`` does both.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import replace
from importlib import resources
from pathlib import Path

import numpy as np

from fedmap._util import atomic_write_bytes
from fedmap.coding.streamcodec import PARTS, PRIOR_FILE, CoderState, blank_state
from fedmap.meta.collections import MapCollection, earth_like
from fedmap.mission.ends.predictive import PredictiveBase
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import run_mission

#: Largest count total per context in the shipped state (a new site outweighs it quickly).
PRIOR_TOTAL = 64


def _scaled(a: np.ndarray, total: int) -> np.ndarray:
    """Every context (last axis) with more than ``total`` counts scaled down to about
    ``total``, keeping its proportions; a class seen at all keeps at least one count."""
    t = a.sum(axis=-1, keepdims=True)
    scale = np.where(t > total, total / np.maximum(t, 1), 1.0)
    out = np.rint(a * scale).astype(np.int64)
    return np.where((a > 0) & (out == 0), 1, out)


def learn_coder_prior(collection: MapCollection | None = None, *, steps: int = 150, rovers: int = 4,
                      total: int = PRIOR_TOTAL, seed: int = 0,
                      on_map: Callable[[int, int], None] | None = None) -> CoderState:
    """A coder state learned on ``collection`` (default: :func:`~fedmap.meta.collections.earth_like`
    at 128², 4 maps per category). ``on_map(done, total)`` follows the progress."""
    coll = collection if collection is not None else earth_like(size=128, per_category=4, seed=seed)
    maps = [m for ms in coll.categories.values() for m in ms]
    learned = blank_state()
    config = replace(MissionConfig(), rovers=rovers, steps=steps, strategies=("predictive",), seed=seed)
    for i, truth in enumerate(maps):
        base = run_mission(config, truth, frames=1).runs["predictive"].sharing.base
        assert isinstance(base, PredictiveBase)
        for state in (*base.up, *base.down):  # the base end's coder state of every link, both ways
            for name in PARTS:
                # the counts this state learned (a state folds from the shipped prior; subtract it)
                getattr(learned, name)[...] += getattr(state, name) - getattr(base.initial, name)
        if on_map is not None:
            on_map(i + 1, len(maps))
    cells, moves, lengths, marks = (_scaled(np.maximum(getattr(learned, n), 0), total) for n in PARTS)
    return CoderState(cells, moves, lengths, marks)


def prior_path() -> Path:
    """Where the shipped coder prior lives (inside the installed package)."""
    return Path(str(resources.files("fedmap.weights").joinpath(PRIOR_FILE)))


def save_coder_prior(state: CoderState, path: str | Path | None = None) -> Path:
    """Write ``state`` as the coder prior (atomically: a crash leaves the old file whole)."""
    out = Path(path) if path is not None else prior_path()
    buf = io.BytesIO()
    np.savez_compressed(buf, **{n: getattr(state, n).astype(np.uint16) for n in PARTS})
    atomic_write_bytes(out, buf.getvalue())
    return out
