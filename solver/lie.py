"""SE(3) and SO(3) maps, batched over a leading axis.

Conventions (DESIGN.md §2): twists are 6-vectors ``[v; w]`` (translation first, metres and
radians), identical to Pinocchio's ``Motion.vector``; homogeneous transforms are ``(..., 4, 4)``
arrays; quaternions cross every boundary in ``(qx, qy, qz, qw)`` order (scalar last).

Every function accepts any number of leading batch dimensions. Pinocchio's ``exp6``/``log6``
are the reference the tests compare against; these versions exist because calibration applies
them to 10^3..10^6 samples at once.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

# Below this rotation angle the closed forms lose digits to cancellation; the Taylor series
# (three terms, truncation error < 1e-16) are exact to double precision there.
_SMALL_ANGLE_RAD = 1e-2


def skew(vector: FloatArray) -> FloatArray:
    """``[v]x`` such that ``skew(a) @ b == cross(a, b)``; shape (..., 3) -> (..., 3, 3)."""
    out = np.zeros((*vector.shape, 3))
    out[..., 0, 1], out[..., 0, 2] = -vector[..., 2], vector[..., 1]
    out[..., 1, 0], out[..., 1, 2] = vector[..., 2], -vector[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -vector[..., 1], vector[..., 0]
    return out


def so3_exp(rotation_vector_rad: FloatArray) -> FloatArray:
    """Rotation matrix of a rotation vector (axis * angle); (..., 3) -> (..., 3, 3)."""
    flat = rotation_vector_rad.reshape(-1, 3)
    return Rotation.from_rotvec(flat).as_matrix().reshape(*rotation_vector_rad.shape[:-1], 3, 3)


def so3_log(rotation: FloatArray) -> FloatArray:
    """Rotation vector (angle in [0, pi]) of a rotation matrix; (..., 3, 3) -> (..., 3)."""
    flat = rotation.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(*rotation.shape[:-2], 3)


def _left_jacobian_coefficients(angle_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Coefficients a, b of ``V = I + a [w]x + b [w]x^2`` (SO(3) left Jacobian)."""
    small = angle_rad < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, angle_rad)
    t2 = angle_rad**2
    a = np.where(small, 0.5 - t2 / 24.0 + t2**2 / 720.0, (1.0 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2**2 / 5040.0, (safe - np.sin(safe)) / safe**3)
    return a, b


def se3_exp(twist: FloatArray) -> FloatArray:
    """``Exp`` of a twist ``[v; w]``; (..., 6) -> (..., 4, 4). Equals ``pin.exp6``."""
    v, w = twist[..., :3], twist[..., 3:]
    angle_rad = np.linalg.norm(w, axis=-1)
    a, b = _left_jacobian_coefficients(angle_rad)
    w_hat = skew(w)
    w_hat2 = w_hat @ w_hat
    eye = np.broadcast_to(np.eye(3), w_hat.shape)
    left_jacobian = eye + a[..., None, None] * w_hat + b[..., None, None] * w_hat2
    out = np.zeros((*twist.shape[:-1], 4, 4))
    out[..., :3, :3] = so3_exp(w)
    out[..., :3, 3] = np.einsum("...ij,...j->...i", left_jacobian, v)
    out[..., 3, 3] = 1.0
    return out


def se3_log(transform: FloatArray) -> FloatArray:
    """``Log`` of a transform as a twist ``[v; w]``; (..., 4, 4) -> (..., 6). = ``pin.log6``."""
    w = so3_log(transform[..., :3, :3])
    angle_rad = np.linalg.norm(w, axis=-1)
    small = angle_rad < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, angle_rad)
    # V^-1 = I - 1/2 [w]x + c [w]x^2 with c = (1 - (t sin t) / (2 (1 - cos t))) / t^2.
    c = np.where(
        small,
        1.0 / 12.0 + angle_rad**2 / 720.0 + angle_rad**4 / 30240.0,
        (1.0 - safe * np.sin(safe) / (2.0 * (1.0 - np.cos(safe)))) / safe**2,
    )
    w_hat = skew(w)
    eye = np.broadcast_to(np.eye(3), w_hat.shape)
    inverse_left_jacobian = eye - 0.5 * w_hat + c[..., None, None] * (w_hat @ w_hat)
    v = np.einsum("...ij,...j->...i", inverse_left_jacobian, transform[..., :3, 3])
    return np.concatenate([v, w], axis=-1)


def inverse(transform: FloatArray) -> FloatArray:
    """Inverse of rigid transforms; (..., 4, 4) -> (..., 4, 4)."""
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    out = np.zeros_like(transform)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, transform[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def adjoint(transform: FloatArray) -> FloatArray:
    """Paper Eq. (5): ``Ad_X = [[R, [t]x R], [0, R]]``; (..., 4, 4) -> (..., 6, 6).

    Maps a twist expressed in the child frame of X into its parent frame (= ``SE3.action``).
    """
    rotation = transform[..., :3, :3]
    out = np.zeros((*transform.shape[:-2], 6, 6))
    out[..., :3, :3] = rotation
    out[..., 3:, 3:] = rotation
    out[..., :3, 3:] = skew(transform[..., :3, 3]) @ rotation
    return out


def adjoint_inverse(transform: FloatArray) -> FloatArray:
    """``Ad_X^-1 = Ad_{X^-1}`` without forming the inverse first; (..., 4, 4) -> (..., 6, 6)."""
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    out = np.zeros((*transform.shape[:-2], 6, 6))
    out[..., :3, :3] = rotation_t
    out[..., 3:, 3:] = rotation_t
    out[..., :3, 3:] = -rotation_t @ skew(transform[..., :3, 3])
    return out


def pose_matrix(position_m: FloatArray, quaternion_xyzw: FloatArray | None) -> FloatArray:
    """Homogeneous transforms from positions (..., 3) and unit quaternions (..., 4), xyzw order.

    With ``quaternion_xyzw=None`` (position-only data) the rotation is the identity.
    """
    out = np.zeros((*position_m.shape[:-1], 4, 4))
    if quaternion_xyzw is None:
        out[..., :3, :3] = np.eye(3)
    else:
        flat = quaternion_xyzw.reshape(-1, 4)
        out[..., :3, :3] = (
            Rotation.from_quat(flat).as_matrix().reshape(*position_m.shape[:-1], 3, 3)
        )
    out[..., :3, 3] = position_m
    out[..., 3, 3] = 1.0
    return out


def matrix_to_quaternion_xyzw(rotation: FloatArray) -> FloatArray:
    """Unit quaternions ``(qx, qy, qz, qw)`` with ``qw >= 0``; (..., 3, 3) -> (..., 4)."""
    flat = Rotation.from_matrix(rotation.reshape(-1, 3, 3)).as_quat()
    flat = np.where(flat[:, 3:4] < 0.0, -flat, flat)
    return flat.reshape(*rotation.shape[:-2], 4)


def rotation_angle_rad(rotation: FloatArray) -> FloatArray:
    """Geodesic angle of rotation matrices in [0, pi]; (..., 3, 3) -> (...)."""
    trace = np.trace(rotation, axis1=-2, axis2=-1)
    return np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))
