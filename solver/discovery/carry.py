"""Carry a discovered model into the deterministic calibration (``kincal calibrate --model``).

The calibration (paper Eq. 8–10) fits geometry, joint compliance and virtual flex axes under a
given gravity vector and payload, so those discovered terms become its options. The other
library terms change what a joint or the sensor *reports*, with coefficients the discovery has
estimated; they are undone on the recording, coefficients held fixed, in the reverse order of
the discovery model (:mod:`solver.discovery.fitting`)::

    X_sensor = depth( Exp(Σ_d f_d(t) δ_d) · X_chain(q + Σ_a c_a φ_a) )

* **joint-angle terms** (gear_periodic, backlash, joint_scale, a joint's thermal_drift): the
  robot stands at ``q_j + Σ_a c_a φ_a[n]`` (features.py, centred over the recording; the
  constant is a link rotation the geometry absorbs), which is the corrected reading;
* **depth_scale** ``s``: the sensor reports ``p + s (zᵀp) z`` for the unit depth axis ``z``
  (measurement-frame z, or the marker's z), so ``zᵀp_meas = (1 + s) zᵀp`` and
  ``p = p_meas − s/(1 + s) (zᵀp_meas) z`` exactly (``z`` read from the measured orientation);
* **thermal_drift of the measurement frame**: ``X = Exp(−f(t) δ) · X_meas`` (measurement frame,
  twist [v; w], m and rad).

Generic "unexplained" structure is never carried: it has no physical name to carry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.discovery.features import DiscoveryData, FeatureBank
from solver.discovery.fitting import depth_direction
from solver.discovery.library import Term, drift_feature

FloatArray = NDArray[np.float64]

# Terms the calibration itself models (options), not corrections of the recording.
CALIBRATION_EFFECTS = ("joint_compliance", "base_flex", "link_bending")
GLOBAL_OPTIONS = ("payload_mass", "gravity_direction")


@dataclass(frozen=True)
class CorrectedRecording:
    """The recording as the discovered model says it really was.

    ``joint_positions`` (N, k) rad, ``measured_pose`` (N, 4, 4) marker in the measurement frame;
    ``applied`` the terms undone; ``skipped`` (term, reason) for those that could not be.
    """

    joint_positions: FloatArray
    measured_pose: FloatArray
    applied: list[Term]
    skipped: list[tuple[Term, str]]


def is_correction(term: Term) -> bool:
    """A library term undone on the recording (not an option of the calibration)."""
    return term.effect not in (*CALIBRATION_EFFECTS, *GLOBAL_OPTIONS, "unexplained")


def correct_recording(
    bank: FeatureBank, terms: list[tuple[Term, FloatArray]]
) -> CorrectedRecording:
    """Undo the correction terms of ``terms`` (term, coefficients) on ``bank``'s recording.

    The bank must be built on the whole recording with the gravity and payload the discovery
    used (load-sign backlash reads the nominal gravity torque).
    """
    data: DiscoveryData = bank.data
    q = np.array(data.joint_positions, dtype=float)
    pose = np.array(data.measured_pose, dtype=float)
    gravity = np.asarray(data.gravity_base, dtype=float)
    applied: list[Term] = []
    skipped: list[tuple[Term, str]] = []
    for term, values in terms:
        if not is_correction(term):
            continue
        if term.axes:
            for spec, value in zip(term.axes, values, strict=True):
                q[:, spec.joint_index] += float(value) * bank.column(spec.feature, gravity, 0.0)
            applied.append(term)
    for term, values in terms:
        if term.effect == "depth_scale":
            if data.position_only and term.variant == "marker_z":
                skipped.append((term, "the marker's depth axis needs measured orientations"))
                continue
            pose = undo_depth_scale(pose, float(values[0]), term.variant)
            applied.append(term)
    for term, values in terms:
        if term.effect == "thermal_drift" and term.joint_index is None:
            shape = bank.column(drift_feature(term), gravity, 0.0)
            pose = lie.se3_exp(-shape[:, None] * np.asarray(values)[None, :]) @ pose
            applied.append(term)
    return CorrectedRecording(q, pose, applied, skipped)


def undo_depth_scale(measured_pose: FloatArray, scale: float, variant: str) -> FloatArray:
    """Measured poses (N, 4, 4) with a depth reading scaled by ``1 + scale`` undone (exact):
    ``p = p_meas − s/(1 + s) (zᵀp_meas) z``, the depth axis ``z`` of :func:`depth_direction`
    (the orientation is not scaled, so the marker's z reads true)."""
    out = measured_pose.copy()
    out[:, :3, 3] -= (scale / (1.0 + scale)) * depth_direction(measured_pose, variant)
    return out
