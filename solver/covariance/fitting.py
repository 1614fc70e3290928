"""Minimising the ML (Eq. 17) or REML negative log-likelihood over PSD covariances.

Projected scoring, started from the moment solution (Eq. 14) and from it with every variance
lifted (:func:`_starts`; the lower optimum is kept): each step solves the cone QP
``min_θ' ½(θ'−θ)ᵀH(θ'−θ) + ∇NLL(θ)ᵀ(θ'−θ)`` over θ' ≥ floor (diagonal) or Σ'_f ⪰ floor
(full), with the solver "auto" picks for Eq. (14) (nnls / clarabel), then searches along the
segment θ → θ' (which stays in the cone). The floor keeps every noise σ at 1e-3 of the RMS
residual on its axis (:func:`noise_floor`: without it the NLL of a small recording has no
minimum). H is the average information (:func:`~.likelihood.average_information`, exact in
expectation and data-aware) plus a tiny proximal term for the null directions
(:func:`_proximal`); the one-step estimator of a large recording uses the expected information
2·I(θ) of Eq. (16). Above ``METRIC_SAMPLES`` samples H is taken on an evenly spaced subset and
scaled to N. Every NLL evaluation is a pass over the samples (:mod:`.samples`: in memory or
streamed).

The Hessian of the NLL is ``2·AI − 2·I`` (:func:`~.likelihood.observed_information`), so AI is
the mean of the observed and the expected curvature and overrates the observed one where the
data curve the NLL less than expected: along the weak directions of a small recording about 2×
(TIAGo Qualisys file), and each scoring step then only halves the error. Once that tail is
reached — the decrease of a step is below what the NLL's rounding can show — a diagonal fit
takes projected Newton steps with the exact Hessian on the face of the box the scoring QP ends
on (:func:`_newton_step`), where the NLL is convex near a minimum: 2 steps per start on that
file's fits, where the scoring took 16–22.

For ML with the expected information the unconstrained step is the moment match of Eq. (13)
weighted by Σ_E⁻¹ ⊗ Σ_E⁻¹ (iteratively reweighted moment matching). The metric changes the
path, not the fixed point; the stopping rule (:func:`fit_likelihood`) makes the end point a
property of the data, not of the arithmetic: the same to 1e-6 under every BLAS kernel
(tests/test_same_numbers.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from typing import Literal

import numpy as np

from solver.arrays import BoolArray, FloatArray
from solver.covariance.layout import CovarianceLayout
from solver.covariance.likelihood import (
    average_information,
    fisher_information_ml,
    gaussian_nll,
    observed_information,
    restricted_nll,
    restriction,
    theta_gradient,
)
from solver.covariance.objective import ProblemScaling, clip_psd, moment_objective
from solver.covariance.samples import ArraySamples, CovarianceSamples
from solver.covariance.solvers import CovarianceSolution, Status, solve_moment
from solver.covariance.statistics import MomentStatistics
from solver.errors import CalibrationError

Estimator = Literal["ml", "reml"]

PROXIMAL_RTOL = 1e-10
"""The proximal weight of the scoring metric relative to a curvature (:func:`_proximal`)."""
METRIC_SAMPLES = 4096
"""The scoring metric H comes from at most this many samples (evenly spaced, scaled to N):
H only shapes the path of the iteration, not its fixed point (the gradient uses every sample),
and a full pass per step would double the cost of each iteration at large N."""


def fit_likelihood(
    estimator: Estimator,
    start_theta: FloatArray,
    samples: CovarianceSamples,
    stats: MomentStatistics,
    scaling: ProblemScaling,
    metric: ArraySamples,
    *,
    transform: FloatArray | None = None,
    restriction_samples: ArraySamples | None = None,
    known_covariance: FloatArray | None = None,
    max_iterations: int = 200,
    one_step: bool = False,
    tolerance: float = 1e-10,
    null_basis: FloatArray | None = None,
    refine: bool = False,
) -> CovarianceSolution:
    """ML or REML estimate of θ (Q,), started from ``start_theta`` (PSD, e.g. moment).

    ``samples``: every used sample (each NLL evaluation is one pass over them, two for
    REML); ``metric``: the samples the scoring metric is taken from (at most
    :data:`METRIC_SAMPLES`, scaled to N); ``transform``: REML's fit basis
    (:func:`~solver.covariance.likelihood.fit_basis_transform`) of ``samples``, or of
    ``restriction_samples`` when REML's restriction terms are taken on those instead
    (:func:`~solver.covariance.likelihood.restriction`; the likelihood terms then cost one
    pass per evaluation). Stops when the predicted decrease ``−∇NLLᵀ(θ'−θ)`` per sample is
    below ``tolerance`` (reported as ``kkt_residual``), or after ``max_iterations`` scoring
    steps; ``one_step``: exactly one full step without line search, status "one_step" (from
    a √N-consistent start such as the moment solution, as efficient as the converged
    estimator up to O(1/N)); one NLL evaluation in all, so ``objective`` is then the NLL at
    the start. ``objective`` is the NLL (constants omitted). ``null_basis`` (Q, k):
    directions (equilibrated, orthonormal) that do not change Σ_E, along which the NLL is
    exactly flat and the step is rounding (the caller fixes them by rule afterwards); they do
    not count in the step-size test of convergence. ``refine``: one full scoring step from
    ``start_theta`` with the average-information metric, no line search, status "one_step"
    (a step of :func:`.estimate.subset_estimate` or of the refined one-step estimator;
    ``objective`` is the NLL at the start).
    """
    started = time.perf_counter()
    layout = stats.layout
    n = samples.n_samples
    if estimator == "reml" and transform is None:
        raise CalibrationError(
            "estimator 'reml' needs fit_jacobian (the deterministic fit's "
            "Jacobian in the residual space)"
        )

    def nll(theta: FloatArray) -> tuple[float, FloatArray]:
        if estimator == "reml" and restriction_samples is None:
            assert transform is not None
            return restricted_nll(
                theta, samples, transform, layout, known_covariance=known_covariance
            )
        value, psi = gaussian_nll(theta, samples, layout, known_covariance=known_covariance)
        if estimator == "ml" or not np.isfinite(value):
            return value, psi
        assert transform is not None and restriction_samples is not None
        extra, extra_psi = restriction(
            theta, restriction_samples, transform, layout, known_covariance=known_covariance
        )
        return value + extra, psi + extra_psi

    floor = noise_floor(stats)
    weight = n / metric.n_samples  # the metric's samples stand for all N
    # iterated diagonal fits: per-entry proximal weights and Newton steps in the tail
    exact = layout.structure == "diag" and not (one_step or refine)

    def newton_tail(
        theta: FloatArray,
        grad: FloatArray,
        average: FloatArray,
        damping: FloatArray,
        face: BoolArray,
    ) -> tuple[FloatArray, float, FloatArray] | None:
        """A projected Newton step (:func:`_newton_step`, the Hessian of the NLL from the
        ``metric`` samples scaled to N like the scoring metric ``average``), sized by the slope
        of the NLL along it (:func:`_slope_search`); None where the NLL is not convex on the
        face or the slope does not confirm the step."""
        observed = weight * observed_information(
            theta,
            metric,
            layout,
            transform=transform,
            known_covariance=known_covariance,
            average=average,
        )
        step = _newton_step(theta, grad, observed, damping, face, floor, scaling)
        if step is None:
            return None
        return _slope_search(nll, theta, step, float(-grad @ step), layout)

    def scoring(start: FloatArray) -> CovarianceSolution:
        theta, (value, psi) = _positive_start(start + floor, nll, layout, scaling)
        status: Status = "iteration_limit"
        decrement, message, iterations, blind, newton_steps = float("inf"), "", 0, 0, 0
        for _ in range(1 if one_step or refine else max_iterations):
            iterations += 1
            grad = theta_gradient(layout, psi)
            average = _metric(
                theta, metric, layout, transform, known_covariance, one_step and not refine
            )
            hess = weight * average
            damping = _proximal(hess, scaling, per_entry=exact)
            gram = hess + np.diag(damping)
            # the QP in θ − floor (the cone shifted by the noise floor, :func:`noise_floor`)
            qp = MomentStatistics(layout, gram, gram @ (theta - floor) - grad, 0.0, n)
            shifted = solve_moment(qp, "auto", start=theta - floor).theta
            target = shifted + floor
            if not np.all(np.isfinite(target)):
                status, message = "error", "scoring QP failed"
                break
            step = target - theta
            decrement = float(-grad @ step)
            if one_step or refine:  # the one-step estimator: the full step, no line search
                theta, status = target, "one_step"
                break
            # Converged, full Σ: the predicted decrease is below the tolerance (or what the
            # NLL's rounding can show; the cone program's steps are not exact enough for
            # more). Diagonal Σ (NNLS steps are exact): below the tolerance, and the step
            # below STEP_RTOL outside the exactly flat directions — a weakly identified entry
            # is crossed by steps whose decrease is below any tolerance, and where the fit
            # stops in it must not depend on rounding.
            rounding = NLL_RTOL * abs(value)
            if layout.structure == "diag":
                done = decrement <= tolerance * n and _small(step, theta, scaling, null_basis)
            else:
                done = decrement <= max(tolerance * n, rounding)
            if done:
                status = "optimal"
                break
            found = _line_search(nll, theta, step, value, decrement, layout, rounding, floor)
            if found is None and blind < BLIND_STEPS:
                # No decrease the NLL's rounding can show (it grows with the conditioning of
                # Σ_E: 1e-9 of −317 on the TIAGo file under OpenBLAS's SSE kernel): the step is
                # sized by the NLL's slope along it, which the gradient gives more precisely.
                blind += 1
                if exact:  # the scoring's steps only halve the error from here on (AI ≈ 2·H)
                    found = newton_tail(theta, grad, average, damping, shifted <= 0.0)
                    newton_steps += found is not None
                if found is None:
                    found = _slope_search(nll, theta, step, decrement, layout)
            if found is None:  # no decrease the NLL's rounding can show along the step
                if decrement <= max(tolerance * n, rounding):
                    status = "optimal"
                    message = (
                        f"converged to the NLL's rounding (last step {decrement / n:.1e} "
                        "per sample)"
                    )
                else:
                    status = "optimal_inaccurate"
                    message = (
                        f"line search stalled (predicted decrease {decrement / n:.2e} per sample)"
                    )
                break
            theta, value, psi = found
        clipped = layout.theta_from_covariances(clip_psd(layout.frame_covariances(theta)))
        if not np.array_equal(clipped, theta):  # a full Σ left the cone by rounding
            theta = clipped
            if not (one_step or refine):
                value = nll(clipped)[0]
        return CovarianceSolution(
            estimator,
            status,
            theta,
            layout.frame_covariances(theta),
            iterations,
            time.perf_counter() - started,
            float(value),
            moment_objective(theta, stats),
            max(decrement, 0.0) / n,
            message
            or _scoring_message(iterations, one_step, restriction_samples, refine, newton_steps),
        )

    if one_step or refine:
        return scoring(start_theta)
    runs = [scoring(start) for start in _starts(start_theta, layout, scaling)]
    best = min(runs, key=lambda run: (run.status != "optimal", _finite_or_inf(run.objective)))
    others = ", ".join(f"{run.objective:.6g} ({run.status})" for run in runs if run is not best)
    return replace(
        best,
        iterations=sum(run.iterations for run in runs),
        wall_time_s=time.perf_counter() - started,
        message=f"{best.message}; best of {len(runs)} starts (the others: NLL {others})",
    )


NLL_RTOL = 1e-10
"""Relative rounding of an NLL evaluation: a predicted decrease below it cannot be checked."""
STEP_RTOL = 1e-9
"""The scoring has converged when its step is below this, in equilibrated units (θ̂ = O(1))."""
BLIND_STEPS = 50
"""At most this many steps whose decrease is below the NLL's rounding are taken on trust."""
LIFT = 0.1
"""The second start of the likelihood fit adds this fraction of the mean equilibrated variance
to every variance (:func:`_starts`)."""


def _starts(
    theta: FloatArray, layout: CovarianceLayout, scaling: ProblemScaling
) -> list[FloatArray]:
    """Where the scoring starts: ``theta`` and ``theta`` with every variance lifted by
    :data:`LIFT` of the mean variance (equilibrated units); the fit keeps the lower optimum.

    The likelihood of a small recording with many covariance entries has several local minima,
    and the moment solution sits on the boundary of the cone (most variances 0), next to one
    of them. Measured on the held-out fits of ``kincal calibrate`` (42 per recording): on the
    UR10e (22 poses, 42 entries) the lifted start ended lower in 4 (by up to 4.9 in NLL) and
    higher in 3; TIAGo (21 positions, 54 entries) lower in 4 of 14 REML fits, by ≤ 0.001;
    TALOS lower in 1 of 41 (by 0.08); FR3 (112 poses) the same in all 42.
    """
    variance = layout.is_variance
    scaled = scaling.to_scaled(theta)
    mean = float(np.mean(np.clip(scaled[variance], 0.0, None))) if np.any(variance) else 0.0
    lift = np.where(variance, LIFT * (mean if mean > 0.0 else 1.0), 0.0)
    return [theta, scaling.from_scaled(scaled + lift)]


NOISE_FLOOR = 1e-3
"""The likelihood fit keeps every measurement-noise σ at or above this fraction of the RMS
residual on its axis (:func:`noise_floor`)."""


def noise_floor(stats: MomentStatistics) -> FloatArray:
    """Lower bounds (Q,) of θ: ``(NOISE_FLOOR · RMS residual)²`` on every noise variance (the
    RMS over all N samples of the residual rows that noise axis reaches), 0 elsewhere.

    The mean square comes from the moment statistics (Eq. 14): a noise variance enters Σ_E as
    ``Σ_rows e_r e_rᵀ``, so its entry of h is ``Σ_n Σ_rows r_{n,r}²``. The floor is therefore the
    same whether the samples were read whole or streamed in chunks.

    A sensor's noise is not zero, and the likelihood of a small recording with many covariance
    entries has no minimum without a bound: when the chain frames can explain a residual
    direction exactly, a noise variance driven to 0 makes some Σ_E singular and the NLL falls
    without end (a 14-pose fold of the TIAGo file: −86.46 → −87.14 in one step, the NLL's
    slope along it 1e4× what its gradient predicts). With the bound every Σ_E ⪰ the floor, and
    the NLL is bounded below. A noise σ at the floor means the data put it below 0.1 % of the
    residuals."""
    layout = stats.layout
    out = np.zeros(layout.n_params)
    if layout.noise_frame is None or stats.n_samples == 0:
        return out
    for p in np.flatnonzero(layout.is_noise & layout.is_variance):
        frame = layout.param_frame[p] - layout.n_chain_frames
        axis = layout.param_row[p]
        n_rows = sum(1 for placement in layout.placements[frame] if placement[axis] >= 0)
        if n_rows:
            mean_square = max(float(stats.cross[p]), 0.0) / (stats.n_samples * n_rows)
            out[p] = NOISE_FLOOR**2 * mean_square
    return out


def _small(
    step: FloatArray, theta: FloatArray, scaling: ProblemScaling, null_basis: FloatArray | None
) -> bool:
    """The step is below :data:`STEP_RTOL` of θ (equilibrated units, at least 1) outside the
    directions ``null_basis`` where the NLL is exactly flat (its size there is rounding)."""
    scaled = scaling.to_scaled(step)
    if null_basis is not None and null_basis.shape[1]:
        scaled = scaled - null_basis @ (null_basis.T @ scaled)
    size = float(np.max(np.abs(scaled), initial=0.0))
    reference = float(np.max(np.abs(scaling.to_scaled(theta)), initial=0.0))
    return size <= STEP_RTOL * max(reference, 1.0)


def _proximal(hess: FloatArray, scaling: ProblemScaling, *, per_entry: bool) -> FloatArray:
    """The proximal weights (Q,) added to the diagonal of the scoring metric ``hess``: the QP then
    has a unique solution along the exactly flat null directions of the NLL, and its step there is
    the rounding of the gradient divided by a weight, not an arbitrary point.

    ``per_entry`` (the iterated fit of a diagonal Σ): :data:`PROXIMAL_RTOL` of each entry's own
    curvature ``H_pp`` — a relative Levenberg–Marquardt term, independent of the units, that changes
    the step along any curved direction by about that fraction (an entry without curvature, a silent
    one, gets the weight below). Otherwise (full Σ, the one-step and refined estimators)
    :data:`PROXIMAL_RTOL` of the largest equilibrated curvature on every entry, the weight the fit
    had before: it is isotropic in the equilibrated units of the moment problem, where the curvature
    of the NLL is not. A noise variance near its floor has a curvature ∝ 1/θ²: on the TIAGo Qualisys
    file (51 entries, marker noise σ ≈ 0.002 mm) 8.8e12 against 0.25–50 along the weakly identified
    directions, so that weight (880) damped every step there to a gradient step, and the fits of
    ``kincal calibrate --covariance diag --seeds 1,2,3`` (9 REML fits of 20–34 rows; ML on the same
    samples) all crawled to the 200-step limit from both starts. With the per-entry weight all 18
    end "optimal", in 29–56 steps for both starts together.
    """
    scaled = np.diag(hess) * scaling.param_scale**2
    isotropic = PROXIMAL_RTOL * float(np.max(scaled, initial=0.0)) / scaling.param_scale**2
    if not per_entry:
        return np.asarray(isotropic, dtype=float)
    return np.asarray(np.where(scaled > 0.0, PROXIMAL_RTOL * np.diag(hess), isotropic))


def _newton_step(
    theta: FloatArray,
    grad: FloatArray,
    observed: FloatArray,
    damping: FloatArray,
    face: BoolArray,
    floor: FloatArray,
    scaling: ProblemScaling,
) -> FloatArray | None:
    """The projected Newton step (Q,) on the face of the box θ ≥ floor that the scoring QP's
    solution lies on (``face``: the entries it puts on their floor), or None where the NLL is not
    convex on that face.

    The entries of the face go to their floor (``s_A = floor_A − θ_A``); the others take the
    minimiser of the NLL's second-order model with its exact Hessian ``observed``
    (:func:`~.likelihood.observed_information`, plus the proximal ``damping``) given that:
    ``s_F = −H_FF⁻¹ (g_F + H_FA s_A)``; the step is then projected onto the box. Solved in
    equilibrated units (θ̂ = O(1)). None unless ``H_FF`` is positive definite (Cholesky) and
    the step descends (``gᵀs < 0``).

    The face of the QP rather than the ε-active set of Bertsekas' projected Newton method (entries
    within ε of the bound with a positive gradient, moved by a diagonal scaling): the QP has already
    decided, with its metric's coupling, which entries reach their floor. On the 18 Qualisys fits of
    :func:`_proximal` the face needs 2 Newton steps per start (scoring alone took 22 and 16 tail
    steps on the first of them); the ε-active set needed up to 12 per start, and taken from the
    first step on it left entries on their way to the floor free, whose curvature is often negative
    (log det is concave in a variance whose optimum is 0): ``H_FF`` indefinite at 18–43 of 31–80
    steps. Near a minimum the Newton step converges quadratically where the scoring, whose metric
    overrates the curvature along weak directions (AI = ½(H + 2·I)), only halves the error per step.
    """
    scale = scaling.param_scale
    free = ~face
    step = np.where(face, (floor - theta) / scale, 0.0)
    curvature = (observed + np.diag(damping)) * np.outer(scale, scale)
    try:
        factor = np.linalg.cholesky(curvature[np.ix_(free, free)])
    except np.linalg.LinAlgError:
        return None
    rhs = grad[free] * scale[free] + curvature[np.ix_(free, face)] @ step[face]
    step[free] = -np.linalg.solve(factor.T, np.linalg.solve(factor, rhs))
    out = np.maximum(theta + step * scale, floor) - theta
    return out if float(grad @ out) < 0.0 else None


def _finite_or_inf(value: float) -> float:
    return value if np.isfinite(value) else float("inf")


def _line_search(
    nll: Callable[[FloatArray], tuple[float, FloatArray]],
    theta: FloatArray,
    step: FloatArray,
    value: float,
    decrement: float,
    layout: CovarianceLayout,
    rounding: float,
    floor: FloatArray,
) -> tuple[FloatArray, float, FloatArray] | None:
    """Armijo search along the step: the first of t = 1, ½, ¼, … whose NLL falls by at least
    1e-4·t·(predicted decrease) and by more than ``rounding`` (the NLL's: a smaller
    "decrease" is noise); None once the predicted decrease t·(decrement) is below ``rounding``
    itself. A full step that is accepted is
    extended along the projected path Π(θ + t·step), t = 2, 4, …, while the NLL keeps falling
    by that much: where the metric overrates the curvature (a variance drifting towards its
    bound with steps of equal size), the path reaches the bound in a few doublings
    (Bertsekas' projected search)."""
    t = 1.0
    while True:
        if t * decrement <= rounding:
            return None
        candidate = theta + t * step
        candidate_value, candidate_psi = nll(candidate)
        if candidate_value <= value - max(1e-4 * t * decrement, rounding):
            break
        t *= 0.5
    while t >= 1.0 and t < MAX_EXTENSION:
        longer = _projected(theta + 2.0 * t * step - floor, layout) + floor
        longer_value, longer_psi = nll(longer)
        if not longer_value <= candidate_value - max(1e-4 * t * decrement, rounding):
            break
        candidate, candidate_value, candidate_psi = longer, longer_value, longer_psi
        t *= 2.0
    return candidate, candidate_value, candidate_psi


MAX_EXTENSION = 2.0**20


def _slope_search(
    nll: Callable[[FloatArray], tuple[float, FloatArray]],
    theta: FloatArray,
    step: FloatArray,
    decrement: float,
    layout: CovarianceLayout,
) -> tuple[FloatArray, float, FloatArray] | None:
    """A step whose decrease is below the NLL's rounding, sized by the slope of the NLL along
    it (−``decrement`` at θ): the full step while the slope there is still ≤ 0, else the
    secant root ``t = decrement / (decrement + slope(1))`` of the slope; None if that slope is
    not negative either (the step is not a descent direction at this precision)."""
    value, psi = nll(theta + step)
    slope = float(theta_gradient(layout, psi) @ step)
    if slope <= 0.0:
        return theta + step, value, psi
    t = decrement / (decrement + slope)
    value, psi = nll(theta + t * step)
    if not float(theta_gradient(layout, psi) @ step) < decrement:
        return None
    return theta + t * step, value, psi


def _projected(theta: FloatArray, layout: CovarianceLayout) -> FloatArray:
    """θ onto the cone: every Σ_f ⪰ 0 (diagonal: θ ≥ 0)."""
    if layout.structure == "diag":
        return np.maximum(theta, 0.0)
    return layout.theta_from_covariances(clip_psd(layout.frame_covariances(theta)))


def _metric(
    theta: FloatArray,
    metric: ArraySamples,
    layout: CovarianceLayout,
    transform: FloatArray | None,
    known_covariance: FloatArray | None,
    one_step: bool,
) -> FloatArray:
    """The scoring metric H on the ``metric`` samples (unscaled): the average information
    (:func:`~solver.covariance.likelihood.average_information`, exact in expectation and
    data-aware, so iterations end in tens of steps where the expected information crawls
    towards boundary optima: TIAGo's 21-pose REML hit 200 steps, it now takes 18); for the
    one-step estimator the expected information 2·I(θ) of Eq. (16), which the classical
    one-step estimator is defined with."""
    if one_step:
        return 2.0 * fisher_information_ml(
            theta, metric.frame_jacobians, layout, known_covariance=known_covariance
        )
    return average_information(
        theta,
        metric,
        layout,
        transform=transform,
        known_covariance=known_covariance,
    )


def _positive_start(
    theta: FloatArray,
    nll,
    layout: CovarianceLayout,
    scaling: ProblemScaling,
) -> tuple[FloatArray, tuple[float, FloatArray]]:
    """The start, with small variances ε·D_p added until every Σ_E is positive definite."""
    value = nll(theta)
    if np.isfinite(value[0]):
        return theta, value
    lift = np.where(layout.is_variance, scaling.param_scale, 0.0)
    for eps in (1e-8, 1e-6, 1e-4, 1e-2):
        value = nll(theta + eps * lift)
        if np.isfinite(value[0]):
            return theta + eps * lift, value
    raise CalibrationError(
        "Σ_E(q) is singular for every start of the likelihood fit: estimate the noise or pass "
        "a known noise covariance, or free more axes"
    )


def _scoring_message(
    iterations: int,
    one_step: bool,
    restriction_samples: ArraySamples | None,
    refine: bool,
    newton_steps: int = 0,
) -> str:
    text = f"projected Fisher scoring, {iterations} steps"
    if newton_steps:
        text += f" ({newton_steps} of them projected Newton steps)"
    if refine:
        text = "one projected scoring step with the average-information metric"
    elif one_step:
        text = (
            "one projected Fisher-scoring step from the moment solution (one-step estimator; "
            "objective at the moment solution)"
        )
    if restriction_samples is not None:
        text += f"; REML restriction terms on {restriction_samples.n_samples} samples"
    return text
