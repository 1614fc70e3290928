"""Score (Lagrange-multiplier) tests of candidate columns against the fitted model.

At the fitted model, with whitened residual ``r`` (R rows) and an orthonormal basis ``Q`` of the
whitened model Jacobian, a candidate with whitened columns ``C`` (R, m) is tested on its part
the model cannot absorb, ``C̃ = (I − QQᵀ) C`` — no refit per candidate. Two statistics:

* classical: ``F = (ΔSS/m) / ((RSS − ΔSS)/(ν − m))`` with ``ΔSS = |P_C̃ r|²``, ν = R − rank(Q),
  exact for Gaussian white noise;
* cluster-robust: per-sample scores ``u_n = C̃_nᵀ r_n`` (leverage-adjusted residuals),
  ``T = sᵀ (Σ u_n u_nᵀ)⁻¹ s`` with ``s = Σ u_n``; valid when the noise is correlated within a
  sample or changes with the configuration (random joint perturbations, paper Eq. 12). Its
  p-value is a cluster sign-flip randomisation (wild cluster / Rademacher: Canay, Romano &
  Shaikh 2017, "Randomization tests under an approximate symmetry assumption"; Cameron,
  Gelbach & Miller 2008): with the per-sample scores as the rows of U (N, m), V = UᵀU is the
  same for every sign pattern ε ∈ {±1}ᴺ, so ``T(ε) = |Zᵀε|²`` with ``Z = U V^{-1/2}`` and
  ``T = T(1)``; p = P_ε(T(ε) ≥ T(1)). Exact over all 2ᴺ⁻¹ patterns (T(ε) = T(−ε)) for
  N ≤ :data:`EXACT_FLIP_SAMPLES` (meet in the middle), else sequential Monte Carlo
  (Besag & Clifford 1991) over a fixed, seeded bank of patterns (the tests of one step read
  the bank once together, each stopping where it would alone: :func:`flip_p_values`). Its
  smallest p is ~2^{−(N−1)}, so 21 samples still reach a Holm level of 1e-4, and an effect
  that dominates makes every u_n agree and p tiny whatever its share of V (the asymptotic χ²
  reference bounded T by N and could not).

The reported p-value is the larger of the two: a candidate must pass both.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
import scipy.special
from numpy.typing import NDArray

from solver.arrays import FloatArray
from solver.discovery.fitting import ModelFit, orthonormal_basis

# Sign-flip randomisation of the cluster-robust statistic (module docstring): exact up to this
# many samples; else at most FLIP_DRAWS seeded patterns, stopping once FLIP_EXCEEDANCES of them
# reach the observed statistic (p = h / draws, Besag & Clifford 1991). 2^16 draws resolve p
# down to 1.5e-5, eight times below the first Holm level of 80 candidates at α = 0.01.
EXACT_FLIP_SAMPLES = 22
FLIP_DRAWS = 1 << 16
FLIP_BATCH = 1 << 12
FLIP_EXCEEDANCES = 32
# The bank is cached in memory (float32) up to this many entries (128 MB: N ≤ 512 samples);
# beyond, each batch is regenerated from its seed when used.
FLIP_CACHE_ENTRIES = 1 << 25

# A candidate direction whose unexplained part is below this fraction of its norm is one the
# model already contains (e.g. isotropic scale vs link lengths): not testable.
TESTABLE_FRACTION = 1e-3


@dataclass(frozen=True, eq=False)
class NullModel:
    """Linearisation of a fit: whitened residual (R,), model basis (R, r), rows per sample d."""

    residual: FloatArray
    basis: FloatArray
    d: int
    flip_seed: int = 0

    @classmethod
    def from_fit(cls, fit: ModelFit, flip_seed: int = 0) -> NullModel:
        return cls(
            fit.residual_w,
            orthonormal_basis(fit.jacobian),
            fit.design.residual.shape[1],
            flip_seed,
        )

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

    def sample_scores(self, columns: FloatArray, residual: FloatArray) -> FloatArray:
        """Per-sample scores (N, m): ``u_n = C_nᵀ (I − H_nn)^{-1/2} r_n`` of whitened
        ``columns`` (R, m) against ``residual`` (R,), H_nn = Q_n Q_nᵀ (d, d) the sample's block
        of the hat matrix: each sample's residual restored to the error's scale (the CR2
        adjustment of Bell & McCaffrey 2002; eigenvalues of I − H_nn floored at 0.05)."""
        n, d, m = self.n_samples, self.d, columns.shape[1]
        adjusted = np.einsum("nij,nj->ni", self.residual_root, residual.reshape(n, d))
        scores = np.einsum("nrm,nr->nm", columns.reshape(n, d, m), adjusted)
        return np.asarray(scores, dtype=np.float64)

    @functools.cached_property
    def residual_root(self) -> FloatArray:
        """(I − H_nn)^{-1/2} of every sample (N, d, d)."""
        q = self.basis.reshape(self.n_samples, self.d, -1)
        hat = np.einsum("nik,njk->nij", q, q)
        values, vectors = np.linalg.eigh(np.eye(self.d)[None] - hat)
        scale = 1.0 / np.sqrt(np.clip(values, 0.05, None))
        return np.asarray(np.einsum("nik,nk,njk->nij", vectors, scale, vectors), dtype=np.float64)


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


def score_test(
    null: NullModel, key: str, columns: FloatArray, certify_below: float | None = None
) -> ScoreTest | None:
    """Test whitened candidate ``columns`` (R, m); None when the model absorbs them entirely.
    ``certify_below``: a level at which only the test's decision is needed. Where
    :func:`flip_p_bound` already puts the sign-flip p-value at or below it, the bound stands
    in for that p-value; where the classical half is already above it, the classical p-value
    does (the p-value, the larger of the two, is then above the level whatever the sign-flip
    half gives). Either way the decision at that level is the full test's, without
    enumerating sign patterns."""
    pending = _pending_test(null, key, columns)
    if pending is None:
        return None
    test, z = pending
    if certify_below is not None:
        if test.p_classical > certify_below:
            return replace(test, p_robust=test.p_classical)
        if (bound := flip_p_bound(z)) <= certify_below:
            return replace(test, p_robust=bound)
    return replace(test, p_robust=flip_p_value(z, null.flip_seed))


def score_tests(null: NullModel, candidates: Mapping[str, FloatArray]) -> dict[str, ScoreTest]:
    """:func:`score_test` of every candidate (key → whitened columns (R, m)), in order, with
    the sign-flip p-values of all of them from one pass over the bank
    (:func:`flip_p_values`: the same p-values as one test at a time); candidates the model
    absorbs entirely are left out."""
    pending = {}
    for key, columns in candidates.items():
        found = _pending_test(null, key, columns)
        if found is not None:
            pending[key] = found
    p_values = flip_p_values([z for _, z in pending.values()], null.flip_seed)
    return {
        key: replace(test, p_robust=p)
        for (key, (test, _)), p in zip(pending.items(), p_values, strict=True)
    }


def _pending_test(
    null: NullModel, key: str, columns: FloatArray
) -> tuple[ScoreTest, FloatArray] | None:
    """A candidate's score test with its sign-flip p-value still to be computed (NaN), and
    its whitened per-sample scores ``Z`` (N, k) that p-value is of; None when the model
    absorbs the candidate entirely."""
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
    z, _ = flip_whitened(null.sample_scores(u, r))
    total = z.sum(axis=0)
    estimate = pinv @ r  # one-step estimate: least squares of r on the projected columns
    covariance = denominator * pinv @ pinv.T
    sandwich = sandwich_covariance(null, pinv, r)
    variance = np.maximum(np.diag(covariance), np.diag(sandwich))
    effect = columns @ estimate
    absorbed = 1.0 - float(np.sum(null.project(effect[:, None]) ** 2)) / max(
        float(effect @ effect), 1e-300
    )
    test = ScoreTest(
        key=key,
        m=m,
        delta_ss=delta_ss,
        f_statistic=float(f_stat),
        p_classical=p_classical,
        robust_statistic=float(total @ total),
        p_robust=float("nan"),
        log_p=log_p,
        estimate=estimate,
        stderr=np.sqrt(variance),
        absorbed_fraction=float(np.clip(absorbed, 0.0, 1.0)),
    )
    return test, z


def flip_whitened(scores: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``Z = U W`` (N, k) of per-sample scores U (N, m) and ``W = V^{-1/2}`` (m, k), V = UᵀU
    (pseudo-inverse root: the k ≤ m directions with a non-negligible variance), so that
    ``T(ε) = |Zᵀε|²``."""
    values, vectors = np.linalg.eigh(scores.T @ scores)
    keep = values > 1e-12 * max(float(values[-1]), 1e-300)
    whiten = vectors[:, keep] / np.sqrt(values[keep])
    return np.asarray(scores @ whiten, dtype=np.float64), np.asarray(whiten, dtype=np.float64)


