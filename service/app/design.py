"""Calibration designs (``kincal design``, ``POST /api/v1/designs``): the ONE place the CLI and
the HTTP service call. Robot + :class:`DesignOptions` (+ candidates, task configurations, a
recording and its calibration for a sequential design) -> :class:`DesignResult`.

The chain and its identifiable parameters are the calibration's: the options are checked by
:func:`service.app.calibrate.check_calibration`, a sequential design rebuilds the calibrated chain
from the result JSON (:func:`service.render.result_json.result_chain`). The maths is
:mod:`solver.design`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import configurations_from_frame, read_configurations
from schemas.dataset.constraints import is_socket_folder
from schemas.dataset.readers import read_frame
from schemas.design import (
    ConeVolume,
    CovarianceDesignReport,
    CriterionReport,
    DesignOptions,
    DesignPose,
    DesignResult,
    MeasurementDesignReport,
    ParameterError,
    SequentialReport,
)
from schemas.robots import RobotDescription
from service.app import calibrate as pipeline
from service.app import measurement_input
from service.render import result_json
from solver.arrays import FloatArray, IntArray
from solver.covariance.identifiability import IdentifiabilityReport, analyse_identifiability
from solver.covariance.layout import CovarianceLayout
from solver.covariance.statistics import design_gram
from solver.design import Design, optimal_design
from solver.design.candidates import (
    ViewCone,
    Volume,
    WorkspaceBox,
    outside_limits,
    sample_candidates,
    tip_poses,
)
from solver.design.criteria import DesignProblem
from solver.design.information import (
    CovariancePrior,
    InformationBlock,
    covariance_information,
    frame_jacobians,
    geometry_information,
    model_information,
    model_noise_std,
)
from solver.design.prediction import (
    equilibrated_pose_jacobian,
    predicted_pose_variance,
    standard_errors,
    task_root,
)
from solver.errors import KincalError
from solver.kinematics import ChainParameters
from solver.measurement import (
    FixedPoints,
    KnownDistance,
    MeasurementModel,
    MeasurementRows,
    MultiMarker,
)
from solver.measurement.models import ModelParameters
from solver.model import KinematicChain, gravity_loads

TASK_SAMPLES = 500
"""Task configurations drawn in the working volume when none are given."""
ROUNDING_RULE = (
    "largest relaxed weights first, skipping candidates closer than min_spacing_rad to a chosen "
    "one; then the best single exchange against the 50 candidates of largest directional "
    "derivative while the criterion improves"
)


@dataclass(frozen=True)
class Recorded:
    """A recording already made and its calibration: a sequential design's prior."""

    joint_positions: FloatArray
    result: CalibrationResult


def recorded_design(
    result: CalibrationResult, recording: Path, source: str | None = None
) -> tuple[RobotDescription, Recorded]:
    """The robot (the result's URDF and chain) and the prior of a sequential design from a
    calibration result and the recording it was calibrated from (joint columns read; any
    measured columns ignored). The CLI's ``--result --recording`` and the service's
    ``calibration_id`` both come here."""
    chain, _ = result_json.result_chain(result)
    configurations = read_configurations(
        recording, chain.joint_names, other_joint_names=chain.other_joint_names, source=source
    )
    robot = RobotDescription(
        result.robot.name, result.robot.urdf, result.robot.base_frame, result.robot.tip_frame
    )
    return robot, Recorded(configurations.joint_positions, result)


@dataclass(frozen=True)
class Sockets:
    """Ball-in-socket candidates: the socket of each candidate ``index`` (N,), the sockets'
    names and the known distances between them."""

    index: IntArray
    labels: tuple[str, ...]
    distances: tuple[KnownDistance, ...] = ()

    def take(self, keep: NDArray[np.bool_]) -> Sockets:
        return Sockets(self.index[keep], self.labels, self.distances)


