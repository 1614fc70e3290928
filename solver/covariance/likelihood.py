"""End-effector covariance (Eq. 12) and the likelihood estimators: ML (Eq. 16–17) and REML.

All residuals, Jacobians and covariances are in the end-effector frame, [v; w], m and rad.
For θ the NLLs return ``Ψ_f = ∂NLL/∂Σ_f`` (F, 6, 6, symmetric); ``∂NLL/∂θ_p = ⟨Ψ_f, E_p⟩``.

Gradient (ML): ``∂/∂Σ_E [log det Σ_E + rᵀΣ_E⁻¹r] = Σ_E⁻¹ − Σ_E⁻¹rrᵀΣ_E⁻¹`` =: Ω, so
``Ψ_f = Σ_n A_fᵀ Ω_n A_f``. Its zero is a moment match weighted by Σ_E⁻¹ ⊗ Σ_E⁻¹, not Eq. (13):
the paper's Eq. (20–21) drop the weights (and a sign), so ML and moment matching differ.

REML: with the deterministic fit's Jacobian X (N, d, p) and V = blockdiag Σ_E(q_n),
``NLL_R = Σ_n log det Σ_E(q_n) + log det(XᵀV⁻¹X) + rᵀPr``, P = V⁻¹ − V⁻¹X(XᵀV⁻¹X)⁻¹XᵀV⁻¹.
It depends on X only through its column space (X is orthonormalised once). Its gradient has
the ML form with ``Ω_n = P_nn − s_n s_nᵀ``, s = Pr (block n).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray
from solver.covariance._blas import gram_tn
from solver.covariance.layout import CovarianceLayout, column_matrix
from solver.covariance.samples import ArraySamples, CovarianceSamples, SampleChunk, total
from solver.covariance.statistics import design_gram
from solver.errors import CalibrationError, SolverError
from solver.small_spd import spd_factors


def ee_covariance_batch(
    frame_jacobians: FloatArray,
    frame_covariances: FloatArray,
    noise_covariance: FloatArray | None = None,
) -> FloatArray:
    """Eq. (12): ``Σ_E(q_n) = Σ_n + Σ_f A_f(q_n) Σ_f A_f(q_n)ᵀ``, (N, d, d) — the one kernel of
    Eq. (12) that the likelihoods, the predictions and the rankings' reference all call.

    ``frame_jacobians`` (N, F, d, 6) map local twists [v; w] of each frame to the
    end-effector-frame residual; ``frame_covariances`` (F, 6, 6) in m²/rad²;
    ``noise_covariance`` (6, 6) acts in the end-effector frame (its first d×d block is used).
    When every Σ_f is diagonal, the frames' columns side by side are scaled by the variances
    and multiplied once per sample (6F instead of (6F)² products per row).
    """
    n, n_frames, d, _ = frame_jacobians.shape
    covariances = np.asarray(frame_covariances, dtype=float)
    variances = np.diagonal(covariances, axis1=1, axis2=2)
    if np.array_equal(covariances, variances[:, :, None] * np.eye(6)):
        columns = frame_jacobians.transpose(0, 2, 1, 3).reshape(n, d, 6 * n_frames)
        out = (columns * variances.reshape(-1)) @ columns.transpose(0, 2, 1)
    else:
        out = np.einsum(
            "nfdi,fij,nfej->nde", frame_jacobians, covariances, frame_jacobians, optimize=True
        )
    if noise_covariance is not None:
        out = out + np.asarray(noise_covariance)[:d, :d]
    return np.asarray(out, dtype=float)


def theta_gradient(layout: CovarianceLayout, psi: FloatArray) -> FloatArray:
    """``∂NLL/∂θ_p = ⟨Ψ_f, E_p⟩``: Ψ_ii for variances, 2Ψ_ij for covariances, (Q,); ``psi``
    per frame of the columns (a tied noise frame: per placement, summed by the fold)."""
    if layout.is_tied:
        return layout.tie_matrix.T @ theta_gradient(layout.untied(), psi)
    f, i, j = layout.param_frame, layout.param_row, layout.param_col
    return np.where(layout.is_variance, 1.0, 2.0) * psi[f, i, j]


@dataclass(frozen=True)
class _Chunk:
    columns: FloatArray  # C (n, d, 6F)
    residuals: FloatArray  # (n, d)
    basis: FloatArray | None  # (n, d, k)


@dataclass(frozen=True)
class _EECovariance:
    """What a kernel needs to form Σ_E on a chunk: the θ layout, every frame's Σ_f (F, 6, 6),
    noise frame included when estimated, a known part of Σ_E (d, d) or None, and the transform
    (p, k) of the fit Jacobian to an orthonormal basis of its column space (REML) or None."""

    layout: CovarianceLayout
    covariances: FloatArray
    known: FloatArray | None
    transform: FloatArray | None = None

    def chunk(self, samples: SampleChunk) -> _Chunk:
        basis = None
        if self.transform is not None:
            assert samples.fit_jacobian is not None
            basis = samples.fit_jacobian @ self.transform
        return _Chunk(column_matrix(samples.frame_jacobians, self.layout), samples.residuals, basis)


def _ee_chunk(
    chunk: _Chunk, covariances: FloatArray, known: FloatArray | None
) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """Σ_E, its inverse and log det for one chunk; None if some Σ_E is not positive definite."""
    cov = ee_covariance_batch(_frame_view(chunk.columns), covariances, known)
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    factors = spd_factors(cov)  # all rows at once: ~2x faster than numpy.linalg (29 vs 64 ms)
    if not np.all(factors.positive_definite):
        return None
    return cov, factors.inverse(), factors.log_det


def _frame_view(columns: FloatArray) -> FloatArray:
    """The column matrix C (n, d, 6F) of :func:`column_matrix` as frame Jacobians
    (n, F, d, 6), without a copy."""
    n, d, c = columns.shape
    return columns.reshape(n, d, c // 6, 6).transpose(0, 2, 1, 3)


def _psi_from_omega(chunk: _Chunk, omega: FloatArray, layout: CovarianceLayout) -> FloatArray:
    """Σ_n A_fᵀ Ω_n A_f for every frame, (F, 6, 6); for diagonal Σ only its diagonal, the
    only entries the gradient of a diagonal θ reads (:func:`theta_gradient`).

    Stacks of 6×6 products per frame: a single (6F × n·d)·(n·d × 6F) GEMM would compute the
    unneeded off-diagonal blocks and, on few cores, suffers from BLAS thread contention.
    """
    cols = chunk.columns
    t = omega @ cols
    n_frames = cols.shape[2] // 6  # the columns' frames (a tied noise: one per placement)
    if layout.structure == "diag":
        diagonal = np.einsum("ndc,ndc->c", cols, t).reshape(n_frames, 6)
        return diagonal[:, :, None] * np.eye(6)
    return np.stack(
        [
            (cols[:, :, 6 * f : 6 * f + 6].transpose(0, 2, 1) @ t[:, :, 6 * f : 6 * f + 6]).sum(0)
            for f in range(n_frames)
        ]
    )


def gaussian_nll(
    theta: FloatArray,
    samples: CovarianceSamples,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
) -> tuple[float, FloatArray]:
    """Eq. (17): ``Σ_n [log det Σ_E(q_n) + r_nᵀ Σ_E(q_n)⁻¹ r_n]`` and Ψ = ∂/∂Σ_f (F, 6, 6).

    Returns (inf, 0) where some Σ_E is not positive definite. Constants (N·d·log 2π) omitted.
    One pass over the samples.
    """
    model = _EECovariance(layout, layout.column_covariances(theta), known_covariance)
    parts = samples.map(_ml_chunk, model)
    done = [part for part in parts if part is not None]
    if len(done) < len(parts):
        return float("inf"), np.zeros((layout.untied().n_frames, 6, 6))
    value = float(sum(part[0] for part in done))
    psi = total([part[1] for part in done])
    return value, 0.5 * (psi + psi.transpose(0, 2, 1))


def _ml_chunk(model: _EECovariance, samples: SampleChunk) -> tuple[float, FloatArray] | None:
    chunk = model.chunk(samples)
    ee = _ee_chunk(chunk, model.covariances, model.known)
    if ee is None:
        return None
    _, inv, logdet = ee
    a = np.einsum("nij,nj->ni", inv, chunk.residuals)
    value = float(logdet.sum() + np.einsum("ni,ni->", a, chunk.residuals))
    omega = inv - a[:, :, None] * a[:, None, :]
    return value, _psi_from_omega(chunk, omega, model.layout)


def fit_basis_transform(samples: CovarianceSamples, *, rtol: float = 1e-10) -> FloatArray:
    """``T`` (p, k) such that ``X_n T`` is an orthonormal basis of the column space of the
    stacked fit Jacobian X (Σ_n T ᵀX_nᵀX_n T = I), from the R factors of the chunks merged in
    order (a tall-skinny QR: as accurate as an SVD of X, one pass). With ``XᵀX = RᵀR =
    V S² Vᵀ``, ``T = V S⁻¹`` over the singular values above ``rtol`` of the largest (the
    unidentifiable parameters the deterministic fit removed are dropped); REML only depends
    on this column space."""
    factors = [r for r in samples.map(_fit_r, None) if r is not None]
    if not factors:
        raise SolverError("fit_jacobian has no rows")
    upper = factors[0]
    for r in factors[1:]:
        upper = np.asarray(np.linalg.qr(np.vstack([upper, r]), mode="r"), dtype=float)
    _, s, vt = np.linalg.svd(upper)
    keep = s > rtol * (s[0] if s.size else 0.0)
    if not np.any(keep):
        raise SolverError("fit_jacobian has no non-zero column")
    return np.asarray(vt[keep].T / s[keep], dtype=float)


def _fit_r(_: None, samples: SampleChunk) -> FloatArray | None:
    """R (p, p) of the chunk's stacked fit Jacobian (n·d, p), None for an empty chunk."""
    if samples.fit_jacobian is None:
        raise SolverError("REML needs the deterministic fit's Jacobian with the samples")
    n, d, p = samples.fit_jacobian.shape
    if n == 0:
        return None
    stacked = samples.fit_jacobian.reshape(n * d, p)
    if n * d < p:
        stacked = np.vstack([stacked, np.zeros((p - n * d, p))])
    return np.asarray(np.linalg.qr(stacked, mode="r"), dtype=float)


