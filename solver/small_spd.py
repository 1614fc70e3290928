"""Many small symmetric positive definite matrices at once: Σ_E(q_n) of Eq. (12) for every
sample of a recording (d = 6 for poses, 3 for positions).

``numpy.linalg`` factors a stack of matrices one LAPACK call per matrix; for 6×6 matrices the
per-call overhead dominates (≈ 3 µs per matrix for ``eigh``, ≈ 2.5 µs for ``cholesky`` +
``inv``), which made the model outlier rule's Mahalanobis distances and the likelihood's
Σ_E⁻¹ the costliest part of a pass over 10⁶ poses. Here the Cholesky–Banachiewicz recurrences
run entry by entry over the whole stack instead (≈ d³/3 vector operations of length N), the
same arithmetic as LAPACK's unblocked ``potrf``, so the results agree to rounding.

Layout: the stack axis is last inside the recurrences (``(d, d, N)``), so every operation is
one contiguous vector; inputs and outputs are ``(N, d, d)`` like ``numpy.linalg``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import BoolArray, FloatArray


@dataclass(frozen=True)
class SpdFactors:
    """Cholesky factors of a stack of symmetric matrices ``Σ_n = L_n L_nᵀ``: ``inverse_factor``
    ``L_n⁻¹`` (d, d, N) (lower triangular), ``log_det`` ``log det Σ_n`` (N,) and
    ``positive_definite`` (N,); rows of a matrix that is not positive definite are NaN."""

    inverse_factor: FloatArray
    log_det: FloatArray
    positive_definite: BoolArray

    def whiten(self, residuals: FloatArray) -> FloatArray:
        """``L_n⁻¹ r_n`` (N, d) for residuals (N, d): ``‖L_n⁻¹ r_n‖² = r_nᵀ Σ_n⁻¹ r_n``."""
        m = self.inverse_factor
        d = m.shape[0]
        r = np.ascontiguousarray(residuals.T)
        out = np.zeros_like(r)
        for i in range(d):
            for j in range(i + 1):
                out[i] += m[i, j] * r[j]
        return out.T

    def inverse(self) -> FloatArray:
        """``Σ_n⁻¹ = L_n⁻ᵀ L_n⁻¹`` (N, d, d), exactly symmetric."""
        m = self.inverse_factor
        d = m.shape[0]
        out = np.zeros_like(m)
        for i in range(d):
            for j in range(i + 1):
                entry = out[i, j]
                for k in range(i, d):  # L⁻¹ is lower triangular: k ≥ max(i, j) = i
                    entry += m[k, i] * m[k, j]
                out[j, i] = entry
        return np.ascontiguousarray(out.transpose(2, 0, 1))

    def condition_bound(self, covariances: FloatArray) -> FloatArray:
        """An upper bound (N,) on each Σ_n's condition number: ``λ_max ≤ tr Σ_n`` and
        ``1/λ_min = ‖L_n⁻¹‖₂² ≤ ‖L_n⁻¹‖_F²``."""
        frobenius2 = np.einsum("ijn,ijn->n", self.inverse_factor, self.inverse_factor)
        return frobenius2 * np.trace(covariances, axis1=1, axis2=2)


def spd_factors(covariances: FloatArray) -> SpdFactors:
    """Cholesky factor ``L_n`` of each symmetric ``Σ_n`` (N, d, d) (its lower triangle is
    read), then ``L_n⁻¹`` by forward substitution and ``log det Σ_n = 2 Σ_j log L_jj``. A pivot
    that is not positive (or NaN) marks Σ_n not positive definite, as LAPACK's ``potrf`` does."""
    a = np.ascontiguousarray(np.asarray(covariances, dtype=float).transpose(1, 2, 0))
    d, n = a.shape[0], a.shape[2]
    lower = np.zeros_like(a)
    positive = np.ones(n, dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(d):
            pivot = a[j, j].copy()
            for k in range(j):
                pivot -= lower[j, k] * lower[j, k]
            positive &= pivot > 0.0
            pivot[~(pivot > 0.0)] = np.nan
            diagonal = lower[j, j]
            np.sqrt(pivot, out=diagonal)
            for i in range(j + 1, d):
                entry = a[i, j].copy()
                for k in range(j):
                    entry -= lower[i, k] * lower[j, k]
                np.divide(entry, diagonal, out=lower[i, j])
        inverse = np.zeros_like(a)
        for j in range(d):
            np.divide(1.0, lower[j, j], out=inverse[j, j])
            for i in range(j + 1, d):
                entry = lower[i, j] * inverse[j, j]
                for k in range(j + 1, i):
                    entry += lower[i, k] * inverse[k, j]
                np.divide(entry, lower[i, i], out=inverse[i, j])
                np.negative(inverse[i, j], out=inverse[i, j])
        log_det = 2.0 * np.log(np.einsum("jjn->jn", lower)).sum(axis=0)
    return SpdFactors(inverse, log_det, positive)
