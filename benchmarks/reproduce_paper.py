"""Reproduction of the paper's experiments (§V) on a simulated LRU2-like Jaco2 (issue 4, item 5).

The study, with everything random seeded:

* **True robot.** Kinova Jaco2 (j2s6s200) of :func:`service.scenarios.scenario` with the paper's
  effects: per-link geometric errors, elastic joints 2 and 3, a flexing base plate (two virtual
  compliant axes at joint 1), an unknown camera frame, an unknown marker, 0.3 mm / 0.2 deg camera
  noise and 10 % gross outliers. Random perturbations ξ_i ~ N(0, Σ_i) in every joint frame
  (Eq. 7) are rotational, as the paper found: backlash/friction about the joint axis with σ
  growing from 0.3 mrad (joint 1) to 1.5 mrad (joint 6), plus bearing play about the two other
  axes at 30 % of that (:func:`true_perturbation_std`).
* **Recording.** 154 configurations seen by the camera (paper §V-A). "Ours" is
  :func:`service.pipeline.calibrate` on this recording alone: 2-sigma outlier removal, the
  deterministic fit (Eq. 8–10), the diagonal covariance calibration (§IV-C, the product's
  default estimator) and 10 held-out 90/10 splits with seeds 1..10.
* **Table II.** Mean held-out error per split before calibration (nominal robot with fitted
  camera and marker), after ours, and after the GP baseline of ref. [13]
  (:func:`solver.gp_baseline.gp_calibration_method`), all on identical splits.
* **Fig. 4b.** Calibrated σ per frame (each split's training set and all kept samples) next to
  the true σ.
* **Manipulation experiment (§V-C).** In each run a pre-grasp pose is drawn in the calibrated
  workspace (a reachable pose: the calibrated model's pose at a random configuration; a new one
  is drawn if fewer than 10 approach configurations exist, as the rover would re-position);
  :func:`service.ranking.rank_target` finds 10 distinct configurations that reach it on the
  calibrated model (IK branches and rotations about the end-effector z axis, which the paper's
  weights W = diag(0.4, 0.4, 0, 0.1, 0.1, 0) ignore) and scores them (Eq. 22–23). Each is
  executed many times on the true robot with fresh ξ draws; the docking error of an execution is
  the x-y translation of the reached pose in the target's end-effector frame (noise-free: the
  physical error, not a camera's view of it). Per configuration the mean over executions is the
  observed error. Three scores pick the lowest- and highest-uncertainty configuration of a run:
  ours (calibrated covariances), the GP baseline (predictive variances of ref. [13] on diag Σ_E,
  scored with Eq. 22–23) and the oracle (the true covariances on the true geometry).
* **Table III.** Per run, Pearson and Spearman correlation between each score and the observed
  error over the 10 configurations.
* **The docking task's own score.** The same candidates and executions, every method re-scored
  with the product's task-point score of the quantity the experiment measures (Var(x) + Var(y)
  of the end-effector origin, :data:`DOCKING_TASK`) instead of the paper's W, which adds rad² of
  roll and pitch to m² of x and y.

* **Protocol variant: the camera noise measured separately (§V-B).** The paper measured Σ_n on
  5 static configurations × 10 detections, only to validate the calibrated Σ_n. The variant
  simulates that experiment on the true robot (one ξ draw per standing configuration, fresh
  camera noise and detector failures per detection; :func:`measure_camera_noise`), gives the
  measured Σ_n to the product's calibration as known (``noise_std``; also the full sample
  covariance via ``noise_covariance`` and, as a limit, the true Σ_n) and re-scores the same
  candidates; reported next to the default, which stays the product's behaviour.

Acceptance (issue 4): ours reduces the mean task error by at least 80 % of the oracle's
reduction, and our score correlates with the observed error better than the GP's. Both are
judged on 95 % bootstrap intervals ("met" only if the whole interval clears the bar), with the
docking task's own score and with the paper's W.

Why more than the paper's 10 runs and more than one recording: the observed error of a
configuration is its random scatter plus the calibrated model's remaining systematic error there
(unknown to every score), and the true task σ of the 10 approaches of one pre-grasp pose differ
by only ~20 %, so the lowest-vs-highest comparison on 10 runs is mostly chance. The study runs
``--runs`` runs (default 150) on each of ``--recordings`` independent recordings (default 4,
seeds 1, 2, …) of the same true robot; the first recording is the paper's (Table II, Fig. 4b,
the paper-sized table of its first 10 runs) and the verdicts use all runs with a two-level
bootstrap (recordings, then runs within them). Ablations on the first recording's runs re-score
the same candidates with other covariance models (the paper's moment estimator, larger
recordings, the true Σ on the calibrated geometry) to show where the gap to the oracle comes from.

Usage: ``python benchmarks/reproduce_paper.py [--out out/reproduce_paper] [--figures DIR]
[--runs 150] [--recordings 4] [--executions 500] [--quick]``. Writes ``reproduce_paper.md`` to
``--out`` and the figures ``reproduce_paper_sigma.png`` (Fig. 4b) and
``reproduce_paper_runs.png`` (Fig. 6) to ``--figures`` (default: ``--out``). The committed
report is ``python benchmarks/reproduce_paper.py --out docs``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray
from scipy import stats

import solver  # noqa: F401  (BLAS defaults before numpy work)
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import PoseDataset
from schemas.ranking import (
    RankingOptions,
    RankingResult,
    TargetPose,
    TargetRankingRequest,
    TaskPointWeights,
)
from service import pipeline, result_json, scenarios
from service import ranking as service_ranking
from service.robots import RobotDescription, load_robot
from solver import lie
from solver.errors import KincalError
from solver.evaluation import cross_validate, split_indices
from solver.gp_baseline import GPErrorModel, fit_gp_error_model, gp_calibration_method, gp_scores
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import KinematicChain, gravity_loads, sample_configurations
from solver.ranking import RandomEffects, TaskMetric, UncertaintyModel, score_configurations
from solver.simulate import gross_error_twists, simulate_recording

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

BACKLASH_STD_RAD = (3.0e-4, 1.5e-3)
"""σ of the rotation about the joint axis, first and last joint frame (linear in between)."""
OFF_AXIS_FRACTION = 0.3
"""σ about the two other axes of a joint frame, relative to the joint-axis σ (bearing play)."""
CAMERA_NOISE = (0.3, 0.2)
"""Camera noise σ: translation mm, rotation deg, per axis of the end-effector frame."""
METHODS = ("ours", "gp", "oracle")
LABELS = {"ours": "Ours", "gp": "GP [13]", "oracle": "Oracle (true Σ)"}
PAPER_RUNS = 10
MIN_REDUCTION_SHARE = 0.8
MAX_TARGET_ATTEMPTS = 50
NOISE_CONFIGURATIONS = 5
NOISE_DETECTIONS = 10
"""Paper §V-B: the camera noise measured on 5 static configurations × 10 detections."""
NOISE_SCREEN_MAD = 5.0
"""Detections beyond this many robust σ in any component are detector failures (§V-B)."""

PAPER_TABLE_II: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "before": (
        (8.40, 6.28, 7.46, 7.49, 8.65, 7.33, 8.15, 7.36, 7.93, 7.13),
        (4.88, 5.61, 4.22, 5.91, 5.68, 5.14, 5.42, 5.47, 3.73, 5.62),
    ),
    "calibrated": (
        (7.10, 4.95, 5.91, 7.38, 7.44, 7.71, 5.57, 6.31, 7.62, 6.48),
        (5.85, 4.06, 2.70, 4.97, 4.13, 4.92, 4.80, 4.30, 3.30, 3.89),
    ),
    "gp": (
        (11.50, 10.46, 9.36, 9.81, 10.25, 9.18, 9.90, 10.9, 10.52, 8.53),
        (5.41, 4.82, 3.27, 4.80, 5.21, 4.73, 5.20, 4.33, 3.11, 4.62),
    ),
}
"""Paper Table II, mm and deg per seed 1..10 (LRU2 Jaco2), for comparison only."""
PAPER_TABLE_III = {
    "ours": (0.00, -0.07, 0.66, -0.05, 0.16, -0.04, 0.68, 0.28, 0.19, 0.67),
    "gp": (-0.04, 0.48, 0.60, -0.14, -0.05, 0.35, -0.09, 0.47, -0.36, -0.09),
}
"""Paper Table III: correlation of the Eq. (23) score with the observed x-y error per run."""
PAPER_SELECTION_MM = (2.495, 4.133)
"""Paper §V-C: mean x-y error of the lowest- and highest-uncertainty approaches (10 runs)."""
PAPER_WINS = 7
TABLE_II_LABELS = {"before": "Init.", "calibrated": "Cal. Ours", "gp": "Cal. GP"}
DOCKING_TASK = RankingOptions(
    weights=TaskPointWeights(point_m=(0.0, 0.0, 0.0), axis_weights=(1.0, 1.0, 0.0))
)
"""The score of the quantity the manipulation experiment measures: Var(x) + Var(y) of the
end-effector origin (the docking point) in the end-effector frame, m² — the product's task-point
score (issue 4 item 1, ``kincal rank --task-point 0,0,0 --task-weights 1,1,0``). The paper's W
instead adds 0.1² rad² of roll and pitch variance to 0.4² m² of x and y variance."""


@dataclasses.dataclass(frozen=True)
class StudySettings:
    """Sizes and seeds. ``n_recordings`` recordings (seeds ``seed``, ``seed + 1``, …) of
    ``n_samples`` each; per recording ``n_runs`` manipulation runs of ``n_approaches``
    configurations, each executed ``n_executions`` times; ``splits`` are the held-out seeds of the
    first recording (Table II, Fig. 4b); ``ablation_samples`` are the sizes of larger recordings
    of the same robot whose covariances re-score the first recording's candidates."""

    n_samples: int = 154
    seed: int = 1
    n_recordings: int = 4
    n_runs: int = 150
    n_approaches: int = 10
    n_executions: int = 500
    splits: tuple[int, ...] = tuple(range(1, 11))
    split_covariances: bool = True
    gp_table: bool = True
    paper_estimator_ablation: bool = True
    ablation_samples: tuple[int, ...] = (500, 2000)
    bootstrap: int = 2000

    @classmethod
    def quick(cls) -> StudySettings:
        """A reduced study for the test: one recording, 2 splits, 40 runs, no GP Table II column
        (tested in tests/service/test_rank_cli.py) and no costly ablations."""
        return cls(
            n_recordings=1,
            n_runs=40,
            n_executions=200,
            splits=(1, 2),
            split_covariances=False,
            gp_table=False,
            paper_estimator_ablation=False,
            ablation_samples=(),
            bootstrap=1000,
        )


