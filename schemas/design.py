"""Calibration designs: which poses to record (``"format": "kincal.design/1"``).

``kincal design`` and ``POST /api/v1/designs`` share these models; the maths lives in
:mod:`solver.design`. Positions are of the chain's tip frame in the robot's base frame, metres;
joint positions in chain order, rad (m for prismatic joints).
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.api import JobStatus
from schemas.calibration import CalibrationOptions, Vector3, known_measurement
from schemas.check import StatedSize
from schemas.ranking import CalibrationReference

DESIGN_FORMAT: Literal["kincal.design/1"] = "kincal.design/1"
CHECK_DESIGN_FORMAT: Literal["kincal.check-design/1"] = "kincal.check-design/1"
DEFAULT_NOISE_MM = 0.05
DEFAULT_NOISE_DEG = 0.003


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class BoxVolume(_Model):
    """The tip inside an axis-aligned box of the base frame."""

    low_m: Vector3 = Field(description="Lower corner x, y, z, m.")
    high_m: Vector3 = Field(description="Upper corner x, y, z, m.")

    @model_validator(mode="after")
    def _ordered(self) -> BoxVolume:
        if not all(lo < hi for lo, hi in zip(self.low_m, self.high_m, strict=True)):
            raise ValueError("box: every low_m coordinate must be below high_m's")
        return self


class ConeVolume(_Model):
    """A sensor's view cone: the tip seen from ``apex_m`` along ``axis`` (base frame)."""

    apex_m: Vector3 = Field(description="Sensor position x, y, z, m (base frame).")
    axis: Vector3 = Field(description="Line of sight, any length (base frame).")
    half_angle_deg: float = Field(gt=0.0, le=90.0, description="Half opening angle, deg.")
    near_m: float = Field(0.0, ge=0.0, description="Nearest distance seen, m.")
    far_m: float = Field(10.0, gt=0.0, description="Farthest distance seen, m.")
    max_incidence_deg: float | None = Field(
        None,
        gt=0.0,
        le=180.0,
        description="Largest angle between the marker axis and the direction back to the "
        "sensor (a planar target is seen from the front); null: any orientation.",
    )
    marker_axis: Vector3 = Field((0.0, 0.0, 1.0), description="Marker normal in the tip frame.")

    @model_validator(mode="after")
    def _valid(self) -> ConeVolume:
        if math.hypot(*self.axis) == 0.0:
            raise ValueError("cone.axis must not be zero")
        if math.hypot(*self.marker_axis) == 0.0:
            raise ValueError("cone.marker_axis must not be zero")
        if self.far_m <= self.near_m:
            raise ValueError("cone.far_m must exceed cone.near_m")
        return self


