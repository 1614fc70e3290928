"""SE(3) and SO(3) maps, batched over a leading axis.

Conventions (DESIGN.md §2): twists are 6-vectors ``[v; w]`` (translation first, metres and
radians), identical to Pinocchio's ``Motion.vector``; homogeneous transforms are ``(..., 4, 4)``
arrays; quaternions cross every boundary in ``(qx, qy, qz, qw)`` order (scalar last).

Every function accepts any number of leading batch dimensions. Pinocchio's ``exp6``/``log6``
are the reference the tests compare against; these versions exist because calibration applies
them to 10^3..10^6 samples at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from solver.arrays import FloatArray, IntArray

# Below this rotation angle the closed forms lose digits to cancellation; the Taylor series
# (three terms, truncation error < 1e-16) are exact to double precision there.
_SMALL_ANGLE_RAD = 1e-2


def skew(vector: FloatArray) -> FloatArray:
    """``[v]x`` such that ``skew(a) @ b == cross(a, b)``; shape (..., 3) -> (..., 3, 3)."""
    out = np.zeros((*vector.shape, 3))
    out[..., 0, 1], out[..., 0, 2] = -vector[..., 2], vector[..., 1]
    out[..., 1, 0], out[..., 1, 2] = vector[..., 2], -vector[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -vector[..., 1], vector[..., 0]
    return out


def so3_exp(rotation_vector_rad: FloatArray) -> FloatArray:
    """Rotation matrix of a rotation vector (axis * angle); (..., 3) -> (..., 3, 3)."""
    from scipy.spatial.transform import Rotation  # lazy: 0.4 s, not for kincal --help

    flat = rotation_vector_rad.reshape(-1, 3)
    return Rotation.from_rotvec(flat).as_matrix().reshape(*rotation_vector_rad.shape[:-1], 3, 3)


def so3_log(rotation: FloatArray) -> FloatArray:
    """Rotation vector (angle in [0, pi]) of a rotation matrix; (..., 3, 3) -> (..., 3)."""
    from scipy.spatial.transform import Rotation  # lazy: 0.4 s, not for kincal --help

    flat = rotation.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(*rotation.shape[:-2], 3)


def _left_jacobian_coefficients(angle_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Coefficients a, b of ``V = I + a [w]x + b [w]x^2`` (SO(3) left Jacobian)."""
    small = angle_rad < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, angle_rad)
    t2 = angle_rad**2
    a = np.where(small, 0.5 - t2 / 24.0 + t2**2 / 720.0, (1.0 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2**2 / 5040.0, (safe - np.sin(safe)) / safe**3)
    return a, b


def se3_exp(twist: FloatArray) -> FloatArray:
    """``Exp`` of a twist ``[v; w]``; (..., 6) -> (..., 4, 4). Equals ``pin.exp6``."""
    v, w = twist[..., :3], twist[..., 3:]
    angle_rad = np.linalg.norm(w, axis=-1)
    a, b = _left_jacobian_coefficients(angle_rad)
    w_hat = skew(w)
    w_hat2 = w_hat @ w_hat
    eye = np.broadcast_to(np.eye(3), w_hat.shape)
    left_jacobian = eye + a[..., None, None] * w_hat + b[..., None, None] * w_hat2
    out = np.zeros((*twist.shape[:-1], 4, 4))
    out[..., :3, :3] = so3_exp(w)
    out[..., :3, 3] = np.einsum("...ij,...j->...i", left_jacobian, v)
    out[..., 3, 3] = 1.0
    return out


def so3_right_jacobian_inverse(rotation_vector_rad: FloatArray) -> FloatArray:
    """``Jr⁻¹(φ) = I + ½[φ]x + c [φ]x²`` with ``c = 1/θ² − (1 + cos θ) / (2 θ sin θ)``;
    (..., 3) -> (..., 3, 3). ``Log(Exp(φ) Exp(δ)) ≈ φ + Jr⁻¹(φ) δ``; equals ``pin.Jlog3``."""
    angle_rad = np.linalg.norm(rotation_vector_rad, axis=-1)
    small = angle_rad < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, angle_rad)
    c = np.where(
        small,
        1.0 / 12.0 + angle_rad**2 / 720.0 + angle_rad**4 / 30240.0,
        1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)),
    )
    w_hat = skew(rotation_vector_rad)
    eye = np.broadcast_to(np.eye(3), w_hat.shape)
    return np.asarray(eye + 0.5 * w_hat + c[..., None, None] * (w_hat @ w_hat), dtype=float)


