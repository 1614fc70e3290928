"""SE(3) maps against Pinocchio, and their group properties, over random and near-identity input."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from solver import lie

finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
twists = arrays(np.float64, (6,), elements=finite)
# Rotation magnitudes from 1e-9 rad to 3 rad, to hit the Taylor branches on purpose.
scales = st.floats(-9.0, 0.5).map(lambda e: 10.0**e)


def _twist(twist: np.ndarray, scale: float) -> np.ndarray:
    out = twist.copy()
    out[3:] *= scale
    return out


@given(twists, scales)
def test_exp_matches_pinocchio(twist: np.ndarray, scale: float) -> None:
    twist = _twist(twist, scale)
    assert np.allclose(lie.se3_exp(twist), pin.exp6(twist).homogeneous, atol=1e-11)


@given(twists, scales)
def test_log_matches_pinocchio_and_inverts_exp(twist: np.ndarray, scale: float) -> None:
    twist = _twist(twist, scale)
    if np.linalg.norm(twist[3:]) >= np.pi - 1e-3:
        return  # log's branch cut: both are right, possibly on different sides
    transform = lie.se3_exp(twist)
    assert np.allclose(lie.se3_log(transform), pin.log6(pin.SE3(transform)).vector, atol=1e-9)
    assert np.allclose(lie.se3_log(transform), twist, atol=1e-9)


@given(twists, twists)
def test_adjoint_is_pinocchio_action_and_maps_twists(a: np.ndarray, b: np.ndarray) -> None:
    """Ad_X Exp(b) Ad_X^-1 identity: X Exp(b) X^-1 = Exp(Ad_X b)."""
    x = lie.se3_exp(a)
    assert np.allclose(lie.adjoint(x), pin.SE3(x).action, atol=1e-12)
    assert np.allclose(lie.adjoint_inverse(x), np.linalg.inv(lie.adjoint(x)), atol=1e-9)
    conjugated = x @ lie.se3_exp(b) @ lie.inverse(x)
    assert np.allclose(conjugated, lie.se3_exp(lie.adjoint(x) @ b), atol=1e-9)


@given(arrays(np.float64, (5, 6), elements=finite))
def test_batched_equals_one_by_one(batch: np.ndarray) -> None:
    together = lie.se3_exp(batch)
    for i, twist in enumerate(batch):
        assert np.array_equal(together[i], lie.se3_exp(twist[None])[0])


@given(arrays(np.float64, (4,), elements=finite).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_quaternion_order_is_xyzw(quaternion: np.ndarray) -> None:
    """Scalar-last round trip, checked against Pinocchio's Eigen (w-first constructor)."""
    quaternion = quaternion / np.linalg.norm(quaternion)
    matrix = lie.pose_matrix(np.zeros(3), quaternion)[:3, :3]
    x, y, z, w = quaternion
    assert np.allclose(matrix, pin.Quaternion(w, x, y, z).toRotationMatrix(), atol=1e-12)
    back = lie.matrix_to_quaternion_xyzw(matrix)
    assert back[3] >= 0.0  # canonical sign: q and -q are the same rotation
    assert np.allclose(back, quaternion, atol=1e-12) or np.allclose(back, -quaternion, atol=1e-12)


def test_known_rotation_about_z() -> None:
    """A quarter turn about z is (0, 0, sin 45°, cos 45°) — fails if w-first slips in."""
    matrix = lie.pose_matrix(np.zeros(3), np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]))
    assert np.allclose(matrix[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


@given(
    angle=st.floats(0.0, np.pi),
    axis=arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)).filter(
        lambda a: np.linalg.norm(a) > 0.1
    ),
)
def test_the_rotation_angle_is_exact_at_every_angle(angle: float, axis: np.ndarray) -> None:
    """The geodesic angle of exp(θ a) is θ to rounding, also near 0 (arccos of the trace
    alone is off by up to ~1e-8 rad there) and near π."""
    rotation = lie.so3_exp(angle * axis / np.linalg.norm(axis))
    assert abs(float(lie.rotation_angle_rad(rotation)) - angle) < 1e-12


residual_twists = arrays(np.float64, (6,), elements=st.floats(-0.15, 0.15))


@given(twists, twists)
def test_ad_is_pinocchios_motion_cross_product(a: np.ndarray, b: np.ndarray) -> None:
    expected = pin.Motion(a).cross(pin.Motion(b)).vector
    assert np.allclose(lie.se3_ad(a) @ b, expected, atol=1e-12)


@given(residual_twists)
def test_left_jacobian_inverse_is_pinocchios_jlog6_of_the_inverse(twist: np.ndarray) -> None:
    """J_l⁻¹(ξ) = Jr⁻¹(−ξ) = Jlog6(Exp(−ξ)), to the series' stated bound (‖ad‖ ≤ 0.6 here:
    (0.6)⁸ / 1 209 600 = 1.4e-8)."""
    exact = pin.Jlog6(pin.exp6(-twist))
    assert np.allclose(lie.se3_left_jacobian_inverse(twist), exact, rtol=0.0, atol=2e-8)


@given(residual_twists, twists)
def test_left_jacobian_inverse_is_the_derivative_of_log_after_a_left_step(
    residual: np.ndarray, direction: np.ndarray
) -> None:
    """``Log(Exp(−h t) Exp(ξ)) = ξ − h J_l⁻¹(ξ) t + O(h²)``: central differences."""
    h = 1e-6
    x = lie.se3_exp(residual)
    plus = lie.se3_log(lie.se3_exp(-h * direction) @ x)
    minus = lie.se3_log(lie.se3_exp(h * direction) @ x)
    numeric = (minus - plus) / (2.0 * h)
    scale = max(1.0, float(np.abs(direction).max()))
    assert np.allclose(
        lie.se3_left_jacobian_inverse(residual) @ direction, numeric, atol=1e-7 * scale
    )
