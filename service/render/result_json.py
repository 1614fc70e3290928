"""The result JSON (``kincal.calibration/1``, DESIGN.md §3): assembled from a calibrated
recording, and read back as a chain for prediction, ranking and reports."""

from __future__ import annotations

import dataclasses
import datetime as dt
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from schemas.calibration import (
    BaselineFit,
    CalibrationOptions,
    CalibrationResult,
    ComplianceCalibration,
    CovarianceFrame,
    CovarianceIdentifiability,
    CovarianceResult,
    CoverageLevel,
    CoverageReport,
    DatasetInfo,
    ErrorStats,
    Evaluation,
    FitPhase,
    FitStatistics,
    HeldoutSplit,
    Identifiability,
    LinkCalibration,
    ModelErrorPart,
    OutlierReport,
    ParameterCovariance,
    PredictiveCovariance,
    RobotInfo,
    SolverReport,
    Transform,
    Verdict,
    VerdictReason,
)
from schemas.dataset import PoseDataset
from schemas.robots import RobotDescription
from service import kincal_version
from service.render import corrections
from service.render.chain import chain_for as chain_for  # its home is light (pre-flight)
from solver import lie
from solver.arrays import FloatArray
from solver.covariance.estimate import CovarianceEstimate, FrameCovariance
from solver.evaluation import SplitError
from solver.kinematics import ChainParameters, forward_kinematics, parameter_names
from solver.measurement.models import FullPose
from solver.measurement.pose import pose_measurement
from solver.model import KinematicChain, build_chain, gravity_loads
from solver.predictive import COVERAGE_LEVELS, CURVE_LEVELS, INNER_FOLDS, Coverage, ModelErrorFit
from solver.selection import fixed_names
from solver.stream.calibrate import BEFORE, CALIBRATED, RecordingCalibration
from solver.stream.coverage import INNER_CV_ROWS, PredictiveCalibration
from solver.stream.screening import MIN_EQUATIONS_PER_COVARIANCE_ENTRY
from solver.stream.sums import ErrorSums
from solver.verdict import FitEvidence, check_fit, position_spread_m, reach_m, verdict_status


@dataclass(frozen=True)
class PreparedData:
    """A dataset turned into solver arrays for one chain."""

    chain: KinematicChain
    joint_positions: FloatArray
    measured_pose: FloatArray
    loads_nm: FloatArray
    measurement: FullPose


def prepare(
    chain: KinematicChain, dataset: PoseDataset, options: CalibrationOptions
) -> PreparedData:
    payload = dataset.payload_kg if dataset.payload_kg is not None else options.payload_kg
    loads = gravity_loads(
        chain,
        dataset.joint_positions,
        gravity_base=np.asarray(options.gravity_base_m_s2),
        payload_kg=payload,
    )
    return PreparedData(
        chain=chain,
        joint_positions=dataset.joint_positions,
        measured_pose=lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw),
        loads_nm=loads,
        measurement=dataset.measurement_model,
    )


def result_measurement(result: CalibrationResult) -> FullPose:
    """What the rows of a pose or position calibration measured, as the model the pose paths
    take (:class:`~solver.measurement.FullPose` or :class:`~solver.measurement.Position`),
    from the document's ``dataset`` (:attr:`schemas.calibration.DatasetInfo.measures_rotation`)."""
    return pose_measurement(rotation=result.dataset.measures_rotation)


def result_chain(
    result: CalibrationResult, *, baseline: bool = False
) -> tuple[KinematicChain, ChainParameters]:
    """Rebuild the calibrated chain from a result JSON (it embeds the URDF).

    ``baseline=True`` gives the "before" model: nominal robot, fitted measurement frame and tool.
    """
    chain = build_chain(
        result.robot.urdf,
        result.robot.base_frame,
        result.robot.tip_frame,
        compliant_joints=result.options.compliant_joints,
        virtual_axes_at=result.options.virtual_axes_at,
        payload_com_m=result.options.payload_com_m,
    )
    if baseline:
        links = chain.nominal_links.copy()
        links[0] = np.array(result.baseline.measurement_frame.matrix) @ links[0]
        links[-1] = links[-1] @ np.array(result.baseline.tool.matrix)
        return chain, ChainParameters(links, np.zeros(len(chain.compliance_axes)))
    links = np.array([link.placement for link in result.links], dtype=float)
    compliance = np.array([c.value_rad_per_nm for c in result.compliance], dtype=float)
    return chain, ChainParameters(links, compliance)


