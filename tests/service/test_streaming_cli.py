"""``kincal calibrate`` from a file, read whole or streamed in chunks on local processes: one
path, the same numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.calibration import CalibrationResult
from schemas.dataset import write_dataset
from service.app import calibrate as pipeline
from service.app import simulate as scenarios
from service.cli import common as cli
from solver.simulate import SimulationSpec, look_at, simulate_recording
from tests.conftest import assert_documents_close, chain, comparable_result
from tests.service.cli_support import run

ROBOT = "kinova"


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    c = chain(ROBOT)
    spec = SimulationSpec(
        n_samples=1500,
        seed=9,
        compliance_rad_per_nm={"j2s6s200_joint_2": 5e-4, "j2s6s200_joint_3": 8e-4},
        perturbation_sigma=np.full((c.n_joints, 6), 1e-4),
        noise_sigma=np.array([5e-5] * 3 + [1e-4] * 3),
        measurement_frame=look_at(np.array([0.8, -0.5, 0.45]), np.array([0.0, 0.0, 0.3])),
    )
    dataset = scenarios.recording_dataset(simulate_recording(c, spec), c, rotation=True)
    path = tmp_path_factory.mktemp("stream") / "big.parquet"
    write_dataset(dataset, path)
    return path


def _calibrate(
    args: list[str],
    out: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> tuple[CalibrationResult, str]:
    code, text, err = run([*args, "-o", str(out)], capsys, monkeypatch)
    assert code == 0, err
    return CalibrationResult.model_validate_json(out.read_text()), text


def test_the_path_never_changes_the_numbers(
    recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 17: ``kincal calibrate`` with its defaults (the file read whole, passes in this
    process) and the same file streamed in chunks on two local processes, or in small chunks
    in this process, give the same result to 1e-8 — held-out splits included — and the same
    REML covariances to 1e-6."""
    base = ["calibrate", str(recording), "--robot", ROBOT]
    memory, text = _calibrate(base, tmp_path / "memory.json", capsys, monkeypatch)
    assert "ran on inprocess (1 worker(s))" in text
    assert memory.covariance is not None and memory.covariance.estimator == "reml"
    assert memory.evaluation is not None and len(memory.evaluation.splits) == 20
    monkeypatch.setattr(pipeline, "IN_MEMORY_ROWS", 500)  # chunks read by the workers
    streamed, text = _calibrate(
        [*base, "--workers", "2", "--chunk-rows", "400"],
        tmp_path / "streamed.json",
        capsys,
        monkeypatch,
    )
    assert "ran on processes (2 worker(s))" in text
    small, _ = _calibrate(
        [*base, "--executor", "inprocess", "--chunk-rows", "300"],
        tmp_path / "small.json",
        capsys,
        monkeypatch,
    )
    want = _numbers(memory)
    for other in (streamed, small):
        got = _numbers(other)
        # The covariance is a scoring solve stopped at a tolerance, not at the last digits:
        # chunked sums in another order move it by ~1e-8 relative on an AVX-512 machine
        # (1.1e-8 seen on a σ). The cross-machine test (tests/test_same_numbers.py) holds it
        # to 1e-6; so does this. Everything else, held-out splits included, to 1e-8.
        assert_documents_close(got.pop("covariance"), want["covariance"], ".covariance", 1e-6)
        assert_documents_close(got, {k: v for k, v in want.items() if k != "covariance"}, rel=1e-8)
    assert memory.covariance.identifiability.rank == small.covariance.identifiability.rank  # type: ignore[union-attr]


def _numbers(result: CalibrationResult) -> dict[str, object]:
    """The result without the words describing weakly identified covariance directions: when
    several singular values of the equilibrated Gram nearly coincide, the eigenvectors inside
    that subspace rotate with rounding, and so may the words describing them (issue filed);
    every number, the rank and the exact null directions are compared (the noise warnings,
    worded from both kinds, are left out too)."""
    document = comparable_result(result)
    identifiability = document["covariance"]["identifiability"]
    identifiability.pop("warnings")
    identifiability["null_directions"] = [
        s for s in identifiability["null_directions"] if not s.startswith("weakly identified")
    ]
    return document


def test_large_files_run_on_local_processes_by_default(
    recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without flags, a file of several chunks on a machine with several cores is read by
    local worker processes (a smaller one in this process)."""
    monkeypatch.setattr(pipeline, "IN_MEMORY_ROWS", 500)
    monkeypatch.setattr(pipeline, "available_cores", lambda: 2)
    args = ["calibrate", str(recording), "--robot", ROBOT, "--no-heldout", "--chunk-rows", "800"]
    _, text = _calibrate(args, tmp_path / "auto.json", capsys, monkeypatch)
    assert "ran on processes (2 worker(s))" in text


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


@pytest.mark.parametrize(
    ("flags", "environment", "message"),
    [
        (["--dask", "nohost"], {}, "--dask: 'nohost' is not a Dask scheduler address"),
        (
            ["--executor", "dask"],
            {"KINCAL_DASK_ADDRESS": "localhost"},
            "KINCAL_DASK_ADDRESS='localhost'",
        ),
        (["--executor", "dask"], {"KINCAL_WORKERS": "many"}, "KINCAL_WORKERS='many'"),
    ],
)
def test_bad_dask_address_or_setting_is_one_clear_error(
    flags: list[str],
    environment: dict[str, str],
    message: str,
    recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A scheduler address without a port was Dask's ValueError ("internal error", exit 1);
    an invalid KINCAL_* setting read for --executor dask too."""
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    args = ["calibrate", str(recording), "--robot", ROBOT, *flags, "-o", str(tmp_path / "x.json")]
    code, _, err = run(args, capsys, monkeypatch)
    assert code == 2 and err.count("\n") == 1 and message in err, err


def test_executor_flags_pick_the_backend() -> None:
    from solver.errors import KincalError

    assert cli._executor(None, None, None) is None  # the calibration chooses
    with cli._executor(None, None, 2) as executor:  # type: ignore[union-attr]
        assert executor.name == "processes" and executor.n_workers == 2
    with pytest.raises(KincalError, match="choose one of inprocess, processes, dask"):
        cli._executor("threads", None, None)
    with pytest.raises(KincalError, match="--dask needs --executor dask"):
        cli._executor("inprocess", "tcp://127.0.0.1:1", None)
