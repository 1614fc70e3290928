"""Predictors trained on some rows only, for the held-out coverage of the predictive
covariance (issue 13): every part of :mod:`solver.predictive` — geometry and compliance
(Eq. 8–10), the random-effect covariances (§IV-C, the calibration's estimator), Cov(θ̂) and the
model-error part (nested cross-validation inside the training rows) — estimated from the
training rows of a split, then scored on its test rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver.calibration import (
    DeterministicFit,
    FitOptions,
    fit_deterministic,
    identifiable_parameter_count,
)
from solver.covariance.estimate import EstimatorName, estimate_from_samples
from solver.covariance.likelihood import ee_covariance_batch
from solver.covariance.samples import ArraySamples
from solver.covariance.solvers import SolverName
from solver.errors import CalibrationError, KincalError
from solver.kinematics import ChainParameters, parameter_names, pose_residuals
from solver.model import KinematicChain
from solver.predictive import (
    Coverage,
    ModelErrorFit,
    PredictionPoint,
    coverage,
    estimate_model_error,
    mahalanobis_squared,
    measurement_axes,
    model_error_part,
    parameter_covariance,
    parameter_part,
    prediction_point,
    row_weights,
    sandwich_meat,
)
from solver.stream.fit import RowSample
from solver.stream.sums import CovarianceSpec

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

INNER_FOLDS = 3
"""Folds of the nested cross-validation that estimates a split's model-error part from its
training rows."""

MIN_RESIDUAL_SAMPLES = 2
"""A held-out predictor is trained only when its rows give at least this many samples' worth
of equations beyond the identifiable parameters."""

NLL_TOLERANCE = 1e-3
"""The held-out predictors' ML/REML iterations stop once the predicted decrease of the whole
negative log-likelihood is below this: θ is then within ~√(2·10⁻³) ≈ 0.05 of its standard
errors of the optimum (the calibration itself iterates to 10⁻¹⁰ per sample), and each split
needs 1 + ``INNER_FOLDS`` covariance estimates."""


@dataclass(frozen=True)
class RandomEffectSettings:
    """How the random-effect covariances are estimated: the frames and θ layout (``spec``),
    the estimator and the moment solver — the calibration's own."""

    spec: CovarianceSpec
    estimator: EstimatorName
    solver: SolverName


@dataclass(frozen=True)
class Predictor:
    """A calibration of some rows, as far as prediction needs it: the parameters, the columns
    of the parameters it estimated (:func:`~solver.kinematics.parameter_names` order) and their
    sandwich covariance (p, p), the random-effect covariances (F, 6, 6) of the chain joints
    ``frames``, the measurement noise (d, d) and the model-error variances (d,) along the
    measurement frame's axes (zeros when not estimated)."""

    params: ChainParameters
    estimated: IntArray
    parameter_covariance: FloatArray
    frames: tuple[int, ...]
    frame_covariances: FloatArray
    noise: FloatArray
    model_error: FloatArray

    def point(
        self, chain: KinematicChain, joint_positions: FloatArray, loads_nm: FloatArray
    ) -> PredictionPoint:
        return prediction_point(
            chain, self.params, self.estimated, joint_positions, loads_nm, self.noise.shape[0]
        )

    def random_part(self, point: PredictionPoint) -> FloatArray:
        """Σ_E(q) (Eq. 12) with Σ_n, (N, d, d)."""
        return ee_covariance_batch(
            point.frame_jacobians[:, list(self.frames)], self.frame_covariances, _padded(self.noise)
        )


def _padded(noise: FloatArray) -> FloatArray:
    out = np.zeros((6, 6))
    d = noise.shape[0]
    out[:d, :d] = noise
    return out


def predictor_from_fit(
    chain: KinematicChain,
    fit: DeterministicFit,
    rows: RowSample,
    position_only: bool,
    options: FitOptions,
    settings: RandomEffectSettings,
) -> Predictor:
    """The random-effect covariances (the calibration's estimator, on the fit's residuals) and
    the sandwich Cov(θ̂) of a fit of ``rows``; no model-error part."""
    d = 3 if position_only else 6
    names = parameter_names(chain)
    estimated = np.array([names.index(n) for n in fit.estimated], dtype=np.intp)
    point = prediction_point(chain, fit.params, estimated, rows.joint_positions, rows.loads_nm, d)
    spec = settings.spec
    frames = list(spec.frames)
    estimate = estimate_from_samples(
        ArraySamples(fit.residuals, point.frame_jacobians[:, frames], point.parameter_jacobian),
        spec.layout,
        known=spec.known,
        estimator=settings.estimator,
        solver=settings.solver,
        noise_name=spec.noise_name,
        standard_errors=False,
        likelihood_tolerance=NLL_TOLERANCE / max(rows.n, 1),
    )
    noise = estimate.noise_covariance()[:d, :d]
    random = ee_covariance_batch(
        point.frame_jacobians[:, frames], estimate.frame_covariances(), _padded(noise)
    )
    weighted = fit.jacobian.reshape(-1, estimated.size)
    covariance = _sandwich(
        weighted.T @ weighted, point, random, d, options.rotation_weight_m_per_rad, 1.0
    )
    return Predictor(
        fit.params,
        estimated,
        covariance,
        tuple(frames),
        estimate.frame_covariances(),
        noise,
        np.zeros(d),
    )


