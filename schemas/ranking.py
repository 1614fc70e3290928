"""Ranking requests and results (``"format": "kincal.ranking/1"``, paper §IV-D, DESIGN.md §3).

A ranking scores configurations by the task-weighted trace of their predicted end-effector
covariance, ``tr(W Σ_E W^T)`` (Eq. 22–23), lower is better. Twists are [v; w] in the
end-effector frame, m and rad. The CLI (``kincal rank``) and the HTTP service share these
models; the arithmetic lives in :mod:`solver.ranking`.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    field_validator,
    model_validator,
)

from schemas.calibration import Matrix6, Vector3, Vector6

RANKING_FORMAT: Literal["kincal.ranking/1"] = "kincal.ranking/1"
PAPER_WEIGHTS: Vector6 = (0.4, 0.4, 0.0, 0.1, 0.1, 0.0)

NonNegative = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Weights6 = tuple[NonNegative, NonNegative, NonNegative, NonNegative, NonNegative, NonNegative]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PoseWeights(_Model):
    """Paper Eq. (22): weights W on the end-effector twist [v_x, v_y, v_z, w_x, w_y, w_z].

    Either ``diagonal`` (6 non-negative numbers; paper default 0.4, 0.4, 0, 0.1, 0.1, 0) or a
    full 6×6 ``matrix``. Rotations count ``rotation_scale_m_per_rad`` metres per radian
    (paper: 1), so the score is in m² under that convention.
    """

    kind: Literal["pose"] = "pose"
    diagonal: Weights6 = PAPER_WEIGHTS
    matrix: Matrix6 | None = Field(None, description="Full W, row-major; replaces diagonal.")
    rotation_scale_m_per_rad: float = Field(1.0, gt=0.0, allow_inf_nan=False)

    @field_validator("matrix")
    @classmethod
    def _square_and_finite(cls, matrix: list[list[float]] | None) -> list[list[float]] | None:
        if matrix is not None and (
            any(len(row) != 6 for row in matrix)
            or not all(math.isfinite(v) for row in matrix for v in row)
        ):
            raise ValueError("weight matrix must be 6×6 finite numbers")
        return matrix


class TaskPointWeights(_Model):
    """Position covariance of a task point ``point_m`` given in the end-effector frame (e.g.
    a docking interface 5 cm ahead: (0, 0, 0.05)), weighted per axis: score
    ``Σ_a w_a Var(δp_a)`` in m². A point at p moves by ``v + w × p``, so no m²/rad² mixing."""

    kind: Literal["task_point"] = "task_point"
    point_m: Vector3
    axis_weights: tuple[NonNegative, NonNegative, NonNegative] = (1.0, 1.0, 1.0)

    @field_validator("point_m")
    @classmethod
    def _finite(cls, point: Vector3) -> Vector3:
        if not all(math.isfinite(v) for v in point):
            raise ValueError("task point must be finite")
        return point


def _weights_kind(value: Any) -> str:
    """``kind`` may be left out (its default is documented): a task point is recognised by its
    ``point_m``, anything else is pose weights."""
    if isinstance(value, dict):
        return str(value.get("kind", "task_point" if "point_m" in value else "pose"))
    return str(getattr(value, "kind", "pose"))


TaskWeights = Annotated[
    Annotated[PoseWeights, Tag("pose")] | Annotated[TaskPointWeights, Tag("task_point")],
    Discriminator(_weights_kind),
]


class RankingOptions(_Model):
    """How configurations are scored."""

    weights: TaskWeights = Field(default_factory=PoseWeights)
    include_noise: bool = Field(
        False, description="Add the measurement noise Σ_n (the same for every configuration)."
    )
    uncertainty: Literal["random_effects", "total"] = Field(
        "random_effects",
        description="Which covariance is scored: 'random_effects' Σ_E(q) of Eq. 12 (the "
        "paper's score: what the robot's own randomness does at q) or 'total', the predicted "
        "covariance Σ_E(q) + J_θ(q) Cov(θ̂) J_θ(q)ᵀ + the model-error part (also what the "
        "calibration does not know; docs/predictive.md).",
    )
    top: int | None = Field(None, ge=1, description="Keep only the best entries.")


class ConfigurationRankingRequest(_Model):
    """Rank given configurations (rows of joint positions in chain order, rad)."""

    joint_positions_rad: list[list[float]] = Field(min_length=1)
    payload_kg: float | list[float] = 0.0
    options: RankingOptions = Field(default_factory=RankingOptions)


class TargetPose(_Model):
    """An end-effector (marker/tool) pose in the calibration's measurement frame — the frame of
    ``kincal predict``. Unit quaternion, scalar LAST."""

    position_m: Vector3
    quaternion_xyzw: tuple[float, float, float, float]

    @model_validator(mode="after")
    def _unit_quaternion(self) -> TargetPose:
        values = (*self.position_m, *self.quaternion_xyzw)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("target pose must be finite")
        norm = math.sqrt(sum(v * v for v in self.quaternion_xyzw))
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"target quaternion (qx,qy,qz,qw) must have unit norm, got {norm:.6g}")
        return self


class TargetRankingRequest(_Model):
    """Find distinct IK solutions for a target pose and rank them.

    ``free_axis``: end-effector axis about which the target may be rotated because the task
    ignores it ("auto": the rotation axis the weights ignore, z preferred; "none": exact pose).
    """

    target: TargetPose
    n_candidates: int = Field(16, ge=1, le=512)
    seed: int = Field(0, ge=0)
    free_axis: Literal["auto", "x", "y", "z", "none"] = "auto"
    n_free_rotations: int = Field(12, ge=1, le=360)
    payload_kg: float = Field(0.0, ge=0.0)
    options: RankingOptions = Field(default_factory=RankingOptions)


class CalibrationReference(_Model):
    """Which calibration the covariances come from."""

    robot: str
    urdf_sha256: str
    created_utc: str
    kincal_version: str
    result_sha256: str = Field(description="SHA-256 of the result's canonical JSON.")
    covariance_structure: str
    covariance_estimator: str


class RankedConfiguration(_Model):
    """One configuration, best first. ``index`` is its 0-based row in the input (or candidate
    number); ``ee_std`` the square roots of diag Σ_E (m, m, m, rad, rad, rad)."""

    rank: int = Field(description="1 = lowest score.")
    index: int
    score: float
    trace_position_m2: float
    trace_rotation_rad2: float
    ee_std: Vector6
    score_parts: dict[str, float] | None = Field(
        None,
        description="uncertainty 'total': the score of each part (random_effects, "
        "parameters, model_error); they add up to score.",
    )
    joint_positions_rad: list[float] | None = None
    free_rotation_rad: float | None = Field(
        None, description="IK: rotation of the target about the free axis this entry reaches."
    )
    ik_translation_error_m: float | None = None
    ik_rotation_error_rad: float | None = None
    ik_source: Literal["restart", "null_space"] | None = None


class RankingResult(_Model):
    """A ranking (``kincal rank -o``, HTTP rankings)."""

    format: Literal["kincal.ranking/1"] = RANKING_FORMAT
    kincal_version: str
    calibration: CalibrationReference
    joint_names: list[str]
    weights: TaskWeights
    task_matrix: list[list[float]] = Field(description="M with score = tr(M Σ_E M^T), d×6.")
    score_unit: str
    include_noise: bool
    uncertainty: Literal["random_effects", "total"] = "random_effects"
    n_configurations: int
    best_index: int | None
    target: TargetPose | None = None
    free_axis: Vector3 | None = None
    ranking: list[RankedConfiguration]