class DesignOptions(_Model):
    """What to design: how many poses, by which criterion, for which stage, where."""

    n_poses: int = Field(25, ge=1, le=2000, description="Poses to choose (K).")
    criterion: Literal["D", "A", "E", "I"] = Field(
        "D",
        description="D: log det of the information (default); A: mean parameter variance; "
        "E: worst-determined direction; I: parameter part of the predicted pose variance over "
        "the task configurations (default: the working volume).",
    )
    stage: Literal["geometry", "covariance", "both"] = Field(
        "geometry",
        description="Information about geometry and compliance (Eq. 8–10), about the "
        "covariances (Eq. 12–17), or both (D: sum of both stages' log det per dimension).",
    )
    measurement: str = Field(
        "pose",
        description="What each recorded row will measure, as the calibration's measurement "
        "option names it (docs/measurements.md): 'pose', 'position', 'components:tz,rx,ry' "
        "(chosen pose components, e.g. a plane contact), 'point' (ball in socket: candidates "
        "must be recorded socket configurations), 'markers' (several markers at once: "
        "marker_offsets_m), 'relative-base' (position of the tip marker in the frame of a "
        "marker on the base) or 'eye-on-head:<joint>' (full pose seen by a sensor after that "
        "joint). The measurement's own unknowns (sockets, marker offsets) are profiled out.",
    )
    marker_offsets_m: list[Vector3] | None = Field(
        None,
        min_length=2,
        max_length=50,
        description="Measurement 'markers': each marker's expected offset from the tip frame "
        "(in the tip frame), x, y, z m; the design's information depends on them.",
    )
    n_candidates: int = Field(
        2000, ge=1, le=100_000, description="Candidates drawn when none are given."
    )
    seed: int = Field(0, ge=0, description="Random seed of the drawn candidates.")
    box: BoxVolume | None = Field(None, description="Workspace box the tip must be in.")
    cone: ConeVolume | None = Field(None, description="Sensor view cone the tip must be in.")
    min_spacing_rad: float = Field(
        0.0, ge=0.0, description="Least joint-space distance (Euclidean, rad) between poses."
    )
    noise_mm: float = Field(DEFAULT_NOISE_MM, gt=0.0, description="Sensor noise σ per axis, mm.")
    noise_deg: float = Field(
        DEFAULT_NOISE_DEG, gt=0.0, description="Sensor rotation noise σ per axis, deg."
    )
    prior_perturbation_deg: float = Field(
        0.05,
        gt=0.0,
        description="Covariance stage: assumed σ of each joint frame's rotational perturbation, "
        "deg (the information depends on it; a result's covariances replace it).",
    )
    method: Literal["auto", "clarabel", "first_order"] = Field(
        "auto",
        description="Relaxation solver: Clarabel (small sets, and E), the first-order method "
        "(large sets), or auto.",
    )
    allow_repeats: bool = Field(
        False, description="Allow a pose more than once (weights up to 1 instead of 1/K)."
    )
    calibration: CalibrationOptions = Field(
        default_factory=CalibrationOptions,
        description="The calibration the poses are for (its compliance, flex axes, gravity, "
        "payload, rank tolerance and covariance frames decide the identifiable parameters).",
    )

    @model_validator(mode="before")
    @classmethod
    def _calibration_measurement(cls, data: object) -> object:
        """Without ``measurement``, the calibration options' own (a ``kincal calibrate``
        config reused for the design) when it names one."""
        if not isinstance(data, dict) or "measurement" in data:
            return data
        calibration = data.get("calibration")
        planned = (
            calibration.get("measurement")
            if isinstance(calibration, dict)
            else getattr(calibration, "measurement", None)
        )
        if isinstance(planned, str) and planned != "auto":
            return {**data, "measurement": planned}
        return data

    @field_validator("measurement")
    @classmethod
    def _measurement_known(cls, value: str) -> str:
        if value == "auto":
            raise ValueError(
                "a design plans one measurement type: choose pose, position, point, markers, "
                "relative-base, components:<subset of tx,ty,tz,rx,ry,rz> or eye-on-head:<joint>"
            )
        return known_measurement(value)

    @property
    def measurement_kind(self) -> str:
        """The measurement type without its argument ('components', 'eye-on-head', ...)."""
        return self.measurement.partition(":")[0]

    @model_validator(mode="after")
    def _measurement_combination(self) -> DesignOptions:
        kind = self.measurement_kind
        if kind not in ("pose", "position") and self.stage != "geometry":
            raise ValueError(
                f"measurement {kind!r}: stage {self.stage!r} is designed for pose and "
                "position recordings only; use stage 'geometry'"
            )
        if kind == "markers" and self.marker_offsets_m is None:
            raise ValueError(
                "measurement 'markers' needs marker_offsets_m: each marker's expected offset "
                "from the tip frame, x,y,z m (at least 2 markers)"
            )
        if kind != "markers" and self.marker_offsets_m is not None:
            raise ValueError("marker_offsets_m is for measurement 'markers'; leave it out")
        planned = self.calibration.measurement
        streamed = ("pose", "position")
        if planned not in ("auto", self.measurement) and (
            kind not in streamed or planned.partition(":")[0] not in streamed
        ):
            raise ValueError(
                f"calibration.measurement {planned!r} differs from measurement "
                f"{self.measurement!r}; leave the calibration's measurement out (or 'auto')"
            )
        if self.calibration.point_distance_m is not None and kind != "point":
            raise ValueError(
                "calibration.point_distance_m is for measurement 'point'; leave it out"
            )
        return self

    @model_validator(mode="after")
    def _combination(self) -> DesignOptions:
        if self.stage != "geometry" and self.criterion == "I":
            raise ValueError("criterion I (task variance) is for stage 'geometry'")
        if self.stage == "both" and self.criterion != "D":
            raise ValueError("stage 'both' uses criterion D")
        if self.criterion == "E" and self.method == "first_order":
            raise ValueError("criterion E is not differentiable: use method 'clarabel' or 'auto'")
        return self


