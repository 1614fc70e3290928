"""Held-out coverage of the predicted covariance on the real recordings of data/real (issue 13).

Per recording, ``kincal calibrate``'s held-out splits (10 random 90/10 splits, seeds 1..10):
every part of the predicted covariance is estimated from a split's training rows only
(geometry, compliance, covariances with the default estimator, Cov(θ̂), and the model-error part
by nested cross-validation inside the training rows), and the split's test poses are scored by
``d² = rᵀ Σ⁻¹ r``, r = Log(X_pred⁻¹ X_meas) (3-D translation for position-only recordings).
Columns: the share of held-out poses inside the predicted 95 % ellipsoid and the mean d²
(χ²_d mean: d) for

- "Σ_E + Σ_n": what ``kincal predict`` wrote before issue 13 (Eq. 12 with the noise);
- "+ Cov(θ̂)": adding the parameter-estimation part;
- "total": adding the model-error part — today's ``kincal predict`` default —, with its
  50/90/95/99 % coverage.

Each recording runs with the default outlier rule, the paper's 2σ rule and no rule (the 2σ
rule truncates the residuals, so the covariances it leaves are too small and the poses it drops
are missing from the test rows as well).

Two results files (``--write-results``): ``docs/results/coverage_folds.{json,md}``, the 10-fold
acceptance table of issue 13 (with each fold's counts, so one fold can be re-run against it),
and ``docs/results/coverage_rules.{json,md}``, the calibration's own coverage under each outlier
rule; docs/coverage.md includes both and tests/test_quoted_numbers.py checks them. A third,
``docs/results/coverage_measurements.{json,md}``: the calibration's own coverage of the other
measurement types (ball in socket, markers; :data:`MEASURED`) with ``kincal calibrate``'s
defaults, which docs/coverage.md and docs/measurements.md include. A fourth,
``docs/results/coverage_partitions.{json,md}`` (issue 31): the 10-fold protocol over
``--partitions`` random partitions of each recording (partition 0 is the acceptance table's),
so a coverage that holds on one partition only shows as such. A fifth, with ``--types``
alone: ``docs/results/coverage_types_partitions.{json,md}`` (issue 31), the same protocol for
the other measurement types (:data:`TYPES`: the twelve platonics arms pooled, the TIAGo
markers, the TIAGo relative base, the DH positioner), each held-out row scored in its type's
residual space under the total predictive covariance of its fold's result.

Usage: ``python -m benchmarks.coverage [--seeds 10] [--folds 10] [--partitions 3]
[--recordings fr3,ur10e,...] [--measured panda_right,...] [--write-results]``, or
``python -m benchmarks.coverage --types platonics,... [--type-partitions platonics=2]
[--write-results]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.results import Row, markdown_table, write_results
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import PoseDataset
from schemas.dataset.readers import read_dataset
from schemas.robots import RobotDescription, example_robot_data_dir, load_robot
from service.app import calibrate as pipeline
from service.app import measurement_input
from service.app import rank as ranking
from service.render import result_json
from solver import lie
from solver.errors import KincalError
from solver.measurement.predictive import total_distances
from solver.predictive import (
    COVERAGE_LEVELS,
    Coverage,
    ScoredRows,
    chi2_quantile,
    coverage,
    mahalanobis_squared,
)
from solver.stream.coverage import PredictiveCalibration, fold_indices
from solver.stream.screening import family_wise_t2

DATA = Path(__file__).resolve().parents[1] / "data" / "real"


@dataclass(frozen=True)
class Recording:
    """A real recording: its file (under data/real) and how to load its robot."""

    label: str
    path: str
    robot: str | None = None
    urdf: str | None = None
    base: str | None = None
    tip: str | None = None
    dh: str | None = None

    def description(self) -> RobotDescription:
        if self.robot is not None:
            return load_robot(self.robot)
        if self.dh is not None:
            return load_robot(dh_path=DATA / self.dh)
        assert self.urdf is not None
        path = Path(self.urdf)
        if not path.is_absolute():
            path = example_robot_data_dir() / self.urdf
            if not path.is_file():
                path = DATA / self.urdf
        return load_robot(urdf_path=path, base_frame=self.base, tip_frame=self.tip)


RECORDINGS = {
    "fr3": Recording("FR3 eye-in-hand (philnad)", "philnad_fr3_eye_in_hand/fr3_poses.csv", "panda"),
    "ur10e": Recording(
        "UR10e (FIGAROH experiment)",
        "figaroh_ur10_experiment/calibration.csv",
        urdf="figaroh_ur10_experiment/ur10e_robot.urdf",
        base="base_link",
        tip="wrist_3_link",
    ),
    "talos": Recording(
        "TALOS left arm, position-only",
        "figaroh_talos_left_arm_contact/talos_left_arm_02_10_contact.csv",
        urdf="robots/talos_data/robots/talos_full_v2.urdf",
        base="base_link",
        tip="gripper_left_base_link",
    ),
    "tiago": Recording(
        "TIAGo vicon gripper3/base1, position-only",
        "figaroh_tiago_mocap/vicon/vicon_calibration_fc10_gripper3_base1.csv",
        urdf="robots/tiago_description/robots/tiago.urdf",
        base="base_footprint",
        tip="arm_7_link",
    ),
}


@dataclass(frozen=True)
class CoverageRow:
    """One recording under one outlier rule."""

    label: str
    rule: str
    n_used: int
    n_input: int
    dimension: int
    n_heldout: int
    random_95: float
    random_mean: float
    parameters_95: float
    parameters_mean: float
    total: tuple[float, ...]
    total_mean: float
    seconds: float

    def row(self) -> Row:
        """The numbers of the results file ``coverage_rules`` (shares as fractions)."""
        return {
            "recording": self.label,
            "rule": self.rule,
            "used": self.n_used,
            "input": self.n_input,
            "dimension": self.dimension,
            "heldout": self.n_heldout,
            "random_inside_95": self.random_95,
            "random_mean_d2": self.random_mean,
            "parameters_inside_95": self.parameters_95,
            "parameters_mean_d2": self.parameters_mean,
            **{_inside(a): v for a, v in zip(COVERAGE_LEVELS, self.total, strict=True)},
            "mean_d2": self.total_mean,
            "seconds": self.seconds,
        }


def _inside(level: float) -> str:
    """The results-file key of the share (or count) inside the ``level`` ellipsoid."""
    return f"inside_{round(100 * level)}"


def _share_and_mean(distances: np.ndarray, dimension: int) -> tuple[float, float]:
    found = coverage(distances, dimension)
    return found.at(0.95), found.mean_d2


RULES = {"model": {}, "2σ": {"outlier_sigma": 2.0}, "none": {"outlier_rule": "none"}}
"""The outlier rules compared: the default model-based rule, the paper's 2σ rule, none."""