def se3_ad(twist: FloatArray) -> FloatArray:
    """``ad_ξ = [[[w]x, [v]x], [0, [w]x]]`` of twists ``ξ = [v; w]``; (..., 6) -> (..., 6, 6):
    the Lie bracket ``[ξ, η] = ad_ξ η``, the derivative of :func:`adjoint` at the identity."""
    out = np.zeros((*twist.shape[:-1], 6, 6))
    w_hat = skew(twist[..., 3:])
    out[..., :3, :3] = w_hat
    out[..., :3, 3:] = skew(twist[..., :3])
    out[..., 3:, 3:] = w_hat
    return out


def se3_left_jacobian_inverse(twist: FloatArray) -> FloatArray:
    """``J_l⁻¹(ξ) = ad_ξ / (Exp(ad_ξ) − I) = Σ_n B_n/n! ad_ξⁿ`` (Bernoulli numbers, B₁ = −½) of
    twists ``ξ = [v; w]``; (..., 6) -> (..., 6, 6). ``Log(Exp(−t) Exp(ξ)) ≈ ξ − J_l⁻¹(ξ) t``;
    equals Pinocchio's ``Jlog6(Exp(−ξ))``.

    The series to ad⁶: what it leaves out is about ``‖ad_ξ‖⁸ / 1 209 600`` (the next term),
    with ``‖ad_ξ‖ ≤ |v| + |w|``: 1e-14 at 0.1, 3e-9 at 0.5: exact to double precision for the
    residuals of a fit, and a Gauss–Newton Jacobian well beyond them."""
    ad = se3_ad(twist)
    ad2 = ad @ ad
    ad4 = ad2 @ ad2
    eye = np.broadcast_to(np.eye(6), ad.shape)
    return np.asarray(
        eye - 0.5 * ad + ad2 / 12.0 - ad4 / 720.0 + (ad4 @ ad2) / 30240.0, dtype=float
    )


def se3_log(transform: FloatArray) -> FloatArray:
    """``Log`` of a transform as a twist ``[v; w]``; (..., 4, 4) -> (..., 6). = ``pin.log6``."""
    w = so3_log(transform[..., :3, :3])
    angle_rad = np.linalg.norm(w, axis=-1)
    small = angle_rad < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, angle_rad)
    # V^-1 = I - 1/2 [w]x + c [w]x^2 with c = (1 - (t sin t) / (2 (1 - cos t))) / t^2.
    c = np.where(
        small,
        1.0 / 12.0 + angle_rad**2 / 720.0 + angle_rad**4 / 30240.0,
        (1.0 - safe * np.sin(safe) / (2.0 * (1.0 - np.cos(safe)))) / safe**2,
    )
    w_hat = skew(w)
    eye = np.broadcast_to(np.eye(3), w_hat.shape)
    inverse_left_jacobian = eye - 0.5 * w_hat + c[..., None, None] * (w_hat @ w_hat)
    v = np.einsum("...ij,...j->...i", inverse_left_jacobian, transform[..., :3, 3])
    return np.concatenate([v, w], axis=-1)


