"""Real federation between processes on Flower (``flwr``): one SuperNode per rover.

The apps here only wire fedmap's boxes to Flower's Message API; the math is the same
code the in-process runner uses (:func:`fedmap.federation.runner.rover_step` and
:func:`~fedmap.federation.runner.base_step`), and what crosses the link is fedmap's own
payload bytes (:mod:`fedmap.comm`) carried as a ``uint8`` array in an ``ArrayRecord``.

Flower is an optional extra (``pip install 'fedmap[flower]'``); nothing outside this
sub-package and :mod:`fedmap.federation.flower_cli` imports it.
"""

from __future__ import annotations

from fedmap.errors import FedmapError

INSTALL_HINT = "Flower is not installed; run: pip install 'fedmap[flower]'"


def require_flwr() -> None:
    """Raise a one-line :class:`FedmapError` when ``flwr`` cannot be imported."""
    try:
        import flwr  # noqa: F401
    except ImportError:
        raise FedmapError(INSTALL_HINT) from None
