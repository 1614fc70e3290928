"""Jacobians of Eq. (9) in the end-effector frame against finite differences of the FK."""

from __future__ import annotations

import numpy as np
import pytest

from solver import lie
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    parameter_names,
    pose_residual_map,
    pose_residuals,
    position_residuals,
    stacked_jacobian,
)
from solver.model import gravity_loads, sample_configurations
from tests.conftest import chain

STEP = 1e-7


def _perturbed_case(name: str, seed: int = 0):  # type: ignore[no-untyped-def]
    c = chain(name, virtual_first=True)
    rng = np.random.default_rng(seed)
    q = sample_configurations(c, 6, rng)
    loads = gravity_loads(c, q, payload_kg=0.7)
    params = ChainParameters(
        c.nominal_links @ lie.se3_exp(rng.normal(scale=0.01, size=(c.n_links, 6))),
        rng.uniform(0.0, 1e-3, len(c.compliance_axes)),
    )
    return c, q, loads, params


def _local_difference(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    return lie.se3_log(lie.inverse(before) @ after) / STEP


@pytest.mark.parametrize("name", ["kinova", "panda", "ur10"])
def test_parameter_columns_equal_finite_differences(name: str) -> None:
    c, q, loads, params = _perturbed_case(name)
    evaluation = evaluate_chain(c, params, q, loads)
    jacobian = stacked_jacobian(evaluation)
    n_link_columns = 6 * c.n_links
    assert jacobian.shape[2] == len(parameter_names(c))
    for column in range(jacobian.shape[2]):
        if column < n_link_columns:
            twists = np.zeros((c.n_links, 6))
            twists[column // 6, column % 6] = STEP
            moved = params.with_link_corrections(twists)
        else:
            compliance = params.compliance_rad_per_nm.copy()
            compliance[column - n_link_columns] += STEP
            moved = ChainParameters(params.links, compliance)
        numeric = _local_difference(evaluation.pose, forward_kinematics(c, moved, q, loads))
        scale = max(1.0, np.abs(jacobian[:, :, column]).max())
        assert np.abs(numeric - jacobian[:, :, column]).max() < 1e-5 * scale, parameter_names(c)[
            column
        ]


def test_perturbation_jacobian_is_the_link_jacobian() -> None:
    """ξ_i right after L_i moves the EE like a link correction of L_i (DESIGN.md §2)."""
    c, q, loads, params = _perturbed_case("kinova", seed=1)
    evaluation = evaluate_chain(c, params, q, loads)
    for i in range(c.n_joints):
        for m in range(6):
            xi = np.zeros((q.shape[0], c.n_joints, 6))
            xi[:, i, m] = STEP
            moved = forward_kinematics(c, params, q, loads, perturbations=xi)
            numeric = _local_difference(evaluation.pose, moved)
            assert np.abs(numeric - evaluation.link_jacobians[:, i, :, m]).max() < 1e-5


def test_residual_is_end_effector_frame() -> None:
    """r = Log(X_model^-1 X_meas): a measured pose X·Exp(δ) gives back δ exactly."""
    c, q, loads, params = _perturbed_case("panda", seed=2)
    model = forward_kinematics(c, params, q, loads)
    delta = np.random.default_rng(5).normal(scale=1e-3, size=(q.shape[0], 6))
    measured = model @ lie.se3_exp(delta)
    assert np.allclose(pose_residuals(model, measured), delta, atol=1e-12)
    position_residual = position_residuals(model, measured)
    expected = np.einsum("nji,nj->ni", model[:, :3, :3], measured[:, :3, 3] - model[:, :3, 3])
    assert np.allclose(position_residual, expected)


def test_rigid_mean_pose_ignores_loads_when_compliance_is_zero() -> None:
    c, q, loads, params = _perturbed_case("ur10", seed=3)
    rigid = ChainParameters(params.links, np.zeros_like(params.compliance_rad_per_nm))
    assert np.allclose(
        forward_kinematics(c, rigid, q, loads), forward_kinematics(c, rigid, q, 0 * loads)
    )
    assert not np.allclose(
        forward_kinematics(c, params, q, loads), forward_kinematics(c, rigid, q, loads)
    )


def test_the_pose_residual_map_is_the_residuals_jacobian_in_a_tip_twist() -> None:
    """``r(X·Exp(h t)) = r − h M t + O(h²)`` (central differences) for model poses 20 mm and
    20 mrad from the measured ones, where Eq. 9's ``M = I`` is off by ~1 %."""
    rng = np.random.default_rng(3)
    model = lie.se3_exp(rng.normal(size=(40, 6)) * 0.5)
    measured = model @ lie.se3_exp(rng.normal(size=(40, 6)) * 0.02)
    residual = pose_residuals(model, measured)
    jacobian = pose_residual_map(residual)
    assert jacobian.shape == (40, 6, 6)
    h, eq9_miss = 1e-6, 0.0
    for direction in np.eye(6):
        plus = pose_residuals(model @ lie.se3_exp(h * direction), measured)
        minus = pose_residuals(model @ lie.se3_exp(-h * direction), measured)
        numeric = (minus - plus) / (2.0 * h)
        np.testing.assert_allclose(jacobian @ direction, numeric, atol=1e-8)
        eq9_miss = max(eq9_miss, float(np.abs(direction - numeric).max()))
    assert eq9_miss > 1e-3
