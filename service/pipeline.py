"""The calibration pipeline: validated dataset -> solver -> result schema.

The CLI and the HTTP service both call these functions; nothing is computed anywhere else.
"""

from __future__ import annotations

import datetime as dt
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.calibration import (
    BaselineFit,
    CalibrationOptions,
    CalibrationResult,
    ComplianceCalibration,
    CovarianceFrame,
    CovarianceIdentifiability,
    CovarianceResult,
    DatasetInfo,
    ErrorStats,
    Evaluation,
    FitPhase,
    FitStatistics,
    HeldoutSplit,
    Identifiability,
    LinkCalibration,
    OutlierReport,
    RobotInfo,
    SolverReport,
    Transform,
)
from schemas.dataset import ChunkRef, DatasetChunks, PoseDataset, plan_dataset_chunks
from service import corrections
from service.robots import RobotDescription
from solver import lie
from solver.calibration import (
    DeterministicFit,
    FitOptions,
    fit_deterministic,
    outlier_mask,
    pose_errors,
)
from solver.covariance.estimate import CovarianceEstimate, FrameCovariance, estimate_covariances
from solver.covariance.layout import ROTATION_AXIS_NAMES
from solver.errors import KincalError
from solver.evaluation import SplitError, cross_validate
from solver.executors import Executor, InProcessExecutor, preload_in_workers
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    parameter_names,
    pose_residuals,
)
from solver.model import KinematicChain, build_chain, gravity_loads
from solver.stream.calibrate import StreamedCalibration, StreamSettings, calibrate_streamed_fits
from solver.stream.chunks import ChunkArrays, StreamProblem, release
from solver.stream.covariance import STREAMED_ESTIMATOR_NOTE, estimate_covariances_streamed
from solver.stream.fit import PassCount, StreamedFit
from solver.stream.sums import CovarianceSpec, ErrorSums, covariance_spec

FloatArray = NDArray[np.float64]

# Streamed passes send DatasetChunkLoader to local worker processes: import this module once,
# in their fork server, rather than in every worker on its first chunk.
preload_in_workers(__name__)

BEFORE = "before"
CALIBRATED = "calibrated"

