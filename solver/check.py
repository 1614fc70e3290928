"""Is it still calibrated? A few new poses tested against a calibration's own predictive
uncertainty (issue 33).

Frames and units (DESIGN.md §2): residuals ``r_n = Log(X_model(q_n)⁻¹ X_measured,n)`` (d = 6,
[v; w], m and rad) or their translation (d = 3, position-only) in the end-effector frame, as in
:mod:`solver.predictive`. The n check poses' residuals stacked, ``r`` (n·d,), are predicted to
be Gaussian with mean zero and the joint covariance

    Σ = blockdiag(Σ_E(q_n) + Σ_n + T_n diag(s) T_nᵀ) + J_θ Cov(θ̂) J_θᵀ          (n·d, n·d)

whose diagonal blocks are the total predictive covariance of ``kincal predict``; the
off-diagonal blocks are the parameter part, shared by every pose (one θ̂ for all of them).

A change of the robot by δ (true = calibrated + δ, in a candidate's coordinates) moves the
residuals by ``A δ`` with ``A`` the candidate's columns (n·d, m) of the end-effector-frame
Jacobian at the calibration. Tests:

- per pose: ``d²_n = r_nᵀ Σ_nn⁻¹ r_n`` ~ χ²_d; the max-type test calls a pose far off when
  ``d²_n`` exceeds the Šidák quantile ``χ²_d⁻¹((1 − α)^(1/n))``; a few far-off poses are set
  aside as bad samples unless a located change explains them;
- global: ``T = rᵀ Σ⁻¹ r`` ~ χ²_{rank Σ};
- score test of a candidate: with ``z = W r``, ``à = W A`` (W the whitening of Σ),
  ``S = ‖P_à z‖²`` ~ χ²_{rank Ã} under no change;
- the global and score tests together at family-wise level α by the min-p rule: drift when
  the smallest p-value is below the α quantile of that minimum under no change (Monte Carlo
  over z ~ N(0, I), which all the statistics are quadratic forms of);
- stated power: under a change δ, ``T`` and ``S`` are non-central χ² with ``λ = ‖Ã δ‖²``;
  the smallest size detected with probability ``power`` solves
  ``P(χ²_ν(λ) > χ²⁻¹_ν(1 − p*)) = power`` at the critical p-value p*.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
import scipy.special

from solver import lie
from solver.arrays import FloatArray, IntArray
from solver.distributions import chi2_quantile, chi2_survival
from solver.model import KinematicChain
from solver.predictive import mahalanobis_squared

MIN_POSES = 3
"""Fewer usable check poses than this: the verdict is inconclusive."""

POWER = 0.9
"""The detection probability a stated size promises."""

INDISTINCT_COS2 = 0.9
"""A candidate reproduces at least this share of the best candidate's fitted pattern
(squared cosine of the angle between it and the candidate's span): not told apart."""

EIGEN_CUT = 1e-12
"""Eigenvalues of the joint covariance below this share of its largest count as zero."""

TWIST_AXES = ("x", "y", "z", "rx", "ry", "rz")


# --- the joint covariance and its whitening ------------------------------------------------


def joint_covariance(
    local: FloatArray, parameter_jacobian: FloatArray, parameter_covariance: FloatArray
) -> FloatArray:
    """``Σ = blockdiag(local_n) + J_θ Cov(θ̂) J_θᵀ`` (n·d, n·d), end-effector frames, m²/m·rad/
    rad²: ``local`` (n, d, d) the parts independent between poses (Σ_E + Σ_n + model error),
    ``parameter_jacobian`` (n, d, p) of the estimated parameters (unweighted),
    ``parameter_covariance`` Cov(θ̂) (p, p)."""
    n, d, _ = local.shape
    stacked = parameter_jacobian.reshape(n * d, -1)
    total = stacked @ parameter_covariance @ stacked.T
    for i in range(n):
        total[i * d : (i + 1) * d, i * d : (i + 1) * d] += local[i]
    return np.asarray(0.5 * (total + total.T), dtype=float)


def whitening(covariance: FloatArray) -> FloatArray:
    """``W`` (ν, N) with ``W Σ Wᵀ = I_ν`` on the range of Σ (N, N), ν = rank Σ (eigenvalues
    below :data:`EIGEN_CUT` of the largest count as zero): ``Wr`` of a residual r ~ N(0, Σ) is
    standard normal."""
    values, vectors = np.linalg.eigh(covariance)
    keep = values > EIGEN_CUT * max(float(values.max()), 0.0)
    return np.asarray((vectors[:, keep] / np.sqrt(values[keep])).T, dtype=float)


def chi2_log_survival(statistic: float, dof: int) -> float:
    """``log P(χ²_dof > statistic)``, finite where the p-value underflows (the leading term of
    the upper incomplete gamma function's asymptotic series, ``Γ(a, x) ≈ x^(a−1) e^(−x)``,
    a = dof/2, x = statistic/2): ranks candidates of different dimensions by their p-values."""
    p_value = chi2_survival(statistic, dof)
    if p_value > 1e-300:
        return float(np.log(p_value))
    a, x = 0.5 * dof, 0.5 * statistic
    return float((a - 1.0) * np.log(x) - x - scipy.special.gammaln(a))


def chi2_log_survivals(statistics: FloatArray, dof: int) -> FloatArray:
    """:func:`chi2_log_survival` of many statistics (N,) at once."""
    p_values = scipy.special.gammaincc(0.5 * dof, 0.5 * np.maximum(statistics, 0.0))
    a, x = 0.5 * dof, 0.5 * np.maximum(statistics, 1e-300)
    tail = (a - 1.0) * np.log(x) - x - scipy.special.gammaln(a)
    return np.where(p_values > 1e-300, np.log(np.maximum(p_values, 1e-300)), tail)


# --- per pose and global tests -------------------------------------------------------------


def sidak_quantile(level: float, n_tests: int, dof: int) -> float:
    """Šidák threshold: the χ²_dof quantile ``(1 − level)^(1/n_tests)``, which one of
    ``n_tests`` independent χ²_dof statistics exceeds with probability ``level``."""
    return chi2_quantile((1.0 - level) ** (1.0 / n_tests), dof)


@dataclass(frozen=True)
class GlobalTest:
    """``statistic`` T = rᵀ Σ⁻¹ r (dimensionless) of the poses tested, ``dof`` rank Σ,
    ``threshold`` its χ² quantile at the test's level, ``p_value``."""

    statistic: float
    dof: int
    threshold: float
    p_value: float

    @property
    def rejects(self) -> bool:
        return self.statistic > self.threshold


def global_test(residuals: FloatArray, covariance: FloatArray, level: float) -> GlobalTest:
    """``T = ‖W r‖²`` ~ χ²_ν: ``residuals`` r (n·d,), ``covariance`` Σ (n·d, n·d) of
    :func:`joint_covariance`."""
    white = whitening(covariance)
    statistic = float(np.sum((white @ residuals) ** 2))
    dof = white.shape[0]
    return GlobalTest(
        statistic, dof, chi2_quantile(1.0 - level, dof), chi2_survival(statistic, dof)
    )


def pose_distances_squared(residuals: FloatArray, covariance: FloatArray) -> FloatArray:
    """``d²_n = r_nᵀ Σ_nn⁻¹ r_n`` (n,) from ``residuals`` (n, d) and the joint covariance
    (n·d, n·d): each pose against its own total predictive covariance (its diagonal block)."""
    n, d = residuals.shape
    blocks = np.stack([covariance[i * d : (i + 1) * d, i * d : (i + 1) * d] for i in range(n)])
    return mahalanobis_squared(residuals, blocks)


def subset_covariance(covariance: FloatArray, rows: IntArray, d: int) -> FloatArray:
    """The joint covariance (m·d, m·d) of the poses ``rows`` (m,) of a joint covariance of d-row
    poses."""
    index = (rows[:, None] * d + np.arange(d)[None, :]).ravel()
    return covariance[np.ix_(index, index)]


# --- candidate changes ---------------------------------------------------------------------


@dataclass(frozen=True)
class Candidate:
    """A change of the robot the check can locate: ``name`` (e.g. "panda_joint3 offset"),
    ``kind`` ("joint_offset", "joint_scale", "base", "tool", "link"), ``components`` and their
    ``units`` ("rad", "m", "1"), and ``jacobian`` (n, d, m): the end-effector-frame residual
    per unit change of each component (m or rad per unit) at the n check poses."""

    name: str
    kind: str
    components: tuple[str, ...]
    units: tuple[str, ...]
    jacobian: FloatArray


def joint_offset_columns(frame_jacobians: FloatArray, joint_screws: FloatArray) -> FloatArray:
    """Residual per radian (or metre) of offset of each joint (n, d, k): a joint reading that
    is short by δ, ``Exp(S_j (q_j + δ)) = Exp(S_j δ) Exp(S_j q_j)``, is the local correction
    ``S_j δ`` of ``L_j``, so its column is ``J_j S_j`` (J_j = Ad_{B_j}⁻¹, Eq. 9).
    ``frame_jacobians`` (n, k+1, d, 6), ``joint_screws`` (k, 6) [v; w] in each joint's frame."""
    k = joint_screws.shape[0]
    return np.einsum("njdc,jc->ndj", frame_jacobians[:, :k], joint_screws)


def base_columns(frame_jacobians: FloatArray, nominal_first_link: FloatArray) -> FloatArray:
    """Residual per unit move of the robot base (n, d, 6), [x, y, z (m), rx, ry, rz (rad)] along
    the robot base frame's axes: ``T_mb ← T_mb Exp(δ)`` with ``L_1 = T_mb N_1`` is the local
    correction ``Ad_{N_1}⁻¹ δ`` of L_1. ``nominal_first_link`` N_1 (4, 4): the URDF's base →
    joint 1 placement."""
    return np.asarray(frame_jacobians[:, 0] @ lie.adjoint_inverse(nominal_first_link))


def candidates_at(
    chain: KinematicChain, frame_jacobians: FloatArray, joint_positions: FloatArray
) -> list[Candidate]:
    """The candidate changes of ``chain`` at the check poses: each joint's offset and scale,
    the base frame (robot base in the measurement frame, 6), the tool or marker frame (its
    pose in the tip frame, 6) and each inner link's geometry (L_2..L_k, 6 each).
    ``frame_jacobians`` (n, k+1, d, 6) of every link frame (Eq. 9) and ``joint_positions``
    (n, k) the configurations (rad or m) they were taken at."""
    joint_screws, joint_names = chain.joint_screws, chain.joint_names
    revolute, nominal_first_link = chain.is_revolute(), chain.nominal_links[0]
    k = joint_screws.shape[0]
    offsets = joint_offset_columns(frame_jacobians, joint_screws)
    twist_units = ("m", "m", "m", "rad", "rad", "rad")
    found: list[Candidate] = []
    for j, name in enumerate(joint_names):
        unit = "rad" if revolute[j] else "m"
        found.append(
            Candidate(
                f"{name} offset", "joint_offset", ("offset",), (unit,), offsets[:, :, j : j + 1]
            )
        )
    for j, name in enumerate(joint_names):
        scaled = offsets[:, :, j : j + 1] * joint_positions[:, j, None, None]
        found.append(Candidate(f"{name} scale", "joint_scale", ("scale",), ("1",), scaled))
    found.append(
        Candidate(
            "base frame",
            "base",
            TWIST_AXES,
            twist_units,
            base_columns(frame_jacobians, nominal_first_link),
        )
    )
    found.append(
        Candidate(
            "tool frame",
            "tool",
            TWIST_AXES,
            twist_units,
            np.ascontiguousarray(frame_jacobians[:, k]),
        )
    )
    for j in range(1, k):
        found.append(
            Candidate(
                f"{joint_names[j]} link geometry",
                "link",
                TWIST_AXES,
                twist_units,
                np.ascontiguousarray(frame_jacobians[:, j]),
            )
        )
    return found


# --- score tests -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScoreTest:
    """A candidate's score test on the check poses: ``statistic`` S = ‖P_Ã z‖² ~ χ²_dof under
    no change, ``p_value`` and ``adjusted`` (family-wise over every test of the check,
    :func:`drift_tests`), ``estimate`` δ̂ (m,) in the candidate's units and ``covariance``
    (m, m) of it, ``fitted`` the whitened pattern Ã δ̂ (ν,), ``columns`` Ã (ν, m)."""

    candidate: Candidate
    statistic: float
    dof: int
    p_value: float
    adjusted: float
    estimate: FloatArray
    covariance: FloatArray
    fitted: FloatArray
    columns: FloatArray
    basis: FloatArray
    """An orthonormal basis (ν, dof) of the span of ``columns``."""

    @property
    def log_p_value(self) -> float:
        return chi2_log_survival(self.statistic, self.dof)

    def interval95(self) -> tuple[FloatArray, FloatArray]:
        """95 % intervals (m,) of each component: δ̂ ∓ 1.96 σ."""
        half = 1.959963984540054 * np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return self.estimate - half, self.estimate + half


def score_test(whitened_residuals: FloatArray, whitened_columns: FloatArray) -> ScoreTest:
    """Score (= likelihood-ratio, the model being linear) test of a change along the columns
    ``Ã`` (ν, m) for whitened residuals ``z`` (ν,): ``δ̂ = Ã⁺ z``, ``Cov(δ̂) = (ÃᵀÃ)⁺``,
    ``S = ‖Ã δ̂‖²`` with ``rank Ã`` degrees of freedom (its candidate left empty, its adjusted
    p-value the raw one: :func:`score_tests` fills them)."""
    norms = np.linalg.norm(whitened_columns, axis=0)
    norms = np.where(norms > 0.0, norms, 1.0)
    u, s, vt = np.linalg.svd(whitened_columns / norms, full_matrices=False)
    keep = s > 1e-8 * max(float(s.max()), 1e-300)
    basis = u[:, keep]
    estimate = ((vt[keep].T / s[keep]) @ (basis.T @ whitened_residuals)) / norms
    covariance = ((vt[keep].T / s[keep] ** 2) @ vt[keep]) / np.outer(norms, norms)
    fitted = basis @ (basis.T @ whitened_residuals)
    statistic, dof = float(fitted @ fitted), int(keep.sum())
    p_value = chi2_survival(statistic, dof)
    return ScoreTest(
        NO_CANDIDATE,
        statistic,
        dof,
        p_value,
        p_value,
        estimate,
        covariance,
        fitted,
        whitened_columns,
        basis,
    )


NO_CANDIDATE = Candidate("", "joint_offset", (), (), np.zeros((0, 0, 0)))


def score_tests(
    white: FloatArray, residuals: FloatArray, candidates: list[Candidate]
) -> list[ScoreTest]:
    """Every candidate's :func:`score_test` on ``residuals`` (n, d) whitened by ``white``
    (ν, n·d) of :func:`whitening`, best first (by the log of their p-value, so candidates of
    different dimensions compare fairly)."""
    z = white @ residuals.ravel()
    tests = []
    for candidate in candidates:
        n, d, m = candidate.jacobian.shape
        test = score_test(z, white @ candidate.jacobian.reshape(n * d, m))
        tests.append(dataclasses.replace(test, candidate=candidate))
    return sorted(tests, key=lambda t: t.log_p_value if t.dof else np.inf)


def reproduced_share(pattern: FloatArray, columns: FloatArray) -> float:
    """Share of ``pattern`` (ν,) that the span of ``columns`` (ν, m) reproduces:
    ``‖P pattern‖² / ‖pattern‖²`` (squared cosine of the angle between them)."""
    norm2 = float(pattern @ pattern)
    if norm2 <= 0.0:
        return 0.0
    coefficients = np.linalg.lstsq(columns, pattern, rcond=None)[0]
    projected = columns @ coefficients
    return float(projected @ projected) / norm2


NESTED_SHARE = 0.999
"""A candidate whose every column the span of another reproduces to this share is nested in
it (a joint's offset in the geometry of the links on either side of it, joint 1's in the
base, the last joint's in the tool)."""

NESTED_LEVEL = 0.05
"""The larger of two nested candidates is located only when its extra components are
significant at this level (likelihood-ratio test): otherwise the simpler change explains the
drift as well."""


def nested_in(inner: ScoreTest, outer: ScoreTest) -> bool:
    """Whether ``inner``'s columns lie in the span of ``outer``'s."""
    return inner.dof < outer.dof and all(
        reproduced_share(column, outer.basis) >= NESTED_SHARE for column in inner.columns.T
    )


@dataclass(frozen=True)
class LocatedDrift:
    """The drift located: ``best`` the candidate that explains it (None: none is significant
    at the check's level, family-wise): the most significant, or a simpler candidate nested in
    it whose extra components are not significant; ``alternatives`` other significant
    candidates of no more components that reproduce ≥ :data:`INDISTINCT_COS2` of its pattern
    (the check poses cannot tell them apart); ``tests`` every candidate's score test, best
    first."""

    best: ScoreTest | None
    alternatives: tuple[ScoreTest, ...]
    tests: tuple[ScoreTest, ...]


def locate_drift(tests: list[ScoreTest], critical_p: float) -> LocatedDrift:
    """The located change among score ``tests`` (best first) significant at ``critical_p``."""
    significant = [t for t in tests if t.p_value <= critical_p]
    if not significant:
        return LocatedDrift(None, (), tuple(tests))
    best = significant[0]
    simpler = [
        t
        for t in significant[1:]
        if nested_in(t, best)
        and chi2_survival(best.statistic - t.statistic, best.dof - t.dof) > NESTED_LEVEL
    ]
    best = simpler[0] if simpler else best
    alternatives = tuple(
        other
        for other in significant
        if other is not best
        and other.dof <= best.dof
        and reproduced_share(best.fitted, other.basis) >= INDISTINCT_COS2
    )
    return LocatedDrift(best, alternatives, tuple(tests))


# --- the drift tests, family-wise ----------------------------------------------------------

NULL_DRAWS = 10_000
"""Monte Carlo draws of the tests' joint null distribution (the false-alarm rate's standard
error from it at 5 %: 0.2 points)."""

NULL_SEED = 33
"""Fixed: the same check gives the same verdict."""

LOCATE_DRAWS = 1000
"""Simulated checks per size when a stated size is checked for location (the located share's
standard error at 90 %: about 1 point)."""

LOCATE_TARGET = 0.92
"""The simulated located share a stated size must reach: :data:`POWER` plus twice the Monte
Carlo error, so that the promise holds."""

SIZE_STEPS = (1.0, 1.15, 1.3, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0)
"""Multiples of the detectable size tried, smallest first, until the change is also located
in :data:`POWER` of simulated checks."""

GLOBAL_WEIGHT = 0.5
"""The global test's share of the level in the weighted min-p rule; the candidates' score
tests share the rest equally."""


def upper_quantile(p_value: float, dof: int) -> float:
    """The χ²_dof value exceeded with probability ``p_value`` (accurate for tiny p)."""
    return float(2.0 * scipy.special.gammainccinv(0.5 * dof, p_value))


@dataclass(frozen=True)
class DriftTests:
    """The tests of drift on a set of poses (:class:`DriftModel`): the global χ² test and the
    located change; ``global_p`` and ``candidate_p`` the critical p-values of the global test
    and of each candidate's score test."""

    global_test: GlobalTest
    located: LocatedDrift
    global_p: float
    candidate_p: float

    @property
    def drifted(self) -> bool:
        return self.global_test.rejects or self.located.best is not None

    def why(self) -> str:
        """Which test rejected, in words."""
        parts = []
        g = self.global_test
        if g.rejects:
            parts.append(f"Σ d² = {g.statistic:.1f} above its χ²_{g.dof} limit {g.threshold:.1f}")
        if self.located.best is not None:
            best = self.located.best
            parts.append(
                f"a {best.candidate.name} change is significant "
                f"(family-wise p = {best.adjusted:.2g})"
            )
        return " and ".join(parts)


def nested_pairs(bases: tuple[FloatArray, ...]) -> dict[int, list[int]]:
    """Outer candidate index -> the candidates nested in it (:func:`nested_in`), from their
    orthonormal ``bases`` (ν, rank)."""
    pairs: dict[int, list[int]] = {}
    for i, inner in enumerate(bases):
        for j, outer in enumerate(bases):
            if inner.shape[1] < outer.shape[1] and all(
                reproduced_share(column, outer) >= NESTED_SHARE for column in inner.T
            ):
                pairs.setdefault(j, []).append(i)
    return pairs


@dataclass(frozen=True)
class DriftModel:
    """The drift tests at a set of poses, before any residual is seen: the global χ² test and
    the score test of every candidate change, family-wise at ``level`` by the weighted min-p
    rule. Test t (the global one first) rejects when its p-value is below ``w_t c``; ``c`` is
    set so that some test rejects with probability ``level`` when nothing changed, by Monte
    Carlo over whitened residuals z ~ N(0, I) (every statistic is a quadratic form of the same
    z, so their joint distribution is known exactly), which makes the false-alarm rate the
    level, not below it as Bonferroni over correlated tests would. ``null`` (draws, T): the
    statistics of the draws; ``ranks``, ``weights`` (T,)."""

    covariance: FloatArray
    white: FloatArray
    candidates: tuple[Candidate, ...]
    ranks: IntArray
    weights: FloatArray
    null: FloatArray
    critical: float
    bases: tuple[FloatArray, ...] = ()
    """Each candidate's orthonormal basis (ν, rank) of its whitened columns."""
    nested: dict[int, list[int]] = dataclasses.field(default_factory=dict)
    """Outer candidate index -> the candidates nested in it (:func:`nested_pairs`)."""

    @classmethod
    def build(cls, covariance: FloatArray, candidates: list[Candidate], level: float) -> DriftModel:
        """The model at the poses of ``covariance`` (n·d, n·d) and ``candidates``."""
        white = whitening(covariance)
        dof = white.shape[0]
        z = np.random.default_rng(NULL_SEED).standard_normal((NULL_DRAWS, dof))
        statistics, ranks, bases = [np.sum(z**2, axis=1)], [dof], []
        for candidate in candidates:
            n, d, m = candidate.jacobian.shape
            basis = score_test(np.zeros(dof), white @ candidate.jacobian.reshape(n * d, m)).basis
            statistics.append(np.sum((z @ basis) ** 2, axis=1))
            ranks.append(basis.shape[1])
            bases.append(basis)
        own = (1.0 - GLOBAL_WEIGHT) / max(len(candidates), 1)
        weights = np.r_[GLOBAL_WEIGHT, np.full(len(candidates), own)]
        model = cls(
            covariance,
            white,
            tuple(candidates),
            np.array(ranks),
            weights,
            np.stack(statistics, axis=1),
            0.0,
            tuple(bases),
        )
        return dataclasses.replace(
            model, critical=model.solve_critical(level), nested=nested_pairs(model.bases)
        )

    def thresholds(self, critical: float) -> FloatArray:
        """Each test's statistic threshold (T,) at ``critical``: its χ² upper quantile at
        ``w_t · critical`` (inf for a test of no dimension); one quantile per distinct
        (rank, weight)."""
        pairs = np.stack([self.ranks, self.weights], axis=1)
        unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
        values = np.array(
            [upper_quantile(min(w * critical, 1.0), int(r)) if r > 0 else np.inf for r, w in unique]
        )
        return np.asarray(values[np.ravel(inverse)], dtype=float)

    def false_alarm(self, critical: float) -> float:
        """The share of null draws in which some test rejects at ``critical``."""
        return float(np.mean(np.any(self.null > self.thresholds(critical), axis=1)))

    def solve_critical(self, level: float) -> float:
        """``c`` with :meth:`false_alarm` = ``level`` (bisection on log c: between level·w_max
        and level/w_min lie Bonferroni's and a single test's)."""
        low, high = np.log(level * 1e-3), np.log(level / float(self.weights.min()))
        for _ in range(30):  # to 1e-7 of log c: well inside the Monte Carlo error
            middle = 0.5 * (low + high)
            if self.false_alarm(float(np.exp(middle))) > level:
                high = middle
            else:
                low = middle
        return float(np.exp(low))

    @property
    def global_p(self) -> float:
        return float(self.weights[0] * self.critical)

    @property
    def candidate_p(self) -> float:
        return float(self.weights[-1] * self.critical) if self.weights.size > 1 else 0.0

    def adjusted(self, p_value: float, weight: float) -> float:
        """The family-wise p-value of a test with this p-value and weight: the null share in
        which some test rejects at the ``c`` that just rejects it; below the Monte Carlo's
        resolution (no draw rejects), the weighted Bonferroni bound ``p / w``, never smaller."""
        share = self.false_alarm(p_value / weight)
        return max(share, p_value) if share > 0.0 else min(1.0, p_value / weight)

    @functools.cached_property
    def locate_noise(self) -> FloatArray:
        """The whitened noise (:data:`LOCATE_DRAWS`, ν) of every simulated check of
        :meth:`simulated_rates`, which adds its change to it (a fixed seed: drawn once)."""
        rng = np.random.default_rng(NULL_SEED + 1)
        return rng.standard_normal((LOCATE_DRAWS, self.white.shape[0]))

    def simulated_rates(self, pattern: FloatArray, target: int) -> tuple[float, float]:
        """Shares of :data:`LOCATE_DRAWS` simulated checks with the whitened change ``pattern``
        (ν,) in which the check detects drift and in which it locates candidate ``target``
        (its index), with the rules of :func:`locate_drift` (smallest p-value among the
        significant; a nested simpler candidate unless the extra components are significant),
        under the linearised model."""
        z = pattern + self.locate_noise
        statistics = np.stack(
            [np.sum(z**2, axis=1)] + [np.sum((z @ b) ** 2, axis=1) for b in self.bases], axis=1
        )
        rejects = statistics > self.thresholds(self.critical)
        detected = np.any(rejects, axis=1)
        scores = statistics[:, 1:]
        ranks = self.ranks[1:]
        significant = rejects[:, 1:]
        masked = np.full(scores.shape, np.inf)  # log p of the significant tests only
        for rank in np.unique(ranks):  # one call per degree of freedom
            tests = np.flatnonzero(ranks == rank)
            hit = significant[:, tests]
            if np.any(hit):
                block = masked[:, tests]
                block[hit] = chi2_log_survivals(scores[:, tests][hit], int(rank))
                masked[:, tests] = block
        log_p = masked
        best = np.argmin(masked, axis=1)
        any_significant = np.any(significant, axis=1)
        for outer, inners in self.nested.items():
            at = np.flatnonzero(any_significant & (best == outer))
            if at.size == 0:
                continue
            choice = np.full(at.size, -1)
            choice_log_p = np.full(at.size, np.inf)
            for inner in inners:
                extra = scores[at, outer] - scores[at, inner]
                keep = significant[at, inner] & (
                    scipy.special.gammaincc(0.5 * (ranks[outer] - ranks[inner]), 0.5 * extra)
                    > NESTED_LEVEL
                )
                better = keep & (log_p[at, inner] < choice_log_p)
                choice = np.where(better, inner, choice)
                choice_log_p = np.where(better, log_p[at, inner], choice_log_p)
            best[at] = np.where(choice >= 0, choice, best[at])
        located = any_significant & (best == target)
        return float(np.mean(detected)), float(np.mean(located))

    def tests(self, residuals: FloatArray) -> DriftTests:
        """:class:`DriftTests` of ``residuals`` (n, d) at these poses. A candidate's
        family-wise p-value is exact near significance; further off it is the weighted
        Bonferroni bound ``p / w`` (capped at 1), which is never below it."""
        tests = score_tests(self.white, residuals, list(self.candidates))
        own = float(self.weights[-1]) if self.weights.size > 1 else 1.0
        significant = self.candidate_p
        tests = [
            dataclasses.replace(
                t,
                adjusted=self.adjusted(t.p_value, own)
                if t.p_value <= 10.0 * significant
                else min(1.0, t.p_value * self.critical / significant),
            )
            for t in tests
        ]
        return DriftTests(
            global_test(residuals.ravel(), self.covariance, self.global_p),
            locate_drift(tests, significant),
            self.global_p,
            significant,
        )


def drift_tests(
    residuals: FloatArray, covariance: FloatArray, candidates: list[Candidate], level: float
) -> DriftTests:
    """:class:`DriftTests` of ``residuals`` (n, d) with joint covariance (n·d, n·d) and the
    ``candidates`` at those poses, family-wise at ``level`` (:class:`DriftModel`)."""
    return DriftModel.build(covariance, candidates, level).tests(residuals)


# --- the verdict ---------------------------------------------------------------------------


def subset_candidates(candidates: list[Candidate], rows: IntArray) -> list[Candidate]:
    """The candidates at the poses ``rows`` only."""
    return [Candidate(c.name, c.kind, c.components, c.units, c.jacobian[rows]) for c in candidates]


@dataclass(frozen=True)
class PoseTests:
    """The check's tests on n poses: ``d2`` (n,) per pose, ``threshold`` the max-type (Šidák)
    quantile over all n poses, ``bad_samples`` indices of poses far off (above it) set aside
    (re-measure them), ``used`` the indices the verdict is on, ``drift`` the tests on those,
    ``verdict`` "holds", "drifted" or "inconclusive" and ``reason`` one line saying why."""

    d2: FloatArray
    threshold: float
    bad_samples: IntArray
    used: IntArray
    drift: DriftTests | None
    verdict: str
    reason: str
    model: DriftModel | None = None
    """The drift model of the poses used (for the stated sizes)."""


def max_bad_samples(n: int) -> int:
    """At most this many far-off poses of n are set aside as bad samples (a fifth, at least
    one); more, and the calibration, not the samples, is in doubt."""
    return max(1, n // 5)


EXPLAIN_LEVEL = 0.05
"""The change that would explain far-off poses must be seen in the other poses at this level
(a change they do not show predicts anything within its wide uncertainty)."""


def explained_by_change(
    residuals: FloatArray,
    covariance: FloatArray,
    whole: DriftTests,
    far: IntArray,
    threshold: float,
) -> bool:
    """Whether the far poses ``far`` are a drift that shows most on them rather than bad
    samples: the change located on every pose (``whole``), estimated from the other poses
    alone, is seen in them (its score test there at :data:`EXPLAIN_LEVEL`) and predicts the
    far poses to within ``threshold`` (their d² under their covariance plus that estimate's).
    A bad sample stays far: the others do not carry its error."""
    best = whole.located.best
    if best is None:
        return False
    n, d = residuals.shape
    rest = np.setdiff1d(np.arange(n), far)
    candidate = subset_candidates([best.candidate], rest)[0]
    rest_covariance = subset_covariance(covariance, rest, d)
    white = whitening(rest_covariance)
    m = candidate.jacobian.shape[2]
    fit = score_test(
        white @ residuals[rest].ravel(), white @ candidate.jacobian.reshape(rest.size * d, m)
    )
    if fit.p_value > EXPLAIN_LEVEL:  # the others do not show the change: nothing to predict
        return False
    columns = best.candidate.jacobian[far]  # (f, d, m)
    predicted = columns @ fit.estimate
    spread = columns @ fit.covariance @ columns.transpose(0, 2, 1)
    blocks = np.stack([covariance[i * d : (i + 1) * d, i * d : (i + 1) * d] for i in far])
    d2 = mahalanobis_squared(residuals[far] - predicted, blocks + spread)
    return bool(np.all(d2 <= threshold))


def pose_verdict(residuals: FloatArray, model: DriftModel, level: float) -> PoseTests:
    """The verdict on ``residuals`` (n, d) with the drift ``model`` of those poses (its joint
    covariance and candidates).

    Max-type test: a pose whose d² exceeds the Šidák quantile at ``level`` over the n poses is
    far off. When 1..:func:`max_bad_samples` poses are far off and at least :data:`MIN_POSES`
    remain, they are set aside as bad samples and the verdict is taken on the rest by the
    drift tests (:class:`DriftModel`) — unless a change located on every pose explains them (a
    drift that shows most on a few poses); more far-off poses are drift. A calibration that
    holds is called drifted with probability about ``level``."""
    covariance = model.covariance
    n, d = residuals.shape
    d2 = pose_distances_squared(residuals, covariance)
    every = np.arange(n)
    if n < MIN_POSES:
        return PoseTests(
            d2,
            np.inf,
            every[:0],
            every,
            None,
            "inconclusive",
            f"{n} check pose(s): at least {MIN_POSES} are needed",
        )
    threshold = sidak_quantile(level, n, d)
    far = every[~(d2 <= threshold)]
    if far.size == 0 or far.size > max_bad_samples(n) or n - far.size < MIN_POSES:
        tests = model.tests(residuals)
        if far.size:
            why = f"{far.size} of {n} poses with d² above {threshold:.1f} (family-wise, Šidák)"
            return PoseTests(d2, threshold, far[:0], every, tests, "drifted", why, model)
        return _decided(d2, threshold, far, every, tests, "", model)
    poses = ", ".join(str(i + 1) for i in far)
    whole = model.tests(residuals)
    if explained_by_change(residuals, covariance, whole, far, threshold):
        why = f"pose(s) {poses} far off, as a located change explains; "
        return _decided(d2, threshold, far[:0], every, whole, why, model)
    used = np.setdiff1d(every, far)
    rest_model = DriftModel.build(
        subset_covariance(covariance, used, d),
        subset_candidates(list(model.candidates), used),
        level,
    )
    rest = rest_model.tests(residuals[used])
    named = f"pose(s) {poses} far off (d² above {threshold:.1f}), set aside as bad samples; "
    return _decided(d2, threshold, far, used, rest, named, rest_model)


def _decided(
    d2: FloatArray,
    threshold: float,
    far: IntArray,
    used: IntArray,
    tests: DriftTests,
    prefix: str,
    model: DriftModel,
) -> PoseTests:
    if tests.drifted:
        return PoseTests(d2, threshold, far, used, tests, "drifted", prefix + tests.why(), model)
    g = tests.global_test
    agree = (
        f"Σ d² = {g.statistic:.1f} of {used.size} poses below its χ²_{g.dof} limit "
        f"{g.threshold:.1f} and no candidate change significant"
    )
    return PoseTests(d2, threshold, far, used, tests, "holds", prefix + agree, model)


# --- stated power --------------------------------------------------------------------------


def detectable_noncentrality(dof: int, level: float, power: float = POWER) -> float:
    """λ with ``P(χ²_dof(λ) > χ²⁻¹_dof(1 − level)) = power``: the non-centrality a test at
    ``level`` on ``dof`` degrees of freedom detects with probability ``power``."""
    threshold = chi2_quantile(1.0 - level, dof)
    return float(scipy.special.chndtrinc(threshold, dof, 1.0 - power))


def detectable_size(whitened_columns: FloatArray, noncentrality: float) -> float:
    """The smallest size ‖δ‖ (the columns' unit) of a change along the worst direction in the
    span of ``whitened_columns`` (ν, m) with ``‖Ã δ‖² = noncentrality``:
    ``sqrt(λ / σ_min(Ã)²)``; inf when some direction does not move the residuals."""
    smallest = float(np.linalg.svd(whitened_columns, compute_uv=False).min())
    return float(np.sqrt(noncentrality) / smallest) if smallest > 0.0 else float("inf")


@dataclass(frozen=True)
class StatedSize:
    """A change the check detects and locates with probability :data:`POWER`: ``name``
    ("panda_joint3 offset", "base translation", ...), ``size`` in ``unit`` along the worst
    direction (any direction of that size or more is detected); ``located`` False when even
    :data:`SIZE_STEPS`' largest multiple of the detectable size is located less often (the
    size then promises detection only)."""

    name: str
    size: float
    unit: str
    located: bool = True


def stated_sizes(model: DriftModel) -> list[StatedSize]:
    """The smallest joint-offset, base and tool changes (translation and rotation separately)
    that the check at the poses of ``model`` detects and locates with probability
    :data:`POWER`. Detection: the smaller of the sizes the global test and the candidate's own
    score test, each at its critical p-value, detect with that probability (non-central χ²;
    either rejecting is drift, so the check detects it at least as often). Location: the first
    multiple of it (:data:`SIZE_STEPS`) at which :meth:`DriftModel.simulated_rates` locates the
    candidate in :data:`LOCATE_TARGET` of simulated checks (a change along the worst
    direction)."""
    overall = detectable_noncentrality(model.white.shape[0], model.global_p)
    sizes = []
    for index, candidate in enumerate(model.candidates):
        if candidate.kind not in SIZED_KINDS:
            continue
        n, d, m = candidate.jacobian.shape
        columns = model.white @ candidate.jacobian.reshape(n * d, m)
        rank = int(model.ranks[index + 1])
        noncentrality = min(overall, detectable_noncentrality(rank, model.candidate_p))
        for name, axes, unit in size_parts(candidate):
            detectable = detectable_size(columns[:, axes], noncentrality)
            if not np.isfinite(detectable):
                sizes.append(StatedSize(name, detectable, unit, False))
                continue
            pattern = columns[:, axes] @ worst_direction(columns[:, axes])
            size, located = detectable * SIZE_STEPS[-1], False
            for step in SIZE_STEPS:
                _, rate = model.simulated_rates(pattern * detectable * step, index)
                if rate >= LOCATE_TARGET:
                    size, located = detectable * step, True
                    break
            sizes.append(StatedSize(name, size if located else detectable, unit, located))
    return sizes


SIZED_KINDS = ("joint_offset", "base", "tool")
"""The kinds of candidate change a check states sizes of."""


def size_parts(candidate: Candidate) -> list[tuple[str, slice, str]]:
    """The parts of a candidate a size is stated for: (name, its columns, unit): a joint's
    offset whole; a frame's translation (m) and rotation (rad) separately."""
    if candidate.kind == "joint_offset":
        return [(candidate.name, slice(0, 1), candidate.units[0])]
    return [
        (f"{candidate.kind} translation", slice(0, 3), "m"),
        (f"{candidate.kind} rotation", slice(3, 6), "rad"),
    ]


def worst_direction(whitened_columns: FloatArray) -> FloatArray:
    """The unit direction (m,) in the span of the columns that moves the whitened residuals
    least (the right singular vector of the smallest singular value)."""
    return np.asarray(np.linalg.svd(whitened_columns)[2][-1], dtype=float)