POINT_CANDIDATES = (
    "measurement 'point': ball-in-socket rows need a physical contact, so the candidates must "
    "be configurations recorded in the sockets: give --candidates a platonics folder of "
    "hole_<k>.csv files or a CSV with a 'socket' column (HTTP: candidates_rad and "
    "candidate_sockets); sampled candidates cannot be measured"
)


@dataclass(frozen=True)
class DesignModel:
    """The chain at which the information is evaluated and its settings; ``measurement``
    the model of a type other than pose or position (None for those)."""

    chain: KinematicChain
    params: ChainParameters
    calibration: CalibrationOptions
    noise_std: FloatArray
    prior: CovariancePrior
    measurement: MeasurementModel | None = None


def design_model(
    robot: RobotDescription, options: DesignOptions, recorded: Recorded | None = None
) -> DesignModel:
    """The chain (checked calibration options, or a result's calibrated chain), the sensor
    noise (options, or the result's noise covariance) and the covariance prior; for the other
    measurement types their model (:func:`service.app.calibrate_measurement.measurement_model`, the
    options checked against the robot as a calibration's are)."""
    d = 3 if options.measurement == "position" else 6
    noise_std = np.r_[[options.noise_mm * 1e-3] * 3, [np.radians(options.noise_deg)] * 3]
    kind, _, argument = options.measurement.partition(":")
    if recorded is not None and kind not in ("pose", "position"):
        raise KincalError(
            f"--measurement {options.measurement}: a sequential design (--result, "
            "calibration_id) plans pose or position rows; design the other types without a "
            "recording"
        )
    if recorded is None:
        calibration = options.calibration
        if kind not in ("pose", "position"):
            calibration = calibration.model_copy(update={"measurement": options.measurement})
        setup = pipeline.check_calibration(robot, calibration)
        chain, params, calibration = (
            setup.chain,
            ChainParameters.nominal(setup.chain),
            setup.options,
        )
        names, index = list(setup.covariance_frames), list(setup.covariance_index)
        sigma = np.radians(options.prior_perturbation_deg)
        frames = np.zeros((len(index), 6, 6))
        frames[:, 3:, 3:] = sigma**2 * np.eye(3)
        noise_cov = np.diag(noise_std**2)
        offsets = options.marker_offsets_m or []
        measurement = measurement_input.measurement_model(kind, argument, chain, len(offsets))
        if measurement is not None:
            noise = model_noise_std(measurement, noise_std[0], noise_std[3])
            prior = CovariancePrior((), (), np.zeros((0, 6, 6)), noise_cov)
            return DesignModel(chain, params, calibration, noise, prior, measurement)
    else:
        result = recorded.result
        chain, params = result_json.result_chain(result)
        calibration = result.options
        frames, noise_cov, names, index = _result_covariances(result, chain, noise_std)
        noise_std = np.sqrt(np.diag(noise_cov))
    prior = CovariancePrior(tuple(names), tuple(index), frames, noise_cov)
    return DesignModel(chain, params, calibration, noise_std[:d], prior)


def _result_covariances(
    result: CalibrationResult, chain: KinematicChain, noise_std: FloatArray
) -> tuple[FloatArray, FloatArray, list[str], list[int]]:
    if result.covariance is None:
        names = list(chain.joint_names)
        frames = np.zeros((len(names), 6, 6))
        frames[:, 3:, 3:] = np.eye(3) * 1e-6
        return frames, np.diag(noise_std**2), names, list(range(len(names)))
    chosen = [f for f in result.covariance.frames if f.name in chain.joint_names]
    frames = np.array([f.matrix for f in chosen], dtype=float)
    names = [f.name for f in chosen]
    noise = np.array(result.covariance.noise.matrix, dtype=float)
    # A noise variance the calibration left at zero would make the information infinite:
    # such an axis gets the sensor noise of the options.
    missing = np.diag(noise) <= 0.0
    noise = noise + np.diag(np.where(missing, noise_std**2, 0.0))
    return frames, noise, names, [chain.joint_names.index(n) for n in names]


