"""Eq. (12), the ML (Eq. 16–17) and REML likelihoods: values, gradients, Fisher information."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from solver.covariance import (
    column_matrix,
    ee_covariance_batch,
    estimate_covariances,
    fisher_information_ml,
    fisher_information_reml,
    fit_basis_transform,
    gaussian_nll,
    make_layout,
    restricted_nll,
    theta_gradient,
)
from solver.covariance.layout import block_diagonal
from solver.covariance.likelihood import average_information, observed_information
from solver.covariance.samples import ArraySamples
from solver.errors import CalibrationError
from tests.solver import covariance_support as S


def case(structure, residual_dim, known, seed=0, n=15, n_frames=2):
    rng = np.random.default_rng(seed)
    jac = S.random_frame_jacobians(n, n_frames, rng, residual_dim=residual_dim)
    layout = make_layout(
        [f"f{i}" for i in range(n_frames)],
        residual_dim,
        structure=structure,
        include_noise=not known,
    )
    roots = rng.normal(size=(layout.n_frames, 6, 6)) * 2e-3
    covs = roots @ roots.transpose(0, 2, 1)
    if structure == "diag":
        covs = np.einsum("fii->fi", covs)[:, :, None] * np.eye(6)
    theta = layout.theta_from_covariances(covs)
    known_cov = np.diag(rng.uniform(1, 3, residual_dim)) * 1e-6 if known else None
    residuals = rng.normal(size=(n, residual_dim)) * 3e-3
    fit = rng.normal(size=(n, residual_dim, 5))
    return layout, theta, jac, residuals, known_cov, fit


def dense(layout, theta, jac, known_cov):
    """V = blockdiag Σ_E(q_n) and ∂V/∂θ_p as dense (N·d)² matrices."""
    cols = column_matrix(jac, layout)
    n, d, _ = cols.shape

    def stack(t):
        blocks = cols @ block_diagonal(layout.frame_covariances(t)) @ cols.transpose(0, 2, 1)
        out = np.zeros((n * d, n * d))
        for k in range(n):
            out[k * d : (k + 1) * d, k * d : (k + 1) * d] = blocks[k]
        return out

    v = stack(theta)
    if known_cov is not None:
        v += np.kron(np.eye(n), known_cov)
    return v, [stack(e) for e in np.eye(layout.n_params)]


CASES = [
    ("diag", 6, False),
    ("full", 6, False),
    ("diag", 3, True),
    ("full", 3, True),
    ("diag", 6, True),
]


@pytest.mark.parametrize(("structure", "d", "known"), CASES)
def test_ml_and_reml_values_equal_the_dense_formulas(structure, d, known):
    layout, theta, jac, r, known_cov, fit = case(structure, d, known)
    v, _ = dense(layout, theta, jac, known_cov)
    x = fit.reshape(-1, fit.shape[2])
    v_inv = np.linalg.inv(v)
    rs = r.reshape(-1)
    p = v_inv - v_inv @ x @ np.linalg.solve(x.T @ v_inv @ x, x.T @ v_inv)
    ml = np.linalg.slogdet(v)[1] + rs @ v_inv @ rs
    samples = ArraySamples(r, jac, fit, chunk_size=4)
    transform = fit_basis_transform(samples)
    basis = x @ transform
    np.testing.assert_allclose(basis.T @ basis, np.eye(5), atol=1e-12)  # orthonormal
    reml = np.linalg.slogdet(v)[1] + np.linalg.slogdet(basis.T @ v_inv @ basis)[1] + rs @ p @ rs
    kw = {"known_covariance": known_cov}
    assert gaussian_nll(theta, samples, layout, **kw)[0] == pytest.approx(ml, rel=1e-10)
    assert restricted_nll(theta, samples, transform, layout, **kw)[0] == pytest.approx(
        reml, rel=1e-10
    )


@pytest.mark.parametrize(("structure", "d", "known"), CASES)
@pytest.mark.parametrize("estimator", ["ml", "reml"])
def test_analytic_gradients_match_finite_differences(structure, d, known, estimator):
    layout, theta, jac, r, known_cov, fit = case(structure, d, known, seed=1)
    samples = ArraySamples(r, jac, fit, chunk_size=4)
    transform = fit_basis_transform(samples)

    def f(t):
        if estimator == "ml":
            return gaussian_nll(t, samples, layout, known_covariance=known_cov)
        return restricted_nll(t, samples, transform, layout, known_covariance=known_cov)

    grad = theta_gradient(layout, f(theta)[1])
    step = 1e-4 * np.abs(theta).max()
    numeric = np.array(
        [
            (f(theta + step * e)[0] - f(theta - step * e)[0]) / (2 * step)
            for e in np.eye(layout.n_params)
        ]
    )
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())


def reml_projection(v_inv, fit):
    """P = V⁻¹ − V⁻¹X(XᵀV⁻¹X)⁻¹XᵀV⁻¹ with X the stacked fit Jacobian (N·d, p)."""
    x = fit.reshape(-1, fit.shape[2])
    return v_inv - v_inv @ x @ np.linalg.solve(x.T @ v_inv @ x, x.T @ v_inv)


@pytest.mark.parametrize(("structure", "d", "known"), CASES[:3])
def test_fisher_information_equals_half_the_trace_formula(structure, d, known):
    layout, theta, jac, _, known_cov, fit = case(structure, d, known, seed=2, n=10)
    v, dv = dense(layout, theta, jac, known_cov)
    v_inv = np.linalg.inv(v)
    p = reml_projection(v_inv, fit)
    ml = 0.5 * np.array([[np.trace(v_inv @ a @ v_inv @ b) for b in dv] for a in dv])
    reml = 0.5 * np.array([[np.trace(p @ a @ p @ b) for b in dv] for a in dv])
    got_ml = fisher_information_ml(theta, jac, layout, known_covariance=known_cov)
    basis = fit @ fit_basis_transform(ArraySamples(np.zeros((10, d)), jac, fit))
    got_reml = fisher_information_reml(
        theta, jac, basis, layout, known_covariance=known_cov, chunk_size=3
    )
    np.testing.assert_allclose(got_ml, ml, rtol=1e-9, atol=1e-12 * np.abs(ml).max())
    np.testing.assert_allclose(got_reml, reml, rtol=1e-9, atol=1e-12 * np.abs(reml).max())


@pytest.mark.parametrize(("structure", "d", "known"), CASES)
def test_average_information_equals_the_dense_formula(structure, d, known):
    """``H_pq = rᵀ P V_p P V_q P r`` with P = V⁻¹ (ML) or the REML projection."""
    layout, theta, jac, r, known_cov, fit = case(structure, d, known, seed=3, n=12)
    v, dv = dense(layout, theta, jac, known_cov)
    v_inv = np.linalg.inv(v)
    p = reml_projection(v_inv, fit)
    rs = r.reshape(-1)
    samples = ArraySamples(r, jac, fit)
    transform = fit_basis_transform(samples)
    for projection, fit_basis in ((v_inv, None), (p, transform)):
        u = np.stack([a @ projection @ rs for a in dv], axis=1)  # V_p P r
        expected = u.T @ projection @ u
        got = average_information(
            theta, samples, layout, transform=fit_basis, known_covariance=known_cov
        )
        np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-12 * np.abs(expected).max())
        assert np.linalg.eigvalsh(got).min() >= -1e-12 * np.linalg.eigvalsh(got).max()


@pytest.mark.parametrize("estimator", ["ml", "reml"])
def test_average_information_is_the_mean_of_observed_and_expected(estimator):
    """AI = ½(H_obs + H_exp) for the NLL (= −2 log L): the observed Hessian from finite
    differences of the analytic gradient, the expected one 2·(Fisher information)."""
    layout, theta, jac, r, _, fit = case("diag", 6, False, seed=4, n=12)
    samples = ArraySamples(r, jac, fit)
    transform = fit_basis_transform(samples)
    fit_basis = transform if estimator == "reml" else None

    def gradient(t):
        if estimator == "ml":
            return theta_gradient(layout, gaussian_nll(t, samples, layout)[1])
        return theta_gradient(layout, restricted_nll(t, samples, transform, layout)[1])

    step = 1e-5 * np.abs(theta).max()
    observed = np.stack(
        [
            (gradient(theta + step * e) - gradient(theta - step * e)) / (2 * step)
            for e in np.eye(layout.n_params)
        ]
    )
    observed = 0.5 * (observed + observed.T)
    if estimator == "ml":
        expected = 2 * fisher_information_ml(theta, jac, layout)
    else:
        expected = 2 * fisher_information_reml(theta, jac, fit @ transform, layout)
    got = average_information(theta, samples, layout, transform=fit_basis)
    mean = 0.5 * (observed + expected)
    np.testing.assert_allclose(got, mean, rtol=1e-4, atol=1e-6 * np.abs(mean).max())


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**16),
    structure=st.sampled_from(["diag", "full"]),
    d=st.sampled_from([3, 6]),
    known=st.booleans(),
    estimator=st.sampled_from(["ml", "reml"]),
    n=st.integers(6, 14),
)
def test_the_nll_hessian_is_twice_the_average_minus_twice_the_expected_information(
    seed, structure, d, known, estimator, n
):
    """``∂²NLL/∂θ∂θᵀ = 2·AI − 2·I`` (:func:`observed_information`), against central differences
    of the analytic gradient, at random θ, residuals and configurations (ML and REML, diagonal
    and full Σ, with and without a known part of Σ_E)."""
    layout, theta, jac, r, known_cov, fit = case(structure, d, known, seed=seed, n=n)
    samples = ArraySamples(r, jac, fit)
    transform = fit_basis_transform(samples) if estimator == "reml" else None

    def gradient(t):
        if transform is None:
            psi = gaussian_nll(t, samples, layout, known_covariance=known_cov)[1]
        else:
            psi = restricted_nll(t, samples, transform, layout, known_covariance=known_cov)[1]
        return theta_gradient(layout, psi)

    step = 1e-5 * np.abs(theta).max()
    numeric = np.stack(
        [
            (gradient(theta + step * e) - gradient(theta - step * e)) / (2 * step)
            for e in np.eye(layout.n_params)
        ]
    )
    got = observed_information(
        theta, samples, layout, transform=transform, known_covariance=known_cov
    )
    np.testing.assert_allclose(got, got.T, rtol=0, atol=1e-10 * np.abs(got).max())
    np.testing.assert_allclose(got, numeric, rtol=1e-6, atol=1e-8 * np.abs(numeric).max())


def test_ee_covariance_batch_is_eq_12():
    rng = np.random.default_rng(3)
    jac = S.random_frame_jacobians(7, 3, rng)
    roots = rng.normal(size=(3, 6, 6))
    covs = roots @ roots.transpose(0, 2, 1)
    noise = np.diag(rng.uniform(size=6))
    want = np.array(
        [noise + sum(jac[n, f] @ covs[f] @ jac[n, f].T for f in range(3)) for n in range(7)]
    )
    np.testing.assert_allclose(ee_covariance_batch(jac, covs, noise), want, rtol=1e-12)
    np.testing.assert_allclose(
        ee_covariance_batch(jac[:, :, :3], covs, noise), want[:, :3, :3], rtol=1e-12
    )


def test_ml_is_a_weighted_moment_match_not_eq_13():
    """The paper's Eq. (20–21) claim ML = moment matching; the ML gradient at the moment
    solution is not zero, and the ML fit ends at a stationary point of Eq. (17)."""
    names = S.jaco_joint_names()
    data = S.simulate_jaco(300, seed=4)
    free = {n: ("w_x", "w_y", "w_z") for n in names}
    noise = np.diag(S.NOISE_STD**2)
    kw = {"free_axes": free, "noise_covariance": noise, "standard_errors": False, "solver": "nnls"}
    moment = estimate_covariances(data.residuals, data.frame_jacobians, names, **kw)
    ml = estimate_covariances(data.residuals, data.frame_jacobians, names, estimator="ml", **kw)
    assert ml.solution.status == "optimal"
    layout = ml.layout
    scale = ml.identifiability.scaling.param_scale
    identifiable = ml.identifiability.identifiable

    def scaled_grad(theta):
        _, psi = gaussian_nll(
            theta,
            ArraySamples(data.residuals, data.frame_jacobians),
            layout,
            known_covariance=noise,
        )
        return theta_gradient(layout, psi) * scale / 300

    at_moment, at_ml = scaled_grad(moment.theta), scaled_grad(ml.theta)
    interior = identifiable & (ml.theta > 1e-3 * ml.theta.max())
    assert np.abs(at_ml[interior]).max() < 1e-4 * np.abs(at_moment[interior]).max()
    assert ml.solution.objective < estimate_nll(moment.theta, data, layout, noise)


def estimate_nll(theta, data, layout, noise):
    samples = ArraySamples(data.residuals, data.frame_jacobians)
    return gaussian_nll(theta, samples, layout, known_covariance=noise)[0]


def test_reml_without_the_fit_jacobian_is_refused():
    rng = np.random.default_rng(5)
    jac = S.random_frame_jacobians(20, 1, rng)
    with pytest.raises(CalibrationError, match="fit_jacobian"):
        estimate_covariances(rng.normal(size=(20, 6)), jac, ["a"], estimator="reml")


def test_the_noise_floor_is_a_thousandth_of_each_axis_rms_residual():
    """The likelihood fit bounds each noise variance below by (1e-3 · RMS residual on the rows
    its axis reaches)², read from the moment statistics (so the same whether the samples were
    read whole or streamed); chain frames are not bounded (fitting.noise_floor)."""
    from solver.covariance.fitting import NOISE_FLOOR, noise_floor
    from solver.covariance.statistics import build_moment_statistics

    def floor_of(layout, residuals):
        jac = rng.normal(size=(residuals.shape[0], layout.n_chain_frames, layout.residual_dim, 6))
        return noise_floor(build_moment_statistics(residuals, jac, layout))

    rng = np.random.default_rng(5)
    residuals = rng.normal(size=(400, 3)) * np.array([1e-3, 2e-3, 4e-3])
    layout = make_layout(["f0", "f1"], 3)
    floor = floor_of(layout, residuals)
    rms = np.sqrt(np.mean(residuals**2, axis=0))
    noise = layout.is_noise & layout.is_variance
    axes = layout.param_row[noise]  # the noise's rotation axes reach no row of a position
    np.testing.assert_allclose(floor[noise][axes < 3], (NOISE_FLOOR * rms) ** 2)
    assert np.all(floor[noise][axes >= 3] == 0.0)
    assert np.all(floor[~layout.is_noise] == 0.0)
    markers = make_layout(
        ["f0"], 6, noise_rows={"noise": ((0, 1, 2, -1, -1, -1), (3, 4, 5, -1, -1, -1))}
    )
    pair = np.hstack([residuals, 3.0 * residuals])  # two markers: the second 3x the first
    tied = floor_of(markers, pair)
    expected = NOISE_FLOOR**2 * 0.5 * (rms**2 + (3.0 * rms) ** 2)
    np.testing.assert_allclose(tied[markers.is_noise & markers.is_variance][:3], expected)
