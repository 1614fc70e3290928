"""Stacks of small SPD matrices factored entry by entry (solver.small_spd) against LAPACK
(numpy.linalg), and the Mahalanobis distances built on them against the eigendecomposition way."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from solver.predictive import _mahalanobis_squared_eigh, mahalanobis_squared
from solver.small_spd import spd_factors


def _spd(rng: np.random.Generator, n: int, d: int, spread: float) -> np.ndarray:
    """Random SPD matrices whose eigenvalues span ``spread`` decades at random scales."""
    rotations = np.linalg.qr(rng.normal(size=(n, d, d)))[0]
    values = 10.0 ** rng.uniform(-spread, 0.0, size=(n, d)) * 10.0 ** rng.uniform(-8, 2, (n, 1))
    return np.einsum("nij,nj,nkj->nik", rotations, values, rotations)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), d=st.sampled_from([1, 2, 3, 6]), spread=st.floats(0, 6))
def test_factors_match_lapack(seed: int, d: int, spread: float) -> None:
    rng = np.random.default_rng(seed)
    covariances = _spd(rng, 50, d, spread)
    factors = spd_factors(covariances)
    assert factors.positive_definite.all()
    sign, log_det = np.linalg.slogdet(covariances)
    assert np.all(sign > 0)
    np.testing.assert_allclose(factors.log_det, log_det, rtol=1e-9, atol=1e-9)
    inverse = factors.inverse()
    reference = np.linalg.inv(covariances)
    scale = np.abs(reference).max(axis=(1, 2), keepdims=True)
    condition = np.linalg.cond(covariances)[:, None, None]
    assert np.all(np.abs(inverse - reference) <= 1e-13 * condition * scale)
    assert np.array_equal(inverse, inverse.transpose(0, 2, 1))
    residuals = rng.normal(size=(50, d))
    whitened = factors.whiten(residuals)
    d2 = np.einsum("nd,nd->n", whitened, whitened)
    expected = np.einsum("nd,nde,ne->n", residuals, reference, residuals)
    np.testing.assert_allclose(d2, expected, rtol=1e-13 * condition.max() + 1e-12)


def test_a_matrix_that_is_not_positive_definite_is_marked_and_only_it() -> None:
    rng = np.random.default_rng(3)
    covariances = _spd(rng, 6, 3, 2.0)
    covariances[1] = np.diag([1.0, -1e-9, 2.0])  # indefinite
    covariances[4] = np.diag([1.0, 0.0, 2.0])  # singular
    covariances[5, 0, 0] = np.nan
    factors = spd_factors(covariances)
    assert factors.positive_definite.tolist() == [True, False, True, True, False, False]
    assert np.all(np.isfinite(factors.log_det[[0, 2, 3]]))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), d=st.sampled_from([3, 6]), spread=st.floats(0, 14))
def test_mahalanobis_matches_the_eigendecomposition_way(seed: int, d: int, spread: float) -> None:
    """Well and badly conditioned (up to 1e14) and singular Σ_n in one stack: the Cholesky
    way where it is safe, the eigendecomposition way elsewhere, the same answers."""
    rng = np.random.default_rng(seed)
    covariances = _spd(rng, 40, d, spread)
    covariances[::7] = np.diag(np.r_[np.ones(d - 1), 0.0])  # singular: inf off its range
    residuals = rng.normal(size=(40, d))
    residuals[::14, -1] = 0.0  # inside the singular range: finite
    found = mahalanobis_squared(residuals, covariances)
    expected = _mahalanobis_squared_eigh(residuals, covariances)
    assert np.array_equal(np.isinf(found), np.isinf(expected))
    finite = np.isfinite(expected)
    # both ways lose ~1e-16 · condition number relative (eigh on its smallest eigenvalues)
    condition = np.minimum(np.linalg.cond(covariances[finite]), 1e16)
    assert np.all(np.abs(found[finite] - expected[finite]) <= 1e-12 * condition * expected[finite])


def test_the_fast_way_is_taken_for_well_conditioned_covariances(monkeypatch) -> None:
    import solver.predictive as predictive

    def refuse(*_args: object) -> None:
        raise AssertionError("the eigendecomposition way was taken")

    monkeypatch.setattr(predictive, "_mahalanobis_squared_eigh", refuse)
    rng = np.random.default_rng(0)
    covariances = _spd(rng, 100, 6, 3.0)
    residuals = rng.normal(size=(100, 6))
    d2 = mahalanobis_squared(residuals, covariances)
    expected = np.einsum("nd,nde,ne->n", residuals, np.linalg.inv(covariances), residuals)
    np.testing.assert_allclose(d2, expected, rtol=1e-9)
    assert d2 == pytest.approx(expected)