def volume_of(options: DesignOptions) -> Volume:
    box = None
    if options.box is not None:
        box = WorkspaceBox(np.array(options.box.low_m), np.array(options.box.high_m))
    return Volume(box=box, cone=None if options.cone is None else view_cone(options.cone))


def view_cone(cone: ConeVolume) -> ViewCone:
    return ViewCone(
        np.array(cone.apex_m),
        np.array(cone.axis),
        float(np.radians(cone.half_angle_deg)),
        cone.near_m,
        cone.far_m,
        None if cone.max_incidence_deg is None else float(np.radians(cone.max_incidence_deg)),
        np.array(cone.marker_axis),
    )


def check_configurations(chain: KinematicChain, q: FloatArray, what: str) -> None:
    """Given configurations must be (N, k) and within the joint limits (naming the row)."""
    if q.ndim != 2 or q.shape[1] != chain.n_joints:
        raise KincalError(
            f"{what}: each configuration needs {chain.n_joints} joint positions "
            f"({', '.join(chain.joint_names)})"
        )
    bad = outside_limits(chain, q)
    if bad.size:
        row = int(bad[0])
        joint = int(
            np.flatnonzero(
                (q[row] < chain.lower_limits - 1e-9) | (q[row] > chain.upper_limits + 1e-9)
            )[0]
        )
        raise KincalError(
            f"{what}: row {row} puts {chain.joint_names[joint]} at {q[row, joint]:.4g}, outside "
            f"its limits [{chain.lower_limits[joint]:.4g}, {chain.upper_limits[joint]:.4g}]; "
            "drop or correct that configuration"
        )


def design_loads(model: DesignModel, q: FloatArray) -> FloatArray:
    """Gravity loads (N, n_axes) N·m of configurations q (N, k) under the calibration's
    gravity and payload."""
    return gravity_loads(
        model.chain,
        q,
        gravity_base=np.asarray(model.calibration.gravity_base_m_s2, dtype=float),
        payload_kg=model.calibration.payload_kg,
    )


def candidate_set(
    model: DesignModel,
    options: DesignOptions,
    given: FloatArray | None,
    sockets: Sockets | None = None,
) -> tuple[FloatArray, list[str], Sockets | None]:
    """The candidates: given ones (within limits, those outside the volume dropped with a
    note, and their ``sockets`` with them), or drawn uniformly within the joint limits inside
    the volume (refused for ball in socket: :data:`POINT_CANDIDATES`)."""
    if isinstance(model.measurement, FixedPoints) and (given is None or sockets is None):
        raise KincalError(POINT_CANDIDATES)
    q, notes, inside = candidate_configurations(model.chain, options, given)
    return q, notes, None if sockets is None or inside is None else sockets.take(inside)


def candidate_configurations(
    chain: KinematicChain, options: DesignOptions, given: FloatArray | None
) -> tuple[FloatArray, list[str], NDArray[np.bool_] | None]:
    """Candidate configurations (N, k): the ``given`` ones within the joint limits, those
    outside the working volume dropped with a note (and which were kept), or
    ``options.n_candidates`` drawn uniformly within the joint limits inside the volume."""
    volume = volume_of(options)
    if given is None:
        rng = np.random.default_rng(options.seed)
        return sample_candidates(chain, options.n_candidates, rng, volume), [], None
    check_configurations(chain, given, "candidates")
    inside = volume.contains(tip_poses(chain, given))
    notes = []
    if not inside.all():
        notes.append(f"{int((~inside).sum())} given candidates outside the working volume dropped")
    return given[inside], notes, inside


