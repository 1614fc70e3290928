"""Denavit–Hartenberg chains: a robot given by a DH or modified-DH table instead of a URDF, and
the DH / modified-DH table of any calibrated chain (docs/dh.md).

Conventions (lengths m, angles rad; ``Rz``/``Rx`` rotations, ``Tz``/``Tx`` translations):

* classic DH (``"dh"``, Denavit & Hartenberg 1955, as in industrial_calibration), row i maps
  frame i-1 to frame i, joint i moving about / along ``z_{i-1}``::

      T_i(q) = Rz(theta_i + q) · Tz(d_i) · Tx(a_i) · Rx(alpha_i)        (revolute)
      T_i(q) = Rz(theta_i) · Tz(d_i + q) · Tx(a_i) · Rx(alpha_i)        (prismatic)

* modified DH (``"mdh"``, Craig 1986), row i holds ``a_{i-1}, alpha_{i-1}, theta_i, d_i`` and
  joint i moves about / along ``z_i``::

      T_i(q) = Rx(alpha_{i-1}) · Tx(a_{i-1}) · Rz(theta_i + q) · Tz(d_i)  (revolute)

The whole chain is ``X_base_tip(q) = B · T_1(q_1) ··· T_k(q_k) · E`` with a constant base
transform ``B`` (the robot's base frame to DH frame 0) and tool transform ``E``.

:func:`dh_urdf` writes the table as URDF text, so a DH device goes through the same Pinocchio
model and calibration as every other robot; :func:`dh_table_of_chain` goes back: the table
whose forward kinematics equal a (calibrated) chain's exactly, derived from the joint axes as
lines in space.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pinocchio as pin

from solver import lie
from solver.arrays import FloatArray
from solver.errors import ModelError
from solver.model import KinematicChain

DhConvention = Literal["dh", "mdh"]
JointKind = Literal["revolute", "prismatic"]

PARALLEL_TOLERANCE = 1e-9
"""Two joint axes whose directions' cross product is below this are parallel (the common
normal is then not unique; the table picks the one through the previous frame's origin)."""


@dataclass(frozen=True)
class DhRow:
    """One row of a DH table (m, rad). For ``"mdh"`` ``a_m``/``alpha_rad`` are Craig's
    ``a_{i-1}``/``alpha_{i-1}``."""

    name: str
    kind: JointKind
    a_m: float
    alpha_rad: float
    d_m: float
    theta_rad: float
    lower: float
    upper: float


def rot_x(angle_rad: float) -> FloatArray:
    """``Rx(angle)`` as a 4x4 homogeneous transform."""
    out = np.eye(4)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out[1:3, 1:3] = [[c, -s], [s, c]]
    return out


def rot_z(angle_rad: float) -> FloatArray:
    """``Rz(angle)`` as a 4x4 homogeneous transform."""
    out = np.eye(4)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out[0:2, 0:2] = [[c, -s], [s, c]]
    return out


def trans(x_m: float, y_m: float, z_m: float) -> FloatArray:
    """Pure translation as a 4x4 homogeneous transform."""
    out = np.eye(4)
    out[:3, 3] = (x_m, y_m, z_m)
    return out


def dh_row_transform(row: DhRow, convention: DhConvention, q: float) -> FloatArray:
    """``T_i(q)`` of one row (module docstring equations), 4x4, frame i-1 -> frame i."""
    theta = row.theta_rad + (q if row.kind == "revolute" else 0.0)
    d = row.d_m + (q if row.kind == "prismatic" else 0.0)
    if convention == "dh":
        return rot_z(theta) @ trans(0.0, 0.0, d) @ trans(row.a_m, 0.0, 0.0) @ rot_x(row.alpha_rad)
    return rot_x(row.alpha_rad) @ trans(row.a_m, 0.0, 0.0) @ rot_z(theta) @ trans(0.0, 0.0, d)


