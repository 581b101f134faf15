"""``python -m fedmap.cli.rover_host SOCKET``: the host of ``fedmap mission --deploy local``'s
rovers (:func:`fedmap.flower.warm.serve_rovers`). It imports fedmap, torch and Flower's
runtime once and forks each rover process, ``fedmap rover ...`` with the arguments the
deploy sends, instead of a fresh Python per rover."""

from __future__ import annotations

import sys

from fedmap.cli import main
from fedmap.flower.warm import serve_rovers


def rover(argv: list[str]) -> int:  # pragma: no cover - runs in a forked rover
    """``fedmap rover ...`` (``argv``), in a rover the host forked: what the command started as a
    process of its own would see, ``sys.argv`` included."""
    sys.argv = ["fedmap", *argv]
    return main(argv)


if __name__ == "__main__":  # pragma: no cover - a long-lived process
    serve_rovers(sys.argv[1], rover)
