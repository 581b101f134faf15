"""Federated fine-tuning of the map predictor across sites (issue 35, part 3).

A *site* is a mission's base station with its own final map. Every site fine-tunes the
shipped predictor (:mod:`fedmap.nets.predictor`) on its own map, and a server averages
the sites' weights with FedAvg (:class:`fedmap.federation.aggregate.FedAvg`, the one
implementation of aggregation). No map leaves its site: what crosses is weights.

* :func:`site_maps` runs a ``raw`` mission on a site and keeps every member's map every
  ``every`` steps (its unknown cells are shaped by exploration: trails, sensor footprints,
  line of sight, what the others shared), the base station's map at the end (the site's
  *final map*) and, for scoring only, the truth and which cells nobody had observed.
* :func:`fine_tuning_samples`: what a site trains on: the members' maps as inputs and
  the site's **final map** as the target (never the truth: a real site does not have it;
  a cell the base never observed is not in the loss).
* :func:`local_round`: one site's fine-tuning from given weights (Adam, a constant
  learning rate; one thread, deterministic algorithms, every draw from the seed, the round
  and the site: the same inputs give the same weights bit for bit).
* :func:`fedavg_predictor`: FedAvg of predictor weights, weighted by the sites' sample counts.
* :func:`federate`, :func:`pooled`, :func:`alone`: R rounds of federated fine-tuning, the
  same on all sites' samples on one machine, and on one site's samples only.
* :func:`evaluate_predictor`: accuracy, impassable IoU, Brier score and ECE of the
  predictor's guesses on a held-out site's cells that nobody had observed.

The Flower apps that run :func:`local_round` on one SuperNode per site and
:func:`fedavg_predictor` on the server are in :mod:`fedmap.flower.predictor.server` and
:mod:`fedmap.flower.predictor.client`; they give the same weights as :func:`federate`.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import CALIBRATION_BINS, prediction_scores
from fedmap.federation.aggregate import FedAvg
from fedmap.maps.grid import IMPASSABLE, UNKNOWN, GridMap
from fedmap.mission.settings import MissionConfig
from fedmap.mission.sim import run_mission
from fedmap.nets.model import Weights, get_weights, set_weights
from fedmap.nets.predictor import (
    MapPredictor,
    PredictorConfig,
    known_rate,
    one_hot,
    one_thread,
    predict,
    training_batch,
    unknown_cell_loss,
)

#: The steps of a held-out site's mission its predictions are scored at (as ``benchmarks/predictor.py``).
SCORED_STEPS = (50, 100, 150, 200)
#: Bins of the expected calibration error.
BINS = CALIBRATION_BINS


@dataclass(frozen=True)
class SiteMaps:
    """What one mission on a site leaves: every member's map every ``every`` steps, the base
    station's final map, and (for scoring a held-out site only) the truth."""

    name: str
    beliefs: np.ndarray  #: (N, H, W) classes: every member's map, every ``every`` steps from step ``every``
    steps: np.ndarray  #: (N,) the step of each map
    nobody: np.ndarray  #: (N, H, W) bool: unknown in every member's map at that step, known in the truth
    final: np.ndarray  #: (H, W) classes: the base station's map at the end of the mission (the site's map)
    truth: np.ndarray  #: (H, W) classes: the ground truth (scoring only; never trained on)

    def __len__(self) -> int:
        return len(self.beliefs)

    def join(self, other: SiteMaps) -> SiteMaps:
        """Two missions on the same site (e.g. two seeds), one after the other; the first's final map."""
        if other.truth.shape != self.truth.shape:
            raise FedmapError(f"site {self.name}: maps of {self.truth.shape} and {other.truth.shape} do not join")
        return replace(self, beliefs=np.concatenate([self.beliefs, other.beliefs]),
                       steps=np.concatenate([self.steps, other.steps]),
                       nobody=np.concatenate([self.nobody, other.nobody]))


