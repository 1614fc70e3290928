"""Sufficient statistics of the moment-matching least squares, paper Eq. (13–14).

``Σ_n ‖vec(r_n r_nᵀ) − B_n θ‖² = θᵀGθ − 2hᵀθ + c`` with ``G = Σ B_nᵀB_n``, ``h = Σ B_nᵀz_n``,
``c = Σ ‖r_n‖⁴``. Their size does not depend on N and they add over samples, files and machines
(:meth:`MomentStatistics.__add__`). Built in chunks of samples with one matrix product per chunk.

Diagonal Σ (the default) builds the per-sample design batch-last — one row of products
``√w a_p[r] a_p[s]`` per matrix entry (r, s), sample index last — and takes its Gram with one
BLAS product per chunk; a column with no rotation rows (``A_f[:, i<3]``) needs 6 of the 21
entries, so the products stop there; the noise frame's unit columns need no product at all.
Full Σ goes through the per-sample column Gram (:func:`_full_gram_chunk`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg.blas

from solver.arrays import BoolArray, FloatArray, IntArray
from solver.covariance._blas import batched_gram_tn, gram_tn
from solver.covariance.layout import CovarianceLayout, column_matrix
from solver.errors import SolverError

DEFAULT_CHUNK_SIZE = 4096
DIAG_BLOCK = 2048
"""Samples per batch-last design block of the diagonal path (36 columns: ~12 MB)."""
_SQRT2 = float(np.sqrt(2.0))


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


@dataclass(frozen=True)
class JacobianRange:
    """Per entry of the frame Jacobians (F, d, 6): the sum, minimum and maximum over ``n``
    samples. Merges over chunks with ``+``; enough for the constant-Jacobian check of
    :func:`~solver.covariance.identifiability.analyse_identifiability` (:meth:`pseudo_samples`)."""

    total: FloatArray
    low: FloatArray
    high: FloatArray
    n: int

    @classmethod
    def of(cls, frame_jacobians: FloatArray) -> JacobianRange:
        """Of frame Jacobians (n, F, d, 6)."""
        if frame_jacobians.shape[0] == 0:
            return cls.empty(frame_jacobians.shape[1:])
        return cls(
            frame_jacobians.sum(axis=0),
            frame_jacobians.min(axis=0),
            frame_jacobians.max(axis=0),
            int(frame_jacobians.shape[0]),
        )

    @classmethod
    def empty(cls, shape: tuple[int, ...]) -> JacobianRange:
        return cls(np.zeros(shape), np.full(shape, np.inf), np.full(shape, -np.inf), 0)

    def __add__(self, other: JacobianRange) -> JacobianRange:
        return JacobianRange(
            self.total + other.total,
            np.minimum(self.low, other.low),
            np.maximum(self.high, other.high),
            self.n + other.n,
        )

    def pseudo_samples(self) -> FloatArray:
        """Two pseudo-samples (2, F, d, 6) with the samples' mean Jacobian and, per entry, its
        largest deviation from the mean: the constant-Jacobian check sees the same mean and
        spread as on all samples."""
        mean = self.total / max(self.n, 1)
        deviation = np.maximum(self.high - mean, mean - self.low)
        return np.stack([mean + deviation, mean - deviation])


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
    it, ``known_covariance`` ((d, d) or per sample (N, d, d)) must already be. A tied layout
    (a noise frame with several placements) is computed untied and folded.
    """
    n_total = frame_jacobians.shape[0]
    if chunk_size < 1:
        raise SolverError(f"chunk_size must be positive, got {chunk_size}")
    if layout.is_tied:  # Σ_E linear in θ = T θ_untied: the Gram and cross term fold
        untied = design_gram(
            frame_jacobians,
            layout.untied(),
            residuals=residuals,
            left=left,
            known_covariance=known_covariance,
            chunk_size=chunk_size,
        )
        tie = layout.tie_matrix
        return MomentStatistics(
            layout,
            tie.T @ untied.gram @ tie,
            tie.T @ untied.cross,
            untied.const,
            untied.n_samples,
            known_covariance,
        )
    if layout.structure == "diag":
        return _diag_design_gram(
            frame_jacobians, layout, residuals, left, known_covariance, chunk_size
        )
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
        gram += _full_gram_chunk(cols, layout)
        if r is not None:
            u = np.einsum("ndp,nd->np", cols, r)  # a_p · r_n for every column
            rr = np.einsum("np,np->p", u[:, layout.column_i], u[:, layout.column_j])
            if known_covariance is not None:  # Σ_n a_iᵀ Σ_known a_j
                flat = cols.reshape(-1, cols.shape[2])
                ak = gram_tn(flat, (known_n @ cols).reshape(-1, cols.shape[2]))
                rr = rr - ak[layout.column_i, layout.column_j]
            cross += 2.0 * half * rr
            sq = np.einsum("ni,ni->n", r, r)
            quad = np.einsum("ni,nij,nj->n" if known.ndim == 3 else "ni,ij,nj->n", r, known_n, r)
            known_sq = np.sum(known_n**2) * (1 if known.ndim == 3 else r.shape[0])
            const += float(np.sum(sq**2 - 2.0 * quad) + known_sq)
    gram = 0.5 * (gram + gram.T)
    return MomentStatistics(layout, gram, cross, const, n_total, known_covariance)