def dh_forward_kinematics(
    rows: Sequence[DhRow],
    convention: DhConvention,
    base: FloatArray,
    tool: FloatArray,
    joint_positions: FloatArray,
) -> FloatArray:
    """``B · T_1(q_1) ··· T_k(q_k) · E`` for configurations (N, k) -> (N, 4, 4), by the direct
    product of the table (the reference the URDF of :func:`dh_urdf` is tested against)."""
    out = np.empty((joint_positions.shape[0], 4, 4))
    for n, q in enumerate(joint_positions):
        pose = np.array(base, dtype=float)
        for row, value in zip(rows, q, strict=True):
            pose = pose @ dh_row_transform(row, convention, float(value))
        out[n] = pose @ tool
    return out


def joint_origins(
    rows: Sequence[DhRow], convention: DhConvention, base: FloatArray, tool: FloatArray
) -> FloatArray:
    """URDF joint origins of the table, (k+1, 4, 4): entry i places joint i+1 (about / along
    its local z) in the frame after joint i; the last entry places the tip.

    The motion of a row commutes with the constant part next to it (``Rz(q)`` with ``Rz(θ)
    Tz(d)``), so classic DH puts ``Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i)`` after joint i and modified
    DH puts ``Rx(α_{i-1}) Tx(a_{i-1})`` before it and ``Rz(θ_i) Tz(d_i)`` after it.
    """
    origins = []
    after = np.array(base, dtype=float)  # constant transform since the last joint
    for row in rows:
        if convention == "dh":
            origins.append(after)
            after = dh_row_transform(row, "dh", 0.0)
        else:
            origins.append(after @ rot_x(row.alpha_rad) @ trans(row.a_m, 0.0, 0.0))
            after = rot_z(row.theta_rad) @ trans(0.0, 0.0, row.d_m)
    origins.append(after @ tool)
    return np.array(origins)


def dh_urdf(
    robot_name: str,
    rows: Sequence[DhRow],
    convention: DhConvention,
    base: FloatArray,
    tool: FloatArray,
    *,
    base_frame: str,
    tip_frame: str,
) -> str:
    """A URDF whose forward kinematics from ``base_frame`` to ``tip_frame`` are the table's:
    one link per joint (``<joint>_link``), joint axes along local z, limits from the rows.
    Inertias are absent (a DH table has none), so no gravity torque and no compliance."""
    if not rows:
        raise ModelError("a DH table needs at least one joint")
    names = [row.name for row in rows]
    links = [base_frame, *[f"{name}_link" for name in names], tip_frame]
    if len(set(names) | set(links)) != len(names) + len(links):
        raise ModelError(
            f"DH joint names {names} and frames {base_frame!r}, {tip_frame!r} must be distinct"
        )
    origins = joint_origins(rows, convention, base, tool)
    parts = [f'<?xml version="1.0"?>\n<robot name="{robot_name}">']
    parts += [f'  <link name="{link}"/>' for link in links]
    for i, row in enumerate(rows):
        parts.append(
            f'  <joint name="{row.name}" type="{row.kind}">\n'
            f'    <parent link="{links[i]}"/>\n    <child link="{links[i + 1]}"/>\n'
            f"    {_origin_xml(origins[i])}\n"
            '    <axis xyz="0 0 1"/>\n'
            f'    <limit lower="{row.lower!r}" upper="{row.upper!r}" effort="1000" '
            'velocity="10"/>\n  </joint>'
        )
    parts.append(
        f'  <joint name="{tip_frame}_joint" type="fixed">\n'
        f'    <parent link="{links[-2]}"/>\n    <child link="{tip_frame}"/>\n'
        f"    {_origin_xml(origins[-1])}\n  </joint>"
    )
    parts.append("</robot>\n")
    return "\n".join(parts)


def _origin_xml(transform: FloatArray) -> str:
    xyz = " ".join(repr(float(v)) for v in transform[:3, 3])
    rpy = " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(transform[:3, :3]))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


# --- the table of a chain -----------------------------------------------------------------------