def measure(recording: Recording, rule: str, seeds: int) -> CoverageRow:
    """Calibrate ``recording`` like ``kincal calibrate`` with the outlier rule ``rule`` (a
    key of :data:`RULES`) and take its held-out splits apart."""
    options = CalibrationOptions(seeds=list(range(1, seeds + 1)), **RULES[rule])  # type: ignore[arg-type]
    setup = pipeline.check_calibration(recording.description(), options)
    started = time.perf_counter()
    run = pipeline.calibrate_source(DATA / recording.path, setup)
    elapsed = time.perf_counter() - started
    predictive = run.predictive
    assert predictive is not None and predictive.coverage is not None, "no coverage measured"
    return _row(
        recording,
        run.result.outliers.n_used,
        run.result.outliers.n_input,
        predictive,
        rule,
        elapsed,
    )


def _row(
    recording: Recording,
    n_used: int,
    n_input: int,
    predictive: PredictiveCalibration,
    rule: str,
    elapsed: float,
) -> CoverageRow:
    found = predictive.coverage
    assert found is not None
    d = found.dimension
    pooled = ScoredRows.join([s.scored for s in predictive.splits.values()], d)
    zero = np.zeros(d)
    random = ScoredRows(pooled.residuals, pooled.random, pooled.random, pooled.axes)
    random_95, random_mean = _share_and_mean(random.distances_squared(zero), d)
    parameters_95, parameters_mean = _share_and_mean(pooled.distances_squared(zero), d)
    return CoverageRow(
        recording.label,
        rule,
        n_used,
        n_input,
        d,
        found.n,
        random_95,
        random_mean,
        parameters_95,
        parameters_mean,
        tuple(found.at(a) for a in COVERAGE_LEVELS),
        found.mean_d2,
        elapsed,
    )


def mean_d2_text(value: float) -> str:
    """A mean d² to one decimal, thousands grouped by a space beyond 1 000 (to the unit)."""
    return f"{value:.1f}" if value < 1000 else f"{value:,.0f}".replace(",", " ")


def _shares(row: Row) -> str:
    return " / ".join(f"{100 * row[_inside(a)]:.0f}" for a in COVERAGE_LEVELS)


RULES_HEADER = (
    "Recording",
    "Outlier rule",
    "Used / input",
    "d",
    "Held-out poses",
    "Σ_E + Σ_n: in 95 % / mean d²",
    "+ Cov(θ̂): in 95 % / mean d²",
    "Total: in 50 / 90 / 95 / 99 %",
    "Total: mean d² (χ² mean)",
)


def render_rules(rows: list[Row]) -> str:
    """The table of ``docs/results/coverage_rules.md``: the calibration's own held-out coverage
    under each outlier rule (shares to the percent, mean d² to 1 and 2 decimals)."""
    return markdown_table(
        RULES_HEADER,
        [
            (
                r["recording"],
                "model (default)" if r["rule"] == "model" else r["rule"],
                f"{r['used']} / {r['input']}",
                r["dimension"],
                r["heldout"],
                f"{100 * r['random_inside_95']:.0f} % / {mean_d2_text(r['random_mean_d2'])}",
                f"{100 * r['parameters_inside_95']:.0f} % / "
                + mean_d2_text(r["parameters_mean_d2"]),
                _shares(r),
                f"{r['mean_d2']:.2f} ({r['dimension']})",
            )
            for r in rows
        ],
    )