# --- the true robot ----------------------------------------------------------------------------


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
    outlier_rows: IndexArray  # 0-based rows with injected gross errors


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
    dataset = scenarios.recording_dataset(recording, scn.chain, position_only=False)
    return Recording(seed, robot, dataset, true_robot, recording.outliers)


def calibration_options(
    recording: Recording, settings: StudySettings, *, heldout: bool = True
) -> CalibrationOptions:
    """The paper's model: base-plate flex axes at joint 1, diagonal covariances, 10 splits."""
    return CalibrationOptions(
        virtual_axes_at=[recording.true_robot.chain.joint_names[0]],
        covariance="diag",
        seeds=list(settings.splits),
        heldout=heldout,
    )


def kept_rows(result: CalibrationResult) -> IndexArray:
    """0-based rows the calibration used (after outlier removal)."""
    return np.array(result.outliers.kept_indices(), dtype=np.intp)


# --- Table II and Fig. 4b ----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TableII:
    """Mean held-out error per split: ``errors[method][seed] = (mm, deg)``."""

    seeds: tuple[int, ...]
    errors: dict[str, dict[int, tuple[float, float]]]

    def mean(self, method: str) -> tuple[float, float]:
        values = np.array([self.errors[method][s] for s in self.seeds])
        return float(values[:, 0].mean()), float(values[:, 1].mean())


def table_ii(result: CalibrationResult, recording: Recording, *, with_gp: bool = True) -> TableII:
    """Before / ours from the result's held-out splits; the GP baseline on the same splits."""
    if result.evaluation is None:
        raise ValueError("Table II needs a calibration result with held-out splits")
    errors: dict[str, dict[int, tuple[float, float]]] = {}
    for split in result.evaluation.splits:
        errors.setdefault(split.method, {})[split.seed] = (
            split.translation_mm,
            float(split.rotation_deg or 0.0),
        )
    if with_gp:
        options = result.options
        data = result_json.prepare(
            result_json.chain_for(recording.robot, options), recording.dataset, options
        )
        used = kept_rows(result)
        for gp_split in cross_validate(
            data.measured_pose[used],
            {
                "gp": gp_calibration_method(
                    data.chain,
                    data.joint_positions[used],
                    data.measured_pose[used],
                    data.loads_nm[used],
                    position_only=data.position_only,
                    baseline_options=pipeline.fit_options(
                        options, baseline=True, n_links=data.chain.n_links
                    ),
                )
            },
            position_only=data.position_only,
            seeds=options.seeds,
            train_fraction=options.train_fraction,
        ):
            errors.setdefault("gp", {})[gp_split.seed] = (
                gp_split.translation_mm,
                float(gp_split.rotation_deg or 0.0),
            )
    return TableII(tuple(result.options.seeds), errors)


def covariance_std(result: CalibrationResult) -> FloatArray:
    """Calibrated σ (k + 1, 6): joint frames in chain order, then the noise; m and rad."""
    if result.covariance is None:
        raise ValueError("the calibration result has no covariances")
    by_name = {frame.name: frame.std for frame in result.covariance.frames}
    rows = [by_name.get(name, (0.0,) * 6) for name in result.robot.joint_names]
    return np.array([*rows, result.covariance.noise.std], dtype=float)


def split_covariance_std(result: CalibrationResult, recording: Recording) -> FloatArray:
    """Paper Fig. 4b: σ (n_splits, k + 1, 6) calibrated on each split's training set.

    The same product call as the full calibration, on the training rows of the kept samples
    (outliers already removed, so no second removal; no nested held-out splits).
    """
    used = kept_rows(result)
    options = result.options.model_copy(update={"heldout": False, "outlier_sigma": None})
    out = []
    for seed in result.options.seeds:
        train, _ = split_indices(used.size, seed, result.options.train_fraction)
        subset = recording.dataset.subset(used[train])
        out.append(covariance_std(pipeline.calibrate(subset, recording.robot, options)))
    return np.array(out)


# --- the manipulation experiment (§V-C) --------------------------------------------------------


def docking_error_xy_m(target_pose: FloatArray, reached_pose: FloatArray) -> FloatArray:
    """Paper §V-C task error: ‖(x, y)‖ of the reached end-effector origin in the target's
    end-effector frame, ``X_target^-1 · X_reached``; poses (..., 4, 4), result (...) in m."""
    relative = lie.inverse(target_pose) @ reached_pose
    return np.asarray(np.linalg.norm(relative[..., :2, 3], axis=-1), dtype=float)


@dataclasses.dataclass(frozen=True)
class ApproachRun:
    """One run: M approach configurations for one pre-grasp pose.

    ``scores[method]`` (M,) in m² (Eq. 22–23); ``error_mm`` (M,) mean docking error over the
    executions; ``scatter_mm`` (M,) mean x-y distance of the executions from the
    configuration's own mean reached pose (the part random effects cause); ``bias_mm`` (M,)
    docking error of that mean pose (the calibrated model's remaining systematic error);
    ``true_xy_std_mm`` (M,) the true √(σ_x² + σ_y²) of the end effector (Eq. 12, true Σ).
    """

    recording: int
    run: int
    attempts: int
    joint_positions: FloatArray
    scores: dict[str, FloatArray]
    error_mm: FloatArray
    scatter_mm: FloatArray
    bias_mm: FloatArray
    true_xy_std_mm: FloatArray

    def pick(self, method: str) -> tuple[int, int]:
        """Indices of the lowest- and highest-score configuration (first on ties)."""
        score = self.scores[method]
        return int(np.argmin(score)), int(np.argmax(score))


def gp_uncertainty_model(result: CalibrationResult, recording: Recording) -> GPErrorModel:
    """The GP baseline trained on the kept recording: residuals of the "before" model."""
    kept = recording.dataset.subset(kept_rows(result))
    residuals = result_json.residuals(result, kept, baseline=True)
    return fit_gp_error_model(kept.joint_positions, residuals)


@dataclasses.dataclass(frozen=True, eq=False)
class Scorers:
    """What scores a recording's approach configurations: ours (the calibrated covariances),
    the GP baseline's predictive variances and the oracle (true Σ on the true geometry)."""

    ours: UncertaintyModel
    gp: GPErrorModel
    oracle: UncertaintyModel

    def scores(self, joint_positions: FloatArray, metric: TaskMetric) -> dict[str, FloatArray]:
        """Eq. (22–23) score (M,) of every method for configurations (M, k) rad."""
        return {
            "ours": score_configurations(self.ours, joint_positions, metric).score,
            "gp": gp_scores(self.gp, joint_positions, metric).score,
            "oracle": score_configurations(self.oracle, joint_positions, metric).score,
        }


def _pregrasp_candidates(
    result: CalibrationResult,
    chain: KinematicChain,
    settings: StudySettings,
    model: UncertaintyModel,
    rng: np.random.Generator,
) -> tuple[FloatArray, RankingResult] | None:
    """One pre-grasp pose (camera frame) and its ranked approaches, or None if too few."""
    reference = sample_configurations(chain, 1, rng)
    target = result_json.predict_poses(result, reference)[0]
    request = TargetRankingRequest(
        target=TargetPose(
            position_m=tuple(target[:3, 3].tolist()),
            quaternion_xyzw=tuple(lie.matrix_to_quaternion_xyzw(target[:3, :3]).tolist()),
        ),
        n_candidates=settings.n_approaches,
        seed=int(rng.integers(2**31)),
        options=RankingOptions(),  # the paper's W, Σ_n excluded
    )
    try:
        ranking = service_ranking.rank_target(result, request, model=model)
    except KincalError:
        return None
    if len(ranking.ranking) < settings.n_approaches:
        return None
    return target, ranking


def approach_run(
    run: int,
    result: CalibrationResult,
    recording: Recording,
    settings: StudySettings,
    *,
    scorers: Scorers,
    metric: TaskMetric,
) -> ApproachRun:
    """Draw a reachable pre-grasp pose, rank its approach configurations, execute them."""
    rng = np.random.default_rng([recording.seed, 1, run])
    chain = recording.true_robot.chain
    found, attempts = None, 0
    while found is None:
        if attempts == MAX_TARGET_ATTEMPTS:
            raise RuntimeError(
                f"run {run}: no pre-grasp pose with {settings.n_approaches} approaches"
            )
        attempts += 1
        found = _pregrasp_candidates(result, chain, settings, scorers.ours, rng)
    target, ranking = found
    entries = sorted(ranking.ranking, key=lambda entry: entry.index)
    q = np.array([entry.joint_positions_rad for entry in entries], dtype=float)
    axis = np.asarray(ranking.free_axis or (0.0, 0.0, 1.0), dtype=float)
    turn = np.zeros((len(entries), 6))
    turn[:, 3:] = np.array([e.free_rotation_rad or 0.0 for e in entries])[:, None] * axis
    targets = target @ lie.se3_exp(turn)  # the rotated target each configuration reaches
    robot = recording.true_robot
    executions = np.random.default_rng([recording.seed, 2, run])
    reached = robot.execute(q, settings.n_executions, executions)
    mean_pose = robot.mean_pose(q)
    truth = score_configurations(scorers.oracle, q, metric)
    return ApproachRun(
        recording=recording.seed,
        run=run,
        attempts=attempts,
        joint_positions=q,
        scores=scorers.scores(q, metric),
        error_mm=1e3 * docking_error_xy_m(targets[:, None], reached).mean(axis=1),
        scatter_mm=1e3 * docking_error_xy_m(mean_pose[:, None], reached).mean(axis=1),
        bias_mm=1e3 * docking_error_xy_m(targets, mean_pose),
        true_xy_std_mm=1e3 * np.sqrt(truth.ee_variance[:, :2].sum(axis=1)),
    )


