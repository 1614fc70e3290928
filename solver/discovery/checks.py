"""Checks beyond the library: lack of fit, unexplained structure, random-looking effects.

All are score tests (:mod:`solver.discovery.scoring`) of *generic* columns against the fitted
model, so their size is known:

* **axis functions** — a deflection about joint j's axis that is a smooth function of one
  variable (Legendre polynomials and harmonics of q_j, or polynomials of τ_j). The library's
  angle terms (scale, harmonics 1..3) and load terms (spring, load-sign backlash) are special
  cases; what the generic basis explains *beyond* them is structure no library term describes.
* **component functions** — each residual component as a smooth function of one variable
  (joint angle, acquisition time, measured range): structure of any direction.
* **floating deflection** — residual scatter about joint j's axis that grows where its load is
  near zero (backlash with nothing to take it up): a permutation test on the squared
  per-sample deflection estimates. Random, so it belongs to the covariance calibration.

* **clustered outliers** — the samples screened out as gross outliers, if they sit in a narrow
  range of one joint's angle (or of acquisition time): a local effect (a damaged gear tooth, a
  bumped camera) that the screening would otherwise hide. Exact test on the span of their
  ranks; real gross outliers fall at random rows and do not cluster.

Distance correlation (bias-corrected, Székely & Rizzo 2014) of the whitened residual vectors
with each joint angle is reported alongside, as a model-free effect size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.special

from solver.arrays import FloatArray, IntArray
from solver.discovery.features import angle_basis, legendre_basis, load_basis
from solver.discovery.fitting import (
    Context,
    ModelFit,
    evaluate,
    orthonormal_basis,
    slices,
    whitened,
)
from solver.discovery.library import Term
from solver.discovery.scoring import NullModel, ScoreTest, holm, score_test, score_tests

COMPONENT_DEGREES = range(1, 4)


@dataclass(frozen=True)
class StructureTest:
    """A generic-basis test: which variable, about which joint, how strong."""

    kind: str  # "angle", "load", "components", "time", "range"
    joint_index: int | None
    p_value: float
    explained_fraction: float  # of the whitened residual sum of squares
    distance_correlation: float | None = None


def unit_columns(ctx: Context, fit: ModelFit) -> dict[int, FloatArray]:
    """Column per unit rotation about every revolute joint's axis at the fit, (n, d) each."""
    joints = tuple((int(j), "joint") for j in np.flatnonzero(ctx.chain.is_revolute()))
    design = evaluate(ctx, fit.terms, fit.params, fit.rows, unit_axes=joints)
    return {j: design.unit[(j, "joint")] for j, _ in joints}


def axis_function_columns(unit: FloatArray, basis: FloatArray, weights: FloatArray) -> FloatArray:
    """Whitened columns (n·d, nb): rotation about an axis by ``basis`` (n, nb) per unit."""
    cols = unit[:, :, None] * basis[:, None, :]
    return whitened(cols, weights).reshape(-1, basis.shape[1])


def component_columns(basis: FloatArray, d: int) -> FloatArray:
    """Columns (n·d, d·nb): each residual component as a function ``basis`` (n, nb)."""
    n, nb = basis.shape
    out = np.zeros((n, d, d, nb))
    for c in range(d):
        out[:, c, c, :] = basis
    return out.reshape(n * d, d * nb)


def with_columns(null: NullModel, columns: FloatArray) -> NullModel:
    """The null model after also fitting ``columns`` (linearised)."""
    basis = orthonormal_basis(np.hstack([null.basis, columns]))
    residual = null.residual - basis @ (basis.T @ null.residual)
    return NullModel(residual, basis, null.d, null.flip_seed)


