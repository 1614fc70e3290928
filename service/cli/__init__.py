"""``kincal`` command line (DESIGN.md §3). Every bad input ends in one line and exit code 2.

One module per command group; this one is the command table (the order ``kincal --help``
lists them in) and the entry point."""

from __future__ import annotations

import inspect
import os
import re
import sys
import traceback
from typing import Any

import typer

from service.cli import bags, calibrate, check, design, discover, export, fleet, predict, serve
from service.cli.common import app
from solver.errors import KincalError

# The command table, in the order ``kincal --help`` lists the commands.
app.command()(calibrate.simulate)
app.command()(calibrate.calibrate)
app.command("import")(bags.import_command)
app.command("dh-urdf")(export.dh_urdf_command)
app.command("export")(export.export_command)
app.command()(predict.predict)
app.command()(predict.rank)
app.command()(check.check)
app.command()(discover.discover)
app.command()(serve.demo)
app.command(epilog=serve.settings_epilog())(serve.serve)
app.add_typer(serve.keys_app, name="keys")
app.command()(fleet.fleet)
app.command()(design.design)


_MARKUP = re.compile(r"\[(?=[a-z#/@][^\[]*?\])")
"""What rich would read as a style tag in a help text ("[default: model]", "[config: x]")."""


def _plain(text: str | None) -> str | None:
    """A help text shown as written: brackets that look like rich markup escaped."""
    return None if text is None else _MARKUP.sub(r"\\[", text)


def _prepare_help(command: Any) -> None:  # typer's (vendored) click.Command
    """``kincal --help`` lists each command with its docstring's whole first paragraph (click
    would cut it at the first full stop, "(paper Eq.", or at 45 characters), and every help
    text is shown as written (rich markup off for the text, on for the panels)."""
    for sub in getattr(command, "commands", {}).values():
        if not sub.short_help and sub.help:
            sub.short_help = " ".join(inspect.cleandoc(sub.help).split("\n\n")[0].split())
        _prepare_help(sub)
    if command.help:  # paragraphs of the docstring, each re-flowed by the help's width
        paragraphs = inspect.cleandoc(command.help).split("\n\n")
        command.help = "\n\n".join(" ".join(p.split()) for p in paragraphs)
    for name in ("help", "short_help", "epilog"):
        setattr(command, name, _plain(getattr(command, name, None)))
    for param in getattr(command, "params", []):
        if getattr(param, "help", None):
            param.help = _plain(param.help)


def click_command() -> Any:
    """The ``kincal`` command as click sees it (also the docs' CLI reference, mkdocs-click)."""
    command = typer.main.get_command(app)
    _prepare_help(command)
    return command


def main() -> None:
    """Entry point: domain errors become one line on stderr and exit code 2.

    Usage errors (unknown option, missing argument) are typer's, also exit code 2.
    """
    try:
        click_command()()
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
