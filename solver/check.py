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

- per pose: ``d²_n = r_nᵀ Σ_nn⁻¹ r_n`` ~ χ²_d; the max-type test rejects when
  ``max d²_n`` exceeds the Šidák quantile ``χ²_d⁻¹((1 − α_max)^(1/n))``;
- global: ``T = rᵀ Σ⁻¹ r`` ~ χ²_{rank Σ}; rejects above ``χ²⁻¹(1 − α_global)``;
- score test of a candidate: with ``z = W r``, ``à = W A`` (W the whitening of Σ),
  ``S = ‖P_à z‖²`` ~ χ²_{rank Ã} under no change; Bonferroni over the candidates;
- stated power: under a change δ, ``T`` is non-central χ² with ``λ = ‖Ã δ‖²``; the smallest
  size detected with probability ``power`` solves ``P(χ²_ν(λ) > χ²⁻¹_ν(1 − α)) = power``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.special
from numpy.typing import NDArray

from solver import lie
from solver.predictive import chi2_quantile, mahalanobis_squared

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

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


def chi2_survival(statistic: float, dof: int) -> float:
    """``P(χ²_dof > statistic)`` (scipy.special, not scipy.stats: see
    :func:`solver.predictive.chi2_quantile`)."""
    if dof <= 0:
        return 1.0
    return float(scipy.special.gammaincc(0.5 * dof, 0.5 * max(statistic, 0.0)))


def chi2_log_survival(statistic: float, dof: int) -> float:
    """``log P(χ²_dof > statistic)``, finite where the p-value underflows (the leading term of
    the upper incomplete gamma function's asymptotic series, ``Γ(a, x) ≈ x^(a−1) e^(−x)``,
    a = dof/2, x = statistic/2): ranks candidates of different dimensions by their p-values."""
    p_value = chi2_survival(statistic, dof)
    if p_value > 1e-300:
        return float(np.log(p_value))
    a, x = 0.5 * dof, 0.5 * statistic
    return float((a - 1.0) * np.log(x) - x - scipy.special.gammaln(a))


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


# --- the verdict ---------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseTests:
    """The check's tests on n poses: ``d2`` (n,) per pose, ``threshold`` the max-type (Šidák)
    quantile over all n poses, ``bad_samples`` indices of poses far off while the rest agree
    (re-measure them; the verdict is taken on the rest), ``used`` the indices the verdict is
    on, ``global_test`` on those, ``verdict`` "holds", "drifted" or "inconclusive" and
    ``reason`` one line saying why."""

    d2: FloatArray
    threshold: float
    bad_samples: IntArray
    used: IntArray
    global_test: GlobalTest | None
    verdict: str
    reason: str


