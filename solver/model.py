"""The compliant probabilistic POE chain of paper Eq. (7), built from a URDF with Pinocchio.

Chain (DESIGN.md §2), k movable joints between a base frame and a tip frame::

    X_0E(q) = prod_{i=1..k} [ L_i · Exp(ξ_i) · V_i · Exp(s_i (q_i + c_i τ_i)) ] · L_{k+1}

``L_i`` is the placement of joint i in its parent joint frame (URDF origins, fixed joints folded
in; ``L_1`` starts at the base frame, ``L_{k+1}`` ends at the tip frame), ``s_i`` the joint screw
``[v; w]`` in joint i's own frame, ``V_i`` the virtual compliant rotations inserted before joint i
(paper §V-A, base-plate flex) and ``τ`` the torque gravity exerts about each compliant axis.

This module only builds the frozen structure (:class:`KinematicChain`) and computes gravity
loads; forward kinematics and Jacobians live in :mod:`solver.kinematics`. It takes URDF *text*,
never paths: locating files is the caller's job.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from solver.arrays import FloatArray
from solver.errors import ModelError
from solver.lie import se3_exp

STANDARD_GRAVITY_BASE = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True, eq=False)
class ComplianceAxis:
    """One compliant rotation axis (paper Eq. 6 and §V-A).

    ``axis`` is a unit vector in the frame right after ``L_i`` (before joint i moves). For a
    joint's own compliance it is the joint axis; a virtual axis is orthogonal to it and models
    flex of the structure carrying the joint.
    """

    name: str
    joint_index: int
    axis: FloatArray
    is_joint_axis: bool


@dataclass(frozen=True, eq=False)
class KinematicChain:
    """Frozen nominal structure of the chain; never mutated (calibration returns parameters)."""

    joint_names: tuple[str, ...]
    joint_screws: FloatArray  # (k, 6) [v; w] in each joint's own frame
    nominal_links: FloatArray  # (k+1, 4, 4): L_1 (base frame -> joint 1) ... L_{k+1} (-> tip)
    lower_limits: FloatArray  # (k,) rad or m
    upper_limits: FloatArray  # (k,)
    base_frame: str
    tip_frame: str
    compliance_axes: tuple[ComplianceAxis, ...]
    other_joint_names: tuple[str, ...]  # URDF joints off the chain (locked at zero)
    urdf_sha256: str
    # Gravity machinery: Pinocchio model reduced to the chain joints, plus a copy holding only a
    # 1 kg point mass at the payload centre, so loads are linear in payload mass.
    pin_model: pin.Model = field(repr=False)
    payload_model: pin.Model = field(repr=False)
    pin_joint_ids: tuple[int, ...] = field(repr=False)
    gravity_rotation_world_base: FloatArray = field(repr=False)  # (3, 3)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_links(self) -> int:
        return len(self.joint_names) + 1

    @property
    def link_names(self) -> tuple[str, ...]:
        """Name of each L_i: the joint it places, and the tip frame for ``L_{k+1}``."""
        return (*self.joint_names, self.tip_frame)

    def is_revolute(self) -> NDArray[np.bool_]:
        """(k,) True for revolute joints (screw has a rotational part)."""
        return np.linalg.norm(self.joint_screws[:, 3:], axis=1) > 0.5


def build_chain(
    urdf_xml: str,
    base_frame: str,
    tip_frame: str,
    *,
    compliant_joints: Sequence[str] | None = None,
    virtual_axes_at: Sequence[str] = (),
    payload_com_m: Sequence[float] = (0.0, 0.0, 0.0),
) -> KinematicChain:
    """Build the chain between two URDF frames.

    ``compliant_joints``: joints with an elastic joint axis (default: every revolute joint; the
    identifiability check later drops those whose gravity torque does not vary).
    ``virtual_axes_at``: joints that get two virtual compliant axes orthogonal to their axis.
    ``payload_com_m``: payload centre of mass in the tip frame (m); its mass is given per sample.
    """
    try:
        full_model = pin.buildModelFromXML(urdf_xml)
    except (RuntimeError, ValueError) as exc:
        raise ModelError(f"URDF could not be parsed by Pinocchio: {exc}") from exc
    base_id = _frame_id(full_model, base_frame, "base")
    tip_id = _frame_id(full_model, tip_frame, "tip")
    chain_ids = _chain_joint_ids(full_model, base_id, tip_id)
    locked = [j for j in range(1, full_model.njoints) if j not in chain_ids]
    model = (
        pin.buildReducedModel(full_model, locked, pin.neutral(full_model)) if locked else full_model
    )
    names = tuple(full_model.names[j] for j in chain_ids)
    joint_ids = tuple(model.getJointId(name) for name in names)
    screws = np.array([_joint_screw(model, j) for j in joint_ids])
    links = _link_placements(
        model, joint_ids, model.getFrameId(base_frame), model.getFrameId(tip_frame)
    )
    lower, upper = _joint_limits(model, joint_ids)
    axes = _compliance_axes(names, screws, compliant_joints, virtual_axes_at)
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    rotation_world_base = data.oMf[model.getFrameId(base_frame)].rotation.copy()
    return KinematicChain(
        joint_names=names,
        joint_screws=screws,
        nominal_links=links,
        lower_limits=lower,
        upper_limits=upper,
        base_frame=base_frame,
        tip_frame=tip_frame,
        compliance_axes=axes,
        other_joint_names=tuple(full_model.names[j] for j in locked),
        urdf_sha256=hashlib.sha256(urdf_xml.encode()).hexdigest(),
        pin_model=model,
        payload_model=_payload_model(model, model.getFrameId(tip_frame), payload_com_m),
        pin_joint_ids=joint_ids,
        gravity_rotation_world_base=rotation_world_base,
    )


def _frame_id(model: pin.Model, name: str, role: str) -> int:
    if not model.existFrame(name):
        known = ", ".join(f.name for f in model.frames if f.type == pin.FrameType.BODY)
        raise ModelError(f"{role} frame {name!r} is not in the URDF; known links: {known}")
    return model.getFrameId(name)


def _chain_joint_ids(model: pin.Model, base_id: int, tip_id: int) -> list[int]:
    """Movable joints on the path base -> tip, in order; errors if there is no such path."""
    base_joint = model.frames[base_id].parentJoint
    tip_joint = model.frames[tip_id].parentJoint
    path = list(model.supports[tip_joint])  # universe ... tip_joint
    if base_joint not in path:
        raise ModelError(
            f"tip frame {model.frames[tip_id].name!r} is not downstream of base frame "
            f"{model.frames[base_id].name!r}; choose a tip on the base's kinematic subtree"
        )
    chain = path[path.index(base_joint) + 1 :]
    if not chain:
        raise ModelError("no movable joint between the base and tip frames")
    for j in chain:
        joint = model.joints[j]
        if joint.nv != 1:
            raise ModelError(
                f"joint {model.names[j]!r} ({joint.shortname()}) has {joint.nv} degrees of "
                "freedom; only revolute, continuous and prismatic joints are supported"
            )
    mimics = {int(j) for j in getattr(model, "mimicking_joints", [])}
    if mimics & set(chain):
        raise ModelError("mimic joints on the calibrated chain are not supported")
    return chain


def _joint_screw(model: pin.Model, joint_id: int) -> FloatArray:
    """Motion subspace of a 1-DOF joint, [v; w] in its own frame, checked to be a pure screw."""
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    screw = np.asarray(data.joints[joint_id].S, dtype=float).reshape(6)
    v_norm, w_norm = np.linalg.norm(screw[:3]), np.linalg.norm(screw[3:])
    revolute = np.isclose(w_norm, 1.0) and v_norm < 1e-12
    prismatic = np.isclose(v_norm, 1.0) and w_norm < 1e-12
    if not (revolute or prismatic):
        raise ModelError(f"joint {model.names[joint_id]!r} is neither revolute nor prismatic")
    return screw


def _link_placements(
    model: pin.Model, joint_ids: tuple[int, ...], base_frame_id: int, tip_frame_id: int
) -> FloatArray:
    """L_1..L_{k+1} as (k+1, 4, 4); L_1 is expressed from the base frame."""
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    first = joint_ids[0]
    parent_placement = data.oMi[model.parents[first]]
    links = [
        (
            data.oMf[base_frame_id].inverse() * parent_placement * model.jointPlacements[first]
        ).homogeneous
    ]
    for previous, joint in itertools.pairwise(joint_ids):
        if model.parents[joint] != previous:
            raise ModelError(
                f"joint {model.names[joint]!r} does not follow {model.names[previous]!r}"
            )
        links.append(model.jointPlacements[joint].homogeneous)
    tip = model.frames[tip_frame_id]
    if tip.parentJoint != joint_ids[-1]:
        raise ModelError(f"tip frame {tip.name!r} is not attached after the last chain joint")
    links.append(tip.placement.homogeneous)
    return np.array(links)


def _joint_limits(model: pin.Model, joint_ids: tuple[int, ...]) -> tuple[FloatArray, FloatArray]:
    """Position limits per chain joint; continuous or unlimited joints get [-pi, pi]."""
    lower, upper = [], []
    for j in joint_ids:
        joint = model.joints[j]
        lo = model.lowerPositionLimit[joint.idx_q] if joint.nq == 1 else -np.pi
        hi = model.upperPositionLimit[joint.idx_q] if joint.nq == 1 else np.pi
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
            lo, hi = -np.pi, np.pi
        lower.append(lo)
        upper.append(hi)
    return np.array(lower), np.array(upper)


def _compliance_axes(
    names: tuple[str, ...],
    screws: FloatArray,
    compliant_joints: Sequence[str] | None,
    virtual_axes_at: Sequence[str],
) -> tuple[ComplianceAxis, ...]:
    revolute = np.linalg.norm(screws[:, 3:], axis=1) > 0.5
    wanted = (
        [n for n, r in zip(names, revolute, strict=True) if r]
        if compliant_joints is None
        else list(compliant_joints)
    )
    for option, chosen in (("compliant_joints", wanted), ("virtual_axes_at", virtual_axes_at)):
        for name in chosen:
            if name not in names:
                raise ModelError(
                    f"{option}: joint {name!r} is not on the chain; chain joints: "
                    f"{', '.join(names)}"
                )
            if not revolute[names.index(name)]:
                raise ModelError(
                    f"{option}: joint {name!r} is prismatic; only revolute joints can be compliant"
                )
    axes: list[ComplianceAxis] = []
    for i, name in enumerate(names):
        joint_axis = screws[i, 3:]
        if name in virtual_axes_at:
            for label, axis in zip(("flex_a", "flex_b"), _orthogonal_axes(joint_axis), strict=True):
                axes.append(ComplianceAxis(f"{name}.{label}", i, axis, is_joint_axis=False))
        if name in wanted:
            axes.append(ComplianceAxis(name, i, joint_axis.copy(), is_joint_axis=True))
    return tuple(axes)


def _orthogonal_axes(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit axes completing ``axis`` to a right-handed orthonormal basis (a, b, axis)."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    first = np.cross(helper, axis)
    first /= np.linalg.norm(first)
    return first, np.cross(axis, first)


def _payload_model(
    model: pin.Model, tip_frame_id: int, payload_com_m: Sequence[float]
) -> pin.Model:
    """Copy of ``model`` whose only mass is 1 kg at the payload centre (tip frame)."""
    payload = model.copy()
    for i in range(len(payload.inertias)):
        payload.inertias[i] = pin.Inertia.Zero()
    tip = model.frames[tip_frame_id]
    com_in_joint = tip.placement.act(np.asarray(payload_com_m, dtype=float))
    payload.inertias[tip.parentJoint] = pin.Inertia(1.0, com_in_joint, np.zeros((3, 3)))
    return payload


def sample_configurations(
    chain: KinematicChain, n: int, rng: np.random.Generator, range_fraction: float = 1.0
) -> FloatArray:
    """Uniform joint positions (n, k) within the central ``range_fraction`` of every joint range."""
    centre = 0.5 * (chain.lower_limits + chain.upper_limits)
    half = 0.5 * range_fraction * (chain.upper_limits - chain.lower_limits)
    return rng.uniform(centre - half, centre + half, size=(n, chain.n_joints))


def pin_configuration(chain: KinematicChain, joint_positions: FloatArray) -> FloatArray:
    """Pinocchio configuration vectors (N, nq) from chain joint positions (N, k).

    Continuous joints are stored by Pinocchio as (cos q, sin q).
    """
    model = chain.pin_model
    out = np.tile(pin.neutral(model), (joint_positions.shape[0], 1))
    for column, j in enumerate(chain.pin_joint_ids):
        joint = model.joints[j]
        if joint.nq == 1:
            out[:, joint.idx_q] = joint_positions[:, column]
        else:
            out[:, joint.idx_q] = np.cos(joint_positions[:, column])
            out[:, joint.idx_q + 1] = np.sin(joint_positions[:, column])
    return out


def gravity_loads(
    chain: KinematicChain,
    joint_positions: FloatArray,
    *,
    gravity_base: FloatArray = STANDARD_GRAVITY_BASE,
    payload_kg: FloatArray | float = 0.0,
) -> FloatArray:
    """Torque gravity exerts about every compliance axis, τ (N, n_axes) in N·m (paper Eq. 6).

    For a joint's own axis this is ``-pin.computeGeneralizedGravity``; for a virtual axis it is
    the gravity moment transmitted through that joint (RNEA with zero velocity and acceleration,
    ``data.f``) about the axis. ``gravity_base`` is in the base frame (m/s^2); loads are linear in
    payload mass, so a per-sample ``payload_kg`` (N,) costs one extra RNEA.
    """
    n = joint_positions.shape[0]
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    gravity_world = chain.gravity_rotation_world_base @ np.asarray(gravity_base, dtype=float)
    q_pin = pin_configuration(chain, joint_positions)
    loads = _moments_about_axes(chain, chain.pin_model, q_pin, joint_positions, gravity_world)
    if np.any(payload != 0.0):
        unit = _moments_about_axes(
            chain, chain.payload_model, q_pin, joint_positions, gravity_world
        )
        loads = loads + payload[:, None] * unit
    return loads


def _moments_about_axes(
    chain: KinematicChain,
    model: pin.Model,
    q_pin: FloatArray,
    joint_positions: FloatArray,
    gravity_world: FloatArray,
) -> FloatArray:
    model = model.copy()
    model.gravity = pin.Motion(np.asarray(gravity_world, dtype=float), np.zeros(3))
    data = model.createData()
    zero = np.zeros(model.nv)
    # Wrench each chain joint transmits, [f; n] in the joint's own (moved) frame, per sample.
    wrench = np.empty((q_pin.shape[0], chain.n_joints, 6))
    for n, q in enumerate(q_pin):
        pin.rnea(model, data, q, zero, zero)
        for column, j in enumerate(chain.pin_joint_ids):
            wrench[n, column] = data.f[j].vector
    # Re-express about the frame before the joint moves: n_pre = R n + p x (R f), (R, p) = Exp(s q).
    motion = se3_exp(joint_positions[:, :, None] * chain.joint_screws[None, :, :])
    rotation, offset = motion[..., :3, :3], motion[..., :3, 3]
    force = np.einsum("nkij,nkj->nki", rotation, wrench[..., :3])
    moment = np.einsum("nkij,nkj->nki", rotation, wrench[..., 3:]) + np.cross(offset, force)
    out = np.empty((q_pin.shape[0], len(chain.compliance_axes)))
    for a, axis in enumerate(chain.compliance_axes):
        out[:, a] = -moment[:, axis.joint_index] @ axis.axis
    return out
