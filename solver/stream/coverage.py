"""The predictive covariance of a calibration and its held-out coverage (issue 13).

A :class:`Predictor` is a calibration of some rows as far as prediction needs it. For a held-out
split every part of :mod:`solver.predictive` — geometry and compliance (Eq. 8–10), the
random-effect covariances (§IV-C, the calibration's estimator), Cov(θ̂) and the model-error part —
is estimated from the split's training rows only, and the split's test rows are scored with it.

The model-error part is fitted (:func:`solver.predictive.estimate_model_error`) to
cross-validated residuals, each with the covariance the other parts of *its* predictor give it:

- the calibration's own: the held-out residuals of its splits, whose predictors re-estimated
  everything on their training rows — so the part also holds what a calibration of this size
  gets wrong about Σ_E itself;
- a split's (for its coverage): the same procedure inside the split's training rows
  (:data:`INNER_FOLDS`-fold cross-validation, nested);
- without held-out splits: the leave-one-out residuals of the deterministic fit (the exact
  deletion identity of least squares at the solution, covariances not re-estimated: a weaker
  estimate, said so in the result).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.calibration import DeterministicFit, FitOptions, identifiable_parameter_count
from solver.covariance.estimate import (
    CovarianceEstimate,
    EstimatorName,
    estimate_from_samples,
    subset_estimate,
)
from solver.covariance.likelihood import ee_covariance_batch
from solver.covariance.samples import ArraySamples
from solver.covariance.solvers import SolverName
from solver.errors import CalibrationError, KincalError
from solver.kinematics import ChainParameters, parameter_names
from solver.measurement.fit import MeasurementFit, covariance_samples, refit_from
from solver.measurement.models import FullPose, MeasurementRows
from solver.measurement.pose import fit_deterministic
from solver.measurement.predictive import Estimator as MeasurementEstimator
from solver.measurement.predictive import Fitter as MeasurementFitter
from solver.model import KinematicChain
from solver.predictive import (
    INNER_FOLDS,
    Coverage,
    ModelErrorFit,
    PredictionPoint,
    ScoredRows,
    coverage,
    estimate_model_error,
    leave_one_out_residuals,
    measurement_axes,
    parameter_covariance,
    parameter_part,
    prediction_point,
    row_weights,
    sandwich_meat,
)
from solver.stream.fit import RowSample
from solver.stream.screening import covariance_too_uncertain
from solver.stream.sums import CovarianceSpec

INNER_CV_ROWS = 500
"""Up to this many training rows a split's model-error part comes from the nested
:data:`INNER_FOLDS`-fold cross-validation; beyond, from the leave-one-out residuals of the
split's deterministic fit (the exact deletion identity), its random-effect covariances not
re-estimated per fold. With more than 500 rows their own estimation error (relative
√(2/n) ≲ 6 % in a variance) moves the 95 % coverage by well under a point, while the nested
folds cost three more calibrations per split (measured on 10⁵ simulated Jaco2 poses, 990
held-out: 96 % inside the 95 % ellipsoid and mean d² 5.85 either way (5.76 nested), in
less than half the held-out stage's time)."""

MIN_RESIDUAL_SAMPLES = 2
"""A predictor is trained only when its rows give at least this many samples' worth of
equations beyond the identifiable parameters."""

NLL_TOLERANCE = 1e-3
"""The held-out predictors' ML/REML iterations stop once the predicted decrease of the whole
negative log-likelihood is below this: θ is then within ~√(2·10⁻³) ≈ 0.05 of its standard
errors of the optimum (the calibration itself iterates to 10⁻¹⁰ per sample)."""


@dataclass(frozen=True)
class RandomEffectSettings:
    """How the random-effect covariances are estimated: the frames and θ layout (``spec``),
    the estimator and the moment solver — the calibration's own."""

    spec: CovarianceSpec
    estimator: EstimatorName
    solver: SolverName


@dataclass(frozen=True)
class WarmStart:
    """The calibration of every row that held-out predictors start from (issue 29, the
    one-step held-out evaluation): its parameters, the names it estimated, and its covariance
    estimate. A predictor of a subset of the rows is then one Gauss–Newton step from
    ``params`` over ``estimated`` (:func:`solver.measurement.fit.refit_from`), and its
    covariances a few scoring steps from the subset's own moment solution with
    ``covariance``'s estimator and scaling (:func:`solver.covariance.estimate.subset_estimate`)."""

    params: ChainParameters
    estimated: list[str]
    covariance: CovarianceEstimate | None = None
    """None: the deterministic part alone starts here (the "before" fit)."""


def subset_reference(
    estimate: CovarianceEstimate | None, n_equations: int
) -> CovarianceEstimate | None:
    """The covariance estimate whose estimator and scaling held-out predictors take a few
    scoring steps with (:func:`~solver.covariance.estimate.subset_estimate`), or None (each
    predictor's covariances iterated to convergence, two starts) when the ``n_equations``
    residual equations of the calibration give fewer than
    :data:`~solver.stream.screening.MIN_EQUATIONS_PER_COVARIANCE_ENTRY` per identifiable entry.

    A few steps suffice where the likelihood is near quadratic around the subset's optimum. On
    fewer equations per entry it has several optima and which one a split lands in depends on
    the start: the 21-row TIAGo Vicon file (position only, 63 equations, 42 entries) is one,
    where the exact path's second (lifted) start wins on some splits."""
    if estimate is None or covariance_too_uncertain(n_equations, estimate.identifiability.rank):
        return None
    return estimate


def one_step_trainers(
    chain: KinematicChain,
    rows: MeasurementRows,
    fit: MeasurementFit,
    estimate: CovarianceEstimate,
    fit_options: FitOptions,
    frames: tuple[int, ...],
    known: FloatArray | None,
    iterated: MeasurementEstimator,
) -> tuple[MeasurementFitter, MeasurementEstimator]:
    """How ``--heldout-method one-step`` (the default) trains the held-out predictors of a
    measurement calibration — ``fit`` and ``estimate`` (random effects at the chain joints
    ``frames``, ``known`` (d, d) the known part of every Σ_E) of its used ``rows`` — for
    :func:`~solver.measurement.predictive.measurement_predictive`:

    - the fit of a subset of those rows: one Gauss–Newton step of Eq. (10) from ``fit`` over
      the parameters it estimated (:func:`~solver.measurement.fit.refit_from`);
    - its covariances: the subset's own moment solution refined by a few scoring steps with
      ``estimate``'s estimator (:func:`~solver.covariance.estimate.subset_estimate`); where
      the rows give too few equations per covariance entry (:func:`subset_reference`),
      ``iterated`` (the estimator iterated to convergence).
    """
    reference = subset_reference(estimate, rows.n * fit.model.dim)

    def fitter(subset: MeasurementRows) -> MeasurementFit:
        return refit_from(chain, fit.model, subset, fit_options, fit.params, fit.estimated)

    def estimator(subset_fit: MeasurementFit, subset: MeasurementRows) -> CovarianceEstimate:
        if reference is None:
            return iterated(subset_fit, subset)
        samples = covariance_samples(chain, subset_fit, subset, frames)
        return subset_estimate(reference, samples, known=known)

    return fitter, estimator


@dataclass(frozen=True)
class Predictor:
    """A calibration of some rows, as far as prediction needs it: the parameters, the columns
    of the parameters it estimated (:func:`~solver.kinematics.parameter_names` order) and their
    sandwich covariance (p, p), the normal matrix ``gram`` (p, p) of its fit, the random-effect
    covariances (F, 6, 6) of the chain joints ``frames`` and the measurement noise (d, d)."""

    params: ChainParameters
    estimated: IntArray
    parameter_covariance: FloatArray
    gram: FloatArray
    frames: tuple[int, ...]
    frame_covariances: FloatArray
    noise: FloatArray
    theta: FloatArray | None = None
    """The random-effect parameters θ (warm start of the predictors of subsets)."""

    @property
    def d(self) -> int:
        return int(self.noise.shape[0])

    def point(
        self, chain: KinematicChain, joint_positions: FloatArray, loads_nm: FloatArray
    ) -> PredictionPoint:
        return prediction_point(
            chain, self.params, self.estimated, joint_positions, loads_nm, self.d
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


def _columns(chain: KinematicChain, estimated: list[str]) -> IntArray:
    names = parameter_names(chain)
    return np.array([names.index(n) for n in estimated], dtype=np.intp)


def sandwich_covariance(
    gram: FloatArray,
    point: PredictionPoint,
    random: FloatArray,
    rotation_weight: float,
    scale: float = 1.0,
) -> FloatArray:
    """Cov(θ̂) (p, p) of a fit with normal matrix ``gram``, the meat summed over ``point``'s
    rows with their Σ_E + Σ_n ``random`` (n, d, d) and multiplied by ``scale`` (used samples
    per row given, when the rows are a subset)."""
    weights = row_weights(random.shape[1], rotation_weight)
    weighted = weights[None, :, None] * point.parameter_jacobian
    return parameter_covariance(gram, scale * sandwich_meat(weighted, random, weights))


def predictor_from_fit(
    chain: KinematicChain,
    fit: DeterministicFit,
    rows: RowSample,
    measurement: FullPose,
    options: FitOptions,
    settings: RandomEffectSettings,
    start_theta: FloatArray | None = None,
    warm: WarmStart | None = None,
) -> Predictor:
    """A deterministic fit of ``rows`` completed into a predictor: the random-effect
    covariances (the calibration's estimator, on the fit's residuals; ML/REML started from
    ``start_theta`` when given, or :func:`subset_estimate` with ``warm``'s) and the sandwich
    Cov(θ̂)."""
    d = measurement.dim
    estimated = _columns(chain, fit.estimated)
    point = prediction_point(chain, fit.params, estimated, rows.joint_positions, rows.loads_nm, d)
    spec = settings.spec
    frames = list(spec.frames)
    samples = ArraySamples(
        fit.residuals, point.frame_jacobians[:, frames], point.parameter_jacobian
    )
    if warm is not None and warm.covariance is not None:
        estimate = subset_estimate(warm.covariance, samples, known=spec.known)
    else:
        estimate = estimate_from_samples(
            samples,
            spec.layout,
            known=spec.known,
            estimator=settings.estimator,
            solver=settings.solver,
            noise_name=spec.noise_name,
            standard_errors=False,
            likelihood_tolerance=NLL_TOLERANCE / max(rows.n, 1),
            start_theta=start_theta,
        )
    noise = estimate.noise_covariance()[:d, :d]
    random = ee_covariance_batch(
        point.frame_jacobians[:, frames], estimate.frame_covariances(), _padded(noise)
    )
    weighted = fit.jacobian.reshape(-1, estimated.size)
    gram = weighted.T @ weighted
    covariance = sandwich_covariance(gram, point, random, options.rotation_weight_m_per_rad)
    return Predictor(
        fit.params,
        estimated,
        covariance,
        gram,
        tuple(frames),
        estimate.frame_covariances(),
        noise,
        estimate.theta,
    )


def train_predictor(
    chain: KinematicChain,
    rows: RowSample,
    measurement: FullPose,
    options: FitOptions,
    settings: RandomEffectSettings,
    start_theta: FloatArray | None = None,
    warm: WarmStart | None = None,
) -> Predictor:
    """Fit geometry and compliance (Eq. 8–10) on ``rows`` (with ``warm``: one step from it,
    over its parameters), then :func:`predictor_from_fit`;
    :class:`CalibrationError` when the rows leave fewer than :data:`MIN_RESIDUAL_SAMPLES`
    samples' worth of equations beyond the parameters."""
    d = measurement.dim
    fitted = identifiable_parameter_count(chain, dim=d, options=options)
    if warm is not None:  # the step fits the parameters of the calibration of every row
        fitted = max(fitted, len(warm.estimated))
    spare = d * rows.n - fitted
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
            measurement=measurement,
            options=options,
            start=None if warm is None else warm.params,
            estimated=None if warm is None else warm.estimated,
        )
    except ZeroDivisionError as exc:  # the rows' rank reached their equations: no residual dof
        raise CalibrationError(f"{rows.n} rows leave no residual degrees of freedom") from exc
    return predictor_from_fit(chain, fit, rows, measurement, options, settings, start_theta, warm)


def score_rows(
    chain: KinematicChain,
    predictor: Predictor,
    rows: RowSample,
    measurement: FullPose,
    *,
    left_out: bool = False,
    rotation_weight: float = 1.0,
) -> ScoredRows:
    """``rows`` scored by ``predictor``; ``left_out``: they are the rows it was fitted to
    (with ``rotation_weight``, the fit's), each scored as if left out of its deterministic fit
    (:func:`~solver.predictive.leave_one_out_residuals`)."""
    point = predictor.point(chain, rows.joint_positions, rows.loads_nm)
    residuals = measurement.residuals(point.pose, rows.measured_pose)
    if left_out:
        weights = row_weights(predictor.d, rotation_weight)
        weighted = weights[None, :, None] * point.parameter_jacobian
        residuals = leave_one_out_residuals(residuals, weighted, weights, predictor.gram)
    random = predictor.random_part(point)
    base = random + parameter_part(point.parameter_jacobian, predictor.parameter_covariance)
    return ScoredRows(residuals, base, random, measurement_axes(point.pose, predictor.d))


def model_error_of(
    chain: KinematicChain,
    predictor: Predictor,
    rows: RowSample,
    measurement: FullPose,
    rotation_weight: float,
) -> ModelErrorFit:
    """The model-error part of a predictor from the rows it was fitted to alone: their
    leave-one-out residuals, by :func:`~solver.predictive.estimate_model_error`."""
    scored = score_rows(
        chain, predictor, rows, measurement, left_out=True, rotation_weight=rotation_weight
    )
    return estimate_model_error(scored.residuals, scored.base, scored.axes)


@dataclass(frozen=True)
class SplitCoverage:
    """One held-out split: its test rows scored by a predictor of its training rows
    (``scored``) with the model-error part estimated from those training rows."""

    scored: ScoredRows
    model_error: ModelErrorFit
    nested: bool = True
    """The model-error part came from the nested cross-validation (else leave-one-out)."""

    @property
    def distances_squared(self) -> FloatArray:
        return self.scored.distances_squared(self.model_error.variance)


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
    measurement: FullPose,
    options: FitOptions,
    settings: RandomEffectSettings,
    *,
    folds: int,
    seed: int,
    start_theta: FloatArray | None = None,
    warm: WarmStart | None = None,
) -> ScoredRows:
    """Every row of ``rows`` scored by a predictor trained on the other folds (with ``warm``:
    one step from it); a fold whose training part cannot be calibrated is left out."""
    d = measurement.dim
    parts = []
    for train, test in fold_indices(rows.n, folds, seed):
        try:
            predictor = train_predictor(
                chain, rows.take(train), measurement, options, settings, start_theta, warm
            )
        except KincalError:
            continue
        parts.append(score_rows(chain, predictor, rows.take(test), measurement))
    return ScoredRows.join(parts, d)


