"""Data-driven model selection for the deterministic fit (issue 30's last open point;
docs/figaroh.md, "Choosing the model by the data"): which of the directions the data identify
to fit, and how far, decided on the training rows alone — measured on the held-out splits of the
FIGAROH side by side (:mod:`benchmarks.figaroh_side_by_side`: UR10e, TIAGo, TALOS; seeds
1..S, 90 % train, all rows, which the default calibration keeps on these three files),
for ``--fix compliance`` (geometry and frames: FIGAROH's model) and the default model
(geometry and joint compliance).

Methods, each fitted on a split's training rows only (exact fits, iterated to convergence):

- ``today``: kincal's fit (pivoted-QR columns, frames first; the physical-range rule
  :func:`solver.calibration.implausible_columns`).
- ``ridge-gcv``: the same columns (pivoted QR of the training rows' Jacobian), the inner-link
  placement corrections ``ξ_i = Log(L_i,nominal⁻¹ L_i)`` (i = 2..k; m and rad) shrunk toward
  the URDF by a Gaussian prior ``ξ ~ N(0, diag(s_t², s_t², s_t², s_r², s_r², s_r²))``: the
  fit minimises ``‖W r‖² + σ̂² Σ_i ‖S⁻¹ ξ_i‖²`` with σ̂ the residual scale of ``today`` (m).
  ``s_r = s_t · 2 rad/m`` (the physical-range rule's 5 cm : 0.1 rad), ``s_t`` on a grid
  5 cm · 2^(−j/2), j = 0..20, so the prior never allows more than the physical range; chosen
  per split by generalised cross-validation of the Gauss–Newton step at the solution,
  ``GCV = (RSS/m) / (1 − tr H/m)²``, ``H = A (AᵀA + σ̂² S⁻²)⁻¹ Aᵀ`` (A the weighted rows'
  Jacobian over the fitted columns, m its rows).
- ``ridge-gcv-2d``: as ``ridge-gcv`` with ``s_t`` (5 cm · 2^−j) and ``s_r`` (0.1 rad · 2^−j),
  j = 0..7, chosen independently (64 fits per split).
- ``ridge-gcv-uncapped`` (``--fix compliance`` only): ``s_t`` up to 1.6 m (``s_r`` likewise
  beyond 0.1 rad) and no physical-range rule: what the data alone choose.
- ``nested-cv``: nested column sets — ``today``'s columns with 0..12 inner-link columns left
  out, largest standard error relative to the physical range (``se/5 cm``, ``se/0.1 rad``)
  first — the number chosen by 5-fold cross-validation within the training rows (mean
  position error of the left-out folds).

Printed: per method, robot and model, the held-out mean position error (mean ± one standard
error over the splits), the largest inner-link correction any split's chosen fit made
(rotation, rad), and FIGAROH's held-out error (docs/figaroh.md, run of 2026-11-28, rounded
there to 0.01 mm).

With ``--write-results`` also ``docs/results/model_selection.{json,md}`` (docs/figaroh.md).
Usage (from the repository root): ``python -m benchmarks.model_selection [--seeds 10]
[--only TIAGo] [--method ridge-gcv] [--write-results]``; about 10 minutes for everything on a
shared 2-core machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.figaroh_side_by_side import DATA, RECORDINGS, Recording, mean_se, robot_of
from benchmarks.results import Row, markdown_table, write_results
from schemas.calibration import CalibrationOptions
from service.app import calibrate as pipeline
from solver import lie
from solver.arrays import FloatArray, IntArray
from solver.calibration import FitOptions, frame_columns, free_columns, pivoted_columns
from solver.errors import CalibrationError
from solver.evaluation import split_indices
from solver.kinematics import parameter_names
from solver.measurement.fit import MeasurementFit, fit_measurement, row_errors, row_weights
from solver.measurement.models import (
    FullPose,
    MeasurementModel,
    MeasurementRows,
    ModelParameters,
    Position,
    chain_column_count,
)
from solver.model import KinematicChain, gravity_loads

FIGAROH_MM = {"UR10e": (4.39, 0.38), "TIAGo": (6.85, 0.35), "TALOS": (0.56, 0.04)}
"""FIGAROH ``full_params`` held-out error, mean ± SE over the ten splits (docs/figaroh.md)."""

PHYSICAL_ROTATION_PER_TRANSLATION_RAD_PER_M = 2.0
"""The physical-range rule's limits, 0.1 rad : 5 cm."""

