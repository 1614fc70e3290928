"""``kincal calibrate --chunk-rows/--executor``: the streamed pipeline from a file, end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import read_dataset, write_dataset
from service import cli, pipeline, scenarios
from solver.simulate import SimulationSpec, look_at, simulate_recording
from tests.conftest import chain, robot
from tests.service.cli_support import run

ROBOT = "kinova"


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    c = chain(ROBOT)
    spec = SimulationSpec(
        n_samples=1500,
        seed=8,
        compliance_rad_per_nm={"j2s6s200_joint_2": 5e-4, "j2s6s200_joint_3": 8e-4},
        perturbation_sigma=np.full((c.n_joints, 6), 1e-4),
        noise_sigma=np.array([5e-5] * 3 + [1e-4] * 3),
        measurement_frame=look_at(np.array([0.8, -0.5, 0.45]), np.array([0.0, 0.0, 0.3])),
    )
    dataset = scenarios.recording_dataset(simulate_recording(c, spec), c, position_only=False)
    path = tmp_path_factory.mktemp("stream") / "big.parquet"
    write_dataset(dataset, path)
    return path


@pytest.mark.parametrize("axes", ["all", "rotation"])
def test_streamed_calibrate_matches_the_in_memory_pipeline(
    axes: str,
    recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "streamed.json"
    args = ["calibrate", str(recording), "--robot", ROBOT, "--estimator", "moment"]
    args += ["--solver", "nnls", "--chunk-rows", "400", "--covariance-axes", axes, "-o", str(out)]
    code, text, err = run(args, capsys, monkeypatch)
    assert code == 0, err
    assert "streamed on inprocess" in text and "held-out splits skipped" in text
    streamed = CalibrationResult.model_validate_json(out.read_text())
    options = CalibrationOptions(
        covariance_estimator="moment", covariance_solver="nnls", heldout=False, covariance_axes=axes
    )
    c = chain(ROBOT)
    dataset = read_dataset(recording, c.joint_names)
    memory = pipeline.calibrate(dataset, robot(ROBOT), options)
    assert streamed.options == options and streamed.evaluation is None
    assert streamed.outliers == memory.outliers
    assert streamed.identifiability.removed == memory.identifiability.removed
    links = np.array([link.placement for link in streamed.links])
    assert np.abs(links - np.array([link.placement for link in memory.links])).max() < 1e-10
    compliance = np.array([a.value_rad_per_nm for a in streamed.compliance])
    expected = np.array([a.value_rad_per_nm for a in memory.compliance])
    assert np.abs(compliance - expected).max() < 1e-9 * np.abs(expected).max()
    for phase in ("before", "after"):
        got, want = getattr(streamed.fit, phase).train, getattr(memory.fit, phase).train
        assert got.n_samples == want.n_samples
        assert got.translation_rms_mm == pytest.approx(want.translation_rms_mm, rel=1e-8)
    assert streamed.covariance is not None and memory.covariance is not None
    variances = [np.diag(f.matrix) for f in streamed.covariance.frames]
    assert np.allclose(variances, [np.diag(f.matrix) for f in memory.covariance.frames], atol=1e-15)


def test_reml_request_is_answered_by_moment_matching_and_said(
    recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "reml.json"
    args = ["calibrate", str(recording), "--robot", ROBOT, "--executor", "inprocess"]
    args += ["--no-heldout", "-o", str(out)]
    code, _, err = run(args, capsys, monkeypatch)
    assert code == 0, err
    result = json.loads(out.read_text())
    assert result["covariance"]["estimator"] == "moment"
    assert any("moment matching" in w for w in result["covariance"]["identifiability"]["warnings"])


def test_dask_address_with_another_executor_is_one_clear_error(
    recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    args = ["calibrate", str(recording), "--robot", ROBOT, "--executor", "processes"]
    args += ["--dask", "tcp://127.0.0.1:1", "-o", str(tmp_path / "x.json")]
    code, _, err = run(args, capsys, monkeypatch)
    assert code == 2 and err.count("\n") == 1 and "--dask needs --executor dask" in err


def test_executor_flags_pick_the_backend() -> None:
    from solver.errors import KincalError

    with cli._executor(None, None, None) as executor:
        assert executor.name == "inprocess"
    with pytest.raises(KincalError, match="choose one of inprocess, processes, dask"):
        cli._executor("threads", None, None)
    with pytest.raises(KincalError, match="--dask needs --executor dask"):
        cli._executor("inprocess", "tcp://127.0.0.1:1", None)
