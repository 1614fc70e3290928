"""Pre-flight checks of a recording: the mistakes that a whole calibration run would only show
at its end (issue 28), caught in well under a second before any fit.

Every entry point calls these — ``kincal calibrate``, ``discover``, ``fleet``, ``design
--recording`` (:func:`check_recording`), ``predict`` and ``rank`` on their configurations
(:func:`check_configurations`), and the HTTP dataset upload (:func:`check_dataset`) — so a
recording in millimetres or degrees is refused the same way everywhere: a
:class:`~solver.errors.DatasetError` with one line naming the file, what is wrong and the fix
(CLI exit code 2, HTTP 422 problem+json).

The checks, each on numbers the recording and the URDF already hold:

* positions spread over more than :data:`solver.verdict.UNIT_SPREAD_FACTOR` times the arm's
  reach: not metres (the unit they look like is named: millimetres, centimetres);
* joint values beyond the URDF limits by more than a margin (:data:`LIMIT_MARGIN_RAD`,
  :data:`LIMIT_MARGIN_M`, :data:`LIMIT_MARGIN_FRACTION` of the range): degrees when every
  one of them is within its limits once read as degrees, else out of range (column order, the
  wrong robot);
* a joint column holding one value in every row (not recorded, or the joint never moved: its
  parameters cannot be calibrated; ``--fix JOINT`` accepts it);
* rows that repeat another row exactly (joints and measurement: one measurement counted twice);
* fewer equations than the parameters asked for (:func:`solver.calibration.check_sample_count`,
  the rank on generic configurations), pose and position recordings.

Imports stay light (no fit machinery): the check runs before ``kincal`` loads the solver's
heavy modules, so a refusal costs little more than reading the file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from schemas.dataset import PoseDataset, plan_dataset_chunks, read_dataset
from schemas.dataset.constraints import is_socket_folder, read_all_markers, read_socket_folder
from solver.errors import DatasetError
from solver.model import KinematicChain
from solver.verdict import UNIT_SPREAD_FACTOR, position_spread_m, reach_m

if TYPE_CHECKING:
    from schemas.calibration import CalibrationOptions
    from solver.calibration import FitOptions

LIMIT_MARGIN_RAD = 0.2
"""Revolute joint readings may lie this far (plus :data:`LIMIT_MARGIN_FRACTION` of the range)
beyond the URDF limits: the FR3 recording reads 0.05 rad past the Panda URDF's joint-6 limit
(valid on an FR3), the DH positioner's turntable 0.39 rad past the ±π of its table."""
LIMIT_MARGIN_M = 0.02
"""The same for prismatic joints, m."""
LIMIT_MARGIN_FRACTION = 0.1
"""Share of a joint's range added to the margin."""
UNLIMITED_RAD = 4 * math.pi
"""Range assumed for a revolute joint without URDF limits (continuous): two turns each way."""
HEAD_ROWS = 65_536
"""Rows of a large recording read for the checks (the whole of a smaller one)."""


@dataclass(frozen=True)
class RecordingView:
    """What the checks read of a recording: joint positions (N, k), positions (N, m, 3) of its
    m markers in m (None for a ball-in-socket folder), rows in the file (``n_rows`` may exceed
    N for a large file read by its head), and whether it has orientations."""

    source: str
    joint_positions: NDArray[np.float64]
    positions_m: NDArray[np.float64] | None
    n_rows: int
    rotation: bool
    plain: bool
    """A pose or position recording (the measurement types have their own unknowns)."""


