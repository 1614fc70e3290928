"""Check poses: the K poses at which ``kincal check`` states the smallest changes (issue 33).

Frames and units are :mod:`solver.check`'s: at candidate configuration n the end-effector-frame
residual (d = 6 rows [v; w], m and rad, or d = 3) is predicted Gaussian with the parts
``L_n`` (d, d), independent between poses (Σ_E + Σ_n + model error), and ``G_n Cov(θ̂) G_nᵀ``,
shared by every pose (``G_n`` (d, p) the parameter Jacobian, ``C = Cov(θ̂)`` (p, p)). A change
along the candidates' columns ``A_n`` (d, M) (:func:`solver.check.candidates_at`; sizes are
stated for :data:`solver.check.SIZED_KINDS`) moves the residuals by ``A_n δ``.

Information. For a set S of K poses the joint covariance is ``Σ_S = D_S + G_S C G_Sᵀ``
(K·d, K·d; :func:`solver.check.joint_covariance`, D_S = blockdiag L_n), and the whitened columns
``Ã = W A_S`` of the check give ``ÃᵀÃ = A_Sᵀ Σ_S⁻¹ A_S``. By Woodbury,

    F(S) = A_Sᵀ Σ_S⁻¹ A_S = Σ_{n∈S} a_nᵀ a_n − X Q Xᵀ,   Q = C (I + H C)⁻¹,
    X = Σ_{n∈S} a_nᵀ v_n (M, p),   H = Σ_{n∈S} v_nᵀ v_n (p, p),

with ``a_n = R_n⁻¹ A_n``, ``v_n = R_n⁻¹ G_n`` and ``L_n = R_n R_nᵀ`` (Cholesky): every sum adds
over poses, so adding a pose is a rank-d update and a greedy step costs one (p, p) solve per
candidate, whatever K.

Stated size. A part c of a candidate (a joint's offset, a frame's translation or rotation:
:func:`solver.check.size_parts`) with columns c is detected with probability
:data:`solver.check.POWER` from the size ``sqrt(λ_c / λ_min(F_cc(S)))`` on, along its worst
direction (:func:`solver.check.detectable_size`): λ_c the non-centrality its tests need
(:func:`solver.check.detectable_noncentrality`; here at the Bonferroni critical p-values of the
check's weights, the same for every set of K poses), λ_min(F_cc) = σ_min(Ã_c)². The check
states the first multiple of that size it also *locates* (tells apart from every other
candidate) often enough. Under a change along c, another candidate o's score statistic has the
non-centrality of c's minus ``δᵀ (F_cc − F_co F_oo⁺ F_oc) δ`` (the part of c's pattern outside
o's span), so what tells c from o is the Schur complement ``F_c|o``; the separation
information of part c is ``e_c(S) = min_o λ_min(F_c|o(S))`` over the candidates o that are
neither nested in c's candidate nor contain it (:data:`solver.check.NESTED_SHARE`: the check
prefers the simpler of nested candidates by its own rule), ``e_c ≤ λ_min(F_cc)``. The located
size is ``s_c(S) = sqrt(λ_c / e_c(S))`` (its location step stays a simulation's,
:func:`solver.check.stated_sizes`).

Criterion (minimax of the relative sizes). Sizes of different parts have different units
(rad, m), and some parts are poorly told apart from any candidates. Each size is measured in
its own scale ``σ_c = e_c(all candidates)^(-1/2)``, the worst-direction standard error of that
change, told from its nearest competitor, were every candidate a check pose; the K poses
minimise the largest relative size

    max_c s_c(S) / σ_c = max_c sqrt(λ_c e_c(all) / e_c(S)),

i.e. maximise the worst part's ``e_c(S) / (λ_c e_c(all))``: a maximin of the weakest-direction
separation information, each part relative to what the candidates can give it. Chosen
greedily, one pose at a time, the one that raises the worst part most (ties, e.g. while a part
is still unseen, broken by the mean over the parts), then single exchanges while the worst part
improves. The minimax is not submodular, so greedy carries no guarantee;
:func:`worst_relative_size` of random sets of K poses shows how far it is from chance
(``kincal design --check`` reports their median).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.check import (
    GLOBAL_WEIGHT,
    NESTED_SHARE,
    SIZED_KINDS,
    Candidate,
    detectable_noncentrality,
    size_parts,
)


@dataclass(frozen=True)
class SizePart:
    """A stated size's part: ``name`` (as :func:`solver.check.stated_sizes` names it),
    ``columns`` (m,) into the stacked candidate columns, ``unit``, ``noncentrality`` λ_c."""

    name: str
    columns: IntArray
    unit: str
    noncentrality: float
    competitors: tuple[IntArray, ...] = ()
    """The columns of each candidate it must be told apart from."""


@dataclass(frozen=True)
class CheckPoseTerms:
    """The whitened per-pose terms of N candidate configurations: ``a`` (N, d, M) every
    candidate's columns and ``v`` (N, d, p) the parameter Jacobian, each ``R_n⁻¹ ·``
    (L_n = R_n R_nᵀ), ``parameter_covariance`` C (p, p), and the ``parts``."""

    a: FloatArray
    v: FloatArray
    parameter_covariance: FloatArray
    parts: tuple[SizePart, ...]

    @classmethod
    def build(
        cls,
        local: FloatArray,
        parameter_jacobian: FloatArray,
        parameter_covariance: FloatArray,
        candidates: list[Candidate],
        n_poses: int,
        level: float,
    ) -> CheckPoseTerms:
        """The terms from :class:`service.app.check.PredictedParts`' arrays: ``local``
        (N, d, d), ``parameter_jacobian`` (N, d, p), Cov(θ̂) (p, p), the ``candidates`` at the
        N configurations (the check's: every candidate counts in its level's split), for
        checks of ``n_poses`` poses at family-wise ``level``."""
        root = np.linalg.cholesky(local)
        columns = np.concatenate([c.jacobian for c in candidates], axis=2)
        starts = np.cumsum([0] + [c.jacobian.shape[2] for c in candidates])
        blocks = [np.arange(a, b) for a, b in itertools.pairwise(starts)]
        d = local.shape[1]
        overall = detectable_noncentrality(n_poses * d, GLOBAL_WEIGHT * level)
        candidate_p = (1.0 - GLOBAL_WEIGHT) * level / max(len(candidates), 1)
        terms = cls(
            np.linalg.solve(root, columns),
            np.linalg.solve(root, parameter_jacobian),
            np.asarray(parameter_covariance, dtype=float),
            (),
        )
        every = terms.information(*terms.sums(np.arange(local.shape[0])))
        parts = []
        for index, candidate in enumerate(candidates):
            if candidate.kind not in SIZED_KINDS:
                continue
            m = candidate.jacobian.shape[2]
            own = detectable_noncentrality(min(m, n_poses * d), candidate_p)
            competitors = tuple(
                block
                for other, block in enumerate(blocks)
                if other != index
                and not nested(every, block, blocks[index])
                and not nested(every, blocks[index], block)
            )
            for name, axes, unit in size_parts(candidate):
                part = SizePart(name, blocks[index][axes], unit, min(overall, own), competitors)
                parts.append(dataclasses.replace(part, competitors=separable(every, part)))
        return dataclasses.replace(terms, parts=tuple(parts))

    @functools.cached_property
    def outer(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Each pose's ``aᵀa`` (N, M, M), ``aᵀv`` (N, M, p) and ``vᵀv`` (N, p, p)."""
        a, v = self.a, self.v
        return (
            np.einsum("ndi,ndj->nij", a, a),
            np.einsum("ndi,ndj->nij", a, v),
            np.einsum("ndi,ndj->nij", v, v),
        )

    def sums(self, rows: IntArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``Σ aᵀa`` (..., M, M), ``X = Σ aᵀv`` (..., M, p) and ``H = Σ vᵀv`` (..., p, p) over
        the poses ``rows`` (..., K) (several sets at once)."""
        aa, av, vv = self.outer
        return aa[rows].sum(axis=-3), av[rows].sum(axis=-3), vv[rows].sum(axis=-3)

    def information(self, aa: FloatArray, x: FloatArray, h: FloatArray) -> FloatArray:
        """``F = Σ aᵀa − X Q Xᵀ`` (..., M, M) from sums (..., M, M), (..., M, p), (..., p, p),
        ``Q = C (I + H C)⁻¹`` (Woodbury: ``A_Sᵀ Σ_S⁻¹ A_S``)."""
        c = self.parameter_covariance
        eye = np.eye(c.shape[0])
        q_t = np.linalg.solve(eye + c @ h, np.broadcast_to(c, h.shape))  # Qᵀ = (I + C H)⁻¹ C
        f = aa - x @ q_t @ np.swapaxes(x, -1, -2)
        return np.asarray(0.5 * (f + np.swapaxes(f, -1, -2)), dtype=float)

    def weakest(self, information: FloatArray) -> FloatArray:
        """The separation information ``e_c = min_o λ_min(F_cc − F_co F_oo⁺ F_oc)`` of every
        part (..., parts) from information (..., M, M)."""
        values = []
        for part in self.parts:
            c = part.columns
            worst = np.linalg.eigvalsh(information[..., c[:, None], c[None, :]])[..., 0]
            for o in part.competitors:
                worst = np.minimum(worst, separation(information, c, o))
            values.append(worst)
        return np.stack(values, axis=-1)


SEPARABLE_SHARE = 1e-6
"""A competitor that leaves a part less than this share of its own worst-direction information
with every candidate a check pose cannot be told from it by any choice of poses (e.g. the base's
translation along joint 1's axis and the next link's): it does not count in the criterion."""


def separation(information: FloatArray, columns: IntArray, other: IntArray) -> FloatArray:
    """``λ_min(F_cc − F_co F_oo⁺ F_oc)`` (...,) of part ``columns`` against candidate ``other``:
    the information of the part's weakest direction outside the other's span."""
    c, o = columns, other
    own = information[..., c[:, None], c[None, :]]
    f_oo = information[..., o[:, None], o[None, :]]
    f_oc = information[..., o[:, None], c[None, :]]
    ridge = 1e-12 * np.trace(f_oo, axis1=-2, axis2=-1)[..., None, None] + 1e-300
    explained = np.swapaxes(f_oc, -1, -2) @ np.linalg.solve(f_oo + ridge * np.eye(o.size), f_oc)
    return np.asarray(np.linalg.eigvalsh(own - explained)[..., 0], dtype=float)


def separable(information: FloatArray, part: SizePart) -> tuple[IntArray, ...]:
    """The competitors of ``part`` that the candidates (``information`` (M, M) of all of them)
    can tell it from (:data:`SEPARABLE_SHARE`)."""
    c = part.columns
    own = float(np.linalg.eigvalsh(information[np.ix_(c, c)])[0])
    return tuple(
        o for o in part.competitors if separation(information, c, o) > SEPARABLE_SHARE * own
    )


def nested(information: FloatArray, inner: IntArray, outer: IntArray) -> bool:
    """Whether the columns ``inner`` lie in the span of ``outer`` in the metric of
    ``information`` (M, M) (each reproduced to :data:`solver.check.NESTED_SHARE`), as
    :func:`solver.check.nested_in` decides it on the whitened columns."""
    if inner.size >= outer.size:
        return False
    f_oo = information[np.ix_(outer, outer)]
    for i in inner:
        f_oi = information[outer, i]
        own = float(information[i, i])
        if own <= 0.0 or float(f_oi @ np.linalg.lstsq(f_oo, f_oi, rcond=None)[0]) < (
            NESTED_SHARE * own
        ):
            return False
    return True


def part_scales(terms: CheckPoseTerms) -> FloatArray:
    """σ_c (parts,): each part's worst-direction standard error, told from its nearest
    competitor, with every candidate a check pose, ``e_c(all)^(-1/2)`` in the part's unit (inf
    where no candidate tells it apart)."""
    every = np.arange(terms.a.shape[0])
    weakest = terms.weakest(terms.information(*terms.sums(every)))
    return np.where(weakest > 0.0, 1.0 / np.sqrt(np.maximum(weakest, 1e-300)), np.inf)


def relative_sizes(terms: CheckPoseTerms, rows: IntArray, scales: FloatArray) -> FloatArray:
    """``s_c(S) / σ_c`` (..., parts) of the poses ``rows`` (..., K): each part's located size in
    its scale (inf where these poses do not tell it apart; NaN for a part no candidate tells
    apart, σ_c = inf, which the criterion leaves out)."""
    weakest = terms.weakest(terms.information(*terms.sums(rows)))
    noncentrality = np.array([p.noncentrality for p in terms.parts])
    with np.errstate(divide="ignore", invalid="ignore"):
        size = np.sqrt(noncentrality / np.maximum(weakest, 0.0))
        return np.asarray(np.where(np.isfinite(scales), size / scales, np.nan), dtype=float)


def worst_relative_size(terms: CheckPoseTerms, rows: IntArray, scales: FloatArray) -> FloatArray:
    """The criterion (...,): the largest :func:`relative_sizes` of the poses ``rows`` (..., K)
    over the parts some candidate tells apart."""
    relative = relative_sizes(terms, rows, scales)[..., np.isfinite(scales)]
    return np.asarray(np.max(relative, axis=-1, initial=0.0), dtype=float)


def _best_addition(
    terms: CheckPoseTerms,
    sums: tuple[FloatArray, FloatArray, FloatArray],
    rows: IntArray,
    weight: FloatArray,
) -> tuple[int, float]:
    """The candidate of ``rows`` whose addition to the poses of ``sums`` maximises the worst
    part's weighted separation ``e_c`` (ties broken by the mean over the parts), and that
    worst value."""
    aa, av, vv = terms.outer
    trial = terms.information(sums[0] + aa[rows], sums[1] + av[rows], sums[2] + vv[rows])
    ratio = terms.weakest(trial) * weight
    best = int(np.lexsort((ratio.mean(axis=1), ratio.min(axis=1)))[-1])
    return int(rows[best]), float(ratio[best].min())


MAX_EXCHANGE_PASSES = 5
"""Passes of single exchanges after the greedy choice (each tries every chosen pose)."""


def choose_check_poses(terms: CheckPoseTerms, n_poses: int, scales: FloatArray) -> IntArray:
    """K = ``n_poses`` distinct candidates (sorted) that minimise the largest relative size:
    greedily, each step adding the candidate that maximises the worst part's
    ``e_c σ_c² / λ_c`` after it (ties broken by the mean over the parts); then single
    exchanges (a chosen pose out, the best candidate for the others in) while the worst part
    improves, at most :data:`MAX_EXCHANGE_PASSES` passes."""
    weight = scales**2 / np.array([p.noncentrality for p in terms.parts])
    weight = np.where(np.isfinite(weight), weight, 0.0)  # a part no candidate sees: no say
    free = np.ones(terms.a.shape[0], dtype=bool)
    chosen: list[int] = []
    for _ in range(n_poses):
        sums = terms.sums(np.asarray(chosen, dtype=np.intp))
        best, _ = _best_addition(terms, sums, np.flatnonzero(free), weight)
        chosen.append(best)
        free[best] = False
    current = float(
        np.min(terms.weakest(terms.information(*terms.sums(np.array(chosen)))) * weight)
    )
    for _ in range(MAX_EXCHANGE_PASSES):
        improved = False
        for slot in range(n_poses):
            others = np.asarray(chosen[:slot] + chosen[slot + 1 :], dtype=np.intp)
            best, value = _best_addition(terms, terms.sums(others), np.flatnonzero(free), weight)
            if value > current * (1.0 + 1e-9):
                free[chosen[slot]], free[best] = True, False
                chosen[slot], current, improved = best, value, True
        if not improved:
            break
    return np.sort(np.asarray(chosen, dtype=np.intp))
