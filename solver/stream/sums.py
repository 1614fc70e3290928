"""What a pass adds up per chunk: pose errors, normal equations, residual spread and the
covariance statistics of Eq. (13–14); every sum merges over chunks with ``+``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver.arrays import BoolArray, FloatArray, IntArray
from solver.calibration import (
    NormalEquations,
    ResidualSpread,
)
from solver.covariance.estimate import (
    known_noise_covariance,
)
from solver.covariance.layout import CovarianceLayout, Structure, make_layout
from solver.covariance.statistics import (
    JacobianRange,
    MomentStatistics,
    build_moment_statistics,
    diag_statistics_batch_last,
    empty_statistics,
)
from solver.measurement.models import FullPose

# --- sums per chunk ------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorSums:
    """Sums of per-sample pose errors: translation (mm) and rotation (deg), and squares."""

    n: int = 0
    translation_mm: float = 0.0
    translation_mm2: float = 0.0
    rotation_deg: float = 0.0
    rotation_deg2: float = 0.0

    @classmethod
    def of(cls, translation_mm: FloatArray, rotation_deg: FloatArray | None) -> ErrorSums:
        rot = np.zeros(0) if rotation_deg is None else rotation_deg
        return cls(
            int(translation_mm.size),
            float(translation_mm.sum()),
            float(translation_mm @ translation_mm),
            float(rot.sum()),
            float(rot @ rot),
        )

    def __add__(self, other: ErrorSums) -> ErrorSums:
        return ErrorSums(
            self.n + other.n,
            self.translation_mm + other.translation_mm,
            self.translation_mm2 + other.translation_mm2,
            self.rotation_deg + other.rotation_deg,
            self.rotation_deg2 + other.rotation_deg2,
        )

    def summary(self, measurement: FullPose) -> tuple[float, float, float | None, float | None]:
        """Mean and RMS translation error (mm), mean and RMS rotation error (deg; None when
        ``measurement`` measures no rotation)."""
        n = max(self.n, 1)
        rotation = (
            (self.rotation_deg / n, float(np.sqrt(self.rotation_deg2 / n)))
            if measurement.measures_rotation
            else (None, None)
        )
        return self.translation_mm / n, float(np.sqrt(self.translation_mm2 / n)), *rotation


@dataclass(frozen=True, eq=False)
class CovarianceSpec:
    """What the covariance statistics (Eq. 13–14) are taken of: the perturbed frames (chain
    joint indices, in ``layout`` order), the θ layout, and a known part of every Σ_E (d, d),
    e.g. a measured noise covariance, or None."""

    frames: tuple[int, ...]
    layout: CovarianceLayout
    known: FloatArray | None = None
    noise_name: str = "noise"

    @property
    def frame_columns(self) -> list[int]:
        """Stacked-Jacobian columns ``6f + i`` of every frame f, frame by frame."""
        return [6 * f + i for f in self.frames for i in range(6)]

    def slots(self, position: dict[int, int]) -> IntArray:
        """For each chain-frame entry of θ, the position of its column ``A_f[:, i]`` in a
        stack whose column c sits at ``position[c]``."""
        layout = self.layout
        chain = np.flatnonzero(~layout.is_noise)
        return np.array(
            [position[6 * self.frames[layout.param_frame[p]] + layout.param_row[p]] for p in chain],
            dtype=np.intp,
        )


@dataclass(frozen=True)
class CovarianceSums:
    """Per chunk (and added): the moment statistics (Eq. 14) of the used samples and the range
    of their frame Jacobians (F, d, 6) for the constant-Jacobian check."""

    stats: MomentStatistics
    jacobians: JacobianRange

    @property
    def n(self) -> int:
        return self.stats.n_samples

    @classmethod
    def empty(cls, spec: CovarianceSpec) -> CovarianceSums:
        shape = (len(spec.frames), spec.layout.residual_dim, 6)
        return cls(empty_statistics(spec.layout, spec.known), JacobianRange.empty(shape))

    def __add__(self, other: CovarianceSums) -> CovarianceSums:
        return CovarianceSums(self.stats + other.stats, self.jacobians + other.jacobians)


@dataclass(frozen=True)
class FitSums:
    """What one fit pass returns per chunk (and, added, for the recording): the normal
    equations over the kept columns (weighted), the spread of the unweighted residuals and
    the pose errors of the used samples, the 0-based rows the outlier rule dropped, and —
    when asked for — the covariance statistics at the same point."""

    normal: NormalEquations
    spread: ResidualSpread
    errors: ErrorSums
    removed_rows: NDArray[np.int64]
    covariance: CovarianceSums | None = None

    def __add__(self, other: FitSums) -> FitSums:
        covariance = self.covariance
        if covariance is None or other.covariance is None:
            covariance = covariance or other.covariance
        else:
            covariance = covariance + other.covariance
        return FitSums(
            self.normal + other.normal,
            self.spread + other.spread,
            self.errors + other.errors,
            np.concatenate([self.removed_rows, other.removed_rows]),
            covariance,
        )


def frame_range(
    spec: CovarianceSpec, columns: FloatArray, position: dict[int, int], used: BoolArray | None
) -> tuple[FloatArray, FloatArray]:
    """Per entry of the frame Jacobians (F·6, d), the minimum and maximum over the used
    samples of a block (columns (C, d, b), not yet zeroed): the dropped samples' columns are
    first overwritten with a used sample's, so plain reductions give the answer."""
    frames = np.array([position[c] for c in spec.frame_columns], dtype=np.intp)
    if used is not None:
        if not used.any():
            shape = (frames.size, columns.shape[1])
            return np.full(shape, np.inf), np.full(shape, -np.inf)
        columns[:, :, ~used] = columns[:, :, [int(np.argmax(used))]]
    return columns.min(axis=2)[frames], columns.max(axis=2)[frames]


