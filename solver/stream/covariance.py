"""Streamed covariance calibration (paper §IV-C): the samples of :mod:`solver.covariance`,
produced chunk by chunk in the workers.

:class:`StreamedSamples` is :class:`~solver.covariance.samples.CovarianceSamples` over a
recording: each ``map`` is one pass, in which every worker sweeps its chunks at the calibrated
parameters (FK, the frame Jacobians ``A_f = Ad_{B_f}⁻¹`` and, for REML, the fit's Jacobian
columns), keeps the samples the outlier rule kept, and applies the estimator's kernel. So
:func:`~solver.covariance.estimate.estimate_from_samples` runs the same estimators — moment
matching, ML, REML — on a streamed recording as on arrays in memory, with the same arithmetic
per chunk. The moment statistics usually come along with the refit's last pass
(:func:`covariance_chunk` computes them on their own otherwise).
"""

from __future__ import annotations

import dataclasses
import functools
import operator
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solver.arrays import FloatArray, IntArray
from solver.batch_chain import pose_residuals, sweep_chain
from solver.covariance.likelihood import ee_covariance_batch
from solver.covariance.samples import ArraySamples, SampleChunk
from solver.executors import Executor
from solver.kinematics import ChainParameters
from solver.predictive import mahalanobis_squared
from solver.stream.chunks import (
    Block,
    StreamProblem,
    cache_derived,
    cached_derived,
    prepared_blocks,
)
from solver.stream.fit import PassCount
from solver.stream.screening import Rule, used_mask
from solver.stream.sums import CovarianceSpec, CovarianceSums, covariance_sums, frame_range


@dataclass(frozen=True, eq=False)
class _CovariancePass:
    problem: StreamProblem
    params: ChainParameters
    spec: CovarianceSpec
    rule: Rule | None


def covariance_chunk(request: _CovariancePass, ref: Any) -> CovarianceSums:
    """Eq. (13–14) statistics and the frame-Jacobian range of one chunk's used samples at
    the calibrated parameters."""
    problem, spec = request.problem, request.spec
    d = problem.residual_dim
    total = CovarianceSums.empty(spec)
    blocks = prepared_blocks(problem, ref)
    columns = spec.frame_columns
    position = {c: s for s, c in enumerate(columns)}
    for index, block in enumerate(blocks):
        used = used_mask(problem, request.rule, ref, index, blocks)
        sweep = sweep_chain(
            problem.chain,
            request.params,
            block.motions,
            block.loads_nm,
            residual_dim=d,
            columns=columns,
        )
        assert sweep.columns is not None and sweep.leading_rows is not None
        residual = pose_residuals(sweep, block.rotation, block.translation).residual
        ranges = frame_range(spec, sweep.columns, position, used)
        n_used = block.n
        if used is not None:
            residual[:, ~used] = 0.0
            sweep.columns[:, :, ~used] = 0.0
            n_used = int(np.count_nonzero(used))
        total = total + covariance_sums(
            spec, sweep.columns, sweep.leading_rows, position, residual, used, ranges, n_used
        )
    return total


def streamed_covariance_sums(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    spec: CovarianceSpec,
    rule: Rule | None = None,
) -> CovarianceSums:
    """One pass: Eq. (13–14) statistics and the Jacobian range of ``spec``'s frames at
    ``params``, summed over chunks in order."""
    request = _CovariancePass(problem, params, spec, rule)
    total: CovarianceSums = functools.reduce(
        operator.add, executor.map(covariance_chunk, request, problem.refs)
    )
    return total


@dataclass(frozen=True, eq=False)
class _SamplesPass:
    problem: StreamProblem
    params: ChainParameters
    frames: tuple[int, ...]
    fit_columns: IntArray | None
    rule: Rule | None
    kernel: Callable[[Any, SampleChunk], Any]
    argument: Any
    token: str


