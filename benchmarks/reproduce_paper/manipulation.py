"""The manipulation experiment (paper §V-C) on one recording: pre-grasp poses, their ranked
approach configurations, executions on the true robot and the three scores (ours, the GP
baseline, the oracle)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from benchmarks.reproduce_paper.settings import StudySettings
from benchmarks.reproduce_paper.simulation import (
    Recording,
    calibration_options,
    kept_rows,
    simulate_study_recording,
)
from schemas.calibration import CalibrationResult
from schemas.ranking import RankingOptions, RankingResult, TargetPose, TargetRankingRequest
from service.app import calibrate as pipeline
from service.app import rank as service_ranking
from service.render import result_json
from solver import lie
from solver.arrays import FloatArray
from solver.errors import KincalError
from solver.gp_baseline import GPErrorModel, fit_gp_error_model, gp_scores
from solver.model import KinematicChain, sample_configurations
from solver.ranking import TaskMetric, UncertaintyModel, score_configurations

MAX_TARGET_ATTEMPTS = 50


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
