"""Flower's ``flower-superlink`` with its Control API closed: ``python -m fedmap.flower.superlink SECRET_FILE ARGS``.

Flower 1.41 serves the Control API (``flwr run``, ``flwr ls``, ``flwr stop``) on the same
port as the Fleet and Runtime APIs and authenticates none of it in open source. Here the
SuperLink's app gets :class:`fedmap.flower.gate.ControlGuard` as its outermost middleware:
a Control API request without the secret in ``SECRET_FILE`` (the launcher's, readable by
its owner only) is refused with 403. fedmap starts this SuperLink on loopback only, behind
the front that forwards the rovers' Fleet API (:mod:`fedmap.flower.gate`). ``ARGS`` are
``flower-superlink``'s own.
"""

from __future__ import annotations

import sys
from pathlib import Path

import flwr.superlink.main as superlink_main
from flwr.superlink.cli import flower_superlink

from fedmap.flower.gate import ControlGuard


def guarded(secret: bytes):
    """Flower's ``create_app``, its app wrapped in :class:`ControlGuard` with ``secret``."""
    create = superlink_main.create_app

    def create_app(*args, **kwargs):
        app = create(*args, **kwargs)
        app.add_middleware(ControlGuard, secret=secret)  # outermost: before Flower's own middleware
        return app
    return create_app


def main(argv: list[str]) -> int:
    secret_file, *rest = argv
    secret = Path(secret_file).read_bytes().strip()
    superlink_main.create_app = guarded(secret)  # flower_superlink imports it when it starts serving
    sys.argv = ["flower-superlink", *rest]
    flower_superlink()
    return 0


if __name__ == "__main__":  # pragma: no cover - a process of its own
    sys.exit(main(sys.argv[1:]))
