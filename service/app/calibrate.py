"""The one calibration entry point: ``kincal calibrate``, the HTTP calibration jobs, ``kincal
fleet``, the demo and the benchmarks all calibrate through :func:`calibrate_source`.

:func:`check_calibration` validates every option against the robot (and a carried discovery)
before any data is read — the HTTP service calls it when it accepts a calibration, so every
option error is a 422 before the 202. :func:`calibrate_source` then reads the recording (or
plans its chunks), carries a discovery's model, chooses where the passes over the data run from
the recording's size and the machine's cores, and runs
:func:`solver.stream.calibrate.calibrate_recording`: the same stages for 100 poses in memory
and for 10⁶ poses streamed from a Parquet file on several processes, so the path never changes
the numbers beyond rounding. The result JSON is assembled by :mod:`service.render.result_json`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.calibration import (
    CalibrationOptions,
    CalibrationResult,
    ModelCorrections,
    RobotInfo,
)
from schemas.dataset import ChunkRef, DatasetChunks, PoseDataset, plan_dataset_chunks
from schemas.discovery import FindingsResult
from schemas.robots import RobotDescription
from service.app import calibrate_measurement as measurement_run
from service.app import measurement_input
from service.app.preflight import chosen_columns, fit_options
from service.render.result_json import ResidualSample, assemble_result, chain_for, sample_residuals
from service.render.urdf_export import export_urdf
from service.render.urdf_export import refusal as urdf_refusal
from solver.covariance.layout import ROTATION_AXIS_NAMES
from solver.errors import KincalError, ModelError
from solver.executors import Executor, InProcessExecutor, ProcessExecutor, preload_in_workers
from solver.measurement import FullPose, MeasurementModel, PoseComponents
from solver.measurement.pose import pose_measurement
from solver.model import KinematicChain
from solver.stream.calibrate import (
    CovarianceSettings,
    HeldoutSettings,
    StreamSettings,
    calibrate_recording,
)
from solver.stream.chunks import ArrayChunks, ChunkArrays, StreamProblem, release, row_ranges
from solver.stream.coverage import PredictiveCalibration
from solver.stream.sums import covariance_spec

# Passes on local worker processes send DatasetChunkLoader: import this module once, in their
# fork server, rather than in every worker on its first chunk.
preload_in_workers(__name__)

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)`` as the stages end: "read", "fit", "baseline",
"covariance" and each held-out split ("heldout"); the HTTP job runner turns it into job
progress."""


def _no_progress(stage: str, done: int, total: int) -> None:
    return None


@dataclass(frozen=True)
class StreamOptions:
    """How a recording is cut and held: ``chunk_rows`` rows per task (Parquet: whole row
    groups up to this); ``block_rows`` samples per vectorised block inside a task;
    ``warm_start_rows`` head rows fitted in memory for the start and the pruning;
    ``cache_mb`` prepared chunks each worker process keeps between passes (0: re-read each
    pass; memory then does not grow with N)."""

    chunk_rows: int = 65_536
    block_rows: int = 8192
    warm_start_rows: int = 10_000
    cache_mb: float = 512.0


# --- checking a calibration before it runs ------------------------------------------------


@dataclass(frozen=True)
class CalibrationSetup:
    """A calibration checked before any data is read: the robot, its chain (built once), the
    options (with a carried discovery's compliance, flex axes, gravity and payload), the
    joints whose frames carry random perturbations, and the findings carried (if any)."""

    robot: RobotDescription
    chain: KinematicChain
    options: CalibrationOptions
    covariance_frames: tuple[str, ...]
    covariance_index: tuple[int, ...]
    findings: FindingsResult | None = None
    free_columns: tuple[int, ...] | None = None
    """Columns the fit may move (:func:`solver.selection.free_columns`); None = all."""


