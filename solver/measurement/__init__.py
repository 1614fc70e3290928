"""Measurement models (issue 15): what a recorded row measures, its residual, Jacobian,
dimension and frame (:mod:`solver.measurement.models`), and the fit, outlier rule and held-out
evaluation for any of them (:mod:`solver.measurement.fit`, imported on first use: it builds on
the least-squares machinery of :mod:`solver.calibration`), the pose and position rows'
deterministic fit among them (:mod:`solver.measurement.pose`)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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

_FIT_NAMES = (
    "HeldoutError",
    "MeasurementFit",
    "fit_measurement",
    "heldout_errors",
    "row_errors",
    "screened_fit",
)


def __getattr__(name: str) -> Any:
    if name in _FIT_NAMES:
        return getattr(importlib.import_module("solver.measurement.fit"), name)
    raise AttributeError(f"module 'solver.measurement' has no attribute {name!r}")


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