def read_view(
    source: str | Path | PoseDataset,
    chain: KinematicChain,
    measurement: str = "auto",
    marker: int | None = None,
) -> RecordingView:
    """Read ``source`` as the calibration will (a dataset file, its head when it is large, a
    ball-in-socket folder, or every marker of a FIGAROH file; or a dataset in memory: a ROS
    bag's); :class:`DatasetError` if it cannot be read."""
    kind = measurement.partition(":")[0]
    if isinstance(source, PoseDataset):
        return dataset_view(source, plain=kind in ("auto", "pose", "position"))
    path = Path(source)
    if kind == "point" or (kind == "auto" and is_socket_folder(path)):
        sockets = read_socket_folder(path, chain.joint_names)
        q = sockets.joint_positions
        return RecordingView(sockets.source, q, None, len(q), False, False)
    if kind == "markers" or (kind == "auto" and marker is None and _several_markers(path)):
        markers = read_all_markers(path, chain.joint_names, chain.other_joint_names)
        q = markers.joint_positions
        return RecordingView(markers.source, q, markers.marker_positions_m, len(q), False, False)
    plan = plan_dataset_chunks(
        path,
        chain.joint_names,
        chunk_rows=HEAD_ROWS,
        other_joint_names=chain.other_joint_names,
        marker=marker,
    )
    dataset = (
        plan.read(plan.refs[0])
        if plan.n_rows > HEAD_ROWS
        else read_dataset(
            path, chain.joint_names, other_joint_names=chain.other_joint_names, marker=marker
        )
    )
    view = dataset_view(dataset, plain=kind in ("auto", "pose", "position"))
    return RecordingView(
        plan.source,
        view.joint_positions,
        view.positions_m,
        plan.n_rows,
        view.rotation,
        view.plain,
    )


def _several_markers(path: Path) -> bool:
    from schemas.dataset.figaroh import figaroh_markers
    from schemas.dataset.readers import read_csv_header

    if path.suffix.lower() != ".csv" or not path.is_file():
        return False
    return len(figaroh_markers(read_csv_header(path, path.name))) > 1


def dataset_view(dataset: PoseDataset, *, plain: bool = True) -> RecordingView:
    """A dataset already in memory (an HTTP upload) as the checks see it."""
    return RecordingView(
        dataset.source,
        dataset.joint_positions,
        dataset.position_m[:, None, :],
        dataset.n_samples,
        dataset.measures_rotation,
        plain,
    )


# --- the checks ----------------------------------------------------------------------------------


def check_recording(
    source: str | Path | PoseDataset,
    chain: KinematicChain,
    options: CalibrationOptions | None = None,
    *,
    marker: int | None = None,
    measurement: str | None = None,
    fixed_joints: Sequence[str] = (),
) -> RecordingView:
    """Every check of :mod:`this module <service.app.preflight>` on ``source`` for ``chain``
    (``options``: the calibration's, for the parameter count; None: a discovery or a design,
    whose model is the chain's, with its ``measurement``). Returns what it read."""
    if measurement is None:
        measurement = "auto" if options is None else options.measurement
    view = read_view(source, chain, measurement, marker)
    fixed = tuple(fixed_joints) + (() if options is None else tuple(options.fixed_parameters))
    check_view(view, chain, fixed_joints=fixed)
    if options is not None and view.plain:
        check_row_count(view, chain, options)
    return view


def check_view(
    view: RecordingView, chain: KinematicChain, *, fixed_joints: Sequence[str] = ()
) -> None:
    """The checks of the recording's numbers (units, limits, constant joints, repeated rows)."""
    check_positions(view, chain)
    check_joint_values(view.joint_positions, chain, view.source)
    check_constant_joints(view, chain, fixed_joints)
    check_repeated_rows(view)


def check_dataset(dataset: PoseDataset, chain: KinematicChain) -> None:
    """The checks an HTTP upload gets: units, limits and repeated rows. Not a constant joint:
    a joint held still on purpose is calibrated with it fixed (``fixed_parameters``), which
    the upload does not know yet; the calibration then reports its parameters unidentifiable."""
    view = dataset_view(dataset)
    check_positions(view, chain)
    check_joint_values(view.joint_positions, chain, view.source)
    check_repeated_rows(view)