# --- statistics --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Selection:
    """Lowest- vs highest-score choice of one method over runs (paper §V-C results).

    ``low_mm``/``high_mm``: mean over runs of the observed error of the chosen configurations;
    ``reduction_pct`` = 100·(1 − low/high); ``wins``: runs where the low pick had the lower
    error; ``pearson``/``spearman`` (runs,): correlation of score and observed error per run
    (Table III); ``*_ci``: 95 % bootstrap intervals over runs.
    """

    method: str
    low_mm: float
    high_mm: float
    reduction_pct: float
    reduction_ci: tuple[float, float]
    wins: int
    pearson: FloatArray
    spearman: FloatArray
    pearson_ci: tuple[float, float]

    @property
    def mean_pearson(self) -> float:
        return float(np.nanmean(self.pearson))


@dataclasses.dataclass(frozen=True)
class Comparison:
    """The acceptance quantities on a set of runs, with bootstrap intervals.

    ``share_of_oracle``: our reduction / the oracle's, on the observed error; ``random_share``:
    the same on the random part of the error only (``scatter``); ``pearson_gap``: mean Pearson
    r of ours minus the GP's.
    """

    n_runs: int
    selections: dict[str, Selection]
    share_of_oracle: float
    share_ci: tuple[float, float]
    pearson_gap: float
    pearson_gap_ci: tuple[float, float]
    scatter: dict[str, Selection]
    random_share: float
    random_share_ci: tuple[float, float]

    @property
    def reduction_verdict(self) -> str:
        """Acceptance: the whole 95 % interval of the share at or above 80 % (:func:`_verdict`)."""
        return _verdict(self.share_ci, MIN_REDUCTION_SHARE)

    @property
    def correlation_verdict(self) -> str:
        """Acceptance: the whole 95 % interval of the Pearson gap (ours − GP) above zero."""
        return _verdict(self.pearson_gap_ci, 0.0, strict=True)


def _verdict(interval: tuple[float, float], bar: float, *, strict: bool = False) -> str:
    """ "met" if the whole interval clears the bar, "not met" if it lies below it, otherwise
    "not demonstrated" (the runs cannot tell at 95 %)."""
    low, high = interval
    if low > bar or (low == bar and not strict):
        return "met"
    if high < bar or (high == bar and strict):
        return "not met"
    return "not demonstrated"


def _picked_errors(runs: Sequence[ApproachRun], method: str, field: str) -> FloatArray:
    """(runs, 2): observed error (``field``) of the lowest- and highest-score pick."""
    out = []
    for run in runs:
        low, high = run.pick(method)
        values = getattr(run, field)
        out.append((values[low], values[high]))
    return np.array(out)


def _correlation(kind: Callable[..., object], x: FloatArray, y: FloatArray) -> float:
    if np.ptp(x) == 0.0 or np.ptp(y) == 0.0:
        return float("nan")
    return float(kind(x, y).statistic)  # type: ignore[attr-defined]


def _reduction_pct(picked: FloatArray) -> FloatArray:
    """100·(1 − mean low / mean high) over axis −2 of (..., runs, 2)."""
    mean = picked.mean(axis=-2)
    return np.asarray(100.0 * (1.0 - mean[..., 0] / mean[..., 1]), dtype=float)


def _interval(samples: FloatArray) -> tuple[float, float]:
    low, high = np.nanpercentile(samples, [2.5, 97.5])
    return float(low), float(high)


def bootstrap_indices(groups: Sequence[int], n_boot: int, rng: np.random.Generator) -> IndexArray:
    """(n_boot, n) resampled run indices: recordings (``groups``, one label per run) with
    replacement, then runs with replacement within each drawn recording (two-level bootstrap).
    One group is the ordinary bootstrap. Groups must be of equal size."""
    labels = np.asarray(groups)
    members = [np.flatnonzero(labels == g) for g in dict.fromkeys(labels.tolist())]
    size = members[0].size
    if any(m.size != size for m in members):
        raise ValueError("two-level bootstrap needs recordings with equal numbers of runs")
    table = np.array(members)  # (G, size)
    chosen = rng.integers(0, len(members), size=(n_boot, len(members)))
    within = rng.integers(0, size, size=(n_boot, len(members), size))
    return np.asarray(table[chosen[:, :, None], within].reshape(n_boot, -1), dtype=np.intp)


def _selection(
    runs: Sequence[ApproachRun], method: str, field: str, resample: IndexArray
) -> tuple[Selection, FloatArray, FloatArray]:
    """A method's selection on ``field``, its bootstrap reductions and mean Pearson r."""
    picked = _picked_errors(runs, method, field)
    values = [getattr(run, field) for run in runs]
    r = np.array(
        [
            _correlation(stats.pearsonr, run.scores[method], v)
            for run, v in zip(runs, values, strict=True)
        ]
    )
    rho = np.array(
        [
            _correlation(stats.spearmanr, run.scores[method], v)
            for run, v in zip(runs, values, strict=True)
        ]
    )
    boot = _reduction_pct(picked[resample])
    boot_r = np.nanmean(r[resample], axis=1)
    selection = Selection(
        method=method,
        low_mm=float(picked[:, 0].mean()),
        high_mm=float(picked[:, 1].mean()),
        reduction_pct=float(_reduction_pct(picked)),
        reduction_ci=_interval(boot),
        wins=int(np.sum(picked[:, 0] < picked[:, 1])),
        pearson=r,
        spearman=rho,
        pearson_ci=_interval(boot_r),
    )
    return selection, boot, boot_r


def compare(
    runs: Sequence[ApproachRun],
    *,
    bootstrap: int = 2000,
    seed: int = 0,
    groups: Sequence[int] | None = None,
) -> Comparison:
    """Selections of every method, the share of the oracle's reduction ours reaches and the
    Pearson gap to the GP, each with a percentile bootstrap over runs (two-level over
    recordings and runs if ``groups`` labels the recording of every run)."""
    rng = np.random.default_rng(seed)
    resample = bootstrap_indices(groups or [0] * len(runs), bootstrap, rng)
    chosen: dict[str, Selection] = {}
    scatter: dict[str, Selection] = {}
    boot: dict[str, FloatArray] = {}
    boot_r: dict[str, FloatArray] = {}
    for method in METHODS:
        chosen[method], boot[method], boot_r[method] = _selection(
            runs, method, "error_mm", resample
        )
        scatter[method], boot[f"{method} random"], _ = _selection(
            runs, method, "scatter_mm", resample
        )
    with np.errstate(divide="ignore", invalid="ignore"):
        share_boot = boot["ours"] / boot["oracle"]
        random_boot = boot["ours random"] / boot["oracle random"]
    return Comparison(
        n_runs=len(runs),
        selections=chosen,
        share_of_oracle=chosen["ours"].reduction_pct / chosen["oracle"].reduction_pct,
        share_ci=_interval(share_boot),
        pearson_gap=chosen["ours"].mean_pearson - chosen["gp"].mean_pearson,
        pearson_gap_ci=_interval(boot_r["ours"] - boot_r["gp"]),
        scatter=scatter,
        random_share=scatter["ours"].reduction_pct / scatter["oracle"].reduction_pct,
        random_share_ci=_interval(random_boot),
    )


# --- ablations: where the gap to the oracle comes from -----------------------------------------


@dataclasses.dataclass(frozen=True)
class Ablation:
    """The first recording's candidates re-scored with another covariance model in place of
    ours; ``comparison`` as in :func:`compare` (its "ours" is this model) with the paper's W,
    ``docking`` with the docking task's own score."""

    label: str
    comparison: Comparison
    docking: Comparison


def rescored(
    runs: Sequence[ApproachRun], model: UncertaintyModel, metric: TaskMetric
) -> list[ApproachRun]:
    """The runs with "ours" replaced by ``model``'s Eq. (22–23) scores of the same candidates."""
    return [
        dataclasses.replace(
            run,
            scores={
                **run.scores,
                "ours": score_configurations(model, run.joint_positions, metric).score,
            },
        )
        for run in runs
    ]


def ablation_models(
    settings: StudySettings, first: RecordingStudy, *, echo: Callable[[str], None] = print
) -> dict[str, UncertaintyModel]:
    """Covariance models to compare with ours on the first recording's candidates.

    The paper's estimator (moment matching solved by PGD, Eq. 14–15) on the same data; the
    product's estimator with rotational perturbations only (``covariance_axes='rotation'``) on
    the same data and on larger recordings of the same true robot; and the true Σ on the
    calibrated geometry (what a perfect covariance calibration would give). The product's
    estimator told Σ_n is the known-noise variant (:class:`KnownNoise`).
    """
    recording = first.recording
    options = calibration_options(recording, settings, heldout=False)
    models: dict[str, UncertaintyModel] = {}
    if settings.paper_estimator_ablation:
        paper = options.model_copy(
            update={"covariance_estimator": "moment", "covariance_solver": "pgd"}
        )
        models[f"paper estimator (moment matching + PGD), N = {settings.n_samples}"] = (
            service_ranking.uncertainty_model(
                pipeline.calibrate(recording.dataset, recording.robot, paper)
            )
        )
        echo("  ablation: paper estimator")
    rotation = options.model_copy(update={"covariance_axes": "rotation"})
    label = "ours, rotational perturbations only (`--covariance-axes rotation`)"
    models[f"{label}, N = {settings.n_samples}"] = service_ranking.uncertainty_model(
        pipeline.calibrate(recording.dataset, recording.robot, rotation)
    )
    echo("  ablation: rotational perturbations only")
    for n in settings.ablation_samples:
        larger = simulate_study_recording(
            dataclasses.replace(settings, n_samples=n), recording.seed
        )
        calibrated = pipeline.calibrate(larger.dataset, larger.robot, options)
        models[f"ours, N = {n} samples of the same robot"] = service_ranking.uncertainty_model(
            calibrated
        )
        echo(f"  ablation: N = {n}")
    ours = first.scorers.ours
    models["true Σ on the calibrated geometry"] = UncertaintyModel.build(
        ours.chain, ours.params, recording.true_robot.effects(), ours.gravity_base
    )
    return models