PHYSICAL_TRANSLATION_M = 0.05
PHYSICAL_ROTATION_RAD = 0.1


class _TowardNominal(MeasurementModel):
    """A pose measurement plus prior rows ``r_p = −w ⊙ ξ_i``, ``A_p = diag(w)`` on the
    inner-link columns of ``L_i`` (i = 2..k): the Gaussian prior of ``ridge-gcv`` as extra
    equations of Eq. (10); ``w`` (6,) is σ̂ / (s_t, s_t, s_t, s_r, s_r, s_r) (m/m, m/rad).
    ``A_p`` takes ``dξ/dδ ≈ I`` for the right-multiplied step δ (exact at ξ = 0)."""

    def __init__(self, weights: FloatArray) -> None:
        self.weights = np.asarray(weights, dtype=float)

    def constraints(
        self, chain: KinematicChain, params: ModelParameters
    ) -> tuple[FloatArray, FloatArray]:
        inner = range(1, chain.n_links - 1)
        n_columns = chain_column_count(chain) + len(self.extra_names())
        residual = np.zeros(6 * len(inner))
        design = np.zeros((6 * len(inner), n_columns))
        for row, link in enumerate(inner):
            xi = lie.se3_log(lie.inverse(chain.nominal_links[link]) @ params.links[link])
            residual[6 * row : 6 * row + 6] = -self.weights * xi
            design[6 * row : 6 * row + 6, 6 * link : 6 * link + 6] = np.diag(self.weights)
        return residual, design


class _PoseTowardNominal(_TowardNominal, FullPose):
    pass


class _PositionTowardNominal(_TowardNominal, Position):
    pass


def toward_nominal(measurement: FullPose, weights: FloatArray) -> MeasurementModel:
    """``measurement`` (a pose or a position) with the prior rows of :class:`_TowardNominal`."""
    if measurement.measures_rotation:
        return _PoseTowardNominal(weights)
    return _PositionTowardNominal(weights)


def data_columns(
    chain: KinematicChain, model: MeasurementModel, rows: MeasurementRows, options: FitOptions
) -> IntArray:
    """The columns :func:`~solver.measurement.fit.fit_measurement` chooses on ``rows`` by
    pivoted QR at its start (frames first), without prior rows."""
    _, jacobian = model.linearise(chain, model.start(chain, rows), rows)
    assert jacobian is not None
    jacobian = jacobian * row_weights(model, options)[None, :, None]
    n_columns = jacobian.shape[2]
    free = free_columns(chain, options, n_columns)
    free[: chain_column_count(chain)] &= model.visible_columns(chain)
    keep, _, _ = pivoted_columns(
        jacobian.reshape(-1, n_columns),
        free,
        options.rank_tolerance,
        frame_columns(chain, n_columns),
    )
    return keep


def fitted_columns(chain: KinematicChain, model: MeasurementModel, fit: MeasurementFit) -> IntArray:
    names = parameter_names(chain) + model.extra_names()
    return np.array([names.index(name) for name in fit.estimated], dtype=np.intp)


def gcv_score(
    chain: KinematicChain, model: MeasurementModel, fit: MeasurementFit, options: FitOptions
) -> float:
    """``(RSS/m) / (1 − tr H/m)²`` (m²) of the Gauss–Newton step at ``fit``, with
    ``H = A (AᵀA + A_pᵀA_p)⁻¹ Aᵀ`` over the fitted columns (``A_p``: the prior rows)."""
    keep = fitted_columns(chain, model, fit)
    design = fit.jacobian.reshape(-1, keep.size)
    data_gram = design.T @ design
    _, prior = model.constraints(chain, fit.params)
    gram = data_gram + prior[:, keep].T @ prior[:, keep]
    trace = float(np.trace(np.linalg.pinv(gram, hermitian=True) @ data_gram))
    m = design.shape[0]
    rss = float(np.sum((fit.residuals * row_weights(model, options)) ** 2))
    return rss / m / (1.0 - trace / m) ** 2


def residual_scale_m(model: MeasurementModel, fit: MeasurementFit, options: FitOptions) -> float:
    """σ̂ = sqrt(‖W r‖² / (m − p)) of a fit (m)."""
    weighted = fit.residuals * row_weights(model, options)
    return float(np.sqrt(np.sum(weighted**2) / (weighted.size - len(fit.estimated))))


