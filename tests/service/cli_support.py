"""Running ``kincal`` in-process for the CLI tests: exit code, stdout, stderr."""

from __future__ import annotations

import sys

import pytest

from service import cli


def run(
    args: list[object], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> tuple[int, str, str]:
    """``kincal *args`` as the console script runs it; SystemExit becomes the exit code."""
    monkeypatch.setattr(sys, "argv", ["kincal", *map(str, args)])
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def run_ok(args: list[object]) -> None:
    """``kincal *args`` that must succeed (exit 0), for module-scoped fixtures that have no
    ``capsys``/``monkeypatch`` of their own; output goes to pytest's capture."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.setattr(sys, "argv", ["kincal", *map(str, args)])
        try:
            cli.main()
        except SystemExit as exc:
            assert exc.code in (0, None), f"kincal {' '.join(map(str, args))} exited {exc.code}"
