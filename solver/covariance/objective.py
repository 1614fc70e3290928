"""The one moment-matching objective all solvers share, paper Eq. (14), and its scaling.

``f(θ) = ‖z − Bθ‖₂² = θᵀGθ − 2hᵀθ + c`` from :class:`MomentStatistics`. Solvers work on the
equilibrated problem ``θ = D θ̂`` (:class:`ProblemScaling`) and always report f of the unscaled
θ, so their answers compare exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import BoolArray, FloatArray
from solver.covariance.layout import CovarianceLayout
from solver.covariance.statistics import MomentStatistics

# Eigenvalues of the equilibrated Gram below this fraction of the largest are dropped from its
# factor: they are rounding noise (G is exact, so true null directions sit at ~1e-16).
FACTOR_EIGEN_RTOL = 1e-13
# A θ entry whose column of B has norm below 1e-12 of the largest has no effect at all (e.g. a
# rotation about an axis through the end-effector origin with position-only residuals).
SILENT_GRAM_RTOL = 1e-24


def moment_objective(theta: FloatArray, stats: MomentStatistics) -> float:
    """Eq. (14) squared: ``Σ_n ‖vec(r_n r_nᵀ) − B_n θ‖²`` (units of θ², e.g. rad⁴)."""
    return float(stats.const - 2.0 * stats.cross @ theta + theta @ stats.gram @ theta)


def moment_residual_norm(theta: FloatArray, stats: MomentStatistics) -> float:
    """``‖z − Bθ‖₂`` of Eq. (14) and Table I's stopping test, from the statistics alone."""
    return float(np.sqrt(max(moment_objective(theta, stats), 0.0)))


def moment_gradient(theta: FloatArray, stats: MomentStatistics) -> FloatArray:
    """``Bᵀ(Bθ − z) = Gθ − h`` (half the gradient of f), the step direction of Eq. (15)."""
    return stats.gram @ theta - stats.cross


@dataclass(frozen=True)
class ProblemScaling:
    """Congruence scaling ``Σ_f = Δ_f Σ̂_f Δ_f`` (keeps PSD), i.e. ``θ_p = D_p θ̂_p``.

    ``axis_scale`` (F, 6) is Δ; ``param_scale`` (Q,) is D_p = δ_{f,i} δ_{f,j}. The scaled
    problem ``min θ̂ᵀĜθ̂ − 2ĥᵀθ̂ + ĉ`` has Ĝ = DGD/κ (unit diagonal on variances), ĥ = Dh/κ with
    max|ĥ| = 1, ĉ = c/κ, and f(θ) = κ·f̂(θ̂).
    """

    axis_scale: FloatArray
    param_scale: FloatArray
    objective_scale: float

    def to_scaled(self, theta: FloatArray) -> FloatArray:
        return theta / self.param_scale

    def from_scaled(self, theta_scaled: FloatArray) -> FloatArray:
        return theta_scaled * self.param_scale


def silent_entries(stats: MomentStatistics) -> BoolArray:
    """θ entries without any effect on the residuals: ‖column of B‖² ≤ SILENT_GRAM_RTOL·max."""
    diag = np.diag(stats.gram)
    return diag <= SILENT_GRAM_RTOL * max(float(diag.max(initial=0.0)), 1e-300)


def problem_scaling(stats: MomentStatistics) -> ProblemScaling:
    """Equilibrate columns of B (variances to unit norm), then scale θ̂ to O(1).

    Silent entries (no effect) get the median scale of the others.
    """
    layout = stats.layout
    loud = ~silent_entries(stats)[layout.is_variance]
    diag_gram = np.diag(stats.gram)[layout.is_variance]
    fallback = float(np.median(diag_gram[loud])) if np.any(loud) else 1.0
    per_axis = np.full((layout.n_frames, 6), fallback)
    f, i = layout.param_frame[layout.is_variance], layout.param_row[layout.is_variance]
    per_axis[f, i] = np.where(loud, diag_gram, fallback)
    unit = per_axis**-0.25  # δ for unit-norm variance columns
    d_unit = unit[layout.param_frame, layout.param_row] * unit[layout.param_frame, layout.param_col]
    tau = float(np.max(np.abs(d_unit * stats.cross), initial=0.0))
    if not np.isfinite(tau) or tau <= 0.0:
        tau = 1.0
    axis_scale = unit * np.sqrt(tau)
    param_scale = d_unit * tau
    return ProblemScaling(axis_scale, param_scale, tau**2)


