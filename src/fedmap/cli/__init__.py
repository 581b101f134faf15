"""``fedmap`` command line: the only typer/rich code; it wires the library's boxes together.

One module per group of commands: :mod:`~fedmap.cli.run` (demo, run, terrain, evaluate),
:mod:`~fedmap.cli.export` (export),
:mod:`~fedmap.cli.mission` (mission),
:mod:`~fedmap.cli.experiments` (reproduce, bandwidth), :mod:`~fedmap.cli.meta`
(meta-train, ablate-init, meta-coder, meta-predictor), :mod:`~fedmap.cli.predictorfed`
(federate-predictor) and :mod:`~fedmap.cli.flower` (base-station, rover, certs);
:mod:`~fedmap.cli.ui` holds the console, progress bars and tables.

Global options (before the command): ``--quiet`` prints no progress, ``--log-json`` prints
each progress event as one JSON object per line. Without a terminal, progress is plain
log lines (:class:`~fedmap.cli.ui.LogProgress`).

User mistakes (bad files, bad options) print one line ``error: ...`` and exit 2.
"""

from __future__ import annotations

import difflib
import functools
import os
import re
import sys
from typing import Any

import click
import typer

from fedmap.errors import FedmapError

#: Every command's name, in the order ``--help`` lists them: a mistyped command is answered
#: from this list before the library (torch and all) is imported. A test checks it is the app's.
COMMANDS = ("demo", "run", "reproduce", "bandwidth", "terrain", "evaluate", "export", "merge", "base-station",
            "rover", "certs", "meta-train", "ablate-init", "meta-coder", "meta-predictor", "federate-predictor",
            "mission", "score", "node")


def _global_options(
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress output (results are still printed)."),
    log_json: bool = typer.Option(False, "--log-json", help="Progress as JSON lines: one object per event."),
) -> None:
    """Federated multi-agent mapping for planetary exploration.

    Without a terminal (output piped to a file, CI, nohup), long commands print a plain
    progress line at each stage boundary and at least every 10 s.
    """
    from fedmap.cli import ui

    ui.set_output(quiet=quiet, log_json=log_json)


@functools.cache
def build_app() -> typer.Typer:
    """The ``fedmap`` app with every command (built once: importing the commands imports the library)."""
    from fedmap.cli import experiments, export, flower, merge, meta, mission, node, predictorfed, run

    app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                      help="Federated multi-agent mapping for planetary exploration.")
    app.callback()(_global_options)
    app.command()(run.demo)
    app.command("run")(run.run)
    app.command()(experiments.reproduce)
    app.command()(experiments.bandwidth)
    app.command()(run.terrain)
    app.command()(run.evaluate)
    app.command()(export.export)
    app.command()(merge.merge)
    app.command("base-station")(flower.base_station)
    app.command()(flower.rover)
    app.command()(flower.certs)
    app.command("meta-train")(meta.meta_train)
    app.command("ablate-init")(meta.ablate_init)
    app.command("meta-coder")(meta.meta_coder)
    app.command("meta-predictor")(meta.meta_predictor)
    app.command("federate-predictor")(predictorfed.federate_predictor)
    app.command()(mission.mission)
    app.command()(mission.score)
    app.add_typer(node.node_app, name="node")
    return app


def __getattr__(name: str) -> Any:
    """``fedmap.cli.app``: the app, built when first asked for (PEP 562)."""
    if name == "app":
        return build_app()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


_GLOBAL_FLAGS = ("--quiet", "-q", "--log-json")


def _home_paths(group: click.Command) -> click.Command:
    """``group`` with ``~`` expanded in every path it takes, as a shell expands it unquoted: a
    quoted ``-o "~/out"`` is the home folder's ``out`` for every command and option alike (one
    command wrote a folder named ``~`` where another read the home folder)."""
    for command in group.commands.values() if isinstance(group, click.Group) else [group]:
        if isinstance(command, click.Group):  # (fedmap node rover|base)
            _home_paths(command)
            continue
        for param in command.params:
            if isinstance(param.type, click.Path) and not hasattr(param.type, "home"):
                base = type(param.type)

                def convert(self, value, param, ctx, base=base):
                    return base.convert(self, os.path.expanduser(value) if isinstance(value, str) else value,
                                        param, ctx)
                param.type.__class__ = type(base.__name__, (base,), {"convert": convert, "home": True})
    return group


def main(argv: list[str] | None = None) -> int:
    """Entry point: one-line errors, no tracebacks for user mistakes. The global options
    ``--quiet`` and ``--log-json`` may also follow the command (``fedmap demo --quiet``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    globals_ = [a for a in args if a in _GLOBAL_FLAGS]
    args = globals_ + [a for a in args if a not in _GLOBAL_FLAGS]
    command = next((a for a in args if not a.startswith("-")), None)
    if command is not None and command not in COMMANDS:  # answered before the library loads
        near = difflib.get_close_matches(command, COMMANDS, n=1)
        print(f"error: No such command '{command}'." + (f" Did you mean '{near[0]}'?" if near else ""), file=sys.stderr)
        return 2
    from fedmap.cli import ui

    try:
        code = _home_paths(typer.main.get_command(build_app()))(args=args, standalone_mode=False)
    except FedmapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except click.UsageError as e:
        if isinstance(e, getattr(click.exceptions, "NoArgsIsHelpError", ())):
            return 0  # help was printed
        message = re.sub(r"( Did you mean [^?]*\?)(?:\1)+", r"\1", e.format_message())  # typer and click both add it
        print(f"error: {message}", file=sys.stderr)
        return 2
    except click.exceptions.Abort:
        print("error: aborted", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("error: interrupted; no partial output was written", file=sys.stderr)
        return 130
    finally:
        ui.set_output()  # --quiet / --log-json last for this command only
    return code if isinstance(code, int) else 0  # typer.Exit(code) comes back as the result