class DesignPose(_Model):
    candidate: int = Field(description="Index in the candidate set.")
    joint_positions: list[float] = Field(description="Chain order, rad (m if prismatic).")
    tip_position_m: Vector3 = Field(description="Nominal tip position, base frame, m.")


class ParameterError(_Model):
    name: str
    standard_error: float = Field(description="Predicted σ, in the parameter's unit.")
    unit: str
    relative_to_noise: float = Field(
        description="σ times the parameter's root-mean-square effect on a measurement, in "
        "units of the sensor noise: comparable across parameters."
    )


class CriterionReport(_Model):
    name: str
    value: float = Field(description="Criterion of the chosen poses (maximised).")
    relaxation_value: float
    upper_bound: float = Field(
        description="Certified bound: no set of poses from these candidates does better."
    )
    efficiency: float = Field(description="Chosen poses against the bound, 1 = optimal.")
    method: str
    status: str
    iterations: int
    elapsed_s: float
    rounding: str


class CovarianceDesignReport(_Model):
    """Identifiability of the covariance statistics the chosen poses give (as the result
    JSON reports it after calibration) and with all candidates."""

    n_entries: int
    rank: int
    candidate_rank: int
    condition_number: float
    unidentifiable: list[str]


class MeasurementDesignReport(_Model):
    """What the design's rows measure (a type other than pose or position) and the
    measurement's own unknowns, profiled out of the predicted standard errors."""

    type: str = Field(description="The measurement option.")
    frame: str = Field(description="Frame of the residual of one row.")
    components: list[str] = Field(description="Components of one row's residual.")
    nuisance_parameters: list[str] = Field(
        description="The measurement's own unknowns the calibration fits too (socket points, "
        "marker offsets): profiled out of the information (Schur complement), so "
        "``parameters`` are the chain's standard errors with them unknown."
    )
    sockets: list[str] = Field(
        default_factory=list, description="Measurement 'point': the sockets of the candidates."
    )
    known_distances: int = Field(
        0, description="Measurement 'point': known socket distances (prior equations)."
    )


class SequentialReport(_Model):
    recorded_poses: int
    unidentifiable_before: list[str] = Field(
        description="Parameters the recording alone cannot identify."
    )
    mean_pose_variance_before_m2: float | None = Field(
        description="The recording's own parameter part of the pose variance (null when it "
        "leaves parameters unidentified)."
    )


class DesignResult(_Model):
    format: Literal["kincal.design/1"] = DESIGN_FORMAT
    kincal_version: str
    robot: str
    urdf_sha256: str
    joint_names: list[str]
    options: DesignOptions
    candidates: int
    candidate_source: Literal["sampled", "given"]
    poses: list[DesignPose]
    criterion: CriterionReport
    parameters: list[ParameterError] = Field(
        description="Geometry/compliance parameters the calibration identifies, with their "
        "predicted standard errors for the chosen poses."
    )
    worst_relative_standard_error: float
    mean_pose_variance_m2: float = Field(
        description="Parameter part of the predicted pose variance (trace, 1 m = 1 rad) averaged "
        "over the task configurations; the sensor noise comes on top."
    )
    task_configurations: int
    covariance: CovarianceDesignReport | None = None
    sequential: SequentialReport | None = None
    measurement: MeasurementDesignReport | None = Field(
        None, description="Measurement types other than pose and position."
    )
    notes: list[str] = Field(default_factory=list)


class DesignedSize(StatedSize):
    """A stated size of designed check poses, with the scale the design measures it in."""

    scale: float | None = Field(
        description="The change's worst-direction standard error were every candidate a check "
        "pose (null: no candidate sees it), in ``unit``."
    )
    relative: float | None = Field(description="size / scale (null: either is null).")