def max_bad_samples(n: int) -> int:
    """At most this many far-off poses of n are bad samples (a fifth, at least one); more,
    and the calibration, not the samples, is in doubt."""
    return max(1, n // 5)


def pose_verdict(residuals: FloatArray, covariance: FloatArray, level: float) -> PoseTests:
    """The verdict on ``residuals`` (n, d) with joint covariance (n·d, n·d): the global test
    and the max-type test (family-wise over the poses, Šidák), each at ``level``.

    Bad-sample rule: when 1..:func:`max_bad_samples` poses exceed the max-type threshold and
    the others pass both tests (at their own count), those poses are named bad samples and the
    calibration holds on the rest. A calibration that holds is therefore called drifted with
    probability about ``level`` (the global test's; the max-type test's alarms on clean poses
    are mostly named bad samples, with probability at most ``level``)."""
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
    whole = global_test(residuals.ravel(), covariance, level)
    if far.size == 0 and not whole.rejects:
        return PoseTests(
            d2,
            threshold,
            far,
            every,
            whole,
            "holds",
            f"Σ d² = {whole.statistic:.1f} below its χ²_{whole.dof} limit {whole.threshold:.1f} "
            f"and every pose's d² below {threshold:.1f}",
        )
    if 0 < far.size <= max_bad_samples(n) and n - far.size >= MIN_POSES:
        rest = np.setdiff1d(every, far)
        rest_test = global_test(
            residuals[rest].ravel(), subset_covariance(covariance, rest, d), level
        )
        rest_max = sidak_quantile(level, rest.size, d)
        if not rest_test.rejects and bool(np.all(d2[rest] <= rest_max)):
            named = ", ".join(str(i + 1) for i in far)
            return PoseTests(
                d2,
                threshold,
                far,
                rest,
                rest_test,
                "holds",
                f"pose(s) {named} far off (d² above {threshold:.1f}) while the other "
                f"{rest.size} agree (Σ d² = {rest_test.statistic:.1f} below "
                f"{rest_test.threshold:.1f}): bad sample(s), re-measure them",
            )
    if whole.rejects:
        why = (
            f"Σ d² = {whole.statistic:.1f} above its χ²_{whole.dof} limit "
            f"{whole.threshold:.1f} (p = {whole.p_value:.2g})"
        )
    else:
        why = f"{far.size} pose(s) with d² above {threshold:.1f} (family-wise, Šidák)"
    return PoseTests(d2, threshold, far[:0], every, whole, "drifted", why)


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
    frame_jacobians: FloatArray,
    joint_screws: FloatArray,
    nominal_first_link: FloatArray,
    joint_positions: FloatArray,
    joint_names: tuple[str, ...],
    revolute: NDArray[np.bool_],
) -> list[Candidate]:
    """The candidate changes at the check poses: each joint's offset and scale, the base frame
    (robot base in the measurement frame, 6), the tool or marker frame (its pose in the tip
    frame, 6) and each inner link's geometry (L_2..L_k, 6 each). ``joint_positions`` (n, k)
    the configurations (rad or m) the Jacobians were taken at."""
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
    no change, ``p_value`` and ``adjusted`` (Bonferroni over the candidates), ``estimate`` δ̂
    (m,) in the candidate's units and ``covariance`` (m, m) of it, ``fitted`` the whitened
    pattern Ã δ̂ (ν,)."""

    candidate: Candidate
    statistic: float
    dof: int
    p_value: float
    adjusted: float
    estimate: FloatArray
    covariance: FloatArray
    fitted: FloatArray

    @property
    def log_p_value(self) -> float:
        return chi2_log_survival(self.statistic, self.dof)

    def interval95(self) -> tuple[FloatArray, FloatArray]:
        """95 % intervals (m,) of each component: δ̂ ∓ 1.96 σ."""
        half = 1.959963984540054 * np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return self.estimate - half, self.estimate + half


def score_test(
    whitened_residuals: FloatArray, whitened_columns: FloatArray
) -> tuple[float, int, FloatArray, FloatArray, FloatArray]:
    """Score (= likelihood-ratio, the model being linear) test of a change along the columns
    ``Ã`` (ν, m) for whitened residuals ``z`` (ν,): ``δ̂ = Ã⁺ z``, ``Cov(δ̂) = (ÃᵀÃ)⁺``,
    ``S = ‖Ã δ̂‖²`` with ``rank Ã`` degrees of freedom. Returns (S, dof, δ̂, Cov(δ̂), Ã δ̂)."""
    norms = np.linalg.norm(whitened_columns, axis=0)
    norms = np.where(norms > 0.0, norms, 1.0)
    scaled = whitened_columns / norms
    u, s, vt = np.linalg.svd(scaled, full_matrices=False)
    keep = s > 1e-8 * max(float(s.max()), 1e-300)
    coefficients = (vt[keep].T / s[keep]) @ (u[:, keep].T @ whitened_residuals)
    estimate = coefficients / norms
    inverse_gram = (vt[keep].T / s[keep] ** 2) @ vt[keep]
    covariance = inverse_gram / np.outer(norms, norms)
    fitted = u[:, keep] @ (u[:, keep].T @ whitened_residuals)
    return float(fitted @ fitted), int(keep.sum()), estimate, covariance, fitted


def score_tests(
    residuals: FloatArray, covariance: FloatArray, candidates: list[Candidate]
) -> list[ScoreTest]:
    """Every candidate's :func:`score_test` on ``residuals`` (n, d) with joint covariance
    (n·d, n·d), Bonferroni-adjusted over the candidates, best first (by the log of their
    p-value, so candidates of different dimensions compare fairly)."""
    white = whitening(covariance)
    z = white @ residuals.ravel()
    tests = []
    for candidate in candidates:
        n, d, m = candidate.jacobian.shape
        columns = white @ candidate.jacobian.reshape(n * d, m)
        statistic, dof, estimate, cov, fitted = score_test(z, columns)
        p_value = chi2_survival(statistic, dof)
        tests.append(
            ScoreTest(
                candidate,
                statistic,
                dof,
                p_value,
                min(1.0, p_value * len(candidates)),
                estimate,
                cov,
                fitted,
            )
        )
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


@dataclass(frozen=True)
class LocatedDrift:
    """The drift located: ``best`` the most significant candidate (None: none is significant
    at the level, family-wise), ``alternatives`` other significant candidates of no more
    components that reproduce ≥ :data:`INDISTINCT_COS2` of its pattern (the check poses cannot
    tell them apart), ``tests`` every candidate's score test, best first."""

    best: ScoreTest | None
    alternatives: tuple[ScoreTest, ...]
    tests: tuple[ScoreTest, ...]


