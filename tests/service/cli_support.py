"""Running ``kincal`` in-process for the CLI tests: exit code, stdout, stderr."""

from __future__ import annotations

import contextlib
import io
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from schemas.calibration import CalibrationResult
from schemas.discovery import FindingsResult
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


def help_text(text: str) -> str:
    """``--help`` output as plain words: rich's panel borders removed, lines joined."""
    return " ".join(text.translate({ord(c): " " for c in "│╭╮╰╯─"}).split())


def run_ok(args: list[object]) -> None:
    """``kincal *args`` that must succeed (exit 0), for module-scoped fixtures that have no
    ``capsys``/``monkeypatch`` of their own; output goes to pytest's capture."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.setattr(sys, "argv", ["kincal", *map(str, args)])
        try:
            cli.main()
        except SystemExit as exc:
            assert exc.code in (0, None), f"kincal {' '.join(map(str, args))} exited {exc.code}"


def write_recording(
    path: Path,
    joint_positions: np.ndarray,
    poses: np.ndarray,
    time_s: np.ndarray | None = None,
) -> None:
    """A recording as a kincal dataset CSV (q1…qk, x y z, qx qy qz qw, and t when given),
    rows in order."""
    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    joints = [f"q{i + 1}" for i in range(joint_positions.shape[1])]
    clock = ["t"] if time_s is not None else []
    rows = [",".join(["sample_id", *joints, "x", "y", "z", "qx", "qy", "qz", "qw", *clock])]
    for i, (q, pose, quat) in enumerate(zip(joint_positions, poses, quaternions, strict=True)):
        values = [*q, *pose[:3, 3], *quat] + ([time_s[i]] if time_s is not None else [])
        rows.append(",".join([str(i)] + [f"{v:.17g}" for v in values]))
    path.write_text("\n".join(rows) + "\n")


def discover_ok(path: Path, flags: list[object], output: Path | None = None) -> FindingsResult:
    """``kincal discover PATH *flags -o OUTPUT`` (exit 0; default PATH.json), its JSON read
    back."""
    output = output or path.with_suffix(".json")
    with contextlib.redirect_stdout(io.StringIO()):
        run_ok(["discover", path, *flags, "-o", output])
    return FindingsResult.model_validate_json(output.read_bytes())


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
