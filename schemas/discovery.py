"""Missing-physics discovery: request options and the findings JSON (``kincal.findings/1``).

``findings[]`` are named effects from the fixed vocabulary :data:`EFFECTS`, each with its
parameters (SI units in the names), standard errors, p-value, the share of its signature the
rest of the model could reproduce and a one-sentence explanation; ``ambiguous[]`` are effects
the data cannot attribute (with poses that would separate them); ``unexplained[]`` is structure
no library term describes; ``random_effects[]`` go to the covariance calibration;
``heldout`` compares the user's model and the discovered one on the same K-fold splits;
``detectability`` states, per library term left out of the model, the smallest size the
recording would have detected, so "nothing found" reads "nothing larger than this".
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from schemas.calibration import CalibrationOptions, DatasetInfo, known_measurement
from solver.discovery.effects import EFFECTS, Effect

FINDINGS_FORMAT: Literal["kincal.findings/1"] = "kincal.findings/1"

Vector3 = tuple[float, float, float]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DiscoveryOptions(_Model):
    """What ``kincal discover`` (and the HTTP service) can be told.

    The user's model is the rigid geometry plus the declared ``compliant_joints`` and
    ``virtual_axes_at``; the measurement frame and the tool are always estimated.
    """

    compliant_joints: list[str] = Field(
        default_factory=list,
        description="Joints the user's model already treats as elastic (default: none).",
    )
    virtual_axes_at: list[str] = Field(
        default_factory=list, description="Joints with declared virtual flex axes."
    )
    gravity_base_m_s2: Vector3 = (0.0, 0.0, -9.81)
    payload_kg: float = Field(0.0, ge=0.0, description="Used when the data has no payload_kg.")
    payload_com_m: Vector3 = (0.0, 0.0, 0.0)
    alpha: float = Field(0.01, gt=0.0, lt=0.5, description="Family-wise error rate per step.")
    seed: int = Field(0, ge=0, description="Folds, bootstrap and pose pool.")
    max_terms: int = Field(6, ge=0, le=20)
    effects: list[Effect] = Field(
        default_factory=lambda: list(EFFECTS), description="Library effects to search."
    )
    folds: int = Field(5, ge=2, le=20, description="K of the K-fold held-out check.")
    bootstrap: int = Field(50, ge=0, le=1000, description="Bootstrap replicates (stability).")
    heldout_level: float = Field(
        0.05, gt=0.0, lt=1.0, description="Paired one-sided test a held-out gain must pass."
    )
    outlier_level: float | None = Field(
        1e-3, gt=0.0, lt=1.0, description="Gross-outlier screening level (None: keep all)."
    )
    detectability: bool = Field(
        True,
        description="State the smallest detectable size of every library term left out (a "
        "report only: the findings do not depend on it; false saves most of a small run).",
    )
    sensor_sigma_mm: float | None = Field(None, gt=0.0, description="Sensor noise, for χ²/dof.")
    sensor_sigma_deg: float | None = Field(None, gt=0.0)
    measurement: str = CalibrationOptions.model_fields["measurement"]  # type: ignore[assignment]
    point_distance_m: float | None = CalibrationOptions.model_fields[  # type: ignore[assignment]
        "point_distance_m"
    ]

    @field_validator("measurement")
    @classmethod
    def _measurement_known(cls, value: str) -> str:
        return known_measurement(value)


class NotCandidate(_Model):
    """A library term left out because the measurement cannot see it (decided by its columns)."""

    effect: Effect
    joint: str | None
    variant: str
    description: str
    remaining_fraction: float = Field(
        description="The largest fraction of one of its columns left once the model's own "
        "columns (geometry, sensor mount, sockets, marker offsets) are fitted, relative to the "
        "column a sensor fixed in the measurement frame would see: rounding (≤ 1e-9)."
    )
    reason: str


class DiscoveryMeasurement(_Model):
    """What the rows measure when they are not the marker's pose or position (issue 15)."""

    type: str = Field(description="ball in socket 'point', 'markers', 'components:…', ….")
    frame: str = Field(description="The frame the residuals are in.")
    components: list[str] = Field(description="Name of each residual row of a sample.")
    labels: list[str] = Field(default_factory=list, description="Sockets or markers.")
    unknowns: dict[str, float] = Field(
        default_factory=dict,
        description="The measurement's own unknowns in the final model (socket points, marker "
        "offsets), m, fitted with the geometry as nuisance parameters.",
    )
    constraint_residuals_m: list[float] = Field(
        default_factory=list, description="Known socket distances minus fitted ones, m."
    )
    left_out: list[str] = Field(
        default_factory=list,
        description="Library effects this measurement cannot see, each with the reason.",
    )
    not_candidates: list[NotCandidate] = Field(
        default_factory=list,
        description="Library terms whose effect on what is measured cancels (e.g. every term "
        "at or before the joint carrying an eye-on-head sensor): not tested, no detectable "
        "size.",
    )


