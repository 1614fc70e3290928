"""The docking task's own score: the same runs scored with the x-y variance of the docking point
instead of the paper's W."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from benchmarks.reproduce_paper.manipulation import ApproachRun, RecordingStudy
from benchmarks.reproduce_paper.selection import Comparison, compare
from benchmarks.reproduce_paper.settings import StudySettings
from schemas.ranking import RankingOptions, TaskPointWeights
from service.app import rank as service_ranking
from solver.ranking import UncertaintyModel, score_configurations

DOCKING_TASK = RankingOptions(
    weights=TaskPointWeights(point_m=(0.0, 0.0, 0.0), axis_weights=(1.0, 1.0, 0.0))
)
"""The score of the quantity the manipulation experiment measures: Var(x) + Var(y) of the
end-effector origin (the docking point) in the end-effector frame, m² — the product's task-point
score (issue 4 item 1, ``kincal rank --task-point 0,0,0 --task-weights 1,1,0``). The paper's W
instead adds 0.1² rad² of roll and pitch variance to 0.4² m² of x and y variance."""


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