FitLike = DeterministicFit | StreamedFit
"""A deterministic fit, in memory or streamed: what the result JSON is assembled from."""

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``, called after each solver run of a stage ("fit", "baseline",
"heldout"); the HTTP job runner turns it into job progress."""


def _no_progress(stage: str, done: int, total: int) -> None:
    return None


@dataclass(frozen=True)
class PreparedData:
    """A dataset turned into solver arrays for one chain."""

    chain: KinematicChain
    joint_positions: FloatArray
    measured_pose: FloatArray
    loads_nm: FloatArray
    position_only: bool


@functools.cache  # reading package metadata costs milliseconds; rankings stamp every answer
def kincal_version() -> str:
    try:
        return metadata.version("kincal")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def chain_for(robot: RobotDescription, options: CalibrationOptions) -> KinematicChain:
    return build_chain(
        robot.urdf_xml,
        robot.base_frame,
        robot.tip_frame,
        compliant_joints=options.compliant_joints,
        virtual_axes_at=options.virtual_axes_at,
        payload_com_m=options.payload_com_m,
    )


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
        position_only=dataset.is_position_only,
    )


def fit_options(
    options: CalibrationOptions, *, baseline: bool = False, n_links: int = 0
) -> FitOptions:
    """Solver settings; ``baseline`` fits only the measurement frame and tool (nominal robot)."""
    return FitOptions(
        max_iterations=options.max_iterations,
        tolerance=options.tolerance,
        rotation_weight_m_per_rad=options.rotation_weight_m_per_rad,
        rank_tolerance=options.rank_tolerance,
        free_links=(0, n_links - 1) if baseline else None,
        fit_compliance=not baseline,
    )


def _fit(data: PreparedData, rows: NDArray[np.intp], options: FitOptions) -> DeterministicFit:
    return fit_deterministic(
        data.chain,
        data.joint_positions[rows],
        data.measured_pose[rows],
        data.loads_nm[rows],
        position_only=data.position_only,
        options=options,
    )


def calibrate(
    dataset: PoseDataset,
    robot: RobotDescription,
    options: CalibrationOptions,
    progress: Progress = _no_progress,
) -> CalibrationResult:
    """Deterministic calibration (Eq. 8–10) with outlier removal (§V-A) and held-out scores."""
    chain = chain_for(robot, options)
    data = prepare(chain, dataset, options)
    everything = np.arange(dataset.n_samples)
    full = fit_options(options)
    first = _fit(data, everything, full)
    progress("fit", 1, 1)
    used = everything
    if options.outlier_sigma is not None:
        used = everything[outlier_mask(first.residuals, options.outlier_sigma)]
    fit = first if used.size == everything.size else _fit(data, used, full)
    baseline = _fit(data, used, fit_options(options, baseline=True, n_links=chain.n_links))
    progress("baseline", 1, 1)
    covariance = covariance_stage(data, used, fit, options)
    progress("covariance", 1, 1)
    splits = heldout_splits(data, used, options, progress) if options.heldout else []
    return _assemble_result(
        dataset=DatasetInfo(
            source=dataset.source, n_samples=dataset.n_samples, position_only=data.position_only
        ),
        robot=robot,
        chain=chain,
        options=options,
        fit=fit,
        baseline_params=baseline.params,
        train_before=_stats(data, used, baseline.params),
        train_after=_stats(data, used, fit.params),
        splits=splits,
        covariance=covariance,
        outliers=OutlierReport(
            sigma=options.outlier_sigma,
            n_input=dataset.n_samples,
            n_used=int(used.size),
            removed_rows=[int(i) + 1 for i in np.setdiff1d(everything, used)],
        ),
    )


def _assemble_result(
    *,
    dataset: DatasetInfo,
    robot: RobotDescription,
    chain: KinematicChain,
    options: CalibrationOptions,
    fit: FitLike,
    baseline_params: ChainParameters,
    train_before: ErrorStats,
    train_after: ErrorStats,
    splits: list[SplitError],
    covariance: CovarianceResult | None,
    outliers: OutlierReport,
) -> CalibrationResult:
    """The result JSON of a calibration, in memory or streamed."""
    return CalibrationResult(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        dataset=dataset,
        robot=RobotInfo(
            name=robot.name,
            base_frame=robot.base_frame,
            tip_frame=robot.tip_frame,
            joint_names=list(chain.joint_names),
            urdf_sha256=chain.urdf_sha256,
            urdf=robot.urdf_xml,
        ),
        options=options,
        measurement_frame=_transform(
            fit.params.links[0] @ lie.inverse(chain.nominal_links[0]), *_link_stderr(fit, chain, 0)
        ),
        tool=_transform(
            lie.inverse(chain.nominal_links[-1]) @ fit.params.links[-1],
            *_link_stderr(fit, chain, chain.n_links - 1),
        ),
        baseline=BaselineFit(
            measurement_frame=_transform(
                baseline_params.links[0] @ lie.inverse(chain.nominal_links[0])
            ),
            tool=_transform(lie.inverse(chain.nominal_links[-1]) @ baseline_params.links[-1]),
        ),
        links=_links(chain, fit),
        compliance=_compliance(chain, fit),
        identifiability=Identifiability(
            n_parameters=len(parameter_names(chain)),
            rank=fit.rank,
            condition_number=fit.condition_number,
            removed=fit.removed,
        ),
        fit=FitStatistics(
            before=FitPhase(
                train=train_before,
                heldout=_heldout_stats(splits, BEFORE, dataset.position_only),
            ),
            after=FitPhase(
                train=train_after,
                heldout=_heldout_stats(splits, CALIBRATED, dataset.position_only),
            ),
        ),
        covariance=covariance,
        evaluation=_evaluation(splits, options) if splits else None,
        outliers=outliers,
        solver=SolverReport(
            name="gauss_newton",
            status="optimal" if fit.converged else "iteration_limit",
            iterations=fit.iterations,
            time_s=fit.elapsed_s,
            objective=fit.cost_history[-1],
        ),
    )


def covariance_stage(
    data: PreparedData, used: NDArray[np.intp], fit: DeterministicFit, options: CalibrationOptions
) -> CovarianceResult | None:
    """Covariances of the random perturbations (paper §IV-C) from the calibrated fit's residuals.

    Residuals are end-effector-frame (``fit.residuals``, outliers removed); the perturbation of
    joint j enters through its frame Jacobian ``J_j = Ad_{B_j}^-1`` at the calibrated geometry
    (Eq. 12); REML gets the deterministic fit's Jacobian with the rotation weighting undone so
    its column space is in residual units.
    """
    if options.covariance == "none":
        return None
    chain = data.chain
    chosen, index = _covariance_frames(chain, options)
    rows = 3 if data.position_only else 6
    evaluation = evaluate_chain(chain, fit.params, data.joint_positions[used], data.loads_nm[used])
    frame_jacobians = evaluation.link_jacobians[:, index, :rows, :]
    unweight = np.ones(rows)
    if not data.position_only:
        unweight[3:] = 1.0 / options.rotation_weight_m_per_rad
    fit_jacobian = fit.jacobian * unweight[None, :, None]
    noise = _known_noise(options)
    estimate = estimate_covariances(
        fit.residuals,
        frame_jacobians,
        chosen,
        structure=options.covariance,
        estimator=options.covariance_estimator,
        solver=options.covariance_solver,
        fit_jacobian=fit_jacobian,
        noise_covariance=noise,
        free_axes=_free_axes(chosen, options),
    )
    return _covariance_result(estimate, index)


def _covariance_frames(
    chain: KinematicChain, options: CalibrationOptions
) -> tuple[list[str], list[int]]:
    """Joints whose frame carries a perturbation (names, chain indices), checked."""
    names = list(chain.joint_names)
    chosen = options.covariance_frames if options.covariance_frames is not None else names
    unknown = [name for name in chosen if name not in names]
    if unknown or len(set(chosen)) != len(chosen):
        raise KincalError(
            f"covariance_frames: {unknown or 'duplicates'} "
            f"{'are not joints of the chain' if unknown else 'given twice'}; "
            f"choose among {', '.join(names)}"
        )
    return list(chosen), [names.index(name) for name in chosen]


def _free_axes(
    chosen: Sequence[str], options: CalibrationOptions
) -> dict[str, tuple[str, ...]] | None:
    """The random axes of each perturbed joint frame (``covariance_axes``); None = all six."""
    if options.covariance_axes == "all":
        return None
    return {name: ROTATION_AXIS_NAMES for name in chosen}


def _known_noise(options: CalibrationOptions) -> FloatArray | None:
    """The known measurement-noise covariance (6, 6) from ``noise_covariance`` or
    ``noise_std`` (validated exclusive by the schema), or None."""
    if options.noise_covariance is not None:
        return np.array(options.noise_covariance, dtype=float)
    if options.noise_std is None:
        return None
    return np.diag(np.square(np.asarray(options.noise_std, dtype=float)))


def heldout_splits(
    data: PreparedData,
    used: NDArray[np.intp],
    options: CalibrationOptions,
    progress: Progress = _no_progress,
) -> list[SplitError]:
    """DESIGN.md §4: nominal robot (frame + tool fitted) vs calibrated, on identical splits."""
    n_links = data.chain.n_links
    total, done = 2 * len(options.seeds), [0]

    def method(baseline: bool) -> Callable[[NDArray[np.intp], NDArray[np.intp]], FloatArray]:
        settings = fit_options(options, baseline=baseline, n_links=n_links)

        def predict_test(train: NDArray[np.intp], test: NDArray[np.intp]) -> FloatArray:
            params = _fit(data, used[train], settings).params
            done[0] += 1
            progress("heldout", done[0], total)
            rows = used[test]
            return forward_kinematics(
                data.chain, params, data.joint_positions[rows], data.loads_nm[rows]
            )

        return predict_test

    return cross_validate(
        data.measured_pose[used],
        {BEFORE: method(True), CALIBRATED: method(False)},
        position_only=data.position_only,
        seeds=options.seeds,
        train_fraction=options.train_fraction,
    )


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
    return pose_residuals(predicted, data.measured_pose, position_only=data.position_only)


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


# --- result assembly -------------------------------------------------------------------------


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


def _link_stderr(
    fit: FitLike, chain: KinematicChain, link: int
) -> tuple[tuple[float | None, ...], tuple[float | None, ...]]:
    """Standard errors of link ``link``'s local twist components (None where not estimated)."""
    lookup = dict(zip(fit.estimated, fit.standard_errors.tolist(), strict=True))
    name = chain.link_names[link]
    values = [lookup.get(f"{name}.{c}") for c in ("tx", "ty", "tz", "rx", "ry", "rz")]
    return tuple(values[:3]), tuple(values[3:])


