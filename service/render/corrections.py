"""Discovered corrections a result carries (``calibrate --model``), applied where it predicts.

A calibration fitted on a recording whose joint readings were corrected (gear_periodic,
joint_scale, load-sign backlash) predicts from the joint positions the robot really stands at,
so ``kincal predict``, ``kincal rank`` and the HTTP rankings turn raw readings into those
positions first (:func:`true_configurations`). Corrections that depend on time, execution order
or the sensor cannot be evaluated at a new configuration: :func:`prediction_note` says so.
The maths is :mod:`solver.discovery.carry`.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np

from schemas.calibration import CalibrationResult, ModelCorrection
from solver.arrays import FloatArray
from solver.discovery.carry import (
    ConfigurationCorrection,
    configuration_corrections,
    corrected_configurations,
    readings_for,
)
from solver.discovery.features import probe_chain
from solver.discovery.library import library_term
from solver.errors import KincalError
from solver.model import KinematicChain

_PROBES: weakref.WeakKeyDictionary[KinematicChain, KinematicChain] = weakref.WeakKeyDictionary()


def _probe(chain: KinematicChain) -> KinematicChain:
    """:func:`probe_chain` of ``chain``, built once per chain (0.5 ms, and rankings reuse a
    cached result's chain on every request)."""
    probe = _PROBES.get(chain)
    if probe is None:
        probe = _PROBES[chain] = probe_chain(chain)
    return probe


def applied_corrections(result: CalibrationResult) -> list[ModelCorrection]:
    """The result's corrections that predict and rank apply at new configurations."""
    record = result.model_corrections
    return [] if record is None else record.applied()


def solver_corrections(
    result: CalibrationResult, probe: KinematicChain
) -> list[ConfigurationCorrection]:
    """The applied corrections as solver axes on ``probe`` (:func:`probe_chain` of the
    result's chain)."""
    out: list[ConfigurationCorrection] = []
    for entry in applied_corrections(result):
        if entry.joint is None or entry.joint not in probe.joint_names:
            raise KincalError(
                f"model correction {entry.description!r} names no joint of the chain "
                f"({', '.join(probe.joint_names)}); the result is inconsistent, re-run calibrate"
            )
        j = probe.joint_names.index(entry.joint)
        try:
            term = library_term(probe, entry.effect, j, entry.variant, "s")
            values = np.array([entry.parameters[p] for p in term.parameters])
            out += configuration_corrections(term, values, entry.feature_means)
        except (KeyError, ValueError) as exc:
            raise KincalError(
                f"model correction {entry.description!r} is incomplete ({exc}); re-run calibrate"
            ) from exc
    return out


def _map_joints(
    result: CalibrationResult,
    chain: KinematicChain,
    joint_positions: FloatArray,
    payload_kg: FloatArray | float | None,
    direction: Callable[..., FloatArray],
) -> FloatArray:
    """``direction`` (:func:`corrected_configurations` or :func:`readings_for`) of the result's
    applied corrections on ``joint_positions`` (N, k) rad; unchanged when there are none."""
    record = result.model_corrections
    q = np.asarray(joint_positions, dtype=float)
    if record is None or not record.applied() or len(q) == 0:
        return q
    probe = _probe(chain)
    payload = record.payload_kg if payload_kg is None else payload_kg
    gravity = np.asarray(record.gravity_base_m_s2, dtype=float)
    return direction(probe, solver_corrections(result, probe), q, gravity, payload)


def true_configurations(
    result: CalibrationResult,
    chain: KinematicChain,
    joint_readings: FloatArray,
    payload_kg: FloatArray | float | None = None,
) -> FloatArray:
    """Joint positions (N, k) rad the robot stands at for raw readings (N, k) rad under the
    result's applied corrections (the readings themselves when there are none).
    ``payload_kg`` (N,) or scalar: the load of load-sign backlash (default: the discovery's)."""
    return _map_joints(result, chain, joint_readings, payload_kg, corrected_configurations)


def raw_readings(
    result: CalibrationResult,
    chain: KinematicChain,
    joint_positions: FloatArray,
    payload_kg: FloatArray | float | None = None,
) -> FloatArray:
    """The inverse of :func:`true_configurations`: the readings (N, k) rad at which the robot
    stands at ``joint_positions`` (N, k) rad (what a controller is sent, e.g. IK solutions)."""
    return _map_joints(result, chain, joint_positions, payload_kg, readings_for)


def prediction_note(result: CalibrationResult) -> str | None:
    """One line naming the carried corrections a prediction cannot apply, or None."""
    record = result.model_corrections
    if record is None or not record.not_applicable():
        return None
    terms = "; ".join(f"{c.description} ({c.reason})" for c in record.not_applicable())
    return (
        f"note: the calibration undid {terms} on its recording; predictions at new "
        "configurations cannot include that"
    )
