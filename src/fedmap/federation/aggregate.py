"""Aggregation math: the one implementation used by the in-process runner and Flower.

Everything works on ``Weights`` (``{name: float32 array}``) so it does not care who
trained the models or how they travelled.

* **FedAvg** (McMahan et al. 2017): ``theta = sum_k (n_k / n) theta_k`` with ``n_k`` the
  agent's number of known cells.
* **FedAdam / FedYogi** (Reddi et al. 2021, Algorithm 2): the server treats the averaged
  update ``delta = avg_k(theta_k) - theta`` as a pseudo-gradient::

      m <- beta1 * m + (1 - beta1) * delta
      v <- beta2 * v + (1 - beta2) * delta^2                          (Adam)
      v <- v - (1 - beta2) * delta^2 * sign(v - delta^2)              (Yogi)
      theta <- theta + eta * m / (sqrt(v) + tau)

  with ``m`` and ``v`` starting at 0 (Reddi et al. start ``v`` at ``tau^2``; the
  ``v0`` option sets it) and no bias correction, as in the paper. Note that in round 1
  the step is ``eta * 0.1 * delta / (sqrt(0.01 delta^2 + ...) + tau)`` ~ ``eta * sign(delta)``
  when ``|delta| >> tau``: every weight moves by about ``eta`` whatever the agents did,
  so ``eta`` must be small for one-shot federation.

* **Coverage-aware FedAvg** (``coverage``): each parameter entry is averaged only over
  the agents that actually changed it, ``theta_j = sum_k n_k t_kj theta_kj / sum_k n_k t_kj``
  with ``t_kj = 1`` when agent k's decoded weight differs from the global weight it
  started from; an entry no agent touched keeps the global value. For encodings whose
  parameters are local in space (feature grids) this makes the one-shot global model the
  union of the local fits instead of a blur of them. For a dense network (every agent
  touches every weight) it reduces to FedAvg.

The averaging is done in float64 and the result cast back to float32.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from fedmap.errors import FedmapError
from fedmap.nets.model import Weights


class Aggregator(Protocol):
    """What the base station needs of an aggregation rule (FedAvg, FedAdam, ...)."""

    name: str

    def aggregate(self, global_w: Weights, updates: list[Weights], counts: list[float]) -> Weights: ...

    def hyperparameters(self) -> dict: ...


def _check_updates(updates: list[Weights], counts: list[float]) -> None:
    if not updates:
        raise FedmapError("no agent updates to aggregate")
    if len(updates) != len(counts):
        raise FedmapError(f"{len(updates)} updates but {len(counts)} weights")
    names = list(updates[0])
    for i, u in enumerate(updates):
        if set(u) != set(names):
            raise FedmapError(f"update {i} has different tensors from update 0")
        for k in names:
            if np.shape(u[k]) != np.shape(updates[0][k]):
                raise FedmapError(f"update {i}: tensor {k!r} has shape {np.shape(u[k])}, expected {np.shape(updates[0][k])}")
    c = np.asarray(counts, dtype=np.float64)
    if (c < 0).any() or not np.isfinite(c).all() or c.sum() <= 0:
        raise FedmapError(f"aggregation weights must be non-negative with a positive sum, got {counts}")


def weighted_average(updates: list[Weights], counts: list[float]) -> Weights:
    """``sum_k (n_k / n) w_k`` per tensor, computed in float64, returned as float32."""
    _check_updates(updates, counts)
    c = np.asarray(counts, dtype=np.float64)
    c = c / c.sum()
    return {
        k: sum(ck * np.asarray(u[k], dtype=np.float64) for ck, u in zip(c, updates)).astype(np.float32)
        for k in updates[0]
    }


@dataclass
class FedAvg:
    """Weighted average of the agents' weights; stateless."""

    name: str = field(default="fedavg", init=False)

    def aggregate(self, global_w: Weights, updates: list[Weights], counts: list[float]) -> Weights:
        return weighted_average(updates, counts)

    def hyperparameters(self) -> dict:
        return {}