def residuals(
    result: CalibrationResult, dataset: PoseDataset, *, baseline: bool = False
) -> FloatArray:
    """End-effector-frame residuals (N, 6 or 3) of a dataset under the calibrated (or "before")
    model, in m and rad."""
    chain, params = result_chain(result, baseline=baseline)
    data = prepare(chain, dataset, result.options)
    predicted = forward_kinematics(chain, params, data.joint_positions, data.loads_nm)
    return data.measurement.residuals(predicted, data.measured_pose)


def predict_poses(
    result: CalibrationResult, joint_positions: FloatArray, payload_kg: FloatArray | None = None
) -> FloatArray:
    """Calibrated mean pose (N, 4, 4) of the marker in the measurement frame for joint
    readings (N, k) rad (corrected by the result's carried joint corrections first)."""
    chain, params = result_chain(result)
    q = corrections.true_configurations(result, chain, joint_positions, payload_kg)
    payload = payload_kg if payload_kg is not None else result.options.payload_kg
    loads = gravity_loads(
        chain,
        q,
        gravity_base=np.asarray(result.options.gravity_base_m_s2),
        payload_kg=payload,
    )
    return forward_kinematics(chain, params, q, loads)


def _transform(
    matrix: FloatArray,
    stderr_translation: tuple[float | None, ...] | None = None,
    stderr_rotation: tuple[float | None, ...] | None = None,
) -> Transform:
    def complete(values: tuple[float | None, ...] | None) -> tuple[float, float, float] | None:
        if values is None or any(v is None for v in values):
            return None
        return (float(values[0]), float(values[1]), float(values[2]))  # type: ignore[arg-type]

    return Transform(
        matrix=matrix.tolist(),
        xyz_m=tuple(matrix[:3, 3].tolist()),
        quaternion_xyzw=tuple(lie.matrix_to_quaternion_xyzw(matrix[:3, :3]).tolist()),
        stderr_translation_m=complete(stderr_translation),
        stderr_rotation_rad=complete(stderr_rotation),
    )


class FittedChain(Protocol):
    """What the result JSON reads of a fit: a streamed pose fit or a measurement model's."""

    @property
    def params(self) -> ChainParameters: ...
    @property
    def estimated(self) -> list[str]: ...
    @property
    def standard_errors(self) -> FloatArray: ...
    @property
    def pruned(self) -> list[str]: ...


def _link_stderr(
    fit: FittedChain, chain: KinematicChain, link: int
) -> tuple[tuple[float | None, ...], tuple[float | None, ...]]:
    """Standard errors of link ``link``'s local twist components (None where not estimated)."""
    lookup = dict(zip(fit.estimated, fit.standard_errors.tolist(), strict=True))
    name = chain.link_names[link]
    values = [lookup.get(f"{name}.{c}") for c in ("tx", "ty", "tz", "rx", "ry", "rz")]
    return tuple(values[:3]), tuple(values[3:])


def _links(chain: KinematicChain, fit: FittedChain) -> list[LinkCalibration]:
    out = []
    for i, name in enumerate(chain.link_names):
        correction = lie.se3_log(lie.inverse(chain.nominal_links[i]) @ fit.params.links[i])
        inner = 0 < i < chain.n_links - 1
        stderr_t, stderr_r = _link_stderr(fit, chain, i)
        out.append(
            LinkCalibration(
                link=name,
                placement=fit.params.links[i].tolist(),
                correction_translation_m=tuple(correction[:3].tolist()) if inner else None,
                correction_rotation_rad=tuple(correction[3:].tolist()) if inner else None,
                stderr_translation_m=stderr_t,  # type: ignore[arg-type]
                stderr_rotation_rad=stderr_r,  # type: ignore[arg-type]
            )
        )
    return out


