"""Issue 13, predictive covariance through the user's path: ``kincal simulate`` → ``kincal
calibrate`` → ``kincal predict`` on poses the calibration never saw, the result JSON's held-out
coverage, ``predict --part``, ``rank --uncertainty total``, the summary and the HTML report."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.stats

from benchmarks import coverage as coverage_benchmark
from schemas.calibration import CalibrationResult
from schemas.dataset import read_dataset
from schemas.ranking import RankingResult
from schemas.robots import example_robot_data_dir
from service.app import rank as ranking
from service.render import result_json
from service.render.report_html import render_report
from service.render.text import summary
from solver import lie
from solver.predictive import coverage
from tests.conftest import computed_once
from tests.service.cli_support import real_calibration, run, run_ok

N_TRAIN = 200
N_FRESH = 600
COV_COLUMNS = [f"cov_{i}{j}" for i in range(6) for j in range(6)]


@dataclass(frozen=True)
class Calibrated:
    folder: Path
    result_path: Path
    result: CalibrationResult
    fresh: pd.DataFrame
    configs: Path
    scratch: Path  # where its tests write (the rest is shared by the xdist workers)


def _calibrate_simulated(folder: Path, seed: int) -> Calibrated:
    """A simulated Jaco2 with geometry and compliance errors and random joint-frame rotations
    (the repo's simulator): the first N_TRAIN poses calibrated with kincal's defaults (the
    model-based outlier rule), the next N_FRESH poses of the same robot kept apart."""
    recording = folder / "recording.csv"
    effects = ["geometry", "compliance", "random", "camera", "marker"]
    run_ok(
        ["simulate", "--robot", "kinova", "--n", N_TRAIN + N_FRESH, "--seed", seed]
        + [arg for effect in effects for arg in ("--effect", effect)]
        + ["-o", recording]
    )
    data = pd.read_csv(recording)
    data.iloc[:N_TRAIN].to_csv(folder / "train.csv", index=False, float_format="%.17g")
    fresh = data.iloc[N_TRAIN:]
    configs = folder / "fresh.csv"
    fresh.to_csv(configs, index=False, float_format="%.17g")
    result_path = folder / "result.json"
    train = folder / "train.csv"
    run_ok(["calibrate", train, "--robot", "kinova", "-o", result_path])
    result = CalibrationResult.model_validate_json(result_path.read_text(encoding="utf-8"))
    return Calibrated(folder, result_path, result, fresh, configs, folder)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Calibrated:
    """Seed 3, calibrated once for both xdist workers; each writes in a folder of its own."""
    shared = computed_once(tmp_path_factory, "predictive", lambda f: _calibrate_simulated(f, 3))
    return dataclasses.replace(shared, scratch=tmp_path_factory.mktemp("predictive"))


def _predict(calibrated: Calibrated, *args: object) -> pd.DataFrame:
    output = calibrated.scratch / f"predicted{len(args)}{'_'.join(map(str, args))}.csv"
    run_ok(["predict", calibrated.result_path, calibrated.configs, "-o", output, *args])
    return pd.read_csv(output)


def _distances(predicted: pd.DataFrame, measured: pd.DataFrame) -> np.ndarray:
    model = lie.pose_matrix(
        predicted[["x", "y", "z"]].to_numpy(), predicted[["qx", "qy", "qz", "qw"]].to_numpy()
    )
    actual = lie.pose_matrix(
        measured[["x", "y", "z"]].to_numpy(), measured[["qx", "qy", "qz", "qw"]].to_numpy()
    )
    residual = lie.se3_log(lie.inverse(model) @ actual)
    covariance = predicted[COV_COLUMNS].to_numpy().reshape(-1, 6, 6)
    return np.einsum(
        "nd,nd->n", residual, np.linalg.solve(covariance, residual[:, :, None])[..., 0]
    )


def test_the_predicted_95_percent_ellipsoid_holds_93_to_97_percent_of_fresh_poses(
    calibrated: Calibrated, tmp_path: Path
) -> None:
    """Acceptance (issue 13): ``kincal predict``'s default covariance (total, Σ_n included) on
    poses of the simulated robot that took no part in the calibration; three robots (seeds 1, 2,
    3), N_FRESH poses each, pooled (one robot alone varies by ~±1.5 %: seed 3 gives 92 %)."""
    distances = [_distances(_predict(calibrated), calibrated.fresh)]
    for seed in (1, 2):
        folder = tmp_path / f"seed{seed}"
        folder.mkdir()
        other = _calibrate_simulated(folder, seed)
        distances.append(_distances(_predict(other), other.fresh))
    pooled = np.concatenate(distances)
    inside = float(np.mean(pooled <= scipy.stats.chi2.ppf(0.95, 6)))
    assert 0.93 <= inside <= 0.97
    assert np.mean(pooled) == pytest.approx(6.0, rel=0.1)


def test_without_its_new_parts_the_prediction_covers_less(calibrated: Calibrated) -> None:
    """The old prediction (Σ_E + Σ_n, ``--part random-effects``) is narrower than the total:
    the parameter-estimation part is what a 200-pose calibration does not know."""
    total = _distances(_predict(calibrated), calibrated.fresh)
    old = _distances(_predict(calibrated, "--part", "random-effects"), calibrated.fresh)
    assert np.mean(old) > np.mean(total)
    assert np.all(old >= total - 1e-9 * np.abs(total))


def test_the_result_reports_the_heldout_coverage_and_what_rebuilds_the_total(
    calibrated: Calibrated,
) -> None:
    predictive = calibrated.result.predictive
    assert predictive is not None and predictive.coverage is not None
    found = predictive.coverage
    assert found.dimension == 6 and found.n_splits == 10
    assert found.n_heldout == sum(
        s.n_test for s in calibrated.result.evaluation.splits if s.method == "calibrated"
    )
    assert [c.level for c in found.levels] == [0.5, 0.9, 0.95, 0.99]
    observed = [c.observed for c in found.curve]
    assert observed == sorted(observed)
    assert 0.88 <= next(c.observed for c in found.levels if c.level == 0.95) <= 1.0
    assert found.chi2_mean == 6.0 and found.mean_mahalanobis_sq == pytest.approx(6.0, rel=0.35)
    names = predictive.parameter_covariance.parameters
    assert not set(names) & set(calibrated.result.identifiability.removed)
    assert len(names) == calibrated.result.identifiability.rank
    matrix = np.array(predictive.parameter_covariance.matrix)
    assert matrix.shape == (len(names), len(names)) and np.allclose(matrix, matrix.T)
    assert np.linalg.eigvalsh(matrix).min() >= -1e-12 * np.abs(matrix).max()
    assert predictive.model_error is not None and len(predictive.model_error.variance) == 6
    text = summary(calibrated.result)
    assert "predictive coverage on" in text and "in the 95 %" in text


def test_predict_parts_add_up_to_the_total(calibrated: Calibrated) -> None:
    parts = {
        part: _predict(calibrated, "--part", part)[COV_COLUMNS].to_numpy()
        for part in ("random-effects", "noise", "parameters", "model-error")
    }
    total = _predict(calibrated)[COV_COLUMNS].to_numpy()
    assert np.allclose(
        total, parts["random-effects"] + parts["parameters"] + parts["model-error"], rtol=1e-12
    )
    without_noise = _predict(calibrated, "--no-noise")[COV_COLUMNS].to_numpy()
    assert np.allclose(total - without_noise, parts["noise"], rtol=1e-9, atol=1e-18)
    dataset = read_dataset(calibrated.configs, list(calibrated.result.robot.joint_names))
    old = ranking.predict_covariances(calibrated.result, dataset.joint_positions)
    assert np.allclose(parts["random-effects"], old.reshape(-1, 36), rtol=1e-12)


def test_rank_scores_the_total_on_request_and_the_paper_score_by_default(
    calibrated: Calibrated,
) -> None:
    outputs = {}
    for name, extra in (("default", []), ("total", ["--uncertainty", "total"])):
        path = calibrated.scratch / f"ranking_{name}.json"
        run_ok(["rank", calibrated.result_path, calibrated.configs, "-o", path, *extra])
        outputs[name] = RankingResult.model_validate_json(path.read_text(encoding="utf-8"))
    default, total = outputs["default"], outputs["total"]
    assert default.uncertainty == "random_effects" and total.uncertainty == "total"
    paper = {e.index: e.score for e in default.ranking}
    for entry in total.ranking:
        assert entry.score_parts is not None
        assert entry.score_parts["random_effects"] == pytest.approx(paper[entry.index])
        assert entry.score == pytest.approx(sum(entry.score_parts.values()))
        assert entry.score > paper[entry.index]


def test_the_html_report_shows_the_coverage_plot(calibrated: Calibrated) -> None:
    dataset = read_dataset(
        calibrated.folder / "train.csv", list(calibrated.result.robot.joint_names)
    )
    page = render_report(
        calibrated.result, result_json.dataset_residuals(calibrated.result, dataset)
    )
    section = page.split("Predicted covariance on held-out poses (coverage)", 1)[1]
    assert '<img alt="Coverage: expected vs observed' in section
    assert "predictive coverage on" in section


def test_a_result_without_the_predictive_block_still_predicts_its_random_effects(
    calibrated: Calibrated,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Results written before issue 13: predict writes Σ_E + Σ_n and says what is missing;
    rank --uncertainty total refuses with the reason."""
    document = json.loads(calibrated.result_path.read_text(encoding="utf-8"))
    document.pop("predictive")
    old_path = calibrated.scratch / "old_result.json"
    old_path.write_text(json.dumps(document), encoding="utf-8")
    output = calibrated.scratch / "old_predicted.csv"
    run_ok(["predict", old_path, calibrated.configs, "-o", output])
    assert "has no predictive covariance" in capsys.readouterr().err
    written = pd.read_csv(output)[COV_COLUMNS].to_numpy()
    expected = _predict(calibrated, "--part", "random-effects")[COV_COLUMNS].to_numpy()
    assert np.allclose(written, expected, rtol=1e-12)
    ranking = calibrated.scratch / "old_ranking.json"
    args = ["rank", old_path, calibrated.configs, "-o", ranking, "--uncertainty", "total"]
    code, _, err = run(args, capsys, monkeypatch)
    assert code == 2 and "has no predictive covariance" in err


def test_real_fr3_recording_heldout_coverage_is_within_the_acceptance_band(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """Acceptance (issue 13) on the real FR3 recording, 10 held-out splits through ``kincal
    calibrate`` with its defaults (the model-based outlier rule keeps the clean rows; the 2σ rule
    truncated the residuals and the test rows): 90-98 % of held-out poses inside the predicted
    95 % ellipsoid, mean Mahalanobis² within 25 % of its χ² mean."""
    result = real_calibration(tmp_path_factory, "fr3")  # kincal calibrate with its defaults
    assert result.predictive is not None and result.predictive.coverage is not None
    found = result.predictive.coverage
    assert found.n_heldout == 110 and found.dimension == 6
    inside = next(c.observed for c in found.levels if c.level == 0.95)
    assert 0.90 <= inside <= 0.98
    assert found.mean_mahalanobis_sq == pytest.approx(found.chi2_mean, rel=0.25)


def test_coverage_benchmark_runs_on_a_small_recording() -> None:
    """benchmarks/coverage.py on the 23-pose UR10e recording with two splits (smoke)."""
    row = coverage_benchmark.measure(coverage_benchmark.RECORDINGS["ur10e"], "none", seeds=2)
    assert row.dimension == 6 and row.n_used == 23 and row.n_heldout > 0
    assert len(row.total) == 4 and all(0.0 <= v <= 1.0 for v in row.total)
    assert "UR10e" in coverage_benchmark.render_rules([row.row()])


def test_splits_with_many_training_rows_take_the_model_error_from_leave_one_out(
    tmp_path: Path,
) -> None:
    """Issue 17: beyond INNER_CV_ROWS training rows a split's model-error part comes from the
    leave-one-out residuals of its own fit (one covariance estimate per split, not four); the
    result says so, and the held-out poses are still covered."""
    recording = tmp_path / "recording.csv"
    effects = ["--effect", "geometry", "--effect", "random"]
    run_ok(["simulate", "--robot", "kinova", "--n", 620, "--seed", 5, *effects, "-o", recording])
    out = tmp_path / "result.json"
    run_ok(["calibrate", recording, "--robot", "kinova", "--seeds", "1,2,3", "-o", out])
    found = CalibrationResult.model_validate_json(out.read_text()).predictive
    assert found is not None and found.coverage is not None
    assert "leave-one-out" in found.coverage.protocol and "3-fold" not in found.coverage.protocol
    assert found.coverage.n_heldout == 3 * 62
    assert 0.85 <= next(c.observed for c in found.coverage.levels if c.level == 0.95) <= 1.0


def test_real_tiago_positions_heldout_coverage_is_within_the_acceptance_band(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Acceptance (issue 13) on a small real recording: the TIAGo Vicon gripper3/base1 file
    (21 poses, position-only, 3-D coverage) through ``kincal calibrate`` with its defaults:
    mean Mahalanobis² within 25 % of its χ² mean (3), and at every level the count of held-out
    poses inside the predicted ellipsoid within the central 99 % of Binomial(n, level).

    Issue 13 stated 90-98 % inside the 95 % ellipsoid. On n = 20 held-out poses that accepts
    18 or 19 only: a predictor of exactly the right covariance falls outside it 43 % of the
    time (20 of 20 inside has probability 0.36). Since issue 30 every row is used (the model
    rule's Σ_E step needs 3 equations per covariance entry, 63 for 42 here) and the count is
    20 of 20 with mean d² 3.00; with 17 rows it was 90 % and 2.88. benchmarks/coverage.py
    measures the 10-fold cross-validation through calibrate → predict on it and the other real
    recordings."""
    recording = coverage_benchmark.RECORDINGS["tiago"]
    assert recording.urdf is not None and recording.base and recording.tip
    output = tmp_path / "tiago.json"
    urdf = example_robot_data_dir() / recording.urdf
    args = ["calibrate", coverage_benchmark.DATA / recording.path, "--urdf", urdf]
    args += ["--base", recording.base, "--tip", recording.tip, "-o", output]
    code, _, err = run(args, capsys, monkeypatch)
    assert code in (0, 3), err
    result = CalibrationResult.model_validate_json(output.read_text(encoding="utf-8"))
    assert result.predictive is not None and result.predictive.coverage is not None
    found = result.predictive.coverage
    assert found.dimension == 3 and found.n_heldout >= 15
    assert found.mean_mahalanobis_sq == pytest.approx(found.chi2_mean, rel=0.25)
    n = found.n_heldout
    for level in found.levels:
        low, high = scipy.stats.binom.interval(0.99, n, level.level)
        assert low <= round(level.observed * n) <= high, (level, n)


def test_the_benchmark_scores_heldout_poses_as_kincal_predict_does(
    calibrated: Calibrated,
) -> None:
    """benchmarks/coverage.py's 10-fold protocol scores a fold's poses with the total that
    ``kincal predict`` writes, and the Σ_E + Σ_n of ``--part random-effects``; a clean pose is
    never screened as a detector failure."""
    dataset = read_dataset(calibrated.configs, list(calibrated.result.robot.joint_names))
    found = coverage_benchmark.heldout_distances(calibrated.result, dataset)
    assert np.allclose(found.total, _distances(_predict(calibrated), calibrated.fresh))
    before = _distances(_predict(calibrated, "--part", "random-effects"), calibrated.fresh)
    assert np.allclose(found.random_effects, before)
    assert found.scored.all()
    row = coverage_benchmark.FoldCoverage(
        "sim", len(found.total), coverage(found.total, 6), coverage(before, 6), 0, (), 1.0, ()
    )
    assert "| sim | 600 | 6 | 600 / 0 |" in coverage_benchmark.render_folds([row.row()])
