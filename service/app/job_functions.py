"""Job functions run by the worker processes of :mod:`service.jobs.runner` (no HTTP, no database).

A job function reads its inputs from ``ctx.params`` and the data folder, calls the pipeline
(the same one as the CLI), reports progress and writes its outputs as artifacts.

Calibrations go through :func:`service.app.calibrate.calibrate_source`, the CLI's entry point; their
passes run in the worker process, or — when the worker's environment names a Dask scheduler
(``KINCAL_DASK_ADDRESS``, see :class:`service.settings.Settings`) — on that cluster (the same
call as ``kincal calibrate --executor dask``): for a large dataset the cluster's workers read
the stored file themselves, so they need the service's data folder at the same path.
"""

from __future__ import annotations

import functools
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from schemas.calibration import CalibrationResult
from schemas.design import DesignResult
from schemas.discovery import FindingsResult
from schemas.robots import RobotDescription, load_robot
from service.app import calibrate as pipeline
from service.app import discover as discovery
from service.app.design import design_model, recorded_design, run_design, socket_candidates
from service.app.job_params import (
    CalibrationJobParams,
    DesignJobParams,
    DiscoveryJobParams,
    RobotRef,
)
from service.render.discovery_html import render_discovery_report
from service.settings import load_settings
from service.storage.files import FileStore
from solver.errors import KincalError
from solver.executors import DaskExecutor, Executor, InProcessExecutor


class JobContext(Protocol):
    """What a job function needs of the worker process running it: its parameters, the data
    folder, progress and artifacts (:class:`service.jobs.worker.JobContext` is the one the
    worker passes; declared here so the use cases do not import the job runner)."""

    params: dict[str, Any]
    files: FileStore
    summary: dict[str, Any]

    def progress(
        self, stage: str, fraction: float | None = None, iteration: int | None = None
    ) -> None: ...

    def write_artifact(self, name: str, filename: str, data: bytes) -> str: ...


@functools.lru_cache(maxsize=16)
def _builtin(name: str, base_frame: str, tip_frame: str) -> RobotDescription:
    return load_robot(name, base_frame=base_frame, tip_frame=tip_frame)


def robot_description(ref: RobotRef, files: FileStore) -> RobotDescription:
    """The URDF and chain a robot reference stands for."""
    if ref.robot_id is None:
        return _builtin(ref.name, ref.base_frame, ref.tip_frame)
    assert ref.urdf_path is not None
    xml = files.read(ref.urdf_path).decode("utf-8")
    return RobotDescription(ref.name, xml, ref.base_frame, ref.tip_frame)


# Overall fraction reached at the end of each stage, (with, without) held-out splits; held-out
# splits report done/total and fill the interval up to their end.
_STAGE_END = {
    "read": (0.05, 0.05),
    "fit": (0.15, 0.35),
    "baseline": (0.25, 0.6),
    "covariance": (0.35, 0.9),
    "heldout": (0.9, 0.9),
}
REPORT_FRACTION = 0.92


def _progress(ctx: JobContext, heldout: bool) -> pipeline.Progress:
    column = 0 if heldout else 1
    stages = list(_STAGE_END)

    def report(stage: str, done: int, total: int) -> None:
        if stage not in _STAGE_END:  # a stage this mapping does not know yet
            ctx.progress(stage, None, done)
            return
        end = _STAGE_END[stage][column]
        index = stages.index(stage)
        start = _STAGE_END[stages[index - 1]][column] if index else 0.0
        ctx.progress(stage, start + (end - start) * done / max(total, 1), done)

    return report


