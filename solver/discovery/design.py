"""Poses that would separate terms the data cannot tell apart (greedy D-optimal design).

Given the fitted model and one or two candidate terms, choose configurations (within the joint
limits) whose measurements would most increase the information on those terms' coefficients
with the geometry (and the model's other terms) as nuisance: the determinant of the Schur
complement of the Fisher information, grown one pose at a time (Woodbury update per pool pose).
Terms driven by time or approach direction cannot be separated by a choice of pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.discovery.fitting import Context, ModelFit, evaluate, orthonormal_basis, whitened
from solver.discovery.library import Term
from solver.discovery.scoring import NullModel, canonical_correlation
from solver.model import sample_configurations


@dataclass(frozen=True)
class SeparatingPoses:
    """``configurations`` (n, k) rad, and how far apart the explanations would be.

    ``separation_*_sigma``: how many noise standard deviations separate the explanations'
    predictions over the recording (now) and with the poses added (after) — for two terms the
    smaller of "first as estimated, against the best fit of the second plus geometry" and the
    reverse; for one term, against the geometry alone. ``correlation_*``: canonical
    correlation of the two terms (or of the term with the geometry) once the geometry is fitted.
    """

    configurations: FloatArray
    separation_now_sigma: float
    separation_after_sigma: float
    correlation_now: float
    correlation_after: float


def pose_separable(term: Term) -> bool:
    return term.family not in ("time", "direction") and term.effect != "thermal_drift"


def separating_poses(
    ctx: Context,
    fit: ModelFit,
    terms: list[Term],
    estimates: list[FloatArray],
    n_poses: int,
    rng: np.random.Generator,
    pool_size: int = 400,
    weights: FloatArray | None = None,
) -> SeparatingPoses | None:
    """Greedy D-optimal poses for the coefficients of ``terms`` (1 or 2 terms).

    ``fit`` is the model without the terms; ``estimates`` each term's coefficients as estimated
    alone; ``weights`` (d,) the noise whitening (default the fit's — pass the one estimated
    with a term in, else the noise scale still contains the effect).
    """
    w = fit.weights if weights is None else weights
    if n_poses <= 0 or not all(pose_separable(t) for t in terms):
        return None
    data = ctx.data
    n = data.n_samples
    pool = sample_configurations(ctx.chain, pool_size, rng)
    joined = data.with_configurations(pool)
    big = Context.build(ctx.chain, joined)
    rows = np.arange(n + pool_size)
    design = evaluate(big, fit.terms, fit.params, rows, candidates=tuple(terms))
    d = data.rows
    nuisance = np.concatenate([fit.nuisance(design.links), design.terms], axis=2)
    target = np.concatenate([design.candidates[t.key] for t in terms], axis=2)
    x = whitened(np.concatenate([nuisance, target], axis=2), w)
    signatures = [
        whitened(design.candidates[t.key] @ e, w) for t, e in zip(terms, estimates, strict=True)
    ]
    used = fit.rows
    norms = np.linalg.norm(x[used].reshape(used.size * d, -1), axis=0)
    x /= np.where(norms > 0, norms, 1.0)
    m = target.shape[2]
    current, pool_rows = x[used].reshape(used.size * d, -1), x[n:]
    information = current.T @ current
    information += 1e-10 * np.trace(information) / information.shape[0] * np.eye(len(information))
    chosen: list[int] = []
    for _ in range(n_poses):
        inverse = np.linalg.inv(information)
        block = inverse[-m:, -m:]
        # Woodbury: new target block = block − U S⁻¹ Uᵀ with U = [F⁻¹ Xᵀ]_target, S = I + X F⁻¹ Xᵀ.
        fx = np.einsum("ij,pdj->pid", inverse, pool_rows)  # (P, p, d)
        s = np.eye(d) + np.einsum("pdj,pje->pde", pool_rows, fx)
        u = fx[:, -m:, :]
        updated = block - u @ np.linalg.solve(s, np.swapaxes(u, 1, 2))
        sign, logdet = np.linalg.slogdet(updated)
        score = np.where(sign > 0, -logdet, -np.inf)
        score[chosen] = -np.inf
        best = int(np.argmax(score))
        chosen.append(best)
        information = information + pool_rows[best].T @ pool_rows[best]
    null_now = NullModel(np.zeros(used.size * d), orthonormal_basis(current[:, :-m]), d)
    extended = np.concatenate([current, pool_rows[chosen].reshape(-1, current.shape[1])])
    null_after = NullModel(np.zeros(extended.shape[0]), orthonormal_basis(extended[:, :-m]), d)
    split = [t.size for t in terms]
    picked = np.r_[used, n + np.asarray(chosen)]
    return SeparatingPoses(
        configurations=pool[chosen],
        separation_now_sigma=_separation(current, signatures, used, split, d),
        separation_after_sigma=_separation(extended, signatures, picked, split, d),
        correlation_now=_correlation(null_now, current[:, -m:], split),
        correlation_after=_correlation(null_after, extended[:, -m:], split),
    )


def _separation(
    design: FloatArray, signatures: list[FloatArray], rows: IntArray, split: list[int], d: int
) -> float:
    """Noise standard deviations between the explanations' predictions on ``rows``."""
    m = sum(split)
    nuisance = design[:, :-m]
    targets = [design[:, -m : -m + split[0] if len(split) > 1 else None]]
    if len(split) > 1:
        targets.append(design[:, -split[1] :])
    out = []
    for i, signature in enumerate(signatures):
        others = [t for j, t in enumerate(targets) if j != i]
        basis = orthonormal_basis(np.hstack([nuisance, *others]))
        s = signature[rows].reshape(-1)
        out.append(float(np.linalg.norm(s - basis @ (basis.T @ s))))
    return min(out)


def _correlation(null: NullModel, target: FloatArray, split: list[int]) -> float:
    """Two terms: their canonical correlation; one term: with the nuisance (geometry)."""
    if len(split) == 2:
        return canonical_correlation(null, target[:, : split[0]], target[:, split[0] :])
    absorbed = null.project(target)
    fraction = np.sum(absorbed**2) / max(float(np.sum(target**2)), 1e-300)
    return float(np.sqrt(np.clip(1.0 - fraction, 0.0, 1.0)))
