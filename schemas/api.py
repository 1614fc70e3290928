"""Request and response bodies of the HTTP API (``/api/v1``), one family per resource.

``*Create``: what a client sends; ``*Public``: what it gets back; ``*sPublic``: a page of a list.
Errors are :class:`Problem` documents (RFC 9457, ``application/problem+json``).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterator
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.calibration import CalibrationOptions, Verdict
from schemas.check import CheckOptions, CheckResult
from schemas.discovery import DiscoveryOptions
from schemas.limits import MAX_JOINT_POSITION, MAX_PAYLOAD_KG
from schemas.ranking import RankingOptions, TargetPose

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


OptionsT = TypeVar("OptionsT", bound=BaseModel)


def _non_finite(value: Any, path: str) -> Iterator[str]:
    if isinstance(value, float) and not math.isfinite(value):
        yield f"{path} is {value}"
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _non_finite(item, f"{path}.{key}")
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            yield from _non_finite(item, f"{path}.{i}")


def require_finite(options: OptionsT) -> OptionsT:
    """Options models of other modules accept NaN/inf (Python's JSON reads ``NaN``); a job
    must not start with them, so the request is refused naming the field."""
    bad = list(_non_finite(options.model_dump(), "options"))
    if bad:
        raise ValueError(f"{bad[0]}; every number must be finite")
    return options


class ProblemFieldError(BaseModel):
    location: str = Field(description="Where: e.g. 'body.options.max_iterations'.")
    pointer: str | None = Field(None, description="JSON pointer into the request body.")
    detail: str


class Problem(BaseModel):
    """RFC 9457 problem details. ``detail`` names the offending field and how to fix it."""

    model_config = ConfigDict(extra="allow")

    type: str = Field("about:blank", description="URI identifying the problem type.")
    title: str
    status: int
    detail: str | None = None
    instance: str | None = Field(None, description="The request path.")
    request_id: str | None = None
    errors: list[ProblemFieldError] | None = None


class Page(BaseModel):
    count: int = Field(description="Total number of items (all pages).")
    offset: int
    limit: int


# --- robots ------------------------------------------------------------------------------------


class RobotCreate(_In):
    """A URDF to upload, and the chain (base -> tip frames) to calibrate in it."""

    name: str = Field(pattern=NAME_PATTERN, description="Short name shown in results.")
    base_frame: str = Field(min_length=1, max_length=200)
    tip_frame: str = Field(min_length=1, max_length=200)
    urdf: str = Field(min_length=1, description="The URDF XML text (size-limited).")


class RobotPublic(BaseModel):
    id: str = Field(description="Built-in robot name, or the id of an uploaded URDF.")
    name: str
    builtin: bool
    base_frame: str
    tip_frame: str
    joint_names: list[str]
    urdf_sha256: str
    created_at: dt.datetime | None = None


class RobotsPublic(BaseModel):
    data: list[RobotPublic]
    count: int


# --- datasets ----------------------------------------------------------------------------------


class DatasetCreate(_In):
    """A dataset as JSON rows (same columns as the CSV contract of DESIGN.md §3)."""

    robot: str = Field(description="Built-in robot name or uploaded robot id.")
    base_frame: str | None = Field(None, description="Override the robot's base frame.")
    tip_frame: str | None = Field(None, description="Override the robot's tip frame.")
    name: str = Field("rows.json", min_length=1, max_length=200)
    rows: list[dict[str, Any]] = Field(
        min_length=1,
        description="One object per measurement: joint columns, x,y,z[,qx,qy,qz,qw], optional "
        "sample_id, t, temperature_c, payload_kg.",
    )


class DatasetPublic(BaseModel):
    id: str
    name: str
    robot: str
    robot_id: str | None = Field(description="Set when the robot is an uploaded URDF.")
    base_frame: str
    tip_frame: str
    joint_names: list[str]
    n_samples: int
    measures_rotation: bool = Field(
        description="Whether the rows hold the marker's orientation (qx, qy, qz, qw) as well as "
        "its position; false: a position-only recording."
    )
    time_start_s: float | None
    time_end_s: float | None
    content_sha256: str = Field(description="SHA-256 of the robot reference and the data.")
    size_bytes: int
    created_at: dt.datetime


class DatasetsPublic(Page):
    data: list[DatasetPublic]


# --- jobs and calibrations ---------------------------------------------------------------------


class JobStatus(BaseModel):
    state: JobState
    stage: str | None = Field(None, description="What the job is doing now.")
    fraction: float = Field(ge=0.0, le=1.0, description="Overall progress.")
    iteration: int | None = Field(None, description="Step within the stage.")
    attempts: int = Field(description="Times a worker started it (>1 after a crash/restart).")
    cancel_requested: bool
    error: str | None = Field(None, description="Why it failed (one line).")
    created_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None


class CalibrationCreate(_In):
    dataset_id: str = Field(min_length=1, max_length=64)
    options: CalibrationOptions = Field(default_factory=CalibrationOptions)
    discovery_id: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        description="A succeeded discovery (POST /api/v1/discoveries) of the dataset's robot "
        "whose findings the calibration carries, as `kincal calibrate --model`: its compliance, "
        "flex axes, gravity and payload replace those options (leave them at their defaults); "
        "its other named terms are undone on the recording and recorded in the result "
        "(`model_corrections`).",
    )

    @field_validator("options")
    @classmethod
    def _finite(cls, options: CalibrationOptions) -> CalibrationOptions:
        return require_finite(options)


class CalibrationLinks(BaseModel):
    self: str
    result: str
    report: str
    urdf: str
    cancel: str


class CalibrationPublic(BaseModel):
    id: str
    dataset_id: str | None
    discovery_id: str | None = Field(
        None, description="The discovery whose findings the calibration carries, if any."
    )
    status: JobStatus
    verdict: Verdict | None = Field(
        None,
        description="Once succeeded: whether the calibration is fit to use (ok, warning or "
        "failed, each reason with its cause and fix; the result's verdict). A failed one has "
        "no URDF unless asked for with GET .../urdf?force=true.",
    )
    options: CalibrationOptions
    links: CalibrationLinks


class CalibrationsPublic(Page):
    data: list[CalibrationPublic]


# --- rankings ----------------------------------------------------------------------------------

MAX_IK_CANDIDATES = 64
JointPosition = Annotated[
    float,
    Field(ge=-MAX_JOINT_POSITION, le=MAX_JOINT_POSITION, allow_inf_nan=False),
]
PayloadKg = Annotated[float, Field(ge=0.0, le=MAX_PAYLOAD_KG, allow_inf_nan=False)]


class RankingCreate(_In):
    """Rank candidates for a task by a succeeded calibration's predicted end-effector
    uncertainty (paper Eq. 22–23; lower score is better). Give exactly one of
    ``joint_positions_rad`` (rows in chain order), ``configurations`` (objects keyed by joint
    name) or ``target`` (a pose whose inverse-kinematics solutions are found and ranked)."""

    calibration_id: str = Field(min_length=1, max_length=64)
    joint_positions_rad: list[list[JointPosition]] | None = Field(
        None,
        min_length=1,
        description="Candidate configurations, rad (m for prismatic joints), joints in chain "
        "order.",
    )
    configurations: list[dict[str, JointPosition]] | None = Field(
        None, min_length=1, description="Candidate configurations as {joint name: rad}."
    )
    target: TargetPose | None = Field(
        None, description="End-effector pose in the calibration's measurement frame."
    )
    n_candidates: int = Field(
        16,
        ge=1,
        le=MAX_IK_CANDIDATES,
        description="Target only: distinct IK solutions wanted (8 restarts each); the search "
        "runs in the request, hence the limit.",
    )
    seed: int = Field(0, ge=0, description="Target only: seed of the IK restarts.")
    free_axis: Literal["auto", "x", "y", "z", "none"] = Field(
        "auto", description="Target only: end-effector axis the task lets the target turn about."
    )
    n_free_rotations: int = Field(12, ge=1, le=360, description="Target only.")
    payload_kg: PayloadKg | list[PayloadKg] | None = Field(
        None,
        description="Payload (one value, or one per configuration); default: the "
        "calibration's payload option.",
    )
    options: RankingOptions = Field(default_factory=RankingOptions)

    @model_validator(mode="after")
    def _one_kind_of_candidates(self) -> RankingCreate:
        given = [
            name
            for name in ("joint_positions_rad", "configurations", "target")
            if getattr(self, name) is not None
        ]
        if len(given) != 1:
            raise ValueError(
                "give exactly one of joint_positions_rad, configurations or target"
                + (f" (got {', '.join(given)})" if given else "")
            )
        if isinstance(self.payload_kg, list) and self.target is not None:
            raise ValueError("payload_kg: a target ranking takes one payload value, not a list")
        return self


# --- discoveries -------------------------------------------------------------------------------


class DiscoveryCreate(_In):
    """Look for the physics a dataset shows and the model in ``options`` lacks
    (``kincal discover``)."""

    dataset_id: str = Field(min_length=1, max_length=64)
    options: DiscoveryOptions = Field(default_factory=DiscoveryOptions)

    @field_validator("options")
    @classmethod
    def _finite(cls, options: DiscoveryOptions) -> DiscoveryOptions:
        return require_finite(options)


class DiscoveryLinks(BaseModel):
    self: str
    result: str
    report: str
    cancel: str


class DiscoveryPublic(BaseModel):
    id: str
    dataset_id: str | None
    status: JobStatus
    options: DiscoveryOptions
    links: DiscoveryLinks


class DiscoveriesPublic(Page):
    data: list[DiscoveryPublic]


# --- checks ------------------------------------------------------------------------------------


class CheckCreate(_In):
    """Test a succeeded calibration against new poses: an uploaded dataset of the calibrated
    robot, recorded in the same frames and of the same measurement type (``kincal check``)."""

    dataset_id: str = Field(min_length=1, max_length=64)
    options: CheckOptions = Field(default_factory=CheckOptions)


class CheckLinks(BaseModel):
    self: str
    calibration: str
    dataset: str


class CheckSummary(BaseModel):
    """A check as listed: when, on which dataset, its verdict and global test."""

    id: str
    calibration_id: str
    dataset_id: str = Field(description="The dataset checked (it may have been deleted since).")
    dataset_name: str
    created_at: dt.datetime
    level: float
    n_poses: int
    verdict: Literal["holds", "drifted", "inconclusive"]
    statistic: float | None = Field(
        description="Σ d² of the global test (null: too few poses for a test)."
    )
    threshold: float | None = Field(description="Its limit at the level (null with it).")
    located: str | None = Field(description="The located change of a drift, if any.")
    links: CheckLinks


class CheckPublic(CheckSummary):
    """A check with its document (the ``kincal check -o`` JSON)."""

    check: CheckResult


class ChecksPublic(Page):
    data: list[CheckSummary]


# --- health ------------------------------------------------------------------------------------


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    status: Literal["ready", "not ready"]
    checks: dict[str, bool]
    workers_alive: int
    workers_configured: int