# --- protocol variant: the camera noise measured separately (paper §V-B) ----------------------


@dataclasses.dataclass(frozen=True, eq=False)
class NoiseExperiment:
    """Paper §V-B on the true robot: ``NOISE_CONFIGURATIONS`` static configurations, each seen
    ``NOISE_DETECTIONS`` times.

    ``deviations`` (M, n, 6): each detection's pose in the end-effector frame of its
    configuration's mean detection, [v; w] m and rad, minus the configuration's mean over the
    kept detections; ``kept`` (M, n): not screened as a gross detector error; ``gross`` (M, n):
    the simulated gross errors (truth, for the report); ``covariance`` (6, 6): the sample
    covariance of the kept deviations (degrees of freedom: kept detections minus one mean per
    configuration).
    """

    joint_positions: FloatArray
    deviations: FloatArray
    kept: BoolArray
    gross: BoolArray
    covariance: FloatArray

    @property
    def std(self) -> FloatArray:
        """σ per pose component (6,), m and rad: what the paper reports and what the
        calibration is told (``noise_std``, the paper's diagonal model)."""
        return np.asarray(np.sqrt(np.diag(self.covariance)), dtype=float)


def _ee_deviations(detected: FloatArray, reference: FloatArray) -> FloatArray:
    """Log(X_reference^-1 · X_detected) (M, n, 6): detections (M, n, 4, 4) in the end-effector
    frame of a per-configuration reference (M, 4, 4) (DESIGN.md §2 residual convention)."""
    return np.asarray(lie.se3_log(lie.inverse(reference)[:, None] @ detected), dtype=float)


def measure_camera_noise(robot: TrueRobot, seed: int) -> NoiseExperiment:
    """Σ_n as the paper measured it (§V-B): subtract each configuration's mean detection,
    then the sample covariance of the pose components over all detections.

    The paper does not mention detector failures in this experiment; the simulated detector
    fails as often as in the recording, and a failure (10 deg / 5 mm against σ = 0.2 deg /
    0.3 mm per component) is 17–50 σ away, so the detections beyond ``NOISE_SCREEN_MAD`` robust
    σ (1.4826 · median absolute deviation from the configuration's median, per component) are
    screened first. The reference pose is the
    configuration's component-wise median detection, which a failure cannot drag.
    """
    rng = np.random.default_rng([seed, 3])
    q = sample_configurations(robot.chain, NOISE_CONFIGURATIONS, rng)
    detected, gross = robot.detect_static(q, NOISE_DETECTIONS, rng)
    first = detected[:, 0]
    median = np.median(_ee_deviations(detected, first), axis=1)
    reference = first @ lie.se3_exp(median)
    deviation = _ee_deviations(detected, reference)
    centred = deviation - np.median(deviation, axis=1, keepdims=True)
    robust_std = 1.4826 * np.median(np.abs(centred).reshape(-1, 6), axis=0)
    kept = np.all(np.abs(centred) <= NOISE_SCREEN_MAD * robust_std, axis=2)
    counts = kept.sum(axis=1)
    mean = (deviation * kept[..., None]).sum(axis=1) / np.maximum(counts, 1)[:, None]
    deviations = deviation - mean[:, None]
    used = deviations[kept]
    dof = used.shape[0] - int(np.count_nonzero(counts))
    return NoiseExperiment(q, deviations, kept, gross, used.T @ used / dof)


KNOWN_NOISE_VARIANTS = {
    "measured": "the measured σ per pose component (the paper's §V-B numbers; `noise_std`)",
    "measured_full": "the measured full sample covariance (`noise_covariance`)",
    "true": "the true Σ_n (the limit of a perfect noise experiment)",
}
"""How the calibration is told Σ_n; "measured" is the protocol variant, the others bound it."""


def known_noise_options(
    recording: Recording, experiment: NoiseExperiment, settings: StudySettings, variant: str
) -> CalibrationOptions:
    """The product's calibration options with Σ_n known (``KNOWN_NOISE_VARIANTS``)."""
    known: dict[str, object] = {
        "measured": {"noise_std": tuple(float(v) for v in experiment.std)},
        "measured_full": {"noise_covariance": experiment.covariance.tolist()},
        "true": {"noise_std": tuple(float(v) for v in recording.true_robot.noise_std)},
    }[variant]
    options = calibration_options(recording, settings, heldout=False).model_dump()
    return CalibrationOptions.model_validate({**options, **known})


@dataclasses.dataclass(frozen=True, eq=False)
class KnownNoise:
    """The protocol variant: per recording the noise experiment, and per way of telling the
    calibration its Σ_n (``KNOWN_NOISE_VARIANTS``) the results and the comparisons of their
    scores in place of "ours" on the same candidates and executions (``per_recording[v]``,
    ``pooled[v]`` as in :class:`StudyResult`)."""

    experiments: tuple[NoiseExperiment, ...]
    results: dict[str, tuple[CalibrationResult, ...]]
    per_recording: dict[str, tuple[Comparison, ...]]
    pooled: dict[str, Comparison]


def known_noise_variant(
    recordings: Sequence[RecordingStudy], settings: StudySettings, metric: TaskMetric
) -> KnownNoise:
    """Measure Σ_n, calibrate with it (each variant) and re-score every recording's runs."""
    experiments = [
        measure_camera_noise(study.recording.true_robot, study.recording.seed)
        for study in recordings
    ]
    results: dict[str, tuple[CalibrationResult, ...]] = {}
    per_recording: dict[str, tuple[Comparison, ...]] = {}
    pooled: dict[str, Comparison] = {}
    for variant in KNOWN_NOISE_VARIANTS:
        calibrated, runs = [], []
        for study, experiment in zip(recordings, experiments, strict=True):
            options = known_noise_options(study.recording, experiment, settings, variant)
            result = pipeline.calibrate(study.recording.dataset, study.recording.robot, options)
            calibrated.append(result)
            runs.append(rescored(study.runs, service_ranking.uncertainty_model(result), metric))
        flat = [run for group in runs for run in group]
        results[variant] = tuple(calibrated)
        per_recording[variant] = tuple(compare(r, bootstrap=settings.bootstrap) for r in runs)
        pooled[variant] = compare(
            flat, bootstrap=settings.bootstrap, groups=[run.recording for run in flat]
        )
    return KnownNoise(tuple(experiments), results, per_recording, pooled)


# --- the docking task's own score -------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class TaskScoring:
    """Every recording's runs (same candidates and executions) scored by ``options`` for all
    three methods; ``per_recording`` and ``pooled`` as for the paper's W. ``rotation_share``:
    median over all candidates of the share of the oracle's paper-W score that comes from roll
    and pitch variance (rad² counted as m²)."""

    options: RankingOptions
    per_recording: tuple[Comparison, ...]
    pooled: Comparison
    runs: tuple[ApproachRun, ...]
    rotation_share: float


def rotation_share_of_score(
    runs: Sequence[ApproachRun], oracle: Sequence[UncertaintyModel]
) -> float:
    """Median share of the paper-W score (diagonal W, Eq. 22–23) that the rotational variance
    contributes (roll and pitch: yaw's weight is 0), over all candidates, with the true
    covariances (``oracle`` per run)."""
    metric = service_ranking.task_metric(RankingOptions())
    weights = np.diag(metric.quadratic_form)  # W diagonal: score = Σ_i w_i² Var_i
    shares = []
    for run, model in zip(runs, oracle, strict=True):
        variance = score_configurations(model, run.joint_positions, metric).ee_variance
        shares.append(variance[:, 3:] @ weights[3:] / (variance @ weights))
    return float(np.median(np.concatenate(shares)))


def task_scoring(
    recordings: Sequence[RecordingStudy], settings: StudySettings, options: RankingOptions
) -> TaskScoring:
    """Re-score every recording's runs with ``options`` (all methods) and compare."""
    metric = service_ranking.task_metric(options)
    per_recording = [study.scored_for(metric) for study in recordings]
    runs = [run for group in per_recording for run in group]
    oracle = [study.scorers.oracle for study in recordings for _ in study.runs]
    return TaskScoring(
        options=options,
        per_recording=tuple(compare(r, bootstrap=settings.bootstrap) for r in per_recording),
        pooled=compare(runs, bootstrap=settings.bootstrap, groups=[run.recording for run in runs]),
        runs=tuple(runs),
        rotation_share=rotation_share_of_score(runs, oracle),
    )


# --- the study ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class RecordingStudy:
    """One recording, its calibration ("ours"), the three scores and its manipulation runs
    (scored with the paper's W)."""

    recording: Recording
    result: CalibrationResult
    scorers: Scorers
    runs: tuple[ApproachRun, ...]

    def scored_for(self, metric: TaskMetric) -> list[ApproachRun]:
        """The same runs (candidates, executions) with every method's score under ``metric``."""
        return [
            dataclasses.replace(run, scores=self.scorers.scores(run.joint_positions, metric))
            for run in self.runs
        ]


@dataclasses.dataclass(frozen=True, eq=False)
class StudyResult:
    settings: StudySettings
    recordings: tuple[RecordingStudy, ...]
    table: TableII
    sigma_full: FloatArray  # (k + 1, 6) calibrated on all kept samples of the first recording
    sigma_splits: FloatArray | None  # (splits, k + 1, 6)
    paper: Comparison  # the first 10 runs of the first recording (paper protocol)
    per_recording: tuple[Comparison, ...]
    pooled: Comparison  # all runs, two-level bootstrap: the verdicts
    ablations: tuple[Ablation, ...]
    known_noise: KnownNoise  # protocol variant: Σ_n measured separately (paper §V-B)
    docking: TaskScoring  # the same runs scored with the docking task's own score
    timings_s: dict[str, float]

    @property
    def first(self) -> RecordingStudy:
        return self.recordings[0]

    @property
    def runs(self) -> tuple[ApproachRun, ...]:
        return tuple(run for study in self.recordings for run in study.runs)