def restricted_nll(
    theta: FloatArray,
    samples: CovarianceSamples,
    transform: FloatArray,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
) -> tuple[float, FloatArray]:
    """REML NLL ``Σ log det Σ_E + log det(XᵀV⁻¹X) + rᵀPr`` and Ψ = ∂/∂Σ_f (F, 6, 6).

    ``transform`` (p, k) from :func:`fit_basis_transform` (X is used through the orthonormal
    basis ``X T``). Two passes over the samples: the sums ``XᵀV⁻¹X`` and ``XᵀV⁻¹r`` first,
    then Ψ, which needs them; O(N·d²·k + N·d·k²) per evaluation.
    """
    model = _EECovariance(layout, layout.column_covariances(theta), known_covariance, transform)
    parts = samples.map(_reml_sums, model)
    done = [part for part in parts if part is not None]
    if len(done) < len(parts):
        return float("inf"), np.zeros((layout.untied().n_frames, 6, 6))
    value = float(sum(part[0] for part in done))
    fisher_x = total([part[1] for part in done])
    u = total([part[2] for part in done])
    fisher_x = 0.5 * (fisher_x + fisher_x.T)
    try:
        chol = np.linalg.cholesky(fisher_x)
    except np.linalg.LinAlgError:
        return float("inf"), np.zeros((layout.untied().n_frames, 6, 6))
    m_inv = np.linalg.inv(fisher_x)
    m_inv_u = m_inv @ u
    value += 2.0 * float(np.log(np.diag(chol)).sum()) - float(u @ m_inv_u)
    psi = total(samples.map(_reml_psi, (model, m_inv, m_inv_u)))
    return value, 0.5 * (psi + psi.transpose(0, 2, 1))


