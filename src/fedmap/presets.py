"""Named federated-mapping methods, one place for every command and benchmark.

``paper``  the source paper: Fourier MLP, UNKNOWN trained as grey, FedAvg, fp32 payloads.
``fedmap`` feature grids + frozen decoder, masked loss, coverage-aware FedAvg, int4 update
           uplink and int8 update downlink (both zstd-compressed).
"""

from __future__ import annotations

from fedmap.errors import FedmapError
from fedmap.federation.runner import FederationConfig
from fedmap.pipeline import PipelineConfig
from fedmap.training import TrainConfig

METHODS: dict[str, dict] = {
    "paper": {"net": "paper", "aggregator": "fedavg", "lr": 1e-3, "masked": False, "uplink": "fp32", "downlink": "fp32"},
    "fedmap": {"net": "grid", "aggregator": "coverage", "lr": 0.05, "masked": True, "uplink": "update-int4+zstd",
               "downlink": "update-int8+zstd"},
}


def method_settings(method: str, **overrides) -> dict:
    """The method's settings with ``overrides`` (None values are ignored) applied."""
    if method not in METHODS:
        raise FedmapError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return {**METHODS[method], **{k: v for k, v in overrides.items() if v is not None}}


def method_config(method: str, *, rounds: int = 1, epochs: int = 100, seed: int = 0, central: bool = True,
                  eval_pairs: int = 75, **overrides) -> PipelineConfig:
    """A :class:`PipelineConfig` for a named method (``overrides``: net, aggregator, lr, masked,
    uplink, downlink)."""
    s = method_settings(method, **overrides)
    fed = FederationConfig(rounds=rounds, aggregator=s["aggregator"], seed=seed, uplink=s["uplink"],
                           downlink=s["downlink"], local=TrainConfig(epochs=epochs, lr=s["lr"], masked=s["masked"]))
    return PipelineConfig(net=s["net"], seed=seed, central=central, eval_pairs=eval_pairs, federation=fed)
