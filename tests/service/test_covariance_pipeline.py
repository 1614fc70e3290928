"""The covariance stage of ``kincal calibrate`` (paper §IV-C) end to end: simulated recording with
known random perturbations -> result JSON -> predicted EE covariance (Eq. 12) vs the truth."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pydantic
import pytest

from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import write_dataset
from service import cli
from service.app import calibrate as pipeline
from service.app import rank as ranking
from service.app import simulate as scenarios
from service.render import result_json
from solver.errors import KincalError
from solver.kinematics import evaluate_chain
from solver.model import sample_configurations
from tests.conftest import robot

EFFECTS = ("geometry", "compliance", "random", "camera", "marker")
TASK_WEIGHTS = np.array([0.4, 0.4, 0.0, 0.1, 0.1, 0.0])


@functools.cache
def _simulated(n_samples: int, rotation: bool = True):  # type: ignore[no-untyped-def]
    scn, recording = scenarios.simulate(
        robot("kinova"), n_samples=n_samples, seed=11, effects=EFFECTS
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=rotation)
    return scn, recording, dataset


@functools.cache
def _calibrated(n_samples: int, **options: object) -> CalibrationResult:
    _, recording, dataset = _simulated(n_samples)
    known = tuple(float(s) for s in recording.noise_sigma)
    settings = CalibrationOptions(heldout=False, outlier_sigma=None, noise_std=known, **options)  # type: ignore[arg-type]
    return pipeline.calibrate(dataset, robot("kinova"), settings)


def _true_ee_covariance(n_samples: int, q: np.ndarray) -> np.ndarray:
    """Eq. (12) on the TRUE robot with the true Σ_j (no noise)."""
    scn, recording, _ = _simulated(n_samples)
    loads = np.zeros((q.shape[0], len(scn.chain.compliance_axes)))
    jac = evaluate_chain(scn.chain, recording.true_params, q, loads).link_jacobians[:, :-1]
    sigma = np.einsum("ja,jb->jab", recording.perturbation_sigma, recording.perturbation_sigma)
    sigma = sigma * np.eye(6)
    return np.einsum("njab,jbc,njdc->nad", jac, sigma, jac)


def _task_score(cov: np.ndarray) -> np.ndarray:
    return np.einsum("a,nab,b->n", TASK_WEIGHTS, cov, TASK_WEIGHTS)


def test_calibrate_recovers_the_task_score_of_held_out_configurations() -> None:
    """With Σ_n known, N=800: the predicted weighted-trace score (Eq. 22) of new configurations
    is within 10 % (median) of the true robot's — wrong frames or residuals would miss by far."""
    result = _calibrated(800)
    assert result.covariance is not None
    assert [f.name for f in result.covariance.frames] == result.robot.joint_names
    assert result.covariance.noise.std == pytest.approx(_simulated(800)[1].noise_sigma)
    chain, _ = result_json.result_chain(result)
    q = sample_configurations(chain, 200, np.random.default_rng(3), range_fraction=0.8)
    predicted = ranking.predict_covariances(result, q, include_noise=False)
    truth = _true_ee_covariance(800, q)
    error = np.abs(_task_score(predicted) / _task_score(truth) - 1.0)
    assert np.median(error) < 0.10, np.median(error)


def test_every_returned_covariance_is_symmetric_psd_and_named() -> None:
    result = _calibrated(800)
    assert result.covariance is not None
    for frame in [*result.covariance.frames, result.covariance.noise]:
        matrix = np.array(frame.matrix)
        np.testing.assert_allclose(matrix, matrix.T, atol=1e-15)
        assert np.linalg.eigvalsh(matrix).min() > -1e-12
        reasons = frame.not_identifiable or (None,) * 6
        for std, reason, variance in zip(frame.std, reasons, np.diag(matrix), strict=True):
            # a number where the data see the axis, else null with the reason
            assert (std is None) == (reason is not None)
            if std is not None:
                assert std == pytest.approx(np.sqrt(variance), rel=1e-12, abs=1e-15)
    statements = " ".join(result.covariance.identifiability.null_directions)
    assert "isotropic translational variance" in statements


def test_frames_subset_and_none() -> None:
    _, _, dataset = _simulated(200)
    chosen = ["j2s6s200_joint_2", "j2s6s200_joint_5"]
    options = CalibrationOptions(heldout=False, covariance_frames=chosen)
    result = pipeline.calibrate(dataset, robot("kinova"), options)
    assert result.covariance is not None
    assert [f.name for f in result.covariance.frames] == chosen
    assert [f.joint_index for f in result.covariance.frames] == [1, 4]
    none = pipeline.calibrate(
        dataset, robot("kinova"), options.model_copy(update={"covariance": "none"})
    )
    assert none.covariance is None