def restriction(
    theta: FloatArray,
    samples: ArraySamples,
    transform: FloatArray,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
) -> tuple[float, FloatArray]:
    """REML's restriction terms ``log det(XᵀV⁻¹X) − uᵀM⁻¹u`` (REML minus ML NLL) and their
    Ψ on ``samples`` (``transform`` their own :func:`fit_basis_transform`).

    They account for the p parameters the deterministic fit used: their gradient is O(p)
    whatever the number of samples (for V = σ²I it is exactly that of −p log σ²), against
    O(N) for the likelihood terms, so on a large recording they may be taken on an evenly
    spaced subset; (inf, 0) where some Σ_E is not positive definite."""
    reml = restricted_nll(theta, samples, transform, layout, known_covariance=known_covariance)
    ml = gaussian_nll(theta, samples, layout, known_covariance=known_covariance)
    if not (np.isfinite(reml[0]) and np.isfinite(ml[0])):
        return float("inf"), np.zeros((layout.untied().n_frames, 6, 6))
    return reml[0] - ml[0], reml[1] - ml[1]


def _reml_sums(
    model: _EECovariance, samples: SampleChunk
) -> tuple[float, FloatArray, FloatArray] | None:
    """A chunk's ``Σ log det Σ_E + rᵀV⁻¹r``, ``XᵀV⁻¹X`` (k, k) and ``XᵀV⁻¹r`` (k,)."""
    chunk = model.chunk(samples)
    ee = _ee_chunk(chunk, model.covariances, model.known)
    if ee is None:
        return None
    _, inv, logdet = ee
    assert chunk.basis is not None
    k = chunk.basis.shape[2]
    q = inv @ chunk.basis  # V⁻¹X, (n, d, k)
    a = np.einsum("nij,nj->ni", inv, chunk.residuals)
    value = float(logdet.sum() + np.einsum("ni,ni->", a, chunk.residuals))
    fisher_x = gram_tn(chunk.basis.reshape(-1, k), q.reshape(-1, k))
    return value, fisher_x, np.einsum("ndk,nd->k", chunk.basis, a)