def train_predictor(
    chain: KinematicChain,
    rows: RowSample,
    position_only: bool,
    options: FitOptions,
    settings: RandomEffectSettings,
) -> Predictor:
    """Fit geometry and compliance (Eq. 8–10) on ``rows``, then :func:`predictor_from_fit`;
    :class:`CalibrationError` when the rows leave fewer than :data:`MIN_RESIDUAL_SAMPLES`
    samples' worth of equations beyond the parameters (no residuals to estimate covariances
    from)."""
    d = 3 if position_only else 6
    spare = d * rows.n - identifiable_parameter_count(
        chain, position_only=position_only, options=options
    )
    if spare < d * MIN_RESIDUAL_SAMPLES:
        raise CalibrationError(
            f"{rows.n} rows leave {spare} equations beyond the parameters, fewer than "
            f"{MIN_RESIDUAL_SAMPLES} samples' worth"
        )
    try:
        fit = fit_deterministic(
            chain,
            rows.joint_positions,
            rows.measured_pose,
            rows.loads_nm,
            position_only=position_only,
            options=options,
        )
    except ZeroDivisionError as exc:  # the rows' rank reached their equations: no residual dof
        raise CalibrationError(f"{rows.n} rows leave no residual degrees of freedom") from exc
    return predictor_from_fit(chain, fit, rows, position_only, options, settings)


@dataclass(frozen=True)
class ScoredRows:
    """Rows scored by a predictor trained without them: end-effector-frame residuals (n, d),
    the covariance of every part but the model error (``base``, (n, d, d)), Σ_E + Σ_n alone
    (``random``, (n, d, d)) and the measurement axes T (n, d, d) of
    :func:`~solver.predictive.measurement_axes`."""

    residuals: FloatArray
    base: FloatArray
    random: FloatArray
    axes: FloatArray

    @classmethod
    def join(cls, parts: list[ScoredRows], d: int) -> ScoredRows:
        if not parts:
            empty = np.zeros((0, d, d))
            return cls(np.zeros((0, d)), empty, empty, empty)
        return cls(
            np.concatenate([p.residuals for p in parts]),
            np.concatenate([p.base for p in parts]),
            np.concatenate([p.random for p in parts]),
            np.concatenate([p.axes for p in parts]),
        )

    def distances_squared(self, model_error: FloatArray) -> FloatArray:
        """Squared Mahalanobis distances (n,) under the total with these model-error
        variances (d,)."""
        total = self.base + model_error_part(self.axes, model_error)
        return mahalanobis_squared(self.residuals, total)


def score_rows(
    chain: KinematicChain, predictor: Predictor, rows: RowSample, position_only: bool
) -> tuple[FloatArray, ScoredRows]:
    """The predicted poses (n, 4, 4) of ``rows`` and their :class:`ScoredRows`."""
    d = predictor.noise.shape[0]
    point = predictor.point(chain, rows.joint_positions, rows.loads_nm)
    residuals = pose_residuals(point.pose, rows.measured_pose, position_only=position_only)
    random = predictor.random_part(point)
    base = random + parameter_part(point.parameter_jacobian, predictor.parameter_covariance)
    return point.pose, ScoredRows(residuals, base, random, measurement_axes(point.pose, d))


def fold_indices(n: int, folds: int, seed: int) -> list[tuple[IntArray, IntArray]]:
    """``folds`` (train, test) index pairs of a random partition of ``range(n)``
    (``default_rng(seed)``), test parts of near-equal size."""
    order = np.random.default_rng(seed).permutation(n)
    parts = np.array_split(order, min(folds, n))
    return [
        (np.sort(np.concatenate(parts[:i] + parts[i + 1 :])), np.sort(part))
        for i, part in enumerate(parts)
    ]


def cross_validated_rows(
    chain: KinematicChain,
    rows: RowSample,
    position_only: bool,
    options: FitOptions,
    settings: RandomEffectSettings,
    *,
    folds: int,
    seed: int,
) -> ScoredRows:
    """Every row of ``rows`` scored by a predictor trained on the other folds; a fold whose
    training part cannot be calibrated (too few rows for the parameters or the covariances)
    is left out."""
    d = 3 if position_only else 6
    parts = []
    for train, test in fold_indices(rows.n, folds, seed):
        try:
            predictor = train_predictor(chain, rows.take(train), position_only, options, settings)
        except KincalError:
            continue
        parts.append(score_rows(chain, predictor, rows.take(test), position_only)[1])
    return ScoredRows.join(parts, d)


