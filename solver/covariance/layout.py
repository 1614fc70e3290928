"""Parameter layout θ of the covariance calibration (paper Eq. 13) and the design of Eq. (12).

Frames: every random source f has a 6×6 covariance Σ_f of a local twist [v; w] (m, rad) and an
end-effector-frame Jacobian A_f(q) (d×6, d = 6 full pose or 3 position-only, DESIGN.md §2).
The measurement noise is one more frame (listed last) whose Jacobian is the first d rows of I_6
— or, for residuals laid out otherwise (a subset of pose components, several markers per row),
a noise frame with one or more placements ``U_k`` (d×6, constant 0/1: noise axis a goes to
residual row ``rows_k[a]``, −1: nowhere), all sharing the frame's Σ_n, so that its part of
Eq. (12) is ``Σ_k U_k Σ_n U_kᵀ`` (e.g. ``blockdiag(Σ_n, …, Σ_n)`` over markers). A layout
with several placements ("tied") computes through :meth:`CovarianceLayout.untied` (each
placement its own frame, the ordinary rank-one columns) and folds the result with
:attr:`CovarianceLayout.tie_matrix`: Σ_E is linear in θ, so Grams, gradients and information
matrices fold as ``Tᵀ·T``.

θ holds one entry per free parameter p = (frame f, axis i, axis j), i ≤ j, with
``Σ_f = Σ_p θ_p E_p``, ``E_p = e_i e_jᵀ + e_j e_iᵀ`` (i ≠ j) or ``e_i e_iᵀ`` (i = j): θ_p is the
variance (m², rad²) or the covariance entry itself. Structure "diag" has only i = j.

Symmetric d×d matrices are handled as weighted half-vectorisations ``vech_w`` (diagonal entries
as they are, off-diagonal ones times √2), so that ``‖vech_w(S)‖₂ = ‖S‖_F = ‖vec(S)‖₂`` and the
paper's vec-based objective (Eq. 14) is unchanged while every row is kept once.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np

from solver.arrays import BoolArray, FloatArray, IntArray
from solver.errors import SolverError

Structure = Literal["diag", "full"]
POSE_AXES = ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z")
ROTATION_AXIS_NAMES = POSE_AXES[3:]
"""The rotational axes of a frame's twist, for ``free_axes`` of a rotation-only perturbation."""
TRANSLATION_AXES = (0, 1, 2)
ROTATION_AXES = (3, 4, 5)