def _reml_psi(
    argument: tuple[_EECovariance, FloatArray, FloatArray], samples: SampleChunk
) -> FloatArray:
    """A chunk's Ψ with ``Ω_n = P_nn − s_n s_nᵀ`` given (XᵀV⁻¹X)⁻¹ and (XᵀV⁻¹X)⁻¹XᵀV⁻¹r."""
    model, m_inv, m_inv_u = argument
    chunk = model.chunk(samples)
    ee = _ee_chunk(chunk, model.covariances, model.known)
    assert ee is not None and chunk.basis is not None  # the first pass saw them all PD
    inv = ee[1]
    q = inv @ chunk.basis
    s = np.einsum("nij,nj->ni", inv, chunk.residuals) - q @ m_inv_u
    p_nn = inv - (q @ m_inv) @ q.transpose(0, 2, 1)
    omega = p_nn - s[:, :, None] * s[:, None, :]
    return _psi_from_omega(chunk, omega, model.layout)


def average_information(
    theta: FloatArray,
    samples: ArraySamples,
    layout: CovarianceLayout,
    *,
    transform: FloatArray | None = None,
    known_covariance: FloatArray | None = None,
) -> FloatArray:
    """Average information of the NLL (ML, or REML with ``transform``): ``H_pq = u_pᵀ P u_q``,
    (Q, Q), with ``u_p = V_p P r`` (V_p = ∂V/∂θ_p, blockdiag over the samples; P = V⁻¹ for
    ML, the REML projection of :func:`restricted_nll` otherwise), on ``samples`` (in memory:
    at most :data:`~.fitting.METRIC_SAMPLES` of them).

    It is the mean of the observed and the expected information of ``NLL = −2 log L`` at any
    θ where ``E[rrᵀ] = V`` (the "AI" of Gilmour, Thompson & Cullis 1995, the metric of REML
    software). Unlike the expected information it sees the data: Fisher scoring crawls towards
    a variance whose optimum is on the boundary θ_p = 0 (its expected curvature grows as the
    variance shrinks), the AI step reaches it (TIAGo's 21-pose REML: 200 steps, now ~20).

    Computed as the Gram of ``Z⊥``, the whitened ``L⁻¹u`` with the whitened fit Jacobian
    ``L⁻¹X`` projected out by an orthonormal basis (V = LLᵀ): PSD by construction, where
    ``Σ uᵀV⁻¹u − (XᵀV⁻¹u)ᵀ(XᵀV⁻¹X)⁻¹(XᵀV⁻¹u)`` loses its small eigenvalues to cancellation
    (−1e-6 of the largest on the TIAGo file). A tied layout is computed untied and folded.
    """
    if layout.is_tied:
        tie = layout.tie_matrix
        untied = average_information(
            tie @ theta,
            samples,
            layout.untied(),
            transform=transform,
            known_covariance=known_covariance,
        )
        return tie.T @ untied @ tie
    model = _EECovariance(layout, layout.column_covariances(theta), known_covariance, transform)
    whole = SampleChunk(
        samples.residuals, samples.frame_jacobians, samples.fit_jacobian, samples.sample_rows
    )
    chunk = model.chunk(whole)
    cov = ee_covariance_batch(_frame_view(chunk.columns), model.covariances, model.known)
    factors = spd_factors(0.5 * (cov + cov.transpose(0, 2, 1)))
    if not np.all(factors.positive_definite):
        raise CalibrationError("Σ_E(q) is not positive definite: no average information")
    white_r = factors.whiten(chunk.residuals)  # L⁻¹r, (n, d)
    n, d = white_r.shape
    left = factors.inverse_factor.transpose(2, 0, 1)  # L⁻¹, (n, d, d)
    basis = None
    if chunk.basis is not None:
        white_x = (left @ chunk.basis).reshape(n * d, -1)
        basis = np.linalg.qr(white_x)[0]  # orthonormal, (n·d, k)
        flat = white_r.reshape(-1)
        white_r = (flat - basis @ (basis.T @ flat)).reshape(n, d)  # (I − QQᵀ) L⁻¹r
    s = np.einsum("nji,nj->ni", left, white_r)  # P r, block n: L⁻ᵀ (projected L⁻¹r)
    cols = chunk.columns
    beta = np.einsum("ndc,nd->nc", cols, s)  # a_cᵀ s_n per column c
    ci, cj = layout.column_i, layout.column_j
    half = np.where(layout.is_variance, 0.5, 1.0)
    # S_p s = half_p (a_i (a_jᵀ s) + a_j (a_iᵀ s)), as (n, d, Q)
    u = half * (cols[:, :, ci] * beta[:, None, cj] + cols[:, :, cj] * beta[:, None, ci])
    white_u = (left @ u).reshape(n * d, -1)
    if basis is not None:
        white_u = white_u - basis @ (basis.T @ white_u)
    norms = np.linalg.norm(white_u, axis=0)
    unit = np.where(norms > 0.0, norms, 1.0)
    gram = gram_tn(white_u / unit)
    return np.asarray(0.5 * (gram + gram.T) * np.outer(unit, unit), dtype=float)


