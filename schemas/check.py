"""A check of a calibration against new poses (``"format": "kincal.check/1"``, issue 33).

Each check pose's measured pose is tested against the calibration's prediction with its total
predictive covariance (Σ_E + Σ_n + Cov(θ̂) + model error, docs/predictive.md) as a Mahalanobis
d²; a global test and a max-type test give the verdict; score tests of candidate changes locate
a drift. Sizes are in SI units, named by ``unit`` ("m", "rad", "1"). The arithmetic lives in
:mod:`solver.check`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.calibration import Verdict
from schemas.ranking import CalibrationReference

CHECK_FORMAT: Literal["kincal.check/1"] = "kincal.check/1"
DEFAULT_LEVEL = 0.05
"""Family-wise false-alarm probability of the verdict (``kincal check --level``)."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CheckOptions(_Model):
    """The options of a check (``kincal check``'s flags)."""

    level: float = Field(
        DEFAULT_LEVEL,
        gt=0.0,
        lt=1.0,
        allow_inf_nan=False,
        description="Family-wise probability of a false alarm when the calibration holds.",
    )


class CheckPose(_Model):
    """One check pose: its residual against the prediction and its d²."""

    index: int = Field(description="Row of the check recording, from 1.")
    sample_id: str | None = None
    d2: float = Field(description="r^T Σ^-1 r under the total predictive covariance.")
    translation_mm: float = Field(description="Length of the residual's translation, mm.")
    rotation_mrad: float | None = Field(description="Residual rotation angle, mrad (full pose).")
    bad_sample: bool = Field(
        description="Far off (d² above the max-type threshold), set aside: re-measure it."
    )


class GlobalTestResult(_Model):
    """Σ d² of the poses the verdict is on (with the parameter part shared between poses)."""

    statistic: float
    dof: int
    threshold: float = Field(description="The χ²_dof quantile at the critical p-value.")
    p_value: float
    n_poses: int


class ChangeComponent(_Model):
    """One component of a located change: its size and 95 % interval, in ``unit``."""

    name: str
    value: float
    low95: float
    high95: float
    unit: str


class CandidateTest(_Model):
    """A candidate change's score test on the check poses."""

    name: str
    kind: Literal["joint_offset", "joint_scale", "base", "tool", "link"]
    statistic: float
    dof: int
    p_value: float
    adjusted_p_value: float = Field(
        description="Family-wise over the global and every candidate's test (min-p rule)."
    )


class LocatedChange(_Model):
    """The candidate change that explains the drift best, with the ones these poses cannot
    tell apart from it."""

    name: str
    kind: Literal["joint_offset", "joint_scale", "base", "tool", "link"]
    components: list[ChangeComponent]
    adjusted_p_value: float
    indistinguishable_from: list[str]


class StatedSize(_Model):
    """The smallest change of this kind the check detects and locates with probability
    ``power`` at its level (along the worst direction: any change of this size or larger is
    detected)."""

    name: str
    size: float | None = Field(description="null: no size of it moves these poses.")
    unit: str
    located: bool = Field(
        description="False: not located that often even at 4× the detectable size; the size "
        "promises detection only."
    )


class CheckResult(_Model):
    """A check (``kincal check -o``)."""

    format: Literal["kincal.check/1"] = CHECK_FORMAT
    kincal_version: str
    created_utc: str
    calibration: CalibrationReference
    calibration_verdict: Verdict | None = Field(
        default=None,
        description="The checked calibration's own verdict (its result's; null: written before "
        "verdicts). A calibration that failed its own tests predicts no better than the "
        "nominal robot: the advice is then to recalibrate, whatever the check says.",
    )
    recording: str
    dimension: int = Field(description="Residual rows per pose: 6 (full pose) or 3 (position).")
    level: float = Field(description="Family-wise false-alarm probability of the verdict.")
    global_critical_p: float | None = Field(
        description="The global test rejects below this p-value (weighted min-p rule)."
    )
    candidate_critical_p: float | None = Field(
        description="A candidate's score test rejects below this p-value."
    )
    verdict: Literal["holds", "drifted", "inconclusive"]
    reason: str
    advice: str
    max_threshold: float | None = Field(
        description="Šidák threshold of a single pose's d² (null: too few poses)."
    )
    poses: list[CheckPose]
    global_test: GlobalTestResult | None
    located: LocatedChange | None
    candidates: list[CandidateTest]
    power: float
    stated_sizes: list[StatedSize]


FLEET_CHECK_FORMAT: Literal["kincal.fleet-check/1"] = "kincal.fleet-check/1"


class FleetCheckUnit(_Model):
    """One unit's check: its calibration result, its check recording and the check."""

    unit: str
    result: str = Field(description="Path of the unit's calibration result.")
    check: CheckResult


class FleetCheck(_Model):
    """Every unit of a fleet checked against its own calibration (``kincal fleet --check``)."""

    format: Literal["kincal.fleet-check/1"] = FLEET_CHECK_FORMAT
    kincal_version: str
    created_utc: str
    level: float = Field(description="Each unit's family-wise false-alarm probability.")
    fleet_false_alarm: float = Field(
        description="Probability that some unit of a fleet that holds is called drifted: "
        "1 − (1 − level)^units (units checked independently)."
    )
    holds: list[str]
    drifted: list[str]
    inconclusive: list[str]
    units: list[FleetCheckUnit]