def recording_study(
    seed: int, settings: StudySettings, metric: TaskMetric, *, heldout: bool
) -> RecordingStudy:
    """Simulate, calibrate (ours) and run the manipulation experiment on one recording."""
    recording = simulate_study_recording(settings, seed)
    result = pipeline.calibrate(
        recording.dataset,
        recording.robot,
        calibration_options(recording, settings, heldout=heldout),
    )
    scorers = Scorers(
        ours=service_ranking.uncertainty_model(result),
        gp=gp_uncertainty_model(result, recording),
        oracle=recording.true_robot.uncertainty_model(),
    )
    runs = tuple(
        approach_run(r, result, recording, settings, scorers=scorers, metric=metric)
        for r in range(settings.n_runs)
    )
    return RecordingStudy(recording, result, scorers, runs)


def run_study(
    settings: StudySettings = StudySettings(), *, echo: Callable[[str], None] = print
) -> StudyResult:
    """The whole reproduction; deterministic for fixed settings."""
    clock: dict[str, float] = {}
    started = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal started
        now = time.perf_counter()
        clock[stage] = now - started
        started = now
        echo(f"  {stage}: {clock[stage]:.1f} s")

    metric = service_ranking.task_metric(RankingOptions())
    recordings = []
    for r in range(settings.n_recordings):
        seed = settings.seed + r
        recordings.append(recording_study(seed, settings, metric, heldout=r == 0))
        lap(f"recording {seed}: calibration and {settings.n_runs} manipulation runs")
    first = recordings[0]
    table = table_ii(first.result, first.recording, with_gp=settings.gp_table)
    lap("Table II (GP baseline on the held-out splits)")
    sigma_splits = None
    if settings.split_covariances:
        sigma_splits = split_covariance_std(first.result, first.recording)
        lap("Fig. 4b covariances per split")
    docking = task_scoring(recordings, settings, DOCKING_TASK)
    lap("docking task's own score (re-scoring)")
    docking_metric = service_ranking.task_metric(DOCKING_TASK)
    docking_first = [run for run in docking.runs if run.recording == first.recording.seed]
    models = ablation_models(settings, first, echo=echo)
    ablations = tuple(
        Ablation(
            label,
            compare(rescored(first.runs, model, metric), bootstrap=settings.bootstrap),
            compare(rescored(docking_first, model, docking_metric), bootstrap=settings.bootstrap),
        )
        for label, model in models.items()
    )
    lap("ablations")
    known_noise = known_noise_variant(recordings, settings, metric)
    lap("known-noise variant (noise experiment, calibration, re-scoring)")
    runs = [run for study in recordings for run in study.runs]
    return StudyResult(
        settings=settings,
        recordings=tuple(recordings),
        table=table,
        sigma_full=covariance_std(first.result),
        sigma_splits=sigma_splits,
        paper=compare(first.runs[:PAPER_RUNS], bootstrap=settings.bootstrap),
        per_recording=tuple(compare(s.runs, bootstrap=settings.bootstrap) for s in recordings),
        pooled=compare(runs, bootstrap=settings.bootstrap, groups=[run.recording for run in runs]),
        ablations=ablations,
        known_noise=known_noise,
        docking=docking,
        timings_s=clock,
    )


# --- figures -----------------------------------------------------------------------------------

_FRAME_COMPONENTS = (("x", "y", "z"), ("roll", "pitch", "yaw"))


def sigma_figure(study: StudyResult, path: Path) -> Path:
    """Paper Fig. 4b: σ per frame (joints, then the camera noise), translation in mm and
    rotation in mrad; bars = calibrated on all kept samples, dots = per split, black = true."""
    names = [*(f"joint {i + 1}" for i in range(study.first.recording.true_robot.chain.n_joints))]
    names.append("noise")
    true = np.vstack(
        [
            study.first.recording.true_robot.perturbation_std,
            study.first.recording.true_robot.noise_std,
        ]
    )
    figure = Figure(figsize=(11.0, 6.2), layout="constrained")
    axes = figure.subplots(2, 1)
    x = np.arange(len(names))
    width = 0.26
    colors = ("tab:blue", "tab:orange", "tab:green")
    for panel, (ax, components) in enumerate(zip(axes, _FRAME_COMPONENTS, strict=True)):
        for c, component in enumerate(components):
            column = 3 * panel + c
            offset = (c - 1) * width
            ax.bar(
                x + offset,
                1e3 * study.sigma_full[:, column],
                width,
                color=colors[c],
                alpha=0.75,
                label=f"{component}: calibrated (all kept samples)",
            )
            if study.sigma_splits is not None:
                for split in study.sigma_splits:
                    ax.plot(x + offset, 1e3 * split[:, column], ".", color=colors[c], ms=3)
            ax.plot(x + offset, 1e3 * true[:, column], "_", color="black", ms=14, mew=2)
        ax.plot([], [], "_", color="black", ms=14, mew=2, label="true σ")
        if study.sigma_splits is not None:
            ax.plot([], [], ".", color="grey", label="per split (training set)")
        ax.set_xticks(x, names)
        unit = "mm" if panel == 0 else "mrad"
        ax.set_ylabel(f"σ {'translation' if panel == 0 else 'rotation'} [{unit}]")
        ax.legend(fontsize=7, ncol=2)
    figure.suptitle(
        "Calibrated standard deviations of the random perturbations (paper Fig. 4b), "
        f"simulated Jaco2, recording {study.first.recording.seed}",
        fontsize=10,
    )
    figure.savefig(path, dpi=110)
    return path


def runs_figure(study: StudyResult, path: Path) -> Path:
    """Paper Fig. 6: observed x-y error of the lowest- and highest-score approach per run
    (first 10 runs), ours and the oracle."""
    runs = study.first.runs[:PAPER_RUNS]
    x = np.arange(1, len(runs) + 1)
    figure = Figure(figsize=(8.0, 3.6), layout="constrained")
    ax = figure.subplots()
    for method, marker in (("ours", "o"), ("oracle", "s")):
        picked = _picked_errors(runs, method, "error_mm")
        ax.plot(
            x - 0.1,
            picked[:, 0],
            marker,
            color="tab:green",
            mfc="none" if method == "oracle" else None,
            label=f"{LABELS[method]}: lowest score",
        )
        ax.plot(
            x + 0.1,
            picked[:, 1],
            marker,
            color="tab:red",
            mfc="none" if method == "oracle" else None,
            label=f"{LABELS[method]}: highest score",
        )
    ax.set_xticks(x)
    ax.set_xlabel("run")
    ax.set_ylabel("mean x-y error [mm]")
    ax.legend(fontsize=7, ncol=2)
    figure.suptitle("Observed docking error of the chosen approaches (paper Fig. 6)", fontsize=10)
    figure.savefig(path, dpi=110)
    return path


# --- the report --------------------------------------------------------------------------------


def _ci(interval: tuple[float, float], scale: float = 1.0, digits: int = 0) -> str:
    return f"[{scale * interval[0]:.{digits}f}, {scale * interval[1]:.{digits}f}]"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def table_ii_markdown(table: TableII) -> str:
    """Paper Table II layout, with the paper's means for comparison."""
    header = ["", "", *map(str, table.seeds), "mean", "paper mean"]
    rows = []
    for method, label in TABLE_II_LABELS.items():
        if method not in table.errors:
            continue
        for i, quantity in enumerate(("Trans. mm", "Rot. deg")):
            values = [table.errors[method][s][i] for s in table.seeds]
            paper = float(np.mean(PAPER_TABLE_II[method][i]))
            rows.append(
                [
                    label if i == 0 else "",
                    quantity,
                    *(f"{v:.2f}" for v in values),
                    f"**{np.mean(values):.2f}**",
                    f"{paper:.2f}",
                ]
            )
    return _table(header, rows)


def sigma_markdown(
    study: StudyResult, *sigmas: FloatArray, noise_label: str = "camera noise"
) -> str:
    """σ per frame, "first / second / … (true)": mm for x, y, z; mrad for roll, pitch, yaw.
    Each of ``sigmas`` is (k + 1, 6), joints then noise; by default the product default's on all
    kept samples of the first recording."""
    sigmas = sigmas or (study.sigma_full,)
    robot = study.first.recording.true_robot
    true = np.vstack([robot.perturbation_std, robot.noise_std])
    names = [*robot.chain.joint_names, noise_label]
    header = ["frame", "x mm", "y mm", "z mm", "roll mrad", "pitch mrad", "yaw mrad"]
    rows = [
        [
            name,
            *(
                " / ".join(f"{1e3 * sigma[f, c]:.2f}" for sigma in sigmas)
                + f" ({1e3 * true[f, c]:.2f})"
                for c in range(6)
            ),
        ]
        for f, name in enumerate(names)
    ]
    return _table(header, rows)


def noise_experiment_markdown(study: StudyResult) -> str:
    """Per recording: the noise experiment's detections and its σ per component."""
    header = [
        "recording",
        "detections kept",
        "gross errors drawn / screened",
        "good detections screened",
        "x mm",
        "y mm",
        "z mm",
        "roll mrad",
        "pitch mrad",
        "yaw mrad",
    ]
    rows = []
    for s, e in zip(study.recordings, study.known_noise.experiments, strict=True):
        rows.append(
            [
                str(s.recording.seed),
                f"{int(e.kept.sum())} of {e.kept.size}",
                f"{int(e.gross.sum())} / {int((e.gross & ~e.kept).sum())}",
                str(int((~e.gross & ~e.kept).sum())),
                *(f"{1e3 * v:.2f}" for v in e.std),
            ]
        )
    true = study.first.recording.true_robot.noise_std
    rows.append(["true", "–", "–", "–", *(f"{1e3 * v:.2f}" for v in true)])
    return _table(header, rows)


