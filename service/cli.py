"""Command-line interface (placeholder until the pipeline lands)."""
from __future__ import annotations


def main() -> None:
    raise SystemExit("kincal: not built yet")