def locate_drift(
    residuals: FloatArray, covariance: FloatArray, candidates: list[Candidate], level: float
) -> LocatedDrift:
    """Score tests of ``candidates`` at the poses (``residuals`` (n, d), joint covariance
    (n·d, n·d)) with family-wise control at ``level`` (Bonferroni), the best named with the
    candidates it cannot be told apart from."""
    tests = score_tests(residuals, covariance, candidates)
    significant = [t for t in tests if t.adjusted <= level]
    if not significant:
        return LocatedDrift(None, (), tuple(tests))
    best = significant[0]
    white = whitening(covariance)
    alternatives = []
    for other in significant[1:]:
        n, d, m = other.candidate.jacobian.shape
        if other.dof > best.dof:
            continue
        columns = white @ other.candidate.jacobian.reshape(n * d, m)
        if reproduced_share(best.fitted, columns) >= INDISTINCT_COS2:
            alternatives.append(other)
    return LocatedDrift(best, tuple(alternatives), tuple(tests))


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
    """A change the check detects with probability :data:`POWER` (global test at its level):
    ``name`` ("panda_joint3 offset", "base translation", ...), ``size`` in ``unit`` along the
    worst direction (any direction of that size or more is detected)."""

    name: str
    size: float
    unit: str


def stated_sizes(
    covariance: FloatArray, candidates: list[Candidate], level: float
) -> list[StatedSize]:
    """The smallest joint-offset, base and tool changes (translation and rotation separately)
    that the global test at ``level`` detects with probability :data:`POWER` at these poses."""
    white = whitening(covariance)
    noncentrality = detectable_noncentrality(white.shape[0], level)
    sizes = []
    for candidate in candidates:
        n, d, m = candidate.jacobian.shape
        columns = white @ candidate.jacobian.reshape(n * d, m)
        if candidate.kind == "joint_offset":
            sizes.append(
                StatedSize(
                    candidate.name, detectable_size(columns, noncentrality), candidate.units[0]
                )
            )
        elif candidate.kind in ("base", "tool"):
            sizes.append(
                StatedSize(
                    f"{candidate.kind} translation",
                    detectable_size(columns[:, :3], noncentrality),
                    "m",
                )
            )
            sizes.append(
                StatedSize(
                    f"{candidate.kind} rotation",
                    detectable_size(columns[:, 3:], noncentrality),
                    "rad",
                )
            )
    return sizes


def worst_direction(whitened_columns: FloatArray) -> FloatArray:
    """The unit direction (m,) in the span of the columns that moves the whitened residuals
    least (the right singular vector of the smallest singular value)."""
    return np.asarray(np.linalg.svd(whitened_columns)[2][-1], dtype=float)
