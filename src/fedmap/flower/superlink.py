"""Flower's ``flower-superlink`` behind fedmap's gate.

``python -m fedmap.flower.superlink SECRET_FILE [--front HOST:PORT [--front-certs DIR] --ready FILE] -- ARGS``

Flower 1.41 serves the Control API (``flwr run``, ``flwr ls``, ``flwr stop``) on the same
port as the Fleet and Runtime APIs and authenticates none of it in open source. Here the
SuperLink's app is served twice by the same uvicorn event loop (:mod:`fedmap.flower.gate`):

- on the address ``ARGS`` give (``--host 127.0.0.1``: loopback only), wrapped in
  :class:`~fedmap.flower.gate.ControlGuard`: a Control API request without the secret in
  ``SECRET_FILE`` (the launcher's, readable by its owner only) is refused with 403. Flower's
  own processes (SuperExec, ServerApp) and fedmap's control calls use this one;
- with ``--front``, on ``HOST:PORT`` (where the rovers reach the base), wrapped in
  :class:`~fedmap.flower.gate.FleetOnly`: the Fleet API's routes and nothing else, over
  mutual TLS with ``--front-certs`` (a client must present a certificate of ``ca.crt``
  there). It opens only once the file ``--ready`` exists (the launcher writes it when every
  rover key is registered), so no rover knocks before its key is known.

``ARGS`` are ``flower-superlink``'s own.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from pathlib import Path

import flwr.superlink.cli.flower_superlink  # noqa: F401 - the module (its package exports the command by that name)
from flwr.superlink.cli import flower_superlink

from fedmap.flower.gate import ControlGuard, FleetOnly, front_tls


def served(secret: bytes, *, front: tuple[str, int] | None, certs: Path | None, ready: Path | None):
    """A stand-in for ``uvicorn.run`` as Flower's SuperLink calls it: the app on Flower's
    address behind :class:`ControlGuard`, and (``front``) on the front's behind :class:`FleetOnly`."""
    import uvicorn

    def run(app, **kwargs) -> None:
        kwargs.pop("workers", None)
        kwargs.pop("reload", None)
        main = uvicorn.Server(uvicorn.Config(ControlGuard(app, secret), **kwargs))
        if front is None:
            main.run()
            return
        host, port = front
        tls = front_tls(certs) if certs is not None else {}
        outer = uvicorn.Server(uvicorn.Config(FleetOnly(app), host=host.strip("[]"), port=port, lifespan="off",
                                              access_log=False, log_config=kwargs.get("log_config"), **tls))
        # the main server's signal handlers are the process's
        outer.capture_signals = contextlib.nullcontext  # type: ignore[method-assign, assignment]

        async def open_front() -> None:
            while ready is not None and not ready.exists() and not main.should_exit:
                await asyncio.sleep(0.1)
            if not main.should_exit:
                await outer.serve()

        async def both() -> None:
            task = asyncio.create_task(open_front())
            try:
                await main.serve()
            finally:
                outer.should_exit = True
                await asyncio.wait_for(task, 30)
        from uvicorn._compat import asyncio_run  # uvicorn's own way: its event loop (uvloop where installed)

        asyncio_run(both(), loop_factory=main.config.get_loop_factory())
    return run


def main(argv: list[str]) -> int:
    ours, theirs = _split(argv)
    p = argparse.ArgumentParser(prog="python -m fedmap.flower.superlink")
    p.add_argument("secret_file", type=Path)
    p.add_argument("--front")
    p.add_argument("--front-certs", type=Path)
    p.add_argument("--ready", type=Path)
    a = p.parse_args(ours)
    front = None
    if a.front:
        host, _, port = a.front.rpartition(":")
        front = (host, int(port))
    secret = a.secret_file.read_bytes().strip()
    # Flower's SuperLink starts its HTTP API with uvicorn.run(...) (its only use of uvicorn): served here instead
    cli = sys.modules["flwr.superlink.cli.flower_superlink"]
    assert hasattr(cli, "uvicorn"), "Flower's SuperLink no longer serves with uvicorn"
    stand_in = type("uvicorn", (), {"run": staticmethod(served(secret, front=front, certs=a.front_certs,
                                                               ready=a.ready))})
    setattr(cli, "uvicorn", stand_in)  # noqa: B010 - a module's attribute, checked above
    sys.argv = ["flower-superlink", *theirs]
    flower_superlink()
    return 0


def _split(argv: list[str]) -> tuple[list[str], list[str]]:
    """Our arguments, and Flower's after ``--``."""
    if "--" not in argv:
        return argv, []
    i = argv.index("--")
    return argv[:i], argv[i + 1:]


if __name__ == "__main__":  # pragma: no cover - a process of its own
    sys.exit(main(sys.argv[1:]))