def split_coverage(
    chain: KinematicChain,
    fit: DeterministicFit,
    train: RowSample,
    test: RowSample,
    measurement: FullPose,
    options: FitOptions,
    settings: RandomEffectSettings,
    *,
    seed: int = 0,
    warm: WarmStart | None = None,
) -> SplitCoverage | None:
    """Every part from the training rows of a split (``fit`` of them given; the model-error
    part by :data:`INNER_FOLDS`-fold cross-validation inside them up to
    :data:`INNER_CV_ROWS` of them, else — or when no fold can be calibrated — from their
    leave-one-out residuals), scored on its test rows; None when the training rows cannot
    give the covariances. With ``warm`` every predictor is one step from it (issue 29)."""
    try:
        predictor = predictor_from_fit(chain, fit, train, measurement, options, settings, warm=warm)
    except KincalError:
        return None
    weight = options.rotation_weight_m_per_rad
    if train.n > INNER_CV_ROWS:
        model_error = model_error_of(chain, predictor, train, measurement, weight)
        return SplitCoverage(score_rows(chain, predictor, test, measurement), model_error, False)
    inner = cross_validated_rows(
        chain,
        train,
        measurement,
        options,
        settings,
        folds=INNER_FOLDS,
        seed=seed,
        start_theta=predictor.theta,
        warm=warm,
    )
    if not inner.residuals.shape[0]:
        model_error = model_error_of(chain, predictor, train, measurement, weight)
        return SplitCoverage(score_rows(chain, predictor, test, measurement), model_error, False)
    model_error = estimate_model_error(inner.residuals, inner.base, inner.axes)
    return SplitCoverage(score_rows(chain, predictor, test, measurement), model_error)


