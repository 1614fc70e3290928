"""The predictive covariance of a measurement-model calibration and its held-out coverage
(issue 15, docs/predictive.md for the pose version): the same three parts as for a pose, in the
residual space of the measurement model.

Frames and units: every quantity is in the space the covariance calibration sees the residual in
(:func:`solver.measurement.fit.covariance_samples`): the model's residual (N, d) rotated into the
tip frame by :meth:`~solver.measurement.models.MeasurementModel.tip_frame_rotation` where the
model gives one (ball in socket, markers), else as the model writes it (chosen components: the
measurement frame); m and rad. For a row with residual r

    Cov(r) = Σ_E(q)                          Eq. (12) with the model's noise layout (+ its Σ_n)
           + J_θ(q) Cov(θ̂) J_θ(q)ᵀ           estimation error of the fitted parameters
           + T(q) diag(s) T(q)ᵀ              model error, diagonal along the residual's own axes

- ``J_θ`` (N, d, p): the model's unweighted Jacobian over the fitted columns — chain parameters
  and the model's own unknowns (socket points, marker offsets), which are listed in Cov(θ̂),
  not profiled out — rotated like the residual.
- ``Cov(θ̂) = G⁺ M G⁺`` the sandwich of the weighted least-squares fit: ``G`` the Gauss–Newton
  normal matrix of the weighted rows plus the model's extra equations (known distances, taken
  as exact), ``M = Σ A_w,nᵀ W Σ_E(q_n) W A_w,n`` over the rows (the extra equations carry no
  random error).
- ``T(q)`` (N, d, d): the rotation into the covariance's space (identity where there is none),
  so ``s`` (d,) are variances along the axes of the model's own residual (the type's frame:
  the robot base for sockets, the flange-mounted markers' measurement frame for markers, the
  measurement frame for chosen components), fitted by maximum likelihood
  (:func:`solver.predictive.estimate_model_error`) to cross-validated residuals.

Every part of a held-out split's prediction comes from its training rows only: the fit (the
model's own unknowns too), the covariances, Cov(θ̂), and the model-error part from an
:data:`INNER_FOLDS`-fold cross-validation inside the training rows (as for poses,
:mod:`solver.stream.coverage`). The calibration's own model-error part comes from the pooled
held-out residuals of its splits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray
from solver.covariance.estimate import CovarianceEstimate
from solver.errors import KincalError
from solver.evaluation import split_indices
from solver.kinematics import parameter_names
from solver.measurement.fit import MeasurementFit, covariance_samples
from solver.measurement.models import MeasurementRows
from solver.model import KinematicChain
from solver.predictive import (
    INNER_FOLDS,
    Coverage,
    ModelErrorFit,
    ScoredRows,
    coverage,
    estimate_model_error,
    gram_inverse,
    mahalanobis_squared,
    model_error_part,
    parameter_part,
)

Fitter = Callable[[MeasurementRows], MeasurementFit]
"""Fits rows with the calibration's settings (the model's own unknowns included)."""
Estimator = Callable[[MeasurementFit, MeasurementRows], CovarianceEstimate]
"""The calibration's covariance estimator (Eq. 12–17) at a fit of those rows."""


@dataclass(frozen=True)
class MeasurementPredictor:
    """A calibration of some rows as far as prediction needs it: the fit, its covariances and
    ``parameter_covariance`` Cov(θ̂) (p, p) of ``fit.estimated``; ``frames`` the perturbed
    chain joints."""

    fit: MeasurementFit
    estimate: CovarianceEstimate
    parameter_covariance: FloatArray
    frames: tuple[int, ...]


def residual_axes(chain: KinematicChain, fit: MeasurementFit, rows: MeasurementRows) -> FloatArray:
    """``T`` (N, d, d): the rotation taking the model's own residual into the covariance's
    space (:meth:`~solver.measurement.models.MeasurementModel.tip_frame_rotation`; identity
    where the residual is not rotated)."""
    rotation = fit.model.tip_frame_rotation(chain, fit.params, rows)
    if rotation is None:
        return np.broadcast_to(np.eye(fit.model.dim), (rows.n, fit.model.dim, fit.model.dim)).copy()
    return np.asarray(rotation, dtype=float)


