"""Table II and Fig. 4b: held-out errors of the product's calibration and of the GP baseline of
ref. [13] on the same splits, and the calibrated σ per frame."""

from __future__ import annotations

import dataclasses

import numpy as np

from benchmarks.reproduce_paper.simulation import Recording, kept_rows
from schemas.calibration import CalibrationResult
from service.app import calibrate as pipeline
from service.render import result_json
from solver.arrays import FloatArray
from solver.evaluation import cross_validate, split_indices
from solver.gp_baseline import gp_calibration_method


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
                    measurement=data.measurement,
                    baseline_options=pipeline.fit_options(
                        options, baseline=True, n_links=data.chain.n_links
                    ),
                )
            },
            rotation=data.measurement.measures_rotation,
            seeds=options.seeds,
            train_fraction=options.train_fraction,
        ):
            errors.setdefault("gp", {})[gp_split.seed] = (
                gp_split.translation_mm,
                float(gp_split.rotation_deg or 0.0),
            )
    return TableII(tuple(result.options.seeds), errors)


def covariance_std(result: CalibrationResult) -> FloatArray:
    """Calibrated σ (k + 1, 6): joint frames in chain order, then the noise; m and rad (NaN
    where the data cannot see the axis: ``std`` null, ``not_identifiable`` says why)."""
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
    options = result.options.model_copy(update={"heldout": False, "outlier_rule": "none"})
    out = []
    for seed in result.options.seeds:
        train, _ = split_indices(used.size, seed, result.options.train_fraction)
        subset = recording.dataset.subset(used[train])
        out.append(covariance_std(pipeline.calibrate(subset, recording.robot, options)))
    return np.array(out)
