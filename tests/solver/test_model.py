"""The chain of Eq. (7) against Pinocchio: FK, gravity torques, structure and model errors."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from solver.errors import ModelError
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import build_chain, gravity_loads, pin_configuration, sample_configurations
from tests.conftest import chain, robot


def _pinocchio_pose(name: str, q: np.ndarray) -> np.ndarray:
    c = chain(name)
    model, data = c.pin_model, c.pin_model.createData()
    base, tip = model.getFrameId(c.base_frame), model.getFrameId(c.tip_frame)
    out = []
    for q_pin in pin_configuration(c, q):
        pin.framesForwardKinematics(model, data, q_pin)
        out.append((data.oMf[base].inverse() * data.oMf[tip]).homogeneous)
    return np.array(out)


def test_fk_equals_pinocchio(builtin_name: str) -> None:
    c = chain(builtin_name)
    q = sample_configurations(c, 300, np.random.default_rng(7))
    ours = forward_kinematics(
        c, ChainParameters.nominal(c), q, np.zeros((300, len(c.compliance_axes)))
    )
    assert np.abs(ours - _pinocchio_pose(builtin_name, q)).max() < 1e-9


def test_gravity_torques_equal_pinocchio(builtin_name: str) -> None:
    """τ = -computeGeneralizedGravity on the joint axes (DESIGN.md §2 sign)."""
    c = chain(builtin_name)
    q = sample_configurations(c, 50, np.random.default_rng(8))
    loads = gravity_loads(c, q)
    model, data = c.pin_model, c.pin_model.createData()
    velocity_index = [model.joints[j].idx_v for j in c.pin_joint_ids]
    for n, q_pin in enumerate(pin_configuration(c, q)):
        expected = -pin.computeGeneralizedGravity(model, data, q_pin)[velocity_index]
        assert np.allclose(loads[n], expected, atol=1e-10)


def test_payload_load_is_linear_and_matches_added_mass() -> None:
    """1.5 kg at 5 cm along the tip z axis equals Pinocchio with that mass appended."""
    description = robot("panda")
    com = (0.0, 0.0, 0.05)
    c = build_chain(
        description.urdf_xml, description.base_frame, description.tip_frame, payload_com_m=com
    )
    q = sample_configurations(c, 20, np.random.default_rng(9))
    ours = gravity_loads(c, q, payload_kg=1.5)
    model = c.pin_model.copy()
    tip = model.frames[model.getFrameId(c.tip_frame)]
    model.appendBodyToJoint(
        tip.parentJoint,
        pin.Inertia(1.5, tip.placement.act(np.array(com)), np.zeros((3, 3))),
        pin.SE3.Identity(),
    )
    data = model.createData()
    for n, q_pin in enumerate(pin_configuration(c, q)):
        assert np.allclose(ours[n], -pin.computeGeneralizedGravity(model, data, q_pin), atol=1e-10)


def test_gravity_direction_is_an_input() -> None:
    """Gravity along the base x axis changes the load of the vertical first joint."""
    c = chain("ur10")
    q = sample_configurations(c, 10, np.random.default_rng(1))
    assert np.allclose(gravity_loads(c, q)[:, 0], 0.0, atol=1e-12)
    tilted = gravity_loads(c, q, gravity_base=np.array([9.81, 0.0, 0.0]))
    assert np.abs(tilted[:, 0]).max() > 1.0


def test_virtual_axes_are_orthogonal_to_the_joint_axis() -> None:
    c = chain("kinova", virtual_first=True)
    axes = [a for a in c.compliance_axes if not a.is_joint_axis]
    joint_axis = c.joint_screws[0, 3:]
    assert [a.name for a in axes] == [f"{c.joint_names[0]}.flex_a", f"{c.joint_names[0]}.flex_b"]
    for a in axes:
        assert abs(a.axis @ joint_axis) < 1e-12 and np.isclose(np.linalg.norm(a.axis), 1.0)
    assert np.isclose(np.linalg.det(np.column_stack([axes[0].axis, axes[1].axis, joint_axis])), 1.0)


def test_virtual_axis_load_is_the_transmitted_gravity_moment() -> None:
    """Check τ about a virtual axis by finite differences of potential energy.

    Rotating the whole subtree after L_1 by a small angle about the axis changes the potential
    energy by -τ·angle; Pinocchio's potential energy is the reference.
    """
    c = chain("kinova", virtual_first=True)
    q = sample_configurations(c, 5, np.random.default_rng(3))
    loads = gravity_loads(c, q)
    model = c.pin_model.copy()
    data = model.createData()
    first = c.pin_joint_ids[0]
    for a, axis in enumerate(c.compliance_axes[:2]):
        for n, q_pin in enumerate(pin_configuration(c, q)):
            energy = []
            for angle in (-1e-6, 1e-6):
                tilted = model.copy()
                tilted.jointPlacements[first] = c.pin_model.jointPlacements[first] * pin.exp6(
                    np.r_[0, 0, 0, axis.axis * angle]
                )
                energy.append(pin.computePotentialEnergy(tilted, tilted.createData(), q_pin))
            assert np.isclose(-(energy[1] - energy[0]) / 2e-6, loads[n, a], atol=1e-5)
    del data


def test_chain_structure(builtin_name: str) -> None:
    c = chain(builtin_name)
    assert c.nominal_links.shape == (c.n_joints + 1, 4, 4)
    assert len(c.joint_names) == {"kinova": 6, "panda": 7, "ur10": 6}[builtin_name]
    assert np.all(c.is_revolute())
    assert np.all(c.lower_limits < c.upper_limits)


@pytest.mark.parametrize(
    ("base", "tip", "message"),
    [
        ("nope", "panda_link8", "base frame 'nope' is not in the URDF"),
        ("panda_link0", "nope", "tip frame 'nope' is not in the URDF"),
        ("panda_link8", "panda_link0", "is not downstream of base frame"),
        ("panda_leftfinger", "panda_link8", "is not downstream of base frame"),
    ],
)
def test_bad_frames_are_model_errors(base: str, tip: str, message: str) -> None:
    with pytest.raises(ModelError, match=message):
        build_chain(robot("panda").urdf_xml, base, tip)


def test_unparsable_urdf_is_a_model_error() -> None:
    with pytest.raises(ModelError, match="URDF could not be parsed"):
        build_chain("<robot name='x'><link name='a'/><joint", "a", "b")


def test_compliant_joint_must_be_on_chain() -> None:
    description = robot("panda")
    with pytest.raises(ModelError, match="not on the chain"):
        build_chain(
            description.urdf_xml,
            "panda_link0",
            "panda_link8",
            compliant_joints=["panda_finger_joint1"],
        )