def inverse(transform: FloatArray) -> FloatArray:
    """Inverse of rigid transforms; (..., 4, 4) -> (..., 4, 4)."""
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    out = np.zeros_like(transform)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, transform[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def adjoint(transform: FloatArray) -> FloatArray:
    """Paper Eq. (5): ``Ad_X = [[R, [t]x R], [0, R]]``; (..., 4, 4) -> (..., 6, 6).

    Maps a twist expressed in the child frame of X into its parent frame (= ``SE3.action``).
    """
    rotation = transform[..., :3, :3]
    out = np.zeros((*transform.shape[:-2], 6, 6))
    out[..., :3, :3] = rotation
    out[..., 3:, 3:] = rotation
    out[..., :3, 3:] = skew(transform[..., :3, 3]) @ rotation
    return out


def adjoint_inverse(transform: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """``Ad_X^-1 = Ad_{X^-1}`` without forming the inverse first; (..., 4, 4) -> (..., 6, 6).

    ``out`` (..., 6, 6), optional: written in place (e.g. a slice of a larger Jacobian array).
    Row i of the upper-right block ``-R^T [t]x`` is ``t x R[:, i]``, written component-wise:
    no skew matrices, no small batched matmuls (the ranking hot path, 10^5..10^6 samples).
    """
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    t = transform[..., :3, 3, None]  # (..., 3, 1)
    if out is None:
        out = np.empty((*transform.shape[:-2], 6, 6))
    out[..., :3, :3] = rotation_t
    out[..., 3:, 3:] = rotation_t
    out[..., 3:, :3] = 0.0
    out[..., :3, 3] = t[..., 1, :] * rotation_t[..., :, 2] - t[..., 2, :] * rotation_t[..., :, 1]
    out[..., :3, 4] = t[..., 2, :] * rotation_t[..., :, 0] - t[..., 0, :] * rotation_t[..., :, 2]
    out[..., :3, 5] = t[..., 0, :] * rotation_t[..., :, 1] - t[..., 1, :] * rotation_t[..., :, 0]
    return out


def adjoint_inverse_apply(transform: FloatArray, twist: FloatArray) -> FloatArray:
    """``Ad_X^-1 · twist`` = ``[R^T (v - t x w); R^T w]`` for one twist (6,); (N, 4, 4) -> (N, 6).

    Equal to ``adjoint_inverse(X) @ twist`` without building the 6x6 matrices.
    """
    rotation = transform[..., :3, :3]
    v, w = twist[:3], twist[3:]
    out = np.empty((*transform.shape[:-2], 6))
    moment = v - np.cross(transform[..., :3, 3], w)
    out[..., :3] = np.einsum("...ji,...j->...i", rotation, moment)
    out[..., 3:] = w @ rotation
    return out


def rodrigues_coefficients(norm_w: float, angle: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``a = sin θ / |w|``, ``b = (1 - cos θ) / |w|²`` with ``θ = |w| angle`` (any shape).

    ``Exp([w]x angle) = I + a [w]x + b [w]x²``; b is written as ``2 sin²(θ/2) / |w|²`` so it
    keeps full relative precision near 0 and needs no small-angle branch.
    """
    theta = norm_w * angle
    return np.sin(theta) / norm_w, 2.0 * np.sin(0.5 * theta) ** 2 / norm_w**2


def combine_rows(matrix: FloatArray, x: FloatArray) -> FloatArray:
    """``out[p] = Σ_j matrix[p, j] · x[j]`` for a small constant matrix (P, M) and a batch-LAST
    x (M, ..., N) -> (P, ..., N).

    Element by element, without BLAS, so a sample's result never depends on where it sits in
    the batch (BLAS kernels round edge columns differently): identical inputs give identical
    outputs. Zero coefficients (common in URDF placements) are skipped. For a matrix used
    many times, build its :class:`RowCombination` once.
    """
    return RowCombination.of(matrix)(x)


@dataclass(frozen=True, eq=False)
class _CombinationStep:
    """The s-th non-zero term of every row that has one: ``out[rows] (+)= coefficients ·
    x[columns]``. ``rows``/``columns`` are slices or a single column where they can be (no
    gather), index arrays otherwise."""

    rows: slice | IntArray
    columns: int | slice | IntArray
    coefficients: FloatArray  # (len(rows),)
    all_rows: bool


@dataclass(frozen=True, eq=False)
class RowCombination:
    """:func:`combine_rows` for one constant matrix (P, M), its zero pattern resolved once.

    Every output element is computed with the same operations in the same order as the
    row-by-row definition (first used column times its coefficient, then ``+= m[p, j] x[j]``
    column by column), so results are bit-identical whichever loop runs: for small batches
    each term position is one numpy call over all rows (a ranking request's ~100
    configurations pay per call, not per element); for large ones the row-by-row loop (its
    temporaries are a P-th the size: big temporaries cost page faults, not just bandwidth).
    """

    n_rows: int
    steps: tuple[_CombinationStep, ...]
    rows: tuple[tuple[tuple[int, float], ...], ...]  # per row: (column, coefficient) used

    @classmethod
    def of(cls, matrix: FloatArray) -> RowCombination:
        matrix = np.asarray(matrix, dtype=float)
        used = [np.flatnonzero(row) for row in matrix]
        steps = []
        for s in range(max((u.size for u in used), default=0)):
            rows = np.array([p for p, u in enumerate(used) if u.size > s], dtype=np.intp)
            columns = np.array([used[p][s] for p in rows], dtype=np.intp)
            steps.append(
                _CombinationStep(
                    _index(rows),
                    _column_index(columns),
                    matrix[rows, columns].copy(),
                    rows.size == matrix.shape[0],
                )
            )
        per_row = tuple(tuple((int(j), float(matrix[p, j])) for j in u) for p, u in enumerate(used))
        return cls(matrix.shape[0], tuple(steps), per_row)

    def __call__(self, x: FloatArray) -> FloatArray:
        tail = x.shape[1:]
        if x[0].size > FUSED_MAX_ELEMENTS:
            return self._row_by_row(x)
        if not self.steps:
            return np.zeros((self.n_rows, *tail))
        lead = (-1,) + (1,) * len(tail)
        first = self.steps[0]
        if first.all_rows:
            out = np.multiply(x[first.columns], first.coefficients.reshape(lead))
        else:
            out = np.zeros((self.n_rows, *tail))
            out[first.rows] = x[first.columns] * first.coefficients.reshape(lead)
        for step in self.steps[1:]:
            term = step.coefficients.reshape(lead) * x[step.columns]
            if step.all_rows:
                out += term
            else:
                out[step.rows] += term
        return out

    def _row_by_row(self, x: FloatArray) -> FloatArray:
        out = np.empty((self.n_rows, *x.shape[1:]))
        for p, used in enumerate(self.rows):
            if not used:
                out[p] = 0.0
                continue
            np.multiply(x[used[0][0]], used[0][1], out=out[p])
            for j, coefficient in used[1:]:
                out[p] += coefficient * x[j]
        return out


FUSED_MAX_ELEMENTS = 2048
"""Above this many elements per row of a batch-last array, the batched helpers here loop row by
row (bit-identical results either way; see :class:`RowCombination`)."""


def _index(rows: IntArray) -> slice | IntArray:
    """``rows`` (increasing) as a slice when they are a contiguous run."""
    if rows.size and np.array_equal(rows, np.arange(rows[0], rows[0] + rows.size)):
        return slice(int(rows[0]), int(rows[0]) + rows.size)
    return rows


def _column_index(columns: IntArray) -> int | slice | IntArray:
    """One column for every row -> that column (x[c] broadcasts); a run -> a slice."""
    if columns.size and np.all(columns == columns[0]):
        return int(columns[0])
    return _index(columns)


def rotate_batch_last(
    x: FloatArray, axis: FloatArray, cos: FloatArray, sin: FloatArray
) -> FloatArray:
    """``Exp([axis]x θ) · x`` for batch-LAST arrays: x (3, ..., N), one unit ``axis`` (3,),
    ``cos = cos θ`` and ``sin = sin θ`` (N,). Returns a new array shaped like x.

    Axis 0 of x holds vector components, so a (3, 4, N) stack of ``[R | t]`` is left-multiplied
    by the rotation. For an axis along a coordinate axis (most URDF joints) only two rows mix;
    otherwise Rodrigues ``c x + s (a × x) + (1 - c)(a·x) a``.
    """
    axis = np.asarray(axis, dtype=float)
    return _rotate(x, axis, _aligned_axis(axis), cos, sin)


def _aligned_axis(axis: FloatArray) -> int:
    """Index u if ``axis`` lies along coordinate axis u (sign included in the axis), else -1."""
    aligned = np.flatnonzero(axis != 0.0)
    return int(aligned[0]) if aligned.size == 1 else -1


def _rotate(
    x: FloatArray, axis: FloatArray, u: int, cos: FloatArray, sin: FloatArray
) -> FloatArray:
    """:func:`rotate_batch_last` with the axis classified (``u`` of :func:`_aligned_axis`)."""
    out = np.empty_like(x)
    if u >= 0:
        if axis[u] < 0.0:
            sin = -sin  # = sin * sign(axis[u]), exactly
        v, w = (u + 1) % 3, (u + 2) % 3
        out[u] = x[u]
        np.multiply(cos, x[v], out=out[v])
        out[v] -= sin * x[w]
        np.multiply(sin, x[v], out=out[w])
        out[w] += cos * x[w]
        return out
    along = (axis[0] * x[0] + axis[1] * x[1] + axis[2] * x[2]) * (1.0 - cos)
    out[0] = cos * x[0] + sin * (axis[1] * x[2] - axis[2] * x[1]) + along * axis[0]
    out[1] = cos * x[1] + sin * (axis[2] * x[0] - axis[0] * x[2]) + along * axis[1]
    out[2] = cos * x[2] + sin * (axis[0] * x[1] - axis[1] * x[0]) + along * axis[2]
    return out


def cos_sin(angle_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(cos, sin)`` of an array; Taylor series when every |angle| <= 1e-2 rad.

    The series (to θ⁸ / θ⁷; truncation below 1e-20 relative) is several times faster than
    libm and is what small deflections (compliance, virtual axes: ~1e-3 rad) hit.
    """
    angle = np.asarray(angle_rad, dtype=float)
    if angle.size and np.abs(angle).max() <= _SMALL_ANGLE_RAD:
        return _cos_sin_series(angle)
    return np.cos(angle), np.sin(angle)


def _cos_sin_series(angle: FloatArray) -> tuple[FloatArray, FloatArray]:
    t2 = angle * angle
    cos = 1.0 - t2 * (0.5 - t2 * (1.0 / 24.0 - t2 * (1.0 / 720.0 - t2 / 40320.0)))
    sin = angle * (1.0 - t2 * (1.0 / 6.0 - t2 * (1.0 / 120.0 - t2 / 5040.0)))
    return cos, sin


def cos_sin_rows(angle_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """:func:`cos_sin` of every row of a C-contiguous (R, N) array, in a few calls for all rows.

    Row r gets exactly ``cos_sin(angle_rad[r])``: the series where that row's every |angle| is
    <= 1e-2 rad, libm elsewhere (element-wise either way, so equal bit for bit).
    """
    angle = np.ascontiguousarray(angle_rad, dtype=float)
    if not angle.size:
        return np.cos(angle), np.sin(angle)
    if angle.shape[1] > FUSED_MAX_ELEMENTS:
        cos, sin = np.empty_like(angle), np.empty_like(angle)
        for r, row in enumerate(angle):
            cos[r], sin[r] = cos_sin(row)
        return cos, sin
    small = np.abs(angle).max(axis=1) <= _SMALL_ANGLE_RAD
    if small.all():
        return _cos_sin_series(angle)
    cos, sin = np.cos(angle), np.sin(angle)
    if small.any():
        cos[small], sin[small] = _cos_sin_series(angle[small])
    return cos, sin


@dataclass(frozen=True, eq=False)
class Screw:
    """A constant screw ``[v; w]`` (6,) classified once, for its many ``Exp(screw · angle)``:
    ``norm_w`` = |w|, unit ``axis`` (z for a prismatic screw), ``aligned`` = the coordinate axis
    the axis lies along (-1 if none; then Rodrigues), ``translates``: v != 0 for a revolute
    screw (its translation comes from :func:`screw_exp`)."""

    vector: FloatArray
    norm_w: float
    axis: FloatArray
    aligned: int
    translates: bool

    @classmethod
    def of(cls, screw: FloatArray) -> Screw:
        vector = np.asarray(screw, dtype=float)
        norm_w = float(np.linalg.norm(vector[3:]))
        axis = np.array([0.0, 0.0, 1.0]) if norm_w == 0.0 else vector[3:] / norm_w
        return cls(vector, norm_w, axis, _aligned_axis(axis), bool(np.any(vector[:3] != 0.0)))

    def motion(
        self, angle: FloatArray, trig: tuple[FloatArray, FloatArray] | None = None
    ) -> ScrewMotion:
        """``Exp(screw · angle)`` for angles (N,); ``trig``: ``cos_sin(|w| · angle)`` if the
        caller computed it (e.g. for all joints at once with :func:`cos_sin_rows`)."""
        if self.norm_w == 0.0:  # prismatic
            ones, zeros = np.ones_like(angle), np.zeros_like(angle)
            return ScrewMotion(
                self.vector, angle, self.axis, ones, zeros, self.vector[:3, None] * angle, self
            )
        translation = screw_exp(self.vector, angle)[:, :3, 3].T if self.translates else None
        cos, sin = trig if trig is not None else cos_sin(self.norm_w * angle)
        return ScrewMotion(self.vector, angle, self.axis, cos, sin, translation, self)


@dataclass(frozen=True)
class ScrewMotion:
    """``E = Exp(screw · angle)`` for one screw (6,) and a batch of angles (N,), batch-LAST.

    ``axis`` (3,) unit rotation axis, ``cos``/``sin`` (N,) of the rotation angle
    ``|w| · angle``, ``translation`` (3, N) or None (pure rotation: every revolute URDF joint).
    ``kind``: the screw classified (:class:`Screw`), None if constructed directly.
    """

    screw: FloatArray
    angle: FloatArray
    axis: FloatArray
    cos: FloatArray
    sin: FloatArray
    translation: FloatArray | None
    kind: Screw | None = field(default=None, repr=False)

    @classmethod
    def of(cls, screw: FloatArray, angle: FloatArray) -> ScrewMotion:
        return Screw.of(screw).motion(angle)

    def advanced(
        self, delta: FloatArray, trig: tuple[FloatArray, FloatArray] | None = None
    ) -> ScrewMotion:
        """The same screw at ``angle + delta`` (N,); for small deltas (joint deflections) by
        angle addition, without evaluating full-range trigonometry again. ``trig``:
        ``cos_sin(|w| · delta)`` if the caller has it."""
        if not np.any(delta):
            return self
        kind = self.kind if self.kind is not None else Screw.of(self.screw)
        if self.translation is not None or kind.norm_w == 0.0:
            return kind.motion(self.angle + delta)
        cos_d, sin_d = trig if trig is not None else cos_sin(kind.norm_w * delta)
        return ScrewMotion(
            self.screw,
            self.angle + delta,
            self.axis,
            self.cos * cos_d - self.sin * sin_d,
            self.sin * cos_d + self.cos * sin_d,
            None,
            kind,
        )

    def rotate(self, x: FloatArray) -> FloatArray:
        """``R_E x`` for x (3, ..., N)."""
        return self._rotate(x, self.sin)

    def rotate_inverse(self, x: FloatArray) -> FloatArray:
        """``R_E^T x`` for x (3, ..., N)."""
        return self._rotate(x, -self.sin)

    def _rotate(self, x: FloatArray, sin: FloatArray) -> FloatArray:
        if self.kind is None:
            return rotate_batch_last(x, self.axis, self.cos, sin)
        return _rotate(x, self.axis, self.kind.aligned, self.cos, sin)


def screw_exp(screw: FloatArray, angle: FloatArray) -> FloatArray:
    """``Exp(screw · angle)`` for ONE fixed screw (6,) and many angles (...,) -> (..., 4, 4).

    The joint motions of Eq. (7). Rodrigues with the screw's skew matrices built once:
    ``R = I + a K + b K^2`` with ``K = [w]x``, ``θ = |w| angle``, ``a = sin θ / |w|``,
    ``b = 2 sin²(θ/2) / |w|²`` (no cancellation, no division by the angle, exact at 0);
    translation ``angle v + b K v + c K² v`` with ``c = (θ - sin θ) / |w|³`` (series below
    1e-2 rad). Equals ``se3_exp(screw * angle)`` to rounding (tested against Pinocchio).
    """
    v, w = np.asarray(screw[:3], dtype=float), np.asarray(screw[3:], dtype=float)
    norm_w = float(np.linalg.norm(w))
    angle = np.asarray(angle, dtype=float)
    out = np.zeros((*angle.shape, 4, 4))
    out[..., 3, 3] = 1.0
    if norm_w == 0.0:  # prismatic
        out[..., 0, 0] = out[..., 1, 1] = out[..., 2, 2] = 1.0
        out[..., :3, 3] = angle[..., None] * v
        return out
    k = skew(w)
    k2 = k @ k
    theta = norm_w * angle
    a, b = rodrigues_coefficients(norm_w, angle[..., None, None])
    out[..., :3, :3] = np.eye(3) + a * k + b * k2
    if np.any(v != 0.0):
        t2 = theta**2
        small = np.abs(theta) < _SMALL_ANGLE_RAD
        c = (
            np.where(
                small,
                theta * t2 * (1.0 / 6.0 - t2 / 120.0 + t2**2 / 5040.0),
                theta - np.sin(theta),
            )
            / norm_w**3
        )
        out[..., :3, 3] = angle[..., None] * v + b[..., 0] * (k @ v) + c[..., None] * (k2 @ v)
    return out


def pose_matrix(position_m: FloatArray, quaternion_xyzw: FloatArray | None) -> FloatArray:
    """Homogeneous transforms from positions (..., 3) and unit quaternions (..., 4), xyzw order.

    With ``quaternion_xyzw=None`` (position-only data) the rotation is the identity.
    """
    from scipy.spatial.transform import Rotation  # lazy: 0.4 s, not for kincal --help

    out = np.zeros((*position_m.shape[:-1], 4, 4))
    if quaternion_xyzw is None:
        out[..., :3, :3] = np.eye(3)
    else:
        flat = quaternion_xyzw.reshape(-1, 4)
        out[..., :3, :3] = (
            Rotation.from_quat(flat).as_matrix().reshape(*position_m.shape[:-1], 3, 3)
        )
    out[..., :3, 3] = position_m
    out[..., 3, 3] = 1.0
    return out


def matrix_to_quaternion_xyzw(rotation: FloatArray) -> FloatArray:
    """Unit quaternions ``(qx, qy, qz, qw)`` with ``qw >= 0``; (..., 3, 3) -> (..., 4)."""
    from scipy.spatial.transform import Rotation  # lazy: 0.4 s, not for kincal --help

    flat = Rotation.from_matrix(rotation.reshape(-1, 3, 3)).as_quat()
    flat = np.where(flat[:, 3:4] < 0.0, -flat, flat)
    return flat.reshape(*rotation.shape[:-2], 4)


def rotation_angle_rad(rotation: FloatArray) -> FloatArray:
    """Geodesic angle of rotation matrices in [0, pi]; (..., 3, 3) -> (...).

    ``atan2(sin θ, cos θ)`` with ``sin θ = |vee(R − Rᵀ)| / 2`` and ``cos θ = (tr R − 1) / 2``:
    accurate at every angle, where ``arccos`` of the trace alone floors at ~1e-8 rad near 0
    (the trace's rounding; 2.1e-8 rad for a rotation whose log is below 1e-10)."""
    w = 0.5 * (rotation[..., [2, 0, 1], [1, 2, 0]] - rotation[..., [1, 2, 0], [2, 0, 1]])
    sin = np.sqrt(w[..., 0] * w[..., 0] + w[..., 1] * w[..., 1] + w[..., 2] * w[..., 2])
    cos = 0.5 * (rotation[..., 0, 0] + rotation[..., 1, 1] + rotation[..., 2, 2] - 1.0)
    return np.arctan2(sin, cos)