def check_configurations(
    joint_positions: NDArray[np.float64], chain: KinematicChain, source: str
) -> None:
    """Configurations to predict or rank: joint values in radians within the limits."""
    check_joint_values(joint_positions, chain, source)


def check_positions(view: RecordingView, chain: KinematicChain) -> None:
    """Positions that spread over more than :data:`UNIT_SPREAD_FACTOR` times the reach are not
    in metres; say which unit they look like."""
    if view.positions_m is None or view.positions_m.size == 0:
        return
    reach = reach_m(chain.nominal_links[:, :3, 3])
    if reach <= 0:
        return
    spread = max(
        position_spread_m(view.positions_m[:, m]) for m in range(view.positions_m.shape[1])
    )
    if spread <= UNIT_SPREAD_FACTOR * reach:
        return
    unit, divide = "millimetres", 1000
    if spread / 100 <= UNIT_SPREAD_FACTOR * reach and spread / 1000 < 0.02 * reach:
        unit, divide = "centimetres", 100
    raise DatasetError(
        f"{view.source}: the positions x, y, z spread over {spread:.4g}, "
        f"{spread / reach:.0f} times the reach of the arm ({reach:.2f} m): they look like "
        f"{unit}, not metres; convert x, y, z to metres (divide by {divide}) and run again"
    )


def _plausible_range(chain: KinematicChain) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    lower = np.asarray(chain.lower_limits, dtype=float).copy()
    upper = np.asarray(chain.upper_limits, dtype=float).copy()
    revolute = chain.is_revolute()
    unlimited = ~np.isfinite(lower) | ~np.isfinite(upper) | (upper <= lower) | (upper - lower > 1e3)
    lower[unlimited & revolute] = -UNLIMITED_RAD
    upper[unlimited & revolute] = UNLIMITED_RAD
    lower[unlimited & ~revolute] = -np.inf
    upper[unlimited & ~revolute] = np.inf
    margin = np.where(revolute, LIMIT_MARGIN_RAD, LIMIT_MARGIN_M)
    margin = margin + LIMIT_MARGIN_FRACTION * np.where(np.isfinite(upper - lower), upper - lower, 0)
    return lower - margin, upper + margin


def check_joint_values(
    joint_positions: NDArray[np.float64], chain: KinematicChain, source: str
) -> None:
    """Joint values beyond the limits (plus the margin): degrees when they all fit once read
    as degrees, else out of range."""
    q = np.asarray(joint_positions, dtype=float)
    if q.size == 0:
        return
    lower, upper = _plausible_range(chain)
    outside = (q < lower) | (q > upper)
    if not outside.any():
        return
    revolute = chain.is_revolute()
    as_radians = np.where(revolute, np.radians(q), q)
    fits_as_degrees = not ((as_radians < lower) | (as_radians > upper)).any() and bool(
        np.abs(q[:, revolute]).max(initial=0.0) > 2 * math.pi
    )
    worst = int(np.argmax(np.abs(q).max(axis=0) * outside.any(axis=0)))
    name = chain.joint_names[worst]
    if fits_as_degrees:
        raise DatasetError(
            f"{source}: the joint values look like degrees, not radians: {name} reads up to "
            f"{np.abs(q[:, worst]).max():.4g}, beyond its limits "
            f"({chain.lower_limits[worst]:.3g} to {chain.upper_limits[worst]:.3g} rad), and every "
            "joint is within its limits once read as degrees; convert the revolute joint "
            "columns to radians (multiply by π/180 = 0.0174533) and run again"
        )
    row = int(np.argmax(outside[:, worst]))
    unit = "rad" if revolute[worst] else "m"
    raise DatasetError(
        f"{source}: data row {row + 1}, column {name}: {q[row, worst]:.4g} {unit} is outside "
        f"the joint's limits ({chain.lower_limits[worst]:.3g} to "
        f"{chain.upper_limits[worst]:.3g} {unit}) in {int(outside[:, worst].sum())} row(s); check "
        "that the joint columns are in chain order and radians (m for prismatic joints), and "
        "that --robot/--urdf is the recorded robot"
    )


