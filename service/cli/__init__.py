"""``kincal`` command line (DESIGN.md §3). Every bad input ends in one line and exit code 2.

One module per command group; this one is the command table (the order ``kincal --help``
lists them in) and the entry point."""

from __future__ import annotations

import inspect
import os
import sys
import traceback
from typing import Any

import typer

from service.cli import calibrate, design, discover, export, fleet, predict, serve
from service.cli.common import app
from solver.errors import KincalError

# The command table, in the order ``kincal --help`` lists the commands.
app.command()(calibrate.simulate)
app.command()(calibrate.calibrate)
app.command("dh-urdf")(export.dh_urdf_command)
app.command("export")(export.export_command)
app.command()(predict.predict)
app.command()(predict.rank)
app.command()(discover.discover)
app.command()(serve.demo)
app.command(epilog=serve.settings_epilog())(serve.serve)
app.add_typer(serve.keys_app, name="keys")
app.command()(fleet.fleet)
app.command()(design.design)


def _full_summaries(command: Any) -> None:  # typer's (vendored) click.Command
    """``kincal --help`` lists each command with its docstring's whole first paragraph; click
    would cut it at the first full stop ("(paper Eq.") or at 45 characters."""
    for sub in getattr(command, "commands", {}).values():
        if not sub.short_help and sub.help:
            sub.short_help = " ".join(inspect.cleandoc(sub.help).split("\n\n")[0].split())
        _full_summaries(sub)


def main() -> None:
    """Entry point: domain errors become one line on stderr and exit code 2.

    Usage errors (unknown option, missing argument) are typer's, also exit code 2.
    """
    try:
        command = typer.main.get_command(app)
        _full_summaries(command)
        command()
    except KincalError as exc:
        typer.echo(f"kincal: error: {exc}", err=True)
        sys.exit(2)
    except Exception as exc:  # a bug, not bad input: keep it short unless asked
        if os.environ.get("KINCAL_DEBUG"):
            traceback.print_exc()
        typer.echo(
            f"kincal: internal error: {type(exc).__name__}: {exc} "
            "(set KINCAL_DEBUG=1 for the traceback and please report it)",
            err=True,
        )
        sys.exit(1)
