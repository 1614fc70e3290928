"""Sufficient statistics of the moment-matching least squares, paper Eq. (13–14).

``Σ_n ‖vec(r_n r_nᵀ) − B_n θ‖² = θᵀGθ − 2hᵀθ + c`` with ``G = Σ B_nᵀB_n``, ``h = Σ B_nᵀz_n``,
``c = Σ ‖r_n‖⁴``. Their size does not depend on N and they add over samples, files and machines
(:meth:`MomentStatistics.__add__`). Built in chunks of samples with one matrix product per chunk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver.covariance._blas import batched_gram_tn, gram_tn
from solver.covariance.layout import CovarianceLayout, column_matrix
from solver.errors import SolverError

FloatArray = NDArray[np.float64]

DEFAULT_CHUNK_SIZE = 4096


@dataclass(frozen=True)
class MomentStatistics:
    """G (Q, Q), h (Q,), c and N of Eq. (14) for one layout; units follow θ (m², rad²).

    ``gram`` G = Σ_n B_nᵀB_n, ``cross`` h = Σ_n B_nᵀ z_n, ``const`` c = Σ_n ‖z_n‖² with
    ``z_n = vec(r_n r_nᵀ − Σ_known)``; ``known_covariance`` (d, d) is a fixed, known part of
    Σ_E (e.g. a separately measured noise covariance), None for 0.
    """

    layout: CovarianceLayout
    gram: FloatArray
    cross: FloatArray
    const: float
    n_samples: int
    known_covariance: FloatArray | None = None

    def __add__(self, other: MomentStatistics) -> MomentStatistics:
        """Statistics of the union of both datasets."""
        if not isinstance(other, MomentStatistics):
            return NotImplemented
        if other.layout != self.layout:
            raise SolverError("cannot merge moment statistics built for different layouts")
        mine, theirs = self.known_covariance, other.known_covariance
        same = (mine is None and theirs is None) or (
            mine is not None and theirs is not None and np.array_equal(mine, theirs)
        )
        if not same:
            raise SolverError("cannot merge moment statistics with different known covariances")
        return MomentStatistics(
            self.layout,
            self.gram + other.gram,
            self.cross + other.cross,
            self.const + other.const,
            self.n_samples + other.n_samples,
            mine,
        )


def empty_statistics(
    layout: CovarianceLayout, known_covariance: FloatArray | None = None
) -> MomentStatistics:
    q = layout.n_params
    return MomentStatistics(layout, np.zeros((q, q)), np.zeros(q), 0.0, 0, known_covariance)


def build_moment_statistics(
    residuals: FloatArray,
    frame_jacobians: FloatArray,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> MomentStatistics:
    """Eq. (13–14) statistics from end-effector-frame residuals and frame Jacobians.

    ``residuals`` (N, d): r_n = Log(X_model⁻¹ X_measured) ([v; w], m and rad).
    ``frame_jacobians`` (N, F_chain, d, 6): A_f(q_n); the noise frame is added by the layout.
    ``known_covariance`` (d, d): known part of every Σ_E (e.g. a measured noise covariance,
    then the layout has no noise frame), subtracted from r rᵀ.
    Memory is bounded by ``chunk_size`` samples (about ``chunk_size·D·Q`` floats).
    """
    residuals = np.asarray(residuals, dtype=float)
    if residuals.shape != (frame_jacobians.shape[0], layout.residual_dim):
        raise SolverError(
            f"residuals must be (N, {layout.residual_dim}) matching frame_jacobians "
            f"{frame_jacobians.shape}, got {residuals.shape}"
        )
    if known_covariance is not None:
        known_covariance = np.asarray(known_covariance, dtype=float)
        if known_covariance.shape != (layout.residual_dim,) * 2:
            raise SolverError(
                f"known_covariance must be ({layout.residual_dim}, "
                f"{layout.residual_dim}), got {known_covariance.shape}"
            )
    return design_gram(
        frame_jacobians,
        layout,
        residuals=residuals,
        known_covariance=known_covariance,
        chunk_size=chunk_size,
    )


def design_gram(
    frame_jacobians: FloatArray,
    layout: CovarianceLayout,
    *,
    residuals: FloatArray | None = None,
    left: FloatArray | None = None,
    known_covariance: FloatArray | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> MomentStatistics:
    """Σ_n K̃_nᵀK̃_n (and K̃_nᵀ vech_w(r̃ r̃ᵀ − Σ̃_known)) for columns C̃ = T_n C.

    ``left`` (N, d, d) is T_n, e.g. the inverse Cholesky factor of Σ_E(q_n) (then the Gram is
    twice the Fisher information of the Gaussian likelihood); ``residuals`` are transformed by
    it, ``known_covariance`` ((d, d) or per sample (N, d, d)) must already be.
    """
    n_total = frame_jacobians.shape[0]
    if chunk_size < 1:
        raise SolverError(f"chunk_size must be positive, got {chunk_size}")
    stats = empty_statistics(layout)
    gram, cross, const = stats.gram.copy(), stats.cross.copy(), 0.0
    known = np.zeros((layout.residual_dim,) * 2) if known_covariance is None else known_covariance
    half = np.where(layout.is_variance, 0.5, 1.0)
    for start in range(0, n_total, chunk_size):
        stop = min(start + chunk_size, n_total)
        cols = column_matrix(frame_jacobians[start:stop], layout)
        r = None if residuals is None else residuals[start:stop]
        known_n = known[start:stop] if known.ndim == 3 else known
        if left is not None:
            cols = left[start:stop] @ cols
            r = None if r is None else np.einsum("nij,nj->ni", left[start:stop], r)
        if layout.structure == "diag":
            # G_pq = Σ_n (a_p·a_q)²: stacks of small products, no tall GEMM (which suffers from
            # BLAS thread contention on few cores).
            ci = np.ascontiguousarray(cols[:, :, layout.column_i])
            m = np.matmul(ci.transpose(0, 2, 1), ci)
            m *= m
            gram += m.sum(axis=0)
            if r is not None:
                u = np.einsum("ndp,nd->np", ci, r)
                rr = np.einsum("np,np->p", u, u)
                if known_covariance is not None:  # Σ_n a_pᵀ Σ_known a_p
                    known_b = np.broadcast_to(known_n, (ci.shape[0], *known_n.shape[-2:]))
                    rr = rr - np.einsum("ndp,nde,nep->p", ci, known_b, ci, optimize=True)
                cross += rr
        else:
            gram += _full_gram_chunk(cols, layout)
            if r is not None:
                u = np.einsum("ndp,nd->np", cols, r)  # a_p · r_n for every column
                rr = np.einsum("np,np->p", u[:, layout.column_i], u[:, layout.column_j])
                if known_covariance is not None:  # Σ_n a_iᵀ Σ_known a_j
                    flat = cols.reshape(-1, cols.shape[2])
                    ak = gram_tn(flat, (known_n @ cols).reshape(-1, cols.shape[2]))
                    rr = rr - ak[layout.column_i, layout.column_j]
                cross += 2.0 * half * rr
        if r is not None:
            sq = np.einsum("ni,ni->n", r, r)
            quad = np.einsum("ni,nij,nj->n" if known.ndim == 3 else "ni,ij,nj->n", r, known_n, r)
            known_sq = np.sum(known_n**2) * (1 if known.ndim == 3 else r.shape[0])
            const += float(np.sum(sq**2 - 2.0 * quad) + known_sq)
    gram = 0.5 * (gram + gram.T)
    return MomentStatistics(layout, gram, cross, const, n_total, known_covariance)


def _full_gram_chunk(columns: FloatArray, layout: CovarianceLayout) -> FloatArray:
    """Σ_n B_nᵀB_n for full Σ via per-sample M_n = C_nᵀC_n (a_p · a_q for all columns).

    ``⟨A E_ij Aᵀ, A' E_kl A'ᵀ⟩ = 2 s_ij s_kl (M_ik M_jl + M_il M_jk)``, s = ½ on variances.
    The sums ``T_fg[(i,k),(j,l)] = Σ_n M_ik M_jl`` over each pair of frames are one batched GEMM,
    about 7× cheaper than the Gram of the per-sample design for 7 frames.
    """
    n, _, n_cols = columns.shape
    n_frames = n_cols // 6
    m = np.matmul(columns.transpose(0, 2, 1), columns)
    blocks = m.reshape(n, n_frames, 6, n_frames, 6).transpose(1, 3, 0, 2, 4)
    blocks = blocks.reshape(n_frames * n_frames, n, 36)
    t = batched_gram_tn(blocks)  # (F², 36, 36)
    f, i, j = layout.param_frame, layout.param_row, layout.param_col
    pair = f[:, None] * n_frames + f[None, :]
    ik_jl = t[pair, i[:, None] * 6 + i[None, :], j[:, None] * 6 + j[None, :]]
    il_jk = t[pair, i[:, None] * 6 + j[None, :], j[:, None] * 6 + i[None, :]]
    half = np.where(layout.is_variance, 0.5, 1.0)
    return 2.0 * np.outer(half, half) * (ik_jl + il_jk)
