"""Streamed covariance calibration (paper §IV-C): moment matching (Eq. 13–14) from chunk sums."""

from __future__ import annotations

import dataclasses
import functools
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solver.batch_chain import (
    pose_residuals,
    sweep_chain,
)
from solver.covariance.estimate import (
    SE_METHOD,
    CovarianceEstimate,
    SolverName,
    frame_results,
)
from solver.covariance.identifiability import (
    RANK_RTOL,
    WEAK_RTOL,
    analyse_identifiability,
    resolve_null_space,
)
from solver.covariance.likelihood import moment_sandwich_meat
from solver.covariance.solvers import PGD_STABLE, concrete_solver, solve_moment
from solver.covariance.uncertainty import theta_covariance, theta_uncertainty
from solver.errors import CalibrationError, SolverError
from solver.executors import Executor
from solver.kinematics import ChainParameters
from solver.stream.chunks import StreamProblem, prepared_blocks
from solver.stream.fit import PassCount
from solver.stream.screening import OutlierRule, used_mask
from solver.stream.sums import CovarianceSpec, CovarianceSums, covariance_sums, frame_range

FloatArray = NDArray[np.float64]


STREAMED_ESTIMATOR_NOTE = (
    "streamed calibration: covariances by moment matching (Eq. 13-14), which streams exactly; "
    "ML/REML need a pass over the data per scoring step (at this many samples the REML "
    "correction is O(p/N))"
)


@dataclass(frozen=True, eq=False)
class _CovariancePass:
    problem: StreamProblem
    params: ChainParameters
    spec: CovarianceSpec
    rule: OutlierRule | None
    theta: FloatArray | None  # None: statistics pass; else the sandwich pass at θ
    stride: int = 1  # sandwich pass: every stride-th row of the recording


def covariance_chunk(request: _CovariancePass, ref: Any) -> CovarianceSums:
    """Residuals and frame Jacobians ``A_f = Ad_{B_f}⁻¹`` (rows d) of one chunk at the
    calibrated parameters, reduced to Eq. (14) statistics or, given θ, the sandwich meat
    (of every ``stride``-th row: only those rows are swept)."""
    problem, spec = request.problem, request.spec
    d = problem.residual_dim
    total = CovarianceSums.empty(spec, sandwich=request.theta is not None)
    blocks = prepared_blocks(problem, ref)
    columns = spec.frame_columns
    position = {c: s for s, c in enumerate(columns)}
    for index, block in enumerate(blocks):
        used = used_mask(problem, request.rule, ref, index, blocks)
        chosen = None
        if request.theta is not None:  # sandwich pass: only its rows are swept
            rows = block.first_row + np.arange(block.n)
            chosen = np.flatnonzero((rows % request.stride == 0) & (True if used is None else used))
            if not chosen.size:
                continue
            block = block.subset(chosen)
        sweep = sweep_chain(
            problem.chain,
            request.params,
            block.motions,
            block.loads_nm,
            residual_dim=d,
            columns=columns,
        )
        assert sweep.columns is not None and sweep.leading_rows is not None
        if request.theta is not None and chosen is not None:
            jacobians = sweep.columns.reshape(len(spec.frames), 6, d, -1).transpose(3, 0, 2, 1)
            meat = moment_sandwich_meat(
                request.theta,
                np.ascontiguousarray(jacobians),
                spec.layout,
                known_covariance=spec.known,
            )
            empty = CovarianceSums.empty(spec, sandwich=True)
            total = total + dataclasses.replace(empty, meat=meat, n=int(chosen.size))
            continue
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
    rule: OutlierRule | None = None,
    *,
    theta: FloatArray | None = None,
    stride: int = 1,
) -> CovarianceSums:
    """One pass: Eq. (13–14) statistics (``theta`` None) or the sandwich meat at ``theta`` (of
    every ``stride``-th row), and the Jacobian range, of ``spec``'s frames at ``params``,
    summed over chunks."""
    request = _CovariancePass(problem, params, spec, rule, theta, stride)
    total: CovarianceSums = functools.reduce(
        operator.add, executor.map(covariance_chunk, request, problem.refs)
    )
    return total


