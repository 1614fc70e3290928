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

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.errors import ModelError
from solver.model import STANDARD_GRAVITY_BASE, KinematicChain

FloatArray = NDArray[np.float64]


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


def static_gravity_loads(
    model: StaticGravityModel,
    joint_positions: FloatArray,
    *,
    gravity_base: FloatArray = STANDARD_GRAVITY_BASE,
    payload_kg: FloatArray | float = 0.0,
    motions: list[lie.ScrewMotion] | None = None,
) -> FloatArray:
    """Torque gravity exerts about every compliance axis, τ (N, n_axes) in N·m (paper Eq. 6).

    ``joint_positions`` (N, k) rad (m for prismatic joints); ``gravity_base`` (3,) m/s² in the
    chain's base frame; ``payload_kg`` scalar or (N,). ``motions``: the caller's
    :func:`joint_motions` of the same configurations, to share their trigonometry. Equals
    :func:`solver.model.gravity_loads` to rounding (tested to 1e-10 N·m on every built-in robot).
    """
    q = np.asarray(joint_positions, dtype=float)
    k, n = q.shape[1], q.shape[0]
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    gravity_world = model.rotation_world_base @ np.asarray(gravity_base, dtype=float)
    if motions is None:
        motions = joint_motions(model, q)
    # Forward: gravity in the frame right after each L_i (before joint i moves), (3, N).
    gravity_pre = []
    g = np.broadcast_to(gravity_world[:, None], (3, n))
    for i in range(k):
        g = lie.combine_rows(model.placements[i, :, :3].T, g)
        gravity_pre.append(g)
        g = motions[i].rotate_inverse(g)
    # Backward: mass and first moment of everything joint i carries, about the pre-motion origin.
    loads = np.empty((n, model.axis_joint.size))
    mass = model.body_mass_kg[-1] + payload
    first_moment = (
        model.body_mass_kg[-1] * model.body_com_m[-1][:, None]
        + payload * model.payload_com_m[:, None]
    )
    for i in range(k - 1, -1, -1):
        first_moment = motions[i].rotate(first_moment)  # about the pre-motion origin:
        if motions[i].translation is not None:  # R h + M t
            first_moment = first_moment + mass * motions[i].translation
        axes_here = np.flatnonzero(model.axis_joint == i)
        if axes_here.size:
            moment = _cross(first_moment, gravity_pre[i])
            for a in axes_here:
                loads[:, a] = lie.combine_rows(model.axis_vector[a][None], moment)[0]
        if i:
            placement = model.placements[i]
            first_moment = (
                lie.combine_rows(placement[:, :3], first_moment)
                + mass * placement[:, 3, None]
                + model.body_mass_kg[i - 1] * model.body_com_m[i - 1][:, None]
            )
            mass = mass + model.body_mass_kg[i - 1]
    return loads


def joint_motions(model: StaticGravityModel, joint_positions: FloatArray) -> list[lie.ScrewMotion]:
    """``Exp(s_i q_i)`` of every chain joint for configurations (N, k), batch-last."""
    q = np.asarray(joint_positions, dtype=float)
    return [
        lie.ScrewMotion.of(model.screws[i], np.ascontiguousarray(q[:, i]))
        for i in range(q.shape[1])
    ]


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of batch-last (3, N) arrays."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