def check_calibration(
    robot: RobotDescription,
    options: CalibrationOptions,
    findings: FindingsResult | None = None,
) -> CalibrationSetup:
    """Every check of ``options`` that needs the robot (the schema checks the rest):
    :class:`~solver.errors.ModelError` / :class:`~solver.errors.KincalError` naming the
    option and the fix. With ``findings`` (``calibrate --model``, an HTTP ``discovery_id``) the
    discovery must be of this robot's joints and the options it sets must be left at their
    defaults."""
    if findings is not None:
        # only with a carried discovery: it imports the discovery modules
        from service.app import discover_carry

        discover_carry.findings_chain(findings, robot)
        options = discover_carry.carried_options(options, findings)
    chain = chain_for(robot, options)
    names = list(chain.joint_names)
    chosen = options.covariance_frames if options.covariance_frames is not None else names
    unknown = [name for name in chosen if name not in names]
    if options.covariance != "none" and not chosen:
        raise ModelError(
            "covariance_frames: empty; name at least one joint whose frame carries random "
            f"perturbations (among {', '.join(names)}), or pass --covariance none"
        )
    if unknown or len(set(chosen)) != len(chosen):
        raise ModelError(
            f"covariance_frames: {unknown or 'duplicates'} "
            f"{'are not joints of the chain' if unknown else 'given twice'}; "
            f"choose among {', '.join(names)}"
        )
    measurement_input.check_sensor_joint(options.measurement, chain)
    kind, _, joint = options.measurement.partition(":")
    if kind == "components":
        PoseComponents(tuple(c.strip() for c in joint.split(",")))
    return CalibrationSetup(
        robot,
        chain,
        options,
        tuple(chosen),
        tuple(names.index(name) for name in chosen),
        findings,
        chosen_columns(chain, options),
    )


# --- reading a recording ---------------------------------------------------------------------


@dataclass(frozen=True)
class DatasetChunkLoader:
    """:data:`solver.stream.chunks.ChunkLoader` of a dataset file; picklable, so worker
    processes and Dask workers read and validate their own chunks."""

    plan: DatasetChunks
    rotation: bool = True
    """Keep the file's orientations (False: positions only, ``measurement`` 'position')."""

    def __call__(self, ref: ChunkRef) -> ChunkArrays:
        dataset = self.plan.read(ref)
        return ChunkArrays(
            dataset.joint_positions,
            dataset.position_m,
            dataset.quaternion_xyzw if self.rotation else None,
            dataset.payload_kg,
            ref.first_row,
        )


def rows_measurement(options: CalibrationOptions, *, file_rotation: bool, source: str) -> FullPose:
    """What a pose recording's rows measure, the model its calibration takes (issue 35): the
    file's columns (``file_rotation``: it has qx,qy,qz,qw), :class:`~solver.measurement.Position`
    when the ``measurement`` option says 'position' (orientations ignored); 'pose' on a file
    without orientations is refused with the fix."""
    if options.measurement == "pose" and not file_rotation:
        raise KincalError(
            f"measurement 'pose' needs the orientation columns qx,qy,qz,qw; {source} has "
            "positions only: use --measurement position (or auto)"
        )
    return pose_measurement(rotation=file_rotation and options.measurement != "position")


@dataclass(frozen=True)
class Recording:
    """A recording opened for one calibration: the chunks the engine passes over, the
    dataset in memory (None when the workers read the file's chunks themselves), the name the
    result gives it, and what carrying a discovery did to it (``corrections`` go into the
    result; ``notes`` one line each for the user)."""

    problem: StreamProblem
    dataset: PoseDataset | None
    source: str
    corrections: ModelCorrections | None
    notes: tuple[str, ...]


IN_MEMORY_ROWS = 65_536
"""Files up to this many rows are read whole (every check across rows, e.g. that ``t`` does
not decrease, sees the whole file); larger ones are read chunk by chunk by the workers."""


