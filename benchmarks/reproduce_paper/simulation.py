"""The simulated true robot (an LRU2-like Jaco2 with the paper's effects) and its calibration
recording (paper §V-A)."""

from __future__ import annotations

import dataclasses

import numpy as np

from benchmarks.reproduce_paper.settings import StudySettings
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import PoseDataset
from schemas.robots import RobotDescription, load_robot
from service.app import simulate as scenarios
from solver import lie
from solver.arrays import BoolArray, FloatArray, IntArray
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import KinematicChain, gravity_loads
from solver.ranking import RandomEffects, UncertaintyModel
from solver.simulate import gross_error_twists, simulate_recording

BACKLASH_STD_RAD = (3.0e-4, 1.5e-3)
"""σ of the rotation about the joint axis, first and last joint frame (linear in between)."""
OFF_AXIS_FRACTION = 0.3
"""σ about the two other axes of a joint frame, relative to the joint-axis σ (bearing play)."""
CAMERA_NOISE = (0.3, 0.2)
"""Camera noise σ: translation mm, rotation deg, per axis of the end-effector frame."""


def true_perturbation_std(chain: KinematicChain) -> FloatArray:
    """σ of ξ_i (k, 6), [v; w] in each joint frame (right after L_i, Eq. 7), m and rad.

    Rotational only (the paper's Fig. 4b finding): about the joint axis (the local axis of the
    joint screw, a coordinate axis for URDF joints) σ grows linearly over ``BACKLASH_STD_RAD``
    toward the end effector; about the two other axes ``OFF_AXIS_FRACTION`` of it. Diagonal, so
    the paper's diagonal model can represent it exactly.
    """
    k = chain.n_joints
    backlash = np.linspace(*BACKLASH_STD_RAD, k)
    std = np.zeros((k, 6))
    std[:, 3:] = OFF_AXIS_FRACTION * backlash[:, None]
    axis = np.argmax(np.abs(chain.joint_screws[:, 3:]), axis=1)
    std[np.arange(k), 3 + axis] = backlash
    return std


@dataclasses.dataclass(frozen=True, eq=False)
class TrueRobot:
    """The simulated robot the study executes on: true geometry, compliance, σ of ξ (k, 6)."""

    chain: KinematicChain
    params: ChainParameters
    perturbation_std: FloatArray
    noise_std: FloatArray
    gravity_base: FloatArray
    outlier_fraction: float = 0.0
    outlier_size: tuple[float, float] = (0.0, 0.0)  # translation m, rotation rad

    def loads(self, joint_positions: FloatArray) -> FloatArray:
        return gravity_loads(self.chain, joint_positions, gravity_base=self.gravity_base)

    def mean_pose(self, joint_positions: FloatArray) -> FloatArray:
        """Pose (N, 4, 4) of the marker in the camera frame with ξ = 0."""
        return forward_kinematics(
            self.chain, self.params, joint_positions, self.loads(joint_positions)
        )

    def execute(
        self, joint_positions: FloatArray, n_executions: int, rng: np.random.Generator
    ) -> FloatArray:
        """Reached poses (M, n_executions, 4, 4), camera frame: each of the M configurations
        (M, k) rad run ``n_executions`` times with fresh ξ_i ~ N(0, Σ_i) (Eq. 7)."""
        m, k = joint_positions.shape
        q = np.repeat(joint_positions, n_executions, axis=0)
        xi = rng.normal(size=(q.shape[0], k, 6)) * self.perturbation_std
        pose = forward_kinematics(self.chain, self.params, q, self.loads(q), perturbations=xi)
        return pose.reshape(m, n_executions, 4, 4)

    def detect_static(
        self, joint_positions: FloatArray, n_detections: int, rng: np.random.Generator
    ) -> tuple[FloatArray, BoolArray]:
        """Camera detections (M, n_detections, 4, 4) of the marker while each of the M
        configurations (M, k) rad stands still, and which detections are gross errors (M, n).

        The arm does not move between the detections of one configuration, so one ξ_i draw per
        configuration (Eq. 7) and fresh camera noise ε per detection; the detector fails
        (a gross error as in the recording) with ``outlier_fraction`` per detection.
        """
        m, k = joint_positions.shape
        xi = rng.normal(size=(m, k, 6)) * self.perturbation_std
        loads = self.loads(joint_positions)
        static = forward_kinematics(
            self.chain, self.params, joint_positions, loads, perturbations=xi
        )
        noise = rng.normal(size=(m, n_detections, 6)) * self.noise_std
        detected = static[:, None] @ lie.se3_exp(noise)
        gross = rng.random((m, n_detections)) < self.outlier_fraction
        twist = gross_error_twists(int(gross.sum()), *self.outlier_size, rng)
        detected[gross] = detected[gross] @ lie.se3_exp(twist)
        return detected, gross

    def effects(self) -> RandomEffects:
        return RandomEffects.from_std(self.perturbation_std, self.noise_std)

    def uncertainty_model(self) -> UncertaintyModel:
        """The oracle: true Σ_i on the true geometry (Eq. 12)."""
        return UncertaintyModel.build(self.chain, self.params, self.effects(), self.gravity_base)


@dataclasses.dataclass(frozen=True, eq=False)
class Recording:
    """The calibration recording and the robot that produced it."""

    seed: int
    robot: RobotDescription
    dataset: PoseDataset
    true_robot: TrueRobot
    outlier_rows: IntArray  # 0-based rows with injected gross errors


def simulate_study_recording(settings: StudySettings, seed: int | None = None) -> Recording:
    """``settings.n_samples`` camera measurements of the true robot (paper §V-A).

    The true robot depends on the seed only (its parameters are drawn first), so recordings of
    different sizes with one seed measure the same robot.
    """
    seed = settings.seed if seed is None else seed
    robot = load_robot("kinova")
    scn = scenarios.scenario(
        robot,
        n_samples=settings.n_samples,
        seed=seed,
        effects=scenarios.PAPER_EFFECTS,
        noise_translation_mm=CAMERA_NOISE[0],
        noise_rotation_deg=CAMERA_NOISE[1],
    )
    spec = dataclasses.replace(scn.spec, perturbation_sigma=true_perturbation_std(scn.chain))
    recording = simulate_recording(scn.chain, spec)
    true_robot = TrueRobot(
        chain=scn.chain,
        params=recording.true_params,
        perturbation_std=recording.perturbation_sigma,
        noise_std=recording.noise_sigma,
        gravity_base=np.asarray(spec.gravity_base, dtype=float),
        outlier_fraction=spec.outlier_fraction,
        outlier_size=(spec.outlier_translation_m, spec.outlier_rotation_rad),
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=True)
    return Recording(seed, robot, dataset, true_robot, recording.outliers)


def calibration_options(
    recording: Recording, settings: StudySettings, *, heldout: bool = True
) -> CalibrationOptions:
    """The paper's model: base-plate flex axes at joint 1, diagonal covariances, 10 splits, and
    the paper's outlier rule (§V-A: 2σ per residual component), not kincal's default model rule
    — Table II reproduces the paper's procedure."""
    return CalibrationOptions(
        outlier_rule="sigma",
        outlier_sigma=2.0,
        virtual_axes_at=[recording.true_robot.chain.joint_names[0]],
        covariance="diag",
        seeds=list(settings.splits),
        heldout=heldout,
    )


def kept_rows(result: CalibrationResult) -> IntArray:
    """0-based rows the calibration used (after outlier removal)."""
    return np.array(result.outliers.kept_indices(), dtype=np.intp)
