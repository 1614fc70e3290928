"""Job functions run by the worker processes of :mod:`service.jobs` (no HTTP, no database).

A job function reads its inputs from ``ctx.params`` and the data folder, calls the pipeline
(the same one as the CLI), reports progress and writes its outputs as artifacts.

Calibrations run in the worker process (:func:`service.pipeline.calibrate`), or — when the
worker's environment names a Dask scheduler (``KINCAL_DASK_ADDRESS``, see
:class:`service.settings.Settings`) — streamed on that cluster
(:func:`service.pipeline.calibrate_streamed` with a :class:`solver.executors.DaskExecutor`,
the same call as ``kincal calibrate --executor dask``): the cluster's workers read the stored
dataset file themselves, so they need the service's data folder at the same path.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from schemas.calibration import CalibrationOptions
from schemas.dataset import read_dataset
from schemas.discovery import DiscoveryOptions, FindingsResult
from service import discovery, pipeline
from service.discovery_html import render_discovery_report
from service.report_html import render_report
from service.robots import RobotDescription, load_robot
from service.settings import Settings
from service.storage.files import FileStore
from service.urdf_export import export_urdf
from service.urdf_export import refusal as urdf_refusal
from service.worker import JobContext
from solver.errors import ModelError
from solver.executors import DaskExecutor


class RobotRef(BaseModel):
    """A built-in robot (``robot_id`` None) or an uploaded URDF, with the calibrated chain."""

    model_config = ConfigDict(extra="forbid")

    name: str
    robot_id: str | None = None
    urdf_path: str | None = None
    base_frame: str
    tip_frame: str


class DatasetRef(BaseModel):
    model_config = ConfigDict(extra="forbid")

    id: str
    name: str
    data_path: str


class DiscoveryRef(BaseModel):
    """A succeeded discovery whose findings a calibration carries (``calibrate --model``)."""

    model_config = ConfigDict(extra="forbid")

    id: str
    findings_path: str


class CalibrationJobParams(BaseModel):
    """``jobs.params`` of a calibration: everything resolved when the job was accepted."""

    model_config = ConfigDict(extra="forbid")

    dataset: DatasetRef
    robot: RobotRef
    options: CalibrationOptions
    discovery: DiscoveryRef | None = None


class DiscoveryJobParams(BaseModel):
    """``jobs.params`` of a discovery: everything resolved when the job was accepted."""

    model_config = ConfigDict(extra="forbid")

    dataset: DatasetRef
    robot: RobotRef
    options: DiscoveryOptions


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


# Overall fraction reached at the end of each pipeline stage, (with, without) held-out splits.
_STAGE_END = {"fit": (0.15, 0.5), "baseline": (0.2, 0.85), "heldout": (0.9, 0.9)}
_STAGE_START = {"fit": (0.05, 0.05), "baseline": (0.15, 0.5), "heldout": (0.2, 0.85)}
REPORT_FRACTION = 0.92


def _progress(ctx: JobContext, heldout: bool) -> pipeline.Progress:
    column = 0 if heldout else 1

    def report(stage: str, done: int, total: int) -> None:
        if stage not in _STAGE_END:  # a stage this mapping does not know yet
            ctx.progress(stage, None, done)
            return
        start, end = _STAGE_START[stage][column], _STAGE_END[stage][column]
        ctx.progress(stage, start + (end - start) * done / max(total, 1), done)

    return report


# Overall fraction reached at the end of each stage of a streamed calibration (Dask).
_STREAMED_STAGE_END = {"read": 0.15, "fit": 0.45, "baseline": 0.8, "covariance": 0.9}


def _streamed_progress(ctx: JobContext) -> pipeline.Progress:
    def report(stage: str, done: int, total: int) -> None:
        ctx.progress(stage, _STREAMED_STAGE_END.get(stage), done)

    return report


def calibration_job(ctx: JobContext) -> None:
    """Calibrate a stored dataset (on the Dask cluster of ``KINCAL_DASK_ADDRESS`` if set),
    carrying a discovery's findings if the job names one (as ``kincal calibrate --model``);
    artifacts: result JSON, HTML report, calibrated URDF (none when the result corrects the
    joint readings, which a URDF cannot express: see :func:`service.urdf_export.refusal`)."""
    ctx.progress("loading", 0.0)
    params = CalibrationJobParams.model_validate(ctx.params)
    robot = robot_description(params.robot, ctx.files)
    options = params.options
    chain = pipeline.chain_for(robot, options)
    path = ctx.files.path(params.dataset.data_path)
    dataset = read_dataset(
        path,
        chain.joint_names,
        other_joint_names=chain.other_joint_names,
        source=params.dataset.name,
    )
    carried = None
    if params.discovery is not None:
        findings = FindingsResult.model_validate_json(
            ctx.files.read(params.discovery.findings_path)
        )
        carried = discovery.carry_model(findings, dataset, robot)
        options = discovery.carried_options(options, carried)
    address = Settings().dask_address
    if address:
        refused = None if carried is None else discovery.streamed_refusal(carried.corrections)
        if refused is not None:
            raise ModelError(f"discovery_id: the discovery's model {refused}; {STREAMED_FIX}")
        ctx.progress("connecting", 0.02)
        with DaskExecutor(address) as executor:
            result = pipeline.calibrate_streamed(
                path,
                robot,
                options,
                executor,
                progress=_streamed_progress(ctx),
                source=params.dataset.name,
            )
    else:
        ctx.progress("fit", 0.05)
        progress = _progress(ctx, options.heldout)
        if carried is None:
            result = pipeline.calibrate(dataset, robot, options, progress)
        else:
            result = discovery.calibrate_carried(carried, robot, options, progress)
            dataset = carried.dataset  # what the calibration fitted (the report's residuals)
    ctx.progress("report", REPORT_FRACTION)
    ctx.write_artifact("result", "result.json", result.model_dump_json(indent=1).encode())
    if urdf_refusal(result.model_corrections) is None:
        ctx.write_artifact("urdf", "calibrated.urdf", export_urdf(result).encode())
    ctx.write_artifact("report", "report.html", render_report(result, dataset).encode())


STREAMED_FIX = (
    "this service streams its calibrations on the Dask cluster of KINCAL_DASK_ADDRESS: "
    "calibrate without discovery_id, or on a service without that setting"
)


DISCOVERY_FRACTION = 0.1
DISCOVERY_REPORT_FRACTION = 0.9


def discovery_job(ctx: JobContext) -> None:
    """Look for missing physics in a stored dataset; artifacts: findings JSON, HTML report
    (with each finding's before/after residual plot)."""
    ctx.progress("loading", 0.0)
    params = DiscoveryJobParams.model_validate(ctx.params)
    robot = robot_description(params.robot, ctx.files)
    chain = discovery.chain_for(robot, params.options)
    dataset = read_dataset(
        ctx.files.path(params.dataset.data_path),
        chain.joint_names,
        other_joint_names=chain.other_joint_names,
        source=params.dataset.name,
    )
    ctx.progress("discover", DISCOVERY_FRACTION)
    with tempfile.TemporaryDirectory(prefix="kincal-discovery-") as folder:
        plot_dir = Path(folder)
        findings = discovery.discover(dataset, robot, params.options, plot_dir, "finding")
        ctx.progress("report", DISCOVERY_REPORT_FRACTION)
        plots = {name: (plot_dir / name).read_bytes() for name in findings.plots}
    ctx.write_artifact("result", "findings.json", findings.model_dump_json(indent=1).encode())
    ctx.write_artifact("report", "report.html", render_discovery_report(findings, plots).encode())