def open_recording(
    source: str | Path | PoseDataset,
    setup: CalibrationSetup,
    stream: StreamOptions = StreamOptions(),
    *,
    marker: int | None = None,
    name: str | None = None,
) -> Recording:
    """Read ``source`` (a dataset file or a dataset already in memory) for ``setup``'s chain,
    or plan its chunks when it is large; with findings, undo the discovered terms on it."""
    chain, options = setup.chain, setup.options
    if isinstance(source, PoseDataset):
        dataset = source
    else:
        plan = plan_dataset_chunks(
            source,
            chain.joint_names,
            chunk_rows=stream.chunk_rows,
            other_joint_names=chain.other_joint_names,
            marker=marker,
            source=name,
        )
        if plan.n_rows > IN_MEMORY_ROWS and setup.findings is None:
            measurement = rows_measurement(
                options, file_rotation=plan.measures_rotation, source=plan.source
            )
            problem = StreamProblem(
                chain,
                DatasetChunkLoader(plan, measurement.measures_rotation),
                plan.refs,
                measurement=measurement,
                gravity_base_m_s2=np.asarray(options.gravity_base_m_s2, dtype=float),
                payload_kg=options.payload_kg,
                block_rows=stream.block_rows,
                cache_bytes=int(stream.cache_mb * 1024 * 1024),
            )
            return Recording(problem, None, plan.source, None, ())
        dataset = measurement_input.read_chain_dataset(source, chain, marker, name)
    corrections: ModelCorrections | None = None
    notes: tuple[str, ...] = ()
    if setup.findings is not None:
        from service.app import discover_carry

        carried = discover_carry.carry_model(setup.findings, dataset, setup.robot)
        dataset, corrections, notes = carried.dataset, carried.record, tuple(carried.notes)
    measurement = rows_measurement(
        options,
        file_rotation=dataset.measurement_model.measures_rotation,
        source=dataset.source,
    )
    problem = StreamProblem(
        chain,
        ArrayChunks(
            dataset.joint_positions,
            dataset.position_m,
            dataset.quaternion_xyzw if measurement.measures_rotation else None,
            dataset.payload_kg,
        ),
        row_ranges(dataset.n_samples, stream.chunk_rows),
        measurement=measurement,
        gravity_base_m_s2=np.asarray(options.gravity_base_m_s2, dtype=float),
        payload_kg=options.payload_kg,
        block_rows=stream.block_rows,
        cache_bytes=int(stream.cache_mb * 1024 * 1024),
    )
    return Recording(problem, dataset, name or dataset.source, corrections, notes)


# --- where the passes run ----------------------------------------------------------------------


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_executor(recording: Recording) -> Executor:
    """Where the passes run when the caller does not say: local processes (one per core, at
    most one per chunk) for a file of several chunks on a machine with several cores, this
    process otherwise (a recording in memory would travel to the workers with every pass; a
    daemonic process, e.g. a service job worker, may not start processes)."""
    chunks = len(recording.problem.refs)
    cores = available_cores()
    if (
        recording.dataset is None
        and chunks > 1
        and cores > 1
        and not multiprocessing.current_process().daemon
    ):
        return ProcessExecutor(min(cores, chunks))
    return InProcessExecutor()


# --- the calibration ---------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationRun:
    """What one calibration produced: the result JSON, the residuals a report plots, what
    carrying a discovery did (``notes``, one line each), where the passes ran
    (``execution``), and the wall time of each stage in seconds with the passes over the
    data (``timings``)."""

    result: CalibrationResult
    residuals: ResidualSample
    notes: tuple[str, ...]
    execution: str
    timings: dict[str, float]
    predictive: PredictiveCalibration | None = None
    """The held-out material behind ``result.predictive`` (benchmarks take its parts apart)."""
    measured: measurement_run.MeasurementCalibration | None = None
    """A measurement-model calibration's fit, covariances and predictive parts (in memory)."""

    def urdf(self) -> str:
        """The calibrated URDF; :class:`KincalError` saying why when the result corrects
        the joint readings (a URDF cannot express that)."""
        refused = urdf_refusal(self.result.model_corrections)
        if refused is not None:
            raise KincalError(refused)
        return export_urdf(self.result)

    @property
    def urdf_refusal(self) -> str | None:
        return urdf_refusal(self.result.model_corrections)

    def report_html(self) -> str:
        from service.render.report_html import render_report

        return render_report(self.result, self.residuals)


