"""Findings carried into a calibration: ``kincal calibrate --model findings.json`` fits the
discovered compliance, flex, tilt and payload (and the measurement's unknowns) and undoes the
other named terms; the options a findings file sets."""

from __future__ import annotations

import dataclasses

import numpy as np
import pydantic

from schemas.calibration import (
    CalibrationOptions,
    ModelCorrection,
    ModelCorrections,
)
from schemas.dataset import PoseDataset
from schemas.discovery import (
    FindingsResult,
)
from schemas.robots import RobotDescription
from service.app import measurement_input
from service.app.discover import measured_data, solver_data
from service.render.chain import chain_for
from solver import lie
from solver.discovery.carry import (
    CorrectedRecording,
    applicable_at_new_configurations,
    correct_recording,
    is_correction,
)
from solver.discovery.explain import describe
from solver.discovery.features import FeatureBank, probe_chain
from solver.discovery.library import UNEXPLAINED, Term, library_term
from solver.errors import ModelError
from solver.model import KinematicChain


@dataclasses.dataclass(frozen=True)
class CarriedModel:
    """What ``kincal calibrate --model findings.json`` calibrates.

    ``dataset`` is the recording with the discovered named terms undone at their discovered
    values (:mod:`solver.discovery.carry`; the compliance, flex axes, gravity and payload go
    into the options instead, :func:`carried_options`); ``notes`` say what was carried and
    how, one line each; ``record`` goes into the result JSON (``model_corrections``) so that
    predict and rank apply the corrections too.
    """

    dataset: PoseDataset
    corrections: list[str]
    notes: list[str]
    record: ModelCorrections


@dataclasses.dataclass(frozen=True)
class CarriedMeasurement:
    """:class:`CarriedModel` for a recording of another measurement type
    (:func:`carry_measured`): its rows with the joint-angle terms undone on the joint
    readings (and, where the rows hold a measured pose, the sensor's terms on it)."""

    recording: measurement_input.MeasuredRecording
    notes: list[str]
    record: ModelCorrections


@dataclasses.dataclass(frozen=True)
class _Carry:
    """The correction terms of a discovery with their values, and what was not carried."""

    terms: list[tuple[Term, np.ndarray]]
    extra_payload_kg: float
    not_carried: list[str]
    notes: list[str]


def findings_chain(findings: FindingsResult, robot: RobotDescription) -> KinematicChain:
    """The chain the discovery of ``findings`` used, built for ``robot``; :class:`ModelError`
    when ``robot`` has other joints than the findings name."""
    chain = chain_for(robot, findings.options)
    if list(chain.joint_names) != findings.robot.joint_names:
        raise ModelError(
            f"the findings are for joints {', '.join(findings.robot.joint_names)} of "
            f"{findings.robot.name}, not {', '.join(chain.joint_names)}; pass the same robot "
            "to calibrate as to discover"
        )
    return chain


def _carry_terms(findings: FindingsResult, chain: KinematicChain, bank: FeatureBank) -> _Carry:
    """The findings' model terms that are corrections of the recording, at their values."""
    names = chain.joint_names
    notes: list[str] = []
    if chain.urdf_sha256 != findings.robot.urdf_sha256:
        notes.append(
            f"the findings were made with another URDF of {findings.robot.name} (sha256 "
            f"{findings.robot.urdf_sha256[:12]}…, this one {chain.urdf_sha256[:12]}…) with the "
            "same joints: make sure it is the same robot"
        )
    terms: list[tuple[Term, np.ndarray]] = []
    extra_payload_kg = 0.0
    not_carried: list[str] = []
    for entry in findings.model.terms:
        if entry.effect == UNEXPLAINED:
            not_carried.append(f"unexplained {entry.variant} structure (no physical name)")
            continue
        index = None if entry.joint is None else names.index(entry.joint)
        term = library_term(bank.probe, entry.effect, index, entry.variant, bank.clock_unit)
        if entry.effect == "payload_mass":
            extra_payload_kg += entry.parameters.get("payload_kg", 0.0)
        if not is_correction(term):
            continue
        missing = [p for p in term.parameters if p not in entry.parameters]
        if missing:
            not_carried.append(
                f"{describe(term, names)} (no {', '.join(missing)} — recorded with another clock?)"
            )
            continue
        terms.append((term, np.array([entry.parameters[p] for p in term.parameters])))
    return _Carry(terms, extra_payload_kg, not_carried, notes)