@dataclass(frozen=True)
class DhTableOfChain:
    """A DH / modified-DH table with base and tool transforms (4x4) reproducing a chain."""

    convention: DhConvention
    rows: tuple[DhRow, ...]
    base: FloatArray
    tool: FloatArray


def dh_table_of_chain(
    joint_names: Sequence[str],
    joint_frames: FloatArray,
    joint_screws: FloatArray,
    tip: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    convention: DhConvention,
) -> DhTableOfChain:
    """The table whose forward kinematics equal a serial chain's.

    ``joint_frames`` (k, 4, 4): each joint's frame in the base frame at q = 0; ``joint_screws``
    (k, 6): ``[v; w]`` in those frames (unit); ``tip`` (4, 4) the tip at q = 0. Every joint
    moves about (along) a line in space; DH frame axes ``z`` are those lines (with the joint's
    sign, so q keeps its meaning), ``x`` their common normals. A prismatic joint's line goes
    through its frame's origin. Parallel axes have no unique common normal: the one through the
    foot of the previous frame is taken (d = 0 there). Exact up to rounding: a joint rotates
    everything after it about the same line in both descriptions.
    """
    k = len(joint_names)
    revolute = np.linalg.norm(joint_screws[:, 3:], axis=1) > 0.5
    directions = np.array(
        [
            frame[:3, :3] @ (screw[3:] if rev else screw[:3])
            for frame, screw, rev in zip(joint_frames, joint_screws, revolute, strict=True)
        ]
    )
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = joint_frames[:, :3, 3].copy()
    # Foot points of the common normal of axes (i, i+1): on axis i (MDH frame i) and on axis
    # i+1 (DH frame i); the last joint's normal is chosen to pass the tip's origin.
    near = tip[:3, 3] if k == 1 else points[0]
    feet_on: list[FloatArray] = []
    feet_next: list[FloatArray] = []
    normals: list[FloatArray] = []
    for i in range(k):
        if i + 1 < k:
            foot, other, normal = _common_normal(
                points[i], directions[i], points[i + 1], directions[i + 1], near
            )
        else:
            foot = _closest_on_line(points[i], directions[i], tip[:3, 3])
            other = foot
            normal = _perpendicular(directions[i], normals[-1] if normals else tip[:3, 0])
        feet_on.append(foot)
        feet_next.append(other)
        normals.append(normal)
        near = other
    rows = []
    kinds: list[JointKind] = ["revolute" if r else "prismatic" for r in revolute]
    if convention == "mdh":
        frames = [_frame(feet_on[i], directions[i], normals[i]) for i in range(k)]
        base = frames[0]
        previous = frames[0]
        for i in range(k):
            a, alpha, theta, d = (
                (0.0, 0.0, 0.0, 0.0)
                if i == 0
                else _mdh_parameters(lie.inverse(previous) @ frames[i])
            )
            rows.append(DhRow(joint_names[i], kinds[i], a, alpha, d, theta, lower[i], upper[i]))
            previous = frames[i]
        tool = lie.inverse(frames[-1]) @ tip
    else:
        # DH frame 0 carries joint 1's axis; frame i (i < k) joint i+1's axis with x along the
        # common normal (i, i+1); frame k is frame k-1 turned with joint k (a = alpha = 0).
        frame0 = _frame(feet_on[0], directions[0], normals[0])
        frames = [frame0] + [
            _frame(feet_next[i], directions[i + 1], normals[i]) for i in range(k - 1)
        ]
        frames.append(frames[-1])
        base = frame0
        for i in range(k):
            d, theta, a, alpha = _dh_parameters(lie.inverse(frames[i]) @ frames[i + 1])
            rows.append(DhRow(joint_names[i], kinds[i], a, alpha, d, theta, lower[i], upper[i]))
        tool = lie.inverse(frames[-1]) @ tip
    return DhTableOfChain(convention, tuple(rows), base, tool)


