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

A calibration fitted on the corrected recording predicts from the joint positions the robot
really stands at. Where the correction is a function of the configuration alone (gear_periodic,
joint_scale, load-sign backlash), :func:`corrected_configurations` gives them for new readings
from the same features (:func:`solver.discovery.features.configuration_feature`) and the
recording's feature means; time, execution order and the sensor cannot be known for a new
configuration, so those corrections are not applicable there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver import lie
from solver.arrays import FloatArray
from solver.discovery.features import (
    DiscoveryData,
    FeatureBank,
    configuration_feature,
    gravity_basis,
    is_configuration_feature,
)
from solver.discovery.library import Term, drift_feature
from solver.model import KinematicChain
from solver.simulate import depth_direction

# Terms the calibration itself models (options), not corrections of the recording.
CALIBRATION_EFFECTS = ("joint_compliance", "base_flex", "link_bending")
GLOBAL_OPTIONS = ("payload_mass", "gravity_direction")


@dataclass(frozen=True)
class CorrectedRecording:
    """The recording as the discovered model says it really was.

    ``joint_positions`` (N, k) rad, ``measured_pose`` (N, 4, 4) marker in the measurement frame;
    ``applied`` the terms undone; ``skipped`` (term, reason) for those that could not be;
    ``feature_means`` the recording mean of each joint-angle term's feature (the centring of
    :meth:`FeatureBank.column`; rad for ``q:<joint>``, else dimensionless).
    """

    joint_positions: FloatArray
    measured_pose: FloatArray
    applied: list[Term]
    skipped: list[tuple[Term, str]]
    feature_means: dict[str, float]


@dataclass(frozen=True)
class ConfigurationCorrection:
    """One axis of a joint-angle correction that is a function of the configuration alone.

    Joint ``joint_index`` stands at ``q_j + coefficient · (φ(q) − mean)`` with φ the feature
    ``feature`` (:func:`configuration_feature`); ``coefficient`` rad per unit feature (per rad
    for ``q:<joint>``), ``mean`` the feature's mean over the recording it was estimated on.
    """

    joint_index: int
    feature: str
    coefficient: float
    mean: float


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
    means: dict[str, float] = {}
    for term, values in terms:
        if not is_correction(term):
            continue
        if term.axes:
            for spec, value in zip(term.axes, values, strict=True):
                q[:, spec.joint_index] += float(value) * bank.column(spec.feature, gravity, 0.0)
                means[spec.feature] = bank.mean(spec.feature, gravity, 0.0)
            applied.append(term)
    for term, values in terms:
        if term.effect == "depth_scale":
            if not data.pose_model.measures_rotation and term.variant == "marker_z":
                skipped.append((term, "the marker's depth axis needs measured orientations"))
                continue
            pose = undo_depth_scale(pose, float(values[0]), term.variant)
            applied.append(term)
    for term, values in terms:
        if term.effect == "thermal_drift" and term.joint_index is None:
            shape = bank.column(drift_feature(term), gravity, 0.0)
            pose = lie.se3_exp(-shape[:, None] * np.asarray(values)[None, :]) @ pose
            applied.append(term)
    return CorrectedRecording(q, pose, applied, skipped, means)


def applicable_at_new_configurations(term: Term) -> bool:
    """A joint-angle correction that is a function of the configuration alone (not of time,
    execution order or the sensor), so it can be evaluated at configurations never recorded."""
    return bool(term.axes) and all(is_configuration_feature(a.feature) for a in term.axes)


def configuration_corrections(
    term: Term, values: FloatArray, feature_means: dict[str, float]
) -> list[ConfigurationCorrection]:
    """The axes of an applicable term (:func:`applicable_at_new_configurations`) with its
    coefficients ``values`` and the recording's feature means."""
    if not applicable_at_new_configurations(term):
        raise ValueError(f"{term.key} depends on more than the configuration")
    return [
        ConfigurationCorrection(a.joint_index, a.feature, float(v), feature_means[a.feature])
        for a, v in zip(term.axes, values, strict=True)
    ]


def correction_offsets_rad(
    probe: KinematicChain,
    corrections: list[ConfigurationCorrection],
    joint_positions: FloatArray,
    gravity_base: FloatArray,
    payload_kg: FloatArray | float,
) -> FloatArray:
    """Σ c (φ(q) − mean) per joint (N, k), rad, at joint readings ``joint_positions`` (N, k).

    ``probe`` is :func:`solver.discovery.features.probe_chain` of the nominal chain (load
    features are gravity moments about its axes); ``gravity_base`` (3,) m/s² in the base
    frame and ``payload_kg`` (N,) or scalar are the load the features were defined under.
    """
    q = np.asarray(joint_positions, dtype=float)
    offsets = np.zeros_like(q)
    loads: dict[str, FloatArray] = {}  # gravity moments by probe axis, swept on first use

    def moment_nm(axis_name: str) -> FloatArray:
        if not loads:
            basis = gravity_basis(probe, q)
            payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (q.shape[0],))
            moments = basis.moments(np.asarray(gravity_base, dtype=float), payload)
            loads.update({name: moments[:, i] for i, name in enumerate(basis.axis_names)})
        return loads[axis_name]

    for c in corrections:
        feature = configuration_feature(c.feature, q, probe.joint_names, moment_nm)
        offsets[:, c.joint_index] += c.coefficient * (feature - c.mean)
    return offsets


def corrected_configurations(
    probe: KinematicChain,
    corrections: list[ConfigurationCorrection],
    joint_readings: FloatArray,
    gravity_base: FloatArray,
    payload_kg: FloatArray | float,
) -> FloatArray:
    """Joint positions (N, k) rad the robot stands at for raw readings (N, k) rad:
    ``q + Σ c (φ(q) − mean)`` (arguments as :func:`correction_offsets_rad`)."""
    q = np.asarray(joint_readings, dtype=float)
    return q + correction_offsets_rad(probe, corrections, q, gravity_base, payload_kg)


def readings_for(
    probe: KinematicChain,
    corrections: list[ConfigurationCorrection],
    joint_positions: FloatArray,
    gravity_base: FloatArray,
    payload_kg: FloatArray | float,
    *,
    max_iterations: int = 50,
) -> FloatArray:
    """Raw readings (N, k) rad at which the robot stands at ``joint_positions`` (N, k) rad: the
    inverse of :func:`corrected_configurations` by fixed-point iteration
    ``r ← q − offsets(r)``, which contracts because the offsets are tiny functions of q (mrad).
    Load-sign backlash jumps where the load changes sign; a position inside the jump has no
    reading, and the last iterate is returned."""
    target = np.asarray(joint_positions, dtype=float)
    readings = target.copy()
    for _ in range(max_iterations):
        offsets = correction_offsets_rad(probe, corrections, readings, gravity_base, payload_kg)
        updated = target - offsets
        step_rad = float(np.max(np.abs(updated - readings), initial=0.0))
        readings = updated
        if step_rad < 1e-15:
            break
    return readings


def undo_depth_scale(measured_pose: FloatArray, scale: float, variant: str) -> FloatArray:
    """Measured poses (N, 4, 4) with a depth reading scaled by ``1 + scale`` undone (exact):
    ``p = p_meas − s/(1 + s) (zᵀp_meas) z``, the depth axis ``z`` of :func:`depth_direction`
    (the orientation is not scaled, so the marker's z reads true)."""
    out = measured_pose.copy()
    out[:, :3, 3] -= (scale / (1.0 + scale)) * depth_direction(measured_pose, variant)
    return out
