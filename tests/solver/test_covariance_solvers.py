"""Solvers of Eq. (14): agreement, PSD answers, honest statuses (incl. the published PGD)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from solver.covariance import (
    PGD_PUBLISHED,
    PGD_STABLE,
    build_moment_statistics,
    make_layout,
    moment_objective,
    published_step_limit,
    solve_clarabel,
    solve_moment,
    solve_nnls,
    solve_pgd,
)
from solver.covariance.solvers import _CVXPY_STATUS, KKT_TOLERANCE
from solver.errors import SolverError
from tests.solver import covariance_support as S

ROTATION_ONLY = ("w_x", "w_y", "w_z")


def jaco_statistics(n, seed, *, free_axes=None, structure="diag"):
    data = S.simulate_jaco(n, seed)
    layout = make_layout(S.jaco_joint_names(), 6, structure=structure, free_axes=free_axes)
    return build_moment_statistics(data.residuals, data.frame_jacobians, layout)


def assert_psd(solution, layout):
    covs = solution.frame_covariances
    assert covs.shape == (layout.n_frames, 6, 6)
    np.testing.assert_array_equal(covs, covs.transpose(0, 2, 1))
    scale = max(float(np.abs(covs).max()), 1e-300)
    assert np.linalg.eigvalsh(covs).min() >= -1e-12 * scale
    np.testing.assert_allclose(layout.frame_covariances(solution.theta), covs)


@pytest.mark.parametrize(
    ("n", "free"),
    [(500, "rotation+noise"), (800, "rotation+noise"), (600, "all")],
)
def test_clarabel_stable_pgd_and_nnls_agree_on_the_objective(n, free):
    names = S.jaco_joint_names()
    free_axes = {name: ROTATION_ONLY for name in names} if free == "rotation+noise" else None
    stats = jaco_statistics(n, seed=n, free_axes=free_axes)
    solutions = [solve_clarabel(stats), solve_pgd(stats, PGD_STABLE), solve_nnls(stats)]
    values = [s.objective for s in solutions]
    for s in solutions:
        assert s.status == "optimal", (s.solver, s.status, s.message)
        assert s.objective == pytest.approx(moment_objective(s.theta, stats), rel=1e-12)
        assert_psd(s, stats.layout)
    assert max(values) - min(values) <= 1e-6 * min(values), values


@pytest.mark.parametrize(("structure", "expected"), [("diag", "nnls"), ("full", "clarabel")])
def test_auto_is_the_exact_solver_for_the_structure(structure, expected):
    stats = jaco_statistics(
        300, seed=3, structure=structure, free_axes={n: ROTATION_ONLY for n in S.jaco_joint_names()}
    )
    auto = solve_moment(stats, "auto")
    assert auto.solver == expected
    assert auto.objective == pytest.approx(solve_clarabel(stats).objective, rel=1e-6)


def test_full_covariances_from_clarabel_and_stable_pgd_agree():
    stats = jaco_statistics(
        400, seed=5, structure="full", free_axes={n: ROTATION_ONLY for n in S.jaco_joint_names()}
    )
    a, b = solve_clarabel(stats), solve_pgd(stats, PGD_STABLE)
    assert a.status in ("optimal", "optimal_inaccurate") and b.status == "optimal"
    assert abs(a.objective - b.objective) <= 1e-6 * b.objective
    assert_psd(a, stats.layout)
    assert_psd(b, stats.layout)


@st.composite
def instances(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    n_frames = draw(st.integers(1, 3))
    d = draw(st.sampled_from([3, 6]))
    n = draw(st.integers(8, 60))
    structure = draw(st.sampled_from(["diag", "full"]))
    jac = S.random_frame_jacobians(n, n_frames, rng, residual_dim=d)
    scale = 10.0 ** draw(st.floats(-4, -1))
    residuals = rng.standard_t(df=draw(st.sampled_from([3, 30])), size=(n, d)) * scale
    names = [f"f{i}" for i in range(n_frames)]
    layout = make_layout(names, d, structure=structure, include_noise=draw(st.booleans()))
    return build_moment_statistics(residuals, jac, layout)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(instances())
def test_every_returned_covariance_is_symmetric_psd(stats):
    layout = stats.layout
    solvers = [
        solve_clarabel(stats),
        solve_pgd(stats, replace(PGD_STABLE, max_iterations=3000)),
        solve_pgd(stats, PGD_PUBLISHED),
    ]
    if layout.structure == "diag":
        solvers.append(solve_nnls(stats))
    for solution in solvers:
        if solution.status == "error":
            continue
        assert np.all(np.isfinite(solution.theta)), solution
        assert_psd(solution, layout)
        assert solution.objective == pytest.approx(
            moment_objective(solution.theta, stats), rel=1e-9, abs=1e-300
        )


@pytest.mark.parametrize("n", [119, 200, 1000])
def test_published_pgd_terminates_and_does_not_claim_success(n):
    """Table I: α = 0.0025 exceeds 2/λmax(G) from N≈119 on; the literal stopping test fires at
    the first decrease. Either way the result must not be reported as optimal."""
    stats = jaco_statistics(n, seed=7)
    assert PGD_PUBLISHED.step > published_step_limit(stats)
    published = solve_pgd(stats, PGD_PUBLISHED)
    assert published.status in ("stopped_early", "diverged", "iteration_limit")
    assert not published.converged
    assert published.iterations <= PGD_PUBLISHED.max_iterations
    reference = solve_nnls(stats)
    assert published.objective > reference.objective * (1 + 1e-3)
    # The published step with a correct stopping rule cannot converge either.
    corrected_stop = solve_pgd(
        stats,
        replace(PGD_PUBLISHED, stopping="projected_gradient", tolerance=1e-9, max_iterations=2000),
    )
    assert corrected_stop.status in ("diverged", "iteration_limit")


def test_published_pgd_with_a_stable_step_still_stops_after_one_decrease():
    stats = jaco_statistics(40, seed=8)
    assert PGD_PUBLISHED.step < published_step_limit(stats)
    published = solve_pgd(stats, PGD_PUBLISHED)
    assert published.iterations == 1
    assert published.status == "stopped_early"
    assert "Table I" in published.message


def test_limits_are_reported_as_such():
    """A first-order run cut short is not a solution; Clarabel cut short is finished by
    projected gradient, and its answer says so (optimal only by its KKT certificate)."""
    stats = jaco_statistics(300, seed=9)
    assert solve_pgd(stats, replace(PGD_STABLE, max_iterations=5)).status == "iteration_limit"
    cut = solve_clarabel(stats, max_iterations=2)
    assert "user_limit" in cut.message and "projected-gradient steps" in cut.message
    assert cut.status == "optimal" and cut.kkt_residual <= KKT_TOLERANCE
    reference = solve_nnls(stats)
    assert cut.moment_objective == pytest.approx(reference.moment_objective, rel=1e-6)


def test_an_inaccurate_or_failed_interior_point_is_never_taken_as_it_is():
    """Clarabel's "AlmostSolved" (cvxpy optimal_inaccurate) and a failure (no answer) both
    end certified by the KKT residual or marked otherwise, and the message says which
    (issue 30: on an AVX2-only CPU the scoring QP of a full-Σ REML failed and REML carried
    a KKT residual of 0.46)."""
    import cvxpy as cp

    stats = jaco_statistics(200, seed=3, structure="full")
    reference = solve_clarabel(stats)
    original = cp.Problem.solve

    def fail(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        raise cp.error.SolverError("Solver 'CLARABEL' failed.")

    try:
        cp.Problem.solve = fail  # type: ignore[method-assign]
        failed = solve_clarabel(stats, start=reference.theta * 0.5)
    finally:
        cp.Problem.solve = original  # type: ignore[method-assign]
    assert "Clarabel failed" in failed.message and "given start" in failed.message
    assert failed.status == "optimal" and failed.kkt_residual <= KKT_TOLERANCE
    assert failed.moment_objective == pytest.approx(reference.moment_objective, rel=1e-6)


def test_cvxpy_statuses_are_mapped_explicitly():
    assert _CVXPY_STATUS["optimal_inaccurate"] == "optimal_inaccurate"
    assert _CVXPY_STATUS["user_limit"] == "iteration_limit"
    assert _CVXPY_STATUS["unbounded"] == "diverged"
    assert _CVXPY_STATUS["solver_error"] == "error"
    stats = jaco_statistics(300, seed=9)
    solution = solve_clarabel(stats)
    assert replace(solution, status="optimal_inaccurate").converged is False


def test_nnls_refuses_full_covariances_and_unknown_solvers_are_refused():
    stats = jaco_statistics(50, seed=1, structure="full")
    with pytest.raises(SolverError, match="diagonal"):
        solve_nnls(stats)
    with pytest.raises(SolverError, match="unknown solver"):
        solve_moment(stats, "sgd")  # type: ignore[arg-type]
