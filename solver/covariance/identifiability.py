"""Identifiability of the covariance entries from the Gram G of Eq. (13–14), in words.

Rank and conditioning are those of the column-equilibrated design B̂ (every variance column
scaled to unit norm, :func:`problem_scaling`): singular values ``s_i = sqrt(eig(Ĝ))``. A direction
is **unidentifiable** if ``s_i < rank_rtol · s_max`` (default 1e-6: the data constrain it a
million times less than the best direction — at double precision G's exact null directions sit
near 1e-8) and **weakly identified** if ``s_i < weak_rtol · s_max`` (default 1e-3).

The words come from the null space, not from a list of expected answers: every frame offers a
dictionary of *atoms* (each entry; equal variance on two axes, "isotropic in a plane"; equal
variance on all three translational or rotational axes, "isotropic"). Two atoms whose effects on
Σ_E agree up to a factor once the null directions are removed form a relation; relations are
merged into classes ("only the sum is identifiable"); null directions no atom pair explains are
listed as explicit linear combinations.

Rule for the unidentifiable part (:func:`resolve_null_space`): among all θ with the same fit
(θ + null direction) the one with minimum norm in equilibrated units is reported, subject to
every Σ_f ⪰ 0. Entries without any effect therefore come out as 0, and interchangeable entries
share their identified sum evenly in equilibrated units.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from solver.arrays import BoolArray, FloatArray
from solver.covariance.layout import (
    POSE_AXES,
    ROTATION_AXES,
    TRANSLATION_AXES,
    CovarianceLayout,
)
from solver.covariance.objective import (
    ProblemScaling,
    clip_psd,
    problem_scaling,
    silent_entries,
)
from solver.covariance.statistics import MomentStatistics

RANK_RTOL = 1e-6
WEAK_RTOL = 1e-3
NULL_SLACK = 1e-10
"""The null-space rule holds every θ at or above its bound to within this (equilibrated units,
relative to the largest entry, at least 1), and sets the entries it leaves within it to the
bound. The null basis comes from an eigendecomposition and is exact only to rounding: held
exactly, two entries at their bound whose rows of the basis cancel to ~1e-15 lock a direction
in which the fit could move by 1e-9 (measured on a 200-pose position recording: the noise's
z variance held at its floor, the frame's z variance carrying twice the even share, depending
on the last bit of the input), so the answer jumped with rounding."""
LDP_FEASIBLE = 1e-12
"""The least-distance program is infeasible when its NNLS residual's last entry is above
−this (exactly 0 in exact arithmetic), or its answer misses a bound by more than this."""


@dataclass(frozen=True)
class Atom:
    """A named direction in θ inside one frame (raw units), e.g. isotropic translation."""

    frame: str
    name: str
    vector: FloatArray
    size: int


@dataclass(frozen=True)
class IdentifiabilityReport:
    """Rank, conditioning and the unidentifiable combinations of θ, by name.

    ``singular_values`` of the equilibrated design (descending); ``null_basis`` (Q, k) and
    ``weak_basis`` (Q, w) are orthonormal in equilibrated units θ̂ = θ / D. ``identifiable``
    (Q,) is False for entries that move along a null direction (their value alone is not
    determined by the data); ``silent`` (Q,) marks entries without any effect. ``statements``
    describe null directions, ``weak_statements`` weakly identified ones; ``warnings`` flag
    noise confusions and constant Jacobians.
    """

    n_params: int
    rank: int
    condition_number: float
    rank_rtol: float
    weak_rtol: float
    singular_values: FloatArray
    null_basis: FloatArray
    weak_basis: FloatArray
    identifiable: BoolArray
    silent: BoolArray
    labels: tuple[str, ...]
    statements: tuple[str, ...]
    weak_statements: tuple[str, ...]
    warnings: tuple[str, ...]
    rule: str
    scaling: ProblemScaling = field(repr=False)

    @property
    def null_dimension(self) -> int:
        return self.n_params - self.rank

    def text(self) -> str:
        """All of it as a paragraph list (for logs and reports)."""
        lines = [
            f"rank {self.rank} of {self.n_params} covariance entries "
            f"(relative singular-value tolerance {self.rank_rtol:g}); condition number of the "
            f"identifiable part {self.condition_number:.3g}"
        ]
        lines += [f"unidentifiable: {s}" for s in self.statements]
        lines += [f"weakly identified: {s}" for s in self.weak_statements]
        lines += [f"warning: {s}" for s in self.warnings]
        if self.statements:
            lines.append(f"rule: {self.rule}")
        return "\n".join(lines)


RULE = (
    "among all solutions with the same fit, the one with minimum norm in equilibrated units "
    "(each variance divided by its column scale) is reported, subject to every Σ ⪰ 0; entries "
    "without any effect are 0 and interchangeable entries share the identified sum"
)


def analyse_identifiability(
    stats: MomentStatistics,
    *,
    rank_rtol: float = RANK_RTOL,
    weak_rtol: float = WEAK_RTOL,
    frame_jacobians: FloatArray | None = None,
) -> IdentifiabilityReport:
    """Numerical rank, condition number and null directions of Eq. (13–14) in words.

    ``frame_jacobians`` (N, F_chain, d, 6), optional, enables the constant-Jacobian check.
    """
    layout = stats.layout
    scaling = problem_scaling(stats)
    d = scaling.param_scale
    gram = d[:, None] * stats.gram * d[None, :]
    eigval, eigvec = np.linalg.eigh(0.5 * (gram + gram.T))
    eigval, eigvec = eigval[::-1], eigvec[:, ::-1]
    lam_max = max(float(eigval[0]), 0.0)
    sing = np.sqrt(np.clip(eigval, 0.0, None))
    s_max = float(sing[0]) if lam_max > 0 else 0.0
    null = sing <= rank_rtol * s_max
    weak = (sing <= weak_rtol * s_max) & ~null
    rank = int(np.count_nonzero(~null))
    cond = float(s_max / sing[rank - 1]) if rank > 0 else float("inf")
    null_basis, weak_basis = eigvec[:, null], eigvec[:, weak]
    row_norm = np.linalg.norm(null_basis, axis=1)
    identifiable = row_norm < 1e-6
    # e_p itself is a null direction: θ_p has no effect
    silent = (row_norm > 1.0 - 1e-9) | silent_entries(stats)
    labels = tuple(layout.labels())
    atoms = _atoms(layout)
    gram_hat = gram / lam_max if lam_max > 0 else gram
    none = np.zeros((layout.n_params, 0))
    statements, explained = _describe(
        gram_hat, rank_rtol**2, null_basis, none, atoms, layout, d, weak=False
    )
    weak_statements, _ = _describe(
        gram_hat,
        weak_rtol**2,
        weak_basis,
        np.hstack([null_basis, explained]),
        atoms,
        layout,
        d,
        weak=True,
    )
    warnings = _noise_warnings(statements + weak_statements, layout)
    if frame_jacobians is not None:
        warnings += _constant_jacobian_warnings(frame_jacobians, layout)
    return IdentifiabilityReport(
        layout.n_params,
        rank,
        cond,
        rank_rtol,
        weak_rtol,
        sing,
        null_basis,
        weak_basis,
        identifiable,
        silent,
        labels,
        tuple(statements),
        tuple(weak_statements),
        tuple(warnings),
        RULE,
        scaling,
    )


def _atoms(layout: CovarianceLayout) -> list[Atom]:
    """Per frame: single entries, plane-isotropic pairs, 3-D isotropic triples (variances)."""
    index = {
        (f, i, j): p
        for p, (f, i, j) in enumerate(
            zip(layout.param_frame, layout.param_row, layout.param_col, strict=True)
        )
    }
    atoms = []
    for f, frame in enumerate(layout.frame_names):
        for p in np.flatnonzero(layout.param_frame == f):
            vec = np.zeros(layout.n_params)
            vec[p] = 1.0
            i, j = layout.param_row[p], layout.param_col[p]
            name = f"var({POSE_AXES[i]})" if i == j else f"cov({POSE_AXES[i]},{POSE_AXES[j]})"
            atoms.append(Atom(frame, name, vec, 1))
        for group, kind in ((TRANSLATION_AXES, "translational"), (ROTATION_AXES, "rotational")):
            present = [a for a in group if (f, a, a) in index]
            subsets = [(a, b) for k, a in enumerate(present) for b in present[k + 1 :]]
            for subset in subsets + ([tuple(present)] if len(present) == 3 else []):
                vec = np.zeros(layout.n_params)
                vec[[index[(f, a, a)] for a in subset]] = 1.0
                if len(subset) == 3:
                    name = f"isotropic {kind} variance"
                else:
                    name = (
                        f"isotropic {kind} variance in the "
                        f"{POSE_AXES[subset[0]]}–{POSE_AXES[subset[1]]} plane"
                    )
                atoms.append(Atom(frame, name, vec, len(subset)))
    return atoms


def _describe(
    gram: FloatArray,
    threshold: float,
    basis: FloatArray,
    known: FloatArray,
    atoms: list[Atom],
    layout: CovarianceLayout,
    param_scale: FloatArray,
    *,
    weak: bool,
) -> tuple[list[str], FloatArray]:
    """Statements for the directions in ``basis`` that ``known`` does not already explain.

    Works in equilibrated units with Ĝ = ``gram``: a unit direction u "has no effect" if
    ``uᵀĜu ≤ threshold``. Returns the statements and the relation vectors they cover.
    """
    q = layout.n_params
    if basis.shape[1] == 0:
        return [], np.zeros((q, 0))
    known = _orthonormal(known)
    vectors = np.array([a.vector / param_scale for a in atoms]).T
    unit = vectors / np.linalg.norm(vectors, axis=0)
    energy = unit.T @ gram @ unit
    statements: list[str] = []
    explained = np.zeros((q, 0))

    def outside(vec: FloatArray) -> bool:
        span = _orthonormal(np.hstack([known, explained]))
        resid = vec - span @ (span.T @ vec)
        return bool(np.linalg.norm(resid) > 1e-6 * np.linalg.norm(vec))

    order = sorted(range(len(atoms)), key=lambda a: atoms[a].size)
    silent = np.diag(energy) <= threshold
    for a in order:
        if silent[a] and atoms[a].size == 1 and outside(unit[:, a]):
            explained = _append(explained, unit[:, a])
            what = "has almost no effect" if weak else "has no effect"
            statements.append(f"{atoms[a].name} of frame {atoms[a].frame} {what} on the residuals")
    live = [a for a in order if not silent[a]]
    reported: list[set[str]] = []
    for members, coef, relations in _parallel_classes(atoms, live, energy, unit, threshold):
        new = [rel for rel in relations if outside(rel)]
        frames = {atoms[m].frame for m in members}
        # A class whose relations all follow from earlier ones is only worth a sentence if it
        # links more sources than an earlier class (e.g. isotropic variance across the chain);
        # in the weak pass it would repeat an exact relation.
        if not new and (weak or any(frames <= earlier for earlier in reported)):
            continue
        for rel in new:
            if outside(rel):
                explained = _append(explained, rel)
        reported.append(frames)
        statements.append(_class_statement(members, atoms, coef, weak))
    # Directions of the basis that the atom relations leave over: explicit combinations.
    span = _orthonormal(np.hstack([known, explained]))
    rest = _orthonormal(basis - span @ (span.T @ basis))
    if rest.shape[1]:
        eigval, eigvec = np.linalg.eigh(rest.T @ gram @ rest)
        rest = rest @ eigvec[:, eigval <= threshold]
    if rest.shape[1]:
        for row in _sparse_relations(rest, span, layout, param_scale):
            statements.append(_combination_statement(row, layout, weak))
        explained = np.hstack([explained, rest])
    return statements, explained


def _parallel_classes(
    atoms: list[Atom],
    live: list[int],
    energy: FloatArray,
    unit: FloatArray,
    threshold: float,
) -> list[tuple[list[int], dict[int, float], list[FloatArray]]]:
    """Classes of atoms of different sources whose effects agree up to a factor.

    A pair (a, b) qualifies if the smallest eigenvalue of its 2×2 block of ÛᵀĜÛ is at most
    ``threshold``; its eigenvector gives effect(u_a) = ratio · effect(u_b). Union-find keeps
    coef(x) = effect(u_x) / effect(u_root). Classes come smallest atoms first, each with its
    relation vectors (equilibrated units).
    """
    parent = {a: a for a in live}
    to_parent = {a: 1.0 for a in live}

    def root_and_coef(a: int) -> tuple[int, float]:
        coef = 1.0
        while parent[a] != a:
            coef *= to_parent[a]
            a = parent[a]
        return a, coef

    idx = np.asarray(live, dtype=int)
    support = np.array([atoms[a].vector != 0 for a in live], dtype=float)
    disjoint = (support @ support.T) == 0
    e = np.diag(energy)[idx]
    c = energy[np.ix_(idx, idx)]
    half_sum, half_diff = 0.5 * (e[:, None] + e[None, :]), 0.5 * (e[:, None] - e[None, :])
    lam_min = half_sum - np.sqrt(half_diff**2 + c**2)
    pairs = []
    for x, y in np.argwhere(np.triu(disjoint & (lam_min <= threshold), k=1)):
        # Eigenvector (α, β) of [[e_a, c], [c, e_b]] for λ_min: α = c, β = λ_min − e_a.
        alpha, beta = c[x, y], lam_min[x, y] - e[x]
        if abs(alpha) > 1e-300:
            a, b = live[x], live[y]
            pairs.append((atoms[a].size + atoms[b].size, a, b, float(-beta / alpha)))
    relations: dict[int, list[FloatArray]] = {}
    involved: set[int] = set()
    for _, a, b, ratio in sorted(pairs):
        (ra, ca), (rb, cb) = root_and_coef(a), root_and_coef(b)
        if ra != rb:
            parent[rb], to_parent[rb] = ra, ca / (ratio * cb)
            relations.setdefault(ra, []).extend(relations.pop(rb, []))
        relations.setdefault(ra, []).append(unit[:, a] - ratio * unit[:, b])
        involved |= {a, b}
    grouped: dict[int, list[int]] = {}
    for a in live:  # ``live`` is sorted by atom size
        if a in involved:
            grouped.setdefault(root_and_coef(a)[0], []).append(a)
    return [
        (members, {m: root_and_coef(m)[1] for m in members}, relations.get(root, []))
        for root, members in grouped.items()
    ]


def _class_statement(
    members: list[int], atoms: list[Atom], coef: dict[int, float], weak: bool
) -> str:
    """'X of frame A and Y of frame B have the same effect …: only A + B is identifiable'.

    ``coef[m]`` = effect(m) / effect(reference), so θ only enters through Σ_m coef[m]·θ_m.
    """
    ref = coef[members[0]]
    rel = {m: coef[m] / ref for m in members}
    by_name: dict[str, list[str]] = {}
    for m in members:
        by_name.setdefault(atoms[m].name, []).append(atoms[m].frame)
    if len(by_name) == 1:
        name, frames = next(iter(by_name.items()))
        subject = f"{name} of frames {', '.join(frames)}"
    else:
        subject = " and ".join(f"{atoms[m].name} of frame {atoms[m].frame}" for m in members)
    terms = " + ".join(_term(rel[m], f"{atoms[m].frame}:{atoms[m].name}") for m in members)
    verb = "nearly the same effect" if weak else "the same effect"
    tail = " well" if weak else ""
    if all(abs(r - 1.0) < 5e-4 for r in rel.values()):
        return (
            f"{subject} have {verb} on the end-effector covariance: only their sum is "
            f"identifiable{tail}"
        )
    return (
        f"{subject} have {verb} on the end-effector covariance up to factors: only "
        f"{terms} is identifiable{tail}"
    )


def _term(coef: float, name: str) -> str:
    return f"{_fmt(coef)}{name}"


def _combination_statement(row: FloatArray, layout: CovarianceLayout, weak: bool) -> str:
    """A null direction (raw θ units) as readable terms, e.g. '2·J5:isotropic … + 1·J6:var(w_z)'."""
    scale = float(np.max(np.abs(row)))
    row = np.where(np.abs(row) > 1e-6 * scale, row, 0.0)
    terms: list[tuple[float, str]] = []
    for f, frame in enumerate(layout.frame_names):
        mine = {
            (int(layout.param_row[p]), int(layout.param_col[p])): float(row[p])
            for p in np.flatnonzero((layout.param_frame == f) & (row != 0))
        }
        for group, kind in ((TRANSLATION_AXES, "translational"), (ROTATION_AXES, "rotational")):
            coefs = {a: mine.pop((a, a)) for a in group if (a, a) in mine}
            terms += [(c, f"{frame}:{name}") for c, name in _group_terms(coefs, kind)]
        terms += [(c, f"{frame}:cov({POSE_AXES[i]},{POSE_AXES[j]})") for (i, j), c in mine.items()]
    text = " ".join(f"{'+' if c > 0 else '−'} {_fmt(abs(c))}{name}" for c, name in terms)
    what = "barely changes any Σ_E(q_n)" if weak else "leaves every Σ_E(q_n) unchanged"
    return f"the combination {text.lstrip('+ ')} {what}"


def _group_terms(coefs: dict[int, float], kind: str) -> list[tuple[float, str]]:
    """Equal coefficients on axes of one kind → isotropic terms; the rest as single entries."""

    def same(x: float, y: float) -> bool:
        return abs(x - y) <= 1e-6 * max(abs(x), abs(y))

    axes = list(coefs)
    if (
        len(axes) == 3
        and same(coefs[axes[0]], coefs[axes[1]])
        and same(coefs[axes[0]], coefs[axes[2]])
    ):
        return [(coefs[axes[0]], f"isotropic {kind} variance")]
    for a, b in ((0, 1), (0, 2), (1, 2)):
        if len(axes) >= 2 and max(a, b) < len(axes) and same(coefs[axes[a]], coefs[axes[b]]):
            rest = [x for k, x in enumerate(axes) if k not in (a, b)]
            plane = (
                f"isotropic {kind} variance in the {POSE_AXES[axes[a]]}–{POSE_AXES[axes[b]]} plane"
            )
            return [(coefs[axes[a]], plane)] + [(coefs[x], f"var({POSE_AXES[x]})") for x in rest]
    return [(coefs[a], f"var({POSE_AXES[a]})") for a in axes]


def _fmt(c: float) -> str:
    return "" if abs(c - 1.0) < 5e-4 else f"{c:.3g}·"


def _echelon(rows: FloatArray, order: list[int]) -> tuple[FloatArray, list[int]]:
    """Reduced row echelon form of the row space of ``rows`` (k, Q), pivots greedily in
    ``order``; rows that are numerically dependent are dropped first."""
    pivots: list[int] = []
    if rows.shape[0] == 0:
        return rows, pivots
    _, sv, vt = np.linalg.svd(rows, full_matrices=False)
    rows = vt[sv > 1e-10 * sv[0]]
    k = rows.shape[0]
    tol = 1e-8 * float(np.abs(rows).max())
    for c in order:
        trial = [*pivots, c]
        if np.linalg.matrix_rank(rows[:, trial], tol=tol) == len(trial):
            pivots = trial
        if len(pivots) == k:
            break
    if len(pivots) < k:  # pivot search failed numerically: keep the orthonormal rows
        return rows, pivots[:0]
    out = np.asarray(np.linalg.solve(rows[:, pivots], rows), dtype=np.float64)
    out[np.abs(out) < 1e-9 * float(np.abs(out).max())] = 0.0
    return out, pivots


def _sparse_relations(
    rest: FloatArray, span: FloatArray, layout: CovarianceLayout, param_scale: FloatArray
) -> FloatArray:
    """Rows (raw θ units) spanning ``rest`` modulo ``span``, as sparse as a few pivot orders
    (natural, reversed, rotations first, translations first) make them."""
    q = layout.n_params
    rotation = np.isin(layout.param_row, ROTATION_AXES) & np.isin(layout.param_col, ROTATION_AXES)
    natural = list(range(q))
    orders = [
        natural,
        natural[::-1],
        sorted(natural, key=lambda p: not rotation[p]),
        sorted(natural, key=lambda p: rotation[p]),
    ]
    known_rows = (span * param_scale[:, None]).T
    rows = (rest * param_scale[:, None]).T
    best: FloatArray | None = None
    for order in orders:
        reduced_known, pivots = _echelon(known_rows, order)
        reduced = rows - rows[:, pivots] @ reduced_known if pivots else rows.copy()
        candidate, _ = _echelon(reduced, [p for p in order if p not in set(pivots)])
        if best is None or np.count_nonzero(candidate) < np.count_nonzero(best):
            best = candidate
    assert best is not None
    return best


def _orthonormal(m: FloatArray) -> FloatArray:
    if m.shape[1] == 0:
        return m
    u, s, _ = np.linalg.svd(m, full_matrices=False)
    return u[:, s > 1e-9 * max(float(s[0]), 1e-300)]


def _append(m: FloatArray, v: FloatArray) -> FloatArray:
    return np.hstack([m, v[:, None]])


def _noise_warnings(statements: list[str], layout: CovarianceLayout) -> list[str]:
    """One warning per set of chain frames that share a statement with the noise frame."""
    if layout.noise_frame is None:
        return []
    noise_names = set(layout.noise_frame_names)
    noise = ", ".join(layout.noise_frame_names)
    chain_names = layout.frame_names[: layout.n_chain_frames]
    groups: dict[tuple[str, ...], list[str]] = {}
    for s in statements:
        mentioned = set(re.findall(r"frames? ([^:]+?) (?:has|have|and) ", s))
        names = {n.strip() for m in mentioned for n in m.split(", ")}
        names |= set(re.findall(r"([^\s·]+):(?:var|cov|isotropic)", s))  # combinations
        if not names & noise_names:
            continue
        chain = tuple(f for f in chain_names if f in names)
        if chain:
            subject = s.split(" have ")[0].split(" has ")[0].split(" leaves ")[0]
            groups.setdefault(chain, []).append(subject.split(" barely ")[0])
    return [
        f"the measurement noise ({noise}) cannot be told apart from frame(s) "
        f"{', '.join(chain)} in {len(subjects)} combination(s) ({'; '.join(subjects)}). The "
        "split is set by the rule; if Σ_n was measured separately, pass it as a known noise "
        "covariance."
        for chain, subjects in groups.items()
    ]


def _constant_jacobian_warnings(frame_jacobians: FloatArray, layout: CovarianceLayout) -> list[str]:
    """A frame whose Jacobian does not change over the data acts like measurement noise."""
    out = []
    mean = frame_jacobians.mean(axis=0)
    spread = np.abs(frame_jacobians - mean).max(axis=(0, 2, 3))
    for f in range(layout.n_chain_frames):
        size = float(np.abs(mean[f]).max())
        if spread[f] <= 1e-3 * size:
            how = "constant" if spread[f] <= 1e-9 * size else "nearly constant"
            out.append(
                f"frame {layout.frame_names[f]} has a {how} Jacobian over the recording (e.g. "
                "right before the end-effector): its covariance is "
                + ("indistinguishable from" if how == "constant" else "hard to separate from")
                + " the measurement noise"
            )
    return out


def resolve_null_space(
    theta: FloatArray,
    report: IdentifiabilityReport,
    layout: CovarianceLayout,
    floor: FloatArray | None = None,
) -> FloatArray:
    """Apply the rule: min ‖m∘(θ̂ + N y)‖ (Frobenius, equilibrated) s.t. every Σ_f ⪰ 0, or
    ⪰ ``floor`` (Q,) where the likelihood fit bounded θ below (its noise floor,
    :func:`~solver.covariance.fitting.noise_floor`).

    ``theta`` (Q,) must be PSD already (⪰ ``floor``); the result has the same fit (it differs
    by a null direction of G), hence the same Σ_E at every training configuration. Diagonal
    Σ: the least-distance program is solved exactly (:func:`_least_norm_diag`) and entries
    within :data:`NULL_SLACK` of their bound are set to it: two fits that end at different
    points of a null direction give the same answer.
    """
    basis = report.null_basis
    fallback = np.where(report.silent, 0.0, theta)  # each silent entry is a null direction
    if basis.shape[1] == 0:
        return theta
    scale = report.scaling.param_scale
    metric = layout.frobenius_weights()
    x0 = fallback / scale
    bound = np.zeros_like(x0) if floor is None else np.where(report.silent, 0.0, floor) / scale
    if layout.structure == "diag":
        slack = NULL_SLACK * max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        found = _least_norm_diag(x0 - bound + slack, basis, metric, bound - slack)
        if found is None:
            return fallback
        out = np.where(found - bound <= slack, bound, found)
    else:
        found = _least_norm_psd(x0, basis, metric, bound, layout)
        if found is None:
            return fallback
        out = found
    out = np.where(report.silent, 0.0, out) * scale
    out = layout.theta_from_covariances(clip_psd(layout.frame_covariances(out)))
    return np.where(report.silent, 0.0, out)  # exact zeros (rows of silent axes stay PSD)


def _least_norm_diag(
    start: FloatArray, basis: FloatArray, metric: FloatArray, bound: FloatArray
) -> FloatArray | None:
    """Diagonal Σ: ``x = bound + start + N y`` minimising ‖m∘x‖ subject to ``start + N y ≥ 0``
    (θ ≥ ``bound``), or None when no y satisfies the constraints.

    A least-squares problem with inequality constraints in the k null-direction weights y,
    solved exactly as Lawson & Hanson do (Solving Least Squares Problems, ch. 23): with
    ``m∘N = QR``, ``z = Ry + Qᵀ(m∘(bound + start))`` it is the least-distance program
    ``min ‖z‖ s.t. A z ≥ c`` (``A = N R⁻¹``), whose answer is the residual of the NNLS problem
    ``min ‖[Aᵀ; cᵀ] u − e_{k+1}‖, u ≥ 0`` (scipy's active-set NNLS): a finite, deterministic
    answer where an interior-point method stops at its tolerance."""
    from scipy.optimize import nnls

    k = basis.shape[1]
    q, r = np.linalg.qr(metric[:, None] * basis)
    target = -(q.T @ (metric * (bound + start)))  # ‖m∘x‖ = ‖R y − target‖ (+ a constant)
    a = np.linalg.solve(r.T, basis.T).T  # N R⁻¹ (n, k)
    c = -start - a @ target
    system = np.vstack([a.T, c[None, :]])
    unit = np.zeros(k + 1)
    unit[k] = 1.0
    if not np.all(np.isfinite(system)):
        return None
    try:
        weights = nnls(system, unit, maxiter=10 * system.shape[1])[0]
    except RuntimeError:  # no answer within its iterations (it needs at most a few per bound)
        return None
    residual = system @ weights - unit
    if not residual[k] < -LDP_FEASIBLE:  # ‖residual‖ = 0: the constraints have no solution
        return None
    y = np.linalg.solve(r, target - residual[:k] / residual[k])
    if np.min(start + basis @ y, initial=0.0) < -LDP_FEASIBLE * max(1.0, float(np.max(start))):
        return None
    return np.asarray(bound + start + basis @ y, dtype=float)


def _least_norm_psd(
    x0: FloatArray,
    basis: FloatArray,
    metric: FloatArray,
    bound: FloatArray,
    layout: CovarianceLayout,
) -> FloatArray | None:
    """Full Σ: ``x = x0 + N y`` minimising ‖m∘x‖ with every Σ̂_f − bound ⪰ 0, a semidefinite
    program (Clarabel through cvxpy); None when the solver finds no answer."""
    import cvxpy as cp

    y = cp.Variable(basis.shape[1])
    x = x0 + basis @ y
    problem = cp.Problem(
        cp.Minimize(cp.sum_squares(cp.multiply(metric, x))),
        _cone_constraints(x - bound, layout),
    )
    try:
        with warnings.catch_warnings():  # the status is checked below
            warnings.simplefilter("ignore", UserWarning)
            problem.solve(solver=cp.CLARABEL)
    except cp.error.SolverError:
        return None
    if y.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
        return None
    return np.asarray(x0 + basis @ y.value, dtype=float)


def _cone_constraints(x, layout: CovarianceLayout) -> list:
    """x ≥ 0 (diagonal) or Σ̂_f ⪰ 0 per frame, for an affine cvxpy expression x (Q,)."""
    import cvxpy as cp
    import scipy.sparse as sp

    if layout.structure == "diag":
        return [x >= 0]
    constraints = []
    for f in range(layout.n_frames):
        mine = np.flatnonzero(layout.param_frame == f)
        if mine.size == 0:
            continue
        # vec(Σ̂_f) (column-major 6×6) = S x: entry (i, j) and, off the diagonal, (j, i).
        rows, cols = layout.param_row[mine], layout.param_col[mine]
        off = rows != cols
        flat = np.concatenate([rows + 6 * cols, (cols + 6 * rows)[off]])
        params = np.concatenate([mine, mine[off]])
        select = sp.csr_matrix((np.ones(flat.size), (flat, params)), shape=(36, layout.n_params))
        constraints.append(cp.reshape(select @ x, (6, 6), order="F") >> 0)
    return constraints


UNSEEN_RTOL = 1e-3
"""An axis's variance is not identifiable when the RMS variation of its effect on Σ_E over the
recording's configurations is below this fraction of the effect's RMS size (the threshold of
:func:`_constant_jacobian_warnings` for a "nearly constant" Jacobian)."""

SILENT_RTOL = 1e-6
"""... or when the RMS size of its effect is below this fraction of the largest axis's."""


def unseen_axes(
    frame_jacobians: FloatArray, layout: CovarianceLayout
) -> list[tuple[str | None, ...]]:
    """Per chain frame, per axis (6): why the data cannot see the variance of that axis, or
    None where they can.

    The sensitivity of Eq. (12) ``Σ_E(q) = Σ_f J_f(q) Σ_f J_f(q)ᵀ`` to the variance θ of
    axis a of frame f at configuration n is ``S_n = u_n u_nᵀ`` (d × d), ``u_n = J_f(q_n) e_a``
    (m per m or rad, the Jacobian's column; ``frame_jacobians`` (N, F_chain, d, 6)). Over the
    recording its size is ``T = Σ_n ‖S_n‖_F² = Σ_n ‖u_n‖⁴`` and its variation around the
    mean ``S̄ = (1/N) Σ_n S_n`` is ``V = Σ_n ‖S_n − S̄‖_F² = T − N ‖S̄‖_F²``. Not seen:

    - ``sqrt(T)`` below :data:`SILENT_RTOL` of the largest axis's: no effect on the
      end-effector;
    - ``sqrt(V / T)`` below :data:`UNSEEN_RTOL` while the measurement noise is estimated too
      (``layout.noise_frame``): the effect is the same end-effector covariance at every
      configuration, which the unknown constant end-effector error Σ_n produces as well, so its
      σ is set by the assumed noise structure, not by the data (e.g. the rotation about the
      last joint's own axis). With a known Σ_n the level of a constant effect is seen.

    Axes the layout does not estimate are None (they are fixed at 0, not estimated).
    """
    constant_is_noise = layout.noise_frame is not None
    n = frame_jacobians.shape[0]
    columns = np.moveaxis(frame_jacobians, 3, 2)  # (N, F, 6, d): u_n per frame and axis
    size = np.einsum("nfad,nfad->nfa", columns, columns)  # ‖u_n‖²
    total = np.sum(size**2, axis=0)  # (F, 6): T
    mean = np.einsum("nfad,nfae->fade", columns, columns) / max(n, 1)  # S̄
    variation = np.clip(total - n * np.einsum("fade,fade->fa", mean, mean), 0.0, None)
    largest = float(np.sqrt(total.max())) if total.size else 0.0
    out: list[tuple[str | None, ...]] = []
    for f in range(layout.n_chain_frames):
        reasons: list[str | None] = []
        for a in range(6):
            if not layout.free_axes[f][a]:
                reasons.append(None)
            elif np.sqrt(total[f, a]) <= SILENT_RTOL * largest:
                reasons.append("no effect on the end-effector in this recording")
            elif constant_is_noise and variation[f, a] <= UNSEEN_RTOL**2 * total[f, a]:
                reasons.append(
                    "its effect on the end-effector covariance is the same at every "
                    "configuration of the recording (RMS variation "
                    f"{np.sqrt(variation[f, a] / total[f, a]):.1e} of its size, below "
                    f"{UNSEEN_RTOL:g}): the estimated measurement noise, a constant "
                    "end-effector error, looks the same; a separately measured noise "
                    "(--noise-std) would let it be seen"
                )
            else:
                reasons.append(None)
        out.append(tuple(reasons))
    return out
