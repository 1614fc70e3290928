"""Score (Lagrange-multiplier) tests of candidate columns against the fitted model.

At the fitted model, with whitened residual ``r`` (R rows) and an orthonormal basis ``Q`` of the
whitened model Jacobian, a candidate with whitened columns ``C`` (R, m) is tested on its part
the model cannot absorb, ``C̃ = (I − QQᵀ) C`` — no refit per candidate. Two statistics:

* classical: ``F = (ΔSS/m) / ((RSS − ΔSS)/(ν − m))`` with ``ΔSS = |P_C̃ r|²``, ν = R − rank(Q),
  exact for Gaussian white noise;
* cluster-robust: per-sample scores ``u_n = C̃_nᵀ r_n`` (leverage-adjusted residuals),
  ``T = sᵀ (Σ u_n u_nᵀ)⁻¹ s`` with ``s = Σ u_n``, referred to F(m, N − m) after dividing by m;
  valid when the noise is correlated within a sample or changes with the configuration
  (random joint perturbations, paper Eq. 12).

The reported p-value is the larger of the two: a candidate must pass both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.special
from numpy.typing import NDArray

from solver.discovery.fitting import ModelFit, orthonormal_basis

FloatArray = NDArray[np.float64]

# A candidate direction whose unexplained part is below this fraction of its norm is one the
# model already contains (e.g. isotropic scale vs link lengths): not testable.
TESTABLE_FRACTION = 1e-3


@dataclass(frozen=True, eq=False)
class NullModel:
    """Linearisation of a fit: whitened residual (R,), model basis (R, r), rows per sample d."""

    residual: FloatArray
    basis: FloatArray
    d: int

    @classmethod
    def from_fit(cls, fit: ModelFit) -> NullModel:
        return cls(fit.residual_w, orthonormal_basis(fit.jacobian), fit.design.residual.shape[1])

    @property
    def n_samples(self) -> int:
        return self.residual.size // self.d

    @property
    def dof(self) -> int:
        return self.residual.size - self.basis.shape[1]

    def project(self, columns: FloatArray) -> FloatArray:
        """Part of ``columns`` (R, m) orthogonal to the model Jacobian."""
        return columns - self.basis @ (self.basis.T @ columns)

    def sample_leverage(self) -> FloatArray:
        return np.sum(self.basis**2, axis=1).reshape(-1, self.d).mean(axis=1)


@dataclass(frozen=True)
class ScoreTest:
    """Result of testing one candidate (see module docstring).

    ``estimate`` is the one-step (linearised) coefficient estimate, ``stderr`` its standard
    error; ``absorbed_fraction`` the share of the estimated effect's signature (whitened) that
    the current model's parameters could reproduce.
    """

    key: str
    m: int
    delta_ss: float
    f_statistic: float
    p_classical: float
    robust_statistic: float
    p_robust: float
    log_p: float
    estimate: FloatArray
    stderr: FloatArray
    absorbed_fraction: float

    @property
    def p_value(self) -> float:
        return max(self.p_classical, self.p_robust)


def score_test(null: NullModel, key: str, columns: FloatArray) -> ScoreTest | None:
    """Test whitened candidate ``columns`` (R, m); None when the model absorbs them entirely."""
    norms = np.linalg.norm(columns, axis=0)
    if not np.all(norms > 0):
        return None
    unit = columns / norms
    projected = null.project(unit)
    u, s, vt = np.linalg.svd(projected, full_matrices=False)
    testable = s > TESTABLE_FRACTION
    if not np.any(testable):
        return None
    # Pseudo-inverse of the projected columns in the candidate's own units (testable part).
    pinv = (vt[testable].T / s[testable]) @ u[:, testable].T / norms[:, None]
    u = u[:, testable]
    m = int(u.shape[1])
    r = null.residual
    coordinates = u.T @ r
    delta_ss = float(coordinates @ coordinates)
    rss = float(r @ r)
    dof_rest = null.dof - m
    if dof_rest <= 0:
        return None
    denominator = max(rss - delta_ss, 1e-300) / dof_rest
    f_stat = delta_ss / m / denominator
    p_classical = float(scipy.special.fdtrc(m, dof_rest, f_stat))
    log_p = log_f_sf(f_stat, m, dof_rest)
    robust, p_robust = _robust(null, u, r, m)
    estimate = pinv @ r  # one-step estimate: least squares of r on the projected columns
    covariance = denominator * pinv @ pinv.T
    sandwich = sandwich_covariance(null, pinv, r)
    variance = np.maximum(np.diag(covariance), np.diag(sandwich))
    effect = columns @ estimate
    absorbed = 1.0 - float(np.sum(null.project(effect[:, None]) ** 2)) / max(
        float(effect @ effect), 1e-300
    )
    return ScoreTest(
        key=key,
        m=m,
        delta_ss=delta_ss,
        f_statistic=float(f_stat),
        p_classical=p_classical,
        robust_statistic=robust,
        p_robust=p_robust,
        log_p=log_p,
        estimate=estimate,
        stderr=np.sqrt(variance),
        absorbed_fraction=float(np.clip(absorbed, 0.0, 1.0)),
    )


def _robust(null: NullModel, u: FloatArray, r: FloatArray, m: int) -> tuple[float, float]:
    """Cluster-robust score statistic (per sample) and its p-value."""
    d = null.d
    n = null.n_samples
    adjusted = r.reshape(n, d) / np.sqrt(np.clip(1.0 - null.sample_leverage(), 0.05, None))[:, None]
    scores = np.einsum("nrm,nr->nm", u.reshape(n, d, m), adjusted)
    total = u.T @ r
    meat = scores.T @ scores
    statistic = float(total @ np.linalg.lstsq(meat, total, rcond=None)[0])
    if n - m <= 0:
        return statistic, 1.0
    return statistic, float(scipy.special.fdtrc(m, n - m, statistic / m))


def sandwich_covariance(null: NullModel, pinv: FloatArray, r: FloatArray) -> FloatArray:
    """Per-sample cluster-robust covariance (m, m) of the estimate ``pinv @ r`` (``pinv``
    (m, R)), residuals scaled up by their sample's leverage."""
    d, n = null.d, null.n_samples
    adjusted = r.reshape(n, d) / np.sqrt(np.clip(1.0 - null.sample_leverage(), 0.05, None))[:, None]
    per_sample = np.einsum("mnr,nr->nm", pinv.reshape(pinv.shape[0], n, d), adjusted)
    return per_sample.T @ per_sample


