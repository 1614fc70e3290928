"""Calibrations whose rows are not a marker pose or position (issue 15): ball in socket,
several markers at once, chosen pose components, a frame on the base, a sensor on the chain.

:func:`measurement_for` reads the ``measurement`` option (and, for 'auto', the source) into a
:class:`~solver.measurement.models.MeasurementModel`, or None for the streamed pose/position
calibration of :mod:`service.app.calibrate`. :func:`calibrate_measurement` reads the recording into
memory, fits it (:func:`solver.measurement.fit_measurement`, Eq. 8–10), screens gross errors,
runs the held-out splits of DESIGN.md §4 and assembles the same result JSON, with the model's
own unknowns in ``measurement``, and the covariance calibration (Eq. 12–17) of every type with
its noise layout (:attr:`~solver.measurement.models.MeasurementModel.noise_rows`).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import time
from dataclasses import dataclass

import numpy as np

from schemas.calibration import (
    CalibrationOptions,
    CalibrationResult,
    DatasetInfo,
    ErrorStats,
    Evaluation,
    FitPhase,
    FitStatistics,
    HeldoutSplit,
    Identifiability,
    MeasuredUnknown,
    MeasurementResult,
    OutlierReport,
    PredictiveCovariance,
    RobotInfo,
    SolverReport,
    Verdict,
    VerdictReason,
)
from service.app.measurement_input import (
    MeasuredRecording,
)
from service.render.result_json import (
    ResidualSample,
    _error_stats,
    chain_fields,
    covariance_result,
    fixed_names,
    kincal_version,
    predictive_block,
    split_fits,
)
from solver.arrays import BoolArray
from solver.calibration import FitOptions, outlier_mask
from solver.covariance.estimate import CovarianceEstimate, estimate_from_samples
from solver.kinematics import parameter_names
from solver.measurement import (
    MeasurementFit,
    MeasurementModel,
    MeasurementRows,
    fit_measurement,
    heldout_errors,
    row_errors,
)
from solver.measurement.fit import HeldoutError, covariance_samples, row_weights
from solver.measurement.predictive import (
    INNER_FOLDS,
    MeasurementPredictive,
    measurement_predictive,
)
from solver.model import KinematicChain
from solver.predictive import mahalanobis_squared
from solver.stream.calibrate import BEFORE, CALIBRATED, MODEL_RULE_ROUNDS, CovarianceSettings
from solver.stream.coverage import NLL_TOLERANCE, one_step_trainers
from solver.stream.screening import (
    covariance_too_uncertain,
    family_wise_t2,
    family_wise_z,
    model_rule_refusal,
    robust_spread,
)
from solver.verdict import FitEvidence, check_fit, position_spread_m, reach_m, verdict_status


def screen(
    model: MeasurementModel,
    fit: MeasurementFit,
    options: CalibrationOptions,
) -> tuple[BoolArray, str]:
    """Rows kept by the outlier rule at the first fit and a note on the rule applied. 'sigma':
    the paper's §V-A rule; 'model': its robust first step (median and 1.4826·MAD per
    component, family-wise threshold at outlier_level; its Σ_E step follows the covariances,
    :func:`screen_by_covariance`)."""
    rule = options.screening
    n = fit.residuals.shape[0]
    if rule == "none":
        return np.ones(n, dtype=bool), "no outlier screening"
    if rule == "sigma":
        sigma = options.outlier_sigma or 2.0
        return outlier_mask(fit.residuals, sigma), f"§V-A rule at {sigma} σ"
    centre, scale = robust_spread(fit.residuals)
    z = family_wise_z(options.outlier_level, n, model.dim)
    kept = np.all(np.abs(fit.residuals - centre) <= z * np.where(scale > 0, scale, np.inf), axis=1)
    return kept, f"model rule, robust first step: |z| <= {z:.2f} per component"


def screen_by_covariance(
    chain: KinematicChain,
    rows: MeasurementRows,
    kept: BoolArray,
    fit: MeasurementFit,
    estimate: CovarianceEstimate,
    settings: CovarianceSettings,
    options: CalibrationOptions,
    fit_options: FitOptions,
) -> tuple[BoolArray, MeasurementFit, CovarianceEstimate, str]:
    """The model rule's Σ_E step, as for a streamed pose recording
    (:func:`solver.stream.calibrate.screen_by_model`): every row (those the first step removed
    too) judged by ``r_nᵀ Σ_E(q_n)⁻¹ r_n`` with Σ_E of Eq. 12 (the model's noise layout
    included) at the fit of the rows ``kept`` (N,), removed beyond Hotelling's T² at which one
    clean row of the recording would fall with probability ``outlier_level``
    (:func:`family_wise_t2`); refit and covariances again on the rows kept, until the removed
    rows no longer change (at most :data:`MODEL_RULE_ROUNDS` rounds). A round that would leave
    too few rows or remove more than half (:func:`model_rule_refusal`) removes nothing.
    Skipped, with the reason in the note, when Σ_E rests on too few equations per covariance
    entry (:func:`~solver.stream.screening.covariance_too_uncertain`). Returns the kept mask
    (N,), the fit and covariances on those rows and a note."""
    d = fit.model.dim
    too_uncertain = covariance_too_uncertain(fit.residuals.size, estimate.identifiability.rank)
    if too_uncertain is not None:
        return kept, fit, estimate, f"model rule, Σ_E step: skipped, {too_uncertain}"
    min_rows = len(fit.estimated) // d + 1
    threshold = np.inf
    for _ in range(MODEL_RULE_ROUNDS):
        samples = covariance_samples(chain, fit, rows, settings.spec.frames)
        sigma_e = estimate.ee_covariance(samples.frame_jacobians, include_noise=True)
        dof = fit.residuals.shape[0] - len(fit.estimated) / d
        threshold = family_wise_t2(options.outlier_level, rows.n, d, dof)
        beyond = mahalanobis_squared(samples.residuals, sigma_e) > threshold
        if np.array_equal(~beyond, kept):
            break
        refused = model_rule_refusal(rows.n, int(beyond.sum()), min_rows, converged=fit.converged)
        if refused is not None:
            return (
                kept,
                fit,
                estimate,
                (
                    f"model rule, Σ_E step: would remove {int(beyond.sum())} of {rows.n} rows "
                    f"({refused}); kept the rows before it"
                ),
            )
        kept = ~beyond
        used = rows.take(np.flatnonzero(kept))
        fit = fit_measurement(chain, fit.model, used, fit_options)
        estimate = estimate_covariances(chain, fit, used, settings)
    return (
        kept,
        fit,
        estimate,
        (
            f"model rule, Σ_E step: T² <= {threshold:.1f} per row against its own Σ_E(q) "
            f"(Eq. 12), level {options.outlier_level}"
        ),
    )


def estimate_covariances(
    chain: KinematicChain,
    fit: MeasurementFit,
    rows: MeasurementRows,
    settings: CovarianceSettings,
    start: CovarianceEstimate | None = None,
) -> CovarianceEstimate:
    """The covariance calibration (paper §IV-C) of the rows ``fit`` used, at the fit. With
    ``start`` (a predictor's covariances, for the predictive coverage): ML/REML started from
    its θ, stopped as the held-out predictors of a pose recording are
    (:data:`~solver.stream.coverage.NLL_TOLERANCE` of the whole log-likelihood), no standard
    errors."""
    spec = settings.spec
    return estimate_from_samples(
        covariance_samples(chain, fit, rows, spec.frames),
        spec.layout,
        known=spec.known,
        estimator=settings.estimator,
        solver=settings.solver,
        noise_name=spec.noise_name,
        standard_errors=start is None,
        likelihood_tolerance=1e-10 if start is None else NLL_TOLERANCE / max(rows.n, 1),
        start_theta=None if start is None else start.theta,
    )


@dataclass(frozen=True)
class MeasurementCalibration:
    """What :func:`calibrate_measurement` produced, before it becomes the result JSON."""

    recording: MeasuredRecording
    fit: MeasurementFit
    baseline: MeasurementFit
    kept: BoolArray
    splits: list[HeldoutError]
    notes: tuple[str, ...]
    elapsed_s: float
    covariance: CovarianceEstimate | None = None
    predictive: MeasurementPredictive | None = None


def calibrate_measurement(
    recording: MeasuredRecording,
    chain: KinematicChain,
    options: CalibrationOptions,
    fit_options: FitOptions,
    baseline_options: FitOptions,
    covariance: CovarianceSettings | None = None,
) -> MeasurementCalibration:
    """Fit, outlier rule, refit and "before" fit on the kept rows, covariances (Eq. 12–17 at
    the refit, with ``covariance``), held-out splits. The model rule takes its robust first
    step, then, with covariances, its Σ_E step (:func:`screen_by_covariance`: every row
    against its own predicted Σ_E, as for a streamed pose recording); with ``covariance``
    "none" the first step alone."""
    started = time.perf_counter()
    model, rows = recording.model, recording.rows
    notes = list(recording.notes)
    first = fit_measurement(chain, model, rows, fit_options)
    kept, rule_note = screen(model, first, options)
    notes.append(rule_note)
    used = rows.take(np.flatnonzero(kept))
    fit = fit_measurement(chain, model, used, fit_options) if not kept.all() else first
    estimate = None if covariance is None else estimate_covariances(chain, fit, used, covariance)
    if estimate is not None and covariance is not None and options.screening == "model":
        kept, fit, estimate, step_note = screen_by_covariance(
            chain, rows, kept, fit, estimate, covariance, options, fit_options
        )
        notes.append(step_note)
        used = rows.take(np.flatnonzero(kept))
    baseline = fit_measurement(chain, model, used, baseline_options)
    one_step = options.heldout_method == "one-step"
    predictive = None
    if estimate is not None and covariance is not None:
        settings, start = covariance, estimate
        frames = tuple(settings.spec.frames)

        def iterated(f: MeasurementFit, r: MeasurementRows) -> CovarianceEstimate:
            return estimate_covariances(chain, f, r, settings, start)

        def refit(r: MeasurementRows) -> MeasurementFit:
            return fit_measurement(chain, model, r, fit_options)

        fitter, estimator = (
            one_step_trainers(
                chain, used, fit, estimate, fit_options, frames, settings.spec.known, iterated
            )
            if one_step
            else (refit, iterated)
        )
        predictive = measurement_predictive(
            chain,
            used,
            fit,
            estimate,
            fitter,
            estimator,
            frames,
            row_weights(model, fit_options),
            options.seeds if options.heldout else (),
            options.train_fraction,
        )
    splits: list[HeldoutError] = []
    if options.heldout:
        splits = heldout_errors(
            chain,
            model,
            used,
            {BEFORE: baseline_options, CALIBRATED: fit_options},
            options.seeds,
            options.train_fraction,
            {BEFORE: baseline, CALIBRATED: fit} if one_step else None,
        )
    return MeasurementCalibration(
        recording,
        fit,
        baseline,
        kept,
        splits,
        tuple(notes),
        time.perf_counter() - started,
        estimate,
        predictive,
    )


def _stats(model: MeasurementModel, residuals: np.ndarray) -> ErrorStats:
    translation_mm, rotation_deg = row_errors(model, residuals)
    return _error_stats(translation_mm, rotation_deg if model.rotation_rows else None)


def _heldout(model: MeasurementModel, splits: list[HeldoutError], method: str) -> ErrorStats | None:
    mine = [s for s in splits if s.method == method]
    if not mine:
        return None
    translation = np.array([s.translation_mm for s in mine])
    rotation = np.array([s.rotation_deg for s in mine]) if model.rotation_rows else None
    stats = _error_stats(translation, rotation)
    return stats.model_copy(update={"n_samples": sum(s.n_test for s in mine)})


def measurement_result(
    calibrated: MeasurementCalibration,
    *,
    robot: RobotInfo,
    chain: KinematicChain,
    options: CalibrationOptions,
    free_columns: tuple[int, ...] | None = None,
    covariance_index: list[int] | None = None,
) -> CalibrationResult:
    """The result JSON of a measurement-model calibration (same schema as a pose one; the
    measurement's own unknowns in ``measurement``; ``covariance`` when estimated, of the chain
    joints ``covariance_index``); ``free_columns``: the chain columns the selection left free
    (None: all), the others listed as fixed."""
    fixed = fixed_names(chain, free_columns)
    recording, fit, baseline = calibrated.recording, calibrated.fit, calibrated.baseline
    model = recording.model
    lookup = dict(zip(fit.estimated, fit.standard_errors.tolist(), strict=True))
    unknowns = [
        MeasuredUnknown(name=n, value=float(v), stderr=lookup.get(n))
        for n, v in zip(model.extra_names(), fit.params.extra, strict=True)
    ]
    splits = calibrated.splits
    after_heldout = _heldout(model, splits, CALIBRATED)
    before_heldout = _heldout(model, splits, BEFORE)
    after_train = _stats(model, fit.residuals)
    tool_positions = _tool_positions(
        chain, fit, recording.rows.take(np.flatnonzero(calibrated.kept))
    )
    evidence = FitEvidence(
        converged=fit.converged,
        iterations=fit.iterations,
        max_iterations=options.max_iterations,
        n_equations=fit.residuals.size + fit.constraint_residuals.size,
        n_parameters=len(fit.estimated),
        train_rms_translation_m=1e-3 * after_train.translation_rms_mm,
        train_rms_rotation_rad=None
        if after_train.rotation_rms_deg is None
        else float(np.radians(after_train.rotation_rms_deg)),
        heldout_translation_m=None
        if after_heldout is None
        else 1e-3 * after_heldout.translation_mean_mm,
        heldout_before_translation_m=None
        if before_heldout is None
        else 1e-3 * before_heldout.translation_mean_mm,
        position_spread_m=position_spread_m(tool_positions),
        reach_m=reach_m(chain.nominal_links[:, :3, 3]),
    )
    reasons = check_fit(evidence)
    removed = np.flatnonzero(~calibrated.kept)
    return CalibrationResult(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        dataset=DatasetInfo(
            source=recording.source,
            n_samples=recording.rows.n,
            measures_rotation=bool(model.rotation_rows),
        ),
        robot=robot,
        options=options,
        **chain_fields(chain, fit, baseline),
        covariance=None
        if calibrated.covariance is None
        else covariance_result(calibrated.covariance, covariance_index or []),
        predictive=None
        if calibrated.predictive is None
        else _predictive(calibrated.predictive, model, options),
        identifiability=Identifiability(
            n_parameters=len(parameter_names(chain)) + len(model.extra_names()),
            rank=fit.rank,
            condition_number=fit.condition_number,
            removed=[name for name in fit.removed if name not in fixed],
            fixed=fixed,
            pruned=fit.pruned,
        ),
        fit=FitStatistics(
            before=FitPhase(train=_stats(model, baseline.residuals), heldout=before_heldout),
            after=FitPhase(train=after_train, heldout=after_heldout),
        ),
        evaluation=Evaluation(
            protocol=f"{len(options.seeds)} random train/test splits "
            f"({options.train_fraction:.0%} train), seeds {options.seeds}, after outlier "
            f"removal, on all {int(calibrated.kept.sum())} used rows; the model's own unknowns "
            "(sockets, marker offsets) fitted on the training rows too; "
            + split_fits(options.heldout_method),
            splits=[
                HeldoutSplit(
                    method=s.method,
                    seed=s.seed,
                    n_train=s.n_train,
                    n_test=s.n_test,
                    translation_mm=s.translation_mm,
                    rotation_deg=s.rotation_deg if model.rotation_rows else None,
                )
                for s in splits
            ],
        )
        if splits
        else None,
        outliers=OutlierReport(
            rule=options.screening,
            level=options.outlier_level if options.screening == "model" else None,
            sigma=options.outlier_sigma if options.screening == "sigma" else None,
            n_input=recording.rows.n,
            n_used=int(calibrated.kept.sum()),
            removed_rows=[int(i) + 1 for i in removed],
        ),
        solver=SolverReport(
            name="levenberg_marquardt",
            status="optimal" if fit.converged else "iteration_limit",
            iterations=fit.iterations,
            time_s=fit.elapsed_s,
            objective=fit.cost_history[-1],
        ),
        verdict=Verdict(
            status=verdict_status(reasons),
            reasons=[VerdictReason(**dataclasses.asdict(r)) for r in reasons],
        ),
        measurement=MeasurementResult(
            type=options.measurement if options.measurement != "auto" else model.name,
            frame=model.frame,
            components=list(model.components),
            unknowns=unknowns,
            labels=list(recording.labels),
            constraint_residuals_m=[
                float(v) / getattr(model, "distance_weight", 1.0) for v in fit.constraint_residuals
            ],
            notes=list(calibrated.notes),
        ),
    )


def _predictive(
    predictive: MeasurementPredictive, model: MeasurementModel, options: CalibrationOptions
) -> PredictiveCovariance:
    """The ``predictive`` block of a measurement calibration: Cov(θ̂) of the chain parameters
    and the model's own unknowns, the model-error part along the residual's own components
    (``model.frame``), the held-out coverage in the residual space (d = ``model.dim``)."""
    space = (
        "residual rotated into the tip frame"
        if model.name in ("point", "markers")
        else f"residual in {model.frame}"
    )
    return predictive_block(
        estimated=predictive.estimated,
        parameter_covariance=predictive.parameter_covariance,
        parameter_method="sandwich G⁺ (Σ A_wᵀ W Σ_E W A_w) G⁺ of the weighted least-squares "
        "fit over the chain parameters and the measurement's own unknowns (listed, not "
        "profiled), G with the known-distance equations (exact); Σ_E (with the noise of the "
        "type's layout) from the calibrated covariances",
        model_error=predictive.model_error,
        axes=list(model.components),
        frame=model.frame,
        model_error_method=(
            "maximum likelihood on the held-out residuals of every split (the measurement's "
            "residual space), each with Σ_E + noise + J_θ Cov(θ̂) J_θᵀ of its split's "
            "training rows"
            if predictive.n_splits
            else f"maximum likelihood on {INNER_FOLDS}-fold cross-validated residuals of the "
            "used rows (no held-out splits)"
        ),
        found=predictive.coverage,
        n_splits=predictive.n_splits,
        coverage_protocol=f"the held-out splits of evaluation ({predictive.n_splits} of "
        f"{len(options.seeds)} gave covariances), d = {model.dim} ({space}); per split, "
        f"geometry, compliance, the measurement's own unknowns, covariances "
        f"({options.covariance_estimator}), Cov(θ̂) and the model-error part "
        f"({INNER_FOLDS}-fold cross-validation inside the training rows, in "
        f"{predictive.nested} splits) from its training rows only",
    )


def _tool_positions(
    chain: KinematicChain, fit: MeasurementFit, rows: MeasurementRows
) -> np.ndarray:
    from solver.kinematics import forward_kinematics

    return forward_kinematics(chain, fit.params, rows.joint_positions, rows.loads_nm)[:, :3, 3]


def measurement_residuals(calibrated: MeasurementCalibration) -> ResidualSample:
    """Residuals of the used rows before and after, in the model's frame."""
    return ResidualSample(
        calibrated.baseline.residuals,
        calibrated.fit.residuals,
        f"the {int(calibrated.kept.sum())} rows used ({calibrated.recording.model.frame})",
    )


__all__ = [
    "MeasurementCalibration",
    "calibrate_measurement",
    "measurement_residuals",
    "measurement_result",
]