def flip_p_bound(z: FloatArray) -> float:
    """Upper bound on the sign-flip p-value of whitened scores ``z`` (N, k), ``ZᵀZ = I``: each
    coordinate of ``Zᵀε`` is a Rademacher sum of unit variance (Hoeffding:
    ``P(|S_j| ≥ s) ≤ 2 exp(−s²/2)``), and ``|Zᵀε|² ≥ t`` needs some ``S_j² ≥ t/k``, so
    ``p ≤ 2k exp(−T(1)/(2k))``. Certifies a small p-value without enumerating patterns."""
    k = z.shape[1]
    if k == 0:
        return 1.0
    observed = float(np.sum(z.sum(axis=0) ** 2))
    return float(min(1.0, 2.0 * k * np.exp(-observed / (2.0 * k))))


def flip_p_value(z: FloatArray, seed: int = 0) -> float:
    """Sign-flip p-value P_ε(|Zᵀε|² ≥ |Zᵀ1|²) of whitened per-sample scores ``z`` (N, k),
    ε uniform on {±1}ᴺ: exact for N ≤ :data:`EXACT_FLIP_SAMPLES`, else Monte Carlo (module
    docstring)."""
    if z.shape[1] == 0:
        return 1.0
    observed = tie_threshold(float(np.sum(z.sum(axis=0) ** 2)))
    if z.shape[0] <= EXACT_FLIP_SAMPLES:
        return flip_p_exact(z, observed)
    return flip_p_sequential(z, observed, seed)


