"""Issue 13: σ of an axis the data cannot see is reported as "not identifiable", not as a
number — JSON, CLI summary and HTML report, through ``kincal calibrate`` on the real FR3."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.calibration import CalibrationResult
from tests.service.cli_support import run

FR3 = Path(__file__).resolve().parents[2] / "data/real/philnad_fr3_eye_in_hand/fr3_poses.csv"


def test_fr3_joint7_rz_is_not_identifiable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A random rotation about joint 7's own axis (and a shift along it) moves the camera the
    same way at every configuration: the recording cannot tell it from measurement noise."""
    out, report = tmp_path / "fr3.json", tmp_path / "fr3.html"
    code, text, _ = run(
        ["calibrate", FR3, "--robot", "panda", "--no-heldout", "-o", out, "--report", report],
        capsys,
        monkeypatch,
    )
    assert code == 0
    result = CalibrationResult.model_validate_json(out.read_text())
    assert result.covariance is not None
    frames = {f.name: f for f in result.covariance.frames}
    joint7 = frames["panda_joint7"]
    assert joint7.std[5] is None and joint7.identifiable is not None
    assert not joint7.identifiable[5]
    assert joint7.not_identifiable is not None and joint7.not_identifiable[5]
    assert "same at every configuration" in joint7.not_identifiable[5]
    # rx and ry of joint 7 turn with the joint: seen, a number
    assert joint7.std[3] is not None and joint7.std[4] is not None
    assert joint7.not_identifiable[3] is None and joint7.not_identifiable[4] is None
    # every axis of the other joints' frames moves with the arm
    for name, frame in frames.items():
        if name != "panda_joint7":
            assert all(s is not None for s in frame.std), name
    # Eq. 12 still sums as fitted: the matrix keeps the rule's entry
    assert np.isfinite(np.array(joint7.matrix)).all()
    assert "panda_joint7 rz: not identifiable" in text
    assert "panda_joint7 rz: not identifiable" in report.read_text()