def _carried_record(
    findings: FindingsResult,
    carry: _Carry,
    corrected: CorrectedRecording,
    names: tuple[str, ...],
) -> tuple[list[str], ModelCorrections]:
    """What the user reads about a carry (one line each) and the result JSON's record."""
    not_carried = carry.not_carried + [
        f"{describe(term, names)} ({reason})" for term, reason in corrected.skipped
    ]
    notes = [f"not carried: {line}" for line in not_carried] + carry.notes
    notes += [
        f"undone on the recording at its discovered value: {describe(term, names)}"
        for term in corrected.applied
    ]
    values = {term.key: v for term, v in carry.terms}
    record = ModelCorrections(
        gravity_base_m_s2=findings.options.gravity_base_m_s2,
        payload_kg=findings.options.payload_kg,
        corrections=[
            _model_correction(term, values[term.key], corrected.feature_means, names)
            for term in corrected.applied
        ],
        not_carried=not_carried,
    )
    model = findings.model
    calibrated = [*model.calibrate_compliant_joints, *model.calibrate_virtual_axes_at]
    if calibrated:
        notes.append(f"calibrated afresh: compliance/flex of {', '.join(calibrated)}")
    if (
        carry.extra_payload_kg
        or model.calibrate_gravity_base_m_s2 != findings.options.gravity_base_m_s2
    ):
        gravity = ", ".join(f"{g:.4g}" for g in model.calibrate_gravity_base_m_s2)
        notes.append(
            f"gravity [{gravity}] m/s² and {carry.extra_payload_kg:+.3g} kg payload from the "
            "findings"
        )
    return notes, record


def carry_model(
    findings: FindingsResult, dataset: PoseDataset, robot: RobotDescription
) -> CarriedModel:
    """The discovered model of ``findings`` applied to ``dataset`` for the calibration."""
    chain = findings_chain(findings, robot)
    bank = FeatureBank(probe_chain(chain), solver_data(dataset, findings.options))
    carry = _carry_terms(findings, chain, bank)
    corrected = correct_recording(bank, carry.terms)
    notes, record = _carried_record(findings, carry, corrected, chain.joint_names)
    pose = corrected.measured_pose
    payload = dataset.payload_kg
    out = dataclasses.replace(
        dataset,
        joint_positions=corrected.joint_positions,
        position_m=pose[:, :3, 3],
        quaternion_xyzw=None
        if dataset.quaternion_xyzw is None
        else lie.matrix_to_quaternion_xyzw(pose[:, :3, :3]),
        payload_kg=None if payload is None else payload + carry.extra_payload_kg,
    )
    return CarriedModel(
        dataset=out,
        corrections=[describe(term, chain.joint_names) for term in corrected.applied],
        notes=notes,
        record=record,
    )