MEASURED = {
    "panda_right": Recording(
        "platonics `panda_right` (ball in socket)", "platonics_ball_socket/panda_right", "panda"
    ),
    "panda_left": Recording("platonics `panda_left`", "platonics_ball_socket/panda_left", "panda"),
    "panda_1": Recording("platonics `panda_1`", "platonics_ball_socket/panda_1", "panda"),
    "tiago_qualisys": Recording(
        "TIAGo Qualisys, 3 markers",
        "figaroh_tiago_mocap/qualysis/qualysis_base_hand_calibration.csv",
        urdf="robots/tiago_description/robots/tiago.urdf",
        base="base_footprint",
        tip="arm_7_link",
    ),
}
"""Recordings of the other measurement types (the type found from the file, as ``kincal
calibrate`` finds it: one point per socket file of a platonics folder, markers of the Qualisys
file)."""


def measured_row(recording: Recording, seeds: int) -> Row:
    """``recording`` calibrated with ``kincal calibrate``'s defaults (``seeds`` held-out
    splits): its own held-out coverage, the model-error σ of each residual component (mm) and
    the wall time of the calibration."""
    setup = pipeline.check_calibration(
        recording.description(), CalibrationOptions(seeds=list(range(1, seeds + 1)))
    )
    started = time.perf_counter()
    result = pipeline.calibrate_source(DATA / recording.path, setup).result
    seconds = time.perf_counter() - started
    predictive = result.predictive
    assert predictive is not None and predictive.coverage is not None, "no coverage measured"
    found = predictive.coverage
    observed = {level.level: level.observed for level in found.levels}
    return {
        "recording": recording.label,
        "measurement": "pose" if result.measurement is None else result.measurement.type,
        "used": result.outliers.n_used,
        "input": result.outliers.n_input,
        "dimension": found.dimension,
        "heldout": found.n_heldout,
        **{_inside(a): observed[a] for a in COVERAGE_LEVELS},
        "mean_d2": found.mean_mahalanobis_sq,
        "model_error_axes": predictive.model_error.axes,
        "model_error_std_mm": [1000.0 * std for std in predictive.model_error.std],
        "model_error_frame": predictive.model_error.frame,
        "seconds": seconds,
    }


MEASURED_HEADER = (
    "Recording",
    "used / input rows",
    "d",
    "held-out rows",
    "in 50 / 90 / 95 / 99 %",
    "mean d² (χ² mean)",
    "model error σ, mm",
    "calibrate s",
)


def render_measured(rows: list[Row]) -> str:
    """The table of ``docs/results/coverage_measurements.md`` (shares to the percent, mean d²
    to 2 decimals, model-error σ to 0.001 mm, the calibration's wall time to 0.1 s)."""

    def model_error(row: Row) -> str:
        stds = zip(row["model_error_axes"], row["model_error_std_mm"], strict=True)
        text = ", ".join(f"{axis} {std:.3f}" for axis, std in stds)
        frame = row["model_error_frame"]
        return text if frame is None else f"{text} ({frame})"

    return markdown_table(
        MEASURED_HEADER,
        [
            (
                r["recording"],
                f"{r['used']} / {r['input']}",
                r["dimension"],
                r["heldout"],
                _shares(r),
                f"{r['mean_d2']:.2f} ({r['dimension']})",
                model_error(r),
                f"{r['seconds']:.1f}",
            )
            for r in rows
        ],
    )


FOLDS = 10
"""The acceptance protocol of issue 13: K-fold cross-validation of the recording."""
BAND_95 = (0.90, 0.98)
"""Issue 13's band: the share of held-out poses inside the predicted 95 % ellipsoid."""
BAND_MEAN = 0.25
"""Issue 13's band: the mean d² within this fraction of the χ²_d mean d."""


@dataclass(frozen=True)
class FoldScore:
    """One fold of the cross-validation: the squared Mahalanobis distances of its scored
    held-out poses under the total (``total``) and under Σ_E + Σ_n (``before``), how many
    poses the training calibration's outlier rule screens out, or why the fold's calibration
    failed (``failed``; none of its poses scored)."""

    test_rows: int
    total: np.ndarray
    before: np.ndarray
    screened: int
    failed: str | None

    def row(self, dimension: int) -> Row:
        """Counts inside each level's χ²_``dimension`` ellipsoid and the means, for the results
        file (a fold of the :class:`FoldCoverage` row)."""
        scored = int(self.total.size)

        def inside(d2: np.ndarray, level: float) -> int:
            return int(np.count_nonzero(d2 <= chi2_quantile(level, dimension)))

        return {
            "test_rows": self.test_rows,
            "scored": scored,
            "screened": self.screened,
            **{_inside(a): inside(self.total, a) for a in COVERAGE_LEVELS},
            "mean_d2": float(np.mean(self.total)) if scored else None,
            "before_inside_95": inside(self.before, 0.95),
            "before_mean_d2": float(np.mean(self.before)) if scored else None,
            "failed": self.failed,
        }


