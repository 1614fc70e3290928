"""``calibrate --model``: the carried corrections are recorded in the result JSON and predict,
rank and the URDF export use them (a hidden 2nd-harmonic gear error on the Jaco2's joint 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from schemas.calibration import CalibrationOptions, CalibrationResult, ModelCorrection
from schemas.dataset import read_dataset
from schemas.discovery import FindingsResult
from schemas.ranking import RankingOptions
from service.app import discover_carry
from service.app import rank as ranking
from service.app import simulate as scenarios
from service.render import corrections, result_json
from service.render.urdf_export import export_urdf
from solver import lie
from solver.discovery.features import probe_chain
from solver.discovery.library import drift_term
from solver.errors import ModelError
from solver.kinematics import forward_kinematics
from solver.model import gravity_loads, sample_configurations
from tests.conftest import robot
from tests.service.cli_support import run, run_ok

EFFECTS = ("geometry", "camera", "marker", "gear_error")
N_SAMPLES, SEED = 150, 5


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """gear.csv, findings.json of discover and model.json of calibrate --model."""
    out = tmp_path_factory.mktemp("corrections")
    data, findings = str(out / "gear.csv"), str(out / "findings.json")
    effects = [f"--effect={e}" for e in EFFECTS]
    size = ["--n", str(N_SAMPLES), "--seed", str(SEED)]
    run_ok(["simulate", "--robot", "kinova", *size, "-o", data, *effects])
    discover = ["discover", data, "--robot", "kinova", "--bootstrap", "10", "--no-detectability"]
    run_ok([*discover, "-o", findings])  # the carried model does not use the detectable sizes
    model = ["--model", findings, "--outlier-sigma", "0", "-o", str(out / "model.json")]
    run_ok(["calibrate", data, "--robot", "kinova", *model])
    return out


@pytest.fixture(scope="module")
def result(folder: Path) -> CalibrationResult:
    return CalibrationResult.model_validate_json((folder / "model.json").read_bytes())


def _held_out(n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Raw joint readings never recorded and the true marker poses (measurement frame) there."""
    scn, recording = scenarios.simulate(
        robot("kinova"), n_samples=N_SAMPLES, seed=SEED, effects=EFFECTS
    )
    q = sample_configurations(scn.chain, n, np.random.default_rng(1234))
    (gear,) = scn.spec.joint_effects
    j = scn.chain.joint_names.index(gear.joint)
    q_true = q.copy()
    q_true[:, j] += gear.size * np.sin(gear.harmonic * q[:, j] + gear.phase_rad)
    loads = gravity_loads(scn.chain, q_true)
    return q, forward_kinematics(scn.chain, recording.true_params, q_true, loads)


def _predict(
    result_path: Path,
    q: np.ndarray,
    folder: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    names: tuple[str, ...],
) -> tuple[np.ndarray, np.ndarray, str]:
    configs = folder / f"configs_{result_path.stem}.csv"
    pd.DataFrame(q, columns=list(names)).to_csv(configs, index=False, float_format="%.17g")
    output = folder / f"poses_{result_path.stem}.csv"
    code, _, err = run(["predict", result_path, configs, "-o", output], capsys, monkeypatch)
    assert code == 0, err
    poses = pd.read_csv(output)
    return poses[["x", "y", "z"]].to_numpy(), poses[["qx", "qy", "qz", "qw"]].to_numpy(), err


def test_the_result_records_the_gear_correction_with_its_centring(
    result: CalibrationResult, folder: Path
) -> None:
    record = result.model_corrections
    assert record is not None
    (entry,) = record.corrections
    third = result.robot.joint_names[2]
    assert (entry.effect, entry.joint, entry.variant) == ("gear_periodic", third, "h2")
    assert entry.applied_in_prediction and entry.reason is None
    # truth: 2e-4 sin(2q + 0.3) = 1.91e-4 sin 2q + 0.59e-4 cos 2q
    np.testing.assert_allclose(
        [entry.parameters["sin_rad"], entry.parameters["cos_rad"]],
        [2e-4 * np.cos(0.3), 2e-4 * np.sin(0.3)],
        atol=1.5e-5,
    )
    recorded = pd.read_csv(folder / "gear.csv")[third].to_numpy()
    assert entry.feature_means == {
        f"sin2:{third}": float(np.sin(2 * recorded).mean()),
        f"cos2:{third}": float(np.cos(2 * recorded).mean()),
    }
    assert record.not_carried == []


