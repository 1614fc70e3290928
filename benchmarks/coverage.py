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

Each recording runs with the default outlier rule and with ``outlier_sigma`` 0 (the paper's 2σ
rule truncates the residuals, so the covariances it leaves are too small and the poses it drops
are missing from the test rows as well).

Usage: ``python benchmarks/coverage.py [--seeds 10] [--recordings fr3,ur10e,...]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import solver  # noqa: F401  (BLAS defaults)
from schemas.calibration import CalibrationOptions
from service import pipeline
from service.robots import RobotDescription, example_robot_data_dir, load_robot
from solver.predictive import COVERAGE_LEVELS, coverage
from solver.stream.coverage import PredictiveCalibration, ScoredRows

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

    def description(self) -> RobotDescription:
        if self.robot is not None:
            return load_robot(self.robot)
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


def _share_and_mean(distances: np.ndarray, dimension: int) -> tuple[float, float]:
    found = coverage(distances, dimension)
    return found.at(0.95), found.mean_d2


def measure(recording: Recording, outlier_sigma: float | None, seeds: int) -> CoverageRow:
    """Calibrate ``recording`` like ``kincal calibrate`` with the given outlier rule and take
    its held-out splits apart."""
    options = CalibrationOptions(outlier_sigma=outlier_sigma, seeds=list(range(1, seeds + 1)))
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
        "none" if outlier_sigma is None else f"{outlier_sigma:g}σ",
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


def table(rows: list[CoverageRow]) -> str:
    """The markdown table of the README."""
    header = [
        "Recording",
        "Outlier rule",
        "Used / input",
        "d",
        "Held-out poses",
        "Σ_E + Σ_n: in 95 % / mean d²",
        "+ Cov(θ̂): in 95 % / mean d²",
        "Total: in 50 / 90 / 95 / 99 %",
        "Total: mean d² (χ² mean)",
        "Time",
    ]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for r in rows:
        total = " / ".join(f"{100 * v:.0f}" for v in r.total)
        lines.append(
            f"| {r.label} | {r.rule} | {r.n_used} / {r.n_input} | {r.dimension} | {r.n_heldout} "
            f"| {100 * r.random_95:.0f} % / {r.random_mean:.1f} "
            f"| {100 * r.parameters_95:.0f} % / {r.parameters_mean:.1f} "
            f"| {total} | {r.total_mean:.2f} ({r.dimension}) | {r.seconds:.0f} s |"
        )
    return "\n".join(lines)


def main(seeds: int = 10, names: list[str] | None = None) -> str:
    rows = []
    for name in names or list(RECORDINGS):
        for sigma in (2.0, None):
            row = measure(RECORDINGS[name], sigma, seeds)
            shares = ", ".join(f"{100 * v:.0f} %" for v in row.total)
            print(
                f"{row.label} ({row.rule}): total {shares}"
                f" in the 50/90/95/99 % ellipsoids, mean d² {row.total_mean:.2f} "
                f"(χ² mean {row.dimension}); Σ_E + Σ_n alone {100 * row.random_95:.0f} % in 95 %",
                flush=True,
            )
            rows.append(row)
    out = table(rows)
    print("\n" + out)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of held-out splits")
    parser.add_argument(
        "--recordings",
        default=",".join(RECORDINGS),
        help="comma-separated: " + ", ".join(RECORDINGS),
    )
    arguments = parser.parse_args()
    main(arguments.seeds, arguments.recordings.split(","))