@dataclass(frozen=True)
class FoldCoverage:
    """A recording's K-fold cross-validation through ``kincal calibrate`` → ``kincal
    predict`` with the defaults: every pose predicted by the calibration of the other folds
    and scored once, under the total covariance (``found``, today's ``kincal predict``) and
    under Σ_E + Σ_n (``before``, ``--part random-effects``: what it wrote before issue 13);
    ``screened``: held-out poses the training calibration's own outlier rule rejects (detector
    failures, not scored); ``failed``: folds whose calibration raised (their poses are not
    scored), with the message; ``folds``: each fold's scores."""

    label: str
    n_input: int
    found: Coverage
    before: Coverage
    screened: int
    failed: tuple[str, ...]
    seconds: float
    folds: tuple[FoldScore, ...]

    def row(self) -> Row:
        """The numbers of the results file ``coverage_folds`` (shares as fractions; each
        fold's counts under ``folds``)."""
        d = self.found.dimension
        return {
            "recording": self.label,
            "poses": self.n_input,
            "dimension": d,
            "scored": self.found.n,
            "screened": self.screened,
            "before_inside_95": self.before.at(0.95),
            "before_mean_d2": self.before.mean_d2,
            **{_inside(a): self.found.at(a) for a in COVERAGE_LEVELS},
            "mean_d2": self.found.mean_d2,
            "failed_folds": len(self.failed),
            "seconds": self.seconds,
            "folds": [fold.row(d) for fold in self.folds],
        }


def _measured_pose(dataset: PoseDataset) -> np.ndarray:
    return lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw)


@dataclass(frozen=True)
class HeldoutDistances:
    """Squared Mahalanobis distances (n,) of held-out poses under the total predicted
    covariance and under Σ_E + Σ_n alone, and which poses are scored (not detector
    failures)."""

    total: np.ndarray
    random_effects: np.ndarray
    scored: np.ndarray


def heldout_distances(result: CalibrationResult, test: PoseDataset) -> HeldoutDistances:
    """The distances of ``test``'s poses under ``kincal predict``'s covariances of ``result``,
    and which are not detector failures: with the model-based outlier rule, a held-out pose is
    one when its distance under the total exceeds the rule's family-wise threshold
    (:func:`~solver.stream.screening.family_wise_t2` with the calibration's N and degrees of
    freedom) — the rule the calibration applied to its own rows, with the covariance a
    held-out pose has (a calibrated row's residual is judged against Σ_E; a new pose's also
    carries the parameter and model-error parts). A clean pose is screened with probability
    below ``outlier_level / N``. Under any other rule every pose is scored."""
    measurement = test.measurement_model
    d = measurement.dim
    pose = result_json.predict_poses(result, test.joint_positions, test.payload_kg)
    residuals = measurement.residuals(pose, _measured_pose(test))
    parts = ranking.predict_covariance_parts(result, test.joint_positions, test.payload_kg)
    random = (parts["random_effects"] + parts["noise"])[:, :d, :d]
    total = random + (parts["parameters"] + parts["model_error"])[:, :d, :d]
    distances = mahalanobis_squared(residuals, total)
    before = mahalanobis_squared(residuals, random)
    return HeldoutDistances(distances, before, not_screened(result, distances, d))


def not_screened(result: CalibrationResult, distances: np.ndarray, d: int) -> np.ndarray:
    """Which held-out rows (n,) of squared distances ``distances`` under ``result``'s total
    (residual dimension ``d``) its model-based outlier rule keeps: the family-wise Hotelling
    threshold with the calibration's N and degrees of freedom (p: the parameters its Cov(θ̂)
    lists); every row under any other rule."""
    outliers = result.outliers
    if outliers.rule != "model" or outliers.level is None or result.predictive is None:
        return np.ones(distances.size, dtype=bool)
    p = len(result.predictive.parameter_covariance.parameters)
    threshold = family_wise_t2(outliers.level, outliers.n_input, d, outliers.n_used - p / d)
    return np.asarray(distances <= threshold)