def holm(p_values: Mapping[str, float], alpha: float) -> set[str]:
    """Keys rejected by Holm's step-down procedure at family-wise level ``alpha``."""
    ordered = sorted(p_values.items(), key=lambda kv: kv[1])
    total = len(ordered)
    rejected: set[str] = set()
    for rank, (key, p) in enumerate(ordered):
        if p > alpha / (total - rank):
            break
        rejected.add(key)
    return rejected


def unexplained_basis(null: NullModel, columns: FloatArray) -> FloatArray:
    """Orthonormal basis of the part of ``columns`` the model cannot absorb.

    Columns are scaled to unit norm before projection; directions whose remaining part is
    below :data:`TESTABLE_FRACTION` are the model's own and are dropped.
    """
    norms = np.linalg.norm(columns, axis=0)
    unit = columns[:, norms > 0] / norms[norms > 0]
    if unit.shape[1] == 0:
        return np.zeros((columns.shape[0], 0))
    projected = null.project(unit)
    # Eigen-decomposition of the small Gram matrix: same basis as an SVD, far cheaper for
    # tall matrices (the bootstrap calls this thousands of times).
    values, vectors = np.linalg.eigh(projected.T @ projected)
    keep = values > TESTABLE_FRACTION**2
    return projected @ (vectors[:, keep] / np.sqrt(values[keep]))


def canonical_correlation(null: NullModel, first: FloatArray, second: FloatArray) -> float:
    """Largest canonical correlation of two candidates' parts the model does not absorb."""
    a = unexplained_basis(null, first)
    b = unexplained_basis(null, second)
    if a.shape[1] == 0 or b.shape[1] == 0:
        return 0.0  # one of them is entirely the model's already: nothing left to share
    return float(np.clip(np.linalg.svd(a.T @ b, compute_uv=False)[0], 0.0, 1.0))


def bootstrap_winners(
    jacobian: FloatArray,
    residual: FloatArray,
    d: int,
    candidates: Mapping[str, FloatArray],
    n_boot: int,
    rng: np.random.Generator,
) -> dict[str, float]:
    """How often each candidate is the best one when samples are resampled (linearised).

    Each replicate draws N samples with replacement, refits the linearised model (projection
    off its Jacobian rows) and ranks the candidates by their classical score-test p-value.
    """
    n = residual.size // d
    wins = dict.fromkeys(candidates, 0)
    if n_boot <= 0 or not candidates:
        return {k: 0.0 for k in candidates}
    a3 = jacobian.reshape(n, d, -1)
    r2 = residual.reshape(n, d)
    c3 = {k: v.reshape(n, d, -1) for k, v in candidates.items()}
    for _ in range(n_boot):
        picks = rng.integers(0, n, size=n)
        null = NullModel(r2[picks].reshape(-1), orthonormal_basis(a3[picks].reshape(n * d, -1)), d)
        null = NullModel(null.project(null.residual[:, None])[:, 0], null.basis, d)
        best, best_log_p = None, np.inf
        for key, cols in c3.items():
            test = _quick_log_p(null, cols[picks].reshape(n * d, -1))
            if test is not None and test < best_log_p:
                best, best_log_p = key, test
        if best is not None:
            wins[best] += 1
    return {k: v / n_boot for k, v in wins.items()}


def _quick_log_p(null: NullModel, columns: FloatArray) -> float | None:
    basis = unexplained_basis(null, columns)
    m = basis.shape[1]
    if m == 0 or null.dof - m <= 0:
        return None
    coordinates = basis.T @ null.residual
    delta = float(coordinates @ coordinates)
    rss = float(null.residual @ null.residual)
    f_stat = delta / m / (max(rss - delta, 1e-300) / (null.dof - m))
    return log_f_sf(f_stat, m, null.dof - m)


def log_f_sf(f_stat: float, m: int, dof: int) -> float:
    """log P(F(m, dof) > f_stat), finite even where scipy's logsf underflows to −inf.

    sf = I_x(dof/2, m/2) with x = dof/(dof + m F); for tiny x the series' first term,
    x^a (1−x)^b / (a B(a, b)), is accurate to a relative O(x).
    """
    tail = float(scipy.special.fdtrc(m, dof, f_stat))
    if tail > 1e-300:
        return math.log(tail)
    a, b = 0.5 * dof, 0.5 * m
    x = dof / (dof + m * f_stat)
    return float(a * np.log(x) + b * np.log1p(-x) - np.log(a) - scipy.special.betaln(a, b))
