"""Measurement models (issue 15): what a recorded row measures, its residual, Jacobian,
dimension and frame, and the fit, outlier rule and held-out evaluation for any of them."""

from __future__ import annotations

from solver.measurement.fit import (
    HeldoutError,
    MeasurementFit,
    fit_measurement,
    heldout_errors,
    row_errors,
    screened_fit,
)
from solver.measurement.models import (
    EyeOnHead,
    FixedPoints,
    FullPose,
    KnownDistance,
    MeasurementModel,
    MeasurementRows,
    ModelParameters,
    MultiMarker,
    PoseComponents,
    Position,
    RelativeBase,
)

__all__ = [
    "EyeOnHead",
    "FixedPoints",
    "FullPose",
    "HeldoutError",
    "KnownDistance",
    "MeasurementFit",
    "MeasurementModel",
    "MeasurementRows",
    "ModelParameters",
    "MultiMarker",
    "PoseComponents",
    "Position",
    "RelativeBase",
    "fit_measurement",
    "heldout_errors",
    "row_errors",
    "screened_fit",
]