def flip_p_values(zs: list[FloatArray], seed: int = 0) -> list[float]:
    """:func:`flip_p_value` of each of ``zs`` (whitened scores (N, k_i) of the same N
    samples), the Monte Carlo ones from one pass over the bank
    (:func:`flip_p_sequential_batched`)."""
    out = [1.0 if z.shape[1] == 0 else float("nan") for z in zs]
    pending = [i for i, z in enumerate(zs) if z.shape[1] > 0]
    observed = [tie_threshold(float(np.sum(zs[i].sum(axis=0) ** 2))) for i in pending]
    if pending and zs[pending[0]].shape[0] <= EXACT_FLIP_SAMPLES:
        for i, level in zip(pending, observed, strict=True):
            out[i] = flip_p_exact(zs[i], level)
        return out
    found = flip_p_sequential_batched([zs[i] for i in pending], observed, seed)
    for i, p in zip(pending, found, strict=True):
        out[i] = p
    return out


def tie_threshold(observed: float) -> float:
    """Patterns within rounding of the observed statistic count as reaching it."""
    return observed * (1.0 - 1e-9) - 1e-12


def flip_p_exact(z: FloatArray, observed: float) -> float:
    """Exact sign-flip p-value over the 2ᴺ⁻¹ patterns with ε₁ = +1 (T(ε) = T(−ε)); the
    observed one (ε = 1) is among them, so p ≥ 2^{−(N−1)}.

    Meet in the middle: ``Zᵀε = a + b`` with a over the first half of the samples (ε₁ = +1)
    and b over the rest; ``|a + b|² = |a|² + |b|² + 2a·b`` for all pairs at once.
    """
    n = z.shape[0]
    half = (n + 1) // 2
    first = z[0] + all_signs(half - 1) @ z[1:half]
    second = all_signs(n - half) @ z[half:]
    first_sq = np.sum(first**2, axis=1)
    second_sq = np.sum(second**2, axis=1)
    count = 0
    step = max(1, (1 << 22) // max(second.shape[0], 1))
    for start in range(0, first.shape[0], step):
        block = first[start : start + step]
        totals = first_sq[start : start + step, None] + second_sq[None, :] + 2.0 * block @ second.T
        count += int(np.count_nonzero(totals >= observed))
    return count / float(first.shape[0] * second.shape[0])


def all_signs(n: int) -> FloatArray:
    """Every sign pattern of length ``n`` (2ⁿ, n); one empty pattern when n = 0."""
    codes = np.arange(1 << n)[:, None] >> np.arange(n)[None, :]
    return np.asarray(1.0 - 2.0 * (codes & 1), dtype=np.float64)


def flip_p_sequential(z: FloatArray, observed: float, seed: int = 0) -> float:
    """Monte Carlo sign-flip p-value (Besag & Clifford 1991): draw patterns in order from the
    seeded bank until :data:`FLIP_EXCEEDANCES` reach ``observed`` (p = h / draws), else
    p = (exceedances + 1) / (FLIP_DRAWS + 1)."""
    n, scores = z.shape[0], z.astype(np.float32)
    count, drawn = 0, 0
    for batch in range(FLIP_DRAWS // FLIP_BATCH):
        reached = _reached(flip_batch(seed, n, batch), scores, observed)
        running = count + np.cumsum(reached)
        stop = _stop_index(running)
        if stop is not None:
            return FLIP_EXCEEDANCES / float(drawn + stop + 1)
        count, drawn = int(running[-1]), drawn + reached.size
    return (count + 1) / float(FLIP_DRAWS + 1)


def flip_p_sequential_batched(
    zs: list[FloatArray], observed: list[float], seed: int = 0
) -> list[float]:
    """:func:`flip_p_sequential` of each of ``zs`` (N, k_i) against its ``observed``
    statistic, bit for bit, from one pass over the bank: each batch of patterns (B, N) is
    multiplied by the float32 scores of every test still drawing, stacked (N, Σk), in one
    product.

    That product sums the N terms ``ε_n z_nj`` in another order than the test's own product,
    so its projections may differ in the last bits. For any order the float32 sum is within
    ``γ Σ_n |z_nj|`` of the exact one (γ = (N−1)u / (1 − (N−1)u), u = 2⁻²⁴; Higham 2002,
    §3.1), so the two differ by at most ``δ_j = 2γ Σ_n |z_nj|``, and a pattern's statistic
    ``T = Σ_j p_j²`` by at most ``Σ_j δ_j (2|p_j| + δ_j)``. A pattern within that margin of
    ``observed`` before the test would have stopped is decided by the test's own product of
    that batch (:func:`_reached`), so every test stops where it would alone."""
    n = zs[0].shape[0] if zs else 0
    gamma = (n - 1) * 2.0**-24 / (1.0 - (n - 1) * 2.0**-24)
    scores = [z.astype(np.float32) for z in zs]
    # (1 + 1e-9): the float64 rounding of the bound itself
    slack = [
        2.0 * gamma * (1.0 + 1e-9) * np.sum(np.abs(z.astype(np.float64)), axis=0) for z in scores
    ]
    counts, drawn = np.zeros(len(zs), dtype=np.int64), 0
    p_values: list[float | None] = [None] * len(zs)
    for batch in range(FLIP_DRAWS // FLIP_BATCH):
        active = [i for i, p in enumerate(p_values) if p is None]
        if not active:
            break
        bank = flip_batch(seed, n, batch)
        starts = np.cumsum([0] + [scores[i].shape[1] for i in active[:-1]])
        part = (bank @ np.hstack([scores[i] for i in active])).astype(np.float64)  # (B, Σk)
        delta = np.concatenate([slack[i] for i in active])
        statistic = np.add.reduceat(part**2, starts, axis=1)  # (B, tests)
        margin = np.add.reduceat(delta * (2.0 * np.abs(part) + delta), starts, axis=1)
        level = np.array([observed[i] for i in active])
        margin += 1e-12 * (statistic + level)  # float64 rounding of the sums
        unsure = np.abs(statistic - level) <= margin
        running = counts[active] + np.cumsum(statistic >= level, axis=0)
        for column, i in enumerate(active):
            own = running[:, column]
            ending = _stop_index(own)
            if np.any(unsure[: FLIP_BATCH if ending is None else ending + 1, column]):
                own = counts[i] + np.cumsum(_reached(bank, scores[i], observed[i]))
                ending = _stop_index(own)
            if ending is not None:
                p_values[i] = FLIP_EXCEEDANCES / float(drawn + ending + 1)
            counts[i] = own[-1]
        drawn += FLIP_BATCH
    return [
        (int(counts[i]) + 1) / float(FLIP_DRAWS + 1) if p is None else p
        for i, p in enumerate(p_values)
    ]


def _stop_index(running: NDArray[np.int64]) -> int | None:
    """Index in a batch of the pattern at which the running exceedance count reaches
    :data:`FLIP_EXCEEDANCES` (the sequential test stops there); None if it does not."""
    if running[-1] < FLIP_EXCEEDANCES:
        return None
    return int(np.searchsorted(running, FLIP_EXCEEDANCES))


def _reached(
    bank: NDArray[np.float32], scores: NDArray[np.float32], observed: float
) -> NDArray[np.bool_]:
    """Which patterns of ``bank`` (B, N) reach ``observed`` with float32 ``scores`` (N, k),
    by the one product :func:`flip_p_sequential` computes."""
    return np.asarray(np.sum((bank @ scores).astype(np.float64) ** 2, axis=1) >= observed)


def flip_batch(seed: int, n: int, batch: int) -> NDArray[np.float32]:
    """Batch ``batch`` (FLIP_BATCH, n) of the seeded bank of sign patterns (±1, float32)."""
    if FLIP_DRAWS * n <= FLIP_CACHE_ENTRIES:
        return _cached_bank(seed, n)[batch * FLIP_BATCH : (batch + 1) * FLIP_BATCH]
    return _generate_batch(seed, n, batch)


@functools.lru_cache(maxsize=2)
def _cached_bank(seed: int, n: int) -> NDArray[np.float32]:
    """The whole bank (FLIP_DRAWS, n) of one seed and sample count, written batch by batch
    into one array (no concatenated copy)."""
    bank = np.empty((FLIP_DRAWS, n), dtype=np.float32)
    for b in range(FLIP_DRAWS // FLIP_BATCH):
        _generate_batch(seed, n, b, out=bank[b * FLIP_BATCH : (b + 1) * FLIP_BATCH])
    return bank


def _generate_batch(
    seed: int, n: int, batch: int, out: NDArray[np.float32] | None = None
) -> NDArray[np.float32]:
    """Batch ``batch`` (FLIP_BATCH, n) of the bank, ±1, written into ``out`` when given.

    Pattern entry k (row-major) is −1 where the top bit of byte k of the raw 64-bit outputs of
    PCG64 seeded with ``SeedSequence([seed, n, batch])`` (bytes in little-endian order) is set,
    +1 where it is clear: one byte per sign read straight from the generator. These are the
    signs ``Generator.integers(0, 2, dtype=int8)`` draws (its bounded-integer method keeps a
    byte's top bit for two values), without its per-byte bounding, and defined without
    depending on it."""
    count = FLIP_BATCH * n
    raw = np.random.default_rng([seed, n, batch]).bit_generator.random_raw(-(-count // 8))
    top_bits = (np.asarray(raw, dtype="<u8").view(np.uint8)[:count] >> 7).view(np.int8)
    if out is None:
        out = np.empty((FLIP_BATCH, n), dtype=np.float32)
    np.subtract(1, 2 * top_bits.reshape(FLIP_BATCH, n), out=out, casting="unsafe")
    return out


def sandwich_covariance(null: NullModel, pinv: FloatArray, r: FloatArray) -> FloatArray:
    """Per-sample cluster-robust covariance (m, m) of the estimate ``pinv @ r`` (``pinv``
    (m, R)), residuals scaled up by their sample's leverage."""
    per_sample = null.sample_scores(np.ascontiguousarray(pinv.T), r)
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
