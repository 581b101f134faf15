"""What the predictor apps do, Flower-free: their run config, and the files a run leaves.

The predictor's federated fine-tuning on Flower (:mod:`fedmap.flower.predictor.server`,
:mod:`fedmap.flower.predictor.client`) is :func:`fedmap.training.predictorfed.federate` on
processes: one SuperNode per site, each holding its own samples (node config ``samples``:
a file of :func:`~fedmap.training.predictorfed.save_site_samples`; ``partition-id``: the
site's index, which seeds its rounds). Weights cross as fedmap ``fp32`` payloads
(:mod:`fedmap.federation.codecs`) in Flower records (:mod:`fedmap.flower.records`).

The server writes the global weights after every round as ``<out>/round{r}.safetensors``
and ``<out>/rounds.json`` (sites, counts, bytes per round); ``<out>.run/status.json`` says
how the run goes (:func:`fedmap.flower.task.write_status`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.nets.model import Weights
from fedmap.nets.predictor import load_predictor, save_predictor, shipped_predictor
from fedmap.training.predictorfed import FineTuning, predictor_from_weights, predictor_weights

#: The predictor app's run config and its defaults (``app/pyproject.toml``; a test checks they match).
PREDICTOR_RUN_DEFAULTS: dict = {"sites": 2, "rounds": 1, "local-steps": 40, "batch": 8, "crop": 96, "lr": 5e-4,
                                "seed": 0, "init": "", "out": "fedmap-out/predictor-federated",
                                "connect-timeout": 120.0, "deadline": 600.0}


@dataclass(frozen=True)
class PredictorRun:
    """The predictor app's run config, checked."""

    sites: int
    rounds: int
    training: FineTuning
    init: str  #: the weights file the rounds start from ("" : the shipped predictor)
    out: Path
    connect_timeout: float
    deadline: float

    @classmethod
    def from_run_config(cls, run_config: dict) -> PredictorRun:
        unknown = sorted(set(run_config) - set(PREDICTOR_RUN_DEFAULTS))
        if unknown:
            raise FedmapError(f"unknown predictor run config key(s): {', '.join(unknown)}")
        c = {**PREDICTOR_RUN_DEFAULTS, **run_config}
        try:
            run = cls(int(c["sites"]), int(c["rounds"]),
                      FineTuning(steps=int(c["local-steps"]), batch=int(c["batch"]), crop=int(c["crop"]),
                                 lr=float(c["lr"]), seed=int(c["seed"])),
                      str(c["init"]), Path(str(c["out"])), float(c["connect-timeout"]), float(c["deadline"]))
        except (TypeError, ValueError) as e:
            raise FedmapError(f"bad predictor run config: {e}") from None
        if run.sites < 1 or run.rounds < 1 or not run.deadline > 0 or not run.connect_timeout > 0:
            raise FedmapError(f"the predictor run needs sites >= 1, rounds >= 1 and positive waits, got {run_config}")
        return run

    def initial_weights(self) -> Weights:
        """The weights round 1 starts from."""
        return predictor_weights(load_predictor(self.init) if self.init else shipped_predictor())


def round_path(out: Path, r: int) -> Path:
    return Path(out) / f"round{r}.safetensors"


def save_round(out: Path, r: int, weights: Weights) -> Path:
    """The global weights after round ``r`` as a predictor file."""
    Path(out).mkdir(parents=True, exist_ok=True)
    return save_predictor(predictor_from_weights(weights), round_path(out, r), extra={"round": r})


def read_rounds(out: Path, rounds: int) -> list[Weights]:
    """The global weights of rounds 1..``rounds`` a run left in ``out``."""
    got = []
    for r in range(1, rounds + 1):
        p = round_path(out, r)
        if not p.is_file():
            raise FedmapError(f"the predictor run left no weights of round {r} ({p})")
        got.append(predictor_weights(load_predictor(p)))
    return got


def write_rounds_log(out: Path, log: dict) -> None:
    atomic_write_bytes(Path(out) / "rounds.json", json.dumps(log, indent=1).encode())


def read_rounds_log(out: Path) -> dict:
    return json.loads((Path(out) / "rounds.json").read_text())
