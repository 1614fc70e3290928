"""The ``kincal`` command as a click object, for the documentation's CLI reference
(mkdocs-click reads :data:`kincal`; docs/reference/cli.md)."""

from __future__ import annotations

from service.cli import click_command

kincal = click_command()
