"""The CLI reference of the documentation site, generated from the command definitions.

An MkDocs hook (``mkdocs.yml``: ``hooks``) replaces the marker ``<!-- kincal cli reference -->``
of docs/reference/cli.md with every command's help, usage and options grouped in the panels of
``kincal <command> --help``. (mkdocs-click cannot read typer's own click classes, so it lists no
options; this reads the same objects ``kincal --help`` prints.)
"""

from __future__ import annotations

import html
import inspect
from typing import Any

from service.cli import click_command

MARKER = "<!-- kincal cli reference -->"


def _text(text: str) -> str:
    """Help text as markdown shows it literally (``<k>`` is no HTML tag)."""
    return html.escape(text, quote=False)


def _cell(text: str) -> str:
    return _text(" ".join(text.split())).replace("|", "\\|")


def _option_names(param: Any) -> str:
    names = [*param.opts, *getattr(param, "secondary_opts", [])]
    if getattr(param, "param_type_name", "") == "argument":
        names = [str(param.metavar or param.name).upper()]
    return ", ".join(f"`{name}`" for name in names)


def _takes(param: Any, ctx: Any) -> str:
    """What a parameter takes, as ``--help`` shows it (typer's own parameter classes)."""
    shown = param.display_type_rich(ctx) if hasattr(param, "display_type_rich") else None
    return str(shown or param.metavar or getattr(param.type, "name", "") or "")


def _command_markdown(path: str, command: Any, ctx: Any) -> list[str]:
    lines = [f"## {path}", ""]
    if command.help:
        lines += [_text(inspect.cleandoc(command.help)), ""]
    lines += ["```text", command.get_usage(ctx).strip(), "```", ""]
    panels: dict[str, list[Any]] = {}
    for param in command.get_params(ctx):
        if getattr(param, "hidden", False):
            continue
        default = "Arguments" if param.param_type_name == "argument" else "Options"
        panels.setdefault(getattr(param, "rich_help_panel", None) or default, []).append(param)
    for panel, params in panels.items():
        lines += [f"**{panel}**", "", "| Name | Takes | Help |", "|---|---|---|"]
        for param in params:
            takes = "" if getattr(param, "is_flag", False) else _takes(param, ctx)
            text = getattr(param, "help", "") or ""
            lines.append(f"| {_option_names(param)} | {_cell(takes)} | {_cell(text)} |")
        lines.append("")
    if command.epilog:
        lines += [command.epilog.replace("\n\n", "\n"), ""]
    return lines


def reference_markdown() -> str:
    """Every command of ``kincal`` as markdown, in the order ``kincal --help`` lists them."""
    root = click_command()
    lines: list[str] = []
    with root.make_context("kincal", [], resilient_parsing=True) as ctx:
        queue = [("kincal " + name, sub, ctx) for name, sub in root.commands.items()]
        while queue:
            path, command, parent = queue.pop(0)
            name = path.rsplit(" ", 1)[-1]
            with command.make_context(name, [], parent=parent, resilient_parsing=True) as sub_ctx:
                if getattr(command, "commands", None):
                    lines += [f"## {path}", "", inspect.cleandoc(command.help or ""), ""]
                    queue[:0] = [
                        (f"{path} {name}", sub, sub_ctx) for name, sub in command.commands.items()
                    ]
                else:
                    lines += _command_markdown(path, command, sub_ctx)
    return "\n".join(lines)


def on_page_markdown(markdown: str, **_: Any) -> str:
    """MkDocs hook: the marker becomes the reference."""
    return markdown.replace(MARKER, reference_markdown()) if MARKER in markdown else markdown