def site_maps(config: MissionConfig, truth: GridMap, *, name: str = "site", every: int = 10,
              elevation: np.ndarray | None = None, profiles: dict[str, np.ndarray] | None = None,
              thresholds=None) -> SiteMaps:
    """A ``raw`` mission of ``config`` on ``truth`` (no predictor), its maps kept (see
    :class:`SiteMaps`). ``elevation``, ``profiles`` and ``thresholds`` as for
    :func:`~fedmap.mission.sim.run_mission` (line of sight needs the elevation)."""
    if every < 1:
        raise FedmapError(f"every must be >= 1, got {every}")
    cfg = replace(config, strategies=("raw",), predictor="none")
    beliefs: list[np.ndarray] = []
    steps: list[int] = []
    nobody: list[np.ndarray] = []
    final: list[np.ndarray] = []
    known = truth.classes != UNKNOWN

    def keep(snap) -> None:
        if snap.step == cfg.steps:
            final.append(snap.global_map.copy())
        if snap.step and snap.step % every == 0:
            unseen = np.all([b == UNKNOWN for b in snap.beliefs], axis=0) & known
            for b in snap.beliefs:
                beliefs.append(b.copy())
                steps.append(snap.step)
                nobody.append(unseen)

    run_mission(cfg, truth, elevation=elevation, profiles=profiles, thresholds=thresholds, frames=1,
                on_snapshot=keep)
    if not beliefs or not final:
        raise FedmapError(f"site {name}: the mission of {cfg.steps} steps kept no map (every={every})")
    return SiteMaps(name, np.stack(beliefs).astype(np.uint8), np.asarray(steps, dtype=np.int64),
                    np.stack(nobody), final[0].astype(np.uint8), truth.classes.astype(np.uint8))


def fine_tuning_samples(site: SiteMaps) -> tuple[np.ndarray, np.ndarray]:
    """``(beliefs, targets)``, both ``(N, H, W)``: a site's members' maps and, as the target
    of every one, the site's final map (cells the base never observed are UNKNOWN there
    and stay out of the loss). The truth is not used."""
    return site.beliefs, np.broadcast_to(site.final, site.beliefs.shape).copy()