def test_rotation_only_perturbations_fix_the_translations_of_joint_frames() -> None:
    """``covariance_axes='rotation'``: every joint frame's translational rows and columns are
    exactly zero, the noise frame keeps all six axes, and the isotropic translational variance
    that "all" cannot tell from Σ_n is no longer a null direction."""
    _, _, dataset = _simulated(200)
    options = CalibrationOptions(heldout=False, covariance_axes="rotation")
    result = pipeline.calibrate(dataset, robot("kinova"), options)
    assert result.covariance is not None and result.options.covariance_axes == "rotation"
    for frame in result.covariance.frames:
        matrix = np.array(frame.matrix)
        assert not matrix[:3].any() and not matrix[:, :3].any()
    assert any(max(frame.std[3:]) > 0.0 for frame in result.covariance.frames)
    assert max(result.covariance.noise.std[:3]) > 0.0
    statements = " ".join(result.covariance.identifiability.null_directions)
    assert "isotropic translational variance" not in statements
    everything = pipeline.calibrate(
        dataset, robot("kinova"), options.model_copy(update={"covariance_axes": "all"})
    )
    assert everything.covariance is not None
    assert any(np.array(f.matrix)[:3, :3].any() for f in everything.covariance.frames)


def test_a_recording_of_positions_gets_covariances() -> None:
    _, _, dataset = _simulated(300, rotation=False)
    result = pipeline.calibrate(dataset, robot("kinova"), CalibrationOptions(heldout=False))
    assert result.covariance is not None
    for frame in result.covariance.frames:
        reasons = frame.not_identifiable or (None,) * 6
        assert all(
            np.isfinite(s) if r is None else s is None
            for s, r in zip(frame.std, reasons, strict=True)
        )


def test_unknown_covariance_frame_is_a_clear_error() -> None:
    _, _, dataset = _simulated(200)
    options = CalibrationOptions(heldout=False, covariance_frames=["elbow"])
    with pytest.raises(KincalError, match=r"covariance_frames.*elbow.*choose among"):
        pipeline.calibrate(dataset, robot("kinova"), options)


# A camera noise with correlated translation and rotation (depth vs tilt), m², m·rad, rad².
_NOISE_STD = np.array([3e-4, 3e-4, 5e-4, 3e-3, 3e-3, 1e-3])
_NOISE_CORRELATION = np.eye(6)
_NOISE_CORRELATION[2, 3] = _NOISE_CORRELATION[3, 2] = 0.6
MEASURED_NOISE = (_NOISE_STD[:, None] * _NOISE_CORRELATION * _NOISE_STD[None, :]).tolist()


def test_known_noise_covariance_is_used_as_given() -> None:
    """noise_covariance (e.g. measured on a static marker, paper §V-B) is Σ_n of the result as
    given, off-diagonal included; a diagonal one calibrates exactly like noise_std."""
    _, recording, dataset = _simulated(200)
    base = CalibrationOptions(heldout=False, outlier_sigma=None)
    full = pipeline.calibrate(
        dataset, robot("kinova"), base.model_copy(update={"noise_covariance": MEASURED_NOISE})
    )
    assert full.covariance is not None and full.options.noise_covariance == MEASURED_NOISE
    np.testing.assert_array_equal(full.covariance.noise.matrix, MEASURED_NOISE)
    std = tuple(float(v) for v in recording.noise_sigma)
    by_std = pipeline.calibrate(
        dataset, robot("kinova"), base.model_copy(update={"noise_std": std})
    )
    diagonal = np.diag(np.square(std)).tolist()
    by_matrix = pipeline.calibrate(
        dataset, robot("kinova"), base.model_copy(update={"noise_covariance": diagonal})
    )
    assert by_std.covariance is not None and by_matrix.covariance is not None
    for a, b in zip(by_std.covariance.frames, by_matrix.covariance.frames, strict=True):
        np.testing.assert_array_equal(a.matrix, b.matrix)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"noise_std": (1e-4, 1e-4, -1e-4, 0.0, 0.0, 0.0)}, "finite and >= 0"),
        ({"noise_covariance": [[1.0] * 5] * 6}, "must be 6×6"),
        ({"noise_covariance": [[1.0, 0.1, 0, 0, 0, 0], *np.eye(6)[1:].tolist()]}, "symmetric"),
        ({"noise_covariance": (-np.eye(6)).tolist()}, "positive semidefinite"),
        ({"noise_covariance": np.full((6, 6), np.inf).tolist()}, "finite"),
        ({"noise_std": (0.0,) * 6, "noise_covariance": np.eye(6).tolist()}, "not both"),
    ],
)
def test_invalid_known_noise_is_refused(options: dict[str, object], message: str) -> None:
    with pytest.raises(pydantic.ValidationError, match=message):
        CalibrationOptions(**options)  # type: ignore[arg-type]


