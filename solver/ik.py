"""Candidate configurations for a target end-effector pose: distinct IK solutions (paper §IV-D).

The paper ranks "possible pre-grasp configurations" that reach the same pose. Given a target
pose of the end effector (marker/tool) in the MEASUREMENT frame — the frame of
``forward_kinematics`` at the calibrated parameters, i.e. what ``kincal predict`` returns — this
module finds distinct joint configurations that reach it on the CALIBRATED chain, gravity-
dependent compliance included:

1. Global search with Pinocchio (damped least-squares CLIK, random restarts within the joint
   limits) on the nominal URDF model. Its target is the requested pose with the calibrated
   measurement frame and tool offset removed: these are the large corrections (camera pose,
   marker offset); the rest (mm / mrad link corrections, compliance) leaves the IK branches
   unchanged. Pinocchio's C++ FK and Jacobians make each restart cheap, and its rigid model
   cannot express gravity-dependent compliance anyway, hence:
2. Polish every seed on the calibrated chain with Newton steps (all seeds at once, numpy):
   residual ``r = Log(X(q)^-1 X_target)`` in the end-effector frame, joint Jacobian from
   :func:`solver.kinematics.evaluate_chain`, gravity loads re-evaluated every step (the
   Jacobian omits dτ/dq, a ~1e-2 relative term, so convergence is linear but fast). Minimum-norm
   steps, so redundant arms stay near their seed.
3. Keep solutions within the joint limits, wrap continuous joints to [-π, π), drop duplicates
   (max joint difference below a tolerance, wrap-around for continuous joints).

Candidates beyond the IK branches: rotations of the target about an end-effector axis the task
ignores (``free_axis``, e.g. z when W's yaw weight is 0) and, for redundant arms (k > 6),
samples along the null space of the joint Jacobian around found solutions. Deterministic for a
given ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from solver import lie
from solver.arrays import BoolArray, FloatArray
from solver.errors import SolverError
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.kinematics import ChainParameters, evaluate_chain
from solver.model import STANDARD_GRAVITY_BASE, KinematicChain, pin_configuration

_LIMIT_TOLERANCE = 1e-9


@dataclass(frozen=True)
class IKOptions:
    """Search settings.

    ``n_candidates``: distinct solutions wanted (fewer may exist). ``n_restarts``: Pinocchio
    restarts (default 8 per wanted candidate). ``free_axis`` (3,) in the end-effector frame, or
    None: the target may be rotated about it; ``n_free_rotations`` evenly spaced angles
    (including 0). ``null_space_step_rad``: size of the random null-space moves (k > 6).
    ``duplicate_tolerance_rad``: solutions closer than this in every joint are one solution.
    ``tolerance``: required residual norm ‖Log(X^-1 X_target)‖ (m and rad).
    """

    n_candidates: int = 16
    n_restarts: int | None = None
    seed: int = 0
    free_axis: tuple[float, float, float] | None = None
    n_free_rotations: int = 12
    null_space_step_rad: float = 0.6
    duplicate_tolerance_rad: float = 1e-3
    tolerance: float = 1e-10
    clik_iterations: int = 200
    newton_iterations: int = 40


@dataclass(frozen=True)
class IKCandidate:
    """One distinct IK solution.

    ``joint_positions`` (k,) rad; ``free_rotation_rad``: rotation of the target about the free
    axis this solution reaches; ``target_pose`` (4, 4) that rotated target (measurement frame);
    ``translation_error_m`` / ``rotation_error_rad``: remaining pose error on the calibrated
    chain; ``source``: "restart" or "null_space".
    """

    joint_positions: FloatArray
    free_rotation_rad: float
    target_pose: FloatArray
    translation_error_m: float
    rotation_error_rad: float
    source: str


def ik_candidates(
    chain: KinematicChain,
    params: ChainParameters,
    target_pose: FloatArray,
    options: IKOptions = IKOptions(),
    *,
    gravity_base: FloatArray = STANDARD_GRAVITY_BASE,
    payload_kg: float = 0.0,
) -> list[IKCandidate]:
    """Distinct configurations reaching ``target_pose`` (4, 4, measurement frame) on the
    calibrated chain; at most ``options.n_candidates``, in order of discovery."""
    target = np.asarray(target_pose, dtype=float)
    if target.shape != (4, 4) or not np.all(np.isfinite(target)):
        raise SolverError("target pose must be a finite 4x4 transform")
    if options.n_candidates < 1:
        raise SolverError("n_candidates must be at least 1")
    rng = np.random.default_rng(options.seed)
    angles, targets = _free_rotations(target, options)
    solver = _Polisher(chain, params, np.asarray(gravity_base, dtype=float), payload_kg, options)
    redundant = chain.n_joints > 6
    n_restarts = options.n_restarts or max(8 * options.n_candidates, 16)
    if redundant:
        n_restarts = max(4, n_restarts // 4)
    seeds, which = _pinocchio_seeds(chain, params, targets, n_restarts, rng, options)
    found = _Collector(chain, options)
    if seeds.size:
        q, ok, err = solver.polish(seeds, targets[which])
        # Redundant arms: keep room for null-space samples around the branches found.
        limit = max(1, options.n_candidates // 2) if redundant else options.n_candidates
        found.add(q[ok], which[ok], err[ok], "restart", limit=limit)
    if redundant and len(found):
        want = 4 * options.n_candidates
        base = rng.integers(0, len(found), size=want)
        start = np.array(found.joint_positions)[base]
        which = np.array(found.target_index)[base]
        step = solver.null_space_steps(start, rng)
        q, ok, err = solver.polish(start + step, targets[which])
        found.add(q[ok], which[ok], err[ok], "null_space")
    return [
        IKCandidate(
            joint_positions=q,
            free_rotation_rad=float(angles[t]),
            target_pose=targets[t],
            translation_error_m=float(e[0]),
            rotation_error_rad=float(e[1]),
            source=source,
        )
        for q, t, e, source in found.items()
    ]


def continuous_joints(chain: KinematicChain) -> BoolArray:
    """(k,) True for joints without position limits (Pinocchio stores them as cos/sin)."""
    return np.array([chain.pin_model.joints[j].nq == 2 for j in chain.pin_joint_ids])


def joint_distance(chain: KinematicChain, a: FloatArray, b: FloatArray) -> FloatArray:
    """Max absolute joint difference (..., ) between (..., k) arrays; continuous joints wrap."""
    diff = np.asarray(a) - np.asarray(b)
    wrapped = np.mod(diff + np.pi, 2.0 * np.pi) - np.pi
    return np.abs(np.where(continuous_joints(chain), wrapped, diff)).max(axis=-1)


def _free_rotations(target: FloatArray, options: IKOptions) -> tuple[FloatArray, FloatArray]:
    if options.free_axis is None or options.n_free_rotations <= 1:
        return np.zeros(1), target[None]
    axis = np.asarray(options.free_axis, dtype=float)
    norm = np.linalg.norm(axis)
    if not norm > 0.0:
        raise SolverError("free axis must be a non-zero vector")
    angles = 2.0 * np.pi * np.arange(options.n_free_rotations) / options.n_free_rotations
    twist = np.zeros((angles.size, 6))
    twist[:, 3:] = angles[:, None] * (axis / norm)
    return angles, target @ lie.se3_exp(twist)


def _pinocchio_seeds(
    chain: KinematicChain,
    params: ChainParameters,
    targets: FloatArray,
    n_restarts: int,
    rng: np.random.Generator,
    options: IKOptions,
) -> tuple[FloatArray, NDArray[np.intp]]:
    """Nominal-model CLIK from random starts; returns converged (M, k) and their target index."""
    model = chain.pin_model
    data = model.createData()
    tip = model.getFrameId(chain.tip_frame)
    base = model.getFrameId(chain.base_frame)
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    world_base = data.oMf[base].homogeneous.copy()
    # Requested pose -> nominal tip frame in Pinocchio's world: remove measurement frame and tool.
    frame = params.links[0] @ lie.inverse(chain.nominal_links[0])
    tool = lie.inverse(chain.nominal_links[-1]) @ params.links[-1]
    goals = world_base @ lie.inverse(frame) @ targets @ lie.inverse(tool)
    continuous = continuous_joints(chain)
    lower, upper = chain.lower_limits, chain.upper_limits
    out, which = [], []
    for attempt in range(n_restarts):
        t = attempt % targets.shape[0]
        q0 = rng.uniform(lower, upper)
        q = _clik(chain, data, tip, pin.SE3(goals[t]), q0, continuous, options.clik_iterations)
        if q is not None:
            out.append(q)
            which.append(t)
    return np.array(out).reshape(-1, chain.n_joints), np.array(which, dtype=np.intp)


def _clik(
    chain: KinematicChain,
    data: pin.Data,
    tip: int,
    goal: pin.SE3,
    q0: FloatArray,
    continuous: BoolArray,
    iterations: int,
) -> FloatArray | None:
    """Damped least-squares CLIK (Pinocchio's classic loop) with joint-limit clamping.

    Works on Pinocchio's configuration vector (continuous joints as cos/sin); gives up when the
    error has not improved for 40 iterations (a limit or singularity traps the restart).
    """
    model = chain.pin_model
    index_q = np.array([model.joints[j].idx_q for j in chain.pin_joint_ids])
    bounded = ~continuous
    lower, upper = chain.lower_limits[bounded], chain.upper_limits[bounded]
    q_pin = pin_configuration(chain, q0[None])[0]
    best, best_iteration = np.inf, 0
    for iteration in range(iterations):
        pin.forwardKinematics(model, data, q_pin)
        pin.updateFramePlacement(model, data, tip)
        error_frame = data.oMf[tip].actInv(goal)
        error = pin.log6(error_frame).vector
        norm = float(np.linalg.norm(error))
        if norm < 1e-8:
            return _chain_angles(chain, q_pin, index_q, continuous)
        if norm < 0.9 * best:
            best, best_iteration = norm, iteration
        elif iteration - best_iteration > 40:
            return None
        jacobian = pin.Jlog6(error_frame) @ pin.computeFrameJacobian(
            model, data, q_pin, tip, pin.LOCAL
        )
        damping = 1e-6 + 1e-2 * min(norm * norm, 1.0)
        step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping * np.eye(6), error)
        step_norm = np.linalg.norm(step)
        if step_norm > 0.5:  # trust region: far from a solution the linearisation is poor
            step *= 0.5 / step_norm
        q_pin = pin.integrate(model, q_pin, step)
        q_pin[index_q[bounded]] = np.clip(q_pin[index_q[bounded]], lower, upper)
    return None


def _chain_angles(
    chain: KinematicChain, q_pin: FloatArray, index_q: NDArray[np.intp], continuous: BoolArray
) -> FloatArray:
    """Chain joint positions (k,) from a Pinocchio configuration (cos/sin -> angle)."""
    out = q_pin[index_q].copy()
    out[continuous] = np.arctan2(q_pin[index_q[continuous] + 1], q_pin[index_q[continuous]])
    return out


class _Polisher:
    """Newton on the calibrated chain (compliance included), many seeds at once."""

    def __init__(
        self,
        chain: KinematicChain,
        params: ChainParameters,
        gravity_base: FloatArray,
        payload_kg: float,
        options: IKOptions,
    ) -> None:
        self.chain, self.params, self.options = chain, params, options
        self.gravity = StaticGravityModel.from_chain(chain)
        self.gravity_base, self.payload_kg = gravity_base, payload_kg
        self.continuous = continuous_joints(chain)

    def _jacobian_and_residual(
        self, q: FloatArray, targets: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Joint Jacobian (M, 6, k) of the EE-frame pose, residual (M, 6), pose (M, 4, 4)."""
        chain, params = self.chain, self.params
        loads = static_gravity_loads(
            self.gravity, q, gravity_base=self.gravity_base, payload_kg=self.payload_kg
        )
        evaluation = evaluate_chain(chain, params, q, loads)
        residual = lie.se3_log(lie.inverse(evaluation.pose) @ targets)  # (M, 6) EE frame
        deflection = loads * params.compliance_rad_per_nm
        jacobian = np.empty((q.shape[0], 6, chain.n_joints))
        for i in range(chain.n_joints):
            # dX/dq_i = X · J_i Ad(V_i) s_i: V_i (virtual flex before joint i) is a rotation.
            rotation = np.broadcast_to(np.eye(3), (q.shape[0], 3, 3))
            for a, axis in enumerate(chain.compliance_axes):
                if axis.joint_index == i and not axis.is_joint_axis:
                    rotation = rotation @ lie.so3_exp(deflection[:, a, None] * axis.axis)
            screw = chain.joint_screws[i]
            moved = np.concatenate([rotation @ screw[:3], rotation @ screw[3:]], axis=1)
            jacobian[:, :, i] = np.einsum("mab,mb->ma", evaluation.link_jacobians[:, i], moved)
        return jacobian, residual, evaluation.pose

    def polish(
        self, seeds: FloatArray, targets: FloatArray
    ) -> tuple[FloatArray, BoolArray, FloatArray]:
        """Refined (M, k), which ones converged within the limits, and their errors (M, 2):
        translation m and rotation rad in the measurement frame."""
        q = seeds.copy()
        for _ in range(self.options.newton_iterations):
            jacobian, residual, _ = self._jacobian_and_residual(q, targets)
            if np.abs(residual).max() < 0.1 * self.options.tolerance:
                break
            q = q + _min_norm_step(jacobian, residual)
        q = np.where(self.continuous, np.mod(q + np.pi, 2.0 * np.pi) - np.pi, q)
        _, residual, pose = self._jacobian_and_residual(q, targets)
        inside = np.all(
            (q >= self.chain.lower_limits - _LIMIT_TOLERANCE)
            & (q <= self.chain.upper_limits + _LIMIT_TOLERANCE),
            axis=1,
        )
        converged = np.linalg.norm(residual, axis=1) < self.options.tolerance
        errors = np.stack(
            [
                np.linalg.norm(pose[:, :3, 3] - targets[:, :3, 3], axis=1),
                lie.rotation_angle_rad(np.swapaxes(pose[:, :3, :3], 1, 2) @ targets[:, :3, :3]),
            ],
            axis=1,
        )
        return q, inside & converged, errors

    def null_space_steps(self, q: FloatArray, rng: np.random.Generator) -> FloatArray:
        """Random moves (M, k) along the joint Jacobian's null space at solutions q."""
        jacobian, _, _ = self._jacobian_and_residual(q, np.broadcast_to(np.eye(4), (len(q), 4, 4)))
        _, _, vt = np.linalg.svd(jacobian)
        null = vt[:, 6:, :]  # (M, k-6, k)
        amount = rng.uniform(-1.0, 1.0, size=null.shape[:2]) * self.options.null_space_step_rad
        return np.einsum("mr,mrk->mk", amount, null)


def _min_norm_step(jacobian: FloatArray, residual: FloatArray) -> FloatArray:
    """``J^T (J J^T + λ I)^-1 r`` per seed with a tiny λ: Gauss–Newton, minimum norm."""
    gram = jacobian @ np.swapaxes(jacobian, 1, 2) + 1e-12 * np.eye(6)
    return np.einsum("mak,ma->mk", jacobian, np.linalg.solve(gram, residual[..., None])[..., 0])


class _Collector:
    """Accepted solutions without duplicates, in discovery order."""

    def __init__(self, chain: KinematicChain, options: IKOptions) -> None:
        self.chain, self.tolerance = chain, options.duplicate_tolerance_rad
        self.limit = options.n_candidates
        self.joint_positions: list[FloatArray] = []
        self.target_index: list[int] = []
        self.errors: list[FloatArray] = []
        self.sources: list[str] = []

    def __len__(self) -> int:
        return len(self.joint_positions)

    def add(
        self,
        q: FloatArray,
        which: NDArray[np.intp],
        errors: FloatArray,
        source: str,
        limit: int | None = None,
    ) -> None:
        for row in range(q.shape[0]):
            if len(self) >= min(self.limit, limit or self.limit):
                return
            if (
                self.joint_positions
                and joint_distance(self.chain, np.array(self.joint_positions), q[row]).min()
                < self.tolerance
            ):
                continue
            self.joint_positions.append(q[row])
            self.target_index.append(int(which[row]))
            self.errors.append(errors[row])
            self.sources.append(source)

    def items(self) -> list[tuple[FloatArray, int, FloatArray, str]]:
        return list(
            zip(self.joint_positions, self.target_index, self.errors, self.sources, strict=True)
        )
