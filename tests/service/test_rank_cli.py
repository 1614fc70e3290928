"""``kincal rank``: configurations and IK candidates ranked best first from a calibration result
with covariances; every bad input ends in one line and exit code 2."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from schemas.calibration import (
    CalibrationOptions,
    CalibrationResult,
    CovarianceFrame,
    CovarianceIdentifiability,
    CovarianceResult,
    SolverReport,
)
from schemas.robots import load_robot
from service.app import calibrate as pipeline
from service.app import rank as ranking
from service.app import simulate as scenarios
from service.render import result_json
from solver import lie
from solver.evaluation import cross_validate
from solver.executors import InProcessExecutor
from solver.gp_baseline import gp_calibration_method
from solver.measurement import FullPose
from solver.model import sample_configurations
from solver.ranking import TaskMetric, ee_covariance
from solver.stream.calibrate import (
    BEFORE,
    CALIBRATED,
    HeldoutProblem,
    HeldoutSettings,
    heldout_splits,
)
from solver.stream.fit import RowSample
from tests.service.cli_support import run

NOISE_STD = (2e-4, 2e-4, 2e-4, 3e-4, 3e-4, 3e-4)


def _frame(name: str, index: int | None, std: np.ndarray) -> CovarianceFrame:
    return CovarianceFrame(
        name=name,
        joint_index=index,
        matrix=np.diag(std**2).tolist(),
        std=tuple(std.tolist()),  # type: ignore[arg-type]
    )


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory) -> CalibrationResult:
    """A real calibration of a small simulated Jaco2 recording, with known covariances filled in
    (the covariance stage is not what these tests are about)."""
    robot = load_robot("kinova")
    scn, recording = scenarios.simulate(
        robot, n_samples=50, seed=4, effects=("geometry", "compliance", "camera", "marker")
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=True)
    calibrated = pipeline.calibrate(dataset, robot, CalibrationOptions(heldout=False))
    k = len(calibrated.robot.joint_names)
    std = np.zeros((k, 6))
    std[:, 3:] = np.linspace(3e-4, 2e-3, k)[:, None]
    covariance = CovarianceResult(
        structure="diag",
        estimator="test fixture (known matrices)",
        solver=SolverReport(
            name="fixture", status="optimal", iterations=0, time_s=0.0, objective=0.0
        ),
        noise=_frame("noise", None, np.array(NOISE_STD)),
        frames=[_frame(name, j, std[j]) for j, name in enumerate(calibrated.robot.joint_names)],
        identifiability=CovarianceIdentifiability(
            rank=0, n_parameters=0, condition_number=1.0, null_directions=[], fixed=[], warnings=[]
        ),
    )
    return calibrated.model_copy(update={"covariance": covariance})


@pytest.fixture(scope="module")
def files(result: CalibrationResult, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("rank")
    with_cov = folder / "result.json"
    with_cov.write_text(result.model_dump_json(), encoding="utf-8")
    without = folder / "no_covariance.json"
    without.write_text(result.model_copy(update={"covariance": None}).model_dump_json(), "utf-8")
    chain, _ = result_json.result_chain(result)
    q = sample_configurations(chain, 30, np.random.default_rng(5), range_fraction=0.8)
    configs = folder / "configs.csv"
    pd.DataFrame(q, columns=list(chain.joint_names)).to_csv(
        configs, index=False, float_format="%.17g"
    )
    return {"result": with_cov, "bare": without, "configs": configs, "folder": folder}


def _rank(
    files: dict[str, Path],
    extra: list[object],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    name: str = "ranking.json",
) -> dict:  # type: ignore[type-arg]
    out = files["folder"] / name
    code, stdout, stderr = run(
        ["rank", files["result"], files["configs"], "-o", out, *extra], capsys, monkeypatch
    )
    assert code == 0, stderr
    assert "best: index" in stdout
    return json.loads(out.read_text())  # type: ignore[no-any-return]


def test_rank_writes_every_configuration_best_first(
    files: dict[str, Path],
    result: CalibrationResult,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    document = _rank(files, [], capsys, monkeypatch)
    entries = document["ranking"]
    assert document["format"] == "kincal.ranking/1"
    assert sorted(e["index"] for e in entries) == list(range(30))
    assert [e["rank"] for e in entries] == list(range(1, 31))
    scores = np.array([e["score"] for e in entries])
    assert np.all(np.diff(scores) >= 0.0) and document["best_index"] == entries[0]["index"]
    assert document["weights"]["diagonal"] == [0.4, 0.4, 0.0, 0.1, 0.1, 0.0]
    assert document["include_noise"] is False
    digest = hashlib.sha256(result.model_dump_json().encode()).hexdigest()
    assert document["calibration"]["result_sha256"] == digest
    # The scores are Eq. (22–23) on the Eq. (12) covariance built from evaluate_chain.
    model = ranking.uncertainty_model(result)
    q = pd.read_csv(files["configs"]).to_numpy()
    sigma = ee_covariance(model, q, include_noise=False)
    w = np.diag([0.4, 0.4, 0.0, 0.1, 0.1, 0.0])
    expected = np.einsum("ab,nbc,dc->nad", w, sigma, w).trace(axis1=1, axis2=2)
    got = np.empty(30)
    got[[e["index"] for e in entries]] = scores
    assert np.allclose(got, expected, rtol=1e-12, atol=0.0)
    trace = np.array([e["trace_position_m2"] for e in entries])
    assert np.allclose(trace, sigma[[e["index"] for e in entries], :3, :3].trace(axis1=1, axis2=2))


def test_weight_options_change_the_score_as_defined(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def by_index(document: dict) -> np.ndarray:  # type: ignore[type-arg]
        out = np.empty(len(document["ranking"]))
        for e in document["ranking"]:
            out[e["index"]] = e["score"]
        return out

    base = by_index(_rank(files, [], capsys, monkeypatch, "a.json"))
    matrix = files["folder"] / "w.json"
    matrix.write_text(json.dumps(np.diag([0.4, 0.4, 0.0, 0.1, 0.1, 0.0]).tolist()))
    same = by_index(_rank(files, ["--weight-matrix", matrix], capsys, monkeypatch, "b.json"))
    assert np.allclose(same, base, rtol=1e-14, atol=0.0)
    noisy = by_index(_rank(files, ["--include-noise"], capsys, monkeypatch, "c.json"))
    noise = np.diag(np.array(NOISE_STD) ** 2)
    w = np.diag([0.4, 0.4, 0.0, 0.1, 0.1, 0.0])
    assert np.allclose(noisy - base, np.trace(w @ noise @ w), rtol=1e-9)
    point = _rank(
        files,
        ["--task-point", "0,0,0.05", "--task-weights", "1,1,0"],
        capsys,
        monkeypatch,
        "d.json",
    )
    assert point["weights"]["kind"] == "task_point" and point["score_unit"] == "m²"
    top = _rank(files, ["--top", "3"], capsys, monkeypatch, "e.json")
    assert len(top["ranking"]) == 3 and top["n_configurations"] == 30


def test_rank_ignores_row_order_scores_duplicates_equally_and_zero_weights_tie(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 4 acceptance through the CLI: CONFIGS rows reversed with three rows repeated give
    every configuration exactly its score and the same order of configurations; W = 0 ties all
    of them (in input order)."""
    q = pd.read_csv(files["configs"])
    rows = [*range(29, -1, -1), 4, 17, 4]
    shuffled = files["folder"] / "shuffled.csv"
    q.iloc[rows].to_csv(shuffled, index=False, float_format="%.17g")

    def scores(configs: Path, extra: list[object], name: str) -> tuple[np.ndarray, list[int]]:
        out = files["folder"] / name
        code, _, stderr = run(
            ["rank", files["result"], configs, "-o", out, *extra], capsys, monkeypatch
        )
        assert code == 0, stderr
        entries = json.loads(out.read_text())["ranking"]
        by_row = np.empty(len(entries))
        by_row[[e["index"] for e in entries]] = [e["score"] for e in entries]
        return by_row, [e["index"] for e in entries]

    base, order = scores(files["configs"], [], "base.json")
    moved, moved_order = scores(shuffled, [], "shuffled.json")
    assert np.array_equal(moved, base[rows])
    assert moved[30] == moved[32] == base[4] and moved[31] == base[17]
    distinct = [rows[i] for i in moved_order if i < 30]
    assert distinct == order
    zero, zero_order = scores(shuffled, ["--weights", "0,0,0,0,0,0"], "zero.json")
    assert np.all(zero == 0.0) and zero_order == list(range(33))


