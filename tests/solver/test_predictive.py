"""The parts of the predictive covariance (solver/predictive.py) against Monte Carlo, finite
differences and known truth."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats
from hypothesis import given
from hypothesis import strategies as st

from solver import lie
from solver.measurement import FullPose, Position
from solver.predictive import (
    coverage,
    estimate_model_error,
    leave_one_out_residuals,
    mahalanobis_squared,
    measurement_axes,
    model_error_part,
    parameter_covariance,
    parameter_part,
    row_weights,
    sandwich_meat,
)


def _random_covariances(rng: np.random.Generator, n: int, d: int, scale: float) -> np.ndarray:
    factors = rng.normal(size=(n, d, d)) * scale
    return factors @ factors.transpose(0, 2, 1) + 1e-3 * scale**2 * np.eye(d)


def _rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = lie.so3_exp(rng.normal(size=(n, 3)))
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    poses[:, 3, 3] = 1.0
    return poses


def test_sandwich_covariance_is_the_spread_of_weighted_least_squares_refits() -> None:
    """Cov(θ̂) = G⁻¹ (Σ A_wᵀ W Σ_n W A_w) G⁻¹ of the rotation-weighted least-squares fit with
    heteroscedastic, correlated 6-D residuals: equal to the covariance of θ̂ over 4000
    Monte Carlo redraws of the residuals (a missing weight or a wrong meat shows at once)."""
    rng = np.random.default_rng(0)
    n, d, p = 60, 6, 5
    jacobian = rng.normal(size=(n, d, p))
    covariances = _random_covariances(rng, n, d, 0.1)
    weights = row_weights(d, 0.3)
    weighted = weights[None, :, None] * jacobian
    design = weighted.reshape(-1, p)
    chol = np.linalg.cholesky(covariances)
    draws = 4000
    noise = np.einsum("nde,kne->knd", chol, rng.normal(size=(draws, n, d)))
    targets = (weights * noise).reshape(draws, -1)
    estimates = np.linalg.lstsq(design, targets.T, rcond=None)[0].T
    empirical = np.cov(estimates.T)
    predicted = parameter_covariance(
        design.T @ design, sandwich_meat(weighted, covariances, weights)
    )
    assert np.allclose(predicted, empirical, rtol=0.12, atol=0.05 * np.abs(predicted).max())
    assert np.allclose(np.sqrt(np.diag(predicted)), np.sqrt(np.diag(empirical)), rtol=0.05)


def test_leave_one_out_residuals_equal_refits_without_the_sample() -> None:
    """The deletion identity W⁻¹(I − H_nn)⁻¹ W r_n equals the residual of sample n under the
    weighted least-squares fit of the other samples, refitted explicitly."""
    rng = np.random.default_rng(5)
    n, d, p = 25, 6, 7
    jacobian = rng.normal(size=(n, d, p))
    target = rng.normal(size=(n, d))
    weights = row_weights(d, 0.4)
    weighted = weights[None, :, None] * jacobian
    design = weighted.reshape(-1, p)
    solution = np.linalg.lstsq(design, (weights * target).reshape(-1), rcond=None)[0]
    residuals = target - np.einsum("ndp,p->nd", jacobian, solution)
    fast = leave_one_out_residuals(residuals, weighted, weights, design.T @ design)
    for left in range(n):
        others = np.delete(np.arange(n), left)
        rows = weighted[others].reshape(-1, p)
        refit = np.linalg.lstsq(rows, (weights * target[others]).reshape(-1), rcond=None)[0]
        assert np.allclose(fast[left], target[left] - jacobian[left] @ refit, atol=1e-10)


def test_parameter_part_is_the_covariance_of_the_propagated_error() -> None:
    """J Cov Jᵀ at new configurations equals the sample covariance of J δθ, δθ ~ N(0, Cov)."""
    rng = np.random.default_rng(1)
    jacobian = rng.normal(size=(3, 6, 4))
    factor = rng.normal(size=(4, 4))
    covariance = factor @ factor.T
    draws = rng.multivariate_normal(np.zeros(4), covariance, size=20000)
    moved = np.einsum("ndp,kp->knd", jacobian, draws)
    empirical = np.einsum("knd,kne->nde", moved, moved) / draws.shape[0]
    part = parameter_part(jacobian, covariance)
    assert np.allclose(part, empirical, rtol=0.05, atol=0.03 * np.abs(part).max())


@given(st.integers(0, 2**31), st.booleans())
def test_measurement_axes_map_an_error_along_the_measurement_frame_to_the_residual(
    seed: int, rotation: bool
) -> None:
    """A small error [δp; δω] along the measurement frame's axes (X' = [Exp(δω) R, p + δp])
    moves the residual Log(X⁻¹X') by T [δp; δω] to first order (finite difference)."""
    rng = np.random.default_rng(seed)
    model = _rotations(rng, 4)
    error = 1e-6 * rng.normal(size=(4, 6))
    measured = model.copy()
    measured[:, :3, :3] = lie.so3_exp(error[:, 3:]) @ model[:, :3, :3]
    measured[:, :3, 3] += error[:, :3]
    measurement = FullPose() if rotation else Position()
    residual = measurement.residuals(model, measured)
    mapped = np.einsum(
        "nab,nb->na", measurement_axes(model, measurement.dim), error[:, : measurement.dim]
    )
    assert np.allclose(residual, mapped, atol=1e-11)


def test_model_error_part_is_diagonal_along_the_measurement_axes() -> None:
    rng = np.random.default_rng(2)
    poses = _rotations(rng, 5)
    variances = np.array([1.0, 4.0, 9.0, 0.01, 0.04, 0.09])
    axes = measurement_axes(poses, 6)
    part = model_error_part(axes, variances)
    back = np.einsum("nda,nde,neb->nab", axes, part, axes)
    assert np.allclose(back, np.diag(variances)[None], atol=1e-12)


@pytest.mark.parametrize("truth_std", [(0.0, 0.0, 0.0), (0.5, 1.0, 0.2)])
def test_model_error_maximum_likelihood_recovers_known_variances(
    truth_std: tuple[float, float, float],
) -> None:
    """Residuals drawn from base_n + T_n diag(s) T_nᵀ (varied base and orientation): the ML
    estimate is within 10 % of s (≈ 0 when there is no model error)."""
    rng = np.random.default_rng(3)
    n = 4000
    poses = _rotations(rng, n)
    axes = measurement_axes(poses, 3)
    base = _random_covariances(rng, n, 3, 0.4)
    truth = np.square(truth_std)
    total = base + model_error_part(axes, truth)
    residuals = np.einsum("nde,ne->nd", np.linalg.cholesky(total), rng.normal(size=(n, 3)))
    fit = estimate_model_error(residuals, base, axes)
    assert fit.converged and fit.n_residuals == n
    assert np.all(np.abs(np.sqrt(fit.variance) - truth_std) <= 0.1 * max(truth_std) + 0.06)


def test_coverage_of_exact_covariances_follows_chi_square() -> None:
    """Residuals drawn from the covariance they are scored with: the observed shares match the
    levels and the mean d² is the dimension."""
    rng = np.random.default_rng(4)
    n = 20000
    covariances = _random_covariances(rng, n, 6, 1.0)
    residuals = np.einsum("nde,ne->nd", np.linalg.cholesky(covariances), rng.normal(size=(n, 6)))
    found = coverage(mahalanobis_squared(residuals, covariances), 6)
    for level in (0.5, 0.9, 0.95, 0.99):
        assert found.at(level) == pytest.approx(level, abs=0.01)
    assert found.mean_d2 == pytest.approx(6.0, rel=0.03)
    assert found.chi2_median == pytest.approx(scipy.stats.chi2.median(6))


def test_a_residual_outside_a_singular_covariance_is_infinitely_far() -> None:
    covariance = np.diag([1.0, 1.0, 0.0])[None]
    assert mahalanobis_squared(np.array([[1.0, 2.0, 0.0]]), covariance)[0] == pytest.approx(5.0)
    assert mahalanobis_squared(np.array([[1.0, 2.0, 1e-3]]), covariance)[0] == np.inf
