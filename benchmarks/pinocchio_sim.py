"""A simulator that shares no formula with the estimator: recordings straight from Pinocchio.

kincal's own simulator (:mod:`solver.simulate`) draws poses with the library's product of
exponentials, so a convention both got wrong would pass every test that uses both. This one
touches only Pinocchio and numpy: each random perturbation ξ_i (DESIGN.md §2: right after the
joint placement L_i, before the joint motion) is put into ``model.jointPlacements`` for that
sample, joint compliance deflects the angle by c·τ with τ = −``computeGeneralizedGravity``,
the camera and the marker are fixed unknown transforms, measurement noise and detector failures
(gross errors) act in the marker frame. The true end-effector covariance of a configuration is
built from finite differences of Pinocchio's forward kinematics, not from adjoints.

It writes the public dataset format (joint columns named after the URDF joints, ``x,y,z`` and
``qx,qy,qz,qw``), so a recording goes through ``kincal calibrate`` like a user's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pinocchio as pin
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from solver.arrays import FloatArray


@dataclass(frozen=True)
class PinocchioRobot:
    """The movable joints between ``base`` and ``tip`` of a URDF, other joints locked."""

    model: pin.Model
    joint_names: tuple[str, ...]
    joint_ids: tuple[int, ...]
    base_id: int
    tip_id: int

    @classmethod
    def from_urdf(cls, urdf_xml: str, base: str, tip: str) -> PinocchioRobot:
        full = pin.buildModelFromXML(urdf_xml)
        tip_joint = full.frames[full.getFrameId(tip)].parentJoint
        base_joint = full.frames[full.getFrameId(base)].parentJoint
        path = list(full.supports[tip_joint])
        chain = [j for j in path[path.index(base_joint) + 1 :] if full.joints[j].nv == 1]
        locked = [j for j in range(1, full.njoints) if j not in chain]
        model = pin.buildReducedModel(full, locked, pin.neutral(full)) if locked else full
        names = tuple(full.names[j] for j in chain)
        return cls(
            model,
            names,
            tuple(model.getJointId(n) for n in names),
            model.getFrameId(base),
            model.getFrameId(tip),
        )

    def sample_q(self, n: int, rng: np.random.Generator) -> FloatArray:
        """Joint angles (n, k) uniform within the limits ([-π, π] for continuous joints)."""
        lower, upper = [], []
        for j in self.joint_ids:
            joint = self.model.joints[j]
            lo, hi = -np.pi, np.pi
            if joint.nq == 1:
                lo = max(lo, self.model.lowerPositionLimit[joint.idx_q])
                hi = min(hi, self.model.upperPositionLimit[joint.idx_q])
            lower.append(lo)
            upper.append(hi)
        return rng.uniform(lower, upper, size=(n, len(self.joint_ids)))

    def configuration(self, angle_rad: FloatArray) -> FloatArray:
        """Pinocchio's configuration vector for joint angles (k,): (cos, sin) for continuous
        joints."""
        q = pin.neutral(self.model)
        for angle, j in zip(angle_rad, self.joint_ids, strict=True):
            joint = self.model.joints[j]
            if joint.nq == 2:
                q[joint.idx_q : joint.idx_q + 2] = np.cos(angle), np.sin(angle)
            else:
                q[joint.idx_q] = angle
        return q

    def tip_in_base(self, model: pin.Model, data: pin.Data, angle_rad: FloatArray) -> pin.SE3:
        pin.framesForwardKinematics(model, data, self.configuration(angle_rad))
        return data.oMf[self.base_id].inverse() * data.oMf[self.tip_id]

    def gravity_torque_nm(self, angle_rad: FloatArray) -> FloatArray:
        """τ (k,): the torque gravity exerts on each joint (N·m), −g(q) of Pinocchio's RNEA."""
        data = self.model.createData()
        tau = pin.computeGeneralizedGravity(self.model, data, self.configuration(angle_rad))
        return -np.array([tau[self.model.joints[j].idx_v] for j in self.joint_ids])


@dataclass(frozen=True)
class TrueRobot:
    """What the simulated robot really is: per joint a geometric error of its placement
    (twist, m and rad), the std of its random perturbation (k, 6) [v; w], joint compliance
    (rad/N·m), the camera (robot base in the measurement frame) and the marker (in the tip
    frame), the noise std (6,) in the marker frame."""

    placement_error: FloatArray
    perturbation_std: FloatArray
    compliance_rad_per_nm: FloatArray
    camera: pin.SE3
    marker: pin.SE3
    noise_std: FloatArray = field(default_factory=lambda: np.array([5e-5] * 3 + [1e-4] * 3))