def fold_scores(
    recording: Recording, folds: int = FOLDS, seed: int = 0, only: int | None = None
) -> tuple[int, int, list[FoldScore]]:
    """The number of poses, their dimension d and the :class:`FoldScore` of every fold of
    ``recording`` with ``kincal calibrate``'s defaults (of fold ``only`` alone if given)."""
    setup = pipeline.check_calibration(recording.description(), CalibrationOptions())
    chain = setup.chain
    dataset = read_dataset(
        DATA / recording.path, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    scores = []
    for index, (train, test) in enumerate(fold_indices(dataset.n_samples, folds, seed)):
        if only is not None and index != only:
            continue
        try:
            result = pipeline.calibrate_source(dataset.subset(train), setup).result
        except KincalError as exc:
            empty = np.zeros(0)
            scores.append(FoldScore(len(test), empty, empty, 0, f"{len(train)} rows: {exc}"))
            continue
        found = heldout_distances(result, dataset.subset(test))
        scores.append(
            FoldScore(
                len(test),
                found.total[found.scored],
                found.random_effects[found.scored],
                int(np.count_nonzero(~found.scored)),
                None,
            )
        )
    return dataset.n_samples, dataset.measurement_model.dim, scores


def cross_validate(recording: Recording, folds: int = FOLDS, seed: int = 0) -> FoldCoverage:
    """:class:`FoldCoverage` of ``recording`` with ``kincal calibrate``'s defaults."""
    started = time.perf_counter()
    n_input, d, scores = fold_scores(recording, folds, seed)
    return FoldCoverage(
        recording.label,
        n_input,
        coverage(np.concatenate([s.total for s in scores]), d),
        coverage(np.concatenate([s.before for s in scores]), d),
        sum(s.screened for s in scores),
        tuple(s.failed for s in scores if s.failed is not None),
        time.perf_counter() - started,
        tuple(scores),
    )


def holds(row: Row) -> str:
    """Whether a ``coverage_folds`` row is inside issue 13's band (:data:`BAND_95`,
    :data:`BAND_MEAN`), and whether it sits on the band's edge (to the percent shown)."""
    share, d = row["inside_95"], row["dimension"]
    if not (BAND_95[0] <= share <= BAND_95[1] and abs(row["mean_d2"] - d) <= BAND_MEAN * d):
        return "**no**"
    shown = round(100 * share)
    for edge, name in zip(BAND_95, ("lower", "upper"), strict=True):
        if shown == round(100 * edge):
            return f"yes, **at the band's {name} edge** ({shown} %)"
    return "yes"


FOLDS_HEADER = (
    "Recording",
    "Poses",
    "d",
    "Scored / screened",
    "Before (Σ_E + Σ_n): in 95 % / mean d²",
    "After (total): in 50 / 90 / 95 / 99 %",
    "After: mean d² (χ² mean)",
    "Failed folds",
    "Holds?",
)


def render_folds(rows: list[Row]) -> str:
    """The table of ``docs/results/coverage_folds.md``: issue 13's acceptance, K-fold
    cross-validation through calibrate → predict (shares to the percent, mean d² to 1 and 2
    decimals)."""
    return markdown_table(
        FOLDS_HEADER,
        [
            (
                r["recording"],
                r["poses"],
                r["dimension"],
                f"{r['scored']} / {r['screened']}",
                f"{100 * r['before_inside_95']:.0f} % / {mean_d2_text(r['before_mean_d2'])}",
                _shares(r),
                f"{r['mean_d2']:.2f} ({r['dimension']})",
                r["failed_folds"],
                holds(r),
            )
            for r in rows
        ],
    )


PARTITIONS = 3
"""Issue 31: the 10-fold protocol repeated over this many random partitions of the recording
(seeds 0, 1, ...; partition 0 is :data:`coverage_folds`'s)."""


def partition_row(partitions: list[FoldCoverage], seeds: list[int]) -> Row:
    """The numbers of the results file ``coverage_partitions``: per partition (its seed, the
    scored and screened poses, the share inside the 95 % ellipsoid, the mean and largest d²,
    each fold's counts) and pooled over the partitions (each pose scored once per
    partition)."""
    d = partitions[0].found.dimension
    every = np.concatenate([s.total for p in partitions for s in p.folds])
    pooled = coverage(every, d)
    return {
        "recording": partitions[0].label,
        "poses": partitions[0].n_input,
        "dimension": d,
        "partitions": [
            {
                "seed": seed,
                "scored": p.found.n,
                "screened": p.screened,
                "inside_95": p.found.at(0.95),
                "mean_d2": p.found.mean_d2,
                "max_d2": float(max((s.total.max() for s in p.folds if s.total.size), default=0)),
                "failed_folds": len(p.failed),
                "folds": [fold.row(d) for fold in p.folds],
            }
            for seed, p in zip(seeds, partitions, strict=True)
        ],
        "inside_95": pooled.at(0.95),
        "mean_d2": pooled.mean_d2,
    }


BAND_MEAN_PARTITIONS = 0.20
"""Issue 31's band over partitions, for every recording and measurement type: the mean d²
within this fraction of d (the share inside the 95 % region in :data:`BAND_95`)."""


def in_band(share: float, mean_d2: float, dimension: int) -> bool:
    """Issue 31's band (:data:`BAND_95`, :data:`BAND_MEAN_PARTITIONS`)."""
    return (
        BAND_95[0] <= share <= BAND_95[1]
        and abs(mean_d2 - dimension) <= BAND_MEAN_PARTITIONS * dimension
    )


def partition_cell(part: Row, dimension: int, share_digits: int) -> str:
    """One partition of a partitions table: its seed, share inside the 95 % region (to
    ``share_digits``), mean and largest d², screened rows; ✗ outside :func:`in_band`."""
    mark = "" if in_band(part["inside_95"], part["mean_d2"], dimension) else " ✗"
    return (
        f"{part['seed']}: {100 * part['inside_95']:.{share_digits}f} % / "
        f"{part['mean_d2']:.2f} / {part['max_d2']:.0f} ({part['screened']}){mark}"
    )


def band_cell(row: Row) -> str:
    """How many of a row's partitions are in the band, and whether the pooled row is."""
    d, parts = row["dimension"], row["partitions"]
    held = sum(in_band(p["inside_95"], p["mean_d2"], d) for p in parts)
    pooled = in_band(row["inside_95"], row["mean_d2"], d)
    return f"{held} of {len(parts)} partitions" + ("" if pooled else "; pooled: **no**")


PARTITIONS_HEADER = (
    "Recording",
    "d",
    "Partition (seed): in 95 % / mean d² / largest d² (screened)",
    "Spread of in 95 %",
    "Pooled: in 95 % / mean d²",
    "In the band",
)


def render_partitions(rows: list[Row]) -> str:
    """The table of ``docs/results/coverage_partitions.md``: the 10-fold protocol over several
    random partitions, each partition's coverage, its spread and the pooled coverage."""
    body = []
    for r in rows:
        d, parts = r["dimension"], r["partitions"]
        shares = [100 * p["inside_95"] for p in parts]
        body.append(
            (
                r["recording"],
                d,
                "; ".join(partition_cell(p, d, 0) for p in parts),
                f"{min(shares):.0f}–{max(shares):.0f} %",
                f"{100 * r['inside_95']:.0f} % / {r['mean_d2']:.2f}",
                band_cell(r),
            )
        )
    return markdown_table(PARTITIONS_HEADER, body)


# --- issue 31: the 10-fold protocol for the other measurement types --------------------------


@dataclass(frozen=True)
class TypeCoverage:
    """A measurement type's 10-fold protocol: ``recordings`` (one, or the arms pooled),
    the ``kincal calibrate`` options a user gives them beyond the defaults, and ``scored``:
    what a held-out row is scored on and in which frame (the page says it)."""

    label: str
    scored: str
    recordings: tuple[Recording, ...]
    options: tuple[tuple[str, object], ...] = ()

    def setup(self, recording: Recording) -> pipeline.CalibrationSetup:
        options = CalibrationOptions(**dict(self.options))  # type: ignore[arg-type]
        return pipeline.check_calibration(recording.description(), options)


def _platonics_arms() -> tuple[Recording, ...]:
    folder = DATA / "platonics_ball_socket"
    arms = sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name.startswith("panda"))
    return tuple(Recording(arm, f"platonics_ball_socket/{arm}", "panda") for arm in arms)