def parameter_jacobian(
    chain: KinematicChain, fit: MeasurementFit, rows: MeasurementRows
) -> FloatArray:
    """``J_θ`` (N, d, p): the model's unweighted Jacobian at ``fit`` over ``fit.estimated``
    (chain columns and the model's own unknowns), rotated like the residual."""
    names = parameter_names(chain) + fit.model.extra_names()
    _, jacobian = fit.model.linearise(chain, fit.params, rows)
    assert jacobian is not None
    columns = jacobian[:, :, [names.index(n) for n in fit.estimated]]
    return np.asarray(residual_axes(chain, fit, rows) @ columns, dtype=float)


def measurement_parameter_covariance(
    chain: KinematicChain,
    fit: MeasurementFit,
    rows: MeasurementRows,
    random: FloatArray,
    weights: FloatArray,
) -> FloatArray:
    """Sandwich ``Cov(θ̂) = G⁺ M G⁺`` (p, p) of ``fit`` over ``rows`` (the rows it used):
    ``random`` (N, d, d) the rows' Σ_E (+ noise) in the covariance's space, ``weights`` (d,)
    the fit's row weights W (rotation rows times the rotation weight; W commutes with the
    rotation into the tip frame, which keeps translation and rotation rows apart).
    ``G = Σ A_wᵀ A_w + CᵀC`` with the model's extra equations C (known distances, exact),
    ``M = Σ A_wᵀ W Σ_E W A_w``."""
    names = parameter_names(chain) + fit.model.extra_names()
    fitted = [names.index(n) for n in fit.estimated]
    weighted = weights[None, :, None] * parameter_jacobian(chain, fit, rows)
    gram = np.einsum("ndp,ndq->pq", weighted, weighted)
    _, extra = fit.model.constraints(chain, fit.params)
    if extra.shape[0]:
        gram = gram + extra[:, fitted].T @ extra[:, fitted]
    scaled = weights[None, :, None] * weighted
    meat = np.einsum("ndp,nde,neq->pq", scaled, random, scaled, optimize=True)
    inverse = gram_inverse(gram)
    covariance = inverse @ meat @ inverse
    return np.asarray(0.5 * (covariance + covariance.T), dtype=float)


def train_predictor(
    chain: KinematicChain,
    rows: MeasurementRows,
    fitter: Fitter,
    estimator: Estimator,
    frames: tuple[int, ...],
    weights: FloatArray,
    fit: MeasurementFit | None = None,
    estimate: CovarianceEstimate | None = None,
) -> MeasurementPredictor:
    """Fit, covariances and Cov(θ̂) from ``rows`` (``fit``/``estimate``: already computed on
    exactly these rows)."""
    fit = fit if fit is not None else fitter(rows)
    estimate = estimate if estimate is not None else estimator(fit, rows)
    samples = covariance_samples(chain, fit, rows, frames)
    random = estimate.ee_covariance(samples.frame_jacobians, include_noise=True)
    covariance = measurement_parameter_covariance(chain, fit, rows, random, weights)
    return MeasurementPredictor(fit, estimate, covariance, frames)


def score_rows(
    chain: KinematicChain, predictor: MeasurementPredictor, rows: MeasurementRows
) -> ScoredRows:
    """Residuals of ``rows`` at the predictor's fit and the covariance its parts other than
    the model error predict for them."""
    fit = predictor.fit
    samples = covariance_samples(chain, fit, rows, predictor.frames)
    random = predictor.estimate.ee_covariance(samples.frame_jacobians, include_noise=True)
    parts = parameter_part(parameter_jacobian(chain, fit, rows), predictor.parameter_covariance)
    axes = residual_axes(chain, fit, rows)
    return ScoredRows(samples.residuals, random + parts, random, axes)


def total_distances(
    chain: KinematicChain,
    predictor: MeasurementPredictor,
    model_error_variance: FloatArray,
    rows: MeasurementRows,
) -> tuple[FloatArray, FloatArray]:
    """``d² = rᵀ Σ_total⁻¹ r`` (n,) of new ``rows`` under the total predictive covariance in
    the model's residual space (Σ_E + noise + J_θ Cov(θ̂) J_θᵀ + T diag(s) Tᵀ, ``s`` =
    ``model_error_variance`` (d,) along the residual's own axes), and under Σ_E + noise alone
    (n,): how a calibration's result scores rows it took no part in (χ²_d if right)."""
    scored = score_rows(chain, predictor, rows)
    total = scored.base + model_error_part(scored.axes, model_error_variance)
    return (
        mahalanobis_squared(scored.residuals, total),
        mahalanobis_squared(scored.residuals, scored.random),
    )