def observed_information(
    theta: FloatArray,
    samples: ArraySamples,
    layout: CovarianceLayout,
    *,
    transform: FloatArray | None = None,
    known_covariance: FloatArray | None = None,
    average: FloatArray | None = None,
) -> FloatArray:
    """The Hessian of the NLL (= −2 log L; ML, or REML with ``transform``) in θ, (Q, Q), on
    ``samples`` (in memory): ``∂²NLL/∂θ_p∂θ_q = 2·AI_pq − 2·I_pq``.

    V is linear in θ (V_pq = 0), so ``∂²/∂θ_p∂θ_q log det V = −tr(V⁻¹V_pV⁻¹V_q)`` and
    ``∂²/∂θ_p∂θ_q rᵀV⁻¹r = 2 rᵀV⁻¹V_pV⁻¹V_qV⁻¹r``; for REML P takes the place of V⁻¹ (its
    log det(XᵀV⁻¹X) term turns −tr(V⁻¹…) into −tr(P…)). With the average information
    ``AI_pq = rᵀPV_pPV_qPr`` (:func:`average_information`) and the expected information
    ``I_pq = ½ tr(PV_pPV_q)`` (:func:`fisher_information_ml`, :func:`fisher_information_reml`)
    the Hessian is ``2·AI − 2·I``: AI = ½(Hessian + 2·I) is the mean of the observed and the
    expected curvature. Where the data curve the NLL less than expected (the weak directions
    of a small recording, ``Hessian < 2·I``) AI overrates the curvature, and scoring with it
    shortens every step there: on the TIAGo Qualisys file by ~2× (:mod:`.fitting`).
    ``average``: AI at θ when the caller has it. Not positive definite in general (a variance
    whose optimum is on its bound often has negative curvature, log det being concave).
    """
    if average is None:
        average = average_information(
            theta, samples, layout, transform=transform, known_covariance=known_covariance
        )
    if transform is None:
        expected = fisher_information_ml(
            theta, samples.frame_jacobians, layout, known_covariance=known_covariance
        )
    else:
        if samples.fit_jacobian is None:
            raise CalibrationError("REML's observed information needs the fit Jacobian")
        expected = fisher_information_reml(
            theta,
            samples.frame_jacobians,
            samples.fit_jacobian @ transform,
            layout,
            known_covariance=known_covariance,
        )
    return np.asarray(2.0 * average - 2.0 * expected, dtype=float)


