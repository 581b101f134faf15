"""Where every network starts: seeded random weights, the empty-map prior, or the meta-init.

``random``  the network's seeded initialisation (for GridNet: zero grids, which *is* the
            empty-map prior, since its frozen decoder renders a zero grid grey).
``empty``   theta_0: the network fitted to an all-UNKNOWN map, so that a region it has not
            been trained on renders as UNKNOWN grey (what the paper's meta-training starts
            from).
``meta``    meta-initialised weights (Reptile on Earth maps): the file shipped with the
            package, ``weights/paper_meta.safetensors``, or any file from
            ``fedmap meta-train``. Nothing is downloaded at run time.

The initial model is deterministic, so rovers and the base station rebuild it alone and
it never travels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fedmap._schema import setting
from fedmap.errors import FedmapError
from fedmap.maps.grid import UNKNOWN, GridMap
from fedmap.nets.model import (
    NET_CHOICES,
    CoordNet,
    GridNet,
    NetConfig,
    Weights,
    build_model,
    get_weights,
    load_model,
    preset,
    set_weights,
)
from fedmap.nets.training import TrainConfig, fit

INITS = ("random", "empty", "meta")

#: The meta-initialised paper network shipped with the package (its metadata holds the
#: exact ``fedmap meta-train`` command that produced it).
SHIPPED_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "paper_meta.safetensors"


@dataclass(frozen=True)
class ModelConfig:
    """The network and where it starts: the ``[model]`` section of a run config."""

    net: str = setting("paper", help="Network (paper: the Fourier MLP, 199,683 parameters; grid: feature grids)",
                       choices=lambda: NET_CHOICES)
    init: str = setting("random", help="Initial weights (empty: the empty-map prior; meta: the shipped meta-init)",
                        choices=lambda: INITS)
    init_weights: str | None = setting(None, help="With init meta: a weights file from fedmap meta-train instead of "
                                       "the shipped one", path=True)
    prior_steps: int = setting(150, help="Steps of the empty-map prior (init empty)")

    def __post_init__(self) -> None:
        preset(self.net)
        check_init(self.init, self.net)
        if self.init_weights is not None and self.init != "meta":
            raise FedmapError(f"init weights are only used with init 'meta', not {self.init!r}")
        if isinstance(self.prior_steps, bool) or not isinstance(self.prior_steps, int) or self.prior_steps < 0:
            raise FedmapError(f"prior_steps must be an integer >= 0, got {self.prior_steps!r}")

    @property
    def start(self) -> str:
        """The initial weights in words, the same in the console and the figures."""
        if self.init == "random":
            return "zero grids (empty-map prior)" if self.net == "grid" else "random init"
        if self.init == "empty":
            return "empty-map prior"
        return f"meta-init ({Path(self.init_weights).name})" if self.init_weights else "meta-init (shipped)"

    def network(self, side: int) -> NetConfig:
        """The network of this config for a ``side x side`` map."""
        return preset(self.net, side)


def check_init(init: str, net: str) -> None:
    """Raise a one-line error for an unknown init or one the network cannot start from."""
    if init not in INITS:
        raise FedmapError(f"unknown init {init!r}; choose one of {', '.join(INITS)}")
    if init == "meta" and net == "grid":
        raise FedmapError("init 'meta' is for the Fourier networks (paper, small); a grid network starts at zero")


def empty_prior(net_config: NetConfig, *, steps: int, seed: int, size: int = 64, lr: float = 1e-3,
                precision: str = "auto") -> CoordNet | GridNet:
    """The network fitted for ``steps`` full-grid Adam steps to an all-UNKNOWN map.

    Fitted on a ``size x size`` grid; the network is a function of continuous
    coordinates, so it renders grey at any resolution. ``precision``: see
    :class:`~fedmap.nets.training.TrainConfig`.
    """
    model = build_model(net_config, seed=seed)
    blank = GridMap(np.full((size, size), UNKNOWN, dtype=np.uint8), source="empty-map")
    fit(model, blank, TrainConfig(epochs=steps, lr=lr, precision=precision), seed=seed)
    return model


def load_init_weights(net_config: NetConfig, path: str | Path | None = None) -> Weights:
    """Weights of a stored network for ``net_config`` (default: the shipped meta-init).

    Raises a one-line :class:`FedmapError` when the file is missing, is not a fedmap
    model file, or was built for another network.
    """
    p = Path(path) if path is not None else SHIPPED_WEIGHTS
    if path is None and not p.is_file():
        raise FedmapError(f"the shipped meta-init weights are missing ({p}); reinstall fedmap or run fedmap meta-train")
    model = load_model(p)
    if model.config != net_config:
        raise FedmapError(f"{p} holds a network built with {model.config.to_dict()}, "
                          f"but this run uses {net_config.to_dict()}")
    return get_weights(model)


def initial_model(net_config: NetConfig, *, init: str, seed: int, prior_steps: int,
                  init_weights: str | Path | None = None, precision: str = "auto") -> CoordNet | GridNet:
    """The model every rover starts round 1 from (see the module docstring).

    ``precision`` is the training precision of the empty-map prior (``init="empty"``).
    """
    if init not in INITS:
        raise FedmapError(f"unknown init {init!r}; choose one of {', '.join(INITS)}")
    if init == "empty":
        return empty_prior(net_config, steps=prior_steps, seed=seed, precision=precision)
    model = build_model(net_config, seed=seed)
    if init == "meta":
        set_weights(model, load_init_weights(net_config, init_weights))
    return model
