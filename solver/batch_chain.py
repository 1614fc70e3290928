"""Forward kinematics, Jacobians and residuals of Eq. (7)–(9) for one chunk, batch-LAST.

The same quantities as :func:`solver.kinematics.evaluate_chain`, :func:`~solver.kinematics.
stacked_jacobian` and :func:`~solver.kinematics.pose_residuals` (tested equal to rounding), laid
out for streaming many chunks through the normal equations: every per-sample array has the
sample index LAST, so each numpy call runs over contiguous rows and no 4×4 or 6×6 matrix is
formed per sample (the technique of :mod:`solver.gravity` and :mod:`solver.ranking`).

Frames (DESIGN.md §2): the chain suffix ``B_i = Exp(s_i q_i) … L_{k+1}`` is carried as
``[R | t]`` with shape (3, 4, n), ``R[r, c] = suffix[r, c]``; the pose ``X_0E`` maps the
end-effector frame into the measurement frame; Jacobian columns map local twists ``[v; w]``
(m, rad) of each link ``L_i`` (and compliance in rad/N·m) to the end-effector-frame residual
``r = Log(X_model⁻¹ X_measured)``.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.kinematics import ChainParameters
from solver.model import KinematicChain

FloatArray = NDArray[np.float64]

_SERIES_ANGLE_RAD = 1e-2
"""Below this rotation angle the log map uses Taylor series (truncation < 1e-16 relative)."""
_FALLBACK_COS = -0.5
"""Residual rotations beyond 120° (cos < -0.5) use scipy's log, exact up to π."""


@dataclass(frozen=True)
class ChainSweep:
    """Result of :func:`sweep_chain` for n samples.

    ``rotation`` (3, 3, n) and ``translation`` (3, n): the pose ``X_0E`` (Eq. 7).
    ``columns`` (P, d, n) or None: column p of the stacked Jacobian (order of
    :func:`solver.kinematics.parameter_names`, unweighted), residual component d, sample n.
    For p < 6k these are also the frame Jacobians ``A_f = Ad_{B_f}⁻¹`` of the perturbations.
    """

    rotation: FloatArray
    translation: FloatArray
    columns: FloatArray | None


def joint_motions(chain: KinematicChain, joint_positions: FloatArray) -> list[lie.ScrewMotion]:
    """``Exp(s_i q_i)`` of every chain joint (batch-last), shared with the gravity loads."""
    q = np.asarray(joint_positions, dtype=float)
    return [
        lie.ScrewMotion.of(chain.joint_screws[i], np.ascontiguousarray(q[:, i]))
        for i in range(chain.n_joints)
    ]


def sweep_chain(
    chain: KinematicChain,
    params: ChainParameters,
    motions: list[lie.ScrewMotion],
    loads_nm: FloatArray,
    *,
    residual_dim: int,
    with_columns: bool,
    column_links: Collection[int] | None = None,
    compliance_columns: bool = True,
) -> ChainSweep:
    """Eq. (7) and the Eq. (9) Jacobian in one backward sweep over the chain.

    ``motions``: :func:`joint_motions` of the read joint positions (N, k); ``loads_nm``
    (N, n_axes): gravity torque about each compliance axis (Eq. 6), so the joints sit at
    ``q + c τ``. ``residual_dim`` 6 (pose) or 3 (position-only: the first three rows).
    ``column_links`` (link indices, None = all) and ``compliance_columns`` say which columns
    to fill; the others stay zero (a fit of the measurement frame and tool needs two links).
    """
    n = loads_nm.shape[0]
    k = chain.n_joints
    axes = chain.compliance_axes
    n_cols = 6 * (k + 1) + len(axes)
    deflection = np.ascontiguousarray((loads_nm * params.compliance_rad_per_nm).T)
    columns = np.zeros((n_cols, residual_dim, n)) if with_columns else None
    suffix = np.empty((3, 4, n))
    suffix[:] = params.links[k][:3, :, None]
    wanted = set(range(k + 1)) if column_links is None else set(column_links)
    comp_columns = columns if compliance_columns else None
    if columns is not None and k in wanted:
        for m in range(residual_dim):  # J_{k+1} = I: the tip link's twist is the residual's
            columns[6 * k + m, m] = 1.0
    for i in range(k - 1, -1, -1):
        motion = motions[i]
        own = [a for a, ax in enumerate(axes) if ax.joint_index == i and ax.is_joint_axis]
        for a in own:
            motion = motion.advanced(deflection[a])
        suffix = _left_motion(suffix, motion)
        if comp_columns is not None and own:
            column = adjoint_inverse_apply(suffix, chain.joint_screws[i])[:residual_dim]
            for a in own:
                np.multiply(column, loads_nm[:, a], out=comp_columns[6 * (k + 1) + a])
        for a in reversed(range(len(axes))):
            if axes[a].joint_index != i or axes[a].is_joint_axis:
                continue
            screw = np.r_[0.0, 0.0, 0.0, axes[a].axis]
            suffix = _left_motion(suffix, lie.ScrewMotion.of(screw, deflection[a]))
            if comp_columns is not None:
                column = adjoint_inverse_apply(suffix, screw)[:residual_dim]
                np.multiply(column, loads_nm[:, a], out=comp_columns[6 * (k + 1) + a])
        if columns is not None and i in wanted:
            link_columns(suffix, columns[6 * i : 6 * i + 6])
        link = params.links[i]
        suffix = lie.combine_rows(link[:3, :3], suffix)
        suffix[:, 3] += link[:3, 3, None]
    return ChainSweep(suffix[:, :3], suffix[:, 3], columns)