def calibrate_source(
    source: str | Path | PoseDataset,
    setup: CalibrationSetup,
    *,
    executor: Executor | None = None,
    stream: StreamOptions = StreamOptions(),
    marker: int | None = None,
    name: str | None = None,
    progress: Progress = _no_progress,
) -> CalibrationRun:
    """Calibrate geometry, compliance (Eq. 8–10) and the covariances of the random
    perturbations (§IV-C) of a recording, with the held-out evaluation of DESIGN.md §4.

    ``source``: a dataset file (CSV, Parquet, JSON; ``marker`` picks a FIGAROH marker) or a
    dataset in memory; ``setup``: :func:`check_calibration` of the robot, the options and the
    findings of a discovery whose model to calibrate (``calibrate --model``); ``executor``:
    where the passes run (default :func:`default_executor`; the caller keeps ownership of one
    it passes); ``name``: the recording's name in the result (default: the file's).
    """
    model = measurement_input.measurement_for(setup.options, setup.chain, source, marker)
    if model is not None:
        return _calibrate_measured(source, setup, model, marker=marker, name=name)
    started = time.perf_counter()
    recording = open_recording(source, setup, stream, marker=marker, name=name)
    timings = {"open": time.perf_counter() - started}
    owned = executor is None
    runner = default_executor(recording) if executor is None else executor
    try:
        calibrated = calibrate_recording(
            recording.problem,
            runner,
            fit_options(setup.options, free_columns=setup.free_columns),
            fit_options(setup.options, baseline=True, n_links=setup.chain.n_links),
            StreamSettings(
                stream.warm_start_rows,
                setup.options.screening,
                setup.options.outlier_sigma or 2.0,
                setup.options.outlier_level,
            ),
            covariance=covariance_settings(recording.problem.residual_dim, setup),
            heldout=HeldoutSettings(
                tuple(setup.options.seeds),
                setup.options.train_fraction,
                method=setup.options.heldout_method,
            )
            if setup.options.heldout
            else None,
            progress=progress,
        )
        execution = f"{runner.name} ({runner.n_workers} worker(s))"
    except BaseException:
        with contextlib.suppress(Exception):  # the workers may be gone: keep the first error
            release(recording.problem, runner)
        raise
    else:
        release(recording.problem, runner)
    finally:
        if owned:
            runner.close()
    timings.update(calibrated.stage_s)
    timings["passes"] = float(calibrated.passes)
    result = assemble_result(
        source=recording.source,
        robot=setup.robot,
        chain=setup.chain,
        options=setup.options,
        calibrated=calibrated,
        frame_index=list(setup.covariance_index),
        measurement=recording.problem.measurement,
        free_columns=setup.free_columns,
    )
    if recording.corrections is not None:
        result = result.model_copy(update={"model_corrections": recording.corrections})
    residuals = sample_residuals(setup.chain, calibrated, recording.problem.measurement)
    return CalibrationRun(
        result, residuals, recording.notes, execution, timings, calibrated.predictive
    )