def test_result_json_round_trip_with_corrections_is_exact(result: CalibrationResult) -> None:
    again = CalibrationResult.model_validate_json(result.model_dump_json())
    assert again == result
    assert again.model_dump_json() == result.model_dump_json()
    old = result.model_dump(exclude={"model_corrections"})
    assert CalibrationResult.model_validate(old).model_corrections is None


def test_predict_applies_the_gear_correction_at_new_raw_readings(
    result: CalibrationResult,
    folder: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """At 200 held-out raw readings: the prediction with the recorded correction is much closer
    to the simulated truth than the same calibration with the correction ignored, and equals
    the calibrated chain at the corrected angles q + Σ c (φ(q) − mean φ) to 1e-12."""
    q, truth = _held_out()
    names = tuple(result.robot.joint_names)
    ignored = folder / "ignored.json"
    ignored.write_text(result.model_copy(update={"model_corrections": None}).model_dump_json())
    with_xyz, with_quat, err = _predict(
        folder / "model.json", q, folder, capsys, monkeypatch, names
    )
    assert err == ""  # nothing the prediction could not apply
    without_xyz, _, _ = _predict(ignored, q, folder, capsys, monkeypatch, names)
    error_with_mm = 1e3 * np.linalg.norm(with_xyz - truth[:, :3, 3], axis=1).mean()
    error_without_mm = 1e3 * np.linalg.norm(without_xyz - truth[:, :3, 3], axis=1).mean()
    print(f"held-out error {error_with_mm:.4f} mm with, {error_without_mm:.4f} mm without")
    assert error_with_mm < 0.4 * error_without_mm  # measured 0.0156 vs 0.0592 mm

    entry = result.model_corrections.corrections[0]  # type: ignore[union-attr]
    j = names.index(entry.joint or "")
    angle = q[:, j]
    means = entry.feature_means
    q_corrected = q.copy()
    q_corrected[:, j] += entry.parameters["sin_rad"] * (
        np.sin(2 * angle) - means[f"sin2:{entry.joint}"]
    ) + entry.parameters["cos_rad"] * (np.cos(2 * angle) - means[f"cos2:{entry.joint}"])
    chain, params = result_json.result_chain(result)
    loads = gravity_loads(chain, q_corrected, gravity_base=np.array([0.0, 0.0, -9.81]))
    expected = forward_kinematics(chain, params, q_corrected, loads)
    np.testing.assert_allclose(with_xyz, expected[:, :3, 3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        lie.pose_matrix(with_xyz, with_quat)[:, :3, :3], expected[:, :3, :3], rtol=0, atol=1e-12
    )


def test_rank_and_covariances_score_the_corrected_configurations(
    result: CalibrationResult,
) -> None:
    q, _ = _held_out(30)
    chain, _ = result_json.result_chain(result)
    q_true = corrections.true_configurations(result, chain, q)
    assert 5e-5 < np.abs(q_true - q).max() < 5e-4
    plain = result.model_copy(update={"model_corrections": None})
    options = RankingOptions()
    scores = [
        [e.score for e in ranking.rank_configurations(r, x, options).ranking]
        for r, x in ((result, q), (plain, q_true), (plain, q))
    ]
    np.testing.assert_allclose(scores[0], scores[1], rtol=1e-12)
    assert not np.allclose(scores[0], scores[2], rtol=1e-9, atol=0)
    np.testing.assert_allclose(
        ranking.predict_covariances(result, q),
        ranking.predict_covariances(plain, q_true),
        rtol=1e-12,
        atol=1e-20,
    )


def test_rank_target_reports_the_raw_readings_that_reach_the_target(
    result: CalibrationResult,
) -> None:
    """IK finds where the robot must stand; the entries give the readings to send, which the
    correction maps back onto that configuration."""
    from service.render import corrections

    chain, _ = result_json.result_chain(result)
    q_true = sample_configurations(chain, 20, np.random.default_rng(7))
    readings = corrections.raw_readings(result, chain, q_true)
    assert np.abs(readings - q_true).max() > 5e-5
    np.testing.assert_allclose(
        corrections.true_configurations(result, chain, readings), q_true, rtol=0, atol=1e-14
    )


def _with_drift(result: CalibrationResult) -> CalibrationResult:
    """``result`` as if discovery had also found a linear thermal drift of joint 2."""
    names = tuple(result.robot.joint_names)
    term = drift_term(probe_chain(result_json.result_chain(result)[0]), 1, "linear", "s")
    drift = discover_carry._model_correction(term, np.array([1e-6]), {"time:linear": 298.0}, names)
    assert not drift.applied_in_prediction
    record = result.model_corrections
    assert record is not None
    corrections: list[ModelCorrection] = [*record.corrections, drift]
    return result.model_copy(
        update={"model_corrections": record.model_copy(update={"corrections": corrections})}
    )


def test_predict_and_rank_say_once_what_they_cannot_apply(
    result: CalibrationResult,
    folder: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    drifted = folder / "drifted.json"
    drifted.write_text(_with_drift(result).model_dump_json())
    q, _ = _held_out(5)
    names = tuple(result.robot.joint_names)
    _, _, err = _predict(drifted, q, folder, capsys, monkeypatch, names)
    assert err.count("\n") == 1 and err.startswith("note:")
    assert f"thermal_drift (linear) on {names[1]}" in err and "time" in err
    assert "gear_periodic" not in err  # that one is applied
    configs = folder / f"configs_{drifted.stem}.csv"
    code, _, err = run(
        ["rank", drifted, configs, "-o", folder / "ranking.json"], capsys, monkeypatch
    )
    assert code == 0 and err.count("\n") == 1 and "thermal_drift" in err


def test_export_urdf_refuses_a_result_with_joint_corrections(
    result: CalibrationResult,
    folder: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    third = result.robot.joint_names[2]
    with pytest.raises(ModelError, match=rf"gear_periodic \(h2\) on {third}.*without --model"):
        export_urdf(result)
    plain = result.model_copy(update={"model_corrections": None})
    assert "kincal_marker" in export_urdf(plain, measurement_frame=True)
    args = ["calibrate", folder / "gear.csv", "--robot", "kinova"]
    args += ["--model", folder / "findings.json", "--export-urdf", folder / "robot.urdf"]
    code, _, err = run([*args, "-o", folder / "refused.json"], capsys, monkeypatch)
    assert code == 2 and err.count("\n") == 1 and "cannot export a URDF" in err
    assert (folder / "refused.json").exists()  # the result is kept, the URDF refused
    assert not (folder / "robot.urdf").exists()


def test_findings_made_with_another_urdf_are_carried_with_a_note(folder: Path) -> None:
    findings = FindingsResult.model_validate_json((folder / "findings.json").read_bytes())
    description = robot("kinova")
    chain = result_json.chain_for(description, CalibrationOptions())
    dataset = read_dataset(folder / "gear.csv", chain.joint_names)
    same = discover_carry.carry_model(findings, dataset, description)
    assert not any("another URDF" in note for note in same.notes)
    edited = findings.model_copy(
        update={"robot": findings.robot.model_copy(update={"urdf_sha256": "0" * 64})}
    )
    carried = discover_carry.carry_model(edited, dataset, description)
    assert any("another URDF" in note and "000000000000" in note for note in carried.notes)
    assert carried.corrections == same.corrections  # noted, still carried


def test_corrections_no_longer_carry_copies_of_the_options_and_old_results_still_load() -> None:
    """Issue 15's parameter selection had copied free_parameters/fixed_parameters into the
    corrections record by mistake (defaults, never read); results written meanwhile load."""
    from schemas.calibration import ModelCorrections

    record = {"gravity_base_m_s2": [0, 0, -9.81], "payload_kg": 0.0}
    record |= {"corrections": [], "not_carried": []}
    old = ModelCorrections.model_validate({**record, "free_parameters": ["all"]})
    assert "free_parameters" not in old.model_dump()
    assert "fixed_parameters" not in ModelCorrections.model_json_schema()["properties"]