def _links(chain: KinematicChain, fit: FitLike) -> list[LinkCalibration]:
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


def _compliance(chain: KinematicChain, fit: FitLike) -> list[ComplianceCalibration]:
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
            )
        )
    return out


def _covariance_result(estimate: CovarianceEstimate, joint_index: list[int]) -> CovarianceResult:
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
        std=tuple(float(v) for v in frame.std),  # type: ignore[arg-type]
        std_stderr=optional(frame.std_se),
        std_ci_low=optional(frame.std_ci_low),
        std_ci_high=optional(frame.std_ci_high),
        identifiable=tuple(bool(v) for v in frame.identifiable),
    )


def _stats(data: PreparedData, rows: NDArray[np.intp], params: ChainParameters) -> ErrorStats:
    predicted = forward_kinematics(
        data.chain, params, data.joint_positions[rows], data.loads_nm[rows]
    )
    translation, rotation = pose_errors(
        predicted, data.measured_pose[rows], position_only=data.position_only
    )
    return _error_stats(translation, rotation)


def _error_stats(translation_mm: FloatArray, rotation_deg: FloatArray | None) -> ErrorStats:
    return ErrorStats(
        n_samples=int(translation_mm.size),
        translation_mean_mm=float(translation_mm.mean()),
        translation_rms_mm=float(np.sqrt(np.mean(translation_mm**2))),
        rotation_mean_deg=None if rotation_deg is None else float(rotation_deg.mean()),
        rotation_rms_deg=None if rotation_deg is None else float(np.sqrt(np.mean(rotation_deg**2))),
    )