class ErrorPair(_Model):
    trans_mm: float
    rot_deg: float | None


class Heldout(_Model):
    before: ErrorPair
    after: ErrorPair
    protocol: str = ""


class Candidate(_Model):
    """One possible explanation with its (one-step) estimate."""

    effect: Effect
    joint: str | None
    variant: str
    parameters: dict[str, float]
    stderr: dict[str, float]
    p_value: float
    absorbed_fraction: float


class Finding(_Model):
    """A named effect: significant, confirmed by held-out error, not ambiguous."""

    effect: Effect
    joint: str | None = Field(description="URDF joint name; None for whole-robot effects.")
    variant: str = Field(description="e.g. h2 (harmonic), load / direction (backlash).")
    parameters: dict[str, float] = Field(description="Final-model values, SI units in names.")
    stderr: dict[str, float]
    p_value: float = Field(description="Score test when the term entered (both statistics).")
    absorbed_fraction: float = Field(
        description="Share of the term's signature the rest of the model could reproduce."
    )
    stability: float | None = Field(
        description="Share of bootstrap replicates in which it was the best candidate."
    )
    heldout: Heldout = Field(description="K-fold held-out error without and with the term.")
    explanation: str
    plot: str | None = Field(None, description="PNG next to the JSON: residuals before/after.")


class Ambiguity(_Model):
    candidates: list[Candidate]
    with_geometry: bool = Field(description="The other explanation is the geometry itself.")
    correlation: float
    kept_in_model: str | None
    separating_poses: list[dict[str, float]] = Field(
        default_factory=list, description="Joint positions (rad) that would separate them."
    )
    separation_now_sigma: float | None = None
    separation_after_sigma: float | None = None
    explanation: str


class Unexplained(_Model):
    joint: str | None
    variable: str = Field(
        description="angle, load, components, time, range; declared: a declared term that "
        "fits with an unphysical sign."
    )
    p_value: float | None
    explained_fraction: float | None
    distance_correlation: float | None
    partially_described_by: list[str]
    explanation: str


class RandomEffect(_Model):
    joint: str
    p_value: float
    variance_ratio: float
    explanation: str
    recommendation: str = "kincal calibrate with covariance estimation (random effects)"


class Dependence(_Model):
    variable: str
    joint: str | None
    p_value: float
    explained_fraction: float
    components: dict[str, float]


class Health(_Model):
    n_samples: int
    n_parameters: int
    sigma_translation_mm: float
    sigma_rotation_deg: float | None
    rms_translation_mm: float
    rms_rotation_deg: float | None
    chi2_per_dof: float | None
    dependences: list[Dependence]


class HealthPair(_Model):
    before: Health
    after: Health


