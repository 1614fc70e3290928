"""Predictive covariance of a pose at a configuration q, and its coverage (issue 13).

Frames and units (DESIGN.md §2): residuals ``r = Log(X_model(q)⁻¹ X_measured)`` in the
end-effector frame, [v; w] in m and rad (position-only: the 3-D translation part). The total
covariance a planner needs for a new configuration is the sum of three independent parts

    Σ_total(q) = Σ_E(q)                              Eq. (12): random perturbations (+ Σ_n)
               + J_θ(q) Cov(θ̂) J_θ(q)ᵀ               the deterministic fit's estimation error
               + T(q) diag(s) T(q)ᵀ                  model error no term describes

- ``J_θ(q)`` (d, p): the columns of the stacked Jacobian (Eq. 9) of the p parameters the fit
  estimated (identifiable ones), the same linearisation Gauss–Newton uses; a parameter error δθ
  moves the residual by ``−J_θ δθ``.
- ``Cov(θ̂)``: the sandwich covariance of the (rotation-weighted) least-squares estimate under
  the calibrated random-effects model: with ``A_w = W A`` the weighted Jacobian rows of the
  used samples, ``G = Σ A_wᵀ A_w`` (the Gauss–Newton normal matrix) and
  ``M = Σ A_wᵀ W Σ_E(q_n) W A_w``, ``Cov(θ̂) = G⁻¹ M G⁻¹``. The homoscedastic ``σ² G⁻¹`` of
  :func:`solver.calibration.parameter_standard_errors` pools metres and radians into one σ²;
  the sandwich weights each sample by the covariance the model predicts for it.
- ``T(q) = blockdiag(R(q)ᵀ, R(q)ᵀ)`` (d, d), R the model's end-effector orientation in the
  measurement frame: ``T u`` is the end-effector-frame residual of an error ``u`` whose
  translation and rotation are given along the measurement frame's axes. The model-error part
  is diagonal along those axes (a sensor's unmodelled errors — depth scale, lens distortion,
  tracker calibration — are axis-aligned in its frame; geometric model error has no preferred
  axis in either frame, so nothing is lost). Its variances ``s`` (d,) are fitted by maximum
  likelihood to cross-validated residuals: residuals of poses that took no part in the fit
  they are scored against, whose predicted covariance already holds the two other parts.

Coverage: for a held-out residual r with predicted covariance Σ, ``d² = rᵀ Σ⁻¹ r`` is χ²_d
distributed when Σ is right; the share of held-out poses with ``d² ≤ χ²_d⁻¹(α)`` is the share
inside the predicted α-ellipsoid, and ``mean d²`` should be d.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.distributions import chi2_quantile
from solver.kinematics import ChainParameters, evaluate_chain, stacked_jacobian
from solver.model import KinematicChain
from solver.small_spd import spd_factors

COVERAGE_LEVELS = (0.5, 0.9, 0.95, 0.99)
"""The ellipsoids whose coverage a calibration reports (issue 13)."""

CURVE_LEVELS = (*np.round(np.arange(0.05, 0.951, 0.05), 2).tolist(), 0.99)
"""Expected levels of the coverage curve (expected vs observed quantile)."""


def row_weights(d: int, rotation_weight: float) -> FloatArray:
    """The fit's residual row weights (d,): 1 for translation, the rotation weight (m/rad)
    for rotation rows (full pose only)."""
    weights = np.ones(d)
    weights[3:] = rotation_weight
    return weights


# --- the parts ------------------------------------------------------------------------------


@dataclass(frozen=True)
class PredictionPoint:
    """The calibrated model at N configurations: ``pose`` (N, 4, 4) in the measurement frame,
    ``frame_jacobians`` (N, k+1, d, 6) of every link frame (Eq. 12's A_j, tip frame last) and
    ``parameter_jacobian`` (N, d, p) of the estimated parameters, unweighted (m or rad per
    parameter unit)."""

    pose: FloatArray
    frame_jacobians: FloatArray
    parameter_jacobian: FloatArray


def prediction_point(
    chain: KinematicChain,
    params: ChainParameters,
    estimated: IntArray,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    d: int,
) -> PredictionPoint:
    """Pose and Jacobians at configurations (N, k) rad with gravity loads (N, n_axes) N·m;
    ``estimated``: the stacked-Jacobian columns (:func:`solver.kinematics.parameter_names`
    order) of the fit's identifiable parameters; ``d`` 6 (full pose) or 3 (position-only)."""
    evaluation = evaluate_chain(chain, params, joint_positions, loads_nm)
    columns = stacked_jacobian(evaluation)[:, :d]
    return PredictionPoint(
        evaluation.pose,
        np.ascontiguousarray(evaluation.link_jacobians[:, :, :d, :]),
        np.ascontiguousarray(columns[:, :, estimated]),
    )


def sandwich_meat(
    weighted_jacobian: FloatArray, covariances: FloatArray, weights: FloatArray
) -> FloatArray:
    """``M = Σ_n A_w,nᵀ W Σ_n W A_w,n`` (p, p): ``weighted_jacobian`` (N, d, p) the fit's rows
    times ``weights`` (d,) (W = diag(weights)), ``covariances`` (N, d, d) the residuals'
    predicted covariances Σ_E(q_n) (m², m·rad, rad²)."""
    scaled = weights[None, :, None] * weighted_jacobian
    return np.asarray(
        np.einsum("ndp,nde,neq->pq", scaled, covariances, scaled, optimize=True), dtype=float
    )


def parameter_covariance(gram: FloatArray, meat: FloatArray) -> FloatArray:
    """Sandwich ``Cov(θ̂) = G⁺ M G⁺`` (p, p) of the least-squares estimate, in the parameters'
    units (local twists m and rad, compliance rad/N·m): ``gram`` G the Gauss–Newton normal
    matrix (Eq. 10, ``AᵀA`` of the weighted rows), ``meat`` M of :func:`sandwich_meat`. The
    pseudo-inverse is taken of the unit-norm-scaled G (its columns span metres and rad/N·m)."""
    inverse = gram_inverse(gram)
    covariance = inverse @ meat @ inverse
    return np.asarray(0.5 * (covariance + covariance.T), dtype=float)


def gram_inverse(gram: FloatArray) -> FloatArray:
    """``G⁺`` (p, p) of a normal matrix whose columns mix units: the pseudo-inverse of the
    unit-diagonal scaled G, scaled back."""
    norms = np.sqrt(np.clip(np.diag(gram), 0.0, None))
    norms = np.where(norms > 0.0, norms, 1.0)
    inverse = np.linalg.pinv(gram / np.outer(norms, norms), hermitian=True)
    return np.asarray(inverse / np.outer(norms, norms), dtype=float)


def leave_one_out_residuals(
    residuals: FloatArray, weighted_jacobian: FloatArray, weights: FloatArray, gram: FloatArray
) -> FloatArray:
    """Residuals (N, d) each sample would have under the least-squares fit of the others,
    linearised at the fit: with the weighted residual ``y_n = W r_n``, the block leverage
    ``H_nn = A_w,n G⁺ A_w,nᵀ`` (d, d) and the fit's normal matrix ``G = Σ A_wᵀ A_w`` (p, p;
    over all its samples, of which these N may be a subset), the left-out residual is
    ``W⁻¹ (I − H_nn)⁻¹ y_n`` (the exact deletion identity of linear least squares).
    ``weighted_jacobian`` (N, d, p) the fit's rows times ``weights`` (d,)."""
    d = weighted_jacobian.shape[1]
    leverage = row_sandwich(weighted_jacobian, gram_inverse(gram))
    complement = np.eye(d)[None] - leverage
    left_out = np.linalg.solve(complement, (weights * residuals)[:, :, None])[..., 0]
    return np.asarray(left_out / weights, dtype=float)


def row_sandwich(jacobian: FloatArray, matrix: FloatArray) -> FloatArray:
    """``J_n M J_nᵀ`` (N, d, d) for every row's ``jacobian`` (N, d, p) and one ``matrix``
    (p, p), as two batched matrix products (a three-operand einsum loops over all N·d²·p²
    products: 35× slower at N = 900, p = 40)."""
    return np.asarray((jacobian @ matrix) @ jacobian.transpose(0, 2, 1), dtype=float)


def parameter_part(parameter_jacobian: FloatArray, covariance: FloatArray) -> FloatArray:
    """``J_θ(q) Cov(θ̂) J_θ(q)ᵀ`` (N, d, d), end-effector frame, m²/m·rad/rad²:
    ``parameter_jacobian`` (N, d, p) unweighted, ``covariance`` (p, p)."""
    return row_sandwich(parameter_jacobian, covariance)


def measurement_axes(model_pose: FloatArray, d: int) -> FloatArray:
    """``T(q) = blockdiag(Rᵀ, Rᵀ)`` (N, d, d): maps an error along the measurement frame's
    axes (translation m, rotation rad) to the end-effector-frame residual; ``model_pose``
    (N, 4, 4) the model's end-effector pose in the measurement frame."""
    rotation_t = np.swapaxes(model_pose[:, :3, :3], 1, 2)
    out = np.zeros((model_pose.shape[0], d, d))
    out[:, :3, :3] = rotation_t
    if d == 6:
        out[:, 3:, 3:] = rotation_t
    return out


def model_error_part(axes: FloatArray, variances: FloatArray) -> FloatArray:
    """``T diag(s) Tᵀ`` (N, d, d): ``axes`` T (N, d, d) of :func:`measurement_axes`,
    ``variances`` s (d,) along the measurement frame's axes (m², rad²)."""
    return np.asarray((axes * variances[None, None, :]) @ np.swapaxes(axes, 1, 2), dtype=float)


# --- the model-error part from cross-validated residuals -----------------------------------


@dataclass(frozen=True)
class ModelErrorFit:
    """Variances ``variance`` (d,) of the model-error part along the measurement frame's axes
    (m², rad²), from ``n_residuals`` cross-validated residuals; ``converged``: the optimiser's
    verdict; ``nll``: the Gaussian negative log-likelihood at the optimum (constants left
    out)."""

    variance: FloatArray
    n_residuals: int
    converged: bool
    nll: float

    @classmethod
    def none(cls, d: int) -> ModelErrorFit:
        """No model-error part (no cross-validated residuals to estimate it from)."""
        return cls(np.zeros(d), 0, False, float("nan"))


JITTER = 1e-6
"""Every model-error variance is at least this share of the residuals' mean square along its
axis (0.1 % of their standard deviation): keeps the likelihood finite where the other parts
are singular (an estimated Σ_n can be exactly 0 on an axis)."""


def estimate_model_error(
    residuals: FloatArray, base: FloatArray, axes: FloatArray
) -> ModelErrorFit:
    """Maximum likelihood of the model-error variances s ≥ 0 (d,) given cross-validated
    residuals ``residuals`` (N, d) (end-effector frame), the covariance the other parts predict
    for each (``base``, (N, d, d)) and the axes T (N, d, d) of :func:`measurement_axes`:

        min_s Σ_n log det Σ_n(s) + r_nᵀ Σ_n(s)⁻¹ r_n,   Σ_n(s) = base_n + T_n diag(s) T_nᵀ

    by bounded L-BFGS-B on s scaled by the residuals' mean square per measurement axis,
    started from the moment estimate ``max(0, mean u_a² − mean (Tᵀ base T)_aa)``, u = Tᵀ r.
    Gradient: ``∂/∂s_a = Σ_n (TᵀΣ⁻¹T)_aa − (TᵀΣ⁻¹r)_a²``.
    """
    n, d = residuals.shape
    if n == 0:
        return ModelErrorFit.none(d)
    along = np.einsum("nda,nd->na", axes, residuals)  # u = Tᵀ r (N, d)
    scale = np.mean(along**2, axis=0)
    scale = np.where(scale > 0.0, scale, max(float(scale.max()), 1e-30))
    floor = JITTER * scale
    base_along = axes.transpose(0, 2, 1) @ base @ axes  # Tᵀ base T (N, d, d)
    start = np.maximum(scale - np.mean(np.diagonal(base_along, axis1=1, axis2=2), axis=0), 0.0)

    def objective(x: FloatArray) -> tuple[float, FloatArray]:
        covariance = base + model_error_part(axes, x * scale + floor)
        try:
            chol = np.linalg.cholesky(covariance)
        except np.linalg.LinAlgError:
            return 1e300, -np.ones(d)
        inverse = np.linalg.inv(covariance)
        whitened = inverse @ residuals[:, :, None]  # Σ⁻¹ r (N, d, 1)
        value = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum() + float(
            np.einsum("nd,nd->", residuals, whitened[:, :, 0])
        )
        projected = ((inverse @ axes) * axes).sum(axis=1)  # diag(Tᵀ Σ⁻¹ T) (N, d)
        t_whitened = np.einsum("nda,nd->na", axes, whitened[:, :, 0])
        gradient = projected.sum(0) - (t_whitened**2).sum(0)
        return value, gradient * scale

    import scipy.optimize  # lazy: 0.1 s at start-up, only for this fit (not for kincal check)

    answer = scipy.optimize.minimize(
        objective,
        start / scale,
        jac=True,
        method="L-BFGS-B",
        bounds=[(0.0, None)] * d,
        options={"maxiter": 500},
    )
    return ModelErrorFit(
        np.asarray(answer.x, dtype=float) * scale + floor, n, bool(answer.success), answer.fun
    )


# --- coverage --------------------------------------------------------------------------------


CHOLESKY_MAX_CONDITION = 1e8
"""Samples whose Σ_n may have a condition number above this go the eigendecomposition way in
:func:`mahalanobis_squared` (the Cholesky way's relative rounding error is ~1e-16 · condition)."""


def mahalanobis_squared(residuals: FloatArray, covariances: FloatArray) -> FloatArray:
    """``d²_n = r_nᵀ Σ_n⁻¹ r_n`` (N,) for residuals (N, d) and covariances (N, d, d); inf where
    Σ_n is singular and r_n leaves its range (the prediction says that pose is impossible).
    Eigenvalues below 1e-12 of a sample's largest count as zero.

    ``d² = ‖L_n⁻¹ r_n‖²`` with the Cholesky factor ``Σ_n = L_n L_nᵀ``
    (:func:`~solver.small_spd.spd_factors`, ~8× faster than an eigendecomposition per sample:
    the model outlier rule evaluates it for every row of a recording). A sample goes the
    eigendecomposition way (:func:`_mahalanobis_squared_eigh`) when its Σ_n is not positive
    definite or may be ill-conditioned (:meth:`~solver.small_spd.SpdFactors.condition_bound`
    above :data:`CHOLESKY_MAX_CONDITION`); below it both ways agree to ~1e-8 relative."""
    symmetric = 0.5 * (covariances + covariances.transpose(0, 2, 1))
    factors = spd_factors(symmetric)
    whitened = factors.whiten(residuals)
    d2 = np.einsum("nd,nd->n", whitened, whitened)
    doubtful = ~(factors.condition_bound(symmetric) <= CHOLESKY_MAX_CONDITION) | ~np.isfinite(d2)
    if np.any(doubtful):
        d2[doubtful] = _mahalanobis_squared_eigh(residuals[doubtful], symmetric[doubtful])
    return d2


def _mahalanobis_squared_eigh(residuals: FloatArray, covariances: FloatArray) -> FloatArray:
    """:func:`mahalanobis_squared` by an eigendecomposition of each symmetric Σ_n: the
    range of a singular Σ_n is the span of its eigenvectors above the cut."""
    values, vectors = np.linalg.eigh(covariances)
    cut = np.clip(values.max(axis=1), 0.0, None) * 1e-12
    along = np.einsum("nde,nd->ne", vectors, residuals)
    inside = values > cut[:, None]
    norm = np.maximum(np.linalg.norm(residuals, axis=1), 1e-300)
    outside = np.any(~inside & (np.abs(along) > 1e-9 * norm[:, None]), axis=1)
    safe = np.where(inside, values, 1.0)
    d2 = np.sum(np.where(inside, along**2 / safe, 0.0), axis=1)
    return np.where(outside, np.inf, d2)


@dataclass(frozen=True)
class Coverage:
    """How well predicted covariances cover held-out residuals: ``dimension`` d (6 or 3),
    ``n`` residuals; ``expected`` levels α and ``observed`` shares with ``d² ≤ χ²_d⁻¹(α)``;
    ``mean_d2`` the mean squared Mahalanobis distance (χ²_d mean: d), ``median_d2`` its
    median (χ²_d median: ``chi2_median``)."""

    dimension: int
    n: int
    expected: tuple[float, ...]
    observed: tuple[float, ...]
    mean_d2: float
    median_d2: float

    @property
    def chi2_median(self) -> float:
        return chi2_quantile(0.5, self.dimension)

    def at(self, level: float) -> float:
        """The observed share inside the ``level`` ellipsoid."""
        return self.observed[self.expected.index(level)]


def coverage(
    distances_squared: FloatArray,
    dimension: int,
    levels: tuple[float, ...] = tuple(sorted({*COVERAGE_LEVELS, *CURVE_LEVELS})),
) -> Coverage:
    """Observed shares of ``distances_squared`` (N,) inside the χ²_``dimension`` quantile of
    each level."""
    quantiles = [chi2_quantile(level, dimension) for level in levels]
    d2 = np.asarray(distances_squared, dtype=float)
    observed = tuple(float(np.mean(d2 <= q)) for q in quantiles)
    return Coverage(
        dimension,
        int(d2.size),
        tuple(float(a) for a in levels),
        observed,
        float(np.mean(d2)),
        float(np.median(d2)),
    )


# --- a calibrated predictor at new configurations ------------------------------------------


@dataclass(frozen=True)
class PredictiveParts:
    """The parts beyond Σ_E of the predicted covariance at N configurations, (N, 6, 6) each,
    end-effector frame, [v; w], m²/m·rad/rad²; ``pose`` (N, 4, 4) the predicted pose."""

    pose: FloatArray
    parameters: FloatArray
    model_error: FloatArray


@dataclass(frozen=True)
class PredictiveModel:
    """A calibrated chain with Cov(θ̂) of its ``estimated`` columns (p, p) and the model-error
    variances (6,) along the measurement frame's axes (zeros on axes the data did not measure,
    e.g. rotations of a position-only recording)."""

    chain: KinematicChain
    params: ChainParameters
    estimated: IntArray
    parameter_covariance: FloatArray
    model_error_variance: FloatArray
    model_error_in_tip_frame: bool = False
    """True: the variances are along the end-effector frame's axes (a measurement type whose
    residual is the tip pose, e.g. relative-base), so T(q) = I."""

    def point(self, joint_positions: FloatArray, loads_nm: FloatArray) -> PredictionPoint:
        """:class:`PredictionPoint` (6-D) at configurations (N, k) rad, loads (N, n_axes)."""
        return prediction_point(
            self.chain, self.params, self.estimated, joint_positions, loads_nm, 6
        )

    def model_error(self, point: PredictionPoint) -> FloatArray:
        """The model-error part ``T diag(s) Tᵀ`` (N, 6, 6) at a :meth:`point`."""
        return model_error_part(
            np.broadcast_to(np.eye(6), (point.pose.shape[0], 6, 6))
            if self.model_error_in_tip_frame
            else measurement_axes(point.pose, 6),
            self.model_error_variance,
        )

    def parts(self, joint_positions: FloatArray, loads_nm: FloatArray) -> PredictiveParts:
        """:class:`PredictiveParts` at configurations (N, k) rad, gravity loads (N, n_axes)."""
        point = self.point(joint_positions, loads_nm)
        return PredictiveParts(
            point.pose,
            parameter_part(point.parameter_jacobian, self.parameter_covariance),
            self.model_error(point),
        )


INNER_FOLDS = 3
"""Folds of the cross-validation inside a split's training rows that gives the split its own
model-error part."""


@dataclass(frozen=True)
class ScoredRows:
    """Rows scored by a predictor: residuals (n, d) in the covariance's space (the end-effector
    frame for poses; :mod:`solver.measurement.predictive` for the other types), the covariance of
    every part but the model error (``base``, (n, d, d)), Σ_E + Σ_n alone (``random``) and
    the measurement axes T (n, d, d) of :func:`~solver.predictive.measurement_axes`."""

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