def known_noise_markdown(study: StudyResult) -> str:
    """Per recording and pooled: share of the oracle's reduction, the default and every way of
    giving Σ_n (``KNOWN_NOISE_VARIANTS``), and the measured variant's reduction."""
    variant = study.known_noise
    header = [
        "recording",
        "runs",
        "oracle reduction",
        "default: share",
        "Σ_n measured: reduction",
        "Σ_n measured: share",
        "full: share",
        "Σ_n true: share",
    ]
    items: list[tuple[str, int | None, Comparison]] = [
        (str(s.recording.seed), i, study.per_recording[i]) for i, s in enumerate(study.recordings)
    ]
    if len(study.recordings) > 1:
        items.append(("**all (two-level bootstrap)**", None, study.pooled))
    rows = []
    for name, i, default in items:
        known = {
            v: (variant.pooled[v] if i is None else variant.per_recording[v][i])
            for v in KNOWN_NOISE_VARIANTS
        }
        o, m = default.selections["oracle"], known["measured"].selections["ours"]
        rows.append(
            [
                name,
                str(default.n_runs),
                f"{o.reduction_pct:.1f} % {_ci(o.reduction_ci)}",
                _recording_share(default),
                f"{m.reduction_pct:.1f} % {_ci(m.reduction_ci)}",
                *(_recording_share(known[v]) for v in KNOWN_NOISE_VARIANTS),
            ]
        )
    return _table(header, rows)


def selection_markdown(comparison: Comparison, *, paper_row: bool) -> str:
    header = [
        "score",
        "lowest-score mm",
        "highest-score mm",
        "reduction",
        "95 % CI",
        "low better in",
        "mean Pearson r",
        "95 % CI",
    ]
    rows = []
    for method in METHODS:
        s = comparison.selections[method]
        rows.append(
            [
                LABELS[method],
                f"{s.low_mm:.3f}",
                f"{s.high_mm:.3f}",
                f"{s.reduction_pct:.1f} %",
                _ci(s.reduction_ci),
                f"{s.wins} of {comparison.n_runs}",
                f"{s.mean_pearson:.2f}",
                _ci(s.pearson_ci, digits=2),
            ]
        )
    if paper_row:
        low, high = PAPER_SELECTION_MM
        rows.append(
            [
                "paper (LRU2, ours)",
                f"{low:.3f}",
                f"{high:.3f}",
                f"{100 * (1 - low / high):.1f} %",
                "–",
                f"{PAPER_WINS} of 10",
                f"{np.mean(PAPER_TABLE_III['ours']):.2f}",
                "–",
            ]
        )
    return _table(header, rows)


def random_part_markdown(comparison: Comparison) -> str:
    header = [
        "score",
        "lowest-score mm",
        "highest-score mm",
        "reduction",
        "95 % CI",
        "mean Pearson r",
    ]
    rows = [
        [
            LABELS[m],
            f"{s.low_mm:.3f}",
            f"{s.high_mm:.3f}",
            f"{s.reduction_pct:.1f} %",
            _ci(s.reduction_ci),
            f"{s.mean_pearson:.2f}",
        ]
        for m, s in comparison.scatter.items()
    ]
    return _table(header, rows)


def _share(value: float, interval: tuple[float, float], digits: int = 0) -> str:
    return f"{100 * value:.{digits}f} % {_ci(interval, 100, digits)}"


def _recording_share(comparison: Comparison) -> str:
    """The share, or a dash where the oracle's own reduction is not above zero (a ratio to
    nothing)."""
    if comparison.selections["oracle"].reduction_ci[0] <= 0.0:
        return "– (oracle's reduction not above 0)"
    return _share(comparison.share_of_oracle, comparison.share_ci)


def per_recording_markdown(study: StudyResult, scoring: TaskScoring | None = None) -> str:
    """Per recording and pooled: reductions, share of the oracle's, Pearson gap and the
    systematic error at the oracle's picks; the paper's W, or ``scoring``'s score."""
    per_recording = study.per_recording if scoring is None else scoring.per_recording
    pooled = study.pooled if scoring is None else scoring.pooled
    all_runs = study.runs if scoring is None else scoring.runs
    header = [
        "recording",
        "runs",
        "oracle reduction",
        "ours reduction",
        "share of oracle",
        "share, random part",
        "Pearson r ours − GP",
        "systematic error at oracle's lowest / highest mm",
    ]
    rows = []
    items = [
        (str(s.recording.seed), c, [r for r in all_runs if r.recording == s.recording.seed])
        for s, c in zip(study.recordings, per_recording, strict=True)
    ]
    if len(study.recordings) > 1:
        items.append(("**all (two-level bootstrap)**", pooled, list(all_runs)))
    for name, c, runs in items:
        o, u = c.selections["oracle"], c.selections["ours"]
        bias = _picked_errors(runs, "oracle", "bias_mm").mean(axis=0)
        rows.append(
            [
                name,
                str(c.n_runs),
                f"{o.reduction_pct:.1f} % {_ci(o.reduction_ci)}",
                f"{u.reduction_pct:.1f} % {_ci(u.reduction_ci)}",
                _recording_share(c),
                _share(c.random_share, c.random_share_ci),
                f"{c.pearson_gap:.2f} {_ci(c.pearson_gap_ci, digits=2)}",
                f"{bias[0]:.3f} / {bias[1]:.3f}",
            ]
        )
    return _table(header, rows)


def table_iii_markdown(study: StudyResult) -> str:
    """Paper Table III: per run (first 10) Pearson r of score vs observed error."""
    runs = study.paper.n_runs
    header = ["run", *map(str, range(1, runs + 1)), "mean", f"mean over all {study.pooled.n_runs}"]
    rows = []
    for method in METHODS:
        r = study.paper.selections[method].pearson
        pooled = study.pooled.selections[method]
        rows.append(
            [
                LABELS[method],
                *(f"{v:.2f}" for v in r),
                f"{np.nanmean(r):.2f}",
                f"{pooled.mean_pearson:.2f} {_ci(pooled.pearson_ci, digits=2)}",
            ]
        )
    for method in ("ours", "gp"):
        paper = PAPER_TABLE_III[method]
        rows.append(
            [f"paper: {LABELS[method]}", *(f"{v:.2f}" for v in paper), f"{np.mean(paper):.2f}", "–"]
        )
    return _table(header, rows)


def ablation_markdown(study: StudyResult) -> str:
    header = [
        "covariances scoring the same candidates",
        "reduction",
        "share of oracle",
        "share, random part",
        "mean Pearson r",
        "docking score: share of oracle",
    ]
    first = study.per_recording[0], study.docking.per_recording[0]
    entries = [(f"ours (product default), N = {study.settings.n_samples}", *first)]
    entries += [(a.label, a.comparison, a.docking) for a in study.ablations]
    rows = []
    for label, c, docking in entries:
        s = c.selections["ours"]
        rows.append(
            [
                label,
                f"{s.reduction_pct:.1f} % {_ci(s.reduction_ci)}",
                _share(c.share_of_oracle, c.share_ci),
                _share(c.random_share, c.random_share_ci),
                f"{s.mean_pearson:.2f}",
                _share(docking.share_of_oracle, docking.share_ci),
            ]
        )
    return _table(header, rows)


@dataclasses.dataclass(frozen=True)
class Diagnostics:
    """Why the comparison is hard, on the first recording's runs.

    ``spread``: median (10th, 90th percentile) over runs of the ratio of the largest to the
    smallest true x-y σ among the approaches; ``agreement``: mean Spearman ρ of our score and the
    oracle's within a run; ``same_low``/``same_high``: share of runs where ours picks the
    oracle's lowest/highest; ``bias_mm``/``scatter_mm``: mean systematic/random error part.
    """

    spread: tuple[float, float, float]
    agreement: float
    same_low: float
    same_high: float
    bias_mm: float
    scatter_mm: float


def diagnostics(runs: Sequence[ApproachRun]) -> Diagnostics:
    ratio = np.array([r.true_xy_std_mm.max() / r.true_xy_std_mm.min() for r in runs])
    rho = [_correlation(stats.spearmanr, r.scores["ours"], r.scores["oracle"]) for r in runs]
    picks = np.array([(r.pick("ours"), r.pick("oracle")) for r in runs])  # (runs, 2, 2)
    return Diagnostics(
        spread=(
            float(np.median(ratio)),
            float(np.percentile(ratio, 10)),
            float(np.percentile(ratio, 90)),
        ),
        agreement=float(np.nanmean(rho)),
        same_low=float(np.mean(picks[:, 0, 0] == picks[:, 1, 0])),
        same_high=float(np.mean(picks[:, 0, 1] == picks[:, 1, 1])),
        bias_mm=float(np.mean([r.bias_mm.mean() for r in runs])),
        scatter_mm=float(np.mean([r.scatter_mm.mean() for r in runs])),
    )