def _touched_mean(reference: np.ndarray, weighted: list[tuple[np.ndarray, float]], fallback: np.ndarray) -> np.ndarray:
    """Per entry, the weighted mean of the ``weighted`` ``(values, weight)`` whose entry
    differs from ``reference``; ``fallback`` where none does. float64 in, float32 out."""
    # in place, with ``where=``: the same sums as adding np.where(touched, weight * v, 0.0),
    # without two model-sized float64 temporaries per update (0.5 GB each at 4096²)
    num = np.zeros_like(reference)
    den = np.zeros_like(reference)
    for values, weight in weighted:
        v = np.array(values, dtype=np.float64)  # a copy: scaled in place below
        touched = v != reference
        v *= weight
        np.add(num, v, out=num, where=touched)
        np.add(den, weight, out=den, where=touched)
        del v
    some = den > 0
    np.maximum(den, 1e-300, out=den)
    np.divide(num, den, out=num)
    np.copyto(num, fallback, where=~some)
    return num.astype(np.float32)


def coverage_average(global_w: Weights, updates: list[Weights], counts: list[float]) -> Weights:
    """Per-entry weighted average over the agents whose value differs from ``global_w``."""
    _check_updates(updates, counts)
    c = np.asarray(counts, dtype=np.float64)
    out: Weights = {}
    for k, g in global_w.items():
        g64 = np.asarray(g, dtype=np.float64)
        out[k] = _touched_mean(g64, [(u[k], float(ck)) for ck, u in zip(c, updates)], g64)
    return out


def metropolis_weight(degree_a: int, degree_b: int) -> float:
    """Metropolis-Hastings weight of the edge between two agents of degrees ``degree_a`` and
    ``degree_b`` (Xiao & Boyd 2004): ``1 / (1 + max(d_a, d_b))``. With every agent keeping
    ``1 - sum`` of its edges' weights for itself, the mixing matrix is symmetric and doubly
    stochastic, so repeated mixing on a connected graph converges to the plain average."""
    if degree_a < 1 or degree_b < 1:
        raise FedmapError(f"an edge joins agents of degree >= 1, got {degree_a} and {degree_b}")
    return 1.0 / (1.0 + max(degree_a, degree_b))


def metropolis_mix(own: Weights, neighbours: list[tuple[Weights, float]], *,
                   untouched: Weights | None = None) -> Weights:
    """One decentralised averaging step (DSGD-style gossip) at one agent:
    ``w <- (1 - sum_j m_j) w + sum_j m_j w_j`` over the ``neighbours``' ``(w_j, m_j)``
    (their Metropolis weights, :func:`metropolis_weight`), in float64, cast to float32.

    With ``untouched`` (the model every agent started from), the step is coverage-aware
    as :func:`coverage_average` is: per entry, the weights are renormalised over the agents
    (itself included) whose entry differs from ``untouched``; an entry none of them touched
    keeps the agent's own value. For a dense network that every agent trains this is the
    plain step."""
    m = np.asarray([mj for _, mj in neighbours], dtype=np.float64)
    if (m < 0).any() or m.sum() > 1 + 1e-12:
        raise FedmapError(f"Metropolis weights must be non-negative and sum to at most 1, got {m.tolist()}")
    self_w = 1.0 - float(m.sum())
    out: Weights = {}
    for k, v in own.items():
        mine = np.asarray(v, dtype=np.float64)
        if untouched is None:
            acc = self_w * mine
            for (w, mj) in neighbours:
                acc = acc + mj * np.asarray(w[k], dtype=np.float64)
            out[k] = acc.astype(np.float32)
            continue
        base = np.asarray(untouched[k], dtype=np.float64)
        out[k] = _touched_mean(base, [(mine, self_w), *((w[k], mj) for w, mj in neighbours)], mine)
    return out


def admm_consensus(dual: np.ndarray, midpoints: list[np.ndarray], rho: float) -> np.ndarray:
    """The minimiser of C-ADMM's primal objective without a data term (an agent with no map):
    ``argmin_theta <theta, dual> + rho sum_j ||theta - m_j||^2 = (sum_j m_j - dual / (2 rho)) / J``
    with ``m_j`` the ``midpoints`` ``(theta_i + theta_j) / 2`` of its ``J`` links."""
    if not midpoints or rho <= 0:
        raise FedmapError("the consensus step needs at least one link and rho > 0")
    return (np.sum(midpoints, axis=0) - np.asarray(dual, dtype=np.float64) / (2 * rho)) / len(midpoints)


