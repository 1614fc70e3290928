"""Optimality criteria of a calibration design and their derivatives in the candidate weights.

A design puts weight ``w_n`` on candidate n (Σw = 1, 0 ≤ w ≤ u); for K poses its information is
``M(w) = P + K Σ_n w_n M_n`` (P: information already held, zero for a first recording). A set S of
K distinct poses is the point ``w = 1_S / K``, so every criterion of a set is the criterion of
that point and the best weights bound every set (the relaxation, :mod:`solver.design.relaxation`).

Criteria, all maximised, all concave in M (so in w), parameters equilibrated
(:mod:`solver.design.information`):

- ``D``: ``log det M / p`` — the log of the geometric mean eigenvalue; invariant to the
  parameter units; with several stages the sum over stages (each per dimension, so each stage
  weighs the same whatever its size);
- ``A``: ``−tr(M⁻¹) / p`` — minus the mean variance of the equilibrated parameters;
- ``I``: ``−tr(M⁻¹ T)`` — minus the parameter part of the predicted pose variance averaged over
  task configurations (``T = mean_t Ĵ_tᵀĴ_t``, Ĵ the pose Jacobian in equilibrated units);
- ``E``: ``λ_min(M)`` — the worst-determined direction (not differentiable: Clarabel only).

The derivative in w_n is ``K tr(∇φ(M) M_n) = K ‖F_n G‖²_F`` with ``∇φ = G Gᵀ``; one matrix
product over all candidates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg

from solver.arrays import FloatArray, IntArray
from solver.design.information import InformationBlock, profiled, profiled_factors
from solver.errors import SolverError

Criterion = Literal["D", "A", "E", "I"]
SMOOTH_CRITERIA: tuple[Criterion, ...] = ("D", "A", "I")


@dataclass(frozen=True)
class DesignProblem:
    """Choose ``count`` poses among the candidates of ``blocks`` (same candidates in each).

    ``task_root`` (p, t): ``T = task_root task_rootᵀ`` for criterion I (first block).
    ``distinct``: every candidate at most once (``w ≤ 1/count``), else repeats allowed (w ≤ 1).
    """

    blocks: tuple[InformationBlock, ...]
    criterion: Criterion
    count: int
    task_root: FloatArray | None = None
    distinct: bool = True

    def __post_init__(self) -> None:
        if len(self.blocks) > 1 and self.criterion != "D":
            raise SolverError("a design for several stages uses criterion D")
        if self.criterion == "I" and self.task_root is None:
            raise SolverError("criterion I needs task configurations")
        sizes = {block.n_candidates for block in self.blocks}
        if len(sizes) != 1:
            raise SolverError("every stage must describe the same candidates")
        if self.count < 1 or (self.distinct and self.count > self.n_candidates):
            raise SolverError(
                f"cannot choose {self.count} distinct poses from {self.n_candidates} candidates"
            )

    @property
    def n_candidates(self) -> int:
        return self.blocks[0].n_candidates

    @property
    def upper_weight(self) -> float:
        """The largest weight of one candidate: 1/K for distinct poses."""
        return 1.0 / self.count if self.distinct else 1.0

    def information(self, block: InformationBlock, weights: FloatArray) -> FloatArray:
        """``P + K Σ w_n M_n`` (p, p), over the candidates with non-zero weight."""
        return profiled(self.full_information(block, weights), block.nuisance)

    def full_information(self, block: InformationBlock, weights: FloatArray) -> FloatArray:
        """``P + K Σ w_n M_n`` (p+e, p+e) with the nuisance parameters (none for pose)."""
        support = np.flatnonzero(weights > 0.0)
        rows = block.factors[support] * np.sqrt(self.count * weights[support])[:, None, None]
        flat = rows.reshape(-1, block.columns)
        return block.prior + flat.T @ flat

    def value(self, weights: FloatArray) -> float:
        """The criterion at ``weights`` (-inf where the information is singular for D, A, I)."""
        return sum(
            (
                criterion_value(self.criterion, self.information(b, weights), self.task_root)
                for b in self.blocks
            ),
            0.0,
        )

    def value_and_gradient(self, weights: FloatArray) -> tuple[float, FloatArray]:
        """The criterion and a (super)gradient in the weights (N,)."""
        total, gradient = 0.0, np.zeros(self.n_candidates)
        for block in self.blocks:
            full = self.full_information(block, weights)
            m = profiled(full, block.nuisance)
            value = criterion_value(self.criterion, m, self.task_root)
            if not np.isfinite(value):
                return value, gradient
            total += value
            root = gradient_root(self.criterion, m, self.task_root)
            factors = profiled_factors(full, block.factors, block.nuisance)
            gradient += self.count * np.sum((factors @ root) ** 2, axis=(1, 2))
        return total, gradient

    def set_value(self, index: IntArray) -> float:
        """The criterion of the K poses ``index`` (the point 1_S / K)."""
        weights = np.zeros(self.n_candidates)
        np.add.at(weights, index, 1.0 / self.count)
        return self.value(weights)

    def swap_values(self, index: IntArray, position: int, pool: IntArray) -> FloatArray:
        """The criterion of the K poses ``index`` with ``index[position]`` replaced by each
        candidate of ``pool`` (P,) -> (P,), by rank-r updates of the information without the
        pose removed, ``C = (M − M_i)⁻¹``: D adds ``log det(I + F_n C F_nᵀ) / p`` (matrix
        determinant lemma), A and I subtract ``tr((I + F_n C F_nᵀ)⁻¹ W_n W_nᵀ)`` with
        ``W_n = F_n C R`` (Woodbury). E, nuisance parameters (the profiled information is no
        rank-r update), or a singular ``M − M_i``, is evaluated set by set."""
        if self.criterion == "E" or any(block.nuisance for block in self.blocks):
            return self._swap_values_by_sets(index, position, pool)
        total = np.zeros(pool.size)
        for block in self.blocks:
            kept = np.delete(index, position)
            m = block.information(kept)
            try:
                chol = scipy.linalg.cholesky(m, lower=True, check_finite=False)
            except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
                return self._swap_values_by_sets(index, position, pool)
            p = block.dimension
            inv_chol = scipy.linalg.solve_triangular(
                chol, np.eye(p), lower=True, check_finite=False
            )
            f = block.factors[pool]  # (P, r, p)
            whitened = f @ inv_chol.T  # F_n L⁻ᵀ: F_n C F_nᵀ = whitenedᵀ whitened
            r = f.shape[1]
            s = np.eye(r) + whitened @ whitened.transpose(0, 2, 1)
            if self.criterion == "D":
                total += (2.0 * np.sum(np.log(np.diag(chol))) + np.linalg.slogdet(s)[1]) / p
                continue
            root = np.eye(p) if self.criterion == "A" else self.task_root
            assert root is not None
            c_root = inv_chol.T @ (inv_chol @ root)  # C R
            base = float(np.sum((inv_chol @ root) ** 2))  # tr(Rᵀ C R)
            w = f @ c_root  # (P, r, c)
            reduction = np.sum(np.linalg.solve(s, w) * w, axis=(1, 2))
            scale = 1.0 / p if self.criterion == "A" else 1.0
            total += -(base - reduction) * scale
        return total

    def _swap_values_by_sets(self, index: IntArray, position: int, pool: IntArray) -> FloatArray:
        values = np.empty(pool.size)
        trial = index.copy()
        for j, n in enumerate(pool):
            trial[position] = n
            values[j] = self.set_value(trial)
        return values


def criterion_value(
    criterion: Criterion, information: FloatArray, task_root: FloatArray | None
) -> float:
    """φ(M) of a (p, p) information matrix; -inf (D, A, I) or ≤ 0 (E) when it is singular."""
    p = information.shape[0]
    if criterion == "E":
        return float(np.linalg.eigvalsh(information)[0])
    try:
        chol = scipy.linalg.cholesky(information, lower=True, check_finite=False)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return -np.inf
    if criterion == "D":
        return float(2.0 * np.sum(np.log(np.diag(chol))) / p)
    inv_chol = scipy.linalg.solve_triangular(chol, np.eye(p), lower=True, check_finite=False)
    if criterion == "A":
        return float(-np.sum(inv_chol**2) / p)
    assert task_root is not None
    return float(-np.sum((inv_chol @ task_root) ** 2))


def gradient_root(
    criterion: Criterion, information: FloatArray, task_root: FloatArray | None
) -> FloatArray:
    """G (p, g) with ``∇φ(M) = G Gᵀ`` (for E: the eigenvector of the smallest eigenvalue, a
    supergradient)."""
    p = information.shape[0]
    if criterion == "E":
        _, vectors = np.linalg.eigh(information)
        return vectors[:, :1]
    chol = scipy.linalg.cholesky(information, lower=True, check_finite=False)
    inv_chol = scipy.linalg.solve_triangular(chol, np.eye(p), lower=True, check_finite=False)
    if criterion == "D":
        return inv_chol.T / np.sqrt(p)  # M⁻¹ = L⁻ᵀ L⁻¹
    inverse = inv_chol.T @ inv_chol
    if criterion == "A":
        return inverse / np.sqrt(p)
    assert task_root is not None
    return inverse @ task_root


def efficiency(criterion: Criterion, value: float, bound: float) -> float:
    """How close a design's criterion is to the relaxation's bound, in [0, 1]:
    D ``exp(φ − φ*)`` (ratio of geometric-mean eigenvalues), A and I ``φ*/φ`` (ratio of the
    variances), E ``φ/φ*`` (ratio of the smallest eigenvalues)."""
    if not np.isfinite(value):
        return 0.0
    if criterion == "D":
        return float(np.exp(min(value - bound, 0.0)))
    if criterion == "E":
        return float(value / bound) if bound > 0.0 else 0.0
    return float(bound / value) if value < 0.0 else 0.0