# --- diagonal Σ: the design built batch-last, its Gram by BLAS --------------------------------


def pair_order(dim: int) -> tuple[IntArray, IntArray, FloatArray]:
    """Entries (r, s), r ≤ s, of a symmetric dim×dim matrix ordered by s, then r, and their
    ``vech_w`` weights (1 on the diagonal, √2 off it).

    The entries of the leading m×m block come first (m(m+1)/2 of them): the design column of
    a Jacobian column whose rows beyond m are zero is zero beyond that prefix.
    """
    rows = np.array([r for s in range(dim) for r in range(s + 1)], dtype=np.intp)
    cols = np.array([s for s in range(dim) for _ in range(s + 1)], dtype=np.intp)
    return rows, cols, np.where(rows == cols, 1.0, _SQRT2)


def _diagonal_entry(i: int) -> int:
    """Position of entry (i, i) in :func:`pair_order`."""
    return i * (i + 3) // 2


def leading_rows(columns: FloatArray) -> IntArray:
    """Per column of a batch-last stack (Q, d, n): one past the last row that is non-zero in
    some sample (0 for a zero column)."""
    q, d, _ = columns.shape
    out = np.zeros(q, dtype=np.intp)
    pending = np.arange(q)
    for row in range(d - 1, -1, -1):
        if not pending.size:
            break
        hit = np.any(columns[pending, row] != 0.0, axis=-1)
        out[pending[hit]] = row + 1
        pending = pending[~hit]
    return out


def pair_products(residuals: FloatArray, known_covariance: FloatArray | None = None) -> FloatArray:
    """``z = vech_w(r rᵀ − Σ_known)`` in :func:`pair_order`, batch-last: residuals (d, n),
    ``known_covariance`` (d, d) or per sample (d, d, n) -> (d(d+1)/2, n)."""
    d = residuals.shape[0]
    rows, cols, weights = pair_order(d)
    z = residuals[rows] * residuals[cols]
    if known_covariance is not None:
        known = known_covariance[rows, cols]
        z -= known if known.ndim == 2 else known[:, None]
    z *= weights[:, None]
    return z


def diag_statistics_batch_last(
    columns: FloatArray,
    slots: IntArray,
    layout: CovarianceLayout,
    *,
    residuals: FloatArray | None = None,
    known_covariance: FloatArray | None = None,
    used: BoolArray | None = None,
    rows: IntArray | None = None,
    zeroed: bool = False,
    block: int = DIAG_BLOCK,
) -> MomentStatistics:
    """Eq. (13–14) statistics of a diagonal layout from batch-last arrays (the streamed path).

    ``columns`` (C, d, n): Jacobian columns, sample index last; ``slots`` (Q_chain,): which
    of them is ``A_f[:, i]`` for each chain-frame entry of θ, in layout order (the noise
    frame's columns are unit vectors and need none). ``residuals`` (d, n), m and rad;
    ``known_covariance`` (d, d); ``used`` (n,): samples to include (None: all), ``zeroed``:
    the other samples' columns are zero already (saves clearing their products); ``rows``
    (Q_chain,): :func:`leading_rows` of those columns when the caller knows them.
    """
    if layout.structure != "diag" or layout.is_tied:
        raise SolverError("diag_statistics_batch_last needs a diagonal, untied layout")
    if block < 1:
        raise SolverError(f"block must be positive, got {block}")
    chain = np.flatnonzero(~layout.is_noise)
    noise = np.flatnonzero(layout.is_noise)
    slots = np.asarray(slots, dtype=np.intp)
    if slots.shape != chain.shape:
        raise SolverError(f"slots must name a column for each of the {chain.size} chain entries")
    support = leading_rows(columns[slots]) if rows is None else np.asarray(rows, dtype=np.intp)
    order = np.concatenate([chain, noise])
    sums = _DiagSums.empty(order.size)
    for start in range(0, columns.shape[2], block):
        part = slice(start, start + block)
        mask = None if used is None else used[part]
        z = None
        if residuals is not None:
            z = pair_products(residuals[:, part], known_covariance)
        sums = sums + _diag_sums(
            columns[:, :, part], slots, support, layout.noise_param_rows, z, mask, zeroed
        )
    return sums.statistics(layout, order, known_covariance)


