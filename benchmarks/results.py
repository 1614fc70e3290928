"""Results files the documentation quotes: a benchmark writes ``docs/results/<name>.json`` (its
numbers) and ``docs/results/<name>.md`` (the table the docs include, rendered from the JSON),
so a page never carries a number no script produced. ``tests/test_quoted_numbers.py`` checks
that each table is the rendering of its JSON, that the pages include the tables, and re-runs
the cheap rows against the JSON (tolerances stated there), so a stale table fails the suite.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"

Row = dict[str, Any]


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-style markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def write_results(
    name: str, command: str, rows: list[Row], render: Callable[[list[Row]], str]
) -> tuple[Path, Path]:
    """``docs/results/<name>.json`` (the rows and the command that made them) and
    ``docs/results/<name>.md`` (``render(rows)``)."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = RESULTS / f"{name}.json"
    data.write_text(json.dumps({"command": command, "rows": rows}, indent=1) + "\n")
    table = RESULTS / f"{name}.md"
    table.write_text(render(rows) + "\n")
    return data, table


def read_results(name: str) -> tuple[str, list[Row]]:
    """The command and rows of ``docs/results/<name>.json``."""
    document = json.loads((RESULTS / f"{name}.json").read_text())
    return document["command"], document["rows"]


def dash(value: float | None, digits: int) -> str:
    """A number with ``digits`` decimals, or "–" when there is none."""
    return "–" if value is None else f"{value:.{digits}f}"


def count_text(n: int) -> str:
    """``n`` as a power of ten (10⁵) when it is one above 10, else with thousands separators."""
    exponent = len(str(n)) - 1
    if n == 10**exponent and exponent > 1:
        return "10" + str(exponent).translate(str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹"))
    return f"{n:,}"


def percent(fraction: float, digits: int, *, signed: bool = False) -> str:
    """A fraction as a percentage with ``digits`` decimals and a space before the sign
    ("0.85 %"); ``signed``: always with its sign, a minus sign for negatives ("−26.5 %")."""
    text = f"{100 * fraction:{'+' if signed else ''}.{digits}f}".replace("-", "−")
    return f"{text} %"