def covariance_sums(
    spec: CovarianceSpec,
    columns: FloatArray,
    leading_rows: IntArray,
    position: dict[int, int],
    residual: FloatArray,
    used: BoolArray | None,
    frame_range: tuple[FloatArray, FloatArray],
    n_used: int,
) -> CovarianceSums:
    """Eq. (13–14) statistics and the frame-Jacobian range of one block from its batch-last
    Jacobian columns (C, d, b) (column c at ``position[c]``; the dropped samples' zeroed) and
    residuals (d, b), m and rad, zero where dropped; ``used`` (b,) or None for all;
    ``frame_range``: :func:`frame_range`."""
    layout = spec.layout
    d = residual.shape[0]
    frames = np.array([position[c] for c in spec.frame_columns], dtype=np.intp)

    def frame_view(values: FloatArray) -> FloatArray:  # (F·6, d) -> (F, d, 6)
        return values.reshape(len(spec.frames), 6, d).transpose(0, 2, 1)

    total = columns.sum(axis=2)[frames]
    if layout.structure == "diag":
        slots = spec.slots(position)
        stats = diag_statistics_batch_last(
            columns,
            slots,
            layout,
            residuals=residual,
            known_covariance=spec.known,
            used=used,
            rows=leading_rows[slots],
            zeroed=True,
        )
    else:
        keep = slice(None) if used is None else used
        jacobians = columns[frames][:, :, keep].reshape(len(spec.frames), 6, d, -1)
        stats = build_moment_statistics(
            np.ascontiguousarray(residual[:, keep].T),
            np.ascontiguousarray(jacobians.transpose(3, 0, 2, 1)),
            layout,
            known_covariance=spec.known,
        )
    low, high = frame_range
    return CovarianceSums(
        stats, JacobianRange(frame_view(total), frame_view(low), frame_view(high), n_used)
    )


def covariance_spec(
    residual_dim: int,
    frame_names: Sequence[str],
    frame_index: Sequence[int],
    *,
    structure: Structure = "diag",
    noise_covariance: FloatArray | None = None,
    noise_name: str = "noise",
    free_axes: Mapping[str, Sequence[str]] | None = None,
    noise_rows: Mapping[str, Sequence[Sequence[int]]] | None = None,
) -> CovarianceSpec:
    """The covariance statistics to take of residuals of ``residual_dim`` d rows: frames
    ``frame_names`` perturbing the chain joints ``frame_index``, the noise frame (or a known
    noise covariance, 6×6 or d×d), diagonal or full Σ; ``free_axes`` and ``noise_rows`` (the
    noise layout of residuals other than a pose or position) as in :func:`make_layout`."""
    d = residual_dim
    known = known_noise_covariance(
        noise_covariance, d, None if noise_rows is None else next(iter(noise_rows.values()))
    )
    layout = make_layout(
        frame_names,
        d,
        structure=structure,
        include_noise=known is None,
        noise_name=noise_name,
        free_axes=free_axes,
        noise_rows=noise_rows,
    )
    return CovarianceSpec(tuple(int(f) for f in frame_index), layout, known, noise_name)