def draw_true_robot(
    robot: PinocchioRobot,
    rng: np.random.Generator,
    *,
    perturbation_std: FloatArray,
    compliance_rad_per_nm: FloatArray | None = None,
    geometry_m: float = 1e-3,
    geometry_rad: float = 2e-3,
) -> TrueRobot:
    k = len(robot.joint_ids)
    error = np.hstack([rng.normal(0, geometry_m, (k, 3)), rng.normal(0, geometry_rad, (k, 3))])
    camera = pin.SE3(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-1, 1, 3))
    marker = pin.SE3(
        Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(), rng.normal(0, 0.05, 3)
    )
    return TrueRobot(
        error,
        np.asarray(perturbation_std, dtype=float),
        np.zeros(k) if compliance_rad_per_nm is None else np.asarray(compliance_rad_per_nm),
        camera,
        marker,
    )


def true_pose(
    robot: PinocchioRobot,
    truth: TrueRobot,
    q: FloatArray,
    xi: FloatArray,
    model: pin.Model | None = None,
) -> pin.SE3:
    """The marker in the measurement frame at reading ``q`` with perturbations ``xi`` (k, 6)."""
    model = model or robot.model.copy()
    for i, j in enumerate(robot.joint_ids):
        placement = robot.model.jointPlacements[j]
        model.jointPlacements[j] = placement * pin.exp6(truth.placement_error[i]) * pin.exp6(xi[i])
    q_link = q + truth.compliance_rad_per_nm * robot.gravity_torque_nm(q)
    return truth.camera * robot.tip_in_base(model, model.createData(), q_link) * truth.marker


@dataclass(frozen=True)
class Recording:
    joint_positions: FloatArray  # (N, k)
    measured: list[pin.SE3]
    gross: NDArray[np.intp]  # rows with a detector failure


def simulate(
    robot: PinocchioRobot,
    truth: TrueRobot,
    n: int,
    rng: np.random.Generator,
    *,
    gross_fraction: float = 0.0,
    gross_translation_m: float = 5e-3,
    gross_rotation_rad: float = np.radians(10.0),
) -> Recording:
    """``n`` measured poses; a ``gross_fraction`` of them are detector failures (a rotation of
    ``gross_rotation_rad`` about a random axis and a translation of ``gross_translation_m`` in a
    random direction, in the marker frame)."""
    q = robot.sample_q(n, rng)
    model = robot.model.copy()
    poses = []
    for row in q:
        xi = rng.normal(size=truth.perturbation_std.shape) * truth.perturbation_std
        noise = rng.normal(size=6) * truth.noise_std
        poses.append(true_pose(robot, truth, row, xi, model) * pin.exp6(noise))
    gross = np.sort(rng.choice(n, size=round(gross_fraction * n), replace=False))
    for i in gross:
        axis = rng.normal(size=(2, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        twist = np.concatenate([gross_translation_m * axis[0], gross_rotation_rad * axis[1]])
        poses[i] = poses[i] * pin.exp6(twist)
    return Recording(q, poses, gross)


def true_ee_covariance(
    robot: PinocchioRobot, truth: TrueRobot, q: FloatArray, step: float = 1e-6
) -> FloatArray:
    """Σ_E(q) without noise (6, 6), marker frame [v; w]: Σ_i D_i diag(σ_i²) D_iᵀ with D_i the
    central finite difference of Log(X(0)⁻¹ X(ξ_i)) over each component of ξ_i."""
    k = len(robot.joint_ids)
    model = robot.model.copy()
    nominal = true_pose(robot, truth, q, np.zeros((k, 6)), model)
    covariance = np.zeros((6, 6))
    for i in range(k):
        columns = np.zeros((6, 6))
        for a in range(6):
            xi = np.zeros((k, 6))
            xi[i, a] = step
            plus = pin.log6(nominal.inverse() * true_pose(robot, truth, q, xi, model)).vector
            xi[i, a] = -step
            minus = pin.log6(nominal.inverse() * true_pose(robot, truth, q, xi, model)).vector
            columns[:, a] = (plus - minus) / (2 * step)
        covariance += columns @ np.diag(truth.perturbation_std[i] ** 2) @ columns.T
    return covariance


def write_dataset(robot: PinocchioRobot, recording: Recording, path: Path) -> Path:
    """The recording in kincal's public dataset format (CSV)."""
    table = pd.DataFrame(recording.joint_positions, columns=list(robot.joint_names))
    xyz = np.array([p.translation for p in recording.measured])
    quaternion = Rotation.from_matrix(np.array([p.rotation for p in recording.measured])).as_quat()
    for c, name in enumerate("xyz"):
        table[name] = xyz[:, c]
    for c, name in enumerate(("qx", "qy", "qz", "qw")):
        table[name] = quaternion[:, c]
    table.to_csv(path, index=False, float_format="%.12g")
    return path


def write_configurations(robot: PinocchioRobot, q: FloatArray, path: Path) -> Path:
    pd.DataFrame(q, columns=list(robot.joint_names)).to_csv(path, index=False, float_format="%.12g")
    return path