TYPES = {
    "platonics": TypeCoverage(
        "platonics, the twelve Panda arms pooled (ball in socket)",
        "the ball centre against its socket point (3-D), robot base frame",
        _platonics_arms(),
    ),
    "tiago_markers": TypeCoverage(
        "TIAGo Qualisys, four markers (three distinct)",
        "the stacked marker positions (3·3-D), measurement frame",
        (MEASURED["tiago_qualisys"],),
    ),
    "tiago_relative": TypeCoverage(
        "TIAGo Vicon gripper3/base1, relative base, joint offsets",
        "the tip position relative to the base marker (3-D), tip frame",
        (
            Recording(
                "TIAGo Vicon relative base",
                "figaroh_tiago_mocap/vicon/relative_encoder/vicon_calibration_fc10_gripper3_base1.csv",
                urdf="robots/tiago_description/robots/tiago.urdf",
                base="base_footprint",
                tip="arm_tool_link",
            ),
        ),
        (("measurement", "relative-base"), ("free_parameters", ["joint_offsets"])),
    ),
    "positioner": TypeCoverage(
        "2-axis positioner, DH table (pose)",
        "the 6-D pose of the target (Log of predicted⁻¹ · measured), tip frame",
        (
            Recording(
                "2-axis positioner",
                "industrial_calibration_2axis_positioner/measurements.yaml",
                dh="industrial_calibration_2axis_positioner/positioner_dh.yaml",
            ),
        ),
    ),
}
"""Issue 31's other measurement types, each with the flags of benchmarks/evaluate_real.py
(the platonics as :data:`MEASURED` calibrates them: the type found from the folder, no socket
distance). The positioner's recording is a pose recording (the streamed path of
:func:`fold_scores`); the others are calibrated in memory (:func:`measured_fold_scores`)."""


def measured_fold_scores(
    recording: Recording,
    setup: pipeline.CalibrationSetup,
    folds: int = FOLDS,
    seed: int = 0,
    only: int | None = None,
) -> tuple[int, int, list[FoldScore]]:
    """:func:`fold_scores` of a measurement-model recording (ball in socket, markers,
    relative base): the recording read once as ``kincal calibrate`` reads it, each fold's
    training rows calibrated by :func:`service.app.calibrate.calibrate_measured` (what
    ``kincal calibrate`` runs on rows in memory, with ``setup``'s options), its held-out rows
    scored in the model's residual space under the result's total predictive covariance
    (:func:`solver.measurement.predictive.total_distances` with the result's Cov(θ̂) and
    model-error part) and under Σ_E + noise; rows the training calibration's outlier rule
    screens out (:func:`not_screened`) are counted, not scored."""
    source = DATA / recording.path
    model = measurement_input.measurement_for(setup.options, setup.chain, source, None)
    assert model is not None, f"{recording.path} is a pose recording"
    whole = measurement_input.read_measured(source, setup.chain, setup.options, model)
    d = whole.model.dim
    scores = []
    for index, (train, test) in enumerate(fold_indices(whole.rows.n, folds, seed)):
        if only is not None and index != only:
            continue
        try:
            run = pipeline.calibrate_measured(
                dataclasses.replace(whole, rows=whole.rows.take(train)), setup
            )
        except KincalError as exc:
            empty = np.zeros(0)
            scores.append(FoldScore(len(test), empty, empty, 0, f"{len(train)} rows: {exc}"))
            continue
        assert run.measured is not None and run.measured.predictive is not None
        predictive = run.measured.predictive
        total, before = total_distances(
            setup.chain,
            predictive.predictor,
            predictive.model_error.variance,
            whole.rows.take(test),
        )
        kept = not_screened(run.result, total, d)
        scores.append(
            FoldScore(len(test), total[kept], before[kept], int(np.count_nonzero(~kept)), None)
        )
    return whole.rows.n, d, scores


