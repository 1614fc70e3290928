"""Smallest detectable size of every library term on one recording (issue 14).

For a candidate with whitened columns ``C`` (R, m), the part the fitted model cannot absorb is
``C̃ = (I − QQᵀ) C`` (:mod:`solver.discovery.scoring`). An effect of coefficients θ adds
``C̃ θ`` to the whitened residual r (to first order: the refit of the null model removes the
rest). The stated size is the smallest ``|θ|`` in the term's weakest direction (largest
variance of the one-step estimate, ``s² (C̃ᵀC̃)⁻¹``: any phase of a gear error, any axis of a
flex) that the decision the report applies — classical F *and* cluster sign-flip test both at
``level`` — takes with probability ``power``. Because the sign-flip test has no closed-form
power, the size is calibrated on the recording itself (:func:`calibrated_size`): the effect is
added at trial sizes to the recording's own residual and to
:data:`DETECTION_REPLICATES` − 1 replicates of it whose samples' residuals have random signs
(projected off the model again), with alternating signs of the effect, and both statistics are
evaluated exactly as the test does (same bank of sign patterns); the size is the smallest of a
geometric scan (steps of :data:`SIZE_STEP`, then bisection) at which the share of replicates
rejecting reaches ``power``. The scan starts at the classical noncentral-F size
(:func:`noncentrality_needed`), which the classical half alone would need.

The level is the first step's Holm threshold, α over the number of candidates tested, so
"nothing found" reads "nothing larger than this". A measurement-frame drift mixes metres and
radians: its translation and rotation parts get one size each (its test keeps 6 dof). No size
is stated (infinite, with the reason) when the model absorbs the weakest direction to
``absorbed_limit`` (the step would be ambiguous with the geometry: e.g. a depth scale along a
flange camera's axis) or when no trial size up to :data:`MAX_SIZE_FACTOR` times the classical
size is found (few samples: the sign-flip test's smallest p-value is ~2^{−(N−1)}).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.special
import scipy.stats
from numpy.typing import NDArray

from solver.discovery.explain import describe
from solver.discovery.fitting import Context, ModelFit, evaluate, whitened
from solver.discovery.library import Term, same_mechanism
from solver.discovery.scoring import (
    FLIP_BATCH,
    FLIP_DRAWS,
    NullModel,
    flip_batch,
    flip_whitened,
    tie_threshold,
    unexplained_basis,
)

FloatArray = NDArray[np.float64]

DETECTION_POWER = 0.8
DETECTION_REPLICATES = 10
SIZE_STEP = 1.25
BISECTIONS = 2
MAX_SIZE_FACTOR = 64.0


@dataclass(frozen=True)
class DetectableSize:
    """The smallest ``parameter`` of ``term`` this recording detects (see module docstring);
    ``smallest`` in the parameter's unit (inf: none, ``reason`` says why)."""

    term: Term
    parameter: str
    smallest: float
    reason: str = ""  # why no size is stated (smallest infinite)


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
    seed: int = 0,
    absorbed_limit: float = 0.97,
    unexplained: frozenset[tuple[str, int]] = frozenset(),
    collinear: float = 0.999,
) -> list[DetectableSize]:
    """Smallest detectable size of each term of ``library`` (not in ``fit``'s model) on the
    recording, for the score test at ``level`` with ``power`` (module docstring); ``seed`` is
    the discovery seed (the sign-flip bank and the replicates). ``unexplained``: (family,
    joint) pairs whose structure the run reported beyond the library — discovery names no
    term of that family there, so none gets a size; nor does a term whose columns, once the
    model is fitted, are collinear with another term's (canonical correlation ≥
    ``collinear``, :func:`collinear_twins`): discovery reports the pair ambiguous."""
    if not library:
        return []
    design = evaluate(ctx, fit.terms, fit.params, fit.rows, candidates=tuple(library))
    null = NullModel.from_fit(fit, seed)
    replicates = noise_replicates(null, DETECTION_REPLICATES, np.random.default_rng(seed))
    testable = [t for t in library if (t.family, t.joint_index) not in unexplained]
    columns = {
        t.key: whitened(design.candidates[t.key], fit.weights).reshape(-1, t.size) for t in testable
    }
    twins = collinear_twins(null, testable, columns, collinear)
    out = []
    for term in library:
        reason = ""
        if (term.family, term.joint_index) in unexplained:
            reason = f"its joint's {term.family}-dependent structure is reported unexplained"
        elif twins.get(term.key):
            twin, correlation = twins[term.key]
            label = describe(twin, ctx.chain.joint_names)
            reason = f"not separable from {label} (correlation {correlation:.4f})"
        if reason:
            out += [DetectableSize(term, name, np.inf, reason) for name, _ in size_groups(term)]
            continue
        out += term_sizes(null, term, columns[term.key], replicates, level, power, absorbed_limit)
    return out


