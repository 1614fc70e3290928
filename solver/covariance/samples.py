"""The samples a covariance calibration is estimated from, in memory or chunk by chunk.

Every estimator of :mod:`solver.covariance` reduces to sums over samples of the residuals
``r_n`` (d,), the frame Jacobians ``A_f(q_n)`` (F, d, 6) and, for REML, the deterministic fit's
Jacobian ``X_n`` (d, p) — all in the end-effector frame, [v; w], m and rad. The estimators are
written once against :class:`CovarianceSamples`: ``samples.map(kernel, argument)`` applies a
module-level ``kernel(argument, chunk)`` to every :class:`SampleChunk` in order and returns the
per-chunk results, which the caller adds in that order. :class:`ArraySamples` holds the
arrays in memory; :class:`solver.stream.covariance.StreamedSamples` produces each chunk in a
worker process from a sweep over the recording. The arithmetic per chunk is the same, so the
two give the same estimate up to rounding.

Quantities that need the samples themselves rather than sums (the scoring metric of the
likelihood fits, the standard errors) are computed on :func:`subsample`: the samples whose
recording row is a multiple of a stride, so the subset does not depend on how the recording
was cut into chunks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.covariance.statistics import DEFAULT_CHUNK_SIZE
from solver.errors import SolverError

A = TypeVar("A")
T = TypeVar("T")


@dataclass(frozen=True)
class SampleChunk:
    """Used samples of one chunk. ``residuals`` (n, d) m and rad; ``frame_jacobians``
    (n, F, d, 6) map a local twist of each perturbed frame to the residual; ``fit_jacobian``
    (n, d, p) the deterministic fit's columns (rotation rows unweighted), None when not asked
    for; ``rows`` (n,) the samples' 0-based rows in the recording."""

    residuals: FloatArray
    frame_jacobians: FloatArray
    fit_jacobian: FloatArray | None
    rows: IntArray

    @property
    def n(self) -> int:
        return int(self.residuals.shape[0])

    @property
    def nbytes(self) -> int:
        fit = 0 if self.fit_jacobian is None else self.fit_jacobian.nbytes
        return self.residuals.nbytes + self.frame_jacobians.nbytes + fit + self.rows.nbytes

    def take(self, index: IntArray) -> SampleChunk:
        return SampleChunk(
            self.residuals[index],
            self.frame_jacobians[index],
            None if self.fit_jacobian is None else self.fit_jacobian[index],
            self.rows[index],
        )


Kernel = Callable[[A, SampleChunk], T]


class CovarianceSamples(Protocol):
    """Samples of a covariance calibration: ``n_samples`` used samples of residual dimension
    ``residual_dim``, out of a recording of ``n_rows`` rows."""

    @property
    def n_samples(self) -> int: ...

    @property
    def residual_dim(self) -> int: ...

    @property
    def n_rows(self) -> int: ...

    def map(self, kernel: Kernel[A, T], argument: A) -> list[T]:
        """``[kernel(argument, chunk) for chunk in chunks]`` in chunk order (one pass over
        the data when streamed); ``kernel`` module-level and ``argument`` picklable."""
        ...

    def on_stride(self, stride: int) -> ArraySamples:
        """The samples whose recording row is a multiple of ``stride``, in memory."""
        ...


@dataclass(frozen=True, eq=False)
class ArraySamples:
    """:class:`CovarianceSamples` held in memory, cut into chunks of ``chunk_size`` samples.

    ``rows`` (N,) the samples' recording rows (default ``0..N−1``); ``n_rows`` the recording's
    length (default: one past the last row)."""

    residuals: FloatArray
    frame_jacobians: FloatArray
    fit_jacobian: FloatArray | None = None
    rows: IntArray | None = None
    recording_rows: int | None = None
    chunk_size: int = DEFAULT_CHUNK_SIZE

    @property
    def n_samples(self) -> int:
        return int(self.residuals.shape[0])

    @property
    def residual_dim(self) -> int:
        return int(self.residuals.shape[1])

    @property
    def sample_rows(self) -> IntArray:
        return np.arange(self.n_samples) if self.rows is None else self.rows

    @property
    def n_rows(self) -> int:
        if self.recording_rows is not None:
            return self.recording_rows
        rows = self.sample_rows
        return int(rows[-1]) + 1 if rows.size else 0

    def chunks(self) -> Iterator[SampleChunk]:
        rows = self.sample_rows
        for start in range(0, self.n_samples, self.chunk_size):
            part = slice(start, start + self.chunk_size)
            yield SampleChunk(
                self.residuals[part],
                self.frame_jacobians[part],
                None if self.fit_jacobian is None else self.fit_jacobian[part],
                rows[part],
            )

    def map(self, kernel: Kernel[A, T], argument: A) -> list[T]:
        return [kernel(argument, chunk) for chunk in self.chunks()]

    def on_stride(self, stride: int) -> ArraySamples:
        if stride == 1:
            return self
        index = np.flatnonzero(self.sample_rows % stride == 0)
        fit = self.fit_jacobian
        return ArraySamples(
            self.residuals[index],
            self.frame_jacobians[index],
            None if fit is None else fit[index],
            self.sample_rows[index],
            self.n_rows,
            self.chunk_size,
        )

    @classmethod
    def join(cls, chunks: list[SampleChunk], n_rows: int) -> ArraySamples:
        """The samples of ``chunks`` (in order) as one in-memory set."""
        if not chunks:
            raise SolverError("no samples to join")
        fits = [c.fit_jacobian for c in chunks]
        return cls(
            np.concatenate([c.residuals for c in chunks]),
            np.concatenate([c.frame_jacobians for c in chunks]),
            None if any(f is None for f in fits) else np.concatenate(fits),  # type: ignore[arg-type]
            np.concatenate([c.rows for c in chunks]),
            n_rows,
        )


def row_stride(n_rows: int, limit: int) -> int:
    """The stride of :func:`subsample`: every s-th recording row, at most ``limit`` rows."""
    return max(1, -(-n_rows // max(limit, 1)))


def subsample(samples: CovarianceSamples, limit: int) -> ArraySamples:
    """The used samples whose recording row is a multiple of ``row_stride(n_rows, limit)``, in
    memory (all of them when the recording has at most ``limit`` rows)."""
    return samples.on_stride(row_stride(samples.n_rows, limit))


def every_kth(samples: ArraySamples, limit: int) -> ArraySamples:
    """Every k-th sample of an in-memory set, at most ``limit`` (all when fewer)."""
    k = max(1, -(-samples.n_samples // max(limit, 1)))
    if k == 1:
        return samples
    index = np.arange(0, samples.n_samples, k)
    fit = samples.fit_jacobian
    return ArraySamples(
        samples.residuals[index],
        samples.frame_jacobians[index],
        None if fit is None else fit[index],
        samples.sample_rows[index],
        samples.n_rows,
        samples.chunk_size,
    )


def total(parts: list[Any]) -> Any:
    """The per-chunk results added in chunk order."""
    out = parts[0]
    for part in parts[1:]:
        out = out + part
    return out
