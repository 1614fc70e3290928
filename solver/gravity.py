"""Static gravity loads for 10^5..10^6 configurations at once (paper Eq. 6, DESIGN.md §2).

Same quantity as :func:`solver.model.gravity_loads` (Pinocchio RNEA, one configuration per
call, ~4·10^4 configurations/s from Python), computed in closed form and vectorised:

    τ_a(q) = u_a · Σ_{b downstream of joint i(a)} (c_b(q) - o_i(q)) × m_b g

for a compliance axis ``a`` at chain joint ``i``: ``u_a`` the axis and ``o_i`` the origin of the
frame right after ``L_i`` (before joint i moves), ``c_b`` and ``m_b`` the centre of mass and mass
of every body carried by joint i (the payload included), all in Pinocchio's world frame, ``g``
gravity. This is the gravity moment transmitted through the joint (``-data.f``) about the axis;
for a joint's own axis it is ``-computeGeneralizedGravity``. Masses and centres of mass are read
once from ``chain.pin_model`` / ``chain.payload_model`` (the nominal URDF, like the RNEA path).

How: the static part of RNEA, written for batches. A forward pass carries only the gravity
vector into every joint frame (``g_i = E_i^T P_i^T g_{i-1}``); a backward pass accumulates the
mass ``M_i`` and first moment ``h_i = Σ_b m_b (c_b - o_i)`` of everything joint i carries
(``h_{i-1} = m b + M_i p_i + P_i E_i h_i``, with ``P_i = (R_i, p_i)`` the constant placement and
``E_i`` the joint motion). Then ``τ_a = u_a · (h_i × g_i)``. No rotation matrix is ever formed
per sample; arrays are batch-LAST (``(3, N)``) so every numpy call runs over contiguous rows.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.arrays import FloatArray
from solver.errors import ModelError
from solver.model import STANDARD_GRAVITY_BASE, KinematicChain


@dataclass(frozen=True, eq=False)
class StaticGravityModel:
    """Everything the closed form needs, extracted once from a chain's Pinocchio models.

    ``placements`` (k, 3, 4): joint placement in its parent joint's (moved) frame, Pinocchio
    world frame for the first chain joint. ``screws`` (k, 6) joint motion subspaces.
    ``body_mass_kg`` (k,), ``body_com_m`` (k, 3): body of each chain joint, CoM in that joint's
    moved frame. ``payload_com_m`` (3,): 1 kg payload point in the last joint's moved frame.
    ``axis_joint`` (n_axes,) and ``axis_vector`` (n_axes, 3): compliance axes (frame right after
    ``L_i``). ``rotation_world_base`` (3, 3): gravity is given in the chain's base frame.
    """

    placements: FloatArray
    screws: FloatArray
    body_mass_kg: FloatArray
    body_com_m: FloatArray
    payload_com_m: FloatArray
    axis_joint: NDArray[np.intp]
    axis_vector: FloatArray
    rotation_world_base: FloatArray
    plan: _GravityPlan = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "plan", _GravityPlan.of(self))

    @classmethod
    def from_chain(cls, chain: KinematicChain) -> StaticGravityModel:
        model, payload = chain.pin_model, chain.payload_model
        ids = chain.pin_joint_ids
        placements = np.array([model.jointPlacements[j].homogeneous[:3] for j in ids])
        last = ids[-1]
        extra = [
            j for j in range(1, payload.njoints) if j != last and payload.inertias[j].mass != 0.0
        ]
        if extra or any(model.parents[j] != p for j, p in zip(ids, (0, *ids[:-1]), strict=True)):
            raise ModelError("the chain's Pinocchio model is not a serial chain of its joints")
        return cls(
            placements=placements,
            screws=chain.joint_screws.copy(),
            body_mass_kg=np.array([model.inertias[j].mass for j in ids]),
            body_com_m=np.array([np.asarray(model.inertias[j].lever) for j in ids]),
            payload_com_m=np.asarray(payload.inertias[last].lever, dtype=float).copy(),
            axis_joint=np.array([a.joint_index for a in chain.compliance_axes], dtype=np.intp),
            axis_vector=np.array([a.axis for a in chain.compliance_axes]).reshape(-1, 3),
            rotation_world_base=chain.gravity_rotation_world_base.copy(),
        )


@dataclass(frozen=True, eq=False)
class _GravityPlan:
    """The constant parts of :func:`static_gravity_loads`, resolved once per model: joint
    screws, placements as :class:`~solver.lie.RowCombination` (mostly signed permutations),
    the compliance axes of each joint, and each body's first moment ``m_b c_b``. Same
    arithmetic as the plain loops, a fraction of the numpy calls (small batches pay per call).
    """

    joints: tuple[lie.Screw, ...]
    to_joint: tuple[lie.RowCombination, ...]  # R_i^T: parent frame -> frame after L_i
    from_joint: tuple[lie.RowCombination, ...]  # R_i
    axes_at: tuple[NDArray[np.intp], ...]
    axis_rows: tuple[lie.RowCombination, ...]  # u_a^T of the axes at joint i
    body_moment: FloatArray  # (k, 3, 1) m_b c_b

    @classmethod
    def of(cls, model: StaticGravityModel) -> _GravityPlan:
        k = model.placements.shape[0]
        axes_at = tuple(np.flatnonzero(model.axis_joint == i) for i in range(k))
        return cls(
            joints=tuple(lie.Screw.of(screw) for screw in model.screws),
            to_joint=tuple(lie.RowCombination.of(p[:, :3].T) for p in model.placements),
            from_joint=tuple(lie.RowCombination.of(p[:, :3]) for p in model.placements),
            axes_at=axes_at,
            axis_rows=tuple(lie.RowCombination.of(model.axis_vector[a]) for a in axes_at),
            body_moment=np.array(
                [
                    m * com[:, None]
                    for m, com in zip(model.body_mass_kg, model.body_com_m, strict=True)
                ]
            ).reshape(k, 3, 1),
        )


def static_gravity_loads(
    model: StaticGravityModel,
    joint_positions: FloatArray,
    *,
    gravity_base: FloatArray = STANDARD_GRAVITY_BASE,
    payload_kg: FloatArray | float = 0.0,
    motions: list[lie.ScrewMotion] | None = None,
    joints: Collection[int] | None = None,
) -> FloatArray:
    """Torque gravity exerts about every compliance axis, τ (N, n_axes) in N·m (paper Eq. 6).

    ``joint_positions`` (N, k) rad (m for prismatic joints); ``gravity_base`` (3,) m/s² in the
    chain's base frame; ``payload_kg`` scalar or (N,). ``motions``: the caller's
    :func:`joint_motions` of the same configurations, to share their trigonometry. ``joints``:
    only the axes at these chain joints are wanted (the others are returned as 0, and the
    passes stop at the first and last of them). Equals :func:`solver.model.gravity_loads` to
    rounding (tested to 1e-10 N·m on every built-in robot).
    """
    q = np.asarray(joint_positions, dtype=float)
    k, n = q.shape[1], q.shape[0]
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    gravity_world = model.rotation_world_base @ np.asarray(gravity_base, dtype=float)
    if motions is None:
        motions = joint_motions(model, q)
    plan = model.plan
    wanted = [i for i in range(k) if plan.axes_at[i].size and (joints is None or i in joints)]
    if len(wanted) < k:
        loads = np.zeros((n, model.axis_joint.size))
        if not wanted:
            return loads
    else:
        loads = np.empty((n, model.axis_joint.size))
    # Forward: gravity in the frame right after each L_i (before joint i moves), (3, N).
    gravity_pre = []
    g = np.broadcast_to(gravity_world[:, None], (3, n))
    for i in range(wanted[-1] + 1):
        g = plan.to_joint[i](g)
        gravity_pre.append(g)
        if i < wanted[-1]:
            g = motions[i].rotate_inverse(g)
    # Backward: mass and first moment of everything joint i carries, about the pre-motion origin.
    mass = model.body_mass_kg[-1] + payload
    first_moment = plan.body_moment[-1] + payload * model.payload_com_m[:, None]
    for i in range(k - 1, wanted[0] - 1, -1):
        first_moment = motions[i].rotate(first_moment)  # about the pre-motion origin:
        if motions[i].translation is not None:  # R h + M t
            first_moment = first_moment + mass * motions[i].translation
        if i in wanted:
            loads[:, plan.axes_at[i]] = plan.axis_rows[i](_cross(first_moment, gravity_pre[i])).T
        if i > wanted[0]:
            first_moment = (
                plan.from_joint[i](first_moment)
                + mass * model.placements[i, :, 3, None]
                + plan.body_moment[i - 1]
            )
            mass = mass + model.body_mass_kg[i - 1]
    return loads


def joint_motions(model: StaticGravityModel, joint_positions: FloatArray) -> list[lie.ScrewMotion]:
    """``Exp(s_i q_i)`` of every chain joint for configurations (N, k), batch-last (the
    trigonometry of all joints in one pass)."""
    angles = np.ascontiguousarray(np.asarray(joint_positions, dtype=float).T)  # (k, N)
    joints = model.plan.joints
    norms = np.array([joint.norm_w for joint in joints])[:, None]
    cos, sin = lie.cos_sin_rows(angles if np.all(norms == 1.0) else norms * angles)
    return [
        joint.motion(angles[i], (cos[i], sin[i])) if joint.norm_w else joint.motion(angles[i])
        for i, joint in enumerate(joints)
    ]


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of batch-last (3, N) arrays (one gathered product per term for
    small N, component by component for large N: the same arithmetic)."""
    if a.shape[1] <= lie.FUSED_MAX_ELEMENTS:
        return a[_NEXT] * b[_PREV] - a[_PREV] * b[_NEXT]
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


_NEXT = np.array([1, 2, 0])
_PREV = np.array([2, 0, 1])
