"""Reproduction of the paper's experiments (§V) on a simulated LRU2-like Jaco2 (issue 4, item 5).

The study, with everything random seeded:

* **True robot.** Kinova Jaco2 (j2s6s200) of :func:`service.app.simulate.scenario` with the paper's
  effects: per-link geometric errors, elastic joints 2 and 3, a flexing base plate (two virtual
  compliant axes at joint 1), an unknown camera frame, an unknown marker, 0.3 mm / 0.2 deg camera
  noise and 10 % gross outliers. Random perturbations ξ_i ~ N(0, Σ_i) in every joint frame
  (Eq. 7) are rotational, as the paper found: backlash/friction about the joint axis with σ
  growing from 0.3 mrad (joint 1) to 1.5 mrad (joint 6), plus bearing play about the two other
  axes at 30 % of that (:func:`true_perturbation_std`).
* **Recording.** 154 configurations seen by the camera (paper §V-A). "Ours" is
  :func:`service.app.calibrate.calibrate` on this recording alone: 2-sigma outlier removal, the
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
  :func:`service.app.rank.rank_target` finds 10 distinct configurations that reach it on the
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

Usage (from the repository root): ``python -m benchmarks.reproduce_paper [--out
out/reproduce_paper] [--figures DIR] [--runs 150] [--recordings 4] [--executions 500]
[--quick] [--write-results]``. Writes ``reproduce_paper.md`` to ``--out`` and the figures
``reproduce_paper_sigma.png`` (Fig. 4b) and ``reproduce_paper_runs.png`` (Fig. 6) to
``--figures`` (default: ``--out``). ``--write-results`` also writes the tables of
docs/reproduce_paper.md, ``docs/results/reproduce_paper_*.{json,md}`` (``results``), and the
figures to ``docs/`` (unless ``--figures`` is given).

Modules, in the order the study uses them: ``settings`` (sizes and seeds), ``paper`` (the
published numbers), ``simulation`` (the true robot and its recording), ``calibration`` (Table II,
Fig. 4b), ``manipulation`` (approach runs and their scores), ``selection`` (statistics and
verdicts), ``docking`` (the task's own score), ``ablations``, ``known_noise`` (the §V-B variant),
``study`` (all of it), ``plots``, ``tables`` and ``report`` (the markdown), ``results`` (the
results files), ``cli`` and
``__main__`` (the command line).
"""

from __future__ import annotations

import solver  # noqa: F401  (BLAS defaults before numpy work)
from benchmarks.reproduce_paper.calibration import TableII, covariance_std, table_ii
from benchmarks.reproduce_paper.cli import main, settings_from_arguments
from benchmarks.reproduce_paper.docking import DOCKING_TASK, TaskScoring
from benchmarks.reproduce_paper.known_noise import KnownNoise, NoiseExperiment, measure_camera_noise
from benchmarks.reproduce_paper.manipulation import ApproachRun, RecordingStudy, Scorers
from benchmarks.reproduce_paper.report import headline, report_markdown, write_report
from benchmarks.reproduce_paper.selection import Comparison, Selection, bootstrap_indices, compare
from benchmarks.reproduce_paper.settings import StudySettings
from benchmarks.reproduce_paper.simulation import (
    Recording,
    TrueRobot,
    simulate_study_recording,
    true_perturbation_std,
)
from benchmarks.reproduce_paper.study import StudyResult, run_study

__all__ = [
    "DOCKING_TASK",
    "ApproachRun",
    "Comparison",
    "KnownNoise",
    "NoiseExperiment",
    "Recording",
    "RecordingStudy",
    "Scorers",
    "Selection",
    "StudyResult",
    "StudySettings",
    "TableII",
    "TaskScoring",
    "TrueRobot",
    "bootstrap_indices",
    "compare",
    "covariance_std",
    "headline",
    "main",
    "measure_camera_noise",
    "report_markdown",
    "run_study",
    "settings_from_arguments",
    "simulate_study_recording",
    "table_ii",
    "true_perturbation_std",
    "write_report",
]
