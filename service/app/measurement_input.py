"""Reading a recording for a calibration whose rows are not a marker pose or position (issue
15): which measurement model the options and the source ask for (:func:`measurement_for`), the
checks a measurement needs before any fit, and the recording in memory with its loads
(:func:`read_measured`). :mod:`service.app.calibrate_measurement` fits what this reads."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.calibration import (
    CalibrationOptions,
)
from schemas.dataset import PoseDataset, read_dataset
from schemas.dataset.constraints import (
    figaroh_marker_count,
    is_socket_folder,
    read_all_markers,
    read_socket_folder,
)
from solver import lie
from solver.errors import KincalError, ModelError
from solver.measurement import (
    EyeOnHead,
    FixedPoints,
    KnownDistance,
    MeasurementModel,
    MeasurementRows,
    MultiMarker,
    PoseComponents,
    RelativeBase,
)
from solver.model import KinematicChain, gravity_loads

IN_MEMORY_MODELS = ("point", "markers", "components", "relative-base", "eye-on-head")
"""Measurements calibrated in memory here; 'pose' and 'position' stream (service.app.calibrate)."""


def refuse_file_measurement(measurement: str, command: str) -> None:
    """The service works on one uploaded dataset (a pose or position per row): a
    :class:`ModelError` for the measurements that read a folder or every marker of a file,
    naming the ``kincal`` ``command`` that reads them."""
    kind = measurement.partition(":")[0]
    if kind in ("point", "markers"):
        raise ModelError(
            f"measurement {kind!r} reads a folder of ball-in-socket hole files or every "
            "marker of a FIGAROH file; the service works on one uploaded dataset (pose or "
            f"position per row): run kincal {command} on the folder or file instead"
        )


def check_sensor_joint(measurement: str, chain: KinematicChain) -> None:
    """For ``eye-on-head:<joint>``: a :class:`ModelError` unless ``<joint>`` is a joint of the
    chain before its last (the sensor rides on the body after it)."""
    kind, _, joint = measurement.partition(":")
    names = list(chain.joint_names)
    if kind == "eye-on-head" and joint not in names[:-1]:
        raise ModelError(
            f"measurement eye-on-head:{joint}: not a joint of the chain before its last; "
            f"choose one of {', '.join(names[:-1])}"
        )


def measurement_kind(options: CalibrationOptions, source: str | Path | PoseDataset) -> str:
    """The measurement in effect: the option, or for 'auto' what the source is."""
    kind = options.measurement.partition(":")[0]
    if kind != "auto":
        return kind
    if isinstance(source, PoseDataset):
        return "auto"
    if is_socket_folder(source):
        return "point"
    return "auto"


def measurement_for(
    options: CalibrationOptions,
    chain: KinematicChain,
    source: str | Path | PoseDataset,
    marker: int | None,
) -> MeasurementModel | None:
    """The model the recording is calibrated with here, or None (pose/position: streamed)."""
    kind = measurement_kind(options, source)
    several = not isinstance(source, PoseDataset) and figaroh_marker_count(source) > 1
    if kind == "auto" and marker is None and several:
        kind = "markers"
    argument = options.measurement.partition(":")[2]
    count = 0
    if kind == "markers" and not isinstance(source, PoseDataset):
        count = figaroh_marker_count(source)
    return measurement_model(kind, argument, chain, max(count, 2))


def measurement_model(
    kind: str, argument: str, chain: KinematicChain, n_markers: int = 2
) -> MeasurementModel | None:
    """The model of a ``measurement`` option's type and argument (``components:tz,rx,ry``:
    kind 'components', argument 'tz,rx,ry'), or None for the streamed pose/position types.
    'point' has one socket and 'markers' ``n_markers`` markers until rows or a design
    complete them."""
    if kind in ("auto", "pose", "position"):
        return None
    if kind == "point":
        return FixedPoints(1)  # sockets and distances come with the rows (read_measured)
    if kind == "markers":
        return MultiMarker(n_markers)
    if kind == "components":
        return PoseComponents(tuple(c.strip() for c in argument.split(",")))
    if kind == "relative-base":
        return RelativeBase()
    if kind == "eye-on-head":  # the joint is checked by check_sensor_joint
        return EyeOnHead(sensor_joint=list(chain.joint_names).index(argument))
    raise KincalError(f"measurement {kind!r} is not known")


@dataclass(frozen=True)
class MeasuredRecording:
    """Rows for a model, the model completed by them (sockets, markers), the recording's
    name, labels of its sockets or markers, and whether rows carry a measured rotation."""

    model: MeasurementModel
    rows: MeasurementRows
    source: str
    labels: tuple[str, ...]
    rotation: bool
    notes: tuple[str, ...] = ()


def _loads(chain: KinematicChain, options: CalibrationOptions, q: np.ndarray) -> np.ndarray:
    """Gravity loads (N, n_axes) N·m of the joint positions, as the streamed path takes them."""
    return gravity_loads(
        chain,
        q,
        gravity_base=np.asarray(options.gravity_base_m_s2, dtype=float),
        payload_kg=options.payload_kg,
    )


def with_rows(
    recording: MeasuredRecording,
    chain: KinematicChain,
    options: CalibrationOptions,
    joint_positions: np.ndarray,
    measured: np.ndarray,
) -> MeasuredRecording:
    """``recording`` with new joint positions (N, k) rad (their loads swept again) and
    measurements (a carried discovery's corrections,
    :func:`service.app.discover_carry.carry_measured`)."""
    rows = recording.rows
    loads = _loads(chain, options, joint_positions)
    return dataclasses.replace(
        recording, rows=MeasurementRows.of(joint_positions, loads, measured, rows.group)
    )


def read_chain_dataset(
    source: str | Path,
    chain: KinematicChain,
    marker: int | None = None,
    name: str | None = None,
) -> PoseDataset:
    """A pose/position recording (file or folder) read for ``chain``'s joints, by name."""
    return read_dataset(
        source,
        chain.joint_names,
        other_joint_names=chain.other_joint_names,
        marker=marker,
        source=name,
    )