def _diag_design_gram(
    frame_jacobians: FloatArray,
    layout: CovarianceLayout,
    residuals: FloatArray | None,
    left: FloatArray | None,
    known_covariance: FloatArray | None,
    chunk_size: int,
) -> MomentStatistics:
    """:func:`design_gram` of a diagonal layout: each chunk turned batch-last."""
    n_total, n_frames, d, _ = frame_jacobians.shape
    if n_frames != layout.n_chain_frames or d != layout.residual_dim:
        column_matrix(frame_jacobians[:0], layout)  # raises the shape error
    chain = np.flatnonzero(~layout.is_noise)
    noise = np.flatnonzero(layout.is_noise)
    per_sample_known = known_covariance is not None and known_covariance.ndim == 3
    sums = _DiagSums.empty(layout.n_params)
    for start in range(0, n_total, chunk_size):
        stop = min(start + chunk_size, n_total)
        n = stop - start
        # column 6f + i is A_f[:, i]: (F, 6, d, n) -> (6F, d, n)
        cols = np.ascontiguousarray(frame_jacobians[start:stop].transpose(1, 3, 2, 0))
        cols = cols.reshape(6 * n_frames, d, n)
        r = None if residuals is None else np.ascontiguousarray(residuals[start:stop].T)
        known = known_covariance
        if per_sample_known:
            assert known_covariance is not None
            known = known_covariance[start:stop].transpose(1, 2, 0)
        if left is None:
            slots, units, order = layout.column_i[chain], layout.noise_param_rows, None
        else:  # whitened: every column general, the noise frame's too (T_n e_i)
            cols, r = _whitened(left[start:stop], cols, r, layout)
            slots, units = np.arange(layout.n_params), np.zeros(0, dtype=np.intp)
            order = np.arange(layout.n_params)
        support = leading_rows(cols[slots])
        z = None if r is None else pair_products(r, known)
        part = _diag_sums(cols, slots, support, units, z, None, False)
        if order is None:
            order = np.concatenate([chain, noise])
        sums = sums + part.permuted(order, layout.n_params)
    return sums.statistics(layout, np.arange(layout.n_params), known_covariance)


def _whitened(
    left: FloatArray, cols: FloatArray, residuals: FloatArray | None, layout: CovarianceLayout
) -> tuple[FloatArray, FloatArray | None]:
    """``T_n a`` for the column of every θ entry (Q, d, n), layout order (noise: ``T_n e_i``),
    and ``T_n r`` (d, n); ``left`` (n, d, d)."""
    t = left.transpose(1, 2, 0)  # (d, d, n)
    d = t.shape[0]
    out = np.zeros((layout.n_params, d, t.shape[2]))
    chain = np.flatnonzero(~layout.is_noise)
    out[chain] = np.einsum("rsn,psn->prn", t, cols[layout.column_i[chain]])
    for p, row in zip(np.flatnonzero(layout.is_noise), layout.noise_param_rows, strict=True):
        if row >= 0:
            out[p] = t[:, row]
    r = None if residuals is None else np.einsum("rsn,sn->rn", t, residuals)
    return out, r