@dataclass(frozen=True)
class ScaledProblem:
    """Ĝ, ĥ, ĉ of :class:`ProblemScaling` and the factor ``Ĝ ≈ RᵀR``, ``Rᵀb = ĥ``.

    ``‖Rθ̂ − b‖² + offset = θ̂ᵀĜθ̂ − 2ĥᵀθ̂ + ĉ`` up to the dropped rounding-level eigenvalues.
    """

    layout: CovarianceLayout
    scaling: ProblemScaling
    gram: FloatArray
    cross: FloatArray
    const: float
    factor: FloatArray  # R (r, Q)
    target: FloatArray  # b (r,)
    offset: float  # ĉ − ‖b‖²
    lipschitz: float  # λmax(Ĝ)


def scaled_problem(stats: MomentStatistics) -> ScaledProblem:
    """Equilibrated Eq. (14) with an eigen-factor of its (rank-deficient) Gram."""
    scaling = problem_scaling(stats)
    d = scaling.param_scale
    kappa = scaling.objective_scale
    gram = (d[:, None] * stats.gram * d[None, :]) / kappa
    gram = 0.5 * (gram + gram.T)
    cross = d * stats.cross / kappa
    const = stats.const / kappa
    eigval, eigvec = np.linalg.eigh(gram)
    lam_max = float(max(eigval[-1], 0.0))
    keep = eigval > FACTOR_EIGEN_RTOL * lam_max if lam_max > 0 else np.zeros_like(eigval, bool)
    root = np.sqrt(eigval[keep])
    factor = root[:, None] * eigvec[:, keep].T
    target = (eigvec[:, keep].T @ cross) / root
    offset = const - float(target @ target)
    return ScaledProblem(stats.layout, scaling, gram, cross, const, factor, target, offset, lam_max)


def projected_gradient_residual(theta: FloatArray, problem: ScaledProblem) -> float:
    """KKT measure ``‖ŷ − Π(ŷ − ∇f̂/L)‖ / max(‖ŷ‖, ‖ĥ‖/L)`` (0 exactly at the optimum).

    ŷ = m∘θ̂ are Frobenius coordinates of the equilibrated θ̂, Π the projection onto the PSD
    cones (:func:`project_psd`), L = λmax(Ĝ); ‖ĥ‖/L is the size of one step from θ̂ = 0, so the
    measure stays meaningful when θ̂ ≈ 0. A scale-free optimality check shared by all solvers.
    """
    layout = problem.layout
    x = problem.scaling.to_scaled(theta)
    metric = layout.frobenius_weights()
    y = metric * x
    grad_y = (problem.gram @ x - problem.cross) / metric
    lip = problem.lipschitz / float(np.min(metric) ** 2) if problem.lipschitz > 0 else 1.0
    step = y - project_psd(y - grad_y / lip, layout)
    size = max(float(np.linalg.norm(y)), float(np.linalg.norm(problem.cross / metric)) / lip)
    return float(np.linalg.norm(step) / max(size, 1e-300))


def project_psd(y: FloatArray, layout: CovarianceLayout) -> FloatArray:
    """Euclidean projection of y = m∘θ (Frobenius coordinates) onto every Σ_f ⪰ 0.

    Diagonal structure: clip at 0. Full: negative eigenvalues of each Σ_f set to 0 (the paper's
    Proj of Eq. 15, [20]).
    """
    if layout.structure == "diag":
        return np.maximum(y, 0.0)
    metric = layout.frobenius_weights()
    covs = layout.frame_covariances(y / metric)
    return metric * layout.theta_from_covariances(clip_psd(covs))


def clip_psd(matrices: FloatArray) -> FloatArray:
    """Symmetrise (..., n, n) and set negative eigenvalues to 0."""
    sym = 0.5 * (matrices + np.swapaxes(matrices, -1, -2))
    eigval, eigvec = np.linalg.eigh(sym)
    out = (eigvec * np.clip(eigval, 0.0, None)[..., None, :]) @ np.swapaxes(eigvec, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))