def _left_motion(suffix: FloatArray, motion: lie.ScrewMotion) -> FloatArray:
    """``E · [R | t]`` for a batch-last suffix (3, 4, n)."""
    out = motion.rotate(suffix)
    if motion.translation is not None:
        out[:, 3] += motion.translation
    return out


def adjoint_inverse_apply(suffix: FloatArray, twist: FloatArray) -> FloatArray:
    """``Ad_B⁻¹ ξ = [Rᵀ(v − t × w); Rᵀ w]`` for a constant twist ξ = [v; w] (6,) and
    suffixes ``B = [R | t]`` (3, 4, n); returns (6, n). Paper Eq. (5), inverse."""
    v, w = np.asarray(twist[:3], dtype=float), np.asarray(twist[3:], dtype=float)
    t = suffix[:, 3]
    moved = np.stack(
        [
            v[0] - (t[1] * w[2] - t[2] * w[1]),
            v[1] - (t[2] * w[0] - t[0] * w[2]),
            v[2] - (t[0] * w[1] - t[1] * w[0]),
        ]
    )
    out = np.empty((6, suffix.shape[-1]))
    out[:3] = _rotate_transposed(suffix[:, :3], moved)
    out[3:] = lie.combine_rows(w[None], suffix[:, :3])[0]
    return out


def _rotate_transposed(rotation: FloatArray, x: FloatArray) -> FloatArray:
    """``Rᵀ x`` for batch-last R (3, 3, n) and x (3, n): ``Σ_r R[r, :] x_r``."""
    out = rotation[0] * x[0]
    out += rotation[1] * x[1]
    out += rotation[2] * x[2]
    return out


def link_columns(suffix: FloatArray, out: FloatArray) -> None:
    """Write ``J_i = Ad_{B_i}⁻¹ = [[Rᵀ, −Rᵀ[t]x], [0, Rᵀ]]`` into ``out`` (6, d, n).

    Column m < 3 (translation twist) is row m of R on top; column 3 + j (rotation about axis j)
    is ``Rᵀ(e_j × t)`` on top and row j of R below (rows ≥ d are not written).
    """
    rotation, t = suffix[:, :3], suffix[:, 3]
    out[0:3, 0:3] = rotation  # out[m, a] = R[m, a]
    np.multiply(rotation[2], t[1], out=out[3, 0:3])
    out[3, 0:3] -= rotation[1] * t[2]
    np.multiply(rotation[0], t[2], out=out[4, 0:3])
    out[4, 0:3] -= rotation[2] * t[0]
    np.multiply(rotation[1], t[0], out=out[5, 0:3])
    out[5, 0:3] -= rotation[0] * t[1]
    if out.shape[1] == 6:
        out[3:6, 3:6] = rotation