def largest_inner_rotation_rad(chain: KinematicChain, params: ModelParameters) -> float:
    """max |ξ_i,rot| over the inner links (rad)."""
    return max(
        float(np.abs(lie.se3_log(lie.inverse(chain.nominal_links[i]) @ params.links[i])[3:]).max())
        for i in range(1, chain.n_links - 1)
    )


@dataclass(frozen=True)
class Problem:
    chain: KinematicChain
    model: FullPose
    options: FitOptions


Method = Callable[[Problem, MeasurementRows], MeasurementFit]


def fit_today(problem: Problem, train: MeasurementRows) -> MeasurementFit:
    return fit_measurement(problem.chain, problem.model, train, problem.options)


def ridge_by_gcv(scales: Sequence[tuple[float, float]], *, physical_rule: bool = True) -> Method:
    """``ridge-gcv`` over prior scales ``(s_t m, s_r rad)``."""

    def fit(problem: Problem, train: MeasurementRows) -> MeasurementFit:
        sigma = residual_scale_m(problem.model, fit_today(problem, train), problem.options)
        keep = data_columns(problem.chain, problem.model, train, problem.options)
        options = (
            problem.options
            if physical_rule
            else dataclasses.replace(problem.options, non_negative_compliance=False)
        )
        best: tuple[float, MeasurementFit] | None = None
        for s_t, s_r in scales:
            weights = sigma / np.array([s_t, s_t, s_t, s_r, s_r, s_r])
            model = toward_nominal(problem.model, weights)
            candidate = fit_measurement(problem.chain, model, train, options, columns=keep)
            score = gcv_score(problem.chain, model, candidate, options)
            if best is None or score < best[0]:
                best = (score, candidate)
        assert best is not None
        return best[1]

    return fit


def one_scale(exponents: range) -> list[tuple[float, float]]:
    return [
        (s, s * PHYSICAL_ROTATION_PER_TRANSLATION_RAD_PER_M)
        for s in (PHYSICAL_TRANSLATION_M * 2.0 ** (-j / 2) for j in exponents)
    ]


TWO_SCALES = [
    (PHYSICAL_TRANSLATION_M * 2.0**-j, PHYSICAL_ROTATION_RAD * 2.0**-k)
    for j, k in itertools.product(range(8), range(8))
]

NESTED_DROPS = 12
FOLDS = 5


def position_errors_mm(
    problem: Problem, params: ModelParameters, rows: MeasurementRows
) -> FloatArray:
    residual, _ = problem.model.linearise(problem.chain, params, rows, jacobian=False)
    return row_errors(problem.model, residual)[0]


def nested_by_cv(problem: Problem, train: MeasurementRows) -> MeasurementFit:
    """``nested-cv``: today's columns less the k inner-link columns of largest relative
    standard error, k by 5-fold cross-validation."""
    chain = problem.chain
    full = fit_today(problem, train)
    keep = fitted_columns(chain, problem.model, full)
    relative = np.where(
        keep % 6 < 3,
        full.standard_errors / PHYSICAL_TRANSLATION_M,
        full.standard_errors / PHYSICAL_ROTATION_RAD,
    )
    inner = (keep >= 6) & (keep < 6 * (chain.n_links - 1))
    order = [keep[i] for i in np.argsort(-relative) if inner[i]]
    sets = [keep] + [
        np.setdiff1d(keep, order[:k]) for k in range(1, min(NESTED_DROPS, len(order)) + 1)
    ]
    folds = np.random.default_rng(0).permutation(train.n) % FOLDS
    scores = []
    for columns in sets:
        errors = []
        for k in range(FOLDS):
            fold_train, fold_test = (
                train.take(np.flatnonzero(m)) for m in (folds != k, folds == k)
            )
            try:
                fit = fit_measurement(
                    chain, problem.model, fold_train, problem.options, columns=columns
                )
            except CalibrationError:
                errors.append(np.full(fold_test.n, np.inf))
                continue
            errors.append(position_errors_mm(problem, fit.params, fold_test))
        scores.append(float(np.concatenate(errors).mean()))
    chosen = sets[int(np.argmin(scores))]
    return fit_measurement(chain, problem.model, train, problem.options, columns=chosen)


