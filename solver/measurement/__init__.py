"""Measurement models (issue 15): what a recorded row measures, its residual, Jacobian,
dimension and frame (:mod:`solver.measurement.models`), and the fit, outlier rule and held-out
evaluation for any of them (:mod:`solver.measurement.fit`, imported on first use: it builds on
the least-squares machinery of :mod:`solver.calibration`), the pose and position rows'
deterministic fit among them (:mod:`solver.measurement.pose`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from solver.lazy_exports import lazy_exports
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

if TYPE_CHECKING:
    from solver.measurement.fit import (
        HeldoutError,
        MeasurementFit,
        fit_measurement,
        heldout_errors,
        row_errors,
        screened_fit,
    )

_HOME = dict.fromkeys(
    [
        "HeldoutError",
        "MeasurementFit",
        "fit_measurement",
        "heldout_errors",
        "row_errors",
        "screened_fit",
    ],
    "fit",
)
"""The fit's names, imported on first use (PEP 562)."""

__getattr__ = lazy_exports(__name__, _HOME)


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
