"""The calibration of a recording as a sequence of stages over its chunks: warm start, first
fit, outlier rule, refit and "before" fit side by side, covariances, held-out evaluation.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from solver.arrays import FloatArray, IntArray
from solver.calibration import (
    FitOptions,
    check_sample_count,
    identifiable_parameter_count,
    implausible_columns,
    lower_cost_restart,
    without_columns,
)
from solver.covariance.estimate import (
    FULL_LIKELIHOOD_SAMPLES,
    SE_SAMPLES,
    CovarianceEstimate,
    EstimatorName,
    estimate_from_samples,
)
from solver.covariance.samples import (
    ArraySamples,
    CovarianceSamples,
    SampleChunk,
    row_stride,
    subsample,
)
from solver.covariance.solvers import SolverName
from solver.evaluation import SplitError, score_splits, split_indices
from solver.executors import Executor
from solver.kinematics import ChainParameters, forward_kinematics, parameter_names
from solver.measurement.models import FullPose
from solver.measurement.pose import fit_deterministic
from solver.model import KinematicChain
from solver.stream.chunks import StreamProblem, count_chunk_rows
from solver.stream.covariance import (
    StreamedSamples,
    model_rule_removed,
    streamed_covariance_sums,
)
from solver.stream.coverage import (
    PredictiveCalibration,
    RandomEffectSettings,
    SplitCoverage,
    WarmStart,
    calibration_predictive,
    split_coverage,
    subset_reference,
)
from solver.stream.fit import (
    FitRequest,
    PassCount,
    RowSample,
    StreamedFit,
    evaluate_starts,
    fit_streamed_together,
    gather_rows,
    read_head,
    warm_start,
    warm_starts,
)
from solver.stream.screening import (
    OutlierRule,
    RowRule,
    Rule,
    covariance_too_uncertain,
    family_wise_t2,
    family_wise_z,
    model_rule_refusal,
    robust_spread,
)
from solver.stream.sums import CovarianceSpec, CovarianceSums

# --- the streamed calibration -------------------------------------------------------------


OutlierRuleName = Literal["model", "sigma", "none"]
HeldoutMethod = Literal["one-step", "exact"]


@dataclass(frozen=True)
class StreamSettings:
    """How a recording is streamed and screened: ``warm_start_rows`` in-memory rows for the
    start and the pruning; ``outlier_rule``: "model" (gross errors judged by the fitted model
    at the family-wise ``outlier_level``), "sigma" (the paper's §V-A rule at
    ``outlier_sigma`` standard deviations) or "none"."""

    warm_start_rows: int = 10_000
    outlier_rule: OutlierRuleName = "model"
    outlier_sigma: float = 2.0
    outlier_level: float = 0.01


@dataclass(frozen=True)
class StreamedCalibration:
    """Everything a streamed calibration produced; ``stage_s``: wall time per stage
    ("read": preparing every chunk, beside the first warm start; "warm_start": the refit's
    and "before" fit's warm starts; "deterministic": the streamed fits); ``passes``: passes
    over the data; ``covariance``: the covariance statistics at ``fit.params`` when a fit
    pass took them along (None: the covariance stage needs a pass for them); ``head``: the
    first rows in memory (the warm starts' rows); ``first``: the streamed fit of every row
    the paper's 2σ rule and no rule judge (None for the model rule, whose first step judges
    at the head rows' fit)."""

    n_rows: int
    first: StreamedFit | None
    fit: StreamedFit
    baseline: StreamedFit
    rule: Rule | None
    removed_rows: NDArray[np.int64]
    stage_s: dict[str, float]
    passes: int
    head: RowSample
    covariance: CovarianceSums | None = None
    screening_refused: Literal["not_converged", "model_misfit"] | None = None
    screening_refused_rows: int = 0
    screening_skipped: str | None = None
    """Why the model rule's Σ_E step judged no row (None: it ran, or the rule is not "model")."""


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
    outlier rule's first step, the refit on the kept samples and the "before" fit
    (measurement frame and tool on the nominal robot).

    The rule's first step is the paper's 2σ rule ("sigma", at a streamed first fit of every
    row) or, for "model", the same per-component test with the median and scaled MAD of the
    head rows' residuals at the head rows' fit and a family-wise threshold
    (:func:`family_wise_z`); the model-based second step needs the covariances and runs in
    :func:`calibrate_recording`.

    Passes: one to prepare the chunks (while the driver fits the head rows), for "sigma" the
    first fit's (its last pass leaves the residuals the rule is applied to), then the refit's
    and the "before" fit's together; with ``covariance`` the refit's passes after the first
    also take the covariance statistics (:attr:`StreamedCalibration.covariance`).
    ``progress(stage)`` is called as "read", "fit" (the rule's first step) and "baseline"
    (the refit and the "before" fit) end.
    """
    report = progress or (lambda stage: None)
    count = PassCount()
    clock = time.perf_counter()
    scanning = executor.map_async(count_chunk_rows, problem, problem.refs)
    head = read_head(problem, settings.warm_start_rows)
    start, keep, pruned = warm_start(problem, head, options)
    if settings.outlier_rule == "none":
        baseline_start, baseline_keep, _ = warm_start(problem, head, baseline_options)
    n_rows = int(sum(scanning.result()))
    count.passes += 1
    check_sample_count(problem.chain, n_rows, dim=problem.residual_dim, options=options)
    stage = {"read": time.perf_counter() - clock, "warm_start": 0.0}
    report("read")
    clock = time.perf_counter()
    rule: Rule | None = None
    if settings.outlier_rule == "none":
        request = FitRequest(start, keep, options, covariance=covariance, pruned=pruned)
        first, baseline = fit_streamed_together(
            problem,
            executor,
            [request, FitRequest(baseline_start, baseline_keep, baseline_options)],
            count,
        )
        fit = first = non_negative_fit(problem, executor, first, request, count)
        report("fit")
    else:
        if settings.outlier_rule == "sigma":
            (first,) = fit_streamed_together(
                problem,
                executor,
                [FitRequest(start, keep, options, keep_residuals=True, pruned=pruned)],
                count,
            )
            rule = sigma_rule(first, settings)
            expect_pruning = _implausible(problem, first).size > 0
        else:
            # the robust first step needs no streamed fit: the head rows' fit, whose parameters
            # start the streamed fits, judges every row (median and MAD resist the outliers
            # that fit has seen); the model-based second step judges every row again
            first = None
            rule = robust_first_step(problem, head, start, n_rows, settings)
            expect_pruning = bool(np.any(start.compliance_rad_per_nm < 0.0))
        report("fit")
        warm = time.perf_counter()
        fit, baseline = fits_under_rule(
            problem,
            executor,
            head,
            rule,
            options,
            baseline_options,
            covariance,
            count,
            expect_pruning=expect_pruning,
        )
        stage["warm_start"] = max(0.0, time.perf_counter() - warm - fit.elapsed_s)
    stage["deterministic"] = time.perf_counter() - clock - stage["warm_start"]
    report("baseline")
    return StreamedCalibration(
        n_rows,
        first,
        fit,
        baseline,
        rule,
        _removed(fit, rule),
        stage,
        count.passes,
        head,
        fit.sums.covariance,
    )


def _removed(fit: StreamedFit, rule: Rule | None) -> NDArray[np.int64]:
    removed = fit.sums.removed_rows if rule is not None else np.zeros(0, dtype=np.int64)
    return np.sort(removed)


def sigma_rule(first: StreamedFit, settings: StreamSettings) -> OutlierRule:
    """The paper's §V-A rule at the first fit's parameters: per component, the mean and σ of
    every sample it used, ``outlier_sigma`` standard deviations."""
    spread = first.sums.spread
    return OutlierRule(first.params, spread.mean, spread.std, settings.outlier_sigma)


def robust_first_step(
    problem: StreamProblem,
    head: RowSample,
    params: ChainParameters,
    n_rows: int,
    settings: StreamSettings,
) -> OutlierRule:
    """The model rule's robust first step at ``params``: per component, the median and
    1.4826·MAD of the head rows' residuals, threshold :func:`family_wise_z` at
    ``outlier_level`` for ``n_rows`` rows."""
    residuals = head.residuals_at(problem, params)
    centre, scale = robust_spread(residuals)
    z = family_wise_z(settings.outlier_level, n_rows, problem.residual_dim)
    return OutlierRule(params, centre, scale, z)


def fits_under_rule(
    problem: StreamProblem,
    executor: Executor,
    head: RowSample,
    rule: Rule,
    options: FitOptions,
    baseline_options: FitOptions,
    covariance: CovarianceSpec | None,
    count: PassCount,
    *,
    expect_pruning: bool = False,
) -> tuple[StreamedFit, StreamedFit]:
    """The refit and the "before" fit on the samples ``rule`` keeps, side by side, each
    warm-started on the head rows it keeps. ``expect_pruning``: the fit before had
    compliances :func:`non_negative_fit` fixes at 0, so the refit will most likely be
    repeated: only the repeat's passes take the covariance statistics along (when the guess
    is wrong the covariance stage takes them in a pass of its own; the numbers are the same)."""
    used_head = head.kept_by(problem, rule)
    (refit_start, refit_keep, refit_pruned), (baseline_start, baseline_keep, _) = warm_starts(
        problem, executor, used_head, [options, baseline_options]
    )
    deferred = expect_pruning and options.non_negative_compliance
    refit = FitRequest(
        refit_start,
        refit_keep,
        options,
        rule,
        covariance=None if deferred else covariance,
        pruned=refit_pruned,
    )
    fit, baseline = fit_streamed_together(
        problem,
        executor,
        [refit, FitRequest(baseline_start, baseline_keep, baseline_options, rule)],
        count,
    )
    return non_negative_fit(
        problem, executor, fit, replace(refit, covariance=covariance), count
    ), baseline


def _implausible(problem: StreamProblem, fit: StreamedFit) -> IntArray:
    """The columns of ``fit`` the data do not place in a physical range
    (:func:`~solver.calibration.implausible_columns`)."""
    names = parameter_names(problem.chain)
    keep = np.array([names.index(n) for n in fit.estimated], dtype=np.intp)
    return implausible_columns(problem.chain, fit.params, keep, fit.standard_errors)


def non_negative_fit(
    problem: StreamProblem,
    executor: Executor,
    fit: StreamedFit,
    request: FitRequest,
    count: PassCount,
) -> StreamedFit:
    """``fit`` with every parameter the data do not place in a physical range fixed
    (:func:`solver.calibration.implausible_columns`: a compliance negative or unidentified at
    0, an inner link's twist component unidentified at its nominal value) and the fit repeated,
    as :func:`solver.measurement.pose.fit_deterministic` does in memory: from the last iterate
    with those reset or from ``request.start`` with every parameter fixed so far reset,
    whichever has the lower cost (:func:`~solver.calibration.lower_cost_restart`; both
    evaluated in one pass, which is the repeated fit's first). The fixed ones are listed in
    ``pruned``."""
    if not request.options.non_negative_compliance:
        return fit
    chain = problem.chain
    names = parameter_names(chain)
    keep = np.array([names.index(n) for n in fit.estimated], dtype=np.intp)
    pruned: list[str] = list(fit.pruned)
    before = fit  # the iterations, costs, passes and time of every fit so far are reported
    while (negative := _implausible(problem, fit)).size:
        pruned += [names[c] for c in negative]
        only_compliance = bool(np.all(negative >= 6 * chain.n_links))
        at_last = without_columns(
            chain,
            fit.params,
            negative,
            at_optimum=(keep, fit.sums.normal) if fit.converged else None,
        )
        fixed = np.array([names.index(n) for n in pruned], dtype=np.intp)
        keep = np.setdiff1d(keep, negative)
        restart = replace(
            request, start=at_last, keep=keep, start_is_close=fit.converged and only_compliance
        )
        fresh = replace(
            request,
            start=without_columns(chain, request.start, fixed),
            keep=keep,
            start_is_close=False,
        )
        chosen, (_, first) = lower_cost_restart(
            restart,
            fresh,
            lambda starts: [
                (sums.normal, sums) for sums in evaluate_starts(problem, executor, starts, count)
            ],
        )
        (fit,) = fit_streamed_together(problem, executor, [replace(chosen, first=first)], count)
        fit = replace(
            fit,
            iterations=before.iterations + fit.iterations,
            cost_history=before.cost_history + fit.cost_history,
            passes=before.passes + fit.passes,
            elapsed_s=before.elapsed_s + fit.elapsed_s,
        )
        before = fit
    if not pruned:
        return fit
    return replace(fit, removed=[n for n in fit.removed if n not in pruned], pruned=pruned)


# --- the whole calibration of a recording --------------------------------------------------

BEFORE = "before"
CALIBRATED = "calibrated"
"""The two methods of the held-out evaluation: the nominal robot with the measurement frame and
tool fitted ("before"), and the full calibration."""

HELDOUT_ROWS = 1_000
"""The held-out evaluation (DESIGN.md §4) fits and scores at most this many used rows, evenly
spaced over the recording (every row below that): each split fits the geometry and, for the
coverage, four sets of covariances on its training rows; a held-out error and a coverage
share need a thousand poses (the 95 % share to ±0.7 %), not millions."""

IN_MEMORY_SAMPLES = FULL_LIKELIHOOD_SAMPLES
"""Up to this many used samples the covariance stage gathers them into memory once (each
likelihood evaluation then costs no sweep of the chain); beyond, every evaluation is a pass
over the recording and the likelihood takes one scoring step. The numbers are the same either
way."""


@dataclass(frozen=True)
class CovarianceSettings:
    """The covariance stage: frames, θ layout and known noise (``spec``), estimator, solver."""

    spec: CovarianceSpec
    estimator: EstimatorName = "reml"
    solver: SolverName = "auto"


@dataclass(frozen=True)
class HeldoutSettings:
    """DESIGN.md §4: one random train/test split per seed, ``train_fraction`` of the rows
    training, on at most ``max_rows`` used rows (evenly spaced over the recording)."""

    seeds: tuple[int, ...]
    train_fraction: float = 0.9
    max_rows: int = HELDOUT_ROWS
    method: HeldoutMethod = "one-step"
    """"one-step": every split's fits are one step from the calibration of all rows (issue
    29, :class:`~solver.stream.coverage.WarmStart`); "exact": iterated to convergence from
    the nominal start, as a calibration of those rows alone would be."""


@dataclass(frozen=True)
class RecordingCalibration:
    """A calibrated recording: the deterministic fits, the covariance estimate (None when not
    asked for), the held-out splits, and ``sample``: the used rows whose row number is a
    multiple of ``sample_stride``, in memory (the held-out evaluation's rows, and what a
    report plots). ``stage_s``: wall time per stage; ``passes``: passes over the data."""

    fits: StreamedCalibration
    covariance: CovarianceEstimate | None
    splits: list[SplitError]
    sample: RowSample
    sample_stride: int
    stage_s: dict[str, float]
    passes: int
    predictive: PredictiveCalibration | None = None
    """The parts of the predictive covariance beyond Σ_E (Cov(θ̂), model error) and their
    held-out coverage (issue 13); None without covariances."""


def calibrate_recording(
    problem: StreamProblem,
    executor: Executor,
    options: FitOptions,
    baseline_options: FitOptions,
    settings: StreamSettings = StreamSettings(),
    covariance: CovarianceSettings | None = None,
    heldout: HeldoutSettings | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> RecordingCalibration:
    """The calibration of a recording, whatever its size and wherever its chunks are
    processed: the deterministic fits (:func:`calibrate_streamed_fits`, Eq. 8–10 and the
    outlier rule), the covariances of the random perturbations (§IV-C; any estimator, by
    :func:`~solver.covariance.estimate.estimate_from_samples`), and the held-out evaluation
    of DESIGN.md §4. ``progress(stage, done, total)`` after "read", "fit", "baseline",
    "covariance" and each held-out split ("heldout").
    """
    report = progress or (lambda stage, done, total: None)
    run = calibrate_streamed_fits(
        problem,
        executor,
        options,
        baseline_options,
        settings,
        covariance=None if covariance is None else covariance.spec,
        progress=lambda stage: report(stage, 1, 1),
    )
    count = PassCount(run.passes)
    stage = dict(run.stage_s)
    estimate = None
    if covariance is not None:
        clock = time.perf_counter()
        estimate = covariance_stage(problem, executor, run, covariance, count)
        stage["covariance"] = time.perf_counter() - clock
        if settings.outlier_rule == "model":
            clock = time.perf_counter()
            run, estimate = screen_by_model(
                problem,
                executor,
                run,
                estimate,
                options,
                baseline_options,
                settings,
                covariance,
                count,
            )
            stage["screening"] = time.perf_counter() - clock
        report("covariance", 1, 1)
    clock = time.perf_counter()
    limit = heldout.max_rows if heldout is not None else HELDOUT_ROWS
    stride = row_stride(run.n_rows, limit)
    sample = gather_rows(problem, executor, run.rule, stride)
    count.passes += 1
    splits: list[SplitError] = []
    coverage: dict[int, SplitCoverage] = {}
    if heldout is not None:
        evaluation = HeldoutProblem(
            problem.chain,
            sample,
            problem.measurement,
            options,
            baseline_options,
            heldout,
            None
            if covariance is None
            else RandomEffectSettings(covariance.spec, covariance.estimator, covariance.solver),
            None if heldout.method == "exact" else _warm_starts(run, estimate, problem),
        )
        splits, coverage = heldout_evaluation(evaluation, executor, report)
    stage["heldout"] = time.perf_counter() - clock
    predictive = None
    if estimate is not None and covariance is not None:
        predictive = _predictive(
            problem, run, estimate, sample, covariance.spec.frames, options, coverage
        )
    return RecordingCalibration(
        run, estimate, splits, sample, stride, stage, count.passes, predictive
    )


def _warm_starts(
    run: StreamedCalibration, estimate: CovarianceEstimate | None, problem: StreamProblem
) -> dict[str, WarmStart]:
    """Where the one-step held-out splits start: the "before" fit and the calibration of all
    used rows, with its covariance estimate where the recording has enough equations for the
    stepped subset estimates (:func:`~solver.stream.coverage.subset_reference`)."""
    n_equations = run.fit.sums.errors.n * problem.residual_dim
    return {
        BEFORE: WarmStart(run.baseline.params, run.baseline.estimated),
        CALIBRATED: WarmStart(
            run.fit.params, run.fit.estimated, subset_reference(estimate, n_equations)
        ),
    }


def _predictive(
    problem: StreamProblem,
    run: StreamedCalibration,
    estimate: CovarianceEstimate,
    sample: RowSample,
    frames: tuple[int, ...],
    options: FitOptions,
    coverage: dict[int, SplitCoverage],
) -> PredictiveCalibration:
    """Cov(θ̂) of the calibration (normal matrix of every used sample, meat over the
    in-memory rows), its model-error part and the coverage of the held-out splits."""
    fit = run.fit
    return calibration_predictive(
        problem.chain,
        fit.params,
        fit.estimated,
        fit.sums.normal.gram,
        fit.sums.errors.n,
        sample,
        estimate,
        frames,
        problem.measurement,
        options.rotation_weight_m_per_rad,
        coverage,
    )


MODEL_RULE_ROUNDS = 3
"""The model-based rule re-judges every sample against the refitted model at most this many
times; it stops as soon as a round removes the same rows as the fit it judged."""


def screen_by_model(
    problem: StreamProblem,
    executor: Executor,
    run: StreamedCalibration,
    estimate: CovarianceEstimate,
    options: FitOptions,
    baseline_options: FitOptions,
    settings: StreamSettings,
    covariance: CovarianceSettings,
    count: PassCount,
) -> tuple[StreamedCalibration, CovarianceEstimate]:
    """The model-based outlier rule's second step: every sample of the recording (including
    those the first step removed) judged against its own predicted covariance, residual
    ``r_nᵀ Σ_E(q_n)⁻¹ r_n`` with Σ_E of Eq. 12 (noise included) at the refit, removed beyond
    the quantile at which one clean sample of the whole recording would fall with probability
    ``outlier_level`` (Bonferroni; Hotelling's T², as Σ_E is itself estimated:
    :func:`family_wise_t2`); then the fits and covariances again on the
    samples kept, until the removed rows no longer change. A round that would leave too few
    rows to fit, or remove more than half of them (:func:`model_rule_refusal`), removes
    nothing: the fit it judged by is kept and :attr:`StreamedCalibration.screening_refused`
    names why (that fit did not converge, or the model does not explain the data).

    A clean sample is removed with probability at most ``outlier_level / N``, so the kept
    residuals are not truncated in any way that biases the covariance (the lost tail mass is
    below ``outlier_level / N`` of the distribution): no correction is needed, unlike after the
    2σ rule, which cuts ~4.6 % of every component.

    Skipped, the reason in :attr:`StreamedCalibration.screening_skipped`, when Σ_E rests on too
    few residual equations per identifiable covariance entry
    (:func:`~solver.stream.screening.covariance_too_uncertain`), as for a measurement model.
    """
    d = problem.residual_dim
    too_uncertain = covariance_too_uncertain(
        run.fit.sums.errors.n * d, estimate.identifiability.rank
    )
    if too_uncertain is not None:
        return replace(run, screening_skipped=too_uncertain), estimate
    frames = covariance.spec.frames
    required = identifiable_parameter_count(problem.chain, dim=d, options=options)
    min_rows = required // d + 1
    for _ in range(MODEL_RULE_ROUNDS):
        # Σ_E(q) comes from the used samples' residuals, which lost p/d degrees of freedom
        # per component to the deterministic fit
        dof = run.fit.sums.errors.n - len(run.fit.estimated) / d
        threshold = family_wise_t2(settings.outlier_level, run.n_rows, d, dof)
        removed = model_rule_removed(
            problem,
            executor,
            run.fit.params,
            frames,
            estimate.frame_covariances(),
            estimate.noise_covariance(),
            threshold,
            run.n_rows,
            count,
        )
        if np.array_equal(removed, run.removed_rows):
            break
        refused = model_rule_refusal(
            run.n_rows, removed.size, min_rows, converged=run.fit.converged
        )
        if refused is not None:
            run = replace(run, screening_refused=refused, screening_refused_rows=removed.size)
            break
        rule = RowRule(removed)
        fit, baseline = fits_under_rule(
            problem,
            executor,
            run.head,
            rule,
            options,
            baseline_options,
            covariance.spec,
            count,
            expect_pruning=bool(run.fit.pruned),
        )
        run = replace(
            run,
            fit=fit,
            baseline=baseline,
            rule=rule,
            removed_rows=_removed(fit, rule),
            passes=count.passes,
            covariance=fit.sums.covariance,
        )
        estimate = covariance_stage(problem, executor, run, covariance, count)
    return run, estimate


def covariance_stage(
    problem: StreamProblem,
    executor: Executor,
    run: StreamedCalibration,
    settings: CovarianceSettings,
    count: PassCount,
    *,
    in_memory_samples: int = IN_MEMORY_SAMPLES,
) -> CovarianceEstimate:
    """§IV-C at the refit's parameters, on the samples it used: gathered into memory up to
    ``in_memory_samples`` of them, else every evaluation a pass over the recording."""
    spec = settings.spec
    sums = run.covariance
    if sums is None:  # the refit stopped at its start: no pass took the statistics along
        sums = streamed_covariance_sums(problem, executor, run.fit.params, spec, run.rule)
        count.passes += 1
    names = parameter_names(problem.chain)
    fit_columns = None
    if settings.estimator == "reml":
        fit_columns = np.array([names.index(n) for n in run.fit.estimated], dtype=np.intp)

    def streamed(columns: IntArray | None) -> StreamedSamples:
        return StreamedSamples(
            problem,
            executor,
            run.fit.params,
            spec.frames,
            columns,
            run.rule,
            sums.n,
            run.n_rows,
            count,
        )

    samples: CovarianceSamples = streamed(fit_columns)
    sub = None
    if sums.n <= in_memory_samples:
        samples = ArraySamples.join(samples.map(_all_samples, None), run.n_rows)
    elif sums.n > FULL_LIKELIHOOD_SAMPLES:
        # REML's fit Jacobian is needed on the subsample only (its restriction terms)
        sub = subsample(samples, SE_SAMPLES)
        samples = streamed(None)
    return estimate_from_samples(
        samples,
        spec.layout,
        known=spec.known,
        estimator=settings.estimator,
        solver=settings.solver,
        noise_name=spec.noise_name,
        statistics=(sums.stats, sums.jacobians),
        sample_subset=sub,
    )


def _all_samples(_: None, chunk: SampleChunk) -> SampleChunk:
    return chunk


@dataclass(frozen=True, eq=False)
class HeldoutProblem:
    """The held-out evaluation of rows in memory (``sample``): the chain, the two methods'
    fit settings and the splits (sent to the workers once per call); with ``coverage`` the
    calibrated method's split also estimates every part of the predictive covariance from its
    training rows and scores its test rows (:func:`solver.stream.coverage.split_coverage`)."""

    chain: KinematicChain
    sample: RowSample
    measurement: FullPose
    options: FitOptions
    baseline_options: FitOptions
    settings: HeldoutSettings
    coverage: RandomEffectSettings | None = None
    starts: dict[str, WarmStart] | None = None
    """Per method, the calibration of all rows its splits start from (None: exact refits)."""


def _heldout_fit(
    evaluation: HeldoutProblem, item: tuple[int, str]
) -> tuple[FloatArray, SplitCoverage | None]:
    """The predicted test poses (n_test, 4, 4) of one method on one split, and for the
    calibrated method (with ``evaluation.coverage``) the split's coverage."""
    seed, method = item
    sample = evaluation.sample
    train, test = split_indices(sample.n, seed, evaluation.settings.train_fraction)
    options = evaluation.baseline_options if method == BEFORE else evaluation.options
    warm = None if evaluation.starts is None else evaluation.starts[method]
    fit = fit_deterministic(
        evaluation.chain,
        sample.joint_positions[train],
        sample.measured_pose[train],
        sample.loads_nm[train],
        measurement=evaluation.measurement,
        options=options,
        start=None if warm is None else warm.params,
        estimated=None if warm is None else warm.estimated,
    )
    predicted = forward_kinematics(
        evaluation.chain, fit.params, sample.joint_positions[test], sample.loads_nm[test]
    )
    coverage = None
    if method == CALIBRATED and evaluation.coverage is not None:
        coverage = split_coverage(
            evaluation.chain,
            fit,
            sample.take(train),
            sample.take(test),
            evaluation.measurement,
            options,
            evaluation.coverage,
            seed=seed,
            warm=warm,
        )
    return predicted, coverage


def heldout_splits(
    evaluation: HeldoutProblem,
    executor: Executor,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[SplitError]:
    """DESIGN.md §4 on the gathered rows: per seed, the nominal robot (frame and tool fitted)
    and the calibration fitted on the training rows and scored on the test rows, the two fits
    of a split side by side on the executor."""
    return heldout_evaluation(evaluation, executor, progress)[0]


def heldout_evaluation(
    evaluation: HeldoutProblem,
    executor: Executor,
    progress: Callable[[str, int, int], None] | None = None,
) -> tuple[list[SplitError], dict[int, SplitCoverage]]:
    """:func:`heldout_splits` and, per seed, the calibrated split's coverage (when
    ``evaluation.coverage`` asks for it and the split's training rows gave the covariances)."""
    seeds = evaluation.settings.seeds
    predictions: dict[tuple[int, str], FloatArray] = {}
    coverage: dict[int, SplitCoverage] = {}
    # one split per worker per map: the executor's contiguous blocks then give each worker a
    # split's cheap and costly fit, and progress (where a job notices a cancel) comes often
    batch = max(1, executor.n_workers)
    for first in range(0, len(seeds), batch):
        chunk = seeds[first : first + batch]
        items = [(seed, method) for seed in chunk for method in (BEFORE, CALIBRATED)]
        for item, (predicted, scored) in zip(
            items, executor.map(_heldout_fit, evaluation, items), strict=True
        ):
            predictions[item] = predicted
            if scored is not None:
                coverage[item[0]] = scored
        if progress is not None:
            progress("heldout", first + len(chunk), len(seeds))
    splits = score_splits(
        evaluation.sample.measured_pose,
        predictions,
        [BEFORE, CALIBRATED],
        rotation=evaluation.measurement.measures_rotation,
        seeds=seeds,
        train_fraction=evaluation.settings.train_fraction,
    )
    return splits, coverage