@dataclass(frozen=True)
class _DiagSums:
    """Gram, cross term, constant and sample count of some θ entries (internal order)."""

    gram: FloatArray
    cross: FloatArray
    const: float
    n: int

    @classmethod
    def empty(cls, size: int) -> _DiagSums:
        return cls(np.zeros((size, size)), np.zeros(size), 0.0, 0)

    def __add__(self, other: _DiagSums) -> _DiagSums:
        return _DiagSums(
            self.gram + other.gram,
            self.cross + other.cross,
            self.const + other.const,
            self.n + other.n,
        )

    def permuted(self, order: IntArray, size: int) -> _DiagSums:
        """Entry k of these sums becomes entry ``order[k]`` of sums over ``size`` entries."""
        gram, cross = np.zeros((size, size)), np.zeros(size)
        gram[np.ix_(order, order)] = self.gram
        cross[order] = self.cross
        return _DiagSums(gram, cross, self.const, self.n)

    def statistics(
        self, layout: CovarianceLayout, order: IntArray, known: FloatArray | None
    ) -> MomentStatistics:
        sums = self.permuted(order, layout.n_params)
        gram = 0.5 * (sums.gram + sums.gram.T)
        return MomentStatistics(layout, gram, sums.cross, self.const, self.n, known)


def _diag_sums(
    columns: FloatArray,
    slots: IntArray,
    support: IntArray,
    unit_axes: IntArray,
    z: FloatArray | None,
    used: BoolArray | None,
    zeroed: bool,
) -> _DiagSums:
    """Sums over one block for the entries ``slots`` (general columns ``columns[slot]``, of
    which the first ``support`` rows may be non-zero) followed by ``unit_axes`` (columns
    ``e_i`` of residual row i, −1 for none: the unwhitened noise frames). ``z`` (D, n):
    :func:`pair_products`; ``used`` (n,) the samples to count, the others' columns already
    zero if ``zeroed``."""
    d, n = columns.shape[1], columns.shape[2]
    count = n if used is None else int(np.count_nonzero(used))
    skip = None if used is None or count == n else ~used
    if z is not None and skip is not None:
        z = z.copy()
        z[:, skip] = 0.0
    n_general = slots.size
    size = n_general + unit_axes.size
    gram, cross = np.zeros((size, size)), np.zeros(size)
    pair_rows, pair_cols, _ = pair_order(d)
    designs = []
    for m in np.unique(support[support > 0]):
        entries = np.flatnonzero(support == m)
        width = int(m) * (int(m) + 1) // 2
        a = columns[slots[entries], : int(m)]
        scaled = a * _SQRT2
        design = np.empty((entries.size, width, n))
        for e in range(width):
            r, s = pair_rows[e], pair_cols[e]
            np.multiply(a[:, r], a[:, s] if r == s else scaled[:, s], out=design[:, e])
        if skip is not None and not zeroed:
            design[:, :, skip] = 0.0
        designs.append((entries, width, design))
    for g, (rows_g, width_g, design_g) in enumerate(designs):
        flat_g = design_g.reshape(rows_g.size, -1)
        for rows_h, width_h, design_h in designs[g:]:
            width = min(width_g, width_h) * n
            block = flat_g[:, :width] @ design_h.reshape(rows_h.size, -1)[:, :width].T
            gram[np.ix_(rows_g, rows_h)] = block
            gram[np.ix_(rows_h, rows_g)] = block.T
        for u, axis in enumerate(unit_axes):
            if axis >= 0 and _diagonal_entry(int(axis)) < width_g:
                column = design_g[:, _diagonal_entry(int(axis))].sum(axis=-1)
                gram[n_general + u, rows_g] = gram[rows_g, n_general + u] = column
        if z is not None:
            cross[rows_g] = flat_g @ z[:width_g].reshape(-1)
    for u, axis in enumerate(unit_axes):
        if axis >= 0:
            gram[n_general + u, n_general + u] = count
            if z is not None:
                cross[n_general + u] = z[_diagonal_entry(int(axis))].sum()
    const = 0.0 if z is None else float(np.vdot(z, z))
    return _DiagSums(gram, cross, const, count)


def _gram_rows(x: FloatArray) -> FloatArray:
    """``x xᵀ`` for C-contiguous x (Q, M) by BLAS ``syrk`` (one triangle), without a copy."""
    upper = scipy.linalg.blas.dsyrk(1.0, x.T, trans=1)
    return np.asarray(np.triu(upper) + np.triu(upper, 1).T, dtype=float)


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