METHODS: dict[str, Method] = {
    "today": fit_today,
    "ridge-gcv": ridge_by_gcv(one_scale(range(21))),
    "ridge-gcv-2d": ridge_by_gcv(TWO_SCALES),
    "ridge-gcv-uncapped": ridge_by_gcv(one_scale(range(-20, 21)), physical_rule=False),
    "nested-cv": nested_by_cv,
}
FIX_COMPLIANCE_ONLY = {"ridge-gcv-uncapped"}
MODELS = {"--fix compliance": FitOptions(fit_compliance=False), "default": FitOptions()}


def load_rows(recording: Recording) -> tuple[KinematicChain, MeasurementRows, FullPose]:
    """The recording's chain (default options), all its rows and what they measure (a pose or
    a position)."""
    from schemas.dataset import read_dataset

    chain = pipeline.check_calibration(robot_of(recording), CalibrationOptions()).chain
    dataset = read_dataset(
        DATA / recording.csv, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    q = dataset.joint_positions
    pose = lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw)
    measurement = FullPose() if dataset.measures_rotation else Position()
    return chain, MeasurementRows.of(q, gravity_loads(chain, q), pose), measurement


def evaluate(recording: Recording, methods: Sequence[str], seeds: Sequence[int]) -> list[Row]:
    """Per model and method: the held-out mean position error of each split (mm) and the
    largest inner-link rotation any split's chosen fit made (rad)."""
    chain, rows, measurement = load_rows(recording)
    out = []
    for model_name, options in MODELS.items():
        problem = Problem(chain, measurement, options)
        for method in methods:
            if method in FIX_COMPLIANCE_ONLY and options.fit_compliance:
                continue
            errors, rotations = [], []
            for seed in seeds:
                train, test = split_indices(rows.n, seed, 0.9)
                fit = METHODS[method](problem, rows.take(train))
                errors.append(
                    float(position_errors_mm(problem, fit.params, rows.take(test)).mean())
                )
                rotations.append(largest_inner_rotation_rad(chain, fit.params))
            out.append(
                {
                    "method": method,
                    "robot": recording.name,
                    "model": model_name,
                    "heldout_mm": [round(e, 4) for e in errors],
                    "largest_inner_rotation_rad": round(max(rotations), 4),
                }
            )
            print(
                f"{recording.name} {model_name} {method}: "
                f"{np.round(errors, 2).tolist()} (max inner rotation {max(rotations):.3f} rad)",
                flush=True,
            )
    return out


def render(rows: Sequence[Row]) -> str:
    """Method × robot × model: held-out mm (mean ± SE over the splits), the largest
    inner-link rotation, FIGAROH's error and whether ``--fix compliance`` is within
    FIGAROH + 1 SE."""
    header = [
        "Method",
        "Robot",
        "Model",
        "Held-out mm",
        "Largest inner rotation rad",
        "FIGAROH mm",
        "≤ FIGAROH + 1 SE",
    ]
    cells = []
    for row in rows:
        mean, se = mean_se(row["heldout_mm"])
        f_mean, f_se = FIGAROH_MM[row["robot"]]
        holds = "–" if row["model"] == "default" else "yes" if mean <= f_mean + f_se else "no"
        cells.append(
            [
                row["method"],
                row["robot"],
                f"`{row['model']}`" if row["model"].startswith("--") else row["model"],
                f"{mean:.3f} ± {se:.3f}",
                f"{row['largest_inner_rotation_rad']:.3f}",
                f"{f_mean:.2f} ± {f_se:.2f}",
                holds,
            ]
        )
    return markdown_table(header, cells)


def main(
    seeds: int = 10,
    only: list[str] | None = None,
    methods: list[str] | None = None,
    *,
    write: bool = False,
) -> str:
    rows = []
    for recording in RECORDINGS:
        if only and recording.name not in only:
            continue
        rows += evaluate(recording, methods or list(METHODS), list(range(1, seeds + 1)))
    text = render(rows)
    print("\n" + text)
    if write:
        command = f"python -m benchmarks.model_selection --seeds {seeds} --write-results"
        for path in write_results("model_selection", command, rows, render):
            print(f"wrote {path}")
    return text


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of held-out splits")
    parser.add_argument("--only", action="append", help="robot name (repeatable)")
    parser.add_argument("--method", action="append", choices=list(METHODS), help="(repeatable)")
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/model_selection.{json,md} (every method, robot and model)",
    )
    arguments = parser.parse_args()
    main(arguments.seeds, arguments.only, arguments.method, write=arguments.write_results)
