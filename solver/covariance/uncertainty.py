"""Standard errors and confidence intervals of the calibrated standard deviations.

Covariance of θ̂: inverse expected Fisher information for ML/REML, the sandwich
``G⁺ M G⁺`` (M from :func:`moment_sandwich_meat`) for moment matching; both restricted to the
identifiable subspace (pseudo-inverse in equilibrated units, null directions removed). Entries
that move along a null direction get NaN and ``identifiable = False``.

σ = sqrt(θ) by the delta method, ``se(σ) = se(θ) / (2σ)``. A two-sided interval on θ that
crosses 0 means the entry is at the boundary: then σ gets the one-sided interval
``[0, sqrt(θ + z_{1−α} se)]`` and ``at_boundary = True``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from solver.arrays import BoolArray, FloatArray
from solver.covariance.identifiability import IdentifiabilityReport


@dataclass(frozen=True)
class ThetaUncertainty:
    """Per θ entry (Q,): standard error, σ = sqrt(θ) (variances only) and its interval."""

    theta_se: FloatArray
    std: FloatArray
    std_se: FloatArray
    std_ci_low: FloatArray
    std_ci_high: FloatArray
    at_boundary: BoolArray
    identifiable: BoolArray
    confidence: float
    method: str


def theta_covariance(
    information: FloatArray, report: IdentifiabilityReport, *, bread: FloatArray | None = None
) -> FloatArray:
    """Cov(θ̂) (Q, Q): ``I⁺`` or, with ``bread`` = G, the sandwich ``G⁺ I G⁺``.

    Pseudo-inverses are taken in equilibrated units on the range of Ĝ (complement of
    ``report.null_basis``).
    """
    d = report.scaling.param_scale
    null = report.null_basis
    q = d.size
    projector = np.eye(q) - null @ null.T
    eigval, eigvec = np.linalg.eigh(projector)
    rng = eigvec[:, eigval > 0.5]  # orthonormal basis of the identifiable subspace

    def restricted_inverse(m: FloatArray) -> FloatArray:
        small = rng.T @ (d[:, None] * m * d[None, :]) @ rng
        return rng @ np.linalg.pinv(0.5 * (small + small.T), rcond=1e-13, hermitian=True) @ rng.T

    if bread is None:
        cov_scaled = restricted_inverse(information)
    else:
        inv_bread = restricted_inverse(bread)
        cov_scaled = inv_bread @ (d[:, None] * information * d[None, :]) @ inv_bread
    return d[:, None] * cov_scaled * d[None, :]


def theta_uncertainty(
    theta: FloatArray,
    covariance: FloatArray,
    report: IdentifiabilityReport,
    is_variance: BoolArray,
    *,
    confidence: float = 0.95,
    method: str,
) -> ThetaUncertainty:
    """Standard errors of θ and intervals of σ = sqrt(θ) for the variance entries."""
    se = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    identifiable = report.identifiable.copy()
    se = np.where(identifiable, se, np.nan)
    z_two = float(ndtri(0.5 + 0.5 * confidence))
    z_one = float(ndtri(confidence))
    var = np.where(is_variance, np.clip(theta, 0.0, None), np.nan)
    std = np.sqrt(var)
    boundary = is_variance & identifiable & (var - z_two * se <= 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        std_se = np.where(boundary, np.nan, se / (2.0 * std))
        low = np.where(boundary, 0.0, np.sqrt(np.clip(var - z_two * se, 0.0, None)))
        high = np.where(boundary, np.sqrt(var + z_one * se), np.sqrt(var + z_two * se))
    unknown = ~identifiable | ~is_variance
    return ThetaUncertainty(
        se,
        std,
        np.where(unknown, np.nan, std_se),
        np.where(unknown, np.nan, low),
        np.where(unknown, np.nan, high),
        boundary,
        identifiable,
        confidence,
        method,
    )
