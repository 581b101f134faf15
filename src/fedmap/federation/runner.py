"""In-process federation: distribute -> local fit -> encode/send -> aggregate, R rounds.

Every payload really goes through bytes (``serialise_weights``) in both directions and
the model is rebuilt from the decoded bytes, so the byte counts are what a link carries.
An agent whose training diverges or whose update is not finite is dropped for that round
(recorded in the history); the round aggregates the survivors.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from fedmap.errors import FedmapError
from fedmap.federation.aggregate import make_aggregator
from fedmap.maps.grid import GridMap, check_same_frame
from fedmap.model import NetConfig, Weights, build_model, deserialise_weights, get_weights, serialise_weights, set_weights
from fedmap.training import TrainConfig, fit, steps_per_epoch


@dataclass(frozen=True)
class FederationConfig:
    rounds: int = 1
    aggregator: str = "fedavg"
    eta: float = 1e-2  # FedAdam / FedYogi server learning rate
    beta1: float = 0.9
    beta2: float = 0.99
    tau: float = 1e-3
    local: TrainConfig = field(default_factory=TrainConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rounds < 1:
            raise FedmapError(f"rounds must be >= 1, got {self.rounds}")
        make_aggregator(self.aggregator, eta=self.eta, beta1=self.beta1, beta2=self.beta2, tau=self.tau)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class FederationResult:
    weights: Weights
    history: list[dict]
    aggregator: dict

    def total_bytes(self) -> dict:
        up = sum(sum(r["uplink_bytes"].values()) for r in self.history)
        down = sum(sum(r["downlink_bytes"].values()) for r in self.history)
        return {"uplink": up, "downlink": down}


def agent_seed(seed: int, round_idx: int, agent: int) -> int:
    """Independent, reproducible seed per (run, round, agent)."""
    return int(np.random.SeedSequence([seed, round_idx, agent]).generate_state(1)[0])


def total_local_steps(local_maps: list[GridMap], config: FederationConfig) -> int:
    return sum(config.rounds * config.local.epochs * steps_per_epoch(m.classes.size, config.local) for m in local_maps)


def run_federation(
    init_weights: Weights,
    net_config: NetConfig,
    local_maps: list[GridMap],
    config: FederationConfig,
    *,
    on_step: Callable[[int, float], None] | None = None,
    on_round: Callable[[dict], None] | None = None,
) -> FederationResult:
    """Run ``config.rounds`` rounds of federated fitting of ``local_maps``."""
    check_same_frame(local_maps)
    aggregator = make_aggregator(config.aggregator, eta=config.eta, beta1=config.beta1, beta2=config.beta2, tau=config.tau)
    global_w = {k: np.asarray(v, dtype=np.float32) for k, v in init_weights.items()}
    model = build_model(net_config)
    history: list[dict] = []
    for r in range(config.rounds):
        t0 = time.perf_counter()
        down_payload = serialise_weights(global_w)
        updates, counts, losses, dropped = [], [], {}, {}
        up_bytes, down_bytes = {}, {}
        for k, local in enumerate(local_maps):
            down_bytes[k] = len(down_payload)
            set_weights(model, deserialise_weights(down_payload))
            try:
                steps = fit(model, local, config.local, seed=agent_seed(config.seed, r, k), on_step=on_step)
                w = get_weights(model)
                if not all(np.isfinite(v).all() for v in w.values()):
                    raise FedmapError("update holds NaN or infinite weights")
            except FedmapError as e:
                dropped[k] = str(e)
                continue
            up_payload = serialise_weights(w)
            up_bytes[k] = len(up_payload)
            updates.append(deserialise_weights(up_payload))
            counts.append(local.n_known)
            losses[k] = steps[-1] if steps else None
        if not updates:
            raise FedmapError(f"round {r + 1}: every agent's update was dropped ({'; '.join(dropped.values())})")
        global_w = aggregator.aggregate(global_w, updates, counts)
        rec = {
            "round": r + 1, "final_loss": losses, "weights": dict(zip(losses, counts)), "dropped": dropped,
            "uplink_bytes": up_bytes, "downlink_bytes": down_bytes, "seconds": time.perf_counter() - t0,
        }
        history.append(rec)
        if on_round is not None:
            on_round(rec)
    return FederationResult(global_w, history, {"name": config.aggregator, **aggregator.hyperparameters()})
