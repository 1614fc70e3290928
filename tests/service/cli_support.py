"""Running ``kincal`` in-process for the CLI tests: exit code, stdout, stderr."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from schemas.calibration import CalibrationResult
from service import cli
from tests.conftest import REAL_DATA, computed_once


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


REAL_RECORDINGS: dict[str, list[object]] = {
    "fr3": [REAL_DATA / "philnad_fr3_eye_in_hand/fr3_poses.csv", "--robot", "panda"],
    "ur10": [REAL_DATA / "figaroh_ur10_experiment/calibration.csv", "--robot", "ur10"],
}
"""Shipped recordings and the ``kincal calibrate`` flags they need."""


def real_calibration(tmp_path_factory: pytest.TempPathFactory, name: str) -> CalibrationResult:
    """``kincal calibrate`` of a shipped recording with its defaults (exit 0), run once per
    test run for every test that checks that calibration (:func:`tests.conftest.computed_once`)."""

    def calibrate(folder: Path) -> CalibrationResult:
        out = folder / "result.json"
        run_ok(["calibrate", *REAL_RECORDINGS[name], "-o", out])
        return CalibrationResult.model_validate_json(out.read_bytes())

    return computed_once(tmp_path_factory, f"real-{name}", calibrate)