def read_measured(
    source: str | Path | PoseDataset,
    chain: KinematicChain,
    options: CalibrationOptions,
    model: MeasurementModel,
    *,
    marker: int | None = None,
    name: str | None = None,
) -> MeasuredRecording:
    """The recording in memory as ``model``'s rows (:class:`KincalError` / ``DatasetError``
    naming the file and the fix when it does not hold what the model needs)."""
    if isinstance(model, FixedPoints):
        if isinstance(source, PoseDataset) or not is_socket_folder(source):
            raise KincalError(
                f"measurement 'point' needs a folder of ball-in-socket hole_<k>.csv files "
                f"(headerless joint positions, one file per socket); got {source}"
            )
        sockets = read_socket_folder(source, chain.joint_names)
        distances: list[KnownDistance] = []
        if options.point_distance_m is not None:
            for holes in sockets.holes.values():
                if 0 in holes and 1 in holes:
                    distances.append(KnownDistance(holes[0], holes[1], options.point_distance_m))
        points = FixedPoints(len(sockets.sockets), tuple(distances))
        q = sockets.joint_positions
        rows = MeasurementRows.of(q, _loads(chain, options, q), None, sockets.socket)
        return MeasuredRecording(points, rows, name or sockets.source, sockets.sockets, False)
    if isinstance(source, PoseDataset):
        dataset = source
    elif isinstance(model, MultiMarker):
        markers = read_all_markers(source, chain.joint_names, chain.other_joint_names)
        q = markers.joint_positions
        positions = markers.marker_positions_m
        keep, notes = distinct_markers(positions)
        model = dataclasses.replace(model, n_markers=len(keep))
        rows = MeasurementRows.of(q, _loads(chain, options, q), positions[:, keep])
        labels = tuple(f"marker {j + 1}" for j in keep)
        return MeasuredRecording(model, rows, name or markers.source, labels, False, notes)
    else:
        dataset = read_chain_dataset(source, chain, marker, name)
    q = dataset.joint_positions
    pose = lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw)
    needs_rotation = isinstance(model, PoseComponents) and bool(model.rotation_rows)
    rotation = dataset.measurement_model.measures_rotation
    if isinstance(model, (RelativeBase, EyeOnHead)):
        model = dataclasses.replace(model, rotation=rotation)
    if needs_rotation and not rotation:
        raise KincalError(
            f"measurement {options.measurement}: the rotation components need quaternion "
            f"columns qx,qy,qz,qw in {dataset.source}; choose translation components only"
        )
    if isinstance(model, MultiMarker):
        raise KincalError("measurement 'markers' needs a FIGAROH file with several markers")
    rows = MeasurementRows.of(q, _loads(chain, options, q), pose)
    return MeasuredRecording(model, rows, name or dataset.source, (), rotation)


def distinct_markers(positions_m: np.ndarray) -> tuple[list[int], tuple[str, ...]]:
    """The markers (N, m, 3) to read: each once, a marker whose positions repeat an earlier
    marker's in every row dropped (it is the same measurement twice: it would count that
    marker double in the fit, and its residual minus the other's is exactly zero, which makes
    the covariance of Eq. 12 singular); with a note per dropped marker."""
    keep: list[int] = []
    notes = []
    for j in range(positions_m.shape[1]):
        same = [k for k in keep if np.array_equal(positions_m[:, j], positions_m[:, k])]
        if same:
            notes.append(f"marker {j + 1} repeats marker {same[0] + 1} in every row: read once")
        else:
            keep.append(j)
    return keep, tuple(notes)