def reweighted(
    fit: ModelFit, extra: list[FloatArray], blocks: list[slice | list[int]]
) -> tuple[NullModel, FloatArray]:
    """Null model (fit's Jacobian only) whitened with the noise the alternative leaves.

    The fit's noise scale still contains whatever the model misses, and the mix of
    translation and rotation rows with it; re-estimating it per block from the residual of the
    linearised fit with the ``extra`` columns too gives the test its power where the signal is.
    ``blocks``: the residual rows sharing a noise scale (``DiscoveryData.noise_blocks``).
    Returns the null model and the row scale (R,) to apply to any further columns.
    """
    d = fit.design.residual.shape[1]
    stacked = np.hstack([fit.jacobian, *extra])
    basis = orthonormal_basis(stacked)
    residual = fit.residual_w - basis @ (basis.T @ fit.residual_w)
    leverage = np.sum(basis**2, axis=1)
    factor = np.ones(d)
    e2 = (residual**2).reshape(-1, d)
    room = (1.0 - leverage).reshape(-1, d)
    for b in blocks:
        factor[b] = 1.0 / np.sqrt(max(float(e2[:, b].sum() / max(room[:, b].sum(), 1.0)), 1e-30))
    scale = np.tile(factor, fit.residual_w.size // d)
    a = fit.jacobian * scale[:, None]
    model_basis = orthonormal_basis(a)
    r = fit.residual_w * scale
    return NullModel(r - model_basis @ (model_basis.T @ r), model_basis, d), scale


def absorbed_in_fit(fit: ModelFit, term: Term) -> float:
    """Share of ``term``'s fitted signature (its whitened columns times its fitted
    coefficients, (R,)) that the rest of ``fit``'s model — geometry, measurement unknowns,
    other terms — reproduces, at the fit's own parameters.

    The model before the term is the other point where this share is judged (the score
    test's ``absorbed_fraction``): there a missing effect has bent the geometry to take up
    what it can, and the geometry's columns move with it (``DiscoveryOptions.absorbed_limit``).
    """
    index = fit.terms.index(term)
    part = slices(fit.terms)[index]
    first = fit.n_nuisance + part.start
    columns = fit.jacobian[:, first : first + term.size]
    rest = np.delete(fit.jacobian, np.arange(first, first + term.size), axis=1)
    value = np.asarray(fit.values()[term.key], dtype=float)
    signature = columns @ value if np.any(value) else columns[:, 0]
    basis = orthonormal_basis(rest)
    left = signature - basis @ (basis.T @ signature)
    share = 1.0 - float(left @ left) / max(float(signature @ signature), 1e-300)
    return float(np.clip(share, 0.0, 1.0))


def conditional_test(
    fit: ModelFit,
    first: FloatArray,
    second: FloatArray,
    blocks: list[slice | list[int]],
    certify_below: float | None = None,
) -> ScoreTest | None:
    """Score test of candidate columns ``first`` with ``second`` in the model as well (both
    whitened, (R, ·)); the noise scale is re-estimated with both fitted (:func:`reweighted`).
    None when ``second`` (and the model) absorb ``first`` entirely. ``certify_below``: as
    :func:`~solver.discovery.scoring.score_test`."""
    base, scale = reweighted(fit, [first, second], blocks)
    given = with_columns(base, second * scale[:, None])
    return score_test(given, "conditional", first * scale[:, None], certify_below)


def lack_of_fit(
    ctx: Context,
    fit: ModelFit,
    term: Term,
    units: dict[int, FloatArray],
    certify_below: float | None = None,
) -> ScoreTest | None:
    """Does joint j need more than the whole library family of ``term`` (angle or load)?

    Tests the extra generic basis about joint j's axis given the model *and* every library
    column of that family on joint j, so two genuine library effects on one joint (e.g.
    harmonics 1 and 2) do not count as a misfit. The noise scale is re-estimated under the
    alternative (:func:`reweighted`). ``certify_below``: as
    :func:`~solver.discovery.scoring.score_test`.
    """
    j = term.joint_index
    if j is None or j not in units or term.family not in ("angle", "load"):
        return None
    rows = fit.rows
    unit = units[j]
    if term.family == "angle":
        q = ctx.data.joint_positions[rows, j]
        family = angle_basis(q, library=True, extra=False)
        extra = angle_basis(q, library=False, extra=True)
    else:
        tau = ctx.bank.nominal_tau(ctx.chain.joint_names[j])[rows]
        family = load_basis(tau, library=True, extra=False)
        extra = load_basis(tau, library=False, extra=True)
    family_cols = axis_function_columns(unit, family, fit.weights)
    extra_cols = axis_function_columns(unit, extra, fit.weights)
    base, scale = reweighted(fit, [family_cols, extra_cols], ctx.data.noise_blocks())
    augmented = with_columns(base, family_cols * scale[:, None])
    key = f"lack_of_fit:{term.family}:{j}"
    return score_test(augmented, key, extra_cols * scale[:, None], certify_below)


def residual_structure(
    ctx: Context,
    fit: ModelFit,
    null: NullModel,
    units: dict[int, FloatArray],
    alpha: float,
    skip: set[tuple[str, int]] | None = None,
) -> list[StructureTest]:
    """Generic-basis tests on the final model, Holm-corrected together; significant ones only."""
    rows = fit.rows
    d = null.d
    labels: dict[str, tuple[str, int | None]] = {}
    columns: dict[str, FloatArray] = {}
    whitened_residual = null.residual.reshape(-1, d)
    for j, unit in units.items():
        q = ctx.data.joint_positions[rows, j]
        generic = angle_basis(q, library=True, extra=True)
        candidates = {
            "angle": axis_function_columns(unit, generic, fit.weights),
            "components": component_columns(legendre_basis(q, COMPONENT_DEGREES), d),
        }
        tau = ctx.bank.nominal_tau(ctx.chain.joint_names[j])[rows]
        if np.ptp(tau) > 1e-9:
            basis = load_basis(tau, library=True, extra=True)
            candidates["load"] = axis_function_columns(unit, basis, fit.weights)
        for kind, candidate in candidates.items():
            if skip is None or (kind, j) not in skip:
                labels[f"{kind}:{j}"], columns[f"{kind}:{j}"] = (kind, j), candidate
    clock = ctx.bank.clock[rows]
    ranges = ctx.data.range_m()
    for kind, variable in (("time", clock), ("range", None if ranges is None else ranges[rows])):
        if variable is not None and np.ptp(variable) > 0:
            labels[kind] = (kind, None)
            columns[kind] = component_columns(legendre_basis(variable, range(1, 5)), d)
    tests = {key: (*labels[key], test) for key, test in score_tests(null, columns).items()}
    rejected = holm({k: v[2].p_value for k, v in tests.items()}, alpha)
    rss = float(null.residual @ null.residual)
    out = []
    for key in rejected:
        kind, joint, result = tests[key]
        dcor = None
        if joint is not None:
            dcor = distance_correlation(ctx.data.joint_positions[rows, joint], whitened_residual)
        out.append(StructureTest(kind, joint, result.p_value, result.delta_ss / rss, dcor))
    return sorted(out, key=lambda s: -s.explained_fraction)


@dataclass(frozen=True)
class FloatingTest:
    joint_index: int
    p_value: float
    variance_ratio: float  # scatter near zero load / scatter elsewhere


# A floating joint multiplies the scatter many times (25-400x in the simulated 2 mrad case);
# a chance excess in a group of ~N/10 samples rarely reaches 5x.
MIN_FLOATING_RATIO = 5.0


def floating_deflection(ctx: Context, fit: ModelFit, alpha: float) -> list[FloatingTest]:
    """Joints whose deflection scatter grows where their gravity load is near zero.

    Per sample, the least-squares rotation about the joint axis explaining the whitened
    residual, standardised by its variance under the model: ``e_n = ĝ_nᵀ r_n`` with
    ``Var(e_n) = 1 − |Q_nᵀ ĝ_n|²`` (the fit removes more of high-leverage samples). The samples
    with the 10 % smallest |τ| are compared with the rest: a one-sided Mann–Whitney test on
    ``e_n²`` (ranks: heavy tails and single gross outliers cannot drive it), and the median
    scatter must grow at least :data:`MIN_FLOATING_RATIO`-fold — a floating joint is a large
    effect, a faint trend is not one. Holm over joints.

    Every sample counts, including those screened out as gross outliers: a floating joint
    produces exactly such samples, and where they sit is the evidence.
    """
    rows = ctx.all_rows
    d = ctx.data.rows
    joints = tuple((int(j), "joint") for j in np.flatnonzero(ctx.chain.is_revolute()))
    design = evaluate(ctx, fit.terms, fit.params, rows, unit_axes=joints)
    residual = whitened(design.residual, fit.weights)
    basis = orthonormal_basis(fit.jacobian)
    basis_rows = np.zeros((rows.size, d, basis.shape[1]))
    basis_rows[fit.rows] = basis.reshape(-1, d, basis.shape[1])
    results: dict[str, tuple[int, float, float]] = {}
    for j, _ in joints:
        tau = ctx.bank.nominal_tau(ctx.chain.joint_names[j])
        magnitude = np.abs(tau)
        reference = float(np.quantile(magnitude, 0.1))
        if np.ptp(tau) <= 1e-9 or reference <= 0.0:
            continue
        g = design.unit[(j, "joint")] * fit.weights
        norm = np.linalg.norm(g, axis=1)
        usable = norm > 1e-9 * max(float(norm.max()), 1e-300)
        if usable.sum() < 20:
            continue
        direction = g[usable] / norm[usable, None]
        kept = 1.0 - np.sum(np.einsum("nd,ndr->nr", direction, basis_rows[usable]) ** 2, axis=1)
        e2 = np.einsum("nd,nd->n", direction, residual[usable]) ** 2 / np.clip(kept, 0.05, None)
        near = magnitude[usable] <= reference
        if near.sum() < 5 or (~near).sum() < 5:
            continue
        ratio = float(np.median(e2[near]) / max(float(np.median(e2[~near])), 1e-300))
        p = _scatter_grows_p(e2[near], e2[~near]) if ratio >= MIN_FLOATING_RATIO else 1.0
        results[str(j)] = (j, p, ratio)
    rejected = holm({k: v[1] for k, v in results.items()}, alpha)
    return [FloatingTest(*results[k]) for k in sorted(rejected)]


def _scatter_grows_p(near: FloatArray, far: FloatArray) -> float:
    """One-sided Mann–Whitney p-value that ``near`` (values of e²) lie above ``far``. scipy.stats
    is imported here, when a joint's scatter has grown enough to be tested: importing it costs
    ~0.5 s at the start of every discovery."""
    import scipy.stats

    return float(scipy.stats.mannwhitneyu(near, far, alternative="greater").pvalue)


@dataclass(frozen=True)
class OutlierCluster:
    """Screened-out samples bunched over ``[low, high]`` of one variable: joint
    ``joint_index``'s angle (rad) or gravity torque (N·m), or acquisition time
    (``joint_index`` None; clock units)."""

    joint_index: int | None
    variable: str  # "angle", "load" or "time"
    p_value: float
    n_outliers: int
    low: float
    high: float


# Two samples always span some interval; three or more bunched together are evidence.
MIN_CLUSTERED = 3


def clustered_outliers(ctx: Context, kept_rows: IntArray, alpha: float) -> OutlierCluster | None:
    """Are the samples left out as gross outliers bunched in one joint angle, one joint's
    gravity torque, or in time? The most significant such variable, or None.

    For m outliers among N samples, the statistic is the span s of their ranks in the
    variable (max − min); under random rows its exact law is
    ``P(span ≤ s) = Σ_{t=m−1..s} (N − t) C(t − 1, m − 2) / C(N, m)``. Holm over the variables.
    More than a quarter of the samples screened out is not a local effect: no test.
    """
    n = ctx.data.n_samples
    out = np.setdiff1d(ctx.all_rows, kept_rows)
    m = int(out.size)
    if m < MIN_CLUSTERED or m > n // 4:
        return None
    variables: dict[str, tuple[int | None, str, FloatArray]] = {
        "time": (None, "time", ctx.bank.clock)
    }
    for index in np.flatnonzero(ctx.chain.is_revolute()):
        j = int(index)
        variables[f"angle:{j}"] = (j, "angle", ctx.data.joint_positions[:, j])
        variables[f"load:{j}"] = (j, "load", ctx.bank.nominal_tau(ctx.chain.joint_names[j]))
    tests: dict[str, OutlierCluster] = {}
    for key, (joint, kind, values) in variables.items():
        if np.ptp(values) <= 1e-12 * max(1.0, float(np.abs(values).max())):
            continue
        ranks = np.empty(n, dtype=int)
        ranks[np.argsort(values, kind="stable")] = np.arange(n)
        span = int(ranks[out].max() - ranks[out].min())
        chosen = values[out]
        p = span_p_value(span, m, n)
        tests[key] = OutlierCluster(joint, kind, p, m, float(chosen.min()), float(chosen.max()))
    rejected = holm({k: v.p_value for k, v in tests.items()}, alpha)
    return min((tests[k] for k in rejected), key=lambda c: c.p_value, default=None)


def span_p_value(span: int, m: int, n: int) -> float:
    """P(rank span of m random rows among n ≤ ``span``), exact (log-space sums)."""
    t = np.arange(m - 1, min(span, n - 1) + 1, dtype=float)
    if t.size == 0:
        return 0.0
    log_terms = np.log(n - t) + _log_comb(t - 1.0, m - 2.0) - _log_comb(float(n), float(m))
    return float(min(1.0, np.exp(scipy.special.logsumexp(log_terms))))


def _log_comb(a: FloatArray | float, b: float) -> FloatArray:
    return np.asarray(
        scipy.special.gammaln(np.asarray(a) + 1.0)
        - scipy.special.gammaln(b + 1.0)
        - scipy.special.gammaln(np.asarray(a) - b + 1.0),
        dtype=np.float64,
    )


def distance_correlation(x: FloatArray, y: FloatArray) -> float:
    """Bias-corrected distance correlation of samples x (n,) or (n, p) and y (n, q), in [−1, 1]."""
    a = _u_centred(_distances(x))
    b = _u_centred(_distances(y))
    n = a.shape[0]
    scale = 1.0 / (n * (n - 3))
    ab = float(np.sum(a * b)) * scale
    aa = float(np.sum(a * a)) * scale
    bb = float(np.sum(b * b)) * scale
    if aa <= 0 or bb <= 0:
        return 0.0
    return ab / np.sqrt(aa * bb)


def _distances(x: FloatArray) -> FloatArray:
    points = x.reshape(x.shape[0], -1)
    return np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)


def _u_centred(distances: FloatArray) -> FloatArray:
    n = distances.shape[0]
    row = distances.sum(axis=1, keepdims=True) / (n - 2)
    col = distances.sum(axis=0, keepdims=True) / (n - 2)
    total = distances.sum() / ((n - 1) * (n - 2))
    out = distances - row - col + total
    np.fill_diagonal(out, 0.0)
    return out
