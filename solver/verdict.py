"""Is a calibration fit to use? Checks that turn silent failures into named causes.

A planner acts on the numbers, so a result the data do not support must say so instead of
"optimal": a fit that stopped at its iteration limit, a calibrated model that predicts held-out
poses worse than the nominal robot with fitted frames, too few equations per parameter, positions
in the wrong unit, orientations the arm cannot explain. Each check gives a :class:`Reason`
(cause and fix); the verdict is "failed" if any reason is, else "warning" if any, else "ok".
Pure arithmetic on numbers the calibration already has; lengths in m, angles in rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

Severity = Literal["failed", "warning"]
VerdictStatus = Literal["ok", "warning", "failed"]

MIN_EQUATIONS_PER_PARAMETER = 2.0
"""Below this many scalar equations per estimated parameter the fit is refused: the residual
is then mostly absorbed by the parameters (the TIAGo file: 54 equations for 39 parameters)."""
FEW_EQUATIONS_PER_PARAMETER = 5.0
"""Below this many, a warning: held-out errors will be well above the training errors."""
UNIT_SPREAD_FACTOR = 5.0
"""Measured positions spread more than this many times the arm's reach cannot come from it
(a recording in mm is 1000 times too large)."""
MODEL_MISFIT_FRACTION = 0.1
"""A calibrated training RMS position error above this fraction of the reach: the model does
not describe the recording at all."""
MIN_HELDOUT_GAIN = 0.05
"""A calibration must predict held-out poses at least this much better (relative, mean
translation error) than the nominal robot with fitted frames; a smaller gain is within what
the splits of a small recording move by and does not justify the fitted parameters."""
ORIENTATION_MISFIT_RAD = np.radians(10.0)
"""A calibrated training RMS rotation error above this: the recorded orientations disagree
with the arm (another rotation convention, or a marker that turns on its mount)."""


@dataclass(frozen=True)
class Reason:
    code: str
    severity: Severity
    message: str
    fix: str


@dataclass(frozen=True)
class FitEvidence:
    """What the checks look at. ``heldout_*``: mean held-out errors of the calibration and of
    the nominal robot with fitted frames ("before"), None without a held-out evaluation;
    ``train_rms_*``: the calibrated fit on its own samples (rotation None when position-only);
    ``position_spread_m``: largest distance of a measured position from their centroid;
    ``reach_m``: sum of the nominal link lengths from the first joint to the tip;
    ``screening_refused``: why the model-based outlier rule refused to remove
    ``screening_refused_rows`` of the ``n_rows`` rows ("not_converged", "model_misfit"), None
    when it did not refuse."""

    converged: bool
    iterations: int
    max_iterations: int
    n_equations: int
    n_parameters: int
    train_rms_translation_m: float
    train_rms_rotation_rad: float | None
    heldout_translation_m: float | None
    heldout_before_translation_m: float | None
    position_spread_m: float
    reach_m: float
    screening_refused: str | None = None
    screening_refused_rows: int = 0
    n_rows: int = 0


def reach_m(link_translations_m: NDArray[np.float64]) -> float:
    """Reach of a chain: sum of the lengths (k + 1, 3) of its links after the base, in m."""
    return float(np.linalg.norm(link_translations_m[1:], axis=1).sum())


def position_spread_m(positions_m: NDArray[np.float64]) -> float:
    """Largest distance (m) of positions (n, 3) from their centroid."""
    if positions_m.size == 0:
        return 0.0
    return float(np.linalg.norm(positions_m - positions_m.mean(axis=0), axis=1).max())


def check_fit(evidence: FitEvidence) -> list[Reason]:
    """Every reason the evidence gives to distrust the calibration, most basic first."""
    e = evidence
    reasons: list[Reason] = []
    if e.reach_m > 0 and e.position_spread_m > UNIT_SPREAD_FACTOR * e.reach_m:
        reasons.append(
            Reason(
                "position_unit",
                "failed",
                f"the measured positions spread over {e.position_spread_m:.3g} m, "
                f"{e.position_spread_m / e.reach_m:.0f} times the arm's reach "
                f"({e.reach_m:.2f} m): they are not in metres",
                "convert x, y, z to metres (divide millimetres by 1000) and calibrate again",
            )
        )
    elif e.reach_m > 0 and e.train_rms_translation_m > MODEL_MISFIT_FRACTION * e.reach_m:
        reasons.append(
            Reason(
                "model_misfit",
                "failed",
                f"the calibrated model misses its own training poses by "
                f"{1e3 * e.train_rms_translation_m:.0f} mm RMS, over "
                f"{MODEL_MISFIT_FRACTION:.0%} of the reach: the robot model, the joint columns or "
                "the tip frame do not match the recording",
                "check --robot/--urdf, --base/--tip and the joint column order and units (rad)",
            )
        )
    if e.train_rms_rotation_rad is not None and e.train_rms_rotation_rad > ORIENTATION_MISFIT_RAD:
        reasons.append(
            Reason(
                "orientation_misfit",
                "failed",
                f"the recorded orientations disagree with the arm: "
                f"{np.degrees(e.train_rms_rotation_rad):.1f}° RMS after calibration (relative "
                "rotations the model cannot explain: another rotation convention, or a marker "
                "that turns on its mount)",
                "check the quaternion columns (qx, qy, qz, qw order, the frame they are in), or "
                "calibrate position-only by leaving out the quaternion columns",
            )
        )
    if not e.converged:
        reasons.append(
            Reason(
                "not_converged",
                "failed",
                f"Levenberg–Marquardt stopped after {e.iterations} of at most {e.max_iterations} "
                "iterations without converging",
                "raise --max-iterations; if it still does not converge, the data or the model "
                "are inconsistent (see the other reasons)",
            )
        )
    if e.screening_refused is not None:
        cause = (
            "the fit they were judged by did not converge"
            if e.screening_refused == "not_converged"
            else "the model does not explain the data"
        )
        reasons.append(
            Reason(
                "outliers_refused",
                "failed",
                f"the model-based outlier rule would have removed {e.screening_refused_rows} of "
                f"{e.n_rows} rows and was refused (every row is kept): {cause}, so the rows "
                "look like outliers because the model is wrong, not the measurements",
                "raise --max-iterations"
                if e.screening_refused == "not_converged"
                else "check --robot/--urdf, --base/--tip and the joint columns; to see the fit "
                "on every row use --outlier-rule none",
            )
        )
    per_parameter = e.n_equations / max(e.n_parameters, 1)
    if per_parameter < FEW_EQUATIONS_PER_PARAMETER:
        severity: Severity = "failed" if per_parameter < MIN_EQUATIONS_PER_PARAMETER else "warning"
        reasons.append(
            Reason(
                "few_equations",
                severity,
                f"{e.n_equations} equations for {e.n_parameters} parameters "
                f"({per_parameter:.1f} per parameter): the parameters absorb the noise",
                "record more poses (kincal design picks informative ones) or fit fewer "
                "parameters (--rigid, --compliant-joints)",
            )
        )
    if (
        e.heldout_translation_m is not None
        and e.heldout_before_translation_m is not None
        and e.heldout_translation_m > (1.0 - MIN_HELDOUT_GAIN) * e.heldout_before_translation_m
    ):
        reasons.append(
            Reason(
                "heldout_worse",
                "failed",
                f"on held-out poses the calibrated model is not at least {MIN_HELDOUT_GAIN:.0%} "
                f"better than the nominal robot with fitted frames "
                f"({1e3 * e.heldout_translation_m:.2f} mm against "
                f"{1e3 * e.heldout_before_translation_m:.2f} mm mean): it fits the training poses, "
                "not the robot",
                "record more (and more varied) poses, or fit fewer parameters; until then the "
                "nominal model with the fitted frames is the better one",
            )
        )
    return reasons


def verdict_status(reasons: list[Reason]) -> VerdictStatus:
    if any(r.severity == "failed" for r in reasons):
        return "failed"
    return "warning" if reasons else "ok"