def collinear_twins(
    null: NullModel, library: list[Term], columns: dict[str, FloatArray], collinear: float
) -> dict[str, tuple[Term, float]]:
    """Terms whose stated size the data cannot tell from another library term (not a shape of
    the same mechanism), once the model is fitted: a direction of the term's part the model
    cannot absorb lies in the other's (a canonical correlation ≥ ``collinear``, as
    :func:`~solver.discovery.scoring.canonical_correlation`). The stated size is the worst
    direction's, so one such direction is enough — e.g. a base flex about the axis of the
    shoulder joint is its compliance — except for a measurement-frame drift, whose sizes are
    per part (all its directions must lie in the other's: a drift of the first joint about
    the vertical is inside a frame drift, not the other way round). Maps the term's key to
    the other term and that correlation."""
    bases = {t.key: unexplained_basis(null, columns[t.key]) for t in library}
    out: dict[str, tuple[Term, float]] = {}
    for i, first in enumerate(library):
        for second in library[i + 1 :]:
            a, b = bases[first.key], bases[second.key]
            if a.shape[1] == 0 or b.shape[1] == 0 or same_mechanism(first, second):
                continue
            values = np.linalg.svd(a.T @ b, compute_uv=False)
            for one, other, width in ((first, second, a.shape[1]), (second, first, b.shape[1])):
                needed = width if len(size_groups(one)) > 1 else 1
                if needed > values.size or values[needed - 1] < collinear:
                    continue
                if values[needed - 1] > out.get(one.key, (other, 0.0))[1]:
                    out[one.key] = (other, float(values[needed - 1]))
    return out


def term_sizes(
    null: NullModel,
    term: Term,
    columns: FloatArray,
    replicates: list[FloatArray],
    level: float,
    power: float,
    absorbed_limit: float,
) -> list[DetectableSize]:
    """:class:`DetectableSize` of each of ``term``'s size groups (module docstring)."""
    groups = size_groups(term)
    dof = min(null.dof, null.n_samples) - term.size
    basis = unexplained_basis(null, columns)
    if dof <= 0 or basis.shape[1] == 0:
        return [DetectableSize(term, name, np.inf, "absorbed by the model") for name, _ in groups]
    scale2 = float(null.residual @ null.residual) / max(null.dof, 1)
    projected = null.project(columns)
    gram = projected.T @ projected
    out = []
    for parameter, indices in groups:
        direction = weakest_direction(gram, indices)
        signature = columns @ direction
        effect = projected @ direction
        absorbed = 1.0 - float(effect @ effect) / max(float(signature @ signature), 1e-300)
        if absorbed >= absorbed_limit:
            reason = f"not separable from the model: {absorbed:.1%} absorbed"
            out.append(DetectableSize(term, parameter, np.inf, reason))
            continue
        needed = noncentrality_needed(basis.shape[1], dof, level, power)
        classical = float(np.sqrt(needed * scale2 / float(effect @ effect)))
        size = calibrated_size(null, basis, effect, replicates, level, power, classical)
        reason = "" if np.isfinite(size) else "not detected at any size tried"
        out.append(DetectableSize(term, parameter, size, reason))
    return out


def weakest_direction(gram: FloatArray, indices: list[int]) -> FloatArray:
    """Unit coefficient vector (m,) within ``indices`` along which the one-step estimate's
    variance ``s² (C̃ᵀC̃)⁻¹`` is largest (the smallest eigenvalue of the block's Gram matrix
    once the other coefficients are free; an absorbed direction comes out as the weakest)."""
    try:
        covariance = np.linalg.pinv(gram, hermitian=True)
    except np.linalg.LinAlgError:
        covariance = np.eye(gram.shape[0])
    block = covariance[np.ix_(indices, indices)]
    _, vectors = np.linalg.eigh(block)
    out = np.zeros(gram.shape[0])
    out[indices] = vectors[:, -1]
    return out


def noise_replicates(null: NullModel, count: int, rng: np.random.Generator) -> list[FloatArray]:
    """The recording's residual and ``count`` − 1 replicates of it with each sample's residual
    block multiplied by a random sign, projected off the model again (whitened, (R,))."""
    out = [null.residual]
    n, d = null.n_samples, null.d
    for _ in range(count - 1):
        signs = np.repeat(rng.choice([-1.0, 1.0], size=n), d)
        out.append(null.project((signs * null.residual)[:, None])[:, 0])
    return out


