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

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from solver import lie
from solver.arrays import FloatArray, IntArray
from solver.kinematics import ChainParameters
from solver.model import KinematicChain

_SERIES_ANGLE_RAD = 1e-2
"""Below this rotation angle the log map uses Taylor series (truncation < 1e-16 relative)."""
_FALLBACK_COS = -0.5
"""Residual rotations beyond 120° (cos < -0.5) use scipy's log, exact up to π."""


@dataclass(frozen=True)
class ChainSweep:
    """Result of :func:`sweep_chain` for n samples.

    ``rotation`` (3, 3, n) and ``translation`` (3, n): the pose ``X_0E`` (Eq. 7).
    ``columns`` (C, d, n) or None: the requested columns of the stacked Jacobian (unweighted),
    residual component d, sample n; column ``6f + i`` (f < k) is also column i of the frame
    Jacobian ``A_f = Ad_{B_f}⁻¹`` of the perturbation ξ_f. ``leading_rows`` (C,): rows of each
    column that can be non-zero; the rows after them are zero by structure (a translation
    column has no rotation rows, the tip link's columns are unit vectors).
    """

    rotation: FloatArray
    translation: FloatArray
    columns: FloatArray | None
    leading_rows: IntArray | None


def column_rows(chain: KinematicChain, column: int, residual_dim: int) -> int:
    """Rows of Jacobian column ``column`` that can be non-zero (a prefix; the others are zero
    by structure): a link's translation column has no rotation rows, the tip link's column m
    is the unit vector e_m, a compliance column is full."""
    k = chain.n_joints
    if column >= 6 * (k + 1):
        return residual_dim
    m = column % 6
    if column >= 6 * k:
        return m + 1 if m < residual_dim else 0
    return min(3, residual_dim) if m < 3 else residual_dim


def is_unit_column(chain: KinematicChain, column: int) -> bool:
    """The tip link's columns are constant unit vectors (``J_{k+1} = I``)."""
    return 6 * chain.n_joints <= column < 6 * (chain.n_joints + 1)


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
    columns: Sequence[int] | None = None,
    out: FloatArray | None = None,
) -> ChainSweep:
    """Eq. (7) and the Eq. (9) Jacobian in one backward sweep over the chain.

    ``motions``: :func:`joint_motions` of the read joint positions (N, k); ``loads_nm``
    (N, n_axes): gravity torque about each compliance axis (Eq. 6), so the joints sit at
    ``q + c τ``. ``residual_dim`` 6 (pose) or 3 (position-only: the first three rows).
    ``columns``: indices (order of :func:`solver.kinematics.parameter_names`) of the Jacobian
    columns to compute, in the order wanted (None: the pose only); ``out`` (C, d, N): where to
    write them (a reusable workspace), else a new array. Only the requested columns are
    formed, each written once.
    """
    n = loads_nm.shape[0]
    k = chain.n_joints
    d = residual_dim
    axes = chain.compliance_axes
    slot = {} if columns is None else {int(c): s for s, c in enumerate(columns)}
    jacobian: FloatArray | None = None
    rows: IntArray | None = None
    if columns is not None:
        jacobian = np.empty((len(slot), d, n)) if out is None else out
        if jacobian.shape != (len(slot), d, n):
            raise ValueError(f"out must be {(len(slot), d, n)}, got {jacobian.shape}")
        rows = np.array([column_rows(chain, c, d) for c in slot], dtype=np.intp)
    loads = np.ascontiguousarray(np.asarray(loads_nm, dtype=float).T)  # (n_axes, N)
    deflection = loads * params.compliance_rad_per_nm[:, None]
    suffix = np.empty((3, 4, n))
    suffix[:] = params.links[k][:3, :, None]
    spare = np.empty_like(suffix)
    scratch = np.empty((2, 4, n))
    for m in range(6):  # J_{k+1} = I: the tip link's twist is the residual's
        s = slot.get(6 * k + m)
        if s is not None:
            assert jacobian is not None
            jacobian[s] = 0.0
            if m < d:
                jacobian[s, m] = 1.0
    for i in range(k - 1, -1, -1):
        motion = motions[i]
        own = [a for a, ax in enumerate(axes) if ax.joint_index == i and ax.is_joint_axis]
        for a in own:
            motion = motion.advanced(deflection[a])
        _move(suffix, motion, scratch)
        for a in own:
            s = slot.get(6 * (k + 1) + a)
            if s is not None:
                assert jacobian is not None
                _twist_column(suffix, chain.joint_screws[i], loads[a], jacobian[s], scratch)
        for a in reversed(range(len(axes))):
            if axes[a].joint_index != i or axes[a].is_joint_axis:
                continue
            screw = np.r_[0.0, 0.0, 0.0, axes[a].axis]
            _move(suffix, lie.ScrewMotion.of(screw, deflection[a]), scratch)
            s = slot.get(6 * (k + 1) + a)
            if s is not None:
                assert jacobian is not None
                _twist_column(suffix, screw, loads[a], jacobian[s], scratch)
        for m in range(6):
            s = slot.get(6 * i + m)
            if s is not None:
                assert jacobian is not None
                _link_column(suffix, m, jacobian[s], scratch)
        _place(params.links[i], suffix, spare, scratch)
        suffix, spare = spare, suffix
    return ChainSweep(suffix[:, :3], suffix[:, 3], jacobian, rows)