def block_samples(
    problem: StreamProblem,
    params: ChainParameters,
    frames: tuple[int, ...],
    fit_columns: IntArray | None,
    block: Block,
    used: NDArray[np.bool_] | None,
) -> SampleChunk:
    """The used samples of one block as a :class:`SampleChunk`: residuals (n, d), the frame
    Jacobians of the chain joints ``frames`` (n, F, d, 6) and, when ``fit_columns`` are given,
    those stacked-Jacobian columns (n, d, p), unweighted."""
    d = problem.residual_dim
    frame_columns = [6 * f + i for f in frames for i in range(6)]
    fitted = [] if fit_columns is None else [int(c) for c in fit_columns]
    requested = fitted + [c for c in frame_columns if c not in set(fitted)]
    position = {c: s for s, c in enumerate(requested)}
    sweep = sweep_chain(
        problem.chain, params, block.motions, block.loads_nm, residual_dim=d, columns=requested
    )
    assert sweep.columns is not None
    residual = pose_residuals(sweep, block.rotation, block.translation).residual
    keep = np.arange(block.n) if used is None else np.flatnonzero(used)

    def samples_first(columns: FloatArray) -> FloatArray:
        """``columns`` (..., n) as a C-ordered (n_used, ...) array: the samples moved to the
        front in one transposing copy, then the used rows gathered (contiguous rows: ~1.5x
        faster than gathering along the last axis first; these are a pass's largest arrays)."""
        moved = np.ascontiguousarray(np.moveaxis(columns, -1, 0))
        return moved[keep] if used is not None else moved

    frame_index = [position[c] for c in frame_columns]
    first = frame_index[0] if frame_index else 0
    if frame_index == list(range(first, first + len(frame_index))):  # a view, no copy
        jacobians = sweep.columns[first : first + len(frame_index)]  # (F·6, d, n)
    else:
        jacobians = sweep.columns[frame_index]
    fit = None
    if fit_columns is not None:
        fit = samples_first(sweep.columns[: len(fitted)].transpose(1, 0, 2))  # (n, d, p)
    return SampleChunk(
        samples_first(residual),
        samples_first(jacobians.reshape(len(frames), 6, d, block.n).transpose(0, 2, 1, 3)),
        fit,
        (block.first_row + keep).astype(np.intp),
    )


def samples_chunk(request: _SamplesPass, ref: Any) -> list[Any]:
    """The kernel's result for every block of one chunk, in order. The blocks' samples are
    swept once per :class:`StreamedSamples` and kept in the worker for its later passes
    while the cache budget allows (the likelihood fits make a pass per evaluation)."""
    problem = request.problem
    samples = cached_derived(problem, ref, request.token)
    if samples is None:
        blocks = prepared_blocks(problem, ref)
        samples = [
            block_samples(
                problem,
                request.params,
                request.frames,
                request.fit_columns,
                block,
                used_mask(problem, request.rule, ref, index, blocks),
            )
            for index, block in enumerate(blocks)
        ]
        cache_derived(problem, ref, request.token, samples, sum(s.nbytes for s in samples))
    return [request.kernel(request.argument, chunk) for chunk in samples]


@dataclass(frozen=True, eq=False)
class StreamedSamples:
    """The used samples of a streamed recording at the calibrated parameters ``params``:
    :class:`~solver.covariance.samples.CovarianceSamples` whose ``map`` is one pass over the
    chunks on ``executor`` (counted in ``count``). ``frames``: chain joints whose frame is
    perturbed; ``fit_columns``: the deterministic fit's kept columns (for REML), or None;
    ``rule``: the outlier rule of the fit; ``n_samples`` used samples of ``n_rows``."""

    problem: StreamProblem
    executor: Executor
    params: ChainParameters
    frames: tuple[int, ...]
    fit_columns: IntArray | None
    rule: Rule | None
    n_samples: int
    n_rows: int
    count: PassCount
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    @property
    def residual_dim(self) -> int:
        return self.problem.residual_dim

    def map(self, kernel: Callable[[Any, SampleChunk], Any], argument: Any) -> list[Any]:
        request = _SamplesPass(
            self.problem,
            self.params,
            self.frames,
            self.fit_columns,
            self.rule,
            kernel,
            argument,
            self.token,
        )
        per_chunk = self.executor.map(samples_chunk, request, self.problem.refs)
        self.count.passes += 1
        return [part for chunk in per_chunk for part in chunk]

    def on_stride(self, stride: int) -> ArraySamples:
        """One pass sweeping only the used rows whose number is a multiple of ``stride``."""
        request = _StridePass(
            self.problem, self.params, self.frames, self.fit_columns, self.rule, stride
        )
        chunks = [c for c in self.executor.map(stride_chunk, request, self.problem.refs) if c.n]
        self.count.passes += 1
        return ArraySamples.join(chunks, self.n_rows)