def type_fold_scores(
    kind: TypeCoverage,
    recording: Recording,
    folds: int = FOLDS,
    seed: int = 0,
    only: int | None = None,
) -> tuple[int, int, list[FoldScore]]:
    """The folds of one recording of ``kind``: the streamed pose path for a pose recording
    (the positioner), the measurement-model path otherwise."""
    setup = kind.setup(recording)
    model = measurement_input.measurement_for(
        setup.options, setup.chain, DATA / recording.path, None
    )
    if model is None:
        return fold_scores(recording, folds, seed, only)
    return measured_fold_scores(recording, setup, folds, seed, only)


def type_row(kind: TypeCoverage, folds: int, seeds: list[int]) -> Row:
    """The numbers of the results file ``coverage_types_partitions``: per partition (seed) the
    folds of every recording of ``kind`` (each fold's counts, with its recording), the scored
    and screened rows, the share inside the 95 % region, the mean and largest d², pooled over
    the recordings; and pooled over the partitions; the CPU seconds of the whole row."""
    started = time.process_time()
    partitions: list[Row] = []
    every: list[np.ndarray] = []
    rows = 0
    d = 0
    for seed in seeds:
        fold_rows: list[Row] = []
        distances: list[np.ndarray] = []
        screened = failed = 0
        rows = 0
        for recording in kind.recordings:
            n, d, scores = type_fold_scores(kind, recording, folds, seed)
            rows += n
            for index, score in enumerate(scores):
                fold_rows.append({"recording": recording.label, "fold": index, **score.row(d)})
                distances.append(score.total)
                screened += score.screened
                failed += score.failed is not None
        joined = np.concatenate(distances)
        found = coverage(joined, d)
        every.append(joined)
        partitions.append(
            {
                "seed": seed,
                "scored": found.n,
                "screened": screened,
                "inside_95": found.at(0.95),
                "mean_d2": found.mean_d2,
                "max_d2": float(joined.max(initial=0.0)),
                "failed_folds": failed,
                "folds": fold_rows,
            }
        )
        print(
            f"{kind.label}, partition {seed}: {found.n} rows scored ({screened} screened, "
            f"{failed} folds failed), {100 * found.at(0.95):.1f} % in 95 %, mean d² "
            f"{found.mean_d2:.2f} (d = {d}), largest {joined.max(initial=0.0):.1f}, "
            f"{time.process_time() - started:.0f} CPU s",
            flush=True,
        )
    pooled = coverage(np.concatenate(every), d)
    return {
        "recording": kind.label,
        "scored_on": kind.scored,
        "recordings": [r.label for r in kind.recordings],
        "rows": rows,
        "dimension": d,
        "partitions": partitions,
        "inside_95": pooled.at(0.95),
        "mean_d2": pooled.mean_d2,
        "cpu_s": time.process_time() - started,
    }


TYPES_HEADER = (
    "Measurement (recordings)",
    "Scored on, frame",
    "Rows",
    "d",
    "Partition (seed): in 95 % / mean d² / largest d² (screened)",
    "Pooled: in 95 % / mean d²",
    "In the band",
    "CPU s",
)


def render_types(rows: list[Row]) -> str:
    """The table of ``docs/results/coverage_types_partitions.md``: the 10-fold protocol of
    each measurement type over its partitions (issue 31's band: :data:`BAND_95`, mean d²
    within :data:`BAND_MEAN_PARTITIONS` of d; ✗ marks a partition outside it)."""
    body = []
    for r in rows:
        d, parts = r["dimension"], r["partitions"]
        body.append(
            (
                r["recording"],
                r["scored_on"],
                r["rows"],
                d,
                "; ".join(partition_cell(p, d, 1) for p in parts),
                f"{100 * r['inside_95']:.1f} % / {r['mean_d2']:.2f}",
                band_cell(r),
                f"{r['cpu_s']:.0f}",
            )
        )
    return markdown_table(TYPES_HEADER, body)


def types_main(names: list[str], folds: int, partitions: dict[str, int], write: bool) -> list[Row]:
    """The ``coverage_types_partitions`` table (printed; written with ``write``):
    ``partitions`` per type name (default :data:`PARTITIONS`)."""
    rows = [
        type_row(TYPES[name], folds, list(range(partitions.get(name, PARTITIONS))))
        for name in names
    ]
    print("\n" + render_types(rows))
    if write:
        arguments = f"--types {','.join(names)} --folds {folds}"
        if partitions:
            arguments += " --type-partitions " + ",".join(f"{k}={v}" for k, v in partitions.items())
        command = f"python -m benchmarks.coverage {arguments} --write-results"
        for path in write_results("coverage_types_partitions", command, rows, render_types):
            print("wrote", path)
    return rows