def _run(args: list[str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    monkeypatch.setattr(sys, "argv", ["kincal", *args])
    try:
        cli.main()
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_cli_calibrate_and_predict_covariance_columns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    scn, recording, _ = _simulated(200)
    data = tmp_path / "data.csv"
    frame = pd.DataFrame(recording.joint_positions, columns=list(scn.chain.joint_names))
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=True)
    frame[["x", "y", "z"]] = dataset.position_m
    frame[["qx", "qy", "qz", "qw"]] = dataset.quaternion_xyzw
    frame.to_csv(data, index=False)
    out = tmp_path / "result.json"
    code, stdout, _ = _run(
        [
            "calibrate",
            str(data),
            "--robot",
            "kinova",
            "--no-heldout",
            "--solver",
            "nnls",
            "--estimator",
            "moment",
            "-o",
            str(out),
        ],
        capsys,
        monkeypatch,
    )
    assert code == 0 and "σ per frame" in stdout
    result = CalibrationResult.model_validate_json(out.read_text())
    assert result.covariance is not None and result.covariance.solver.name == "nnls+moment"

    configs = tmp_path / "configs.csv"
    frame[list(scn.chain.joint_names)].head(5).to_csv(configs, index=False)
    with_noise, without = tmp_path / "with.csv", tmp_path / "without.csv"
    assert (
        _run(["predict", str(out), str(configs), "-o", str(with_noise)], capsys, monkeypatch)[0]
        == 0
    )
    assert (
        _run(
            ["predict", str(out), str(configs), "-o", str(without), "--no-noise"],
            capsys,
            monkeypatch,
        )[0]
        == 0
    )
    names = [f"cov_{i}{j}" for i in range(6) for j in range(6)]
    a = pd.read_csv(with_noise)[names].to_numpy().reshape(-1, 6, 6)
    b = pd.read_csv(without)[names].to_numpy().reshape(-1, 6, 6)
    np.testing.assert_allclose(
        a - b, np.broadcast_to(np.array(result.covariance.noise.matrix), a.shape), atol=1e-18
    )
    np.testing.assert_allclose(a, np.transpose(a, (0, 2, 1)), atol=1e-18)


def test_cli_calibrate_with_a_measured_noise_covariance(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _, _, dataset = _simulated(200)
    data, noise, out = tmp_path / "data.csv", tmp_path / "noise.json", tmp_path / "result.json"
    write_dataset(dataset, data)
    noise.write_text(json.dumps(MEASURED_NOISE))
    args = ["calibrate", str(data), "--robot", "kinova", "--no-heldout", "-o", str(out)]
    code, _, stderr = _run([*args, "--noise-covariance", str(noise)], capsys, monkeypatch)
    assert code == 0, stderr
    result = CalibrationResult.model_validate_json(out.read_text())
    assert result.covariance is not None and result.options.noise_covariance == MEASURED_NOISE
    np.testing.assert_array_equal(result.covariance.noise.matrix, MEASURED_NOISE)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--covariance", "triangular"], "covariance"),
        (["--solver", "adam"], "covariance_solver"),
        (["--covariance", "full", "--solver", "nnls"], "nnls"),
        (["--noise-std", "1,2"], "--noise-std takes 6 comma-separated numbers"),
        (
            ["--noise-std", "0,0,0,-1,0,0"],
            "option noise_std (--noise-std): Value error, standard deviations",
        ),
        (["--noise-covariance", "{missing}"], "cannot read noise covariance"),
        (["--noise-covariance", "{not_json}"], "is not JSON"),
        (
            ["--noise-covariance", "{asymmetric}"],
            "option noise_covariance (--noise-covariance): Value error, must be",
        ),
        (["--noise-covariance", "{measured}", "--noise-std", "0,0,0,0,0,0"], "not both"),
        (["--covariance-frames", "elbow"], "covariance_frames"),
        (["--covariance-axes", "twist"], "covariance_axes"),
    ],
)
def test_bad_covariance_options_are_one_line_errors(
    extra: list[str],
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scn, recording, dataset = _simulated(200)
    data = tmp_path / "data.csv"
    frame = pd.DataFrame(recording.joint_positions, columns=list(scn.chain.joint_names))
    frame[["x", "y", "z"]] = dataset.position_m
    frame.to_csv(data, index=False)
    files = {
        "missing": tmp_path / "missing.json",
        "not_json": tmp_path / "noise.csv",
        "asymmetric": tmp_path / "asymmetric.json",
        "measured": tmp_path / "measured.json",
    }
    files["not_json"].write_text("1,0,0\n0,1,0\n")
    files["asymmetric"].write_text(json.dumps([[1, 2, 0, 0, 0, 0], *np.eye(6)[1:].tolist()]))
    files["measured"].write_text(json.dumps(MEASURED_NOISE))
    extra = [arg.format(**files) for arg in extra]
    code, _, stderr = _run(
        [
            "calibrate",
            str(data),
            "--robot",
            "kinova",
            "--no-heldout",
            "-o",
            str(tmp_path / "r.json"),
            *extra,
        ],
        capsys,
        monkeypatch,
    )
    assert code == 2 and message in stderr and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1