def dh_table_of_links(
    chain: KinematicChain, links: FloatArray, convention: DhConvention
) -> DhTableOfChain:
    """:func:`dh_table_of_chain` of ``chain`` with link placements ``links`` (k+1, 4, 4), e.g.
    calibrated ones: the table whose forward kinematics are ``L_1 Exp(s_1 q_1) ··· L_{k+1}``."""
    frames = np.empty((chain.n_joints, 4, 4))
    placement = np.eye(4)
    for i in range(chain.n_joints):
        placement = placement @ links[i]
        frames[i] = placement
    return dh_table_of_chain(
        chain.joint_names,
        frames,
        chain.joint_screws,
        placement @ links[-1],
        chain.lower_limits,
        chain.upper_limits,
        convention,
    )


def _closest_on_line(point: FloatArray, direction: FloatArray, target: FloatArray) -> FloatArray:
    return np.asarray(point + direction * float(direction @ (target - point)), dtype=float)


def _perpendicular(direction: FloatArray, hint: FloatArray) -> FloatArray:
    """Unit vector perpendicular to ``direction``, as close to ``hint`` as possible."""
    candidate = hint - direction * float(direction @ hint)
    if np.linalg.norm(candidate) < 1e-6:
        candidate = np.cross(direction, np.eye(3)[int(np.argmin(np.abs(direction)))])
    return np.asarray(candidate / np.linalg.norm(candidate), dtype=float)


def _common_normal(
    p1: FloatArray, u1: FloatArray, p2: FloatArray, u2: FloatArray, near: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Feet of the common normal of two lines (on line 1, on line 2) and its unit direction
    (from line 1 to line 2; ``u1 × u2`` when the lines meet)."""
    cross = np.cross(u1, u2)
    if np.linalg.norm(cross) < PARALLEL_TOLERANCE:
        foot = _closest_on_line(p1, u1, near)
        other = _closest_on_line(p2, u2, foot)
        gap = other - foot
        if np.linalg.norm(gap) < 1e-12:
            return foot, other, _perpendicular(u1, np.eye(3)[0])
        return foot, other, gap / np.linalg.norm(gap)
    # Solve p1 + s u1 + t n = p2 + r u2 with n = u1 × u2 (normalised): a 3x3 linear system.
    normal = cross / np.linalg.norm(cross)
    s, r, t = np.linalg.solve(np.column_stack([u1, -u2, normal]), p2 - p1)
    foot = p1 + s * u1
    other = p2 + r * u2
    if t < 0.0:
        normal = -normal
    return foot, other, normal


def _frame(origin: FloatArray, z_axis: FloatArray, x_axis: FloatArray) -> FloatArray:
    out = np.eye(4)
    x = x_axis - z_axis * float(z_axis @ x_axis)
    x /= np.linalg.norm(x)
    out[:3, 0], out[:3, 1], out[:3, 2] = x, np.cross(z_axis, x), z_axis
    out[:3, 3] = origin
    return out


def _mdh_parameters(transform: FloatArray) -> tuple[float, float, float, float]:
    """``(a, alpha, theta, d)`` of ``Rx(alpha) Tx(a) Rz(theta) Tz(d)`` = ``transform``."""
    rotation, position = transform[:3, :3], transform[:3, 3]
    alpha = float(np.arctan2(-rotation[1, 2], rotation[2, 2]))
    theta = float(np.arctan2(-rotation[0, 1], rotation[0, 0]))
    d = float(position[2] * np.cos(alpha) - position[1] * np.sin(alpha))
    return float(position[0]), alpha, theta, d


def _dh_parameters(transform: FloatArray) -> tuple[float, float, float, float]:
    """``(d, theta, a, alpha)`` of ``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` = ``transform``."""
    rotation, position = transform[:3, :3], transform[:3, 3]
    theta = float(np.arctan2(rotation[1, 0], rotation[0, 0]))
    alpha = float(np.arctan2(rotation[2, 1], rotation[2, 2]))
    a = float(position[0] * np.cos(theta) + position[1] * np.sin(theta))
    return float(position[2]), theta, a, alpha