def cross_validated(
    chain: KinematicChain,
    rows: MeasurementRows,
    fitter: Fitter,
    estimator: Estimator,
    frames: tuple[int, ...],
    weights: FloatArray,
    folds: int,
    seed: int,
    min_train_rows: int,
) -> ScoredRows:
    """``folds``-fold cross-validated rows: each fold scored by a predictor trained on the
    others; a fold whose training rows are fewer than ``min_train_rows`` (or whose calibration
    fails) is skipped."""
    order = np.random.default_rng(seed).permutation(rows.n)
    scored = []
    for fold in np.array_split(order, folds):
        train = np.setdiff1d(order, fold)
        if train.size < min_train_rows or fold.size == 0:
            continue
        try:
            predictor = train_predictor(chain, rows.take(train), fitter, estimator, frames, weights)
        except KincalError:
            continue
        scored.append(score_rows(chain, predictor, rows.take(np.sort(fold))))
    return ScoredRows.join(scored, int(weights.size))


@dataclass(frozen=True)
class MeasurementPredictive:
    """The predictive parts of a measurement calibration: ``estimated`` names (chain
    parameters and the model's own unknowns) of ``parameter_covariance`` (p, p), the
    model-error part along the residual's own axes, the held-out ``coverage`` (None without
    splits) over ``n_splits`` splits, ``nested`` of which had an inner cross-validation;
    ``predictor``: the calibration's own (all used rows), which with ``model_error`` predicts
    new rows (:func:`total_distances`)."""

    estimated: list[str]
    parameter_covariance: FloatArray
    model_error: ModelErrorFit
    coverage: Coverage | None
    n_splits: int
    nested: int
    predictor: MeasurementPredictor


def measurement_predictive(
    chain: KinematicChain,
    rows: MeasurementRows,
    fit: MeasurementFit,
    estimate: CovarianceEstimate,
    fitter: Fitter,
    estimator: Estimator,
    frames: tuple[int, ...],
    weights: FloatArray,
    seeds: Sequence[int],
    train_fraction: float,
) -> MeasurementPredictive:
    """Cov(θ̂) of the calibration (``fit`` and ``estimate`` of ``rows``, the rows it used),
    and per seed (split of :func:`solver.evaluation.split_indices`): a predictor from the
    training rows, its model-error part from :data:`INNER_FOLDS`-fold cross-validation
    inside them, the test rows' ``d² = rᵀ Σ_total⁻¹ r`` (χ²_d if right). The calibration's
    model-error part: maximum likelihood on the pooled held-out residuals of the splits
    (without splits: on :data:`INNER_FOLDS`-fold cross-validated residuals of all rows)."""
    d = fit.model.dim
    min_rows = len(fit.estimated) // d + 2
    whole = train_predictor(chain, rows, fitter, estimator, frames, weights, fit, estimate)
    pooled: list[ScoredRows] = []
    distances: list[FloatArray] = []
    nested = 0
    for seed in seeds:
        train, test = split_indices(rows.n, seed, train_fraction)
        if train.size < min_rows:
            continue
        try:
            predictor = train_predictor(chain, rows.take(train), fitter, estimator, frames, weights)
        except KincalError:
            continue
        scored = score_rows(chain, predictor, rows.take(test))
        pooled.append(scored)
        inner = cross_validated(
            chain,
            rows.take(train),
            fitter,
            estimator,
            frames,
            weights,
            INNER_FOLDS,
            seed,
            min_rows,
        )
        if inner.residuals.shape[0]:
            nested += 1
            error = estimate_model_error(inner.residuals, inner.base, inner.axes).variance
        else:
            error = np.zeros(d)
        total = scored.base + model_error_part(scored.axes, error)
        distances.append(mahalanobis_squared(scored.residuals, total))
    if pooled:
        joined = ScoredRows.join(pooled, d)
        measured: Coverage | None = coverage(np.concatenate(distances), d)
    else:
        joined = cross_validated(
            chain, rows, fitter, estimator, frames, weights, INNER_FOLDS, 0, min_rows
        )
        measured = None
    model_error = (
        estimate_model_error(joined.residuals, joined.base, joined.axes)
        if joined.residuals.shape[0]
        else ModelErrorFit.none(d)
    )
    return MeasurementPredictive(
        list(fit.estimated),
        whole.parameter_covariance,
        model_error,
        measured,
        len(pooled),
        nested,
        whole,
    )
