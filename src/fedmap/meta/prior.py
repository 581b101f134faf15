"""The empty-map prior theta_0: the network fitted to an all-UNKNOWN map.

A network started from theta_0 renders every region it has not been trained on as
UNKNOWN grey, which is what the paper's meta-training starts from.
"""

from __future__ import annotations

import numpy as np
import torch

from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.model import NetConfig, build_model
from fedmap.training import TrainConfig, fit


def empty_prior(net_config: NetConfig, *, steps: int, seed: int, size: int = 64, lr: float = 1e-3) -> torch.nn.Module:
    """The network fitted for ``steps`` full-grid Adam steps to an all-UNKNOWN map.

    Fitted on a ``size x size`` grid; the network is a function of continuous
    coordinates, so it renders grey at any resolution.
    """
    model = build_model(net_config, seed=seed)
    blank = GridMap(np.full((size, size), UNKNOWN, dtype=np.uint8), source="empty-map")
    fit(model, blank, TrainConfig(epochs=steps, lr=lr), seed=seed)
    return model
