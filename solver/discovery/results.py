"""What discovery returns (solver side; :mod:`schemas.discovery` is the JSON form)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.discovery.design import SeparatingPoses
from solver.discovery.detectability import DetectableSize
from solver.discovery.fitting import ModelParameters, Unseen
from solver.discovery.health import HealthReport
from solver.discovery.library import Term
from solver.distributions import t_sf


@dataclass(frozen=True)
class HeldoutError:
    """Mean held-out error over all K-fold test samples, and the whitened test SSE.

    ``per_sample`` (n,) whitened test SSE of each sample, in sample order (for paired tests).
    """

    translation_mm: float
    rotation_deg: float | None
    whitened_sse: float
    per_sample: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False, compare=False)
    # one entry per fold partition when several were used (:func:`repeated_heldout`)
    translation_by_split_mm: tuple[float, ...] = field(default=(), repr=False, compare=False)
    rotation_by_split_deg: tuple[float, ...] = field(default=(), repr=False, compare=False)
    sse_by_split: tuple[float, ...] = field(default=(), repr=False, compare=False)

    def improved_by(self, other: HeldoutError, level: float) -> bool:
        """``other`` predicts held-out samples better: lower total whitened error, and a
        one-sided paired t-test over samples significant at ``level``."""
        if other.whitened_sse >= self.whitened_sse:
            return False
        gain = self.per_sample - other.per_sample
        if gain.size < 3 or float(np.std(gain)) == 0.0:
            return True
        t = float(gain.mean() / (gain.std(ddof=1) / np.sqrt(gain.size)))
        return t_sf(t, gain.size - 1) < level

    def confirmed_by(self, other: HeldoutError, level: float) -> bool:
        """``other`` (the model with one more term) is confirmed on held-out samples: it is
        :meth:`improved_by` at ``level`` (per-sample gains averaged over the fold
        partitions); its whitened error is lower on every partition and, on average, by more
        than the split-to-split noise (the standard deviation over partitions of this model's
        own whitened error: how much it moves with nothing but the split); and neither the
        translation nor the rotation error a user reads gets worse by more than its own
        split-to-split noise."""
        if not self.improved_by(other, level):
            return False
        if len(self.sse_by_split) != len(other.sse_by_split):
            raise ValueError("held-out errors from different fold partitions")
        if any(a <= b for a, b in zip(self.sse_by_split, other.sse_by_split, strict=True)):
            return False
        if self.whitened_sse - other.whitened_sse <= _split_noise(self.sse_by_split):
            return False
        if other.translation_mm - self.translation_mm > _split_noise(self.translation_by_split_mm):
            return False
        if self.rotation_deg is None or other.rotation_deg is None:
            return True
        worse_deg = other.rotation_deg - self.rotation_deg
        return worse_deg <= _split_noise(self.rotation_by_split_deg)


def _split_noise(by_split: tuple[float, ...]) -> float:
    """Standard deviation of one held-out number over fold partitions (0 with one)."""
    return float(np.std(by_split, ddof=1)) if len(by_split) > 1 else 0.0


@dataclass(frozen=True)
class TermEstimate:
    """A term with its reported parameters and standard errors (see explain.py)."""

    term: Term
    parameters: dict[str, float]
    stderr: dict[str, float]
    p_value: float
    absorbed_fraction: float
    stability: float | None = None


@dataclass(frozen=True)
class PlotPanel:
    """Before/after residuals against the variable that drives a term (display units)."""

    driver: FloatArray
    driver_label: str
    before: FloatArray
    after: FloatArray
    fitted: FloatArray
    value_label: str


@dataclass(frozen=True)
class Finding:
    """A named effect with its final-model estimate and the held-out errors when it entered."""

    estimate: TermEstimate
    step: int
    heldout_before: HeldoutError
    heldout_after: HeldoutError
    explanation: str
    panels: list[PlotPanel] = field(default_factory=list)


@dataclass(frozen=True)
class Ambiguity:
    """Terms the data cannot tell apart (``with_geometry``: one term vs the geometry).

    ``kept`` is the term added to the model (it improves the held-out error whichever label is
    right), or None. ``poses`` would separate them.
    """

    candidates: list[TermEstimate]
    with_geometry: bool
    correlation: float
    step: int
    kept: Term | None
    poses: SeparatingPoses | None
    explanation: str


@dataclass(frozen=True)
class Unexplained:
    """Structure no library term describes, by joint (None: time or range)."""

    joint_index: int | None
    variable: str
    p_value: float
    explained_fraction: float
    distance_correlation: float | None
    partial: list[str]
    explanation: str


@dataclass(frozen=True)
class RandomEffect:
    """A random-looking effect for the covariance calibration (floating backlash)."""

    joint_index: int
    p_value: float
    variance_ratio: float
    explanation: str


@dataclass(frozen=True)
class Step:
    """One step of the loop: the best candidate and what happened to it."""

    step: int
    candidate: str
    action: str  # accepted, ambiguous, rejected_heldout, rejected_sign, unexplained, pruned
    p_value: float
    heldout_before_mm: float | None = None
    heldout_after_mm: float | None = None


@dataclass(frozen=True)
class DiscoveryResult:
    """Findings, ambiguities, unexplained structure and random effects, with the evidence."""

    findings: list[Finding]
    ambiguous: list[Ambiguity]
    unexplained: list[Unexplained]
    random_effects: list[RandomEffect]
    steps: list[Step]
    heldout_before: HeldoutError
    heldout_after: HeldoutError
    health_before: HealthReport
    health_after: HealthReport
    terms: tuple[Term, ...]
    params: ModelParameters
    joint_names: tuple[str, ...]
    n_candidates: int
    clock_unit: str
    outlier_rows: IntArray  # 0-based samples left out as gross outliers of the final model
    detectable: list[DetectableSize] | None = field(default_factory=list)  # None: not computed
    detection_level: float = float("nan")  # per-test level of the detectable sizes
    detection_power: float = float("nan")
    # library terms the measurement cannot see (not tested, no detectable size)
    unseen: list[Unseen] = field(default_factory=list)