class Step(_Model):
    step: int
    candidate: str
    action: Literal[
        "accepted", "ambiguous", "rejected_heldout", "rejected_sign", "unexplained", "pruned"
    ] = Field(
        description="rejected_sign: a compliance, flex or backlash whose refit with it added "
        "put it below zero (the next candidate is tried); pruned: one that fit below zero in "
        "the final model, removed (fixed at 0) and the model refit"
    )
    p_value: float | None
    heldout_before_mm: float | None
    heldout_after_mm: float | None


class ModelTerm(_Model):
    effect: str
    joint: str | None
    variant: str
    parameters: dict[str, float]


class DiscoveredModel(_Model):
    """The model after discovery, and what ``kincal calibrate --model`` takes of it: the
    ``calibrate_*`` options, and the ``corrections`` undone on the recording."""

    terms: list[ModelTerm]
    calibrate_compliant_joints: list[str]
    calibrate_virtual_axes_at: list[str]
    calibrate_gravity_base_m_s2: Vector3
    calibrate_payload_kg: float
    corrections: list[str] = Field(
        default_factory=list,
        description="Named terms `kincal calibrate --model` undoes on the recording at their "
        "discovered values (joint-angle terms, sensor depth scale, measurement-frame drift).",
    )
    not_carried: list[str] = Field(
        description="Terms calibrate cannot represent: unexplained structure, which has no name."
    )


class RobotRef(_Model):
    name: str
    base_frame: str
    tip_frame: str
    joint_names: list[str]
    urdf_sha256: str


class OutlierScreen(_Model):
    level: float | None
    removed_rows: list[int] = Field(description="1-based data rows left out as gross outliers.")


class DetectableSize(_Model):
    effect: Effect
    joint: str | None
    variant: str
    parameter: str = Field(
        description="The size stated, SI units in the name: backlash_rad, amplitude_rad (a "
        "gear error at any phase), flex_rad_per_nm (either axis ⟂ the joint), "
        "translation_/rotation_… (a measurement-frame drift), else the term's parameter."
    )
    smallest: float | None = Field(
        description="Smallest size this recording detects at `level` with `power` (calibrated "
        "on the recording: the effect added to it at trial sizes, both halves of the score "
        "test as run) and tells from every other library term (the joint test at the "
        "discovery's alpha with that term fitted too, see `separated_from`); null when no "
        "size is (see `reason`)."
    )
    separated_from: str | None = Field(
        None,
        description="The other library term that sets `smallest`: detecting would take less, "
        "but below `smallest` this term and that one cannot be told apart on this recording "
        "(discovery would report them ambiguous). Null when detection sets it.",
    )
    reason: str | None = Field(
        None,
        description="Why no size is stated: the model absorbs the term ('not separable from "
        "the model', e.g. a depth scale along a flange camera's axis) or no trial size was "
        "detected on this recording.",
    )


class Detectability(_Model):
    level: float = Field(
        description="Per-test level: alpha over the number of library terms tested (Holm's "
        "first step)."
    )
    power: float = Field(description="Probability that an effect of the stated size is found.")
    sizes: list[DetectableSize]


class FindingsResult(_Model):
    format: Literal["kincal.findings/1"] = FINDINGS_FORMAT
    kincal_version: str
    created_utc: str
    dataset: DatasetInfo
    robot: RobotRef
    options: DiscoveryOptions
    findings: list[Finding]
    ambiguous: list[Ambiguity]
    unexplained: list[Unexplained]
    random_effects: list[RandomEffect]
    heldout: Heldout
    health: HealthPair
    steps: list[Step]
    outliers: OutlierScreen
    model: DiscoveredModel
    n_candidates: int = Field(description="Library terms tested at the first step.")
    detectability: Detectability | None = Field(
        None,
        description="Smallest detectable size of every library term left out (null when "
        "the options turned it off).",
    )
    plots: list[str] = Field(default_factory=list, description="PNG files next to the JSON.")
    measurement: DiscoveryMeasurement | None = Field(
        None, description="The measurement of the rows when not the marker's pose/position."
    )
    elapsed_s: float