def nested_model_error(
    chain: KinematicChain,
    rows: RowSample,
    position_only: bool,
    options: FitOptions,
    settings: RandomEffectSettings,
    *,
    folds: int = INNER_FOLDS,
    seed: int = 0,
) -> ModelErrorFit:
    """The model-error part from ``rows`` alone: :func:`cross_validated_rows` inside them,
    then :func:`~solver.predictive.estimate_model_error`."""
    scored = cross_validated_rows(
        chain, rows, position_only, options, settings, folds=folds, seed=seed
    )
    return estimate_model_error(scored.residuals, scored.base, scored.axes)


@dataclass(frozen=True)
class SplitCoverage:
    """One held-out split: its test rows scored by a predictor of its training rows
    (``scored``) and the model-error part estimated inside those training rows
    (``model_error``)."""

    scored: ScoredRows
    model_error: ModelErrorFit

    @property
    def distances_squared(self) -> FloatArray:
        return self.scored.distances_squared(self.model_error.variance)


def split_coverage(
    chain: KinematicChain,
    fit: DeterministicFit,
    train: RowSample,
    test: RowSample,
    position_only: bool,
    options: FitOptions,
    settings: RandomEffectSettings,
    *,
    folds: int = INNER_FOLDS,
    seed: int = 0,
) -> SplitCoverage | None:
    """Every part from the training rows of a split (``fit`` of them given), scored on its
    test rows; None when the training rows cannot give the covariances."""
    try:
        predictor = predictor_from_fit(chain, fit, train, position_only, options, settings)
    except KincalError:
        return None
    model_error = nested_model_error(
        chain, train, position_only, options, settings, folds=folds, seed=seed
    )
    return SplitCoverage(score_rows(chain, predictor, test, position_only)[1], model_error)


@dataclass(frozen=True)
class PredictiveCalibration:
    """What a predictor needs beyond the calibrated model to rebuild the total covariance of
    a new configuration (issue 13), and how well it held on the held-out splits.

    ``estimated``: the parameter names of ``parameter_covariance`` (p, p), the sandwich
    Cov(θ̂) of the calibration over every used sample; ``model_error``: the model-error part
    fitted to the held-out residuals of all splits (None without held-out splits);
    ``coverage``: the held-out residuals of every split under the total its training rows
    predicted (None without splits); ``splits``: the per-seed material."""

    estimated: list[str]
    parameter_covariance: FloatArray
    model_error: ModelErrorFit | None
    coverage: Coverage | None
    splits: dict[int, SplitCoverage]


def calibration_parameter_covariance(
    chain: KinematicChain,
    params: ChainParameters,
    estimated: list[str],
    gram: FloatArray,
    n_used: int,
    rows: RowSample,
    random_part: Callable[[PredictionPoint], FloatArray],
    position_only: bool,
    rotation_weight: float,
) -> FloatArray:
    """Sandwich Cov(θ̂) (p, p) of a calibration whose normal matrix over its ``n_used``
    samples is ``gram``: the meat summed over ``rows`` (all or an evenly spaced subset of the
    used samples) and scaled to ``n_used``; ``random_part(point)`` gives Σ_E + Σ_n there."""
    d = 3 if position_only else 6
    names = parameter_names(chain)
    columns = np.array([names.index(n) for n in estimated], dtype=np.intp)
    point = prediction_point(chain, params, columns, rows.joint_positions, rows.loads_nm, d)
    return _sandwich(gram, point, random_part(point), d, rotation_weight, n_used / max(rows.n, 1))


def _sandwich(
    gram: FloatArray,
    point: PredictionPoint,
    random: FloatArray,
    d: int,
    rotation_weight: float,
    scale: float,
) -> FloatArray:
    """Cov(θ̂) from the normal matrix and the meat over ``point``'s rows, scaled by
    ``scale`` (the used samples per row given)."""
    weights = row_weights(d, rotation_weight)
    weighted = weights[None, :, None] * point.parameter_jacobian
    return parameter_covariance(gram, scale * sandwich_meat(weighted, random, weights))


def pooled_predictive(
    estimated: list[str],
    parameter_cov: FloatArray,
    splits: dict[int, SplitCoverage],
    d: int,
) -> PredictiveCalibration:
    """The calibration's model-error part from the held-out residuals of every split (each
    scored by a predictor of its own training rows) and the coverage of the splits (each under
    the model-error part of its nested cross-validation)."""
    if not splits:
        return PredictiveCalibration(estimated, parameter_cov, None, None, splits)
    pooled = ScoredRows.join([s.scored for s in splits.values()], d)
    model_error = estimate_model_error(pooled.residuals, pooled.base, pooled.axes)
    distances = np.concatenate([s.distances_squared for s in splits.values()])
    return PredictiveCalibration(
        estimated, parameter_cov, model_error, coverage(distances, d), splits
    )