def save_site_samples(path: str | os.PathLike, beliefs: np.ndarray, targets: np.ndarray) -> Path:
    """A site's fine-tuning samples as one ``.npz`` (what a site's SuperNode reads), atomically."""
    buf = io.BytesIO()
    np.savez_compressed(buf, beliefs=np.asarray(beliefs, dtype=np.uint8), targets=np.asarray(targets, dtype=np.uint8))
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def load_site_samples(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``(beliefs, targets)`` written by :func:`save_site_samples` (one-line errors)."""
    p = Path(path)
    if not p.is_file():
        raise FedmapError(f"no such site samples file: {p}")
    try:
        with np.load(p, allow_pickle=False) as z:
            b, t = z["beliefs"], z["targets"]
    except (OSError, KeyError, ValueError) as e:
        raise FedmapError(f"{p} is not a site samples file ({type(e).__name__}: {e})".splitlines()[0]) from e
    _check_samples(b, t, str(p))
    return b.astype(np.uint8), t.astype(np.uint8)


def _check_samples(beliefs: np.ndarray, targets: np.ndarray, what: str) -> None:
    if beliefs.ndim != 3 or beliefs.shape != targets.shape or not len(beliefs):
        raise FedmapError(f"{what}: need (N, H, W) beliefs and targets of one shape, got {beliefs.shape} and "
                          f"{targets.shape}")


# -- one site's round, and the server's average ----------------------------------------------

@dataclass(frozen=True)
class FineTuning:
    """How a site fine-tunes the predictor in one round."""

    steps: int = 40  #: Adam steps per round (Adam's moments start afresh every round)
    batch: int = 8  #: maps per step
    crop: int = 96  #: side of the random square crop of every map
    lr: float = 5e-4  #: constant Adam learning rate
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("steps", "batch", "crop"):
            if getattr(self, name) < 1:
                raise FedmapError(f"fine-tuning {name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0:
            raise FedmapError(f"fine-tuning lr must be > 0, got {self.lr}")


def predictor_weights(model: MapPredictor) -> Weights:
    """The predictor's whole state (weights and ``base_rate``) as ``{name: float32 array}``."""
    return get_weights(model)


def predictor_from_weights(weights: Weights, config: PredictorConfig | None = None) -> MapPredictor:
    """A predictor holding ``weights`` (names and shapes checked)."""
    model = MapPredictor(config)
    set_weights(model, weights)
    return model.eval()


def local_round(weights: Weights, beliefs: np.ndarray, targets: np.ndarray, training: FineTuning, *,
                round: int, site: int, config: PredictorConfig | None = None,
                on_step: Callable[[int, float], None] | None = None) -> Weights:
    """One site's fine-tuning round: the predictor holding ``weights`` trained for
    ``training.steps`` Adam steps on the site's ``(N, H, W)`` ``beliefs`` and ``targets``
    (binary cross-entropy of P(impassable) on the cells unknown in the belief and known in
    the target, random crops and the 8 rotations/reflections, as
    :func:`~fedmap.nets.predictor.train_predictor`). The loss is on the probabilities
    :func:`~fedmap.nets.predictor.predict` gives: every map's logits are moved by its
    base-rate correction ``logit(known_rate(map)) - logit(base_rate)``, and ``base_rate``
    stays the offline model's, so the fine-tuning learns what that correction misses at the
    site (setting ``base_rate`` to the site's rate instead made the first rounds' guesses
    worse: the network had not followed yet). Every draw comes from
    ``(training.seed, round, site)``; one thread, deterministic algorithms: the same inputs
    give the same weights bit for bit, in any process."""
    b, y = np.asarray(beliefs, dtype=np.uint8), np.asarray(targets, dtype=np.uint8)
    _check_samples(b, y, f"site {site}")
    t = training
    rng = np.random.default_rng(np.random.SeedSequence([t.seed, round, site, 3535]))
    with one_thread(deterministic=True):
        model = predictor_from_weights(weights, config).train()
        # the base-rate correction predict() applies, per map (the whole map's known cells, as predict sees them)
        shift = np.array([_logit(known_rate(x)) for x in b]) - _logit(float(model.base_rate))
        opt = torch.optim.Adam(model.parameters(), lr=t.lr)
        for step in range(1, t.steps + 1):
            idx, xb, target, weight = training_batch(b, y, rng, t.batch, t.crop)
            logits = model(one_hot(xb))[:, 0] + torch.from_numpy(shift[idx].astype(np.float32))[:, None, None]
            loss = unknown_cell_loss(logits, target, weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if on_step is not None:
                on_step(step, loss.item())
        return predictor_weights(model.eval())


def _logit(p: float) -> float:
    return float(np.log(p) - np.log1p(-p))


def fedavg_predictor(updates: Sequence[Weights], counts: Sequence[float]) -> Weights:
    """FedAvg of the sites' predictor weights: ``sum_k (n_k / n) w_k`` per tensor (the
    ``base_rate`` too, which fine-tuning leaves as it was), with ``n_k`` a site's sample
    count (:class:`~fedmap.federation.aggregate.FedAvg`: float64 sums, float32 out)."""
    return FedAvg().aggregate({}, list(updates), [float(c) for c in counts])


# -- runs ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Site:
    """A site's fine-tuning samples (what stays at the site)."""

    name: str
    beliefs: np.ndarray
    targets: np.ndarray

    @classmethod
    def of(cls, maps: SiteMaps) -> Site:
        return cls(maps.name, *fine_tuning_samples(maps))

    @property
    def count(self) -> int:
        """FedAvg's weight of the site: its number of maps."""
        return len(self.beliefs)


def federate(init: Weights, sites: Sequence[Site], training: FineTuning, rounds: int, *,
             config: PredictorConfig | None = None,
             on_round: Callable[[int, Weights], None] | None = None) -> list[Weights]:
    """``rounds`` rounds of FedAvg: every site (index ``k``) runs :func:`local_round` from
    the global weights, the server averages them in site order. Returns the global weights
    after every round (``[round 1, ..., round R]``). ``config``: the network's shape (default: the shipped one's)."""
    if rounds < 1 or not sites:
        raise FedmapError("federated fine-tuning needs at least one round and one site")
    held, out = init, []
    for r in range(1, rounds + 1):
        updates = [local_round(held, s.beliefs, s.targets, training, round=r, site=k, config=config)
                   for k, s in enumerate(sites)]
        held = fedavg_predictor(updates, [s.count for s in sites])
        out.append(held)
        if on_round is not None:
            on_round(r, held)
    return out


def pooled(init: Weights, sites: Sequence[Site], training: FineTuning, rounds: int, *,
           config: PredictorConfig | None = None) -> list[Weights]:
    """All sites' samples on one machine: ``rounds`` rounds of :func:`local_round` on their
    union (the same Adam steps per round as one site's round). Weights after every round."""
    joined = Site("pooled", np.concatenate([s.beliefs for s in sites]), np.concatenate([s.targets for s in sites]))
    return alone(init, joined, training, rounds, config=config)


def alone(init: Weights, site: Site, training: FineTuning, rounds: int, *, index: int = 0,
          config: PredictorConfig | None = None) -> list[Weights]:
    """One site fine-tuning by itself for ``rounds`` rounds. Weights after every round."""
    held, out = init, []
    for r in range(1, rounds + 1):
        held = local_round(held, site.beliefs, site.targets, training, round=r, site=index, config=config)
        out.append(held)
    return out


# -- scoring on a held-out site --------------------------------------------------------------

def evaluate_predictor(model: MapPredictor, site: SiteMaps, *, at: Sequence[int] | None = SCORED_STEPS) -> dict:
    """The predictor's guesses on ``site``'s cells nobody had observed (truth known), on
    every member's map at the steps ``at`` (None: every kept map): accuracy (P(impassable)
    > 1/2), impassable IoU, Brier score, ECE (:data:`BINS` equal bins), and an "all free"
    guess's accuracy beside them. ``predict`` with its base-rate correction, as rovers use it."""
    keep = np.ones(len(site), dtype=bool) if at is None else np.isin(site.steps, list(at))
    ps, ys = [], []
    for b, m in zip(site.beliefs[keep], site.nobody[keep]):
        if not m.any():
            continue
        _, p_imp = predict(model, b)
        ps.append(p_imp[m].astype(np.float64))
        ys.append(site.truth[m] == IMPASSABLE)
    if not ps:
        raise FedmapError(f"site {site.name}: no cell nobody observed at steps {list(at or [])}")
    return scores(np.concatenate(ps), np.concatenate(ys))


def scores(p: np.ndarray, y: np.ndarray) -> dict:
    """Accuracy, impassable IoU, Brier, ECE of P(impassable) ``p`` against ``y`` (bool: impassable)."""
    return prediction_scores(p, y)


# -- the four-way comparison -----------------------------------------------------------------

METHODS = ("federated", "pooled", "offline")  #: beside them, one "alone:<site>" per training site


def compare(init: Weights, sites: Sequence[Site], held_out: SiteMaps, training: FineTuning, rounds: int, *,
            federated: list[Weights] | None = None, at: Sequence[int] | None = SCORED_STEPS,
            on_progress: Callable[[str], None] | None = None) -> dict:
    """Federated vs pooled vs the offline model (``init``) vs each site alone, scored on
    ``held_out`` after every round (:func:`evaluate_predictor`). ``federated``: the global
    weights of every round when they were made elsewhere (Flower), else :func:`federate`
    runs in process. Returns ``{"rounds": R, "sites": [...], "held_out": name, "counts":
    {...}, "offline": scores, "per_round": {method: [scores of round 1..R]}, "final": {method: scores}}``."""
    say = on_progress or (lambda _: None)
    runs: dict[str, list[Weights]] = {}
    if federated is None:
        say("federated")
    runs["federated"] = federated if federated is not None else federate(init, sites, training, rounds)
    if len(runs["federated"]) != rounds:
        raise FedmapError(f"{len(runs['federated'])} federated rounds given, {rounds} asked")
    say("pooled")
    runs["pooled"] = pooled(init, sites, training, rounds)
    for k, s in enumerate(sites):
        say(f"alone:{s.name}")
        runs[f"alone:{s.name}"] = alone(init, s, training, rounds, index=k)
    say("scoring")
    offline = evaluate_predictor(predictor_from_weights(init), held_out, at=at)
    per_round = {name: [evaluate_predictor(predictor_from_weights(w), held_out, at=at) for w in ws]
                 for name, ws in runs.items()}
    final = {"offline": offline, **{name: rows[-1] for name, rows in per_round.items()}}
    return {"rounds": rounds, "sites": [s.name for s in sites], "held_out": held_out.name,
            "counts": {s.name: s.count for s in sites}, "training": asdict(training), "offline": offline,
            "per_round": per_round, "final": final,
            "federated_minus_pooled": final["federated"]["accuracy"] - final["pooled"]["accuracy"],
            "federated_minus_offline": final["federated"]["accuracy"] - offline["accuracy"]}


def plot_rounds(results: Sequence[dict], path: str | os.PathLike, *, metric: str = "accuracy") -> Path:
    """One panel per comparison (:func:`compare`): ``metric`` on the held-out site after every
    round, federated vs pooled vs offline vs each site alone; written as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.6), squeeze=False, sharey=False)
    for ax, res in zip(axes[0], results):
        r = np.arange(0, res["rounds"] + 1)
        off = res["offline"][metric]
        style = {"federated": dict(color="tab:blue", lw=2.2), "pooled": dict(color="tab:orange", lw=2, ls="--")}
        others = iter(["tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"] * 8)
        for name, rows in res["per_round"].items():
            ys = [off, *(row[metric] for row in rows)]
            kw = style.get(name) or dict(lw=1, alpha=0.8, color=next(others))
            ax.plot(r, ys, marker="o", ms=3, label=name, **kw)
        ax.axhline(off, color="grey", ls=":", lw=1.5, label="offline (shipped)")
        ax.axhline(res["offline"]["accuracy_all_free"] if metric == "accuracy" else np.nan, color="k", lw=0.8,
                   alpha=0.4, label="all free" if metric == "accuracy" else None)
        ax.set_title(f"held out: {res['held_out']}", fontsize=10)
        ax.set_xlabel("round")
        ax.set_ylabel(f"{metric} on cells nobody observed")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


__all__ = ["BINS", "METHODS", "SCORED_STEPS", "FineTuning", "Site", "SiteMaps", "alone", "evaluate_predictor", "federate",
           "compare", "fedavg_predictor", "fine_tuning_samples", "load_site_samples", "local_round", "plot_rounds", "pooled",
           "predictor_from_weights", "predictor_weights", "save_site_samples", "scores", "site_maps"]
