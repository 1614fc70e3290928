"""Polishing a cone program's answer on its face: Eq. (14) (and the scoring QPs that share
its form) solved exactly once the face of the PSD cone that holds the optimum is known.

An interior-point or first-order answer is accurate to its tolerance (a KKT residual of 1e-8
moves θ by 1e-4 relative on a rank-deficient full-Σ problem), and where it stops depends on the
last bits of the BLAS arithmetic. The optimum itself lies on a face of the cone: every Σ̂_f =
U_f S_f U_fᵀ with U_f the eigenvectors of Σ̂_f that are not zero at the optimum. On that face the
problem is an unconstrained linear least squares in S_f, solved to rounding by an SVD; the
answer is kept when it is feasible (every S_f ⪰ 0) and its KKT residual is smaller — that check
certifies the face was guessed right. Diagonal layouts are the special case of 1×1 blocks (the
face is the support of θ̂).
"""

from __future__ import annotations

import numpy as np

from solver.arrays import FloatArray
from solver.covariance.layout import CovarianceLayout
from solver.covariance.objective import ScaledProblem, projected_gradient_residual

FACE_RTOLS = (1e-6, 1e-9, 1e-4)
"""Eigenvalues of Σ̂_f above this fraction of the largest of all frames span the face; each is
tried in turn and the polish with the smallest KKT residual is kept."""


def face_map(theta_scaled: FloatArray, layout: CovarianceLayout, rtol: float) -> FloatArray:
    """M (Q, S) with θ̂ = M s for every θ̂ on the face of the cone that ``theta_scaled`` (Q,)
    lies on (eigenvalues of Σ̂_f at most ``rtol`` of the largest of all frames count as zero).

    s holds, per frame, the weighted half-vectorisation of S_f (off-diagonal entries as
    (e_a e_bᵀ + e_b e_aᵀ)/√2, so that ‖s‖ = ‖S‖_F whichever eigenbasis of a repeated
    eigenvalue U_f is). Diagonal layouts: the entries above ``rtol`` of the largest.
    """
    if layout.structure == "diag":
        values = np.asarray(theta_scaled, dtype=float)
        on = values > rtol * max(float(values.max(initial=0.0)), 1e-300)
        return np.eye(layout.n_params)[:, on]
    values, vectors = np.linalg.eigh(layout.frame_covariances(theta_scaled))
    largest = max(float(values.max(initial=0.0)), 1e-300)
    columns: list[FloatArray] = []
    for f in range(layout.n_frames):
        mine = np.flatnonzero(layout.param_frame == f)
        if mine.size == 0:
            continue
        basis = vectors[f][:, values[f] > rtol * largest]  # (6, r), zero on fixed axes
        rows, cols = layout.param_row[mine], layout.param_col[mine]
        for a in range(basis.shape[1]):
            for b in range(a, basis.shape[1]):
                u_a, u_b = basis[:, a], basis[:, b]
                entry = u_a[rows] * u_b[cols]
                if a != b:
                    entry = (entry + u_b[rows] * u_a[cols]) / np.sqrt(2.0)
                column = np.zeros(layout.n_params)
                column[mine] = entry
                columns.append(column)
    if not columns:
        return np.zeros((layout.n_params, 0))
    return np.stack(columns, axis=1)


def polish_on_face(theta: FloatArray, problem: ScaledProblem) -> tuple[FloatArray, float]:
    """The exact minimiser of ``‖Rθ̂ − b‖²`` on the face ``theta`` (Q,, unscaled, PSD) lies on,
    when that is feasible and closer to optimal; else ``theta``. Returns θ and its KKT
    residual (:func:`~.objective.projected_gradient_residual`).

    The face is kept as the answer found it (its eigenvectors): what is solved exactly is the
    value S_f on it. Diagonal Σ: exact. Full Σ: the eigenvectors carry the answer's own error,
    so the polish ends near a KKT residual of 1e-9, not at rounding (a full-Σ Panda position
    recording; Newton steps that also turn the face were tried and leave the cone where the
    moment problem is only weakly identified).
    """
    layout = problem.layout
    best, best_kkt = theta, projected_gradient_residual(theta, problem)
    theta_scaled = problem.scaling.to_scaled(theta)
    for rtol in FACE_RTOLS:
        face = face_map(theta_scaled, layout, rtol)
        if face.shape[1] == 0:
            continue
        s = np.linalg.lstsq(problem.factor @ face, problem.target, rcond=None)[0]
        candidate_scaled = face @ s
        if not _feasible(candidate_scaled, layout):
            continue
        candidate = problem.scaling.from_scaled(candidate_scaled)
        kkt = projected_gradient_residual(candidate, problem)
        if kkt < best_kkt:
            best, best_kkt = candidate, kkt
    return best, best_kkt


def _feasible(theta_scaled: FloatArray, layout: CovarianceLayout) -> bool:
    """Every Σ̂_f ⪰ 0 up to rounding (eigenvalues ≥ −1e-12 of the largest)."""
    values = np.linalg.eigvalsh(layout.frame_covariances(theta_scaled))
    return bool(values.min(initial=0.0) >= -1e-12 * max(float(values.max(initial=0.0)), 1e-300))