def quaternion_rotation(quaternion_xyzw: FloatArray) -> FloatArray:
    """Rotation matrices (3, 3, n) of unit quaternions (n, 4), scalar LAST (DESIGN.md §3)."""
    x, y, z, w = (np.ascontiguousarray(quaternion_xyzw[:, i]) for i in range(4))
    out = np.empty((3, 3, x.size))
    out[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[0, 1] = 2.0 * (x * y - z * w)
    out[0, 2] = 2.0 * (x * z + y * w)
    out[1, 0] = 2.0 * (x * y + z * w)
    out[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[1, 2] = 2.0 * (y * z - x * w)
    out[2, 0] = 2.0 * (x * z - y * w)
    out[2, 1] = 2.0 * (y * z + x * w)
    out[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return out


@dataclass(frozen=True)
class PoseResiduals:
    """End-effector-frame residuals of n samples, batch-last.

    ``residual`` (d, n): ``Log(X_model⁻¹ X_measured)`` ([v; w], m and rad) or, position-only,
    ``R_modelᵀ(p_measured − p_model)`` (m). ``translation_error_m`` (n,) = |p_model − p_measured|;
    ``rotation_error_rad`` (n,) geodesic angle (None if position-only), as
    :func:`solver.calibration.pose_errors` computes them.
    """

    residual: FloatArray
    translation_error_m: FloatArray
    rotation_error_rad: FloatArray | None


def pose_residuals(
    sweep: ChainSweep,
    measured_rotation: FloatArray | None,
    measured_translation_m: FloatArray,
) -> PoseResiduals:
    """DESIGN.md §2 residuals from a sweep and measured poses: rotation (3, 3, n) (None for
    position-only data) and translation (3, n), measurement frame."""
    rotation = sweep.rotation
    delta = measured_translation_m - sweep.translation
    relative_t = _rotate_transposed(rotation, delta)
    distance = np.sqrt(np.einsum("in,in->n", delta, delta))
    if measured_rotation is None:
        return PoseResiduals(relative_t, distance, None)
    relative_r = rotation[0][:, None, :] * measured_rotation[0][None, :, :]
    relative_r += rotation[1][:, None, :] * measured_rotation[1][None, :, :]
    relative_r += rotation[2][:, None, :] * measured_rotation[2][None, :, :]
    twist, angle = _se3_log_batch_last(relative_r, relative_t)
    return PoseResiduals(twist, distance, angle)


def _se3_log_batch_last(
    rotation: FloatArray, translation: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``Log`` of ``[R | t]`` (3, 3, n), (3, n) → twist [v; w] (6, n) and the angle (n,).

    ``w = θ / sin θ · vee(R − Rᵀ) / 2`` with θ = atan2(sin θ, cos θ) (series for θ < 1e-2),
    ``v = V(w)⁻¹ t = t − ½ w × t + c w × (w × t)`` as in :func:`solver.lie.se3_log`. The
    angle is returned as ``arccos((tr R − 1) / 2)``, the formula of
    :func:`solver.lie.rotation_angle_rad`, so error statistics match the in-memory path.
    """
    cos = 0.5 * (rotation[0, 0] + rotation[1, 1] + rotation[2, 2] - 1.0)
    w = np.empty((3, cos.size))
    np.subtract(rotation[2, 1], rotation[1, 2], out=w[0])
    np.subtract(rotation[0, 2], rotation[2, 0], out=w[1])
    np.subtract(rotation[1, 0], rotation[0, 1], out=w[2])
    w *= 0.5
    sin = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    theta = np.arctan2(sin, cos)
    t2 = theta * theta
    ratio = 1.0 + t2 * (1.0 / 6.0 + t2 * (7.0 / 360.0 + t2 * (31.0 / 15120.0)))
    c = 1.0 / 12.0 + t2 * (1.0 / 720.0 + t2 * (1.0 / 30240.0))
    large = np.flatnonzero(theta >= _SERIES_ANGLE_RAD)
    if large.size:
        th, s_l, c_l = theta[large], sin[large], cos[large]
        ratio[large] = th / s_l
        c[large] = (1.0 - th * s_l / (2.0 * (1.0 - c_l))) / (th * th)
    w *= ratio
    far = np.flatnonzero(cos < _FALLBACK_COS)
    if far.size:  # near π the skew part loses digits: scipy's quaternion route is exact there
        w[:, far] = lie.so3_log(np.ascontiguousarray(rotation[:, :, far].transpose(2, 0, 1))).T
        th = np.sqrt(np.einsum("in,in->n", w[:, far], w[:, far]))
        c[far] = (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))) / (th * th)
    cross = _cross(w, translation)
    v = _cross(w, cross)
    v *= c
    v += translation
    v -= 0.5 * cross
    out = np.concatenate([v, w])
    return out, np.arccos(np.clip(cos, -1.0, 1.0))


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of batch-last (3, n) arrays."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