def main(
    seeds: int = 10,
    names: list[str] | None = None,
    folds: int = FOLDS,
    *,
    measured: list[str] | None = None,
    partitions: int = PARTITIONS,
    write: bool = False,
) -> tuple[list[Row], list[Row], list[Row], list[Row]]:
    """The four tables (printed; written as results files with ``write``): the rows of
    ``coverage_folds``, ``coverage_rules``, ``coverage_measurements`` and
    ``coverage_partitions``."""
    chosen = names or list(RECORDINGS)
    chosen_measured = list(MEASURED) if measured is None else measured
    validated: list[Row] = []
    spread: list[Row] = []
    for name in chosen:
        fold = cross_validate(RECORDINGS[name], folds)
        more = [cross_validate(RECORDINGS[name], folds, seed) for seed in range(1, partitions)]
        spread.append(partition_row([fold, *more], list(range(partitions))))
        print(
            f"{fold.label}: {folds}-fold, {fold.found.n} poses scored ({fold.screened} "
            f"screened, {len(fold.failed)} folds failed): {100 * fold.found.at(0.95):.0f} % in "
            f"the 95 % ellipsoid, mean d² {fold.found.mean_d2:.2f} (χ² mean "
            f"{fold.found.dimension}), {fold.seconds:.0f} s",
            flush=True,
        )
        for message in fold.failed:
            print(f"  failed fold: {message}", flush=True)
        validated.append(fold.row())
    rows: list[Row] = []
    for name in chosen:
        for rule in RULES:
            row = measure(RECORDINGS[name], rule, seeds)
            shares = ", ".join(f"{100 * v:.0f} %" for v in row.total)
            print(
                f"{row.label} ({row.rule}): total {shares}"
                f" in the 50/90/95/99 % ellipsoids, mean d² {row.total_mean:.2f} "
                f"(χ² mean {row.dimension}); Σ_E + Σ_n alone {100 * row.random_95:.0f} % in 95 %"
                f", {row.seconds:.1f} s",
                flush=True,
            )
            rows.append(row.row())
    others: list[Row] = []
    for name in chosen_measured:
        other = measured_row(MEASURED[name], seeds)
        print(
            f"{other['recording']} ({other['measurement']}): "
            + ", ".join(f"{100 * other[_inside(a)]:.0f} %" for a in COVERAGE_LEVELS)
            + f" in the 50/90/95/99 % ellipsoids, mean d² {other['mean_d2']:.2f} (χ² mean "
            f"{other['dimension']}), {other['seconds']:.1f} s",
            flush=True,
        )
        others.append(other)
    print(
        "\n"
        + render_folds(validated)
        + "\n\n"
        + render_rules(rows)
        + "\n\n"
        + render_measured(others)
        + "\n\n"
        + render_partitions(spread)
    )
    if write:
        arguments = f"--seeds {seeds} --folds {folds} --partitions {partitions}"
        if names is not None and names != list(RECORDINGS):
            arguments += f" --recordings {','.join(names)}"
        if chosen_measured != list(MEASURED):
            arguments += f" --measured {','.join(chosen_measured)}"
        command = f"python -m benchmarks.coverage {arguments} --write-results"
        for path in (
            *write_results("coverage_folds", command, validated, render_folds),
            *write_results("coverage_rules", command, rows, render_rules),
            *write_results("coverage_measurements", command, others, render_measured),
            *write_results("coverage_partitions", command, spread, render_partitions),
        ):
            print("wrote", path)
    return validated, rows, others, spread


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of held-out splits")
    parser.add_argument("--folds", type=int, default=FOLDS, help="folds of the cross-validation")
    parser.add_argument(
        "--recordings",
        default=",".join(RECORDINGS),
        help="comma-separated: " + ", ".join(RECORDINGS),
    )
    parser.add_argument(
        "--measured",
        default=",".join(MEASURED),
        help="other measurement types, comma-separated: " + ", ".join(MEASURED),
    )
    parser.add_argument(
        "--partitions",
        type=int,
        default=PARTITIONS,
        help="random partitions of the K-fold protocol (seeds 0, 1, ...)",
    )
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/coverage_{folds,rules,measurements,partitions}.{json,md}",
    )
    parser.add_argument(
        "--types",
        default=None,
        help="run only issue 31's measurement-type table (coverage_types_partitions), for "
        "these types, comma-separated: " + ", ".join(TYPES),
    )
    parser.add_argument(
        "--type-partitions",
        default="",
        help="partitions per type where not --partitions, e.g. platonics=2",
    )
    arguments = parser.parse_args()
    if arguments.types is not None:
        per_type = dict(
            (k, int(v))
            for k, _, v in (p.partition("=") for p in arguments.type_partitions.split(",") if p)
        )
        for name in arguments.types.split(","):
            per_type.setdefault(name, arguments.partitions)
        types_main(arguments.types.split(","), arguments.folds, per_type, arguments.write_results)
        raise SystemExit(0)
    main(
        arguments.seeds,
        arguments.recordings.split(","),
        arguments.folds,
        measured=arguments.measured.split(","),
        partitions=arguments.partitions,
        write=arguments.write_results,
    )