def estimate_covariances_streamed(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    spec: CovarianceSpec,
    *,
    solver: SolverName = "auto",
    rule: OutlierRule | None = None,
    confidence: float = 0.95,
    notes: Sequence[str] = (),
    sandwich_rows: int = 50_000,
    sums: CovarianceSums | None = None,
    count: PassCount | None = None,
) -> CovarianceEstimate:
    """Moment-matching covariance calibration (paper §IV-C, Eq. 13–14) of a streamed recording:
    the same steps as :func:`solver.covariance.estimate.estimate_covariances` with
    ``estimator="moment"``, its sums over samples taken chunk by chunk.

    ``spec`` (:func:`covariance_spec`): frames, layout and known noise; residuals and
    Jacobians in the end-effector frame ([v; w], m and rad) at ``params``; ``rule``: the
    outlier rule of the deterministic fit (the same samples are used); ``notes`` start the
    warnings; ``sums``: the statistics at ``params`` when a fit pass already took them (the
    deterministic fit's last pass), else one pass takes them.

    Standard errors need the sandwich ``Σ_n 2K̃ᵀK̃`` at θ̂, a second pass with a 6×6 whitening
    per sample; beyond ``sandwich_rows`` samples it is summed over every s-th row of the
    recording (s fixed by the row number, so independent of the chunking) and scaled by the
    ratio of counts — an unbiased estimate of the sum, for errors that need 2 digits, not 10.
    Only those rows are swept.
    """
    count = count if count is not None else PassCount()
    layout = spec.layout
    if sums is None:
        sums = streamed_covariance_sums(problem, executor, params, spec, rule)
        count.passes += 1
    if sums.n < 2:
        raise CalibrationError(f"covariance calibration needs at least 2 samples, got {sums.n}")
    assert sums.stats is not None
    stats = sums.stats
    if not (np.all(np.isfinite(stats.gram)) and np.all(np.isfinite(stats.cross))):
        raise CalibrationError("residuals or frame Jacobians contain NaN or inf")
    report = analyse_identifiability(
        stats, rank_rtol=RANK_RTOL, weak_rtol=WEAK_RTOL, frame_jacobians=_jacobian_range(sums)
    )
    structure = layout.structure
    solver_used = concrete_solver(solver, structure)
    moment = solve_moment(stats, solver_used, pgd_settings=PGD_STABLE)
    if not np.all(np.isfinite(moment.theta)):
        raise SolverError(
            f"moment solver {solver_used!r} failed ({moment.status}): {moment.message}"
        )
    notes = [*notes, *report.warnings]
    if not moment.converged:
        notes.append(
            f"moment solver {solver_used!r} ended with status {moment.status!r}"
            + (f": {moment.message}" if moment.message else "")
        )
    theta = resolve_null_space(moment.theta, report, layout)
    cov, unc = None, None
    stride = max(1, -(-sums.n // sandwich_rows))  # ceil
    meat_sums = streamed_covariance_sums(
        problem, executor, params, spec, rule, theta=theta, stride=stride
    )
    count.passes += 1
    try:
        assert meat_sums.meat is not None
        meat = meat_sums.meat * (sums.n / meat_sums.n)  # a sum over all samples
        cov = theta_covariance(meat, report, bread=stats.gram)
        unc = theta_uncertainty(
            theta,
            cov,
            report,
            layout.is_variance,
            confidence=confidence,
            method=SE_METHOD["moment"],
        )
    except CalibrationError as exc:
        notes.append(f"no standard errors: {exc}")
    frames, noise = frame_results(layout, theta, unc, spec.known, spec.noise_name)
    return CovarianceEstimate(
        "moment",
        structure,
        solver_used,
        sums.n,
        frames,
        noise,
        theta,
        layout,
        report,
        moment,
        moment,
        stats,
        cov,
        unc,
        tuple(notes),
    )


def _jacobian_range(sums: CovarianceSums) -> FloatArray:
    """Two pseudo-samples (2, F, d, 6) with the recording's mean Jacobian and, per entry, its
    largest deviation from the mean: the constant-Jacobian check sees the same mean and
    spread as on all samples."""
    mean = sums.jacobian_sum / sums.n
    deviation = np.maximum(sums.jacobian_max - mean, mean - sums.jacobian_min)
    return np.stack([mean + deviation, mean - deviation])
