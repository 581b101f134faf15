"""``python -m fedmap.flower.register CONNECTION KEY...``: Flower's own ``flwr supernode
register CONNECTION KEY`` for every key, one after another in one process.

Each ``flwr`` process costs about a second of CPU, nearly all of it Flower's CLI starting
up, and a local mission registers a key per rover; here the CLI starts once. A key that
fails ends the run with exit 1 and one line naming it on stderr; the keys before it stay
registered, as they would with one ``flwr`` call each.
"""

from __future__ import annotations

import sys

from flwr.cli.app import app


def main(argv: list[str]) -> int:
    connection, *keys = argv
    for key in keys:
        try:
            app(["supernode", "register", key, connection], standalone_mode=False)
        except SystemExit as e:  # Flower's CLI exits on some failures
            if e.code not in (0, None):
                print(f"registering {key} failed (exit {e.code})", file=sys.stderr)
                return 1
        except Exception as e:  # noqa: BLE001 - Flower's (click's) errors, reported in one line
            print(f"registering {key} failed: {' '.join(str(e).split())}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":  # pragma: no cover - a process of its own
    sys.exit(main(sys.argv[1:]))