def test_rank_target_ranks_ik_candidates_that_reach_it(
    files: dict[str, Path],
    result: CalibrationResult,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    q = pd.read_csv(files["configs"]).to_numpy()[:1]
    pose = result_json.predict_poses(result, q)[0]
    target = [*pose[:3, 3], *lie.matrix_to_quaternion_xyzw(pose[:3, :3])]
    out = files["folder"] / "target.json"
    text = ",".join(f"{v:.17g}" for v in target)
    args = ["rank", files["result"], "--target", text, "--n-candidates", "6", "--seed", "2"]
    code, _, stderr = run([*args, "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    document = json.loads(out.read_text())
    entries = document["ranking"]
    assert 1 <= len(entries) <= 6 and document["free_axis"] == [0.0, 0.0, 1.0]
    assert np.all(np.diff([e["score"] for e in entries]) >= 0.0)
    joints = np.array([e["joint_positions_rad"] for e in entries])
    reached = result_json.predict_poses(result, joints)
    for e, x in zip(entries, reached, strict=True):
        assert e["ik_translation_error_m"] < 1e-6 and e["ik_rotation_error_rad"] < 1e-6
        rotated = pose @ lie.se3_exp(np.r_[0.0, 0.0, 0.0, 0.0, 0.0, e["free_rotation_rad"]])
        assert np.linalg.norm(x[:3, 3] - rotated[:3, 3]) < 1e-6
        assert lie.rotation_angle_rad(x[:3, :3].T @ rotated[:3, :3]) < 1e-6
    scores = TaskMetric.pose_weights()
    model = ranking.uncertainty_model(result)
    sigma = ee_covariance(model, joints, include_noise=False)
    expected = np.einsum("ab,nab->n", scores.quadratic_form, sigma)
    assert np.allclose([e["score"] for e in entries], expected, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--weights", "1,2,3"], "--weights takes 6 comma-separated numbers"),
        (["--weights", "0.4,0.4,0,-0.1,0.1,0"], "--weights: Input should be greater than or equal"),
        (["--task-weights", "1,1,0"], "--task-weights needs --task-point"),
        (["--weights", "1,1,1,1,1,1", "--task-point", "0,0,0.05"], "--task-point replaces"),
        (["--task-point", "0,0"], "--task-point takes 3 comma-separated numbers"),
        (["--rotation-scale", "0"], "--rotation-scale: Input should be greater than 0"),
        (["--weight-matrix", "missing.json"], "cannot read weight matrix"),
    ],
)
def test_bad_rank_options_are_one_line_errors(
    files: dict[str, Path],
    extra: list[object],
    message: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = files["folder"] / "bad.json"
    code, _, stderr = run(
        ["rank", files["result"], files["configs"], "-o", out, *extra], capsys, monkeypatch
    )
    assert code == 2
    assert stderr.count("\n") == 1 and message in stderr, stderr


def test_rank_needs_covariance_and_exactly_one_input(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = files["folder"] / "bad.json"
    code, _, stderr = run(["rank", files["bare"], files["configs"], "-o", out], capsys, monkeypatch)
    assert code == 2 and "run calibrate with covariance first" in stderr
    assert stderr.count("\n") == 1
    code, _, stderr = run(["rank", files["result"], "-o", out], capsys, monkeypatch)
    assert code == 2 and "exactly one of CONFIGS" in stderr
    code, _, stderr = run(
        ["rank", files["result"], "--target", "0.3,0,0.4,0,0,0,2", "-o", out], capsys, monkeypatch
    )
    assert code == 2 and "--target" in stderr and "unit norm" in stderr
    code, _, stderr = run(
        ["rank", files["result"], "--target", "1,2,3", "-o", out], capsys, monkeypatch
    )
    assert code == 2 and "--target takes 7 comma-separated numbers" in stderr
    code, _, stderr = run(
        ["rank", files["result"], "--target", "5,5,5,0,0,0,1", "--n-candidates", "2", "-o", out],
        capsys,
        monkeypatch,
    )
    assert code == 2 and "no configuration within the joint limits reaches" in stderr
    assert not out.exists()


def test_gp_calibration_method_is_a_table_ii_column() -> None:
    """Paper Table II layout: "before", ours and the GP baseline on identical splits; on a
    recording dominated by joint compliance (smooth in q) the GP improves on "before", the
    physical model beats both."""
    robot = load_robot("kinova")
    scn, recording = scenarios.simulate(
        robot, n_samples=60, seed=3, effects=("compliance", "camera", "marker")
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=True)
    options = CalibrationOptions(heldout=False, seeds=[1, 2])
    data = result_json.prepare(result_json.chain_for(robot, options), dataset, options)
    used = np.arange(dataset.n_samples)
    gp = cross_validate(
        data.measured_pose,
        {
            "gp": gp_calibration_method(
                data.chain,
                data.joint_positions,
                data.measured_pose,
                data.loads_nm,
                measurement=FullPose(),
                baseline_options=pipeline.fit_options(
                    options, baseline=True, n_links=data.chain.n_links
                ),
            )
        },
        rotation=True,
        seeds=options.seeds,
    )
    sample = RowSample(data.joint_positions, data.measured_pose, data.loads_nm, used)
    problem = HeldoutProblem(
        data.chain,
        sample,
        data.measurement,
        pipeline.fit_options(options),
        pipeline.fit_options(options, baseline=True, n_links=data.chain.n_links),
        HeldoutSettings(tuple(options.seeds)),
    )
    ours = heldout_splits(problem, InProcessExecutor())
    mean = {
        name: np.mean([s.translation_mm for s in [*gp, *ours] if s.method == name])
        for name in ("gp", BEFORE, CALIBRATED)
    }
    assert mean[CALIBRATED] < mean["gp"] < mean[BEFORE]
