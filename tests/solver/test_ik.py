"""IK candidates for a target pose: they reach it on the calibrated chain (compliance included),
respect the joint limits, are distinct, and the search is deterministic."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from solver import lie
from solver.errors import SolverError
from solver.ik import IKCandidate, IKOptions, continuous_joints, ik_candidates, joint_distance
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import KinematicChain, gravity_loads, sample_configurations
from tests.conftest import chain


def _calibrated(c: KinematicChain) -> ChainParameters:
    """Perturbed geometry, a camera-like measurement frame, a marker offset, compliance."""
    rng = np.random.default_rng(0)
    links = c.nominal_links @ lie.se3_exp(
        rng.normal(scale=[1e-3] * 3 + [2e-3] * 3, size=(c.n_links, 6))
    )
    links[0] = lie.se3_exp(np.array([0.4, -0.3, 1.1, 0.3, -0.5, 1.2])) @ links[0]
    links[-1] = links[-1] @ lie.se3_exp(np.array([0.03, -0.02, 0.05, 0.3, -0.2, 0.5]))
    return ChainParameters(links, rng.uniform(2e-4, 1e-3, len(c.compliance_axes)))


@functools.cache
def _case(name: str) -> tuple[KinematicChain, ChainParameters, np.ndarray, np.ndarray]:
    c = chain(name, virtual_first=True)
    params = _calibrated(c)
    q = sample_configurations(c, 1, np.random.default_rng(1), range_fraction=0.7)
    target = forward_kinematics(c, params, q, gravity_loads(c, q, payload_kg=0.4))[0]
    return c, params, q[0], target


@functools.cache
def _solve(name: str, free: bool) -> tuple[IKCandidate, ...]:
    c, params, _, target = _case(name)
    options = IKOptions(n_candidates=8, seed=3, free_axis=(0.0, 0.0, 1.0) if free else None)
    return tuple(ik_candidates(c, params, target, options, payload_kg=0.4))


def _reached(c: KinematicChain, params: ChainParameters, candidate: IKCandidate) -> np.ndarray:
    q = candidate.joint_positions[None]
    return forward_kinematics(c, params, q, gravity_loads(c, q, payload_kg=0.4))[0]


@pytest.mark.parametrize("name", ["kinova", "panda", "ur10"])
@pytest.mark.parametrize("free", [False, True], ids=["exact pose", "free yaw"])
def test_candidates_reach_the_target_within_limits_and_are_distinct(name: str, free: bool) -> None:
    c, params, _, target = _case(name)
    candidates = _solve(name, free)
    assert len(candidates) >= (4 if name != "kinova" or free else 2)
    for candidate in candidates:
        reached = _reached(c, params, candidate)
        goal = candidate.target_pose
        # Independent check with Pinocchio's gravity and the plain FK, not the IK's own numbers.
        assert np.linalg.norm(reached[:3, 3] - goal[:3, 3]) < 1e-6
        assert lie.rotation_angle_rad(reached[:3, :3].T @ goal[:3, :3]) < 1e-6
        assert candidate.translation_error_m < 1e-9 and candidate.rotation_error_rad < 1e-9
        q = candidate.joint_positions
        assert np.all(q >= c.lower_limits - 1e-9) and np.all(q <= c.upper_limits + 1e-9)
        rotation = lie.se3_exp(np.r_[0.0, 0.0, 0.0, 0.0, 0.0, candidate.free_rotation_rad])
        assert np.allclose(goal, target @ rotation, atol=1e-12)
        if not free:
            assert candidate.free_rotation_rad == 0.0
    q_all = np.array([cd.joint_positions for cd in candidates])
    for i in range(len(q_all)):
        others = np.delete(q_all, i, axis=0)
        assert joint_distance(c, others, q_all[i]).min() >= 1e-3
    if free:
        assert len({cd.free_rotation_rad for cd in candidates}) > 1


def test_the_configuration_that_produced_the_target_is_among_the_candidates() -> None:
    c, _, q_true, _ = _case("kinova")
    q_all = np.array([cd.joint_positions for cd in _solve("kinova", False)])
    assert joint_distance(c, q_all, q_true).min() < 1e-8


def test_redundant_arm_samples_the_null_space() -> None:
    candidates = _solve("panda", False)
    sources = [cd.source for cd in candidates]
    assert "null_space" in sources and "restart" in sources


def test_search_is_deterministic_for_a_seed() -> None:
    c, params, _, target = _case("ur10")
    options = IKOptions(n_candidates=4, seed=11, n_restarts=12)
    first = ik_candidates(c, params, target, options, payload_kg=0.4)
    second = ik_candidates(c, params, target, options, payload_kg=0.4)
    assert [x.joint_positions.tolist() for x in first] == [
        x.joint_positions.tolist() for x in second
    ]


def test_joint_distance_wraps_continuous_joints_only() -> None:
    c = chain("kinova")
    continuous = continuous_joints(c)
    assert continuous.any() and not continuous.all()
    a = np.zeros(c.n_joints)
    b = np.where(continuous, 2.0 * np.pi - 1e-4, 0.0)
    assert joint_distance(c, a, b) == pytest.approx(1e-4, abs=1e-9)
    bounded = int(np.flatnonzero(~continuous)[0])
    b = np.zeros(c.n_joints)
    b[bounded] = 2.0 * np.pi
    assert joint_distance(c, a, b) == pytest.approx(2.0 * np.pi)


def test_unreachable_target_gives_no_candidates_and_bad_input_is_an_error() -> None:
    c, params, _, target = _case("ur10")
    far = target.copy()
    far[:3, 3] += 10.0
    assert ik_candidates(c, params, far, IKOptions(n_candidates=2, n_restarts=4)) == []
    with pytest.raises(SolverError, match="4x4"):
        ik_candidates(c, params, target[:3], IKOptions())
    with pytest.raises(SolverError, match="n_candidates"):
        ik_candidates(c, params, target, IKOptions(n_candidates=0))