@dataclass(frozen=True)
class CovarianceLayout:
    """Which covariance entries are estimated, and in which order θ stores them.

    ``frame_names`` lists every source, the noise frame(s) (if any) last. ``free_axes[f][i]``
    says whether axis i of frame f may carry randomness; for "full" all pairs of free axes are
    parameters. ``residual_dim`` d is 6 (pose), 3 (position-only) or any other residual size
    with ``noise_rows``. ``noise_frame`` names the first noise frame; ``noise_rows`` (per noise
    frame, its placements, each the residual row of the 6 axes, −1: none; empty for the
    default) lays the noise out; the default is one noise frame on rows 0..d−1.
    """

    frame_names: tuple[str, ...]
    structure: Structure
    residual_dim: int
    free_axes: tuple[tuple[bool, ...], ...]
    noise_frame: str | None
    noise_rows: tuple[tuple[tuple[int, ...], ...], ...] = ()

    @property
    def n_frames(self) -> int:
        return len(self.frame_names)

    @property
    def n_noise_frames(self) -> int:
        if self.noise_frame is None:
            return 0
        return max(len(self.noise_rows), 1)

    @property
    def n_chain_frames(self) -> int:
        """Frames whose Jacobians the caller supplies (all but the noise frames)."""
        return self.n_frames - self.n_noise_frames

    @property
    def noise_frame_names(self) -> tuple[str, ...]:
        return self.frame_names[self.n_chain_frames :]

    @property
    def placements(self) -> tuple[tuple[tuple[int, ...], ...], ...]:
        """Per noise frame (or, without one, of the known noise), its placements' rows."""
        if self.noise_rows:
            return self.noise_rows
        d = self.residual_dim
        return ((tuple(a if a < d else -1 for a in range(6)),),)

    @property
    def is_tied(self) -> bool:
        """Some estimated noise frame has several placements sharing its Σ_n."""
        return self.noise_frame is not None and any(len(p) > 1 for p in self.placements)

    @cached_property
    def noise_param_rows(self) -> IntArray:
        """Residual row of every noise entry of θ (diagonal layouts: its unit column), −1
        where the axis does not reach the residual, in θ order of the noise entries; for an
        untied layout (one placement per noise frame)."""
        if self.is_tied:
            raise SolverError("a tied noise layout has no single row per entry: use untied()")
        noise = np.flatnonzero(self.is_noise)
        table = np.array([p[0] for p in self.placements], dtype=np.intp).reshape(-1, 6)
        return table[self.param_frame[noise] - self.n_chain_frames, self.param_row[noise]]

    def noise_jacobians(self) -> FloatArray:
        """``U_k`` (K, d, 6) of every placement of every noise frame, in frame order (the
        columns :func:`column_matrix` appends)."""
        rows = [r for frame in self.placements for r in frame]
        out = np.zeros((len(rows), self.residual_dim, 6))
        for k, placement in enumerate(rows):
            for axis, row in enumerate(placement):
                if row >= 0:
                    out[k, row, axis] = 1.0
        return out

    @cached_property
    def _untied(self) -> tuple[CovarianceLayout, FloatArray]:
        names = list(self.frame_names[: self.n_chain_frames])
        free = list(self.free_axes[: self.n_chain_frames])
        rows: list[tuple[tuple[int, ...], ...]] = []
        for name, frame_free, frame in zip(
            self.noise_frame_names,
            self.free_axes[self.n_chain_frames :],
            self.placements,
            strict=True,
        ):
            for k, placement in enumerate(frame):
                names.append(name if len(frame) == 1 else f"{name}@{k + 1}")
                free.append(frame_free)
                rows.append((placement,))
        untied = CovarianceLayout(
            tuple(names),
            self.structure,
            self.residual_dim,
            tuple(free),
            self.noise_frame,
            tuple(rows),
        )
        tie = np.zeros((untied.n_params, self.n_params))
        source = np.arange(untied.n_frames)
        source[self.n_chain_frames :] = np.repeat(
            np.arange(self.n_chain_frames, self.n_frames), [len(p) for p in self.placements]
        )
        for q in range(untied.n_params):
            match = (
                (self.param_frame == source[untied.param_frame[q]])
                & (self.param_row == untied.param_row[q])
                & (self.param_col == untied.param_col[q])
            )
            tie[q, np.flatnonzero(match)[0]] = 1.0
        return untied, tie

    def untied(self) -> CovarianceLayout:
        """Every placement of a noise frame its own frame (``<name>@k``), same free axes."""
        return self._untied[0] if self.is_tied else self

    @property
    def tie_matrix(self) -> FloatArray:
        """T (Q_untied, Q): the untied θ of a θ (each noise placement a copy of its frame's)."""
        return self._untied[1] if self.is_tied else np.eye(self.n_params)

    def column_covariances(self, theta: FloatArray) -> FloatArray:
        """Σ of every frame of the columns of :func:`column_matrix` (each noise placement
        its frame's Σ_n), (F_chain + K, 6, 6)."""
        if not self.is_tied:
            return self.frame_covariances(theta)
        return self.untied().frame_covariances(self.tie_matrix @ theta)

    @cached_property
    def _params(self) -> tuple[IntArray, IntArray, IntArray]:
        frames, rows, cols = [], [], []
        for f, free in enumerate(self.free_axes):
            axes = [i for i in range(6) if free[i]]
            for a, i in enumerate(axes):
                for j in axes[a:] if self.structure == "full" else (i,):
                    frames.append(f)
                    rows.append(i)
                    cols.append(j)
        return (
            np.array(frames, dtype=np.intp),
            np.array(rows, dtype=np.intp),
            np.array(cols, dtype=np.intp),
        )

    @property
    def param_frame(self) -> IntArray:
        return self._params[0]

    @property
    def param_row(self) -> IntArray:
        return self._params[1]

    @property
    def param_col(self) -> IntArray:
        return self._params[2]

    @property
    def n_params(self) -> int:
        return int(self.param_frame.size)

    @cached_property
    def is_variance(self) -> BoolArray:
        """True for diagonal entries (variances) of θ, (Q,)."""
        return self.param_row == self.param_col

    @cached_property
    def is_noise(self) -> BoolArray:
        """True for entries of the noise frame, (Q,)."""
        return self.param_frame >= self.n_chain_frames

    @cached_property
    def column_i(self) -> IntArray:
        """Index of A_f[:, i] in the stacked column matrix C (d, 6F), (Q,)."""
        return self.param_frame * 6 + self.param_row

    @cached_property
    def column_j(self) -> IntArray:
        return self.param_frame * 6 + self.param_col

    def labels(self) -> list[str]:
        """``frame:var(w_x)`` / ``frame:cov(v_x,w_y)`` per θ entry."""
        out = []
        for f, i, j in zip(self.param_frame, self.param_row, self.param_col, strict=True):
            entry = f"var({POSE_AXES[i]})" if i == j else f"cov({POSE_AXES[i]},{POSE_AXES[j]})"
            out.append(f"{self.frame_names[f]}:{entry}")
        return out

    def frame_covariances(self, theta: FloatArray) -> FloatArray:
        """Σ_f of every frame from θ (Q,), (F, 6, 6), symmetric, m² / m·rad / rad²."""
        covs = np.zeros((self.n_frames, 6, 6))
        covs[self.param_frame, self.param_row, self.param_col] = theta
        covs[self.param_frame, self.param_col, self.param_row] = theta
        return covs

    def theta_from_covariances(self, frame_covariances: FloatArray) -> FloatArray:
        """θ (Q,) from Σ_f (F, 6, 6); entries outside the layout are dropped."""
        sym = 0.5 * (frame_covariances + frame_covariances.transpose(0, 2, 1))
        return sym[self.param_frame, self.param_row, self.param_col].copy()

    def frobenius_weights(self) -> FloatArray:
        """m_p = √2 for covariance entries, 1 for variances: ‖m∘θ‖₂ = ‖blockdiag(Σ_f)‖_F."""
        return np.where(self.is_variance, 1.0, np.sqrt(2.0))