def _calibrate_measured(
    source: str | Path | PoseDataset,
    setup: CalibrationSetup,
    model: MeasurementModel,
    *,
    marker: int | None,
    name: str | None,
) -> CalibrationRun:
    """A recording whose rows are not marker poses or positions (ball in socket, several
    markers, pose components, a frame on the base, a sensor on the chain): read into memory
    and calibrated by :mod:`service.app.calibrate_measurement`."""
    started = time.perf_counter()
    recording = measurement_input.read_measured(
        source, setup.chain, setup.options, model, marker=marker, name=name
    )
    corrections: ModelCorrections | None = None
    notes: tuple[str, ...] = ()
    if setup.findings is not None:
        from service.app import discover_carry

        carried = discover_carry.carry_measured(
            setup.findings, recording, setup.robot, setup.chain, setup.options
        )
        recording, corrections, notes = carried.recording, carried.record, tuple(carried.notes)
    opened = time.perf_counter() - started
    run = calibrate_measured(recording, setup)
    result = run.result
    if corrections is not None:
        result = result.model_copy(update={"model_corrections": corrections})
    return dataclasses.replace(
        run, result=result, notes=notes, timings={"open": opened, **run.timings}
    )


def calibrate_measured(
    recording: measurement_input.MeasuredRecording, setup: CalibrationSetup
) -> CalibrationRun:
    """Calibrate the rows of a measurement model in memory (what ``kincal calibrate`` does
    once it has read them: :func:`service.app.calibrate_measurement.calibrate_measurement`
    and its result JSON); benchmarks pass a subset of a recording's rows
    (``dataclasses.replace(recording, rows=recording.rows.take(index))``)."""
    calibrated = measurement_run.calibrate_measurement(
        recording,
        setup.chain,
        setup.options,
        fit_options(setup.options, free_columns=setup.free_columns),
        fit_options(setup.options, baseline=True, n_links=setup.chain.n_links),
        covariance_settings(recording.model.dim, setup, recording.model.noise_rows),
    )
    timings = {"calibration": calibrated.elapsed_s}
    robot = setup.robot
    result = measurement_run.measurement_result(
        calibrated,
        robot=RobotInfo(
            name=robot.name,
            base_frame=robot.base_frame,
            tip_frame=robot.tip_frame,
            joint_names=list(setup.chain.joint_names),
            urdf_sha256=setup.chain.urdf_sha256,
            urdf=robot.urdf_xml,
        ),
        chain=setup.chain,
        options=setup.options,
        free_columns=setup.free_columns,
        covariance_index=list(setup.covariance_index),
    )
    return CalibrationRun(
        result,
        measurement_run.measurement_residuals(calibrated),
        (),
        "in memory (measurement model)",
        timings,
        measured=calibrated,
    )


def calibrate(
    dataset: PoseDataset,
    robot: RobotDescription,
    options: CalibrationOptions,
    progress: Progress = _no_progress,
) -> CalibrationResult:
    """:func:`calibrate_source` of a dataset in memory, its result JSON."""
    setup = check_calibration(robot, options)
    return calibrate_source(dataset, setup, progress=progress).result


def covariance_settings(
    residual_dim: int,
    setup: CalibrationSetup,
    noise_rows: Mapping[str, Sequence[Sequence[int]]] | None = None,
) -> CovarianceSettings | None:
    """The covariance stage of ``setup`` for residuals of ``residual_dim`` rows with the noise
    layout ``noise_rows`` (None: a pose's or position's; see
    :func:`solver.covariance.layout.make_layout`); None: ``covariance`` "none"."""
    options = setup.options
    if options.covariance == "none":
        return None
    free_axes = None
    if options.covariance_axes == "rotation":
        free_axes = {name: ROTATION_AXIS_NAMES for name in setup.covariance_frames}
    noise = None
    if options.noise_covariance is not None:
        noise = np.array(options.noise_covariance, dtype=float)
    elif options.noise_std is not None:
        noise = np.diag(np.square(np.asarray(options.noise_std, dtype=float)))
    spec = covariance_spec(
        residual_dim,
        setup.covariance_frames,
        setup.covariance_index,
        structure=options.covariance,
        noise_covariance=noise,
        free_axes=free_axes,
        noise_rows=noise_rows,
    )
    return CovarianceSettings(spec, options.covariance_estimator, options.covariance_solver)
