"""Calibration options and the result JSON (``"format": "kincal.calibration/1"``, DESIGN.md §3).

Units are in the field names. Matrices are row-major nested lists; the 4x4 ``placement`` /
``matrix`` fields are authoritative (full float precision), the xyz/quaternion fields are for
reading. The result embeds the URDF, so ``predict``, ``rank`` and the URDF export need nothing
else.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

RESULT_FORMAT: Literal["kincal.calibration/1"] = "kincal.calibration/1"

Vector3 = tuple[float, float, float]
Matrix4 = Annotated[list[list[float]], Field(min_length=4, max_length=4)]
Matrix6 = Annotated[list[list[float]], Field(min_length=6, max_length=6)]
Vector6 = tuple[float, float, float, float, float, float]
OptionalVector6 = tuple[
    float | None, float | None, float | None, float | None, float | None, float | None
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


def known_measurement(value: str) -> str:
    """``value`` if it names a measurement (the ``measurement`` option of calibrate and
    discover), else a ValueError listing them."""
    kind, _, argument = value.partition(":")
    plain = ("auto", "pose", "position", "point", "markers", "relative-base")
    if kind in plain and not argument:
        return value
    if kind in ("components", "eye-on-head") and argument:
        return value
    raise ValueError(
        f"unknown measurement {value!r}; choose auto, pose, position, point, markers, "
        "relative-base, components:<tx,ty,tz,rx,ry,rz subset> or eye-on-head:<joint>"
    )


class CalibrationOptions(_Model):
    """Everything a calibration run can be told: the HTTP body, the CLI flags
    (:data:`service.cli.flags.CALIBRATION_FLAGS`) and a ``--config`` TOML file share this model, so
    each field is checked here once (and against the robot by
    :func:`service.app.calibrate.check_calibration`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    compliant_joints: list[str] | None = Field(
        None, description="Joints with an elastic axis; None = every revolute joint."
    )
    virtual_axes_at: list[str] = Field(
        default_factory=list,
        description="Joints that get two virtual compliant axes orthogonal to their axis "
        "(flex of the structure carrying them, paper §V-A).",
    )
    free_parameters: list[str] = Field(
        default_factory=lambda: ["all"],
        min_length=1,
        description="What to calibrate: classes (all, geometry, joint_offsets, base, tool, "
        "compliance), links by joint or tip name, parameters <link>.<tx|ty|tz|rx|ry|rz> or "
        "compliance.<axis>, shell patterns of those; the base and tool (measurement frame and "
        "marker) are always free unless fixed (docs/calibration-options.md).",
    )
    fixed_parameters: list[str] = Field(
        default_factory=list,
        description="Parameters held at their starting value (nominal geometry, compliance 0; "
        "base and tool at the closed-form alignment), same names as free_parameters, e.g. a "
        "whole link such as torso_2_joint, or compliance.",
    )
    gravity_base_m_s2: Vector3 = Field(
        (0.0, 0.0, -9.81), description="Gravity in the robot's base frame, m/s²."
    )
    payload_kg: float = Field(0.0, ge=0.0, description="Used when the data has no payload_kg.")
    payload_com_m: Vector3 = Field(
        (0.0, 0.0, 0.0), description="Payload centre of mass in the tip frame, m."
    )
    rotation_weight_m_per_rad: float = Field(
        1.0, gt=0.0, description="How much 1 rad of rotation residual counts against 1 m."
    )
    outlier_rule: Literal["model", "sigma", "none"] = Field(
        "model",
        description="How gross errors (detector failures) are screened out: 'model' judges each "
        "sample against its own predicted covariance Σ_E(q) (Eq. 12) at the family-wise "
        "outlier_level, iterated with the fit, and keeps clean data (with covariance 'none' "
        "only its first, robust per-component step runs); 'sigma' is the paper's "
        "§V-A rule (drop a sample with a residual component beyond outlier_sigma standard "
        "deviations: ~21 % of clean 6-D samples at 2σ, so its covariances come out too "
        "small); 'none' keeps every sample. Giving only outlier_sigma selects 'sigma' "
        "(0 or null: 'none').",
    )
    outlier_level: float = Field(
        0.01,
        gt=0.0,
        lt=1.0,
        description="Model rule: probability that any clean sample of the whole recording is "
        "removed (Bonferroni over its samples).",
    )
    outlier_sigma: float | None = Field(
        2.0,
        ge=0.0,
        description="Sigma rule (paper §V-A): standard deviations a residual component may lie "
        "from its mean (0 or null: no screening).",
    )
    max_iterations: int = Field(
        50, ge=1, le=1000, description="Levenberg-Marquardt iterations at most (Eq. 10, damped)."
    )
    tolerance: float = Field(
        1e-10,
        gt=0.0,
        lt=1.0,
        description="Relative cost change at which Levenberg-Marquardt stops.",
    )
    rank_tolerance: float = Field(
        1e-7,
        gt=0.0,
        lt=1.0,
        description="A parameter is unidentifiable when its pivoted-QR diagonal, relative to "
        "the largest, falls below this.",
    )
    heldout: bool = Field(True, description="Run the 10-split held-out evaluation.")
    heldout_method: Literal["one-step", "exact"] = Field(
        "one-step",
        description="Held-out splits calibrated in one step from the calibration of all rows "
        "(about one fit's cost) or exact (each split iterated to convergence, ~4x slower). "
        "One-step: one Gauss-Newton step for geometry and compliance from the calibration of "
        "all rows over its parameters, and for the covariances the one-step estimator from the "
        "split's own moment solution refined by two scoring steps; exact: from the nominal "
        "robot, parameters chosen on the split's own rows, covariances iterated to convergence.",
    )
    seeds: list[Annotated[int, Field(ge=0)]] = Field(
        default_factory=lambda: list(range(1, 11)),
        min_length=1,
        description="Seeds of the held-out splits (non-negative integers, one split each).",
    )
    train_fraction: float = Field(
        0.9, gt=0.0, lt=1.0, description="Share of the rows each held-out split trains on."
    )
    covariance: Literal["diag", "full", "none"] = Field(
        "diag",
        description="Structure of the random-effect covariances Σ_n, Σ_1..Σ_k (paper §IV-C); "
        "'none' skips the covariance calibration.",
    )
    covariance_solver: Literal["auto", "clarabel", "pgd", "nnls"] = Field(
        "auto",
        description="Solver of the moment problem (Eq. 14): clarabel (cvxpy, PSD cones), pgd "
        "(paper Eq. 15, stable step), nnls (diagonal only, exact) or auto (nnls for diagonal, "
        "clarabel for full covariances).",
    )
    covariance_estimator: Literal["moment", "ml", "reml"] = Field(
        "reml",
        description="moment matching (paper Eq. 14), maximum likelihood (Eq. 16-17) or "
        "restricted ML, which accounts for the parameters the deterministic fit used "
        "(default: most accurate in tests/solver/test_covariance_recovery.py).",
    )
    covariance_frames: list[str] | None = Field(
        None, description="Joints whose frame carries a random perturbation; None = every joint."
    )
    covariance_axes: Literal["all", "rotation"] = Field(
        "all",
        description="Which axes of a joint frame's perturbation are random: all six, or "
        "'rotation' only (backlash, friction and bearing play rotate a joint frame; the paper "
        "found almost only rotational uncertainty in the chain, §V-B). Fewer parameters for the "
        "same residuals; the measurement noise Σ_n keeps all axes.",
    )
    noise_std: Vector6 | None = Field(
        None,
        description="Known measurement-noise standard deviations (x,y,z m; rx,ry,rz rad) in the "
        "end-effector frame; None = estimate Σ_n with the rest.",
    )
    noise_covariance: Matrix6 | None = Field(
        None,
        description="Known measurement-noise covariance Σ_n (6×6, [v; w] in the end-effector "
        "frame, m², m·rad, rad²), e.g. the sample covariance of repeated detections of a "
        "static marker (paper §V-B); symmetric positive semidefinite. Not together with "
        "noise_std; None = estimate Σ_n with the rest.",
    )

    measurement: str = Field(
        "auto",
        description="What each row measures (docs/measurements.md): 'pose' (x,y,z and "
        "quaternion), 'position' (x,y,z), 'components:tz,rx,ry' (chosen pose components in the "
        "measurement frame, e.g. a plane contact), 'point' (ball in socket: a folder of "
        "headerless hole_<k>.csv joint files, one unknown point per socket file), 'markers' "
        "(every FIGAROH marker of the file at once, each with its own offset), "
        "'relative-base' (the marker in the frame of an unknown marker on the robot base), "
        "'eye-on-head:<joint>' (the sensor rides on the body after that joint), or 'auto' "
        "(a folder of hole files: point; a FIGAROH file with several markers and no --marker: "
        "markers; otherwise pose or position by the file's columns).",
    )
    point_distance_m: float | None = Field(
        None,
        gt=0.0,
        description="Measurement 'point': known distance between the sockets hole_0 and hole_1 "
        "of each placement, m (0.05 for the platonics tool). Without it the link lengths stay "
        "the URDF's (a robot scaled about its base fits every socket as well).",
    )

    @model_validator(mode="after")
    def _solver_fits_structure(self) -> CalibrationOptions:
        if self.covariance == "full" and self.covariance_solver == "nnls":
            raise ValueError(
                "covariance_solver 'nnls' handles diagonal covariances only; use 'auto' or "
                "'clarabel' with covariance 'full'"
            )
        return self

    @field_validator("measurement")
    @classmethod
    def _measurement_known(cls, value: str) -> str:
        return known_measurement(value)

    @field_validator("outlier_sigma")
    @classmethod
    def _zero_disables(cls, value: float | None) -> float | None:
        return None if value == 0.0 else value

    @model_validator(mode="after")
    def _sigma_selects_its_rule(self) -> CalibrationOptions:
        if "outlier_sigma" in self.model_fields_set and "outlier_rule" not in self.model_fields_set:
            self.outlier_rule = "none" if self.outlier_sigma is None else "sigma"
        elif self.outlier_rule == "sigma" and self.outlier_sigma is None:
            raise ValueError("outlier_rule 'sigma' needs outlier_sigma > 0 (e.g. 2.0)")
        return self

    @property
    def screening(self) -> Literal["model", "sigma", "none"]:
        """The outlier rule in effect."""
        return (
            "none"
            if self.outlier_rule == "sigma" and self.outlier_sigma is None
            else self.outlier_rule
        )

    @field_validator("noise_std")
    @classmethod
    def _noise_std_valid(cls, value: Vector6 | None) -> Vector6 | None:
        if value is not None and not all(math.isfinite(v) and v >= 0.0 for v in value):
            raise ValueError(f"standard deviations must be finite and >= 0, got {list(value)}")
        return value

    @field_validator("noise_covariance")
    @classmethod
    def _noise_covariance_valid(
        cls, value: list[list[float]] | None, info: ValidationInfo
    ) -> list[list[float]] | None:
        if value is None:
            return None
        if info.data.get("noise_std") is not None:
            raise ValueError("give noise_std or noise_covariance, not both")
        if any(len(row) != 6 for row in value):
            raise ValueError("must be 6×6 (six rows of six numbers)")
        matrix = np.array(value, dtype=float)
        if not np.all(np.isfinite(matrix)):
            raise ValueError("entries must be finite")
        scale = max(float(np.abs(matrix).max()), np.finfo(float).tiny)
        unit = matrix / scale  # relative tolerances, and no overflow for huge entries
        if np.abs(unit - unit.T).max() > 1e-9:
            raise ValueError("must be symmetric")
        smallest = float(np.linalg.eigvalsh(unit).min())
        if smallest < -1e-9:
            raise ValueError(
                f"must be positive semidefinite (smallest eigenvalue {smallest * scale:.3g})"
            )
        return value


class Transform(_Model):
    matrix: Matrix4
    xyz_m: Vector3
    quaternion_xyzw: tuple[float, float, float, float]
    stderr_translation_m: Vector3 | None = None
    stderr_rotation_rad: Vector3 | None = None


class RobotInfo(_Model):
    name: str
    base_frame: str
    tip_frame: str
    joint_names: list[str]
    urdf_sha256: str
    urdf: str = Field(repr=False)


class BaselineFit(_Model):
    """The nominal robot with only the measurement frame and the tool fitted: the "before"."""

    measurement_frame: Transform
    tool: Transform


class LinkCalibration(_Model):
    """Calibrated placement L_i of one joint (or of the tip, last entry) in its parent frame.

    ``correction_*``: the local twist Log(L_nominal^-1 L_calibrated). For the first link and
    the tip it also contains the measurement frame / tool offset, so it is left out there
    (see ``measurement_frame`` and ``tool``).
    """

    link: str
    placement: Matrix4
    correction_translation_m: Vector3 | None
    correction_rotation_rad: Vector3 | None
    stderr_translation_m: tuple[float | None, float | None, float | None]
    stderr_rotation_rad: tuple[float | None, float | None, float | None]


class ComplianceCalibration(_Model):
    axis: str
    joint: str
    kind: Literal["joint", "virtual"]
    axis_vector: Vector3
    value_rad_per_nm: float
    stderr_rad_per_nm: float | None
    estimated: bool
    significant: bool = Field(
        description="Estimated and more than 2 standard errors from zero; otherwise the data "
        "cannot tell this compliance from none."
    )
    pruned: bool = Field(
        False,
        description="Fixed at 0 and the fit repeated: estimated negative (deflecting against "
        "the gravity torque, which no spring does) or with a standard error above 0.01 rad/N·m "
        "(not identified in any physical range).",
    )


class Identifiability(_Model):
    n_parameters: int
    rank: int
    condition_number: float
    removed: list[str] = Field(description="Parameters the data cannot identify (not fitted).")
    fixed: list[str] = Field(
        default_factory=list,
        description="Parameters held fixed by free_parameters / fixed_parameters (not fitted, "
        "no standard error).",
    )
    pruned: list[str] = Field(
        default_factory=list,
        description="Parameters fixed and the fit repeated: compliances at 0 (negative, or "
        "with a standard error beyond any physical compliance, > 0.01 rad/N·m) and inner-link "
        "twist components at their nominal value (standard error > 0.1 rad or > 0.05 m: the "
        "data do not place them in any physical range).",
    )


class ErrorStats(_Model):
    n_samples: int
    translation_mean_mm: float
    translation_rms_mm: float
    rotation_mean_deg: float | None
    rotation_rms_deg: float | None


class FitPhase(_Model):
    train: ErrorStats
    heldout: ErrorStats | None = None


class FitStatistics(_Model):
    before: FitPhase
    after: FitPhase


class HeldoutSplit(_Model):
    method: str
    seed: int
    n_train: int
    n_test: int
    translation_mm: float
    rotation_deg: float | None


class Evaluation(_Model):
    protocol: str
    splits: list[HeldoutSplit]


class OutlierReport(_Model):
    rule: Literal["model", "sigma", "none"] = Field(
        "sigma", description="The outlier rule applied (see CalibrationOptions.outlier_rule)."
    )
    level: float | None = Field(
        None, description="Model rule: family-wise probability of removing a clean sample."
    )
    sigma: float | None
    n_input: int
    n_used: int
    removed_rows: list[int] = Field(description="1-based data rows dropped as outliers.")
    note: str | None = Field(
        None,
        description="Model rule: a step that judged no row, and why (e.g. its Σ_E step, when "
        "the covariances rest on too few equations per entry to judge rows by).",
    )

    def kept_indices(self) -> list[int]:
        """0-based indices of the samples the calibration used: all but ``removed_rows``."""
        removed = set(self.removed_rows)
        return [i for i in range(self.n_input) if i + 1 not in removed]


class SolverReport(_Model):
    name: str
    status: Literal[
        "optimal",
        "optimal_inaccurate",
        "one_step",
        "stopped_early",
        "iteration_limit",
        "diverged",
        "error",
    ] = Field(
        description="stopped_early: the paper's PGD stopping rule fired before optimality; "
        "one_step: the one-step likelihood estimator of a large recording (see the message)."
    )
    iterations: int
    time_s: float
    objective: float
    message: str | None = Field(
        None,
        description="How the solver got there, in words: its own status, a refinement, the "
        "starts of a likelihood fit, or why a fallback estimate is carried.",
    )


class CovarianceFrame(_Model):
    """Covariance of the random local twist ξ ~ N(0, Σ) of one frame (Eq. 7, DESIGN.md §2).

    ``name`` is the joint whose frame (right after L_i, before the joint moves) carries the
    perturbation, or ``"noise"`` for the measurement noise (end-effector frame). ``matrix`` is
    6x6 in [v; w] order, m² / m·rad / rad²; ``std`` the square roots of its diagonal (m, rad),
    None for an axis the data cannot see (``not_identifiable`` says why; ``matrix`` keeps the
    value the identifiability rule set there, so Eq. 12 sums as fitted).
    """

    name: str
    joint_index: int | None = Field(description="0-based chain joint; None for the noise.")
    matrix: Matrix6
    std: OptionalVector6 = Field(
        description="σ per axis x, y, z, rx, ry, rz (m, rad); null: not identifiable."
    )
    std_stderr: tuple[float | None, ...] | None = Field(
        None, description="Standard error of each std entry (None where not identifiable)."
    )
    std_ci_low: tuple[float | None, ...] | None = Field(
        None, description="Lower end of the confidence interval of each std (None: unknown)."
    )
    std_ci_high: tuple[float | None, ...] | None = Field(
        None, description="Upper end of the confidence interval of each std (None: unknown)."
    )
    identifiable: tuple[bool, ...] | None = Field(
        None,
        description="Per axis: determined by the data on its own (False: only a combination "
        "with other frames is, see identifiability.null_directions, or not at all, see "
        "not_identifiable).",
    )
    not_identifiable: tuple[str | None, ...] | None = Field(
        None,
        description="Per axis: why the data cannot see this axis's variance (its std is "
        "null), or null where they can. Rule: the axis's effect on the end-effector covariance "
        "(Eq. 12) over the recording's configurations is nil or does not vary (RMS variation "
        "below 1e-3 of its size), so a constant end-effector error looks the same "
        "(README, σ that the data cannot see).",
    )


class CovarianceIdentifiability(_Model):
    rank: int
    n_parameters: int
    condition_number: float
    null_directions: list[str] = Field(description="What the data cannot tell apart, in words.")
    fixed: list[str] = Field(description="Entries fixed by rule (named), and the rule.")
    warnings: list[str]


class CovarianceResult(_Model):
    """Calibrated random effects (paper §IV-C): Σ_n and Σ_1..Σ_k."""

    structure: Literal["diag", "full"]
    estimator: str
    n_samples: int | None = Field(None, description="Residuals the covariances came from.")
    confidence: float = Field(0.95, description="Level of the std confidence intervals.")
    stderr_method: str | None = Field(None, description="How standard errors were computed.")
    solver: SolverReport
    noise: CovarianceFrame = Field(
        description="Σ_n: the measurement noise (tip frame; measurement 'markers': each "
        "marker's position noise, the same for all, independent across markers; measurement "
        "'components': the chosen components', in the measurement frame)."
    )
    frames: list[CovarianceFrame]
    identifiability: CovarianceIdentifiability


LEGACY_POSITION_FLAG = "position_only"
"""The field result and findings documents written before issue 35 carried instead of
``measures_rotation`` (its negation); read, never written."""


class DatasetInfo(_Model):
    source: str
    n_samples: int
    measures_rotation: bool = Field(
        description="Whether each row measured the marker's orientation as well as its position "
        "(a pose: 6-D residuals) or its position alone (3-D residuals); the measurement model is "
        "service.render.result_json.result_measurement."
    )

    @model_validator(mode="before")
    @classmethod
    def _from_position_only(cls, data: object) -> object:
        """Documents written before issue 35 said ``position_only``, the negation."""
        if not isinstance(data, dict) or LEGACY_POSITION_FLAG not in data:
            return data
        data = dict(data)
        position_only = data.pop(LEGACY_POSITION_FLAG)
        if not isinstance(position_only, bool):  # coerced, "true" would turn into its negation
            raise ValueError(f"{LEGACY_POSITION_FLAG} must be true or false, got {position_only!r}")
        data.setdefault("measures_rotation", not position_only)  # both given: the new one counts
        return data


class ModelCorrection(_Model):
    """A discovered term undone on the recording before the fit (``calibrate --model``).

    Joint-angle terms: the joint stands at ``q_j + Σ_a c_a (φ_a(q) − mean_a)``, the features
    φ_a of :mod:`solver.discovery.features` (keys such as ``sin2:<joint>``, ``q:<joint>``,
    ``sign_tau:<joint>``), ``mean_a`` their mean over the calibration's recording.
    """

    effect: str
    joint: str | None = Field(description="URDF joint name; None for the measurement frame.")
    variant: str
    description: str
    parameters: dict[str, float] = Field(
        description="Discovered values, held fixed (names and units as in findings.json)."
    )
    feature_means: dict[str, float] = Field(
        default_factory=dict,
        description="Recording mean of each driving feature (rad for q:<joint>, else "
        "dimensionless): the centring that makes the correction at a new configuration "
        "equal to what was undone on the recording.",
    )
    applied_in_prediction: bool = Field(
        description="A function of the configuration alone: predict and rank evaluate the "
        "calibrated model at the corrected joint positions."
    )
    reason: str | None = Field(
        None, description="Why predict/rank cannot apply it to a new configuration."
    )


LEGACY_CORRECTION_KEYS = ("free_parameters", "fixed_parameters")


class ModelCorrections(_Model):
    """What ``calibrate --model findings.json`` undid on the recording, and what it could not."""

    @model_validator(mode="before")
    @classmethod
    def _drop_copied_options(cls, data: object) -> object:
        """Results written between issue 15's parameter selection and this fix carry copies of
        the options' free_parameters/fixed_parameters here (defaults, never read): accepted and
        dropped, so those stored results still load."""
        if isinstance(data, dict):
            return {k: v for k, v in data.items() if k not in LEGACY_CORRECTION_KEYS}
        return data

    gravity_base_m_s2: Vector3 = Field(
        description="Gravity (base frame) of the load-sign backlash features (the discovery's)."
    )
    payload_kg: float = Field(
        description="Payload of those features when the configurations give none."
    )
    corrections: list[ModelCorrection]
    not_carried: list[str] = Field(description="Terms not carried, each with the reason.")

    def applied(self) -> list[ModelCorrection]:
        """The corrections predict and rank apply at new configurations."""
        return [c for c in self.corrections if c.applied_in_prediction]

    def not_applicable(self) -> list[ModelCorrection]:
        """The corrections that cannot be applied to a new configuration."""
        return [c for c in self.corrections if not c.applied_in_prediction]


class VerdictReason(_Model):
    code: str = Field(description="Machine-readable cause, e.g. heldout_worse, position_unit.")
    severity: Literal["failed", "warning"]
    message: str = Field(description="What is wrong, with the numbers that show it.")
    fix: str = Field(description="What to do about it.")


class Verdict(_Model):
    """Whether the calibration is fit to use (solver.verdict): 'failed' results are written
    but marked, the CLI exits 3 and no URDF is exported unless forced."""

    status: Literal["ok", "warning", "failed"]
    reasons: list[VerdictReason] = Field(default_factory=list)


class ParameterCovariance(_Model):
    """Cov(θ̂) of the parameters the deterministic fit estimated (issue 13): with the predicted
    pose's parameter Jacobian J_θ(q) (the stacked-Jacobian columns named ``parameters``,
    DESIGN.md §2), ``J_θ(q) Cov(θ̂) J_θ(q)ᵀ`` is the parameter-estimation part of the predicted
    covariance. Units: local twists m and rad, compliance rad/N·m."""

    parameters: list[str] = Field(description="Column names, as identifiability.removed names.")
    matrix: list[list[float]] = Field(description="p×p, row-major, in the order of parameters.")
    method: str


class ModelErrorPart(_Model):
    """Model error no term of the model describes (issue 13): a diagonal covariance along the
    measurement frame's axes, ``T(q) diag(variance) T(q)ᵀ`` in the end-effector frame with
    ``T = blockdiag(Rᵀ, Rᵀ)`` and R the predicted end-effector orientation in the measurement
    frame. Fitted by maximum likelihood to cross-validated residuals (``method`` says which);
    docs/predictive.md."""

    axes: list[str] = Field(
        description="x, y, z (m) [, rx, ry, rz (rad)] of the measurement frame; for the "
        "other measurement types the residual's components (measurement.components)."
    )
    variance: list[float] = Field(description="m² and rad², one per axis.")
    std: list[float] = Field(description="m and rad, one per axis.")
    n_residuals: int = Field(description="Cross-validated residuals it was fitted to.")
    method: str
    frame: str | None = Field(
        default=None,
        description="The frame of the axes: None for a pose/position recording (the "
        "measurement frame); for the other measurement types the residual's frame of the type "
        "(measurement.frame).",
    )


class CoverageLevel(_Model):
    level: float = Field(description="Expected share inside the predicted ellipsoid.")
    observed: float = Field(description="Share of held-out poses inside it.")


class CoverageReport(_Model):
    """How the predicted covariance held on the held-out splits (issue 13): every part
    estimated from a split's training rows only, scored on its test rows. A pose is inside the
    α-ellipsoid when ``d² = rᵀ Σ_total⁻¹ r ≤ χ²_d⁻¹(α)``, r = Log(X_pred⁻¹ X_meas) (3-D
    translation for position-only data)."""

    dimension: int = Field(description="6 (full pose) or 3 (position-only).")
    n_heldout: int = Field(description="Held-out poses scored (over all splits).")
    n_splits: int
    levels: list[CoverageLevel] = Field(description="The 50, 90, 95 and 99 % ellipsoids.")
    curve: list[CoverageLevel] = Field(description="Expected vs observed, 5 % to 99 %.")
    mean_mahalanobis_sq: float = Field(description="Mean d² over the held-out poses.")
    chi2_mean: float = Field(description="Its value if the covariance is right: the dimension.")
    median_mahalanobis_sq: float
    chi2_median: float
    protocol: str


class PredictiveCovariance(_Model):
    """What a predictor needs to rebuild the total predicted covariance of a new configuration
    beyond the calibrated chain and ``covariance``: Σ_total(q) = Σ_E(q) (Eq. 12, + Σ_n) +
    J_θ(q) Cov(θ̂) J_θ(q)ᵀ + the model-error part; and its held-out coverage."""

    parameter_covariance: ParameterCovariance
    model_error: ModelErrorPart
    coverage: CoverageReport | None = Field(description="None without held-out splits.")


class MeasuredUnknown(_Model):
    name: str = Field(description="e.g. point_0.x (a socket), marker_2.z (a marker offset).")
    value: float = Field(description="m")
    stderr: float | None = Field(description="m; None where the data do not identify it.")


class MeasurementResult(_Model):
    """What each row measured and the measurement's own unknowns (issue 15): sockets of a
    ball-in-socket recording (robot base frame), marker offsets (flange frame)."""

    type: str = Field(description="The measurement model, as the measurement option names it.")
    frame: str = Field(description="The frame its residual is expressed in.")
    components: list[str] = Field(description="The residual's components per row.")
    unknowns: list[MeasuredUnknown]
    labels: list[str] = Field(
        default_factory=list, description="Sockets (placement/hole) or markers, in order."
    )
    constraint_residuals_m: list[float] = Field(
        default_factory=list, description="Known socket distance minus the fitted one, m."
    )
    notes: list[str] = Field(default_factory=list)

    def unknown_names(self) -> list[str]:
        """The names of the measurement's own unknowns (they may appear in
        ``predictive.parameter_covariance`` next to the chain parameters)."""
        return [u.name for u in self.unknowns]


class CalibrationResult(_Model):
    format: Literal["kincal.calibration/1"] = RESULT_FORMAT
    kincal_version: str
    created_utc: str
    dataset: DatasetInfo
    robot: RobotInfo
    options: CalibrationOptions
    measurement_frame: Transform = Field(
        description="Robot base frame expressed in the measurement frame (camera, tracker)."
    )
    tool: Transform = Field(description="Marker/tool frame expressed in the tip frame.")
    baseline: BaselineFit
    links: list[LinkCalibration]
    compliance: list[ComplianceCalibration]
    identifiability: Identifiability
    fit: FitStatistics
    evaluation: Evaluation | None
    outliers: OutlierReport
    solver: SolverReport
    verdict: Verdict | None = Field(
        None,
        description="Whether the result is fit to use, with causes and fixes (None: written by "
        "a kincal that did not check).",
    )
    covariance: CovarianceResult | None = Field(
        None, description="Random-effect covariances; None until that stage has run."
    )
    model_corrections: ModelCorrections | None = Field(
        None,
        description="Discovered terms undone on the recording (calibrate --model); None "
        "without --model.",
    )
    predictive: PredictiveCovariance | None = Field(
        None,
        description="Parameter-estimation and model-error parts of the predicted covariance "
        "and their held-out coverage; None without covariances.",
    )
    measurement: MeasurementResult | None = Field(
        None,
        description="The measurement model and its own unknowns; None for pose and position "
        "recordings.",
    )

    @field_validator("links")
    @classmethod
    def _links_present(cls, links: list[LinkCalibration]) -> list[LinkCalibration]:
        if len(links) < 2:
            raise ValueError("a chain has at least one joint and the tip")
        return links