def check_constant_joints(
    view: RecordingView, chain: KinematicChain, fixed_joints: Sequence[str] = ()
) -> None:
    """A joint that reads one value in every row was not recorded or never moved."""
    q = view.joint_positions
    if len(q) < 2:
        return
    constant = [
        j
        for j in range(q.shape[1])
        if np.ptp(q[:, j]) == 0.0 and chain.joint_names[j] not in fixed_joints
    ]
    if constant:
        name = chain.joint_names[constant[0]]
        others = f" (and {len(constant) - 1} more)" if len(constant) > 1 else ""
        raise DatasetError(
            f"{view.source}: column {name}{others} holds the same value "
            f"({q[0, constant[0]]:.6g}) in all {len(q)} rows: the joint was not recorded or "
            f"never moved, so its parameters cannot be calibrated; check the column, or if it "
            f"was held still on purpose keep it at its nominal values with --fix {name}"
        )


def check_repeated_rows(view: RecordingView) -> None:
    """Rows identical to an earlier row in every joint and measured number."""
    q = view.joint_positions
    columns = [q]
    if view.positions_m is not None:
        columns.append(view.positions_m.reshape(len(q), -1))
    table = np.ascontiguousarray(np.hstack(columns))
    if len(table) < 2:
        return
    _, first, counts = np.unique(table, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        repeated = int(np.sum(counts[counts > 1] - 1))
        row = int(first[counts > 1].min())
        copy = int(np.flatnonzero((table == table[row]).all(axis=1))[1])
        raise DatasetError(
            f"{view.source}: data rows {row + 1} and {copy + 1} are identical (joints and "
            f"measurement), {repeated} repeated row(s) in all: a measurement recorded twice "
            "counts twice in the fit; remove the repeated rows and run again"
        )


def check_row_count(
    view: RecordingView, chain: KinematicChain, options: CalibrationOptions
) -> None:
    """Fewer equations than the parameters the fit would estimate (generic rank)."""
    from solver.calibration import check_sample_count
    from solver.errors import CalibrationError
    from solver.measurement.pose import pose_measurement

    rotation = view.rotation and options.measurement != "position"
    try:
        check_sample_count(
            chain,
            view.n_rows,
            dim=pose_measurement(rotation=rotation).dim,
            options=fit_options(options, free_columns=chosen_columns(chain, options)),
        )
    except CalibrationError as exc:
        raise DatasetError(
            f"{view.source}: {exc}; or fit fewer parameters (--free joint_offsets)"
        ) from exc


# --- the options as the fit takes them (shared with service.app.calibrate) ----------------------


def chosen_columns(chain: KinematicChain, options: CalibrationOptions) -> tuple[int, ...] | None:
    """The columns ``free_parameters`` / ``fixed_parameters`` leave free (None: all, the
    default); :class:`ModelError` listing the valid names for an unknown one."""
    from solver.selection import free_columns

    if options.free_parameters == ["all"] and not options.fixed_parameters:
        return None
    return free_columns(chain, options.free_parameters, options.fixed_parameters)


def fit_options(
    options: CalibrationOptions,
    *,
    baseline: bool = False,
    n_links: int = 0,
    free_columns: tuple[int, ...] | None = None,
) -> FitOptions:
    """Solver settings; ``baseline`` fits only the measurement frame and tool (nominal robot);
    ``free_columns`` the columns the (not baseline) fit may move."""
    from solver.calibration import FitOptions

    return FitOptions(
        max_iterations=options.max_iterations,
        tolerance=options.tolerance,
        rotation_weight_m_per_rad=options.rotation_weight_m_per_rad,
        rank_tolerance=options.rank_tolerance,
        free_links=(0, n_links - 1) if baseline else None,
        fit_compliance=not baseline,
        free_columns=None if baseline else free_columns,
    )