def _compliance(chain: KinematicChain, fit: FittedChain) -> list[ComplianceCalibration]:
    lookup = dict(zip(fit.estimated, fit.standard_errors.tolist(), strict=True))
    out = []
    for a, axis in enumerate(chain.compliance_axes):
        stderr = lookup.get(f"compliance.{axis.name}")
        out.append(
            ComplianceCalibration(
                axis=axis.name,
                joint=chain.joint_names[axis.joint_index],
                kind="joint" if axis.is_joint_axis else "virtual",
                axis_vector=tuple(axis.axis.tolist()),
                value_rad_per_nm=float(fit.params.compliance_rad_per_nm[a]),
                stderr_rad_per_nm=stderr,
                estimated=stderr is not None,
                significant=stderr is not None
                and abs(float(fit.params.compliance_rad_per_nm[a])) > 2.0 * stderr,
                pruned=f"compliance.{axis.name}" in fit.pruned,
            )
        )
    return out


def covariance_result(estimate: CovarianceEstimate, joint_index: list[int]) -> CovarianceResult:
    solution, moment = estimate.solution, estimate.moment_solution
    extra_time = moment.wall_time_s if solution is not moment else 0.0
    report = estimate.identifiability
    fixed = [
        f"{label}: no effect on the data, fixed at 0"
        for label, silent in zip(report.labels, report.silent, strict=True)
        if silent
    ]
    if report.statements:
        fixed.append(f"rule for the unidentifiable combinations: {report.rule}")
    assert estimate.noise is not None  # estimated, or the known one (fixed)
    return CovarianceResult(
        structure=estimate.structure,
        estimator=estimate.estimator,
        n_samples=estimate.n_samples,
        confidence=estimate.uncertainty.confidence if estimate.uncertainty else 0.95,
        stderr_method=estimate.uncertainty.method if estimate.uncertainty else None,
        solver=SolverReport(
            name=f"{estimate.solver}+{estimate.estimator}",
            status=solution.status,
            iterations=moment.iterations + (solution.iterations if solution is not moment else 0),
            time_s=solution.wall_time_s + extra_time,
            objective=solution.objective,
            message=solution.message or None,
        ),
        noise=_covariance_frame(estimate.noise, None),
        frames=[
            _covariance_frame(frame, j)
            for frame, j in zip(estimate.frames, joint_index, strict=True)
        ],
        identifiability=CovarianceIdentifiability(
            rank=report.rank,
            n_parameters=report.n_params,
            condition_number=report.condition_number,
            null_directions=list(report.statements)
            + [f"weakly identified: {s}" for s in report.weak_statements],
            fixed=fixed,
            warnings=list(estimate.warnings),
        ),
    )


def _covariance_frame(frame: FrameCovariance, joint_index: int | None) -> CovarianceFrame:
    def optional(values: FloatArray) -> tuple[float | None, ...]:
        return tuple(float(v) if np.isfinite(v) else None for v in values)

    return CovarianceFrame(
        name=frame.name,
        joint_index=joint_index,
        matrix=frame.covariance.tolist(),
        std=tuple(  # type: ignore[arg-type]
            None if reason is not None else float(v)
            for v, reason in zip(frame.std, frame.unseen, strict=True)
        ),
        std_stderr=optional(frame.std_se),
        std_ci_low=optional(frame.std_ci_low),
        std_ci_high=optional(frame.std_ci_high),
        identifiable=tuple(bool(v) for v in frame.identifiable),
        not_identifiable=frame.unseen if any(r is not None for r in frame.unseen) else None,
    )


def _error_stats(translation_mm: FloatArray, rotation_deg: FloatArray | None) -> ErrorStats:
    return ErrorStats(
        n_samples=int(translation_mm.size),
        translation_mean_mm=float(translation_mm.mean()),
        translation_rms_mm=float(np.sqrt(np.mean(translation_mm**2))),
        rotation_mean_deg=None if rotation_deg is None else float(rotation_deg.mean()),
        rotation_rms_deg=None if rotation_deg is None else float(np.sqrt(np.mean(rotation_deg**2))),
    )


def split_fits(method: str) -> str:
    """How the held-out splits were calibrated on their training rows, in words."""
    if method == "exact":
        return "each split's fits iterated to convergence from the nominal robot (exact)"
    return (
        "each split's geometry one Gauss-Newton step from the calibration of all used rows, "
        "its covariances the one-step estimator from its own moment solution refined by two "
        "scoring steps (one-step; iterated to convergence instead where those steps do not "
        "converge or the rows give fewer than "
        f"{MIN_EQUATIONS_PER_COVARIANCE_ENTRY:g} equations per covariance entry)"
    )


