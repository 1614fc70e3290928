"""The parameters of the service's jobs as the HTTP layer stores them (``jobs.params``) and
the job functions read them back (:mod:`service.app.job_functions`): references to stored
robots, datasets and results, resolved when a job is accepted. Plain pydantic models, so the
request processes import them without the pipelines the jobs run."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from schemas.calibration import CalibrationOptions
from schemas.design import DesignCreate
from schemas.discovery import DiscoveryOptions


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


class RecordedRef(BaseModel):
    """A sequential design's prior in the service: a succeeded calibration's result file and
    the dataset it calibrated."""

    model_config = ConfigDict(extra="forbid")

    calibration_id: str
    result_path: str
    dataset: DatasetRef


class DesignJobParams(BaseModel):
    """``jobs.params`` of a design: the robot resolved when the job was accepted (none for a
    sequential design: the calibration's), the recording and its calibration for a
    sequential design, and the request as sent."""

    model_config = ConfigDict(extra="forbid")

    robot: RobotRef | None = None
    recorded: RecordedRef | None = None
    request: DesignCreate
