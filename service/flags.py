"""Parsing of comma-separated CLI flags, shared by every command."""

from __future__ import annotations

import math

from solver.errors import KincalError


def numbers(text: str, option: str, count: int | None = None) -> list[float]:
    """Comma-separated finite numbers of a flag, with a one-line error naming the flag."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or (count is not None and len(values) != count):
        expected = f"{count} comma-separated numbers" if count else "comma-separated numbers"
        raise KincalError(f"{option} takes {expected}, got {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise KincalError(f"{option} must be finite numbers, got {text!r}")
    return values
