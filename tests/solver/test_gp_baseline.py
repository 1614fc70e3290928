"""GP baseline of paper ref. [13]: it learns a configuration-dependent pose error, works as a
``cross_validate`` method, and its variances are positive and grow away from the data."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from solver import lie
from solver.errors import CalibrationError
from solver.evaluation import cross_validate
from solver.gp_baseline import (
    GPErrorModel,
    GPSettings,
    corrected_poses,
    fit_gp_error_model,
    gp_method,
    gp_scores,
)
from solver.kinematics import pose_residuals, position_residuals
from solver.measurement import FullPose
from solver.ranking import TaskMetric

SETTINGS = GPSettings(n_restarts_optimizer=0)


@functools.cache
def _data(n: int = 80) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint angles, a "before" model's poses, and measurements off by a smooth error + noise."""
    rng = np.random.default_rng(0)
    q = rng.uniform(-1.5, 1.5, size=(n, 4))
    before = lie.se3_exp(rng.normal(scale=0.3, size=(n, 6)) + np.r_[0.5, 0.0, 0.3, 0, 0, 0])
    error = np.stack(
        [
            2e-3 * np.sin(q[:, 0]),
            1e-3 * np.cos(q[:, 1]) * q[:, 0],
            1.5e-3 * np.sin(q[:, 1] + q[:, 2]),
            2e-3 * np.cos(q[:, 0]),
            1e-3 * q[:, 2],
            5e-4 * np.sin(2.0 * q[:, 3]),
        ],
        axis=1,
    )
    noise = rng.normal(scale=5e-5, size=(n, 6))
    return q, before, before @ lie.se3_exp(error + noise)


def test_gp_correction_reduces_training_residuals() -> None:
    q, before, measured = _data()
    residuals = pose_residuals(before, measured)
    model = fit_gp_error_model(q, residuals, SETTINGS)
    after = pose_residuals(corrected_poses(model, before, q), measured)
    rms = lambda r: float(np.sqrt(np.mean(r**2)))  # noqa: E731
    assert rms(after) < 0.2 * rms(residuals)


@functools.cache
def _model() -> GPErrorModel:
    q, before, measured = _data()
    return fit_gp_error_model(q, pose_residuals(before, measured), SETTINGS)


def test_gp_variances_are_positive_and_grow_away_from_the_data() -> None:
    q, _, _ = _data()
    model = _model()
    _, near = model.predict(q[:10])
    _, far = model.predict(q[:10] + 6.0)
    assert np.all(near > 0.0) and np.all(far > 0.0)
    assert np.all(far.mean(axis=0) > near.mean(axis=0))


def test_gp_is_a_cross_validation_method_and_beats_the_uncorrected_model() -> None:
    q, before, measured = _data()
    methods = {
        "before": lambda train, test: before[test],
        "gp": gp_method(q, measured, before, measurement=FullPose(), settings=SETTINGS),
    }
    splits = cross_validate(measured, methods, rotation=True, seeds=(1, 2))
    by = {(s.method, s.seed): s for s in splits}
    for seed in (1, 2):
        assert by[("gp", seed)].translation_mm < 0.5 * by[("before", seed)].translation_mm
        assert by[("gp", seed)].rotation_deg < 0.5 * by[("before", seed)].rotation_deg  # type: ignore[operator]


def test_gp_method_refits_the_baseline_on_training_rows_only() -> None:
    q, before, measured = _data()
    seen: list[tuple[int, ...]] = []

    def baseline(train: np.ndarray, rows: np.ndarray) -> np.ndarray:
        seen.append(tuple(train.tolist()))
        return before[rows]

    method = gp_method(q, measured, baseline, measurement=FullPose(), settings=SETTINGS)
    train, test = np.arange(0, 60), np.arange(60, 80)
    method(train, test)
    assert seen and all(set(s) == set(train.tolist()) for s in seen)


def test_gp_of_positions_corrects_translation_only() -> None:
    q, before, measured = _data()
    residuals = position_residuals(before, measured)
    model = fit_gp_error_model(q, residuals, SETTINGS)
    corrected = corrected_poses(model, before, q)
    assert np.array_equal(corrected[:, :3, :3], before[:, :3, :3])
    after = position_residuals(corrected, measured)
    assert np.sqrt(np.mean(after**2)) < 0.2 * np.sqrt(np.mean(residuals**2))
    scores = gp_scores(model, q, TaskMetric.pose_weights())
    assert np.all(scores.ee_variance[:, 3:] == 0.0) and np.all(scores.score > 0.0)


def test_gp_scores_put_the_variances_on_the_covariance_diagonal() -> None:
    q, _, _ = _data()
    model = _model()
    metric = TaskMetric.pose_weights()
    scores = gp_scores(model, q[:5], metric)
    _, variance = model.predict(q[:5])
    expected = np.array([np.trace(metric.matrix @ np.diag(v) @ metric.matrix.T) for v in variance])
    assert np.allclose(scores.score, expected, rtol=1e-12)


def test_bad_gp_input_is_a_calibration_error() -> None:
    with pytest.raises(CalibrationError, match="residuals"):
        fit_gp_error_model(np.zeros((5, 3)), np.zeros((5, 2)))
    with pytest.raises(CalibrationError, match="at least 3"):
        fit_gp_error_model(np.zeros((2, 3)), np.zeros((2, 6)))