def make_layout(
    frame_names: Sequence[str],
    residual_dim: int,
    *,
    structure: Structure = "diag",
    include_noise: bool = True,
    noise_name: str = "noise",
    free_axes: Mapping[str, Sequence[str]] | None = None,
    noise_rows: Mapping[str, Sequence[Sequence[int]]] | None = None,
) -> CovarianceLayout:
    """Layout for the caller's frames (+ the noise frame(s), last).

    ``free_axes`` maps a frame name to the axes (names from ``POSE_AXES``) that may be random;
    frames not named have all six free. ``noise_rows``: the noise frame by name, with its
    placements (one or more; each the residual row of the six axes, −1: none; an axis that
    reaches no row in any placement is not free), for residuals other than a pose or position
    (then ``residual_dim`` may be any size); None: one noise frame ``noise_name`` on rows
    0..d−1 (d = 6 or 3).
    """
    if noise_rows is None and residual_dim not in (3, 6):
        raise SolverError(f"residual_dim must be 3 or 6, got {residual_dim}")
    if noise_rows is not None:
        _check_noise_rows(noise_rows, residual_dim)
    if structure not in ("diag", "full"):
        raise SolverError(f"structure must be 'diag' or 'full', got {structure!r}")
    noise_names = (noise_name,) if noise_rows is None else tuple(noise_rows)
    names = tuple(frame_names) + (noise_names if include_noise else ())
    if len(set(names)) != len(names):
        raise SolverError(f"frame names must be unique (noise frame is {noise_name!r}): {names}")
    free_axes = dict(free_axes or {})
    unknown = set(free_axes) - set(names)
    if unknown:
        raise SolverError(f"free_axes names unknown frames {sorted(unknown)}; frames: {names}")
    free = []
    for name in names:
        axes = free_axes.get(name, POSE_AXES)
        bad = set(axes) - set(POSE_AXES)
        if bad:
            raise SolverError(
                f"free_axes[{name!r}] has unknown axes {sorted(bad)}; use {POSE_AXES}"
            )
        placements = (noise_rows or {}).get(name, [range(6)])
        reaches = [any(p[k] >= 0 for p in placements) for k in range(6)]
        free.append(tuple(a in axes and reaches[k] for k, a in enumerate(POSE_AXES)))
    rows = (
        ()
        if noise_rows is None
        else tuple(
            tuple(tuple(int(r) for r in placement) for placement in noise_rows[name])
            for name in noise_names
        )
    )
    layout = CovarianceLayout(
        names,
        structure,
        residual_dim,
        tuple(free),
        noise_names[0] if include_noise else None,
        rows,
    )
    if layout.n_params == 0:
        raise SolverError("no free covariance entries: check free_axes")
    return layout