def known_noise_section(study: StudyResult) -> list[str]:
    """Report lines of the protocol variant (Σ_n measured separately)."""
    s, first = study.settings, study.first
    variant = study.known_noise
    robot = first.recording.true_robot
    dof = float(np.mean([e.kept.sum() - np.any(e.kept, axis=1).sum() for e in variant.experiments]))
    rotation_noise = float(np.mean(robot.noise_std[3:]))
    variance_error = float(np.sqrt(2 / dof) * (1e3 * rotation_noise) ** 2)
    largest_joint = float((1e3 * robot.perturbation_std.max()) ** 2)
    failure_m, failure_rad = robot.outlier_size
    measured, exact = variant.pooled["measured"], variant.pooled["true"]
    if exact.reduction_verdict == "met":
        reading = (
            "An exact Σ_n meets the bar, so the gap of the default is the camera noise's "
            "confusion with the perturbations, and a larger noise experiment would close it."
        )
    else:
        reading = (
            "Even the exact Σ_n does not meet the bar pooled (per recording in the table): the "
            "camera noise's confusion with the last joints is only part of the gap; the rest "
            "is the sampling error of the joint covariances estimated from "
            f"{first.result.outliers.n_used} residuals "
            "(see the larger recordings under *Where the gap to the oracle comes from*)."
        )
    return [
        "## Protocol variant: camera noise measured separately (paper §V-B)",
        "",
        "Everything above is the product default: Σ_n is estimated together with the "
        "perturbations from the recording. The paper also measured the camera noise "
        f"separately ({NOISE_CONFIGURATIONS} configurations × {NOISE_DETECTIONS} AprilTag "
        "detections, mean per configuration subtracted, σ per pose component), but only to "
        "validate the calibrated Σ_n. This variant goes one step further and gives that "
        "measured Σ_n to the calibration as known (`kincal calibrate --noise-std`, or the full "
        "matrix with `--noise-covariance FILE`), so that only the perturbations are estimated; "
        "everything else (recording, outlier removal, model, estimator, candidates, "
        "executions, oracle) is the same as above, and the candidates of every run are "
        "re-scored with the variant's covariances. It is not what the product does by "
        "default and not what the paper did.",
        "",
        f"Simulated noise experiment per recording: {NOISE_CONFIGURATIONS} configurations of "
        "the true robot, each standing still while the camera detects the marker "
        f"{NOISE_DETECTIONS} times: one draw of the joint perturbations ξ per configuration "
        "(the arm does not move), fresh camera noise per detection, and detector failures as "
        "often as in the recording (the paper does not mention any; they are screened "
        f"beforehand at {NOISE_SCREEN_MAD:.0f} robust σ, being {np.degrees(failure_rad):.0f} deg "
        f"/ {1e3 * failure_m:.0f} mm against {CAMERA_NOISE[1]} deg / {CAMERA_NOISE[0]} mm). "
        "Deviations in the end-effector frame of the configuration's "
        "median detection, configuration mean subtracted; σ = √diag of their sample "
        "covariance (degrees of freedom: kept detections − configurations):",
        "",
        noise_experiment_markdown(study),
        "",
        f"With {dof:.0f} degrees of freedom (mean over recordings) a measured σ_n is known "
        f"to about ±{100 / np.sqrt(2 * dof):.0f} % and its variance to "
        f"±{100 * np.sqrt(2 / dof):.0f} %: for the camera's rotation "
        f"({1e3 * rotation_noise:.2f} mrad) that is ±{variance_error:.1f} mrad², against "
        f"{largest_joint:.2f} mrad² for the largest joint perturbation "
        f"({np.sqrt(largest_joint):.2f} mrad).",
        "",
        "σ per frame calibrated on all kept samples of recording "
        f"{first.recording.seed}, with the measured Σ_n (σ per component) / with the true "
        "Σ_n (true value in parentheses; compare the table of Fig. 4b):",
        "",
        sigma_markdown(
            study,
            covariance_std(variant.results["measured"][0]),
            covariance_std(variant.results["true"][0]),
            noise_label="camera noise (given)",
        ),
        "",
        f"Manipulation experiment on the same {s.n_runs} runs per recording: share of the "
        "oracle's reduction with the default and with Σ_n given to the calibration: "
        f"*Σ_n measured* = {KNOWN_NOISE_VARIANTS['measured']}, the protocol variant; "
        f"*full* = {KNOWN_NOISE_VARIANTS['measured_full']}; *Σ_n true* = "
        f"{KNOWN_NOISE_VARIANTS['true']}. The oracle is the same; 95 % bootstrap intervals:",
        "",
        known_noise_markdown(study),
        "",
        f"Pooled share: default {_share(study.pooled.share_of_oracle, study.pooled.share_ci)}, "
        f"Σ_n measured {_share(measured.share_of_oracle, measured.share_ci)}, Σ_n true "
        f"{_share(exact.share_of_oracle, exact.share_ci)} ({measured.reduction_verdict} / "
        f"{exact.reduction_verdict} for the 80 % bar). {reading}",
        "",
    ]


def docking_section(study: StudyResult) -> list[str]:
    """Report lines: the same runs scored with the docking task's own score."""
    docking, paper = study.docking, study.pooled
    weights = docking.options.weights
    assert isinstance(weights, TaskPointWeights)
    ours, oracle = docking.pooled.selections["ours"], docking.pooled.selections["oracle"]
    dock, paper_w = diagnostics(docking.runs), diagnostics(study.runs)
    grows = oracle.reduction_pct > paper.selections["oracle"].reduction_pct
    change = "grows" if grows else "changes"
    better = " (a better score for the task even with perfect covariances)" if grows else ""
    return [
        "## The docking task's own score (task point)",
        "",
        "The experiment measures the x-y error of the end-effector origin. The paper's W "
        "scores something else: it adds 0.1² × (roll and pitch variance in rad²) to 0.4² × "
        "(x and y variance in m²), and with the true covariances the rotational part is "
        f"{100 * docking.rotation_share:.0f} % of that score (median over all candidates). The "
        "product's task-point score (issue 4 item 1; `kincal rank --task-point "
        f"{','.join(f'{v:g}' for v in weights.point_m)} --task-weights "
        f"{','.join(f'{v:g}' for v in weights.axis_weights)}`, in m², no rad² mixed in) is "
        "Var(x) + Var(y) of the docking point in the end-effector frame: the quantity the "
        "experiment measures. The same candidates and executions, every method re-scored with "
        "it (ours: the same calibrated covariances; GP: its variances; oracle: true Σ):",
        "",
        selection_markdown(docking.pooled, paper_row=False),
        "",
        "Random part only:",
        "",
        random_part_markdown(docking.pooled),
        "",
        "Per recording:",
        "",
        per_recording_markdown(study, docking),
        "",
        f"With the task's own score the oracle's reduction {change} from "
        f"{paper.selections['oracle'].reduction_pct:.1f} % to {oracle.reduction_pct:.1f} %"
        f"{better}, and ours from "
        f"{paper.selections['ours'].reduction_pct:.1f} % to {ours.reduction_pct:.1f} %. "
        f"Ours picks the oracle's lowest-score approach in {100 * dock.same_low:.0f} % of the "
        f"runs and its highest in {100 * dock.same_high:.0f} % with the task's score, against "
        f"{100 * paper_w.same_low:.0f} % and {100 * paper_w.same_high:.0f} % with the paper's "
        f"W (agreement with the oracle's whole order of a run: mean Spearman ρ "
        f"{dock.agreement:.2f} and {paper_w.agreement:.2f}).",
        "",
    ]