def whitening(
    theta: FloatArray,
    frame_jacobians: FloatArray,
    layout: CovarianceLayout,
    known_covariance: FloatArray | None,
    *,
    inverse: bool,
) -> FloatArray:
    """Per sample L⁻¹ (inverse=True) or Lᵀ (False) with Σ_E(q_n) = L Lᵀ, (N, d, d).

    Lᵀ is the symmetric square root (works for singular PSD Σ_E); L⁻¹ needs Σ_E ≻ 0.
    """
    cols = column_matrix(frame_jacobians, layout)
    cov = ee_covariance_batch(_frame_view(cols), layout.column_covariances(theta), known_covariance)
    if not inverse:
        eigval, eigvec = np.linalg.eigh(0.5 * (cov + cov.transpose(0, 2, 1)))
        root = (eigvec * np.sqrt(np.clip(eigval, 0.0, None))[:, None, :]) @ eigvec.transpose(
            0, 2, 1
        )
        return root
    try:
        chol = np.linalg.cholesky(0.5 * (cov + cov.transpose(0, 2, 1)))
    except np.linalg.LinAlgError as exc:
        raise CalibrationError(
            "Σ_E(q) is singular at the estimate: standard errors need a positive-definite "
            "end-effector covariance (estimate the noise or pass a known noise covariance)"
        ) from exc
    return np.linalg.inv(chol)


def fisher_information_ml(
    theta: FloatArray,
    frame_jacobians: FloatArray,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
) -> FloatArray:
    """Expected Fisher information of θ for Eq. (16): ``½ Σ_n tr(Σ_E⁻¹ ∂_pΣ_E Σ_E⁻¹ ∂_qΣ_E)``.

    Equal to half the moment Gram of the whitened Jacobians L_n⁻¹A_f, (Q, Q).
    """
    left = whitening(theta, frame_jacobians, layout, known_covariance, inverse=True)
    return 0.5 * design_gram(frame_jacobians, layout, left=left).gram