def _heldout_stats(
    splits: list[SplitError], method: str, measurement: FullPose
) -> ErrorStats | None:
    """Mean over splits of the per-split mean errors (RMS over the split means)."""
    mine = [s for s in splits if s.method == method]
    if not mine:
        return None
    translation = np.array([s.translation_mm for s in mine])
    rotation = (
        np.array([s.rotation_deg for s in mine], dtype=float)
        if measurement.measures_rotation
        else None
    )
    stats = _error_stats(translation, rotation)
    return stats.model_copy(update={"n_samples": sum(s.n_test for s in mine)})


def _evaluation(calibrated: RecordingCalibration, options: CalibrationOptions) -> Evaluation:
    splits = calibrated.splits
    used = calibrated.fits.fit.sums.errors.n
    rows = calibrated.sample.n
    on = (
        f"all {used} used rows"
        if rows == used
        else f"{rows} of {used} used rows (rows whose number is a multiple of "
        f"{calibrated.sample_stride})"
    )
    return Evaluation(
        protocol=f"{len(options.seeds)} random train/test splits "
        f"({options.train_fraction:.0%} train), seeds {options.seeds}, after outlier removal, "
        f"on {on}; {split_fits(options.heldout_method)}",
        splits=[
            HeldoutSplit(
                method=s.method,
                seed=s.seed,
                n_train=s.n_train,
                n_test=s.n_test,
                translation_mm=s.translation_mm,
                rotation_deg=s.rotation_deg,
            )
            for s in splits
        ],
    )


def _sums_stats(sums: ErrorSums, measurement: FullPose) -> ErrorStats:
    mean_mm, rms_mm, mean_deg, rms_deg = sums.summary(measurement)
    return ErrorStats(
        n_samples=sums.n,
        translation_mean_mm=mean_mm,
        translation_rms_mm=rms_mm,
        rotation_mean_deg=mean_deg,
        rotation_rms_deg=rms_deg,
    )


def _verdict(
    chain: KinematicChain,
    options: CalibrationOptions,
    calibrated: RecordingCalibration,
    measurement: FullPose,
) -> Verdict:
    """:func:`solver.verdict.check_fit` on the calibration's own numbers."""
    fit = calibrated.fits.fit
    splits = calibrated.splits
    after = _heldout_stats(splits, CALIBRATED, measurement)
    before = _heldout_stats(splits, BEFORE, measurement)
    _, rms_mm, _, rms_deg = fit.sums.errors.summary(measurement)
    evidence = FitEvidence(
        converged=fit.converged,
        iterations=fit.iterations,
        max_iterations=options.max_iterations,
        n_equations=fit.sums.errors.n * measurement.dim,
        n_parameters=len(fit.estimated),
        train_rms_translation_m=1e-3 * rms_mm,
        train_rms_rotation_rad=None if rms_deg is None else float(np.radians(rms_deg)),
        heldout_translation_m=None if after is None else 1e-3 * after.translation_mean_mm,
        heldout_before_translation_m=None if before is None else 1e-3 * before.translation_mean_mm,
        position_spread_m=position_spread_m(calibrated.sample.measured_pose[:, :3, 3]),
        reach_m=reach_m(chain.nominal_links[:, :3, 3]),
        screening_refused=calibrated.fits.screening_refused,
        screening_refused_rows=calibrated.fits.screening_refused_rows,
        n_rows=calibrated.fits.n_rows,
    )
    reasons = check_fit(evidence)
    return Verdict(
        status=verdict_status(reasons),
        reasons=[VerdictReason(**dataclasses.asdict(r)) for r in reasons],
    )


def chain_fields(chain: KinematicChain, fit: FittedChain, baseline: FittedChain) -> dict[str, Any]:
    """The result's fields of the calibrated chain: ``measurement_frame``, ``tool``,
    ``baseline`` (frame and tool of the "before" fit), ``links`` and ``compliance``."""
    return {
        "measurement_frame": _transform(
            fit.params.links[0] @ lie.inverse(chain.nominal_links[0]), *_link_stderr(fit, chain, 0)
        ),
        "tool": _transform(
            lie.inverse(chain.nominal_links[-1]) @ fit.params.links[-1],
            *_link_stderr(fit, chain, chain.n_links - 1),
        ),
        "baseline": BaselineFit(
            measurement_frame=_transform(
                baseline.params.links[0] @ lie.inverse(chain.nominal_links[0])
            ),
            tool=_transform(lie.inverse(chain.nominal_links[-1]) @ baseline.params.links[-1]),
        ),
        "links": _links(chain, fit),
        "compliance": _compliance(chain, fit),
    }