def calibrated_size(
    null: NullModel,
    basis: FloatArray,
    effect: FloatArray,
    replicates: list[FloatArray],
    level: float,
    power: float,
    start: float,
) -> float:
    """Smallest size s (scan by :data:`SIZE_STEP` down or up from ``start``, then bisection)
    at which ``s · effect`` (R,) added to the replicates (alternating signs) is rejected by
    both halves of the score test in at least ``power`` of them; inf when none up to
    :data:`MAX_SIZE_FACTOR` · ``start``."""
    trials = _Trials(null, basis, effect, replicates)
    count = len(replicates)
    needed = int(np.ceil(power * count - 1e-9))

    def detected(size: float) -> bool:
        hits = 0
        for done in range(count):
            hits += trials.rejected(done, size, level)
            if hits >= needed or hits + count - done - 1 < needed:
                break
        return hits >= needed

    if detected(start):  # scan down from the classical size, else up
        low, high = start / SIZE_STEP, start
        while detected(low):
            low, high = low / SIZE_STEP, low
            if high < start / MAX_SIZE_FACTOR:
                return float(high)
    else:
        low, high = start, start * SIZE_STEP
        while not detected(high):
            low, high = high, high * SIZE_STEP
            if high > MAX_SIZE_FACTOR * start:
                return float("inf")
    for _ in range(BISECTIONS):
        middle = float(np.sqrt(low * high))
        low, high = (low, middle) if detected(middle) else (middle, high)
    return float(high)


# The sign-flip half is evaluated on the first DETECTION_DRAWS patterns of the test's bank (an
# estimate of the same p-value at half the cost), in two chunks: most trial sizes are refused
# within the first.
DETECTION_DRAWS = FLIP_DRAWS // 2
_CHUNKS = ((0, 1), (1, DETECTION_DRAWS // FLIP_BATCH))  # batches of the bank


class _Trials:
    """The replicates r_b with an effect ``σ_b · s · e`` added (σ_b alternating ±1): both
    statistics of the score test as functions of s (linear in s before the quadratic forms);
    the sign-flip bank's products with every replicate's scores are computed together, chunk
    by chunk as needed."""

    def __init__(
        self, null: NullModel, basis: FloatArray, effect: FloatArray, replicates: list[FloatArray]
    ):
        self.m = basis.shape[1]
        self.dof = null.dof - self.m
        self.signs = np.resize([1.0, -1.0], len(replicates))
        self.coords = [basis.T @ r for r in replicates], basis.T @ effect
        self.norms = [(float(r @ r), 2.0 * float(r @ effect)) for r in replicates]
        self.effect_norm = float(effect @ effect)
        self.scores = (
            [null.sample_scores(basis, r) for r in replicates],
            null.sample_scores(basis, effect),
        )
        self.stacked = np.hstack([self.scores[1], *self.scores[0]]).astype(np.float32)
        self.seed, self.n = null.flip_seed, null.n_samples
        # per chunk: the bank's products with the effect's and each replicate's scores
        self.projections: list[list[NDArray[np.float32]]] = []

    def rejected(self, b: int, size: float, level: float) -> bool:
        """Do both halves of the score test reject replicate ``b`` at ``level`` with the
        effect at ``size``? The sign-flip half counts patterns chunk by chunk and stops once
        too many reach the observed statistic."""
        m, signed = self.m, self.signs[b] * size
        coords = self.coords[0][b] + signed * self.coords[1]
        delta = float(coords @ coords)
        rss = self.norms[b][0] + signed * self.norms[b][1] + size**2 * self.effect_norm
        f_stat = delta / m / (max(rss - delta, 1e-300) / self.dof)
        if float(scipy.special.fdtrc(m, self.dof, f_stat)) > level:
            return False
        allowed = np.floor(level * (DETECTION_DRAWS + 1)) - 1  # most exceedances to reject
        if allowed < 0:
            return False
        z, whiten = flip_whitened(self.scores[0][b] + signed * self.scores[1])
        total = z.sum(axis=0)
        observed = tie_threshold(float(total @ total))
        whiten32 = whiten.astype(np.float32)
        count = 0
        for chunk, (start, stop) in enumerate(_CHUNKS):
            if chunk == len(self.projections):
                block = np.concatenate(
                    [flip_batch(self.seed, self.n, b) @ self.stacked for b in range(start, stop)]
                )
                parts = range(0, block.shape[1], m)
                self.projections.append([np.ascontiguousarray(block[:, i : i + m]) for i in parts])
            effect, *noise = self.projections[chunk]
            flipped = (noise[b] + np.float32(signed) * effect) @ whiten32
            count += int(np.count_nonzero(np.einsum("ij,ij->i", flipped, flipped) >= observed))
            if count > allowed:
                return False
        return True
