"""Issue 13: no silent failures. A calibration the data do not support ends with its named
cause and fix, exit code 3, the result written and marked (``verdict``), and no URDF unless
``--force-urdf`` — through ``kincal calibrate`` with its defaults."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from schemas.calibration import CalibrationResult
from schemas.robots import example_robot_data_dir
from solver.verdict import FitEvidence, check_fit, verdict_status
from tests.service.cli_support import run, run_ok

REAL = Path(__file__).resolve().parents[2] / "data" / "real"
TIAGO_FILE = (
    REAL / "figaroh_tiago_mocap/vicon/relative_encoder/"
    "vicon_calibration_fc10_gripper3_base1_withrpy.csv"
)


def _calibrate(
    args: list[object],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> tuple[int, CalibrationResult, str, Path]:
    out, urdf = tmp_path / "result.json", tmp_path / "robot.urdf"
    code, stdout, stderr = run(
        ["calibrate", *args, "-o", out, "--export-urdf", urdf], capsys, monkeypatch
    )
    return code, CalibrationResult.model_validate_json(out.read_text()), stdout + stderr, urdf


def _codes(result: CalibrationResult) -> set[str]:
    assert result.verdict is not None
    return {r.code for r in result.verdict.reasons if r.severity == "failed"}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("verdict") / "jaco2.csv"
    run_ok(["simulate", "--robot", "kinova", "--n", "200", "--seed", "3", "-o", path])
    return path


def test_a_sound_calibration_is_ok_and_exports(
    simulated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    code, result, _, urdf = _calibrate(
        [simulated, "--robot", "kinova", "--seeds", "1,2"], tmp_path, capsys, monkeypatch
    )
    assert code == 0 and result.verdict is not None and result.verdict.status != "failed"
    assert urdf.exists()


def test_positions_in_millimetres_are_refused_before_the_fit(
    simulated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 28: the pre-flight checks refuse them (exit 2, nothing written); the verdict's
    ``position_unit`` reason stays for results computed without them
    (test_each_check_names_its_cause)."""
    table = pd.read_csv(simulated)
    table[["x", "y", "z"]] *= 1000.0
    mm = tmp_path / "mm.csv"
    table.to_csv(mm, index=False)
    out, urdf = tmp_path / "result.json", tmp_path / "robot.urdf"
    code, _, err = run(
        ["calibrate", mm, "--robot", "kinova", "-o", out, "--export-urdf", urdf],
        capsys,
        monkeypatch,
    )
    assert code == 2 and "millimetres" in err and "divide by 1000" in err
    assert not out.exists() and not urdf.exists()