def _move(suffix: FloatArray, motion: lie.ScrewMotion, scratch: FloatArray) -> None:
    """``suffix ← E · suffix`` in place for a batch-last ``[R | t]`` (3, 4, n)."""
    axis = motion.axis
    aligned = np.flatnonzero(axis != 0.0)
    if aligned.size == 1:
        u = int(aligned[0])
        sin = motion.sin if axis[u] > 0.0 else -motion.sin
        v, w = (u + 1) % 3, (u + 2) % 3
        new_v, term = scratch[0], scratch[1]
        np.multiply(motion.cos, suffix[v], out=new_v)
        np.multiply(sin, suffix[w], out=term)
        new_v -= term
        np.multiply(sin, suffix[v], out=term)
        suffix[w] *= motion.cos
        suffix[w] += term
        suffix[v] = new_v
    else:
        suffix[:] = motion.rotate(suffix)
    if motion.translation is not None:
        suffix[:, 3] += motion.translation


def _place(link: FloatArray, suffix: FloatArray, out: FloatArray, scratch: FloatArray) -> None:
    """``out ← L · suffix`` for a constant placement L (4, 4) (zero coefficients skipped, so
    the URDF's exact zeros cost nothing; element by element, no BLAS: a sample's result does
    not depend on where it sits in the batch)."""
    term = scratch[0]
    for p in range(3):
        used = np.flatnonzero(link[p, :3])
        if not used.size:
            out[p] = 0.0
        else:
            np.multiply(suffix[used[0]], link[p, used[0]], out=out[p])
            for j in used[1:]:
                np.multiply(suffix[j], link[p, j], out=term)
                out[p] += term
        out[p, 3] += link[p, 3]


def _link_column(suffix: FloatArray, m: int, out: FloatArray, scratch: FloatArray) -> None:
    """Column m of ``J_i = Ad_{B_i}⁻¹ = [[Rᵀ, −Rᵀ[t]x], [0, Rᵀ]]`` into ``out`` (d, n).

    Column m < 3 (translation twist) is row m of R on top and zeros below; column 3 + j
    (rotation about axis j) is ``Rᵀ(e_j × t)`` on top and row j of R below.
    """
    d = out.shape[0]
    if m < 3:
        out[:3] = suffix[m, :3]
        out[3:] = 0.0
        return
    j = m - 3
    j1, j2 = (j + 1) % 3, (j + 2) % 3
    t = suffix[:, 3]
    term = scratch[0, :3]
    np.multiply(suffix[j2, :3], t[j1], out=out[:3])
    np.multiply(suffix[j1, :3], t[j2], out=term)
    out[:3] -= term
    if d > 3:
        out[3:] = suffix[j, :3]


def _twist_column(
    suffix: FloatArray, twist: FloatArray, load: FloatArray, out: FloatArray, scratch: FloatArray
) -> None:
    """``Ad_B⁻¹ ξ · τ`` (d, n) for a constant twist ξ (6,) (a compliance axis) and its load
    τ (n,): one column of :func:`_link_column` when ξ is a unit twist (every URDF joint
    along a coordinate axis), the general product otherwise."""
    used = np.flatnonzero(twist)
    if used.size == 1 and twist[used[0]] == 1.0:
        _link_column(suffix, int(used[0]), out, scratch)
    else:
        out[:] = adjoint_inverse_apply(suffix, twist)[: out.shape[0]]
    out *= load


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
    angle is θ, the formula of :func:`solver.lie.rotation_angle_rad`, so error statistics
    match the in-memory path.
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
    return out, theta


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of batch-last (3, n) arrays."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