def assemble_result(
    *,
    source: str,
    robot: RobotDescription,
    chain: KinematicChain,
    options: CalibrationOptions,
    calibrated: RecordingCalibration,
    frame_index: list[int],
    measurement: FullPose,
    free_columns: tuple[int, ...] | None = None,
) -> CalibrationResult:
    """The result JSON of a recording calibrated by
    :func:`solver.stream.calibrate.calibrate_recording`; ``frame_index``: the chain joint of
    each covariance frame; ``measurement``: what its rows measured (written into the
    document's public ``dataset`` field); ``free_columns``: the columns the fit could move
    (None: all)."""
    fixed = fixed_names(chain, free_columns)
    fits = calibrated.fits
    fit, baseline = fits.fit, fits.baseline
    splits = calibrated.splits
    return CalibrationResult(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        dataset=DatasetInfo(
            source=source,
            n_samples=fits.n_rows,
            measures_rotation=measurement.measures_rotation,
        ),
        robot=RobotInfo(
            name=robot.name,
            base_frame=robot.base_frame,
            tip_frame=robot.tip_frame,
            joint_names=list(chain.joint_names),
            urdf_sha256=chain.urdf_sha256,
            urdf=robot.urdf_xml,
        ),
        options=options,
        **chain_fields(chain, fit, baseline),
        identifiability=Identifiability(
            n_parameters=len(parameter_names(chain)),
            rank=fit.rank,
            condition_number=fit.condition_number,
            removed=[name for name in fit.removed if name not in fixed],
            fixed=fixed,
            pruned=fit.pruned,
        ),
        fit=FitStatistics(
            before=FitPhase(
                train=_sums_stats(baseline.sums.errors, measurement),
                heldout=_heldout_stats(splits, BEFORE, measurement),
            ),
            after=FitPhase(
                train=_sums_stats(fit.sums.errors, measurement),
                heldout=_heldout_stats(splits, CALIBRATED, measurement),
            ),
        ),
        covariance=None
        if calibrated.covariance is None
        else covariance_result(calibrated.covariance, frame_index),
        predictive=None
        if calibrated.predictive is None
        else _predictive_result(calibrated.predictive, options),
        evaluation=_evaluation(calibrated, options) if splits else None,
        verdict=_verdict(chain, options, calibrated, measurement),
        outliers=OutlierReport(
            rule=options.screening,
            level=options.outlier_level if options.screening == "model" else None,
            sigma=options.outlier_sigma if options.screening == "sigma" else None,
            n_input=fits.n_rows,
            n_used=fit.sums.errors.n,
            removed_rows=[int(i) + 1 for i in fits.removed_rows],
            note=None
            if fits.screening_skipped is None
            else f"model rule, Σ_E step: skipped, {fits.screening_skipped}",
        ),
        solver=SolverReport(
            name="levenberg_marquardt",
            status="optimal" if fit.converged else "iteration_limit",
            iterations=fit.iterations,
            time_s=fit.elapsed_s,
            objective=fit.cost_history[-1],
        ),
    )


MODEL_ERROR_AXES = ("x", "y", "z", "rx", "ry", "rz")


def _predictive_result(
    predictive: PredictiveCalibration, options: CalibrationOptions
) -> PredictiveCovariance:
    """The ``predictive`` block: Cov(θ̂), the model-error part and the held-out coverage."""
    return predictive_block(
        estimated=predictive.estimated,
        parameter_covariance=predictive.parameter_covariance,
        parameter_method="sandwich G⁻¹ (Σ A_wᵀ W Σ_E W A_w) G⁻¹ of the weighted least-squares "
        "fit, Σ_E (with Σ_n) from the calibrated covariances",
        model_error=predictive.model_error,
        axes=list(MODEL_ERROR_AXES[: predictive.model_error.variance.size]),
        model_error_method=(
            "maximum likelihood on the held-out residuals of every split, each with "
            "Σ_E + Σ_n + J_θ Cov(θ̂) J_θᵀ of its split's training rows"
            if predictive.splits
            else "maximum likelihood on the leave-one-out residuals of the deterministic fit "
            "(no held-out splits; covariances not re-estimated per left-out sample, so what a "
            "calibration of this size gets wrong about Σ_E is not in it)"
        ),
        found=predictive.coverage,
        n_splits=len(predictive.splits),
        coverage_protocol=f"the held-out splits of evaluation ({len(predictive.splits)} of "
        f"{len(options.seeds)} gave covariances); per split, geometry, compliance, "
        f"covariances ({options.covariance_estimator}), Cov(θ̂) and the model-error part "
        f"({_model_error_protocol(predictive)}) from its training rows only",
    )