def _check_noise_rows(noise_rows: Mapping[str, Sequence[Sequence[int]]], residual_dim: int) -> None:
    """Each noise frame: at least one placement of six rows in −1..d−1, no row twice."""
    if len(noise_rows) != 1:
        raise SolverError(f"noise_rows must name one noise frame, got {list(noise_rows)}")
    used: list[int] = []
    for name, placements in noise_rows.items():
        for rows in placements:
            if len(rows) != 6 or any(not -1 <= int(r) < residual_dim for r in rows):
                raise SolverError(
                    f"noise_rows[{name!r}]: each placement must give 6 residual rows in "
                    f"0..{residual_dim - 1} (or -1), got {list(rows)}"
                )
            used += [int(r) for r in rows if r >= 0]
        if not placements:
            raise SolverError(f"noise_rows[{name!r}] has no placement")
    if len(set(used)) != len(used):
        raise SolverError(f"noise_rows place two noise axes on one residual row: {noise_rows}")


def column_matrix(frame_jacobians: FloatArray, layout: CovarianceLayout) -> FloatArray:
    """Stack [A_1 … A_F, I_d×6 (noise)] into C (n, d, 6F): column f·6+i is A_f[:, i].

    ``frame_jacobians`` (n, F_chain, d, 6) maps local twists [v; w] of each chain frame to the
    end-effector-frame residual.
    """
    n, n_frames, d, six = frame_jacobians.shape
    if six != 6 or d != layout.residual_dim or n_frames != layout.n_chain_frames:
        raise SolverError(
            f"frame_jacobians must be (N, {layout.n_chain_frames}, {layout.residual_dim}, 6), "
            f"got {frame_jacobians.shape}"
        )
    cols = frame_jacobians.transpose(0, 2, 1, 3).reshape(n, d, 6 * n_frames)
    if layout.noise_frame is None:
        return np.ascontiguousarray(cols)
    units = layout.noise_jacobians().transpose(1, 0, 2).reshape(d, -1)
    noise = np.broadcast_to(units, (n, d, units.shape[1]))
    return np.concatenate([cols, noise], axis=2)


def vech_indices(dim: int) -> tuple[IntArray, IntArray, FloatArray]:
    """Rows, columns and √2-weights of ``vech_w`` for a dim×dim symmetric matrix."""
    rows, cols = np.triu_indices(dim)
    weights = np.where(rows == cols, 1.0, np.sqrt(2.0))
    return rows.astype(np.intp), cols.astype(np.intp), weights


def vech_w(matrices: FloatArray) -> FloatArray:
    """Weighted half-vectorisation of symmetric (..., d, d) → (..., d(d+1)/2)."""
    rows, cols, weights = vech_indices(matrices.shape[-1])
    return matrices[..., rows, cols] * weights


def design_matrix(columns: FloatArray, layout: CovarianceLayout) -> FloatArray:
    """Per-sample design K_n (n, D, Q) of Eq. (13): ``vech_w(Σ_E(q_n)) = K_n θ``.

    Column p of K_n is ``vech_w(A_f E_p A_fᵀ)``; ``columns`` is C from :func:`column_matrix`
    (possibly whitened on the left). This is the paper's B^(n) with duplicate rows merged.
    """
    rows, cols, weights = vech_indices(columns.shape[1])
    ci = _gather_columns(columns, layout.column_i)
    if layout.structure == "diag":
        return (ci[:, rows, :] * weights[None, :, None]) * ci[:, cols, :]
    cj = _gather_columns(columns, layout.column_j)
    half = np.where(layout.is_variance, 0.5, 1.0)
    both = ci[:, rows, :] * cj[:, cols, :] + cj[:, rows, :] * ci[:, cols, :]
    both *= (weights[:, None] * half[None, :])[None]
    return both


def _gather_columns(columns: FloatArray, index: IntArray) -> FloatArray:
    """C[:, :, index] in C order (fancy indexing on the last axis would not be)."""
    if index.size == columns.shape[2] and np.array_equal(index, np.arange(index.size)):
        return columns
    return np.ascontiguousarray(np.take(columns, index, axis=2))


def block_diagonal(frame_covariances: FloatArray) -> FloatArray:
    """blockdiag(Σ_1 … Σ_F), (6F, 6F), matching the columns of :func:`column_matrix`."""
    n_frames = frame_covariances.shape[0]
    out = np.zeros((6 * n_frames, 6 * n_frames))
    for f in range(n_frames):
        out[6 * f : 6 * f + 6, 6 * f : 6 * f + 6] = frame_covariances[f]
    return out