def calibration_job(ctx: JobContext) -> None:
    """Calibrate a stored dataset through :func:`service.app.calibrate.calibrate_source` (its
    passes on the Dask cluster of ``KINCAL_DASK_ADDRESS`` if set, else in this worker),
    carrying a discovery's findings if the job names one (as ``kincal calibrate --model``);
    artifacts: result JSON, HTML report, calibrated URDF (none when the result corrects the
    joint readings, which a URDF cannot express: see :func:`service.render.urdf_export.refusal`);
    the verdict goes in the job's summary, which its status shows."""
    ctx.progress("loading", 0.0)
    params = CalibrationJobParams.model_validate(ctx.params)
    robot = robot_description(params.robot, ctx.files)
    findings = None
    if params.discovery is not None:
        findings = FindingsResult.model_validate_json(
            ctx.files.read(params.discovery.findings_path)
        )
    setup = pipeline.check_calibration(robot, params.options, findings)
    address = load_settings().dask_address
    if address:
        ctx.progress("connecting", 0.02)
    executor: Executor = DaskExecutor(address) if address else InProcessExecutor()
    with executor:
        run = pipeline.calibrate_source(
            ctx.files.path(params.dataset.data_path),
            setup,
            executor=executor,
            name=params.dataset.name,
            progress=_progress(ctx, setup.options.heldout),
        )
    ctx.progress("report", REPORT_FRACTION)
    ctx.write_artifact("result", "result.json", run.result.model_dump_json(indent=1).encode())
    if run.result.verdict is not None:
        ctx.summary["verdict"] = run.result.verdict.model_dump(mode="json")
    if run.urdf_refusal is None:
        ctx.write_artifact("urdf", "calibrated.urdf", run.urdf().encode())
    ctx.write_artifact("report", "report.html", run.report_html().encode())


DISCOVERY_FRACTION = 0.1
DISCOVERY_REPORT_FRACTION = 0.9


def discovery_job(ctx: JobContext) -> None:
    """Look for missing physics in a stored dataset; artifacts: findings JSON, HTML report
    (with each finding's before/after residual plot)."""
    ctx.progress("loading", 0.0)
    params = DiscoveryJobParams.model_validate(ctx.params)
    robot = robot_description(params.robot, ctx.files)
    ctx.progress("discover", DISCOVERY_FRACTION)
    with tempfile.TemporaryDirectory(prefix="kincal-discovery-") as folder:
        plot_dir = Path(folder)
        findings = discovery.discover_source(
            ctx.files.path(params.dataset.data_path),
            robot,
            params.options,
            plot_dir,
            "finding",
            name=params.dataset.name,
        )
        ctx.progress("report", DISCOVERY_REPORT_FRACTION)
        plots = {name: (plot_dir / name).read_bytes() for name in findings.plots}
    ctx.write_artifact("result", "findings.json", findings.model_dump_json(indent=1).encode())
    ctx.write_artifact("report", "report.html", render_discovery_report(findings, plots).encode())


JointRows = Callable[[list[list[float]] | None, str, int], NDArray[np.float64] | None]
"""Joint positions of a request field (rows of k numbers, field name, k) as an (N, k) array;
raises naming the field when a row does not have k numbers."""


def joint_rows(rows: list[list[float]] | None, field: str, k: int) -> NDArray[np.float64] | None:
    """:data:`JointRows` raising a :class:`KincalError` (a job's error message)."""
    if rows is None:
        return None
    for i, row in enumerate(rows):
        if len(row) != k:
            raise KincalError(f"{field}.{i}: {len(row)} joint positions; the chain has {k}")
    return np.array(rows, dtype=float).reshape(-1, k)


def design_now(
    files: FileStore, params: DesignJobParams, rows: JointRows = joint_rows
) -> DesignResult:
    """The design of a stored request (``POST /api/v1/designs``), in the calling thread: the
    HTTP route for small candidate sets (``rows`` its 422 problem per field), the design job
    otherwise."""
    body = params.request
    recorded = None
    if params.recorded is not None:
        result = CalibrationResult.model_validate_json(files.read(params.recorded.result_path))
        dataset = params.recorded.dataset
        robot, recorded = recorded_design(
            result, files.path(dataset.data_path), source=dataset.name
        )
    else:
        assert params.robot is not None
        robot = robot_description(params.robot, files)
    model = design_model(robot, body.options, recorded)
    k = model.chain.n_joints
    return run_design(
        robot,
        body.options,
        candidates=rows(body.candidates_rad, "candidates_rad", k),
        task=rows(body.task_rad, "task_rad", k),
        recorded=recorded,
        model=model,
        sockets=socket_candidates(body.candidate_sockets),
    )


def design_job(ctx: JobContext) -> None:
    """A large design (``POST /api/v1/designs`` beyond the synchronous limit); artifact: the
    design document."""
    ctx.progress("design", 0.0)
    params = DesignJobParams.model_validate(ctx.params)
    result = design_now(ctx.files, params)
    ctx.write_artifact("result", "design.json", result.model_dump_json(indent=1).encode())
