"""The map predictor's shipped weights, learned offline from missions on Earth-like maps.

:func:`exploration_samples` runs a ``raw`` mission on every map of a collection (by
default the built-in Earth-like collection of the meta-initialisation, never a test site)
and keeps, every ``every`` steps, the map every rover holds: its own observations (trails,
sensor footprints) and what the others shared with it, beside the truth. Those are the
maps a rover runs the predictor on, so the training masks are shaped like exploration.
Half the maps are explored with the default sensor radius, half with a shorter one (as in
the CADRE presets), so the network sees both footprints.

:func:`learn_predictor` fits :class:`~fedmap.nets.predictor.MapPredictor` to them
(:func:`~fedmap.nets.predictor.train_predictor`); :func:`save_shipped_predictor` writes
``fedmap/weights/predictor.safetensors``. ``fedmap meta-predictor`` does all three; the
same options and seed give the same file, byte for byte.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from fedmap.errors import FedmapError
from fedmap.meta.collections import MapCollection, earth_like
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import run_mission
from fedmap.nets.predictor import (
    SHIPPED_PREDICTOR,
    MapPredictor,
    PredictorConfig,
    PredictorTraining,
    save_predictor,
    train_predictor,
)

#: The sensor radii the maps of a collection are explored with, in turn (cells).
RADII = (8.0, 5.0)


def check_every(every: int, steps: int, names: tuple[str, str] = ("every", "steps")) -> None:
    """``every`` (a rover's map is kept every that many steps) in [1, ``steps``], else a one-line
    error naming them as ``names`` (the CLI's flags)."""
    if not 1 <= every <= steps:
        raise FedmapError(f"{names[0]} must be in [1, {names[1]}] = [1, {steps}] (a rover's map is kept every that "
                          f"many steps), got {every}")


def exploration_samples(collection: MapCollection | None = None, *, steps: int = 150, rovers: int = 4,
                        every: int = 10, seed: int = 0,
                        on_map: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(beliefs, truths)``, both ``(N, H, W)`` classes: every rover's map every ``every``
    steps (from step ``every``) of a ``raw`` mission on every map of ``collection``
    (default: :func:`~fedmap.meta.collections.earth_like` at 128², 6 maps per category).
    ``on_map(done, total)`` follows the progress."""
    check_every(every, steps)
    coll = collection if collection is not None else earth_like(size=128, per_category=6, seed=seed)
    maps = coll.maps()
    beliefs: list[np.ndarray] = []
    truths: list[np.ndarray] = []
    for i, truth in enumerate(maps):
        config = replace(MissionConfig(), rovers=rovers, steps=steps, strategies=("raw",), seed=seed + i,
                         sensor_radius=RADII[i % len(RADII)])

        def keep(snap) -> None:
            if snap.step and snap.step % every == 0:
                for b in snap.beliefs:
                    beliefs.append(b.copy())
                    truths.append(truth.classes)

        run_mission(config, truth, frames=1, on_snapshot=keep)
        if on_map is not None:
            on_map(i + 1, len(maps))
    return np.stack(beliefs).astype(np.uint8), np.stack(truths).astype(np.uint8)


def learn_predictor(collection: MapCollection | None = None, *, steps: int = 150, every: int = 10,
                    config: PredictorConfig | None = None, training: PredictorTraining | None = None, seed: int = 0,
                    on_map: Callable[[int, int], None] | None = None,
                    on_step: Callable[[int, float], None] | None = None) -> MapPredictor:
    """A predictor learned from missions on ``collection`` (see :func:`exploration_samples`);
    ``training`` defaults to :class:`~fedmap.nets.predictor.PredictorTraining` with ``seed``."""
    beliefs, truths = exploration_samples(collection, steps=steps, every=every, seed=seed, on_map=on_map)
    return train_predictor(beliefs, truths, config=config, training=training or PredictorTraining(seed=seed),
                           on_step=on_step)


def save_shipped_predictor(model: MapPredictor, path: str | Path | None = None, *, extra: dict | None = None) -> Path:
    """Write ``model`` where the mission reads the shipped predictor (or to ``path``), atomically."""
    return save_predictor(model, SHIPPED_PREDICTOR if path is None else path, extra=extra)