def report_markdown(study: StudyResult, sigma_png: str, runs_png: str) -> str:
    """The whole report; figure links relative to the report's folder."""
    s, first, pooled = study.settings, study.first, study.pooled
    result = first.result
    injected = set(first.recording.outlier_rows.tolist())
    removed = set((np.array(result.outliers.removed_rows, dtype=int) - 1).tolist())
    covariance = result.covariance
    estimator = covariance.estimator if covariance is not None else "none"
    d = diagnostics(first.runs)
    ours, oracle = pooled.selections["ours"], pooled.selections["oracle"]
    docking = study.docking.pooled
    dock_ours, dock_oracle = docking.selections["ours"], docking.selections["oracle"]
    variant = study.known_noise.pooled["measured"]
    known = variant.selections["ours"]
    variant_recordings = study.known_noise.per_recording["measured"]
    paper_width = float(np.subtract(*study.paper.selections["ours"].reduction_ci[::-1]))
    paper_reduction = 100 * (1 - PAPER_SELECTION_MM[0] / PAPER_SELECTION_MM[1])
    total_runs = pooled.n_runs
    seeds = ", ".join(str(r.recording.seed) for r in study.recordings)
    out = [
        "# Paper reproduction on a simulated LRU2-like Jaco2 (issue 4)",
        "",
        "Generated by `python benchmarks/reproduce_paper.py` "
        f"(kincal {result_json.kincal_version()}): {s.n_recordings} recording(s) of {s.n_samples} "
        f"samples (seeds {seeds}), {s.n_runs} manipulation runs per recording × "
        f"{s.n_approaches} approaches × {s.n_executions} executions, {len(s.splits)} held-out "
        f"splits, {s.bootstrap} bootstrap resamples. Everything is simulated and seeded; the "
        "study and its parameters are described in the script's docstring.",
        "",
        f"Recording {first.recording.seed}: {result.outliers.n_input} samples, "
        f"{len(removed)} removed by the 2σ rule ({len(injected & removed)} of {len(injected)} "
        f"injected outliers, {len(removed - injected)} good samples), {result.outliers.n_used} "
        f"used; covariances estimated with `{estimator}` (the product default).",
        "",
        "## Table II: mean held-out error (recording "
        f"{first.recording.seed}, 90/10 splits after outlier removal)",
        "",
        table_ii_markdown(study.table),
        "",
        "The paper's robot had much larger unmodelled errors "
        f"({np.mean(PAPER_TABLE_II['calibrated'][0]):.2f} mm after calibration); the "
        "simulated one has exactly the modelled effects, so after ours only the random "
        "perturbations, the camera noise and the estimation error of "
        f"{result.outliers.n_used} samples remain. "
        'The GP of ref. [13] is fitted to the residuals of the "before" model per split.',
        "",
        "## Fig. 4b: standard deviations of the random perturbations",
        "",
        f"![σ per frame, calibrated and true]({sigma_png})",
        "",
        "Calibrated on all kept samples of recording "
        f"{first.recording.seed} (true value in parentheses):",
        "",
        sigma_markdown(study),
        "",
        "## Manipulation experiment (§V-C)",
        "",
        f"Per run: a pre-grasp pose, {s.n_approaches} distinct approach configurations reaching "
        "it on the "
        "calibrated model (IK branches, rotations about the end-effector z axis), each executed "
        f"{s.n_executions} times on the true robot; observed error = mean x-y docking error in "
        "the end-effector frame. Scores: ours (calibrated covariances, Eq. 22–23 with the paper's "
        "W), the GP's predictive variances on diag Σ_E, and the oracle (true Σ, true geometry).",
        "",
        f"### The paper's protocol: the first {study.paper.n_runs} runs of recording "
        f"{first.recording.seed}",
        "",
        selection_markdown(study.paper, paper_row=True),
        "",
        f"At this size the 95 % interval of our reduction is {paper_width:.0f} percentage points "
        "wide: ten runs cannot resolve the differences the simulated robot allows (the paper's "
        f"{PAPER_WINS} of 10 and {paper_reduction:.0f} % are one such 10-run draw, on a robot "
        "with larger errors).",
        "",
        f"![lowest- vs highest-score error per run]({runs_png})",
        "",
        f"### All {total_runs} runs ({s.n_recordings} recording(s) × {s.n_runs})",
        "",
        selection_markdown(pooled, paper_row=False),
        "",
        "Random part only (x-y distance of each execution from the configuration's own mean "
        "pose; removes the calibrated model's systematic error, which no score can see):",
        "",
        random_part_markdown(pooled),
        "",
        "Per recording (share of oracle = our reduction / the oracle's; 95 % bootstrap intervals):",
        "",
        per_recording_markdown(study),
        "",
        "The systematic part (calibrated model vs true robot) is unknown to every score; where it "
        "happens to be larger at the low-uncertainty approaches it cancels the random part's "
        "benefit in the observed error, and the share of the oracle's (then tiny) reduction is "
        "meaningless for that recording.",
        "",
        "## Table III: correlation of the score with the observed x-y error (Pearson r per run)",
        "",
        table_iii_markdown(study),
        "",
        *docking_section(study),
        *known_noise_section(study),
        "## Acceptance (issue 4)",
        "",
        "Scored with the docking task's own score (task point, the product's recommendation "
        "for a task that measures a position):",
        "",
        f"- **Reduction ≥ 80 % of the oracle's:** ours {dock_ours.reduction_pct:.1f} % "
        f"{_ci(dock_ours.reduction_ci)}, oracle {dock_oracle.reduction_pct:.1f} % "
        f"{_ci(dock_oracle.reduction_ci)}; share "
        f"{_share(docking.share_of_oracle, docking.share_ci, 1)} → "
        f"**{docking.reduction_verdict}** (on the random part: "
        f"{_share(docking.random_share, docking.random_share_ci, 1)}). Per recording: "
        f"{', '.join(_recording_share(c).split(' [')[0] for c in study.docking.per_recording)}.",
        f"- **Our score correlates with the observed error better than the GP's:** mean Pearson "
        f"r {dock_ours.mean_pearson:.2f} vs {docking.selections['gp'].mean_pearson:.2f}, gap "
        f"{docking.pearson_gap:.2f} {_ci(docking.pearson_gap_ci, digits=2)} → "
        f"**{docking.correlation_verdict}**.",
        "",
        "Scored with the paper's W (as published; the tables above):",
        "",
        f"- **Reduction ≥ 80 % of the oracle's:** ours {ours.reduction_pct:.1f} % "
        f"{_ci(ours.reduction_ci)}, oracle {oracle.reduction_pct:.1f} % "
        f"{_ci(oracle.reduction_ci)}; share "
        f"{_share(pooled.share_of_oracle, pooled.share_ci, 1)} → **{pooled.reduction_verdict}** "
        f"(on the random part: {_share(pooled.random_share, pooled.random_share_ci, 1)}). Per "
        f"recording: {', '.join(_recording_share(c).split(' [')[0] for c in study.per_recording)}.",
        f"- **Our score correlates with the observed error better than the GP's:** mean Pearson "
        f"r {ours.mean_pearson:.2f} vs {pooled.selections['gp'].mean_pearson:.2f}, gap "
        f"{pooled.pearson_gap:.2f} {_ci(pooled.pearson_gap_ci, digits=2)} → "
        f"**{pooled.correlation_verdict}**.",
        f"- *Protocol variant, Σ_n measured separately (paper §V-B, not the product default):* "
        f"reduction {known.reduction_pct:.1f} % {_ci(known.reduction_ci)}; share "
        f"{_share(variant.share_of_oracle, variant.share_ci, 1)} → "
        f"**{variant.reduction_verdict}** (on the random part: "
        f"{_share(variant.random_share, variant.random_share_ci, 1)}). Per recording: "
        f"{', '.join(_recording_share(c).split(' [')[0] for c in variant_recordings)}.",
        "",
        '"met" / "not met" need the whole 95 % interval (two-level bootstrap over recordings '
        'and runs) on one side of the bar; otherwise "not demonstrated".',
        "",
        "## Where the gap to the oracle comes from",
        "",
        f"Candidates and observed errors of recording {first.recording.seed}'s {s.n_runs} runs, "
        "re-scored with other covariances:",
        "",
        ablation_markdown(study),
        "",
        f"- The approaches of one pre-grasp pose differ little in true x-y σ: largest/smallest "
        f"= {d.spread[0]:.2f} (median; 10–90 %: {d.spread[1]:.2f}–{d.spread[2]:.2f}). The "
        "oracle's reduction is bounded by that spread, and small errors in calibrated "
        "covariances re-order such candidates.",
        f"- Our score vs the oracle's within a run: mean Spearman ρ {d.agreement:.2f}; ours "
        f"picks the oracle's lowest in {100 * d.same_low:.0f} % and its highest in "
        f"{100 * d.same_high:.0f} % of runs.",
        f"- Observed error = systematic part (calibrated model vs true robot, mean "
        f"{d.bias_mm:.2f} mm) + random part (mean {d.scatter_mm:.2f} mm); the systematic part is "
        "the same for every score and makes the lowest-vs-highest comparison noisy (the paper's "
        "10 runs cannot resolve it).",
        "",
        "## Timings",
        "",
        ", ".join(f"{stage}: {seconds:.0f} s" for stage, seconds in study.timings_s.items())
        + " (wall clock on a shared machine).",
        "",
    ]
    return "\n".join(out)


def write_report(study: StudyResult, out: Path, figures: Path | None = None) -> Path:
    """``out/reproduce_paper.md`` and the two PNGs (in ``figures``, default ``out``)."""
    figures = figures or out
    out.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    sigma = sigma_figure(study, figures / "reproduce_paper_sigma.png")
    runs = runs_figure(study, figures / "reproduce_paper_runs.png")
    report = out / "reproduce_paper.md"
    text = report_markdown(
        study,
        Path(os.path.relpath(sigma, out)).as_posix(),
        Path(os.path.relpath(runs, out)).as_posix(),
    )
    report.write_text(text, encoding="utf-8")
    return report


def _reductions(comparison: Comparison) -> str:
    return ", ".join(
        f"{LABELS[m]} {s.reduction_pct:.1f} % {_ci(s.reduction_ci)}"
        for m, s in comparison.selections.items()
    )


def headline(study: StudyResult) -> str:
    """A few lines for the terminal (and the README)."""
    ours, before = study.table.mean("calibrated"), study.table.mean("before")
    gp = "GP –"
    if "gp" in study.table.errors:
        gp = "GP {:.2f} / {:.2f}".format(*study.table.mean("gp"))
    p, k, d = study.pooled, study.known_noise.pooled["measured"], study.docking.pooled
    return "\n".join(
        [
            f"Table II mean (mm / deg): before {before[0]:.2f} / {before[1]:.2f}, ours "
            f"{ours[0]:.2f} / {ours[1]:.2f}, {gp}",
            f"paper's W: reduction lowest vs highest score: {_reductions(p)}",
            f"share of the oracle's reduction: {_share(p.share_of_oracle, p.share_ci)} "
            f"({p.reduction_verdict}); random part {_share(p.random_share, p.random_share_ci)}",
            f"mean Pearson r: ours {p.selections['ours'].mean_pearson:.2f}, GP "
            f"{p.selections['gp'].mean_pearson:.2f}, gap {p.pearson_gap:.2f} "
            f"{_ci(p.pearson_gap_ci, digits=2)} ({p.correlation_verdict})",
            f"variant with Σ_n measured separately (§V-B): share of the oracle's reduction "
            f"{_share(k.share_of_oracle, k.share_ci)} ({k.reduction_verdict}); random part "
            f"{_share(k.random_share, k.random_share_ci)}",
            f"docking task's own score (task point): reduction {_reductions(d)}",
            f"docking score: share of the oracle's reduction "
            f"{_share(d.share_of_oracle, d.share_ci)} ({d.reduction_verdict}); mean Pearson r "
            f"ours {d.selections['ours'].mean_pearson:.2f}, GP "
            f"{d.selections['gp'].mean_pearson:.2f}, gap {d.pearson_gap:.2f} "
            f"{_ci(d.pearson_gap_ci, digits=2)} ({d.correlation_verdict})",
        ]
    )


def main(
    settings: StudySettings = StudySettings(),
    out: Path = Path("out/reproduce_paper"),
    figures: Path | None = None,
    *,
    echo: Callable[[str], None] = print,
) -> StudyResult:
    """Run the study, write the report and the figures, print the headline numbers."""
    study = run_study(settings, echo=echo)
    report = write_report(study, out, figures)
    echo(headline(study))
    echo(f"wrote {report}")
    return study


def settings_from_arguments(arguments: argparse.Namespace) -> StudySettings:
    settings = StudySettings.quick() if arguments.quick else StudySettings()
    changes = {
        "n_runs": arguments.runs,
        "n_recordings": arguments.recordings,
        "n_executions": arguments.executions,
    }
    return dataclasses.replace(settings, **{k: v for k, v in changes.items() if v is not None})


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/reproduce_paper"))
    parser.add_argument("--figures", type=Path, default=None, help="PNG folder (default --out)")
    parser.add_argument("--runs", type=int, default=None, help="manipulation runs per recording")
    parser.add_argument("--recordings", type=int, default=None, help="independent recordings")
    parser.add_argument("--executions", type=int, default=None, help="executions per approach")
    parser.add_argument("--quick", action="store_true", help="the reduced study of the test")
    arguments = parser.parse_args()
    main(settings_from_arguments(arguments), arguments.out, arguments.figures)