@dataclass(frozen=True)
class PredictiveCalibration:
    """What a predictor needs beyond the calibrated model to rebuild the total covariance of
    a new configuration (issue 13), and how well it held on the held-out splits.

    ``estimated``: the parameter names of ``parameter_covariance`` (p, p), the sandwich
    Cov(θ̂) of the calibration over every used sample; ``model_error``: the model-error part
    from the held-out residuals of the splits (without splits: the leave-one-out residuals of
    the calibration's in-memory rows); ``coverage``: the
    held-out residuals of every split under the total its training rows predicted (None
    without splits); ``splits``: the per-seed material."""

    estimated: list[str]
    parameter_covariance: FloatArray
    model_error: ModelErrorFit
    coverage: Coverage | None
    splits: dict[int, SplitCoverage]


def calibration_predictive(
    chain: KinematicChain,
    params: ChainParameters,
    estimated: list[str],
    gram: FloatArray,
    n_used: int,
    rows: RowSample,
    estimate: CovarianceEstimate,
    frames: tuple[int, ...],
    measurement: FullPose,
    rotation_weight: float,
    splits: dict[int, SplitCoverage],
) -> PredictiveCalibration:
    """The predictive parts of a calibration whose fit of ``n_used`` samples has the normal
    matrix ``gram``: Cov(θ̂) with the meat over ``rows`` (all or an evenly spaced subset of
    the used samples, scaled to ``n_used``), the model-error part from the held-out residuals
    of ``splits`` (none: the leave-one-out residuals of ``rows``), and their coverage."""
    d = measurement.dim
    columns = _columns(chain, estimated)
    point = prediction_point(chain, params, columns, rows.joint_positions, rows.loads_nm, d)
    random = estimate.ee_covariance(point.frame_jacobians[:, list(frames)], include_noise=True)
    covariance = sandwich_covariance(gram, point, random, rotation_weight, n_used / max(rows.n, 1))
    noise = estimate.noise_covariance()[:d, :d]
    predictor = Predictor(
        params, columns, covariance, gram, frames, estimate.frame_covariances(), noise
    )
    if not splits:
        model_error = model_error_of(chain, predictor, rows, measurement, rotation_weight)
        return PredictiveCalibration(estimated, covariance, model_error, None, splits)
    pooled = ScoredRows.join([s.scored for s in splits.values()], d)
    model_error = estimate_model_error(pooled.residuals, pooled.base, pooled.axes)
    measured = coverage(np.concatenate([s.distances_squared for s in splits.values()]), d)
    return PredictiveCalibration(estimated, covariance, model_error, measured, splits)
