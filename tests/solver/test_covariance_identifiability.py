"""Identifiability: rank, conditioning and null directions in words, and the null-space rule."""

from __future__ import annotations

import numpy as np
import pytest

from solver.covariance import (
    analyse_identifiability,
    build_moment_statistics,
    estimate_covariances,
    make_layout,
    moment_objective,
    resolve_null_space,
    solve_clarabel,
)
from tests.solver import covariance_support as S


def random_case(names, n=200, seed=0, residual_dim=6, constant=()):
    rng = np.random.default_rng(seed)
    jac = S.random_frame_jacobians(n, len(names), rng, residual_dim=residual_dim)
    for f, name in enumerate(names):
        if name in constant:
            jac[:, f] = np.eye(6)[:residual_dim]
    r = rng.normal(size=(n, residual_dim)) * 1e-3
    return r, jac


def test_isotropic_translation_of_any_frames_is_named_as_a_sum():
    names = ["shoulder", "elbow", "wrist"]
    r, jac = random_case(names)
    stats = build_moment_statistics(r, jac, make_layout(names, 6))
    report = analyse_identifiability(stats)
    assert report.null_dimension == 3  # 4 sources with translation, one identifiable sum
    assert report.rank == stats.layout.n_params - 3
    assert np.isfinite(report.condition_number) and report.condition_number > 1
    (statement,) = report.statements
    assert "isotropic translational variance of frames shoulder, elbow, wrist, noise" in statement
    assert "only their sum is identifiable" in statement
    assert any("noise" in w and "shoulder" in w for w in report.warnings)
    translational = np.isin(stats.layout.param_row, (0, 1, 2))
    np.testing.assert_array_equal(report.identifiable, ~translational)


def test_isotropic_translation_is_found_for_rotation_only_frames_too():
    names = ["a", "b"]
    r, jac = random_case(names, seed=1)
    free = {"b": ("w_x", "w_y", "w_z")}
    report = analyse_identifiability(
        build_moment_statistics(r, jac, make_layout(names, 6, free_axes=free))
    )
    (statement,) = report.statements
    assert "isotropic translational variance of frames a, noise" in statement


def test_a_frame_with_a_constant_jacobian_is_confused_with_the_noise():
    names = ["base", "tool"]
    r, jac = random_case(names, seed=2, constant=("tool",))
    stats = build_moment_statistics(r, jac, make_layout(names, 6))
    report = analyse_identifiability(stats, frame_jacobians=jac)
    for axis in ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z"):
        assert any(
            f"var({axis}) of frames tool, noise have the same effect" in s
            for s in report.statements
        ), report.text()
    assert any("tool" in w and "constant Jacobian" in w for w in report.warnings)
    assert any("measurement noise" in w and "tool" in w for w in report.warnings)


def test_rotational_noise_has_no_effect_on_residuals_of_positions():
    names = ["a"]
    r, jac = random_case(names, seed=3, residual_dim=3)
    report = analyse_identifiability(build_moment_statistics(r, jac, make_layout(names, 3)))
    for axis in ("w_x", "w_y", "w_z"):
        assert f"var({axis}) of frame noise has no effect on the residuals" in report.statements


def test_the_rule_keeps_the_fit_zeroes_silent_entries_and_splits_sums_evenly():
    names = ["base", "tool"]
    r, jac = random_case(names, seed=4, residual_dim=3, constant=("tool",))
    jac_pose = S.random_frame_jacobians(200, 1, np.random.default_rng(4))[:, :, :3]
    jac[:, :1] = jac_pose
    stats = build_moment_statistics(r, jac, make_layout(names, 3))
    report = analyse_identifiability(stats)
    raw = solve_clarabel(stats).theta
    raw_objective = moment_objective(raw, stats)
    ruled = resolve_null_space(raw, report, stats.layout)
    assert moment_objective(ruled, stats) == pytest.approx(raw_objective, rel=1e-7)
    covs = stats.layout.frame_covariances(ruled)
    tool, noise = covs[1], covs[2]
    np.testing.assert_allclose(noise[3:, 3:], 0.0, atol=1e-12 * np.abs(covs).max())
    # tool and noise have identical translational columns: the identified sums split evenly
    np.testing.assert_allclose(
        np.diag(tool)[:3], np.diag(noise)[:3], rtol=1e-5, atol=1e-9 * np.abs(covs).max()
    )


def test_jaco_report_names_the_wrist_and_noise_confusions():
    names = S.jaco_joint_names()
    data = S.simulate_jaco(400, seed=11)
    free = {n: ("w_x", "w_y", "w_z") for n in names}
    stats = build_moment_statistics(
        data.residuals, data.frame_jacobians, make_layout(names, 6, free_axes=free)
    )
    report = analyse_identifiability(stats, frame_jacobians=data.frame_jacobians)
    text = report.text()
    assert report.rank == stats.layout.n_params - 3
    assert (
        "var(w_z) of frame j2s6s200_joint_6 and var(w_x) of frame noise have the same effect"
    ) in text
    assert (
        "var(w_z) of frame j2s6s200_joint_4 and var(w_y) of frame j2s6s200_joint_5 have the "
        "same effect"
    ) in text
    assert any("j2s6s200_joint_6" in w for w in report.warnings)
    assert any("j2s6s200_joint_1" in s and "j2s6s200_joint_2" in s for s in report.weak_statements)


def test_estimate_reports_unidentifiable_entries_without_standard_errors():
    names = ["shoulder", "elbow"]
    r, jac = random_case(names, seed=5)
    estimate = estimate_covariances(r, jac, names)
    shoulder = estimate.frame("shoulder")
    assert not shoulder.identifiable[:3].any() and shoulder.identifiable[3:].all()
    assert np.isnan(shoulder.std_se[:3]).all()
    assert estimate.warnings  # noise confusion is reported, not hidden


@pytest.mark.parametrize("structure", ["diag", "full"])
def test_entries_without_effect_on_positions_come_out_exactly_zero(structure):
    names = S.jaco_joint_names()
    data = S.simulate_jaco(150, seed=12, residual_dim=3)
    free = {n: ("w_x", "w_y", "w_z") for n in names}
    estimate = estimate_covariances(
        data.residuals,
        data.frame_jacobians,
        names,
        structure=structure,
        free_axes=free,
        standard_errors=False,
    )
    silent = estimate.identifiability.silent
    labels = np.array(estimate.layout.labels())
    assert "noise:var(w_x)" in labels[silent]
    assert "j2s6s200_joint_6:var(w_z)" in labels[silent]  # its axis passes through the EE origin
    np.testing.assert_array_equal(estimate.theta[silent], 0.0)
    assert np.all(np.isfinite(estimate.theta))
    assert estimate.moment_solution.status == "optimal"
