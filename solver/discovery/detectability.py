"""Smallest detectable size of every library term on one recording (issue 14).

For a candidate with whitened columns ``C`` (R, m), the part the fitted model cannot absorb is
``C̃ = (I − QQᵀ) C`` (:mod:`solver.discovery.scoring`). An effect of coefficients θ adds
``C̃ θ`` to the whitened residual; its one-step estimate has covariance ``V``, the larger (per
coefficient) of the classical ``s² (C̃ᵀC̃)⁻¹`` (s² = RSS/ν, the residual scale) and the
per-sample cluster-robust sandwich — the score test rejects only when both of its statistics
do, so the weaker one decides. The test statistic is then noncentral F(m, ν', λ) with
``λ = θᵀ V⁻¹ θ`` and ν' the smaller reference dof (ν, or N − m for the robust statistic). The
smallest detectable size is the smallest ``|θ|`` (worst direction: any phase of a gear error,
any axis of a flex) that the test rejects at ``level`` with probability ``power``::

    size = sqrt(λ* · largest eigenvalue of V),   P(F(m, ν', λ*) > F_crit(level)) = power.

The level is the first step's Holm threshold, α over the number of candidates tested, so
"nothing found" reads "nothing larger than this". A measurement-frame drift mixes metres and
radians: its translation and rotation parts get one size each (its test keeps 6 dof).
The robust statistic is bounded by the number of samples; where the bound lies below the
critical value no size is detectable (:func:`robust_can_reject`) and the size is infinite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.stats
from numpy.typing import NDArray

from solver.discovery.fitting import Context, ModelFit, evaluate, whitened
from solver.discovery.library import Term
from solver.discovery.scoring import NullModel, sandwich_covariance

FloatArray = NDArray[np.float64]

DETECTION_POWER = 0.8


@dataclass(frozen=True)
class DetectableSize:
    """The smallest ``parameter`` of ``term`` this recording detects (see module docstring);
    ``smallest`` in the parameter's unit (inf: the model absorbs the term entirely)."""

    term: Term
    parameter: str
    smallest: float


def noncentrality_needed(m: int, dof: int, level: float, power: float) -> float:
    """λ* with P(F(m, dof, λ*) > F_{1−level}(m, dof)) = power."""
    critical = float(scipy.stats.f.isf(level, m, dof))

    def shortfall(lam: float) -> float:
        return float(scipy.stats.ncf.sf(critical, m, dof, lam)) - power

    high = 1.0
    while shortfall(high) < 0.0:
        high *= 2.0
    return float(scipy.optimize.brentq(shortfall, 0.0, high, xtol=1e-8))


def size_groups(term: Term) -> list[tuple[str, list[int]]]:
    """(reported size, coefficient indices whose Euclidean norm it is) of a term."""
    if term.effect == "gear_periodic":
        return [("amplitude_rad", [0, 1])]
    if term.effect in ("base_flex", "link_bending"):
        return [("flex_rad_per_nm", [0, 1])]
    if term.effect == "gravity_direction":
        return [("tilt_rad", [0, 1])]
    if term.effect == "thermal_drift" and term.joint_index is None:
        names = term.parameters
        return [
            (names[0].replace("tx_", "translation_"), [0, 1, 2]),
            (names[3].replace("rx_", "rotation_"), [3, 4, 5]),
        ]
    return [(term.parameters[0], [0])]


def smallest_detectable(
    ctx: Context,
    fit: ModelFit,
    library: list[Term],
    level: float,
    power: float = DETECTION_POWER,
) -> list[DetectableSize]:
    """Smallest detectable size of each term of ``library`` (not in ``fit``'s model) on the
    recording, for a score test at ``level`` with ``power`` (module docstring)."""
    if not library:
        return []
    design = evaluate(ctx, fit.terms, fit.params, fit.rows, candidates=tuple(library))
    null = NullModel.from_fit(fit)
    scale2 = float(null.residual @ null.residual) / max(null.dof, 1)
    out = []
    for term in library:
        columns = whitened(design.candidates[term.key], fit.weights).reshape(-1, term.size)
        dof = min(null.dof, null.n_samples) - term.size
        if dof <= 0:
            continue
        if not robust_can_reject(term.size, null.n_samples, level):
            out += [DetectableSize(term, name, np.inf) for name, _ in size_groups(term)]
            continue
        covariance = estimate_covariance(null, columns, scale2)
        needed = noncentrality_needed(term.size, dof, level, power)
        for parameter, indices in size_groups(term):
            block = covariance[np.ix_(indices, indices)]
            largest = float(np.linalg.eigvalsh(block)[-1]) if np.all(np.isfinite(block)) else np.inf
            out.append(DetectableSize(term, parameter, float(np.sqrt(needed * largest))))
    return out


def robust_can_reject(m: int, n_samples: int, level: float) -> bool:
    """Can the cluster-robust score statistic reach ``level`` at all?

    ``T = sᵀ(Σ u_n u_nᵀ)⁻¹ s`` with ``s = Σ u_n`` never exceeds the number of samples N
    (Cauchy–Schwarz), and it is referred to F(m, N − m) after dividing by m: when
    ``m · F_{1−level}(m, N − m) ≥ N`` no effect of any size is found (e.g. 23 samples against
    some 80 candidates at α = 0.01). The size is then infinite.
    """
    if n_samples - m <= 0:
        return False
    return bool(m * scipy.stats.f.isf(level, m, n_samples - m) < n_samples)


def estimate_covariance(null: NullModel, columns: FloatArray, scale2: float) -> FloatArray:
    """Covariance (m, m) of a candidate's one-step estimate: classical, each coefficient's
    variance raised to the sandwich's where that is larger (as the fit's standard errors);
    infinite where the model absorbs a direction of the candidate."""
    projected = null.project(columns)
    gram = projected.T @ projected
    if np.linalg.matrix_rank(gram, tol=1e-12 * max(float(np.trace(gram)), 1e-300)) < gram.shape[0]:
        return np.full(gram.shape, np.inf)
    pinv = np.linalg.solve(gram, projected.T)
    classical = scale2 * np.linalg.inv(gram)
    robust = sandwich_covariance(null, np.asarray(pinv, dtype=np.float64), null.residual)
    ratio = np.diag(robust) / np.diag(classical)
    raise_by = np.sqrt(np.maximum(ratio, 1.0))
    return np.asarray(classical * np.outer(raise_by, raise_by), dtype=np.float64)
