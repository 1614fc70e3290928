"""Missing-physics discovery pipeline: dataset + robot + options -> findings JSON (+ plots).

The CLI (``kincal discover``) and the HTTP service both call :func:`discover`; the maths is in
:mod:`solver.discovery`.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import time
from pathlib import Path

import numpy as np

from schemas.calibration import (
    CalibrationOptions,
    DatasetInfo,
)
from schemas.dataset import PoseDataset
from schemas.discovery import (
    EFFECTS,
    DiscoveryMeasurement,
    DiscoveryOptions,
    Effect,
    FindingsResult,
    HealthPair,
    NotCandidate,
    OutlierScreen,
    RandomEffect,
    RobotRef,
    Step,
)
from schemas.robots import RobotDescription
from service import kincal_version
from service.app import measurement_input
from service.render.chain import chain_for
from service.render.findings import (
    ambiguity_schema,
    detectability_schema,
    finding_figure,
    finding_schema,
    health_schema,
    heldout_schema,
    joint_name,
    model_schema,
    slug,
    unexplained_schema,
)
from solver import discovery as solver_discovery
from solver import lie
from solver.discovery.explain import describe
from solver.discovery.features import probe_chain
from solver.discovery.fitting import ModelParameters as FitParameters
from solver.executors import Executor
from solver.measurement import ModelParameters as MeasuredParameters
from solver.measurement import RelativeBase
from solver.measurement.pose import pose_measurement
from solver.model import KinematicChain

__all__ = ["EFFECTS", "chain_for", "discover", "discover_source"]


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
    executor: Executor | None = None,
) -> FindingsResult:
    """Run discovery on a recording file or folder, read as ``kincal calibrate`` reads it for
    ``options.measurement`` (:mod:`service.app.calibrate_measurement`: a platonics
    ball-in-socket folder, a FIGAROH file with all its markers, chosen pose components, ...);
    ``executor``: where the detectable sizes are computed (None: in this process; the
    findings do not depend on it)."""
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
        executor,
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
    measurement_input.check_sensor_joint(options.measurement, chain)
    reading = measurement_options(options)
    model = measurement_input.measurement_for(reading, chain, source, marker)
    if model is None:
        dataset = measurement_input.read_chain_dataset(source, chain, marker, name)
        return SourceData(solver_data(dataset, options), dataset.source, None, None)
    recording = measurement_input.read_measured(
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
    recording: measurement_input.MeasuredRecording, options: DiscoveryOptions
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
        pose_model=pose_measurement(rotation=recording.rotation),
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
    executor: Executor | None = None,
) -> FindingsResult:
    chain = chain_for(robot, options)
    result = solver_discovery.discover(chain, data, solver_options(options), executor)
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
            label = slug(describe(f.estimate.term, names))
            path = plot_dir / f"{plot_stem}_{i:02d}_{label}.png"
            finding_figure(f.panels, f.explanation, path)
            plot = path.name
            plots.append(plot)
        findings.append(finding_schema(f, names, options, plot))
    return FindingsResult(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        dataset=DatasetInfo(  # the findings document's field (public), from the rows' model
            source=source,
            n_samples=data.n_samples,
            measures_rotation=data.pose_model.measures_rotation,
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
        ambiguous=[ambiguity_schema(a, names) for a in result.ambiguous],
        unexplained=[unexplained_schema(u, names) for u in result.unexplained],
        random_effects=[
            RandomEffect(
                joint=names[r.joint_index],
                p_value=r.p_value,
                variance_ratio=r.variance_ratio,
                explanation=r.explanation,
            )
            for r in result.random_effects
        ],
        heldout=heldout_schema(result.heldout_before, result.heldout_after, options),
        health=HealthPair(
            before=health_schema(result.health_before, names),
            after=health_schema(result.health_after, names),
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
        model=model_schema(result, names, options),
        n_candidates=result.n_candidates,
        detectability=detectability_schema(result, names),
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
            joint=joint_name(u.term.joint_index, names),
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
        pose_model=dataset.measurement_model,
        time_s=dataset.time_s,
        payload_kg=payload
        if payload is not None
        else np.full(dataset.n_samples, options.payload_kg),
        gravity_base=np.asarray(options.gravity_base_m_s2, dtype=float),
    )
