"""Missing-physics discovery pipeline: dataset + robot + options -> findings JSON (+ plots).

The CLI (``kincal discover``) and the HTTP service both call :func:`discover`; the maths is in
:mod:`solver.discovery`.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import re
import time
from pathlib import Path

import numpy as np
import pydantic

from schemas.calibration import (
    CalibrationOptions,
    DatasetInfo,
    ModelCorrection,
    ModelCorrections,
)
from schemas.dataset import PoseDataset
from schemas.discovery import (
    EFFECTS,
    Ambiguity,
    Candidate,
    Dependence,
    Detectability,
    DetectableSize,
    DiscoveredModel,
    DiscoveryMeasurement,
    DiscoveryOptions,
    Effect,
    ErrorPair,
    Finding,
    FindingsResult,
    Health,
    HealthPair,
    Heldout,
    ModelTerm,
    NotCandidate,
    OutlierScreen,
    RandomEffect,
    RobotRef,
    Step,
    Unexplained,
)
from schemas.robots import RobotDescription
from service.app import calibrate_measurement as measurement_run
from service.render.chain import chain_for
from service.render.result_json import kincal_version
from solver import discovery as solver_discovery
from solver import lie
from solver.discovery.carry import (
    CorrectedRecording,
    applicable_at_new_configurations,
    correct_recording,
    is_correction,
)
from solver.discovery.explain import describe, reported_parameters
from solver.discovery.features import FeatureBank, probe_chain
from solver.discovery.fitting import ModelParameters as FitParameters
from solver.discovery.health import HealthReport
from solver.discovery.library import UNEXPLAINED, Term, library_term
from solver.discovery.results import HeldoutError, PlotPanel, TermEstimate
from solver.errors import ModelError
from solver.measurement import ModelParameters as MeasuredParameters
from solver.measurement import RelativeBase
from solver.model import KinematicChain

__all__ = [
    "EFFECTS",
    "CarriedModel",
    "carry_model",
    "chain_for",
    "discover",
    "discover_source",
    "summary",
]

PROTOCOL = "{k}-fold cross-validation (seed {seed}), the same folds before and after"


def solver_options(options: DiscoveryOptions) -> solver_discovery.DiscoveryOptions:
    sensor = None
    if options.sensor_sigma_mm is not None and options.sensor_sigma_deg is not None:
        sensor = (options.sensor_sigma_mm * 1e-3, math.radians(options.sensor_sigma_deg))
    return solver_discovery.DiscoveryOptions(
        alpha=options.alpha,
        seed=options.seed,
        max_terms=options.max_terms,
        folds=options.folds,
        bootstrap=options.bootstrap,
        effects=tuple(options.effects),
        sensor_sigma=sensor,
        outlier_level=options.outlier_level,
        heldout_level=options.heldout_level,
        detectability=options.detectability,
    )


def discover(
    dataset: PoseDataset,
    robot: RobotDescription,
    options: DiscoveryOptions,
    plot_dir: Path | None = None,
    plot_stem: str = "findings",
) -> FindingsResult:
    """Run discovery on a pose/position recording; with ``plot_dir`` also write one PNG per
    finding there."""
    started = time.perf_counter()
    return _discover(
        solver_data(dataset, options), dataset.source, robot, options, plot_dir, plot_stem, started
    )


def discover_source(
    source: Path,
    robot: RobotDescription,
    options: DiscoveryOptions,
    plot_dir: Path | None = None,
    plot_stem: str = "findings",
    *,
    marker: int | None = None,
    name: str | None = None,
) -> FindingsResult:
    """Run discovery on a recording file or folder, read as ``kincal calibrate`` reads it for
    ``options.measurement`` (:mod:`service.app.calibrate_measurement`: a platonics
    ball-in-socket folder, a FIGAROH file with all its markers, chosen pose components, ...)."""
    started = time.perf_counter()
    read = read_source(source, robot, options, marker=marker, name=name)
    return _discover(
        read.data,
        read.source,
        robot,
        options.model_copy(update={"effects": read.effects})
        if read.effects is not None
        else options,
        plot_dir,
        plot_stem,
        started,
        read.measurement,
    )


@dataclasses.dataclass(frozen=True)
class SourceData:
    """A recording as discovery reads it: its rows, where they came from, the library
    effects its measurement can see (None: as asked) and what the findings say about the
    measurement (None for pose and position rows)."""

    data: solver_discovery.DiscoveryData
    source: str
    effects: list[Effect] | None
    measurement: DiscoveryMeasurement | None


def read_source(
    source: Path,
    robot: RobotDescription,
    options: DiscoveryOptions,
    *,
    marker: int | None = None,
    name: str | None = None,
) -> SourceData:
    """Read a recording file or folder as ``kincal calibrate`` reads it for
    ``options.measurement`` (:mod:`service.app.calibrate_measurement`)."""
    chain = chain_for(robot, options)
    measurement_run.check_sensor_joint(options.measurement, chain)
    reading = measurement_options(options)
    model = measurement_run.measurement_for(reading, chain, source, marker)
    if model is None:
        dataset = measurement_run.read_chain_dataset(source, chain, marker, name)
        return SourceData(solver_data(dataset, options), dataset.source, None, None)
    recording = measurement_run.read_measured(
        source, chain, reading, model, marker=marker, name=name
    )
    data, described, effects = measured_data(recording, options)
    return SourceData(data, recording.source, effects, described)


def measurement_options(options: DiscoveryOptions) -> CalibrationOptions:
    """The calibration options :mod:`service.app.calibrate_measurement` reads a recording with."""
    return CalibrationOptions(
        measurement=options.measurement,
        point_distance_m=options.point_distance_m,
        gravity_base_m_s2=options.gravity_base_m_s2,
        payload_kg=options.payload_kg,
    )


LEFT_OUT: dict[str, dict[str, str]] = {
    "point": {
        "depth_scale": "no sensor measures the ball: nothing is read along a camera's depth "
        "axis (the sockets are fixed points of the robot base frame)",
    },
    "markers": {
        "depth_scale": "a camera's depth scale moves each marker along its own line of sight, "
        "not the flange frame the library's column moves; not modelled for several markers",
    },
    "components": {
        "depth_scale": "the components are measured in the frame of a contact (e.g. a plane), "
        "not along a camera's depth axis",
    },
}
"""Library effects a measurement cannot see, with the reason (reported in ``left_out``)."""


def measured_data(
    recording: measurement_run.MeasuredRecording, options: DiscoveryOptions
) -> tuple[solver_discovery.DiscoveryData, DiscoveryMeasurement, list[Effect] | None]:
    """The rows of a measurement model as discovery sees them, what the findings say about
    the measurement, and the library effects searched (None: as asked)."""
    model, rows = recording.model, recording.rows
    n = rows.n
    pose_rows = isinstance(model, RelativeBase)
    kind = model.name
    measured_pose = (
        rows.measured
        if rows.measured.shape[1:] == (4, 4)
        else _marker_positions_as_poses(rows.measured, n)
    )
    data = solver_discovery.DiscoveryData(
        joint_positions=rows.joint_positions,
        measured_pose=measured_pose,
        position_only=recording.position_only,
        payload_kg=np.full(n, options.payload_kg),
        gravity_base=np.asarray(options.gravity_base_m_s2, dtype=float),
        measurement=None if pose_rows else model,
        measured=None if pose_rows or rows.measured.shape[1:] == (4, 4) else rows.measured,
        group=rows.group,
    )
    reasons = LEFT_OUT.get(kind, {})
    left_out = [
        f"{effect}: {reason}" for effect, reason in reasons.items() if effect in options.effects
    ]
    effects = [e for e in options.effects if e not in reasons] if reasons else None
    frame = (
        "end effector (tip) frame; the measurement frame is the marker on the robot base, "
        "fitted as the measurement frame always is"
        if pose_rows
        else model.frame
    )
    described = DiscoveryMeasurement(
        type=options.measurement if options.measurement != "auto" else kind,
        frame=frame,
        components=list(model.components),
        labels=list(recording.labels),
        left_out=left_out,
    )
    return data, described, effects


def _marker_positions_as_poses(measured: np.ndarray, n: int) -> np.ndarray:
    """Identity poses at the mean marker position (N, 4, 4) (sockets: at the origin)."""
    pose = np.tile(np.eye(4), (n, 1, 1))
    if measured.ndim == 3 and measured.shape[2] == 3 and measured.shape[1]:
        pose[:, :3, 3] = measured.mean(axis=1)
    return pose


def _discover(
    data: solver_discovery.DiscoveryData,
    source: str,
    robot: RobotDescription,
    options: DiscoveryOptions,
    plot_dir: Path | None,
    plot_stem: str,
    started: float,
    measurement: DiscoveryMeasurement | None = None,
) -> FindingsResult:
    chain = chain_for(robot, options)
    result = solver_discovery.discover(chain, data, solver_options(options))
    if measurement is not None and not data.is_pose:
        measurement = measurement.model_copy(
            update={
                **_measured_unknowns(chain, data, result.params),
                "not_candidates": _not_candidates(result, data, chain.joint_names),
            }
        )
    names = chain.joint_names
    plots: list[str] = []
    findings = []
    for i, f in enumerate(result.findings, start=1):
        plot = None
        if plot_dir is not None and f.panels:
            label = _slug(describe(f.estimate.term, names))
            path = plot_dir / f"{plot_stem}_{i:02d}_{label}.png"
            finding_figure(f.panels, f.explanation, path)
            plot = path.name
            plots.append(plot)
        findings.append(_finding(f, names, options, plot))
    return FindingsResult(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        dataset=DatasetInfo(
            source=source, n_samples=data.n_samples, position_only=data.position_only
        ),
        robot=RobotRef(
            name=robot.name,
            base_frame=robot.base_frame,
            tip_frame=robot.tip_frame,
            joint_names=list(names),
            urdf_sha256=chain.urdf_sha256,
        ),
        options=options,
        findings=findings,
        ambiguous=[_ambiguity(a, names) for a in result.ambiguous],
        unexplained=[_unexplained(u, names) for u in result.unexplained],
        random_effects=[
            RandomEffect(
                joint=names[r.joint_index],
                p_value=r.p_value,
                variance_ratio=r.variance_ratio,
                explanation=r.explanation,
            )
            for r in result.random_effects
        ],
        heldout=_heldout(result.heldout_before, result.heldout_after, options),
        health=HealthPair(
            before=_health(result.health_before, names),
            after=_health(result.health_after, names),
        ),
        steps=[
            Step(
                step=s.step,
                candidate=s.candidate,
                action=s.action,  # type: ignore[arg-type]
                p_value=None if math.isnan(s.p_value) else s.p_value,
                heldout_before_mm=s.heldout_before_mm,
                heldout_after_mm=s.heldout_after_mm,
            )
            for s in result.steps
        ],
        outliers=OutlierScreen(
            level=options.outlier_level,
            removed_rows=[int(i) + 1 for i in result.outlier_rows],
        ),
        model=_model(result, names, options),
        n_candidates=result.n_candidates,
        detectability=_detectability(result, names),
        plots=plots,
        measurement=measurement,
        elapsed_s=time.perf_counter() - started,
    )


def _measured_unknowns(
    chain: KinematicChain, data: solver_discovery.DiscoveryData, params: FitParameters
) -> dict[str, object]:
    """The measurement model's own unknowns and its known-distance residuals at the final
    model (``params``: the discovery's :class:`~solver.discovery.fitting.ModelParameters`)."""
    model = data.model
    extra = params.extra
    probe = probe_chain(chain)
    measured = MeasuredParameters(params.links, np.zeros(len(probe.compliance_axes)), extra)
    residual, _ = model.constraints(probe, measured)
    weight = getattr(model, "distance_weight", 1.0)
    return {
        "unknowns": {n: float(v) for n, v in zip(model.extra_names(), extra, strict=True)},
        "constraint_residuals_m": [float(v) / weight for v in residual],
    }


def _not_candidates(
    result: solver_discovery.DiscoveryResult,
    data: solver_discovery.DiscoveryData,
    names: tuple[str, ...],
) -> list[NotCandidate]:
    """The library terms the measurement cannot see (``result.unseen``), each with why: the
    measurement cancels it, or the model's own columns reproduce it on these rows."""
    sensor = data.model.sensor_joint_index
    cancels = (
        f"a sensor riding on the body after {names[sensor]} moves with it, so the term moves "
        "the sensor and the tip alike"
        if sensor is not None
        else f"what is measured ({data.model.frame}) does not change with it"
    )
    absorbed = (
        "the model's own columns (link corrections, the measurement's unknowns) reproduce it "
        "exactly on these rows"
    )
    return [
        NotCandidate(
            effect=u.term.effect,  # type: ignore[arg-type]
            joint=_joint(u.term.joint_index, names),
            variant=u.term.variant,
            description=describe(u.term, names),
            remaining_fraction=u.left,
            reason=f"its effect cancels in the residual ({u.left:.1g} of a column left after "
            f"the model's own columns): {cancels if u.cancelled else absorbed}",
        )
        for u in result.unseen
    ]


def solver_data(dataset: PoseDataset, options: DiscoveryOptions) -> solver_discovery.DiscoveryData:
    """The recording as discovery sees it (gravity and payload of the user's model)."""
    payload = dataset.payload_kg
    return solver_discovery.DiscoveryData(
        joint_positions=dataset.joint_positions,
        measured_pose=lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw),
        position_only=dataset.is_position_only,
        time_s=dataset.time_s,
        payload_kg=payload
        if payload is not None
        else np.full(dataset.n_samples, options.payload_kg),
        gravity_base=np.asarray(options.gravity_base_m_s2, dtype=float),
    )


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

    recording: measurement_run.MeasuredRecording
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
        if dataset.is_position_only
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
    recording: measurement_run.MeasuredRecording,
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
    out = measurement_run.with_rows(
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


def summary(findings: FindingsResult) -> str:
    """What a user reads after ``kincal discover``."""
    lines = [
        f"tested {findings.n_candidates} library terms on {findings.dataset.n_samples} samples "
        f"({len(findings.outliers.removed_rows)} gross outliers left out)"
    ]
    for f in findings.findings:
        lines.append(f"found: {f.explanation}")
    for a in findings.ambiguous:
        lines.append(f"ambiguous: {a.explanation}")
    for u in findings.unexplained:
        text = u.explanation
        lines.append(text if text.startswith("unexplained") else f"unexplained: {text}")
    for r in findings.random_effects:
        lines.append(f"random: {r.explanation}")
    unseen = [] if findings.measurement is None else findings.measurement.not_candidates
    if unseen:
        joints = sorted({u.joint for u in unseen if u.joint}, key=findings.robot.joint_names.index)
        lines.append(
            f"not candidates: {len(unseen)} library terms "
            f"{'on ' + ', '.join(joints) + ' ' if joints else ''}whose effect cancels in what is "
            "measured (each with the reason in measurement.not_candidates)"
        )
    if not (findings.findings or findings.ambiguous or findings.unexplained):
        lines.append("nothing missing: no library term or structure is significant")
    if findings.detectability is not None and findings.detectability.sizes:
        lines += detectability_lines(findings.detectability)
    elif findings.detectability is None:
        lines.append("smallest detectable sizes: not computed (--no-detectability)")
    before, after = findings.heldout.before, findings.heldout.after
    rot = (
        ""
        if before.rot_deg is None or after.rot_deg is None
        else f", {before.rot_deg:.3g} → {after.rot_deg:.3g} deg"
    )
    lines.append(f"held-out error: {before.trans_mm:.3g} → {after.trans_mm:.3g} mm{rot}")
    return "\n".join(lines)


# Display scale and unit of a size by the end of its parameter name (first match wins).
DISPLAY_UNITS = (
    ("_rad_per_nm", 1e6, "µrad/N·m"),
    ("_rad_per_s", 3.6e6, "mrad/h"),
    ("_rad_per_sample", 1e5, "mrad/100 samples"),
    ("_m_per_s", 3.6e6, "mm/h"),
    ("_m_per_sample", 1e5, "mm/100 samples"),
    ("_rad", 1e3, "mrad"),
    ("_m", 1e3, "mm"),
    ("_kg", 1.0, "kg"),
    ("scale", 1e3, "mm/m"),
    ("scale_error", 1e3, "mm/m"),
)


def display_size(
    value: float | None,
    parameter: str,
    reason: str | None = None,
    separated_from: str | None = None,
) -> str:
    """A detectable size in an engineer's unit, e.g. ``0.12 mrad``; ``–`` when none, with the
    reason when one is given, and the term it must be told from when that set the size."""
    if value is None:
        return f"– ({reason})" if reason else "–"
    shown = f"{value:.2g}"
    for suffix, scale, unit in DISPLAY_UNITS:
        if parameter.endswith(suffix):
            shown = f"{value * scale:.2g} {unit}"
            break
    return f"{shown} (to tell from {separated_from})" if separated_from else shown


def detectability_groups(
    detectability: Detectability,
) -> dict[str, list[DetectableSize]]:
    """Detectable sizes by term label (effect, variant, size parameter when it is not the
    only one), in report order."""
    groups: dict[str, list[DetectableSize]] = {}
    for size in detectability.sizes:
        variant = f" ({size.variant})" if size.variant else ""
        part = (
            size.parameter.split("_")[0]
            if size.parameter.startswith(("translation", "rotation"))
            else ""
        )
        label = f"{size.effect}{variant}" + (f" {part}" if part else "")
        groups.setdefault(label, []).append(size)
    return groups


def detectability_lines(detectability: Detectability) -> list[str]:
    """The CLI's statement of what this recording could have seen."""
    lines = [
        f"smallest detectable sizes (score test at {detectability.level:.2g} per term, "
        f"{detectability.power:.0%} power; at least the size at which it is told from the "
        "library term named) — nothing larger went unseen:"
    ]
    for label, sizes in detectability_groups(detectability).items():
        shown = ", ".join(
            f"{s.joint + ' ' if s.joint else ''}"
            f"{display_size(s.smallest, s.parameter, s.reason, s.separated_from)}"
            for s in sizes
        )
        lines.append(f"  {label}: {shown}")
    return lines


# --- conversion ------------------------------------------------------------------------------


def _detectability(
    result: solver_discovery.DiscoveryResult, names: tuple[str, ...]
) -> Detectability | None:
    if result.detectable is None:
        return None
    return Detectability(
        level=result.detection_level,
        power=result.detection_power,
        sizes=[
            DetectableSize(
                effect=d.term.effect,  # type: ignore[arg-type]
                joint=_joint(d.term.joint_index, names),
                variant=d.term.variant,
                parameter=d.parameter,
                smallest=d.smallest if math.isfinite(d.smallest) else None,
                reason=d.reason or None,
                separated_from=None
                if d.separated_from is None
                else describe(d.separated_from, names),
            )
            for d in result.detectable
        ],
    )


def _pair(error: HeldoutError) -> ErrorPair:
    return ErrorPair(trans_mm=error.translation_mm, rot_deg=error.rotation_deg)


def _heldout(before: HeldoutError, after: HeldoutError, options: DiscoveryOptions) -> Heldout:
    return Heldout(
        before=_pair(before),
        after=_pair(after),
        protocol=PROTOCOL.format(k=options.folds, seed=options.seed),
    )


def _finite(values: dict[str, float]) -> dict[str, float]:
    return {k: float(v) for k, v in values.items() if math.isfinite(v)}


def _joint(index: int | None, names: tuple[str, ...]) -> str | None:
    return None if index is None else names[index]


def _finding(
    f: solver_discovery.Finding,
    names: tuple[str, ...],
    options: DiscoveryOptions,
    plot: str | None,
) -> Finding:
    e = f.estimate
    return Finding(
        effect=e.term.effect,  # type: ignore[arg-type]
        joint=_joint(e.term.joint_index, names),
        variant=e.term.variant,
        parameters=_finite(e.parameters),
        stderr=_finite(e.stderr),
        p_value=e.p_value,
        absorbed_fraction=e.absorbed_fraction,
        stability=e.stability,
        heldout=_heldout(f.heldout_before, f.heldout_after, options),
        explanation=f.explanation,
        plot=plot,
    )


def _candidate(e: TermEstimate, names: tuple[str, ...]) -> Candidate:
    return Candidate(
        effect=e.term.effect,  # type: ignore[arg-type]
        joint=_joint(e.term.joint_index, names),
        variant=e.term.variant,
        parameters=_finite(e.parameters),
        stderr=_finite(e.stderr),
        p_value=e.p_value,
        absorbed_fraction=e.absorbed_fraction,
    )


def _ambiguity(a: solver_discovery.Ambiguity, names: tuple[str, ...]) -> Ambiguity:
    poses = a.poses
    return Ambiguity(
        candidates=[_candidate(c, names) for c in a.candidates],
        with_geometry=a.with_geometry,
        correlation=a.correlation,
        kept_in_model=None if a.kept is None else describe(a.kept, names),
        separating_poses=[]
        if poses is None
        else [dict(zip(names, map(float, q), strict=True)) for q in poses.configurations],
        separation_now_sigma=None if poses is None else poses.separation_now_sigma,
        separation_after_sigma=None if poses is None else poses.separation_after_sigma,
        explanation=a.explanation,
    )


def _unexplained(u: solver_discovery.Unexplained, names: tuple[str, ...]) -> Unexplained:
    return Unexplained(
        joint=_joint(u.joint_index, names),
        variable=u.variable,
        p_value=None if math.isnan(u.p_value) else u.p_value,
        explained_fraction=None if math.isnan(u.explained_fraction) else u.explained_fraction,
        distance_correlation=u.distance_correlation,
        partially_described_by=u.partial,
        explanation=u.explanation,
    )


def _health(report: HealthReport, names: tuple[str, ...]) -> Health:
    return Health(
        n_samples=report.n_samples,
        n_parameters=report.n_parameters,
        sigma_translation_mm=report.sigma_translation_mm,
        sigma_rotation_deg=report.sigma_rotation_deg,
        rms_translation_mm=report.rms_translation_mm,
        rms_rotation_deg=report.rms_rotation_deg,
        chi2_per_dof=report.chi2_per_dof,
        dependences=[
            Dependence(
                variable=d.variable,
                joint=_joint(d.joint_index, names),
                p_value=d.p_value,
                explained_fraction=d.explained_fraction,
                components=d.components,
            )
            for d in report.dependences
        ],
    )


def _model(
    result: solver_discovery.DiscoveryResult, names: tuple[str, ...], options: DiscoveryOptions
) -> DiscoveredModel:
    """The final model; the compliance-like part maps onto ``kincal calibrate`` options."""
    values = {}
    start = 0
    for t in result.terms:
        values[t.key] = result.params.theta[start : start + t.size]
        start += t.size
    compliant = list(options.compliant_joints)
    virtual = list(options.virtual_axes_at)
    gravity = np.asarray(options.gravity_base_m_s2, dtype=float)
    payload = options.payload_kg
    terms, corrections, not_carried = [], [], []
    for t in result.terms:
        params, _ = reported_parameters(t, values[t.key], np.zeros((t.size, t.size)))
        label = describe(t, names) if t.effect != UNEXPLAINED else f"unexplained {t.variant}"
        terms.append(
            ModelTerm(
                effect=t.effect,
                joint=_joint(t.joint_index, names),
                variant=t.variant,
                parameters=_finite(params),
            )
        )
        if t.declared:
            continue
        if t.effect == "joint_compliance" and t.joint_index is not None:
            compliant.append(names[t.joint_index])
        elif t.effect in ("base_flex", "link_bending") and t.joint_index is not None:
            virtual.append(names[t.joint_index])
        elif t.effect == "gravity_direction":
            tilt = np.r_[values[t.key], 0.0]
            gravity = lie.so3_exp(tilt) @ gravity
        elif t.effect == "payload_mass":
            payload += float(values[t.key][0])
        elif is_correction(t):
            corrections.append(label)
        else:
            not_carried.append(label)
    return DiscoveredModel(
        terms=terms,
        calibrate_compliant_joints=sorted(set(compliant), key=names.index),
        calibrate_virtual_axes_at=sorted(set(virtual), key=names.index),
        calibrate_gravity_base_m_s2=(float(gravity[0]), float(gravity[1]), float(gravity[2])),
        calibrate_payload_kg=max(payload, 0.0),
        corrections=corrections,
        not_carried=not_carried,
    )


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")[:60]


# --- figures ---------------------------------------------------------------------------------


def finding_figure(panels: list[PlotPanel], title: str, path: Path) -> Path:
    """Residuals against the variable that drives a term: before (model without it) and after.

    Angles are shown in mrad; the fitted term is the line the "before" points should follow.
    """
    from matplotlib.figure import Figure  # plotting only: kept out of a calibration's start-up

    figure = Figure(figsize=(5.2 * len(panels), 3.6), layout="constrained")
    axes = figure.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels, strict=True):
        scale, unit = (1e3, "mrad") if "[rad]" in panel.value_label else (1e3, "mm / mrad")
        order = np.argsort(panel.driver)
        ax.scatter(
            panel.driver,
            panel.before * scale,
            s=9,
            alpha=0.55,
            color="tab:red",
            label="before (without the term)",
        )
        ax.scatter(
            panel.driver,
            panel.after * scale,
            s=9,
            alpha=0.65,
            color="tab:blue",
            label="after (with the term)",
        )
        ax.plot(
            panel.driver[order],
            panel.fitted[order] * scale,
            color="black",
            lw=1.2,
            label="fitted term",
        )
        ax.set_xlabel(panel.driver_label)
        ax.set_ylabel(
            panel.value_label.replace("[rad]", f"[{unit}]").replace("(m / rad)", f"[{unit}]")
        )
        ax.axhline(0.0, color="grey", lw=0.6)
    axes[0].legend(fontsize=7, loc="best")
    figure.suptitle(_wrap(title, 70 * len(panels)), fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    return path


def _wrap(text: str, width: int) -> str:
    words, lines, line = text.split(), [], ""
    for word in words:
        if len(line) + len(word) + 1 > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    lines.append(line)
    return "\n".join(lines)