@dataclass(frozen=True, eq=False)
class _StridePass:
    problem: StreamProblem
    params: ChainParameters
    frames: tuple[int, ...]
    fit_columns: IntArray | None
    rule: Rule | None
    stride: int


def stride_chunk(request: _StridePass, ref: Any) -> SampleChunk:
    """The used samples of one chunk whose row number is a multiple of the stride (only they
    are swept)."""
    problem = request.problem
    blocks = prepared_blocks(problem, ref)
    parts = []
    for index, block in enumerate(blocks):
        used = used_mask(problem, request.rule, ref, index, blocks)
        rows = block.first_row + np.arange(block.n)
        chosen = np.flatnonzero((rows % request.stride == 0) & (True if used is None else used))
        if chosen.size:
            chunk = block_samples(
                problem,
                request.params,
                request.frames,
                request.fit_columns,
                block.subset(chosen),
                None,
            )
            parts.append(dataclasses.replace(chunk, rows=rows[chosen].astype(np.intp)))
    if not parts:
        d = problem.residual_dim
        fit = None if request.fit_columns is None else np.zeros((0, d, request.fit_columns.size))
        return SampleChunk(
            np.zeros((0, d)),
            np.zeros((0, len(request.frames), d, 6)),
            fit,
            np.zeros(0, dtype=np.intp),
        )
    return SampleChunk(
        np.concatenate([p.residuals for p in parts]),
        np.concatenate([p.frame_jacobians for p in parts]),
        None if request.fit_columns is None else np.concatenate([p.fit_jacobian for p in parts]),  # type: ignore[misc]
        np.concatenate([p.rows for p in parts]),
    )


@dataclass(frozen=True)
class _Predicted:
    frame_covariances: FloatArray  # (F, 6, 6)
    noise_covariance: FloatArray  # (6, 6)
    threshold: float


def _beyond(predicted: _Predicted, samples: SampleChunk) -> NDArray[np.int64]:
    covariance = ee_covariance_batch(
        samples.frame_jacobians, predicted.frame_covariances, predicted.noise_covariance
    )
    far = mahalanobis_squared(samples.residuals, covariance) > predicted.threshold
    return samples.rows[far].astype(np.int64)


def model_rule_removed(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    frames: tuple[int, ...],
    frame_covariances: FloatArray,
    noise_covariance: FloatArray,
    threshold: float,
    n_rows: int,
    count: PassCount,
) -> NDArray[np.int64]:
    """One pass over every sample of the recording: the sorted 0-based rows whose squared
    Mahalanobis distance to the model at ``params`` with covariances Σ_f of ``frames`` and
    Σ_n exceeds ``threshold`` — the model-based outlier rule (each sample judged against its
    own predicted Σ_E(q), Eq. 12)."""
    samples = StreamedSamples(problem, executor, params, frames, None, None, n_rows, n_rows, count)
    predicted = _Predicted(frame_covariances, noise_covariance, threshold)
    parts = samples.map(_beyond, predicted)
    return np.sort(np.concatenate([np.zeros(0, dtype=np.int64), *parts]))
