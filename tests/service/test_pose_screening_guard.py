"""The model outlier rule's Σ_E step on a pose recording (solver.stream.calibrate.screen_by_model)
judges rows only when the covariances rest on enough equations per entry, as for a measurement
model (solver.stream.screening.covariance_too_uncertain)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.robots import example_robot_data_dir
from tests.service.cli_support import run

TIAGO_POSITIONS = (
    Path(__file__).resolve().parents[2]
    / "data/real/figaroh_tiago_mocap/vicon/vicon_calibration_fc10_gripper3_base1.csv"
)


def _outliers(
    extra: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str], mp: pytest.MonkeyPatch
) -> dict[str, object]:
    out = tmp_path / f"result{len(extra)}.json"
    urdf = example_robot_data_dir() / "robots/tiago_description/robots/tiago.urdf"
    args = ["calibrate", TIAGO_POSITIONS, "--urdf", urdf, "--base", "base_footprint"]
    args += ["--tip", "arm_tool_link", "--no-heldout", *extra, "-o", out]
    code, _, stderr = run(args, capsys, mp)
    assert code in (0, 3), stderr
    outliers: dict[str, object] = json.loads(out.read_text())["outliers"]
    return outliers


def test_too_few_equations_per_covariance_entry_skip_the_sigma_e_step(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """21 TIAGo positions (63 equations) against ~40 identifiable covariance entries: a Σ_E(q)
    from them is too uncertain to judge a row by, so the model rule stops at its robust first
    step (the rows ``--covariance none`` removes, which has no Σ_E step) and says why. Without
    the guard the Σ_E step removed rows the first step kept (17 of 21 rows used)."""
    first_step = _outliers(["--covariance", "none"], tmp_path, capsys, monkeypatch)
    assert first_step["note"] is None
    default = _outliers([], tmp_path, capsys, monkeypatch)
    assert default["rule"] == "model"
    assert default["removed_rows"] == first_step["removed_rows"]
    note = default["note"]
    assert isinstance(note, str) and "Σ_E step: skipped" in note and "too uncertain" in note
