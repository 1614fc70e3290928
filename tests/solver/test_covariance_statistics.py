"""Sufficient statistics of Eq. (13–14): the paper's explicit vec design, additive, fast."""

from __future__ import annotations

import numpy as np
import pytest

from solver.covariance import (
    build_moment_statistics,
    column_matrix,
    design_matrix,
    empty_statistics,
    make_layout,
    moment_objective,
    moment_residual_norm,
)
from solver.errors import SolverError
from tests.solver import covariance_support as S


def paper_design(frame_jacobians, layout):
    """B_n of Eq. (13) built literally with vec (column-major) and the unit matrices E_p."""
    cols = column_matrix(frame_jacobians, layout)
    n = cols.shape[0]
    d = layout.residual_dim
    design = np.zeros((n, d * d, layout.n_params))
    for p, (f, i, j) in enumerate(
        zip(layout.param_frame, layout.param_row, layout.param_col, strict=True)
    ):
        e = np.zeros((6 * layout.n_frames,) * 2)
        e[6 * f + i, 6 * f + j] = e[6 * f + j, 6 * f + i] = 1.0
        design[:, :, p] = (cols @ e @ cols.transpose(0, 2, 1)).transpose(0, 2, 1).reshape(n, -1)
    return design


@pytest.mark.parametrize("structure", ["diag", "full"])
@pytest.mark.parametrize("residual_dim", [6, 3])
@pytest.mark.parametrize("known", [False, True])
def test_statistics_equal_the_papers_vec_design(structure, residual_dim, known):
    rng = np.random.default_rng(1)
    jac = S.random_frame_jacobians(40, 2, rng, residual_dim=residual_dim)
    r = rng.normal(size=(40, residual_dim)) * 1e-3
    free = {"b": ("v_x", "w_y", "w_z")}
    known_cov = np.diag(rng.uniform(1, 2, residual_dim)) * 1e-7 if known else None
    layout = make_layout(
        ["a", "b"], residual_dim, structure=structure, free_axes=free, include_noise=not known
    )
    stats = build_moment_statistics(r, jac, layout, known_covariance=known_cov, chunk_size=7)
    design = paper_design(jac, layout)
    offset = 0.0 if known_cov is None else known_cov
    z = (r[:, :, None] * r[:, None, :] - offset).transpose(0, 2, 1).reshape(40, -1)
    gram = np.einsum("nkp,nkq->pq", design, design)
    cross = np.einsum("nkp,nk->p", design, z)
    np.testing.assert_allclose(stats.gram, gram, rtol=1e-12, atol=1e-14 * np.abs(gram).max())
    np.testing.assert_allclose(stats.cross, cross, rtol=1e-10, atol=1e-14 * np.abs(cross).max())
    assert stats.const == pytest.approx(float(np.sum(z**2)), rel=1e-12)
    per_sample = design_matrix(column_matrix(jac, layout), layout)  # vech_w rows of B_n
    np.testing.assert_allclose(
        np.einsum("nkp,nkq->pq", per_sample, per_sample),
        gram,
        rtol=1e-12,
        atol=1e-14 * np.abs(gram).max(),
    )
    theta = rng.uniform(0, 1e-6, layout.n_params)
    explicit = float(np.sum((z - np.einsum("nkp,p->nk", design, theta)) ** 2))
    assert moment_objective(theta, stats) == pytest.approx(explicit, rel=1e-9)
    assert moment_residual_norm(theta, stats) == pytest.approx(np.sqrt(explicit), rel=1e-9)


@pytest.mark.parametrize("structure", ["diag", "full"])
def test_statistics_of_two_halves_merge_to_the_whole(structure):
    rng = np.random.default_rng(2)
    jac = S.jaco_frame_jacobians(300, seed=3)
    r = S.sample_residuals(jac, S.true_frame_covariances(), np.diag(S.NOISE_STD**2), rng)
    layout = make_layout(S.jaco_joint_names(), 6, structure=structure)
    whole = build_moment_statistics(r, jac, layout, chunk_size=64)
    first = build_moment_statistics(r[:137], jac[:137], layout, chunk_size=1000)
    second = build_moment_statistics(r[137:], jac[137:], layout, chunk_size=5)
    merged = empty_statistics(layout) + first + second
    assert merged.n_samples == whole.n_samples == 300
    for got, want in ((merged.gram, whole.gram), (merged.cross, whole.cross)):
        assert np.abs(got - want).max() <= 1e-10 * np.abs(want).max()
    assert merged.const == pytest.approx(whole.const, rel=1e-10)


def test_merging_statistics_of_different_layouts_is_refused():
    rng = np.random.default_rng(0)
    jac = S.random_frame_jacobians(5, 1, rng)
    r = rng.normal(size=(5, 6))
    a = build_moment_statistics(r, jac, make_layout(["a"], 6))
    b = build_moment_statistics(r, jac, make_layout(["a"], 6, structure="full"))
    with pytest.raises(SolverError):
        a + b