def test_a_fit_that_does_not_converge_is_named(
    simulated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    code, result, text, urdf = _calibrate(
        [simulated, "--robot", "kinova", "--no-heldout", "--max-iterations", "1"],
        tmp_path,
        capsys,
        monkeypatch,
    )
    assert code == 3 and "not_converged" in _codes(result)
    assert "--max-iterations" in text and not urdf.exists()


def test_force_urdf_writes_a_failed_calibration_anyway(
    simulated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    code, _, _, urdf = _calibrate(
        [simulated, "--robot", "kinova", "--no-heldout", "--max-iterations", "1", "--force-urdf"],
        tmp_path,
        capsys,
        monkeypatch,
    )
    assert code == 3 and urdf.exists()


def test_real_ur10e_calibration_that_does_not_beat_the_nominal_model_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The UR10 experiment (23 real poses of a UR10e): the full calibration predicts held-out
    poses no better than the nominal UR10e with fitted frames (4.37 against 4.38 mm)."""
    args = [
        REAL / "figaroh_ur10_experiment/calibration.csv",
        "--urdf",
        REAL / "figaroh_ur10_experiment/ur10e_robot.urdf",
        "--base",
        "base_link",
        "--tip",
        "wrist_3_link",
    ]
    code, result, text, urdf = _calibrate(args, tmp_path, capsys, monkeypatch)
    assert code == 3 and "heldout_worse" in _codes(result)
    assert "better than the nominal robot" in text and not urdf.exists()


def test_real_tiago_orientations_that_disagree_with_the_arm_are_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The TIAGo Vicon file with rpy (gripper marker in the frame of a marker on the mobile
    base): it used to end "optimal", exit 0, with a URDF, and 741 mm held-out."""
    urdf_path = example_robot_data_dir() / "robots/tiago_description/robots/tiago.urdf"
    args = [TIAGO_FILE, "--urdf", urdf_path, "--base", "base_footprint", "--tip", "arm_7_link"]
    code, result, text, urdf = _calibrate(args, tmp_path, capsys, monkeypatch)
    assert code == 3 and {"orientation_misfit", "heldout_worse"} <= _codes(result)
    assert "position-only" in text and not urdf.exists()


def _evidence(**change: object) -> FitEvidence:
    base = {
        "converged": True,
        "iterations": 5,
        "max_iterations": 50,
        "n_equations": 6000,
        "n_parameters": 40,
        "train_rms_translation_m": 2e-4,
        "train_rms_rotation_rad": 1e-3,
        "heldout_translation_m": 3e-4,
        "heldout_before_translation_m": 4e-3,
        "position_spread_m": 0.6,
        "reach_m": 1.0,
    }
    return FitEvidence(**{**base, **change})  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "change, code, status",
    [
        ({}, None, "ok"),
        ({"position_spread_m": 600.0}, "position_unit", "failed"),
        ({"train_rms_translation_m": 0.3}, "model_misfit", "failed"),
        ({"train_rms_rotation_rad": np.radians(20.0)}, "orientation_misfit", "failed"),
        ({"converged": False, "iterations": 50}, "not_converged", "failed"),
        ({"n_equations": 150}, "few_equations", "warning"),
        ({"n_equations": 60}, "few_equations", "failed"),
        ({"heldout_translation_m": 5e-3}, "heldout_worse", "failed"),
    ],
)
def test_each_check_names_its_cause(
    change: dict[str, object], code: str | None, status: str
) -> None:
    reasons = check_fit(_evidence(**change))
    assert verdict_status(reasons) == status
    assert [r.code for r in reasons] == ([] if code is None else [code])
    assert all(r.fix for r in reasons)


def test_no_reported_compliance_is_negative_on_the_real_fr3(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The FR3 recording used to report joint 6 at −1.46e-3 ± 3.6e-4 rad/N·m, "significant":
    a joint bending against its load. Every compliance is now ≥ 0; the ones fixed at 0 are
    listed (``identifiability.pruned``, ``compliance[].pruned``) and said in the summary."""
    out = tmp_path / "fr3.json"
    code, text, _ = run(
        [
            "calibrate",
            REAL / "philnad_fr3_eye_in_hand/fr3_poses.csv",
            "--robot",
            "panda",
            "--no-heldout",
            "-o",
            out,
        ],
        capsys,
        monkeypatch,
    )
    result = CalibrationResult.model_validate_json(out.read_text())
    assert code == 0
    assert all(c.value_rad_per_nm >= 0.0 for c in result.compliance)
    assert "compliance.panda_joint6" in result.identifiability.pruned
    assert "compliance.panda_joint6" not in result.identifiability.removed
    assert all(
        c.pruned == (f"compliance.{c.axis}" in result.identifiability.pruned)
        for c in result.compliance
    )
    assert "panda_joint6" in text and "fixed at 0" in text


def test_implausible_compliance_columns() -> None:
    from solver.calibration import PLAUSIBLE_COMPLIANCE_RAD_PER_NM, implausible_compliance_columns
    from solver.kinematics import ChainParameters
    from tests.conftest import chain

    c = chain("kinova")
    offset = 6 * c.n_links
    compliance = np.array([1e-4, -1e-6, 2e-4, 0.0, 0.0, 0.0])[: len(c.compliance_axes)]
    params = ChainParameters(c.nominal_links, compliance)
    keep = np.array([0, offset, offset + 1, offset + 2], dtype=np.intp)
    stderr = np.array([1e-3, 1e-5, 1e-5, 10 * PLAUSIBLE_COMPLIANCE_RAD_PER_NM])
    assert implausible_compliance_columns(c, params, keep, stderr).tolist() == [
        offset + 1,
        offset + 2,
    ]


def test_the_html_report_leads_with_a_failed_verdict(
    simulated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    report = tmp_path / "report.html"
    code, _, _, _ = _calibrate(
        [
            simulated,
            "--robot",
            "kinova",
            "--no-heldout",
            "--max-iterations",
            "1",
            "--report",
            report,
        ],
        tmp_path,
        capsys,
        monkeypatch,
    )
    text = report.read_text()
    assert code == 3 and "Verdict: failed" in text and "--max-iterations" in text
    assert text.index("Verdict: failed") < text.index("Fit (mean and RMS error)")


@pytest.mark.parametrize(
    ("extra", "cause"),
    [
        (["--max-iterations", "1"], "did not converge"),
        ([], "the model does not explain the data"),
    ],
)
def test_an_outlier_rule_that_would_remove_every_row_is_refused(
    extra: list[str],
    cause: str,
    simulated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A badly wrong fit (the 55-row TALOS fold under Gauss–Newton, stopped at 3.1 mm RMS)
    judged every row an outlier against its own Σ_E and calibrate failed with "0 samples give
    0 equations". Here the model rule's judgement is made that of such a fit (every row
    beyond the threshold): the rows stay, the verdict names the cause, exit 3, no URDF."""
    import solver.stream.calibrate as stream_calibrate

    def every_row(*args: object) -> np.ndarray:
        return np.arange(int(args[7]), dtype=np.int64)  # n_rows

    monkeypatch.setattr(stream_calibrate, "model_rule_removed", every_row)
    code, result, text, urdf = _calibrate(
        [simulated, "--robot", "kinova", "--no-heldout", *extra], tmp_path, capsys, monkeypatch
    )
    assert code == 3 and "outliers_refused" in _codes(result)
    assert result.outliers.n_used == result.outliers.n_input == 200
    assert "would have removed 200 of 200 rows" in text and cause in text
    assert not urdf.exists()


def test_model_rule_refusal() -> None:
    from solver.stream.screening import model_rule_refusal

    assert model_rule_refusal(100, 0, 10, converged=False) is None
    assert model_rule_refusal(100, 50, 10, converged=True) is None
    assert model_rule_refusal(100, 51, 10, converged=True) == "model_misfit"
    assert model_rule_refusal(100, 100, 10, converged=False) == "not_converged"
    assert model_rule_refusal(20, 10, 11, converged=True) == "model_misfit"