def read_candidates(path: Path, model: DesignModel) -> tuple[FloatArray, Sockets | None]:
    """Candidates of ``kincal design --candidates``: joint columns of a file (a recording
    works too); for measurement 'point' a platonics folder of hole_<k>.csv files (read as
    ``kincal calibrate`` reads it: sockets, and with ``point_distance_m`` the known distance
    of each placement's hole_0/hole_1) or a file with a ``socket`` column."""
    chain = model.chain
    if not isinstance(model.measurement, FixedPoints):
        q = read_configurations(
            path, chain.joint_names, other_joint_names=chain.other_joint_names
        ).joint_positions
        return q, None
    if is_socket_folder(path):
        recording = measurement_input.read_measured(path, chain, model.calibration, FixedPoints(1))
        points = recording.model
        assert isinstance(points, FixedPoints)
        return recording.rows.joint_positions, Sockets(
            recording.rows.group, recording.labels, points.distances
        )
    if path.is_dir():
        raise KincalError(f"--candidates {path}: no hole_<k>.csv files; {POINT_CANDIDATES}")
    frame = read_frame(path, path.name)
    if "socket" not in frame.columns:
        raise KincalError(f"--candidates {path}: no 'socket' column; {POINT_CANDIDATES}")
    if model.calibration.point_distance_m is not None:
        raise KincalError(
            f"--point-distance pairs the hole_0/hole_1 files of each placement of a platonics "
            f"folder; {path.name} has a socket column only: give the folder or drop "
            "--point-distance"
        )
    q = configurations_from_frame(
        frame.drop(columns="socket"),
        chain.joint_names,
        source=path.name,
        other_joint_names=chain.other_joint_names,
    ).joint_positions
    return q, socket_candidates(frame["socket"].astype(str).tolist())


def socket_candidates(sockets: list[int] | list[str] | None) -> Sockets | None:
    """The sockets of candidates named by a value each (HTTP ``candidate_sockets``, a CSV's
    ``socket`` column), numbered in sorted order."""
    if sockets is None:
        return None
    labels, index = np.unique(np.asarray(sockets), return_inverse=True)
    return Sockets(index.astype(np.intp), tuple(f"socket {v}" for v in labels))


