"""The meta-initialised weights shipped with the package (and any other weights file).

``weights/paper_meta.safetensors`` is the paper network after the empty-map prior and
Reptile on the built-in Earth-like collection; its metadata holds the exact
``fedmap meta-train`` command that produced it. Nothing is downloaded at run time.
"""

from __future__ import annotations

from pathlib import Path

from fedmap.errors import FedmapError
from fedmap.model import NetConfig, Weights, get_weights, load_model

SHIPPED_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "paper_meta.safetensors"


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
