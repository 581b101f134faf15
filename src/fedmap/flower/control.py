"""Flower's CLI for fedmap's own Control API calls: ``python -m fedmap.flower.control register CONNECTION KEY...``
or ``python -m fedmap.flower.control run APP CONNECTION RUN_CONFIG``.

The SuperLink fedmap starts answers its Control API only with the launcher's secret
(:mod:`fedmap.flower.superlink`); this process reads it from the file named by
:data:`CONTROL_SECRET_ENV` and adds it to every request Flower's CLI makes (its HTTP client is
httpx's). ``register``: ``flwr supernode register CONNECTION KEY`` for every key, in one
process (each ``flwr`` process costs about a second of CPU, nearly all of it Flower's CLI
starting up), printing one JSON line ``{"key": ..., "node-id": ...}`` per key. A key that
fails ends with exit 1 and one line naming it on stderr. ``run``: ``flwr run APP
CONNECTION --run-config RUN_CONFIG``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
from pathlib import Path

import httpx

from fedmap.flower import CONTROL_SECRET_ENV
from fedmap.flower.gate import CONTROL_HEADER


def with_secret(secret: str) -> None:
    """Every httpx client made in this process from now on sends ``secret`` in :data:`CONTROL_HEADER`."""
    base = httpx.Client

    class Client(base):  # type: ignore[misc, valid-type]
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.headers[CONTROL_HEADER] = secret

    httpx.Client = Client  # type: ignore[misc]


def _flwr(args: list[str]) -> tuple[int, str]:
    """Flower's CLI on ``args`` in this process: (exit code, what it printed)."""
    from flwr.cli.app import app

    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            app(args, standalone_mode=False)
    except SystemExit as e:  # Flower's CLI exits on some failures
        return (0 if e.code in (0, None) else int(e.code) if isinstance(e.code, int) else 1), out.getvalue()
    except Exception as e:  # noqa: BLE001 - Flower's (click's) errors, reported in one line
        return 1, out.getvalue() + " " + " ".join(str(e).split())
    return 0, out.getvalue()


def main(argv: list[str]) -> int:
    secret_file = os.environ.get(CONTROL_SECRET_ENV)
    if secret_file:
        with_secret(Path(secret_file).read_text().strip())
    what, *rest = argv
    if what == "register":
        connection, *keys = rest
        import flwr.cli.supernode.register  # noqa: F401 - the module (the package's name "register" is its command)

        register = sys.modules["flwr.cli.supernode.register"]
        said: list = []
        register.print_json_to_stdout = said.append  # type: ignore[attr-defined]  # Flower prints the JSON answer past any redirection
        for key in keys:
            said.clear()
            code, text = _flwr(["supernode", "register", key, connection, "--format", "json"])
            node = said[-1].get("node-id") if said and isinstance(said[-1], dict) else None
            if code != 0 or node is None:
                print(f"registering {key} failed (exit {code}): {' '.join(text.split())[-300:]}", file=sys.stderr)
                return 1
            print(json.dumps({"key": key, "node-id": int(node)}), flush=True)
        return 0
    if what == "run":
        app_dir, connection, run_config = rest
        code, text = _flwr(["run", app_dir, connection, "--run-config", run_config])
        if code != 0:
            print(f"flwr run failed (exit {code}): {' '.join(text.split())[-300:]}", file=sys.stderr)
        return code
    print(f"unknown command {what!r}", file=sys.stderr)
    return 2


if __name__ == "__main__":  # pragma: no cover - a process of its own
    sys.exit(main(sys.argv[1:]))