def predictive_block(
    *,
    estimated: list[str],
    parameter_covariance: FloatArray,
    parameter_method: str,
    model_error: ModelErrorFit,
    axes: list[str],
    model_error_method: str,
    found: Coverage | None,
    n_splits: int,
    coverage_protocol: str,
    frame: str | None = None,
) -> PredictiveCovariance:
    """The ``predictive`` block of any calibration (pose or other measurement type): Cov(θ̂)
    of ``estimated``, the model-error variances along ``axes`` (of ``frame``, the residual's
    frame; None: the measurement frame of a pose recording) and the held-out coverage."""
    variance = model_error.variance
    error = ModelErrorPart(
        axes=axes,
        variance=variance.tolist(),
        std=np.sqrt(variance).tolist(),
        n_residuals=model_error.n_residuals,
        method=model_error_method,
        frame=frame,
    )
    report = None
    if found is not None:
        report = CoverageReport(
            dimension=found.dimension,
            n_heldout=found.n,
            n_splits=n_splits,
            levels=[CoverageLevel(level=a, observed=found.at(a)) for a in COVERAGE_LEVELS],
            curve=[CoverageLevel(level=a, observed=found.at(a)) for a in CURVE_LEVELS],
            mean_mahalanobis_sq=found.mean_d2,
            chi2_mean=float(found.dimension),
            median_mahalanobis_sq=found.median_d2,
            chi2_median=found.chi2_median,
            protocol=coverage_protocol,
        )
    return PredictiveCovariance(
        parameter_covariance=ParameterCovariance(
            parameters=list(estimated),
            matrix=parameter_covariance.tolist(),
            method=parameter_method,
        ),
        model_error=error,
        coverage=report,
    )


def _model_error_protocol(predictive: PredictiveCalibration) -> str:
    """How the held-out splits got their model-error parts, in words."""
    nested = sum(split.nested for split in predictive.splits.values())
    inner = f"{INNER_FOLDS}-fold cross-validation inside the training rows"
    loo = (
        "leave-one-out residuals of the training rows' fit (more than "
        f"{INNER_CV_ROWS} training rows, or no inner fold could be calibrated)"
    )
    if nested == len(predictive.splits):
        return inner
    if nested == 0:
        return loo
    return f"{inner} in {nested} splits, {loo} in the others"


@dataclass(frozen=True)
class ResidualSample:
    """End-effector-frame residuals (n, d), m and rad, of used rows under the "before" model
    (nominal robot, frame and tool fitted) and the calibrated one; ``description`` says which
    rows they are."""

    before: FloatArray
    after: FloatArray
    description: str


def sample_residuals(
    chain: KinematicChain, calibrated: RecordingCalibration, measurement: FullPose
) -> ResidualSample:
    """The residuals of the rows the calibration kept in memory (every used row, or an
    evenly spaced subset of a large recording)."""
    sample = calibrated.sample

    def of(params: ChainParameters) -> FloatArray:
        predicted = forward_kinematics(chain, params, sample.joint_positions, sample.loads_nm)
        return measurement.residuals(predicted, sample.measured_pose)

    used = calibrated.fits.fit.sums.errors.n
    description = f"the {sample.n} samples used"
    if sample.n != used:
        description = (
            f"{sample.n} of the {used} samples used (rows whose number is a multiple of "
            f"{calibrated.sample_stride})"
        )
    return ResidualSample(
        of(calibrated.fits.baseline.params), of(calibrated.fits.fit.params), description
    )


def dataset_residuals(result: CalibrationResult, dataset: PoseDataset) -> ResidualSample:
    """The residuals of the samples of ``dataset`` (the recording ``result`` was calibrated
    on) that the calibration used."""
    kept = dataset.subset(result.outliers.kept_indices())
    return ResidualSample(
        residuals(result, kept, baseline=True),
        residuals(result, kept),
        f"the {kept.n_samples} samples used",
    )