class CheckDesign(_Model):
    """Check poses chosen for a calibration (``kincal design --check K -o``): the K candidates
    at which ``kincal check`` states the smallest changes, and the sizes it states there."""

    format: Literal["kincal.check-design/1"] = CHECK_DESIGN_FORMAT
    kincal_version: str
    calibration: CalibrationReference
    joint_names: list[str]
    candidates: int = Field(description="Candidate configurations chosen from.")
    candidate_source: Literal["sampled", "given"]
    level: float = Field(description="The check's family-wise false-alarm probability.")
    power: float
    criterion: str = Field(description="What the poses minimise, in words.")
    worst_relative_size: float = Field(
        description="The criterion: the largest detectable size over its scale."
    )
    random_worst_relative_size: float = Field(
        description="The criterion's median over random sets of as many candidates."
    )
    random_draws: int
    poses: list[DesignPose] = Field(
        description="The chosen poses; ``candidate`` is the row of the given candidates "
        "(0-based) or the number of the drawn one."
    )
    stated_sizes: list[DesignedSize] = Field(
        description="What kincal check states at these poses (no pose set aside)."
    )
    notes: list[str] = []


class DesignCreate(_Model):
    """``POST /api/v1/designs``: a robot, the options, and optionally the candidates and the
    task configurations (each a list of joint vectors in chain order, rad). With
    ``calibration_id`` a sequential design: the next poses given a succeeded calibration and
    its dataset (``kincal design --result --recording``), whose robot and options it uses."""

    robot: str | None = Field(
        None,
        description="Built-in robot name or uploaded robot id (required unless calibration_id "
        "is given; left out with calibration_id).",
    )
    calibration_id: str | None = Field(
        None,
        max_length=40,
        description="Sequential design: a succeeded calibration; its dataset is the recording "
        "already made, its result the calibrated chain, noise and covariances; the chosen poses "
        "add to the recording's information.",
    )
    base_frame: str | None = Field(None, max_length=200)
    tip_frame: str | None = Field(None, max_length=200)
    options: DesignOptions = Field(default_factory=DesignOptions)
    candidates_rad: list[list[float]] | None = Field(
        None, min_length=1, max_length=100_000, description="Candidate configurations."
    )
    task_rad: list[list[float]] | None = Field(
        None, min_length=1, max_length=10_000, description="Task configurations (criterion I)."
    )
    candidate_sockets: list[int] | None = Field(
        None,
        min_length=1,
        max_length=100_000,
        description="Measurement 'point': the socket (0, 1, ...) each of candidates_rad was "
        "recorded in (ball-in-socket rows need a physical contact).",
    )

    @model_validator(mode="after")
    def _sockets(self) -> DesignCreate:
        point = self.options.measurement_kind == "point"
        if point and (self.candidates_rad is None or self.candidate_sockets is None):
            missing = "candidates_rad" if self.candidates_rad is None else "candidate_sockets"
            raise ValueError(
                f"{missing}: measurement 'point' needs recorded socket configurations "
                "(candidates_rad) and the socket of each (candidate_sockets): ball-in-socket "
                "rows need a physical contact, so candidates cannot be sampled"
            )
        if not point and self.candidate_sockets is not None:
            raise ValueError("candidate_sockets is for measurement 'point'; leave it out")
        if point and self.options.calibration.point_distance_m is not None:
            raise ValueError(
                "options.calibration.point_distance_m: known socket distances pair the "
                "hole_0/hole_1 files of a platonics folder; use kincal design --candidates "
                "FOLDER --point-distance, or leave it out here"
            )
        if (
            self.candidates_rad is not None
            and self.candidate_sockets is not None
            and len(self.candidate_sockets) != len(self.candidates_rad)
        ):
            raise ValueError(
                f"candidate_sockets: {len(self.candidate_sockets)} sockets for "
                f"{len(self.candidates_rad)} candidates_rad; give one per candidate"
            )
        return self


class DesignLinks(_Model):
    self: str
    result: str
    cancel: str


class DesignJobPublic(BaseModel):
    """A design run as a job (large candidate sets)."""

    id: str
    status: JobStatus
    links: DesignLinks


class DesignJobsPublic(BaseModel):
    data: list[DesignJobPublic]
    count: int
    offset: int
    limit: int