def fisher_information_reml(
    theta: FloatArray,
    frame_jacobians: FloatArray,
    fit_basis: FloatArray,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
    chunk_size: int = 512,
) -> FloatArray:
    """Expected Fisher information of the REML likelihood: ``½ tr(P V_p P V_q)``, (Q, Q).

    Whitened (W = blockdiag L_n⁻¹, U orthonormal basis of W X, Π_n = U_n U_nᵀ = R_n R_nᵀ with
    R_n its d×d square root, S̃ = L⁻¹ ∂Σ_E L⁻ᵀ):
    ``tr(PV_pPV_q) = Σ_n ⟨S̃_p, S̃_q⟩ − 2 Σ_n ⟨S̃_p R_n, S̃_q R_n⟩ + ⟨Z_p, Z_q⟩``,
    ``Z_p = Σ_n U_nᵀ S̃_p U_n``. A tied layout is computed untied and folded (``Tᵀ I T``).
    """
    if layout.is_tied:
        tie = layout.tie_matrix
        untied = fisher_information_reml(
            tie @ theta,
            frame_jacobians,
            fit_basis,
            layout.untied(),
            known_covariance=known_covariance,
            chunk_size=chunk_size,
        )
        return tie.T @ untied @ tie
    left = whitening(theta, frame_jacobians, layout, known_covariance, inverse=True)
    n, d, k = fit_basis.shape
    white_x = left @ fit_basis
    basis = np.linalg.svd(white_x.reshape(n * d, k), full_matrices=False)[0].reshape(n, d, -1)
    proj = basis @ basis.transpose(0, 2, 1)
    eigval, eigvec = np.linalg.eigh(proj)
    root = eigvec * np.sqrt(np.clip(eigval, 0.0, None))[:, None, :]  # R Rᵀ = Π_n, (n, d, d)
    term1 = design_gram(frame_jacobians, layout, left=left).gram
    q = layout.n_params
    half = np.where(layout.is_variance, 0.5, 1.0)
    term2, z = np.zeros((q, q)), np.zeros((q, basis.shape[2], basis.shape[2]))
    ci, cj = layout.column_i, layout.column_j
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        cols = left[start:stop] @ column_matrix(frame_jacobians[start:stop], layout)
        a_r = cols.transpose(0, 2, 1) @ root[start:stop]  # (m, 6F, d): a_cᵀ R
        # S̃_p R = s_p (a_i (a_jᵀR) + a_j (a_iᵀR)), as (m, d, d, Q)
        r_i = a_r[:, ci, :].transpose(0, 2, 1)[:, None]
        r_j = a_r[:, cj, :].transpose(0, 2, 1)[:, None]
        sr = half * (cols[:, :, ci][:, :, None, :] * r_j + cols[:, :, cj][:, :, None, :] * r_i)
        term2 += gram_tn(sr.reshape(-1, q))
        beta = cols.transpose(0, 2, 1) @ basis[start:stop]  # (m, 6F, k): a_cᵀ u
        zb = beta[:, ci, :].transpose(1, 2, 0) @ beta[:, cj, :].transpose(1, 0, 2)  # Σ_m, (Q,k,k)
        z += half[:, None, None] * (zb + zb.transpose(0, 2, 1))
    zf = z.reshape(q, -1)
    out = 0.5 * (term1 - 2.0 * term2 + gram_tn(zf.T))
    return 0.5 * (out + out.T)


def moment_sandwich_meat(
    theta: FloatArray,
    frame_jacobians: FloatArray,
    layout: CovarianceLayout,
    *,
    known_covariance: FloatArray | None = None,
) -> FloatArray:
    """Cov of h under Gaussian residuals: ``Σ_n B_nᵀ Cov(vec r rᵀ) B_n = 2 Σ_n K̃ᵀK̃``, (Q, Q).

    K̃ uses the coloured Jacobians L_nᵀA_f (Σ_E = LLᵀ): ``Cov(⟨S_p, rrᵀ⟩, ⟨S_q, rrᵀ⟩) =
    2 tr(S_p Σ_E S_q Σ_E)``. The moment estimator's covariance is G⁺ · meat · G⁺.
    """
    left = whitening(theta, frame_jacobians, layout, known_covariance, inverse=False)
    return 2.0 * design_gram(frame_jacobians, layout, left=left).gram


def check_likelihood_inputs(
    residuals: FloatArray, frame_jacobians: FloatArray, layout: CovarianceLayout
) -> None:
    if residuals.shape != (frame_jacobians.shape[0], layout.residual_dim):
        raise SolverError(f"residuals must be (N, {layout.residual_dim}), got {residuals.shape}")
    if not np.all(np.isfinite(residuals)):
        raise CalibrationError("residuals contain NaN or inf")
