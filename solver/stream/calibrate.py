"""The streamed calibration as a sequence of stages: warm start, first fit, outlier rule,
refit and "before" fit side by side.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver.calibration import (
    FitOptions,
    check_sample_count,
)
from solver.executors import Executor
from solver.stream.chunks import StreamProblem, count_chunk_rows
from solver.stream.fit import (
    FitRequest,
    PassCount,
    StreamedFit,
    fit_streamed_together,
    read_head,
    warm_start,
    warm_starts,
)
from solver.stream.screening import OutlierRule
from solver.stream.sums import CovarianceSpec, CovarianceSums

# --- the streamed calibration -------------------------------------------------------------


@dataclass(frozen=True)
class StreamSettings:
    """How a recording is streamed: ``warm_start_rows`` in-memory rows for the start and the
    pruning; ``outlier_sigma`` the §V-A rule (None: off)."""

    warm_start_rows: int = 10_000
    outlier_sigma: float | None = 2.0


@dataclass(frozen=True)
class StreamedCalibration:
    """Everything a streamed calibration produced; ``stage_s``: wall time per stage
    ("read": preparing every chunk, beside the first warm start; "warm_start": the refit's
    and "before" fit's warm starts; "deterministic": the streamed fits); ``passes``: passes
    over the data; ``covariance``: the covariance statistics at ``fit.params`` when a fit
    pass took them along (None: the covariance stage needs a pass for them)."""

    n_rows: int
    first: StreamedFit
    fit: StreamedFit
    baseline: StreamedFit
    rule: OutlierRule | None
    removed_rows: NDArray[np.int64]
    stage_s: dict[str, float]
    passes: int
    covariance: CovarianceSums | None = None


def calibrate_streamed_fits(
    problem: StreamProblem,
    executor: Executor,
    options: FitOptions,
    baseline_options: FitOptions,
    settings: StreamSettings = StreamSettings(),
    covariance: CovarianceSpec | None = None,
    progress: Callable[[str], None] | None = None,
) -> StreamedCalibration:
    """Deterministic calibration of a streamed recording: warm start on the head rows, the
    first fit, the 2σ rule, the refit on the kept samples and the "before" fit (measurement
    frame and tool on the nominal robot), as :func:`service.pipeline.calibrate` does in memory.

    Passes: one to prepare the chunks (while the driver fits the head rows), the first fit's
    (its last pass leaves the residuals the 2σ rule is applied to), then the refit's and the
    "before" fit's together; with ``covariance`` the refit's passes after the first also take
    the covariance statistics (:attr:`StreamedCalibration.covariance`). ``progress(stage)`` is
    called as "read", "fit" (the first fit) and "baseline" (the refit and the "before" fit)
    end.
    """
    report = progress or (lambda stage: None)
    count = PassCount()
    clock = time.perf_counter()
    scanning = executor.map_async(count_chunk_rows, problem, problem.refs)
    head = read_head(problem, settings.warm_start_rows)
    start, keep = warm_start(problem, head, options)
    if settings.outlier_sigma is None:
        baseline_start, baseline_keep = warm_start(problem, head, baseline_options)
    n_rows = int(sum(scanning.result()))
    count.passes += 1
    check_sample_count(problem.chain, n_rows, position_only=problem.position_only, options=options)
    stage = {"read": time.perf_counter() - clock, "warm_start": 0.0}
    report("read")
    clock = time.perf_counter()
    rule = None
    if settings.outlier_sigma is None:
        first, baseline = fit_streamed_together(
            problem,
            executor,
            [
                FitRequest(start, keep, options, covariance=covariance),
                FitRequest(baseline_start, baseline_keep, baseline_options),
            ],
            count,
        )
        fit = first
        report("fit")
    else:
        (first,) = fit_streamed_together(
            problem, executor, [FitRequest(start, keep, options, keep_residuals=True)], count
        )
        report("fit")
        spread = first.sums.spread
        rule = OutlierRule(first.params, spread.mean, spread.std, settings.outlier_sigma)
        warm = time.perf_counter()
        used_head = head.kept_by(problem, rule)
        (refit_start, refit_keep), (baseline_start, baseline_keep) = warm_starts(
            problem, executor, used_head, [options, baseline_options]
        )
        stage["warm_start"] = time.perf_counter() - warm
        fit, baseline = fit_streamed_together(
            problem,
            executor,
            [
                FitRequest(refit_start, refit_keep, options, rule, covariance=covariance),
                FitRequest(baseline_start, baseline_keep, baseline_options, rule),
            ],
            count,
        )
    stage["deterministic"] = time.perf_counter() - clock - stage["warm_start"]
    report("baseline")
    removed = fit.sums.removed_rows if rule is not None else np.zeros(0, dtype=np.int64)
    return StreamedCalibration(
        n_rows,
        first,
        fit,
        baseline,
        rule,
        np.sort(removed),
        stage,
        count.passes,
        fit.sums.covariance,
    )
