"""The whole reproduction (:func:`run_study`): every recording's calibration and manipulation runs,
Table II, Fig. 4b, the comparisons, the docking score, the ablations and the protocol variant."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

from benchmarks.reproduce_paper.ablations import Ablation, ablation_models
from benchmarks.reproduce_paper.calibration import (
    TableII,
    covariance_std,
    split_covariance_std,
    table_ii,
)
from benchmarks.reproduce_paper.docking import DOCKING_TASK, TaskScoring, task_scoring
from benchmarks.reproduce_paper.known_noise import KnownNoise, known_noise_variant
from benchmarks.reproduce_paper.manipulation import (
    ApproachRun,
    RecordingStudy,
    recording_study,
    rescored,
)
from benchmarks.reproduce_paper.paper import PAPER_RUNS
from benchmarks.reproduce_paper.selection import Comparison, compare
from benchmarks.reproduce_paper.settings import StudySettings
from schemas.ranking import RankingOptions
from service.app import rank as service_ranking
from solver.arrays import FloatArray


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