@dataclass
class CoverageAvg:
    """FedAvg per parameter entry over the agents that touched it; stateless."""

    name: str = field(default="coverage", init=False)

    def aggregate(self, global_w: Weights, updates: list[Weights], counts: list[float]) -> Weights:
        return coverage_average(global_w, updates, counts)

    def hyperparameters(self) -> dict:
        return {}


def check_server_settings(name: str, *, eta: float, beta1: float, beta2: float, tau: float, v0: float = 0.0) -> None:
    """The server optimiser's settings (FedAdam, FedYogi) in range, else a one-line error
    naming ``name``; checked whatever the aggregator, so a typo waits for no switch to FedAdam."""
    if not (math.isfinite(eta) and eta > 0 and math.isfinite(tau) and tau > 0 and math.isfinite(v0) and v0 >= 0):
        raise FedmapError(f"{name}: eta and tau must be finite and positive and v0 >= 0 "
                          f"(got eta={eta}, tau={tau}, v0={v0})")
    if not (0 <= beta1 < 1 and 0 <= beta2 < 1):
        raise FedmapError(f"{name}: betas must be in [0, 1), got {beta1}, {beta2}")


@dataclass
class _FedOpt:
    """Shared server-optimiser state for FedAdam and FedYogi."""

    eta: float = 1e-2
    beta1: float = 0.9
    beta2: float = 0.99
    tau: float = 1e-3
    v0: float = 0.0
    m: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    v: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    if TYPE_CHECKING:  # each subclass sets ``name`` as an init=False field; not a field here

        @property
        def name(self) -> str: ...

    def __post_init__(self) -> None:
        check_server_settings(self.name, eta=self.eta, beta1=self.beta1, beta2=self.beta2, tau=self.tau, v0=self.v0)

    def _second_moment(self, v: np.ndarray, d2: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def aggregate(self, global_w: Weights, updates: list[Weights], counts: list[float]) -> Weights:
        avg = weighted_average(updates, counts)
        out: Weights = {}
        for k, g in global_w.items():
            g64 = np.asarray(g, dtype=np.float64)
            delta = avg[k].astype(np.float64) - g64
            m = self.m.get(k, np.zeros_like(g64))
            v = self.v.get(k, np.full_like(g64, self.v0))
            m = self.beta1 * m + (1 - self.beta1) * delta
            v = self._second_moment(v, delta * delta)
            self.m[k], self.v[k] = m, v
            out[k] = (g64 + self.eta * m / (np.sqrt(v) + self.tau)).astype(np.float32)
        return out

    def hyperparameters(self) -> dict:
        return {k: v for k, v in asdict(self).items() if k in ("eta", "beta1", "beta2", "tau", "v0")}


@dataclass
class FedAdam(_FedOpt):
    name: str = field(default="fedadam", init=False)

    def _second_moment(self, v: np.ndarray, d2: np.ndarray) -> np.ndarray:
        return self.beta2 * v + (1 - self.beta2) * d2


@dataclass
class FedYogi(_FedOpt):
    name: str = field(default="fedyogi", init=False)

    def _second_moment(self, v: np.ndarray, d2: np.ndarray) -> np.ndarray:
        return v - (1 - self.beta2) * d2 * np.sign(v - d2)


AGGREGATORS: dict[str, type] = {"fedavg": FedAvg, "fedadam": FedAdam, "fedyogi": FedYogi, "coverage": CoverageAvg}


def make_aggregator(name: str, **hparams: float | None) -> Aggregator:
    """Build an aggregator by name; FedAdam/FedYogi take eta, beta1, beta2, tau, v0."""
    key = name.lower()
    if key not in AGGREGATORS:
        raise FedmapError(f"unknown aggregator {name!r}; choose one of {', '.join(AGGREGATORS)}")
    if key in ("fedavg", "coverage"):
        return AGGREGATORS[key]()
    return AGGREGATORS[key](**{k: v for k, v in hparams.items() if v is not None})