def _heldout_stats(splits: list[SplitError], method: str, position_only: bool) -> ErrorStats | None:
    """Mean over splits of the per-split mean errors (RMS over the split means)."""
    mine = [s for s in splits if s.method == method]
    if not mine:
        return None
    translation = np.array([s.translation_mm for s in mine])
    rotation = None if position_only else np.array([s.rotation_deg for s in mine], dtype=float)
    stats = _error_stats(translation, rotation)
    return stats.model_copy(update={"n_samples": sum(s.n_test for s in mine)})


def _evaluation(splits: list[SplitError], options: CalibrationOptions) -> Evaluation:
    return Evaluation(
        protocol=f"{len(options.seeds)} random train/test splits "
        f"({options.train_fraction:.0%} train), seeds {options.seeds}, after outlier removal",
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


# --- streamed calibration (issue 7): recordings larger than memory ------------------------


@dataclass(frozen=True)
class StreamOptions:
    """How :func:`calibrate_streamed` cuts and holds a recording.

    ``chunk_rows``: rows per task (Parquet: whole row groups up to this); ``block_rows``:
    samples per vectorised block inside a task; ``warm_start_rows``: head rows fitted in
    memory for the start and the pruning; ``cache_mb``: prepared chunks each worker process
    keeps between passes (0: re-read each pass; memory then does not grow with N).
    """

    chunk_rows: int = 65_536
    block_rows: int = 8192
    warm_start_rows: int = 10_000
    cache_mb: float = 512.0


@dataclass(frozen=True)
class DatasetChunkLoader:
    """:data:`solver.stream.chunks.ChunkLoader` of a dataset file; picklable, so worker processes
    and Dask workers read and validate their own chunks."""

    plan: DatasetChunks

    def __call__(self, ref: ChunkRef) -> ChunkArrays:
        dataset = self.plan.read(ref)
        return ChunkArrays(
            dataset.joint_positions,
            dataset.position_m,
            dataset.quaternion_xyzw,
            dataset.payload_kg,
            ref.first_row,
        )


def stream_problem(
    path: str | Path,
    chain: KinematicChain,
    options: CalibrationOptions,
    stream: StreamOptions = StreamOptions(),
    *,
    marker: int | None = None,
) -> StreamProblem:
    """Plan the chunks of a dataset file (first chunk validated) for one chain."""
    plan = plan_dataset_chunks(
        path,
        chain.joint_names,
        chunk_rows=stream.chunk_rows,
        other_joint_names=chain.other_joint_names,
        marker=marker,
    )
    return StreamProblem(
        chain,
        DatasetChunkLoader(plan),
        plan.refs,
        position_only=plan.position_only,
        gravity_base_m_s2=np.asarray(options.gravity_base_m_s2, dtype=float),
        payload_kg=options.payload_kg,
        block_rows=stream.block_rows,
        cache_bytes=int(stream.cache_mb * 1024 * 1024),
    )


def calibrate_streamed(
    path: str | Path,
    robot: RobotDescription,
    options: CalibrationOptions,
    executor: Executor | None = None,
    stream: StreamOptions = StreamOptions(),
    *,
    marker: int | None = None,
    progress: Progress = _no_progress,
    timings: dict[str, float] | None = None,
    source: str | None = None,
) -> CalibrationResult:
    """:func:`calibrate` for a dataset file read in chunks, each pass mapped over ``executor``
    (default in-process); see :mod:`solver.stream` for what differs: warm start and pruning
    on the head rows, moment-matching covariances, no held-out splits (``heldout`` is stored
    as False). ``progress`` is called as the stages "read", "fit", "baseline" and
    "covariance" end; ``timings`` (optional) receives the wall time of each stage in seconds
    and the number of passes over the data (``passes``); ``source`` names the dataset in the
    result (default: the file's name).
    """
    chain = chain_for(robot, options)
    started = time.perf_counter()
    problem = stream_problem(path, chain, options, stream, marker=marker)
    executor = executor or InProcessExecutor()
    stage: dict[str, float] = {"plan": time.perf_counter() - started}
    spec = _streamed_covariance_spec(problem, options)
    try:
        run = calibrate_streamed_fits(
            problem,
            executor,
            fit_options(options),
            fit_options(options, baseline=True, n_links=chain.n_links),
            StreamSettings(stream.warm_start_rows, options.outlier_sigma),
            covariance=spec,
            progress=lambda name: progress(name, 1, 1),
        )
        stage.update(run.stage_s)
        clock = time.perf_counter()
        count = PassCount(run.passes)
        covariance = _streamed_covariance(problem, executor, run, options, spec, count)
        stage["covariance"] = time.perf_counter() - clock
        stage["passes"] = float(count.passes)
        progress("covariance", 1, 1)
    finally:
        release(problem, executor)
    if timings is not None:
        timings.update(stage)
    load = problem.load
    if source is None:
        source = load.plan.source if isinstance(load, DatasetChunkLoader) else str(path)
    position_only = problem.position_only
    return _assemble_result(
        dataset=DatasetInfo(source=source, n_samples=run.n_rows, position_only=position_only),
        robot=robot,
        chain=chain,
        options=options.model_copy(update={"heldout": False}),
        fit=run.fit,
        baseline_params=run.baseline.params,
        train_before=_sums_stats(run.baseline.sums.errors, position_only),
        train_after=_sums_stats(run.fit.sums.errors, position_only),
        splits=[],
        covariance=covariance,
        outliers=OutlierReport(
            sigma=options.outlier_sigma,
            n_input=run.n_rows,
            n_used=run.fit.sums.errors.n,
            removed_rows=[int(i) + 1 for i in run.removed_rows],
        ),
    )


def _streamed_covariance_spec(
    problem: StreamProblem, options: CalibrationOptions
) -> CovarianceSpec | None:
    """The covariance statistics the streamed fit takes along (None: no covariances)."""
    if options.covariance == "none":
        return None
    chosen, index = _covariance_frames(problem.chain, options)
    return covariance_spec(
        problem,
        chosen,
        index,
        structure=options.covariance,
        noise_covariance=_known_noise(options),
        free_axes=_free_axes(chosen, options),
    )


def _streamed_covariance(
    problem: StreamProblem,
    executor: Executor,
    run: StreamedCalibration,
    options: CalibrationOptions,
    spec: CovarianceSpec | None,
    count: PassCount,
) -> CovarianceResult | None:
    """§IV-C on the streamed fit (moment matching; the same samples as the fit; the
    statistics from the fit's last pass when it took them)."""
    if spec is None:
        return None
    notes = [] if options.covariance_estimator == "moment" else [STREAMED_ESTIMATOR_NOTE]
    estimate = estimate_covariances_streamed(
        problem,
        executor,
        run.fit.params,
        spec,
        solver=options.covariance_solver,
        rule=run.rule,
        notes=notes,
        sums=run.covariance,
        count=count,
    )
    return _covariance_result(estimate, list(spec.frames))


def _sums_stats(sums: ErrorSums, position_only: bool) -> ErrorStats:
    mean_mm, rms_mm, mean_deg, rms_deg = sums.summary(position_only)
    return ErrorStats(
        n_samples=sums.n,
        translation_mean_mm=mean_mm,
        translation_rms_mm=rms_mm,
        rotation_mean_deg=mean_deg,
        rotation_rms_deg=rms_deg,
    )
