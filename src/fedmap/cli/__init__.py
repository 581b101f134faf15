"""``fedmap`` command line: the only typer/rich code; it wires the library's boxes together.

One module per group of commands: :mod:`~fedmap.cli.run` (demo, run, terrain, evaluate),
:mod:`~fedmap.cli.experiments` (reproduce, bandwidth), :mod:`~fedmap.cli.meta`
(meta-train, ablate-init) and :mod:`~fedmap.cli.flower` (base-station, rover, certs);
:mod:`~fedmap.cli.ui` holds the console, progress bars and tables.

User mistakes (bad files, bad options) print one line ``error: ...`` and exit 2.
"""

from __future__ import annotations

import sys

import click
import typer

from fedmap.cli import experiments, flower, meta, run
from fedmap.errors import FedmapError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Federated multi-agent mapping for planetary exploration.",
)
app.command()(run.demo)
app.command("run")(run.run)
app.command()(experiments.reproduce)
app.command()(experiments.bandwidth)
app.command()(run.terrain)
app.command()(run.evaluate)
app.command("base-station")(flower.base_station)
app.command()(flower.rover)
app.command()(flower.certs)
app.command("meta-train")(meta.meta_train)
app.command("ablate-init")(meta.ablate_init)


def main(argv: list[str] | None = None) -> int:
    """Entry point: one-line errors, no tracebacks for user mistakes."""
    try:
        app(args=argv, standalone_mode=False)
    except FedmapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except click.UsageError as e:
        if isinstance(e, getattr(click.exceptions, "NoArgsIsHelpError", ())):
            return 0  # help was printed
        print(f"error: {e.format_message()}", file=sys.stderr)
        return 2
    except click.exceptions.Abort:
        print("error: aborted", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("error: interrupted; no partial output was written", file=sys.stderr)
        return 130
    return 0