def run_design(
    robot: RobotDescription,
    options: DesignOptions,
    *,
    candidates: FloatArray | None = None,
    task: FloatArray | None = None,
    recorded: Recorded | None = None,
    model: DesignModel | None = None,
    sockets: Sockets | None = None,
) -> DesignResult:
    """Choose ``options.n_poses`` poses (see the module docstring); ``model``: the
    :func:`design_model` of these arguments when the caller has already built it;
    ``sockets``: the socket of each candidate (measurement 'point')."""
    if model is None:
        model = design_model(robot, options, recorded)
    chain = model.chain
    q, notes, sockets = candidate_set(model, options, candidates, sockets)
    if recorded is not None:
        check_configurations(chain, recorded.joint_positions, "recording")
    if q.shape[0] < options.n_poses and not options.allow_repeats:
        raise KincalError(
            f"n_poses: {options.n_poses} poses wanted but only {q.shape[0]} candidates; give "
            "more candidates, widen the working volume or allow repeats"
        )
    loads = design_loads(model, q)
    prior_q = None if recorded is None else recorded.joint_positions
    old = None if prior_q is None else (prior_q, design_loads(model, prior_q))
    rows = model.noise_std.shape[0]
    fit = pipeline.fit_options(model.calibration)
    if model.measurement is None:
        geometry = geometry_information(
            chain, model.params, q, loads, model.noise_std, options=fit, recorded=old
        )
    else:
        model, geometry = measurement_block(model, options, q, loads, sockets)
        rows = 6 if model.measurement is not None and model.measurement.rotation_rows else 3
    if task is not None:
        check_configurations(chain, task, "task")
    else:
        task = sample_candidates(
            chain, TASK_SAMPLES, np.random.default_rng([options.seed, 1]), volume_of(options)
        )
    task_jac = equilibrated_pose_jacobian(
        chain, model.params, task, design_loads(model, task), geometry, rows
    )
    blocks: list[InformationBlock] = []
    if options.stage in ("geometry", "both"):
        blocks.append(geometry)
    covariance, layout = None, None
    if options.stage in ("covariance", "both"):
        covariance, layout = covariance_information(
            chain,
            model.params,
            q,
            loads,
            model.prior,
            residual_dim=rows,
            structure="full" if model.calibration.covariance == "full" else "diag",
            recorded=old,
        )
        blocks.append(covariance)
    equations = model.noise_std.shape[0]  # per pose
    unknowns = geometry.columns - int(np.linalg.matrix_rank(geometry.prior))
    needed = -(-unknowns // equations)
    if recorded is None and options.n_poses < needed:
        raise KincalError(
            f"n_poses: {options.n_poses} poses give {options.n_poses * equations} equations "
            f"for {unknowns} identifiable parameters; choose at least {needed} poses"
        )
    problem = DesignProblem(
        tuple(blocks),
        options.criterion,
        options.n_poses,
        task_root=task_root(task_jac) if options.criterion == "I" else None,
        distinct=not options.allow_repeats,
    )
    design = optimal_design(problem, q, method=options.method, spacing_rad=options.min_spacing_rad)
    if not np.isfinite(design.value):
        raise KincalError(
            f"n_poses: no {options.n_poses} of these candidates determine every parameter "
            "(singular information); give more varied candidates or choose more poses"
        )
    information = geometry.information(design.chosen)
    se, relative = standard_errors(geometry, information)
    positions = tip_poses(chain, q[design.chosen])[:, :3, 3]
    return DesignResult(
        kincal_version=result_json.kincal_version(),
        robot=robot.name,
        urdf_sha256=chain.urdf_sha256,
        joint_names=list(chain.joint_names),
        options=options,
        candidates=int(q.shape[0]),
        candidate_source="sampled" if candidates is None else "given",
        poses=[
            DesignPose(
                candidate=int(n),
                joint_positions=q[n].tolist(),
                tip_position_m=(float(p[0]), float(p[1]), float(p[2])),
            )
            for n, p in zip(design.chosen, positions, strict=True)
        ],
        criterion=_criterion_report(options, design),
        parameters=[
            ParameterError(
                name=name,
                standard_error=float(s),
                unit=parameter_unit(name),
                relative_to_noise=float(r),
            )
            for name, s, r in zip(geometry.names, se, relative, strict=True)
        ],
        worst_relative_standard_error=float(np.max(relative)),
        mean_pose_variance_m2=float(np.mean(predicted_pose_variance(information, task_jac))),
        task_configurations=int(task.shape[0]),
        covariance=None
        if layout is None
        else _covariance_report(model, q, loads, design, layout, rows),
        sequential=None
        if recorded is None or prior_q is None
        else _sequential_report(model, geometry, task_jac, prior_q),
        measurement=None
        if model.measurement is None
        else _measurement_report(options, model.measurement, geometry, sockets),
        notes=notes,
    )


def measurement_block(
    model: DesignModel,
    options: DesignOptions,
    q: FloatArray,
    loads: FloatArray,
    sockets: Sockets | None,
) -> tuple[DesignModel, InformationBlock]:
    """The geometry block of a measurement type other than pose/position
    (:func:`solver.design.information.model_information`, its own unknowns as nuisance
    columns) at the nominal chain and the measurement's expected unknowns: the given marker
    offsets; for ball in socket the ball offset and socket points that fit the candidates
    (the model's own start, :meth:`FixedPoints.start`), with the known distances. Returns
    the model completed (sockets, markers) and the block."""
    measurement = model.measurement
    nominal = ChainParameters.nominal(model.chain)
    group = None
    if isinstance(measurement, FixedPoints):
        assert sockets is not None
        counts = np.bincount(sockets.index, minlength=len(sockets.labels))
        if np.any(counts == 0):
            raise KincalError(
                "candidates: every socket of the working volume needs candidates; "
                f"{[sockets.labels[g] for g in np.flatnonzero(counts == 0)]} have none left "
                "(widen the working volume)"
            )
        measurement = FixedPoints(len(sockets.labels), sockets.distances)
        group = sockets.index
        params: ModelParameters = measurement.start(
            model.chain, MeasurementRows.of(q, loads, None, group)
        )
    elif isinstance(measurement, MultiMarker):
        offsets = np.asarray(options.marker_offsets_m, dtype=float)
        measurement = MultiMarker(offsets.shape[0])
        params = ModelParameters(nominal.links, nominal.compliance_rad_per_nm, offsets.ravel())
    else:
        params = ModelParameters(nominal.links, nominal.compliance_rad_per_nm)
    assert measurement is not None
    block = model_information(
        model.chain,
        params,
        measurement,
        q,
        loads,
        model.noise_std,
        options=pipeline.fit_options(model.calibration),
        group=group,
    )
    completed = DesignModel(
        model.chain, params, model.calibration, model.noise_std, model.prior, measurement
    )
    return completed, block


def _measurement_report(
    options: DesignOptions,
    measurement: MeasurementModel,
    block: InformationBlock,
    sockets: Sockets | None,
) -> MeasurementDesignReport:
    return MeasurementDesignReport(
        type=options.measurement,
        frame=measurement.frame,
        components=list(measurement.components),
        nuisance_parameters=list(block.nuisance_names),
        sockets=[] if sockets is None else list(sockets.labels),
        known_distances=0 if sockets is None else len(sockets.distances),
    )


def parameter_unit(name: str) -> str:
    if name.startswith("compliance."):
        return "rad/N·m"
    return "m" if name.rsplit(".", 1)[-1].startswith("t") else "rad"


def _criterion_report(options: DesignOptions, design: Design) -> CriterionReport:
    relaxation = design.relaxation
    return CriterionReport(
        name=options.criterion,
        value=design.value,
        relaxation_value=relaxation.value,
        upper_bound=relaxation.upper_bound,
        efficiency=design.efficiency,
        method=relaxation.method,
        status=relaxation.status,
        iterations=relaxation.iterations,
        elapsed_s=relaxation.elapsed_s,
        rounding=ROUNDING_RULE,
    )


def _covariance_report(
    model: DesignModel,
    q: FloatArray,
    loads: FloatArray,
    design: Design,
    layout: CovarianceLayout,
    rows: int,
) -> CovarianceDesignReport:
    """Identifiability of the covariance statistics (the result JSON's report) for the chosen
    poses and for all candidates."""
    index = model.prior.frame_index

    def report(
        configurations: FloatArray, configuration_loads: FloatArray
    ) -> IdentifiabilityReport:
        jac = frame_jacobians(
            model.chain, model.params, configurations, configuration_loads, index, rows
        )
        return analyse_identifiability(design_gram(jac, layout))

    chosen = report(q[design.chosen], loads[design.chosen])
    everything = report(q, loads)
    return CovarianceDesignReport(
        n_entries=layout.n_params,
        rank=chosen.rank,
        candidate_rank=everything.rank,
        condition_number=chosen.condition_number,
        unidentifiable=list(chosen.statements),
    )


def _sequential_report(
    model: DesignModel, geometry: InformationBlock, task_jac: FloatArray, prior_q: FloatArray
) -> SequentialReport:
    before = np.linalg.svd(geometry.prior, compute_uv=False)
    rank = int(np.sum(before > 1e-9 * max(before[0], 1e-300)))
    unidentified: list[str] = []
    if rank < geometry.dimension:
        # Parameters moving along the recording's null directions.
        _, vectors = np.linalg.eigh(geometry.prior)
        null = vectors[:, : geometry.dimension - rank]
        weight = np.sum(null**2, axis=1)
        unidentified = [n for n, w in zip(geometry.names, weight, strict=True) if w > 1e-6]
    variance = (
        float(np.mean(predicted_pose_variance(geometry.prior, task_jac)))
        if rank == geometry.dimension
        else None
    )
    return SequentialReport(
        recorded_poses=int(prior_q.shape[0]),
        unidentifiable_before=unidentified,
        mean_pose_variance_before_m2=variance,
    )