def carry_measured(
    findings: FindingsResult,
    recording: measurement_input.MeasuredRecording,
    robot: RobotDescription,
    chain: KinematicChain,
    options: CalibrationOptions,
) -> CarriedMeasurement:
    """The discovered model of ``findings`` applied to a recording of another measurement
    type (ball in socket, markers, pose components, a frame on the base, a sensor on the
    chain), read for the calibration's ``chain`` and (carried) ``options``.

    Joint-angle terms (gear, backlash, scale, a joint's drift) are undone on the joint
    readings, which every type has: the robot stood at the corrected angles whatever measured
    it, and the loads are swept again at them. The sensor's terms (depth scale, drift of the
    measurement frame) are undone on a measured pose where the rows hold one (components,
    relative-base, eye-on-head) and not carried otherwise (sockets measure nothing; a marker
    set's depth and drift are not the flange frame's), with that reason. Compliance, flex,
    gravity and payload are the calibration's options (:func:`carried_options`), as for a
    pose recording. The features are those the discovery saw (:func:`measured_data`)."""
    discovery_chain = findings_chain(findings, robot)
    data, _, _ = measured_data(recording, findings.options)
    bank = FeatureBank(probe_chain(discovery_chain), data)
    carry = _carry_terms(findings, discovery_chain, bank)
    names = discovery_chain.joint_names
    measured = recording.rows.measured
    holds_pose = measured.shape[1:] == (4, 4)
    if not holds_pose:
        sensor = [(t, v) for t, v in carry.terms if not t.axes]
        carry = dataclasses.replace(
            carry,
            terms=[(t, v) for t, v in carry.terms if t.axes],
            not_carried=carry.not_carried
            + [
                f"{describe(t, names)} (changes what a sensor reports; the rows of "
                f"'{recording.model.name}' hold no measured pose to undo it on)"
                for t, _ in sensor
            ],
        )
    corrected = correct_recording(bank, carry.terms)
    notes, record = _carried_record(findings, carry, corrected, names)
    out = measurement_input.with_rows(
        recording,
        chain,
        options,
        corrected.joint_positions,
        corrected.measured_pose if holds_pose else measured,
    )
    return CarriedMeasurement(out, notes, record)


MODEL_OPTIONS = (
    "compliant_joints",
    "virtual_axes_at",
    "gravity_base_m_s2",
    "payload_kg",
    "payload_com_m",
)
"""The calibration options a carried model sets (``calibrate --model``, ``discovery_id``)."""


def model_options_set(options: CalibrationOptions) -> list[str]:
    """The :data:`MODEL_OPTIONS` of ``options`` away from their defaults. A carried model
    replaces them, so they are refused rather than silently dropped."""
    default = CalibrationOptions()
    return [name for name in MODEL_OPTIONS if getattr(options, name) != getattr(default, name)]


def model_options(findings: FindingsResult) -> dict[str, object]:
    """The :data:`MODEL_OPTIONS` a discovery's model sets: its compliant joints and flex axes,
    gravity and payload (calibrated afresh by the calibration that carries it)."""
    model = findings.model
    return {
        "compliant_joints": list(model.calibrate_compliant_joints),
        "virtual_axes_at": list(model.calibrate_virtual_axes_at),
        "gravity_base_m_s2": model.calibrate_gravity_base_m_s2,
        "payload_kg": model.calibrate_payload_kg,
        "payload_com_m": findings.options.payload_com_m,
    }


def carried_options(options: CalibrationOptions, findings: FindingsResult) -> CalibrationOptions:
    """``options`` with the discovered model's compliance, flex axes, gravity and payload: the
    one merge of ``calibrate --model`` and of the service's calibrations with a discovery.
    :class:`ModelError` naming the :data:`MODEL_OPTIONS` set as well."""
    given = model_options_set(options)
    if given:
        raise ModelError(
            f"{', '.join(given)}: the discovered model sets them; leave them at their defaults "
            "(discover with them instead)"
        )
    try:
        return CalibrationOptions.model_validate(
            {**options.model_dump(), **model_options(findings)}
        )
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ModelError(f"the discovered model gives an invalid {where}: {first['msg']}") from exc


def _model_correction(
    term: Term, values: np.ndarray, feature_means: dict[str, float], names: tuple[str, ...]
) -> ModelCorrection:
    """One carried term as the result JSON records it, with why predict cannot apply it."""
    applicable = applicable_at_new_configurations(term)
    reason = None
    if not applicable:
        if term.joint_index is None:
            reason = "changes what the sensor reports, not where the robot stands"
        elif term.effect == "thermal_drift":
            reason = "depends on the time since the recording started"
        else:
            reason = "depends on the direction the joint was approached from (execution order)"
    return ModelCorrection(
        effect=term.effect,
        joint=None if term.joint_index is None else names[term.joint_index],
        variant=term.variant,
        description=describe(term, names),
        parameters={p: float(v) for p, v in zip(term.parameters, values, strict=True)},
        feature_means={a.feature: feature_means[a.feature] for a in term.axes},
        applied_in_prediction=applicable,
        reason=reason,
    )
