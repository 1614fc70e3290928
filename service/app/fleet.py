"""Fleet mode: calibrate one dataset per robot serial in parallel and compare the robots.

Each robot is calibrated by :func:`service.app.calibrate.calibrate_source` (in the worker that
takes it: the fleet is parallel over robots, not within one), robots spread over an executor
(:mod:`solver.executors`: in-process, local processes, Dask). The summary compares what is
comparable between robots of one model:

- per joint: compliance of each estimated axis (rad/N·m), the σ of the random perturbation of
  each joint frame (per axis, m and rad, §IV-C), and the geometric correction of each inner
  link (local twist of L_i, m and rad);
- per robot: RMS translation error after calibration (mm, training data).

The measurement frame and tool are each robot's own mounting and are not compared. Link
corrections are only comparable in one gauge: the pruning QR drops a different one of two
interchangeable columns on different data, and the kept columns absorb what the dropped ones
would have done. Each robot's fit is linearised again at its solution
(:func:`unit_information`, in the worker) and the link corrections are compared in the gauge
every robot identifies (:mod:`solver.fleet_gauge`): each robot's estimate projected onto the
subspace orthogonal to every robot's gauge directions, its standard error through the same
projection. A column pruned on any robot, or mostly outside that subspace (share below
:data:`MIN_SHARE`), is left out and listed with the reason (``link_gauge`` of the report).

Only estimated values are compared: a compliance fixed at 0 as implausible (negative, or not
identified in any physical range: ``pruned``) and a σ the data cannot see (``std`` null) are not
values of the robot and never make it an outlier.

Population spread per parameter: median, MAD (scaled by 1.4826, a σ for Gaussian data), mean,
std, min, max. A robot is an outlier in a parameter when its robust z-score
``(x − median) / (1.4826 · MAD)`` exceeds the threshold, e.g. a worn joint: much larger
compliance or perturbation σ at that joint than the rest of the fleet; and when the deviation
exceeds 3 of that robot's own standard errors of the parameter (a poorly identified parameter,
e.g. a wrist compliance, scatters without anything being wrong; a σ without a standard error, at
the boundary 0, is never flagged).

The threshold is family-wise (:func:`family_wise_z`): the MAD of a dozen robots is itself a
rough estimate, and a fleet compares dozens of parameters, so Iglewicz & Hoaglin's 3.5 alone
flags a healthy robot in most fleets (12 Gaussian robots: 12 % per parameter). A parameter over
n robots is flagged beyond the larger of ``z_threshold`` (3.5) and the |z| the largest of n
Gaussian robots exceeds with probability ``false_alarm / m`` (m parameters compared): a fleet
of healthy robots raises any alarm with probability at most ``false_alarm`` (default 1 %).
"""

from __future__ import annotations

import functools
import json
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import SUFFIXES, PoseDataset
from schemas.dataset.constraints import is_socket_folder
from schemas.dataset.paths import check_fleet_folder
from schemas.robots import RobotDescription
from service.app import calibrate as pipeline
from solver.errors import KincalError
from solver.executors import Executor, InProcessExecutor
from solver.fleet_gauge import (
    DIRECTION_TOLERANCE,
    UnitInformation,
    common_gauge,
    common_gauge_values,
)
from solver.kinematics import TWIST_COMPONENTS, parameter_names

FLEET_FORMAT = "kincal.fleet/1"
MAD_TO_SIGMA = 1.4826
DEFAULT_Z_THRESHOLD = 3.5
FALSE_ALARM = 0.01
"""Probability that a fleet of healthy robots (each parameter Gaussian over the fleet) shows any
outlier at all (see :func:`family_wise_z`)."""
SIGNIFICANCE = 3.0
"""A flagged deviation from the median must also exceed this many of the robot's own standard
errors (a poorly identified parameter scatters without anything being wrong)."""


@dataclass(frozen=True)
class FleetJob:
    """What every robot of the fleet is calibrated with (shared by all tasks)."""

    robot: RobotDescription
    options: CalibrationOptions
    marker: int | None = None


@dataclass(frozen=True)
class RobotOutcome:
    """One robot's calibration: the result, or the one-line error that stopped it."""

    serial: str
    source: str
    result: CalibrationResult | None
    error: str | None = None
    information: UnitInformation | None = None  # its fit linearised again, for the link gauge
    information_error: str | None = None


def calibrate_one(job: FleetJob, item: tuple[str, str]) -> RobotOutcome:
    """Calibrate one robot's dataset (runs in a worker; its passes in that worker) and
    linearise its fit again at the solution (:func:`unit_information`)."""
    serial, path = item
    try:
        setup = pipeline.check_calibration(job.robot, job.options)
        run = pipeline.calibrate_source(
            path, setup, executor=InProcessExecutor(), marker=job.marker
        )
    except KincalError as exc:
        return RobotOutcome(serial, path, None, str(exc))
    try:
        information = unit_information(path, setup, run.result, job.marker)
    except (KincalError, ValueError, np.linalg.LinAlgError) as exc:
        # the calibration stands; only its link corrections stay out of the comparison
        return RobotOutcome(serial, path, run.result, information_error=str(exc))
    return RobotOutcome(serial, path, run.result, information=information)


def compared_link_columns(result: CalibrationResult) -> list[str]:
    """The link columns the fleet compares, in stacked-Jacobian order: every twist component
    of the inner links ``L_2..L_k`` (the measurement frame and the tool are each robot's own
    mounting), as ``<link>.<tx..rz>``."""
    return [f"{link.link}.{c}" for link in result.links[1:-1] for c in TWIST_COMPONENTS]


def unit_information(
    source: str, setup: pipeline.CalibrationSetup, result: CalibrationResult, marker: int | None
) -> UnitInformation:
    """The robot's fit linearised again at its solution over the rows it used (the Gram of
    the weighted design over its free columns and the compared link columns, its residual
    variance, its link corrections) for the fleet's common gauge (:mod:`solver.fleet_gauge`).
    Every recording is read as a measurement model's rows (a pose/position recording as
    :func:`~solver.measurement.pose_measurement`), so both fit paths give one design."""
    from service.app import measurement_input
    from solver.calibration import free_columns
    from solver.measurement import ModelParameters
    from solver.measurement.fit import weighted_system
    from solver.measurement.models import chain_column_count

    chain, options = (
        setup.chain,
        pipeline.fit_options(setup.options, free_columns=setup.free_columns),
    )
    model = measurement_input.measurement_for(setup.options, chain, source, marker)
    recording_source: str | PoseDataset = source
    if model is None:
        recording_source = measurement_input.read_chain_dataset(source, chain, marker)
        model = recording_source.measurement_model
    recording = measurement_input.read_measured(
        recording_source, chain, setup.options, model, marker=marker
    )
    model, rows = recording.model, recording.rows.take(np.asarray(result.outliers.kept_indices()))
    names = parameter_names(chain) + model.extra_names()
    unknowns = {u.name: u.value for u in result.measurement.unknowns} if result.measurement else {}
    extra = (
        np.array([unknowns[n] for n in model.extra_names()])
        if all(n in unknowns for n in model.extra_names())
        else model.start(chain, rows).extra
    )
    params = ModelParameters(
        np.array([link.placement for link in result.links], dtype=float),
        np.array([c.value_rad_per_nm for c in result.compliance], dtype=float),
        extra,
    )
    design, target = weighted_system(chain, model, params, rows, options)
    free = free_columns(chain, options, len(names))
    free[: chain_column_count(chain)] &= model.visible_columns(chain)
    compared = compared_link_columns(result)
    position = {n: i for i, n in enumerate(compared)}
    identifiability = result.identifiability
    held = {*identifiability.removed, *identifiability.pruned, *identifiability.fixed}
    # a nuisance column fixed by choice (a compliance pruned at 0 as unphysical) is part of
    # the unit's model, not of its gauge; a compared column the fit held is a gauge direction
    chosen = np.isin(names, [*identifiability.pruned, *identifiability.fixed])
    columns = np.flatnonzero((free & ~chosen) | np.isin(names, compared))
    kept = np.array([free[i] and names[i] not in held for i in columns])
    a = design[:, columns]
    estimate = np.zeros(len(compared))
    for link in result.links[1:-1]:
        assert link.correction_translation_m is not None and link.correction_rotation_rad
        for c, value in zip(
            TWIST_COMPONENTS,
            [*link.correction_translation_m, *link.correction_rotation_rad],
            strict=True,
        ):
            estimate[position[f"{link.link}.{c}"]] = value
    estimate[[position[n] for n in held if n in position]] = 0.0
    return UnitInformation(
        gram=a.T @ a,
        kept=kept,
        compared=np.array([position.get(names[i], -1) for i in columns], dtype=np.intp),
        estimate_compared=estimate,
        sigma2=float(target @ target) / max(1, target.size - int(kept.sum())),
        n_rows=int(target.size),
    )


def fleet_datasets(directory: str | Path) -> dict[str, str]:
    """Datasets of a fleet folder, by serial, sorted: its files (serial = the file name without
    suffix) and its ball-in-socket sub-folders (serial = the folder name)."""
    folder = Path(directory)
    check_fleet_folder(folder)
    files = sorted(
        p
        for p in folder.iterdir()
        if (p.suffix.lower() in SUFFIXES and p.is_file()) or is_socket_folder(p)
    )
    if not files:
        raise KincalError(
            f"{folder}: no datasets ({', '.join(SUFFIXES)}, or ball-in-socket folders); put one "
            "file (or socket folder) per robot serial there"
        )
    twice = [serial for serial, n in Counter(p.stem for p in files).items() if n > 1]
    if twice:
        raise KincalError(
            f"{folder}: serial(s) {', '.join(twice)} have more than one file; keep one per robot"
        )
    return {p.stem: str(p) for p in files}


@dataclass(frozen=True)
class ParameterSpread:
    """Population spread of one parameter over the robots that have it."""

    parameter: str
    joint: str | None
    unit: str
    n_robots: int
    median: float
    mad_sigma: float
    mean: float
    std: float
    min: float
    max: float
    z_threshold: float | None = DEFAULT_Z_THRESHOLD  # |robust z| to be flagged (None: < 3 robots)


@dataclass(frozen=True)
class Outlier:
    """A robot whose parameter is far from the fleet's (robust z-score)."""

    serial: str
    parameter: str
    joint: str | None
    value: float
    median: float
    robust_z: float
    z_threshold: float = DEFAULT_Z_THRESHOLD  # the parameter's (family-wise) threshold


@dataclass(frozen=True)
class RobotSummary:
    serial: str
    source: str
    n_samples: int
    n_used: int
    rms_after_mm: float
    parameters: dict[str, float]
    gauge_differs: bool = False


@dataclass(frozen=True)
class LinkGauge:
    """The common gauge the link corrections are compared in (:mod:`solver.fleet_gauge`):
    its dimension among the ``n_columns`` inner-link twist components, the robots that span
    it, the compared columns with the share of each the gauge holds, the columns left out
    with the reason, and the calibrated robots whose fit could not be linearised again (their
    link corrections are not compared) with the reason."""

    dimension: int
    n_columns: int
    direction_tolerance: float
    min_share: float
    robots: list[str]
    compared: dict[str, float]
    left_out: dict[str, str]
    robots_left_out: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class FleetReport:
    """Per-robot parameters, their population spread and the outliers (JSON via
    :meth:`to_json`)."""

    robot: str
    n_robots: int
    z_threshold: float
    robots: list[RobotSummary]
    population: list[ParameterSpread]
    outliers: list[Outlier]
    failures: dict[str, str] = field(default_factory=dict)
    false_alarm: float = FALSE_ALARM
    format: str = FLEET_FORMAT
    link_gauge: LinkGauge | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1, allow_nan=False)


@dataclass(frozen=True)
class FleetParameter:
    """One comparable value of a robot: its name, joint, unit, value and standard error."""

    name: str
    joint: str | None
    unit: str
    value: float
    stderr: float | None = None  # the robot's own standard error, if known
    needs_stderr: bool = True  # flag only deviations significant against ``stderr``


def robot_parameters(result: CalibrationResult) -> list[FleetParameter]:
    """The comparable parameters of one calibrated robot in its own fit (see the module
    docstring); its link corrections are compared in the fleet's common gauge
    (:func:`link_parameters`)."""
    out = [
        FleetParameter(
            f"compliance.{c.axis}", c.joint, "rad/N·m", c.value_rad_per_nm, c.stderr_rad_per_nm
        )
        for c in result.compliance
        if c.estimated
    ]
    if result.covariance is not None:
        for frame in result.covariance.frames:
            axes = ("vx", "vy", "vz", "wx", "wy", "wz")
            frame_errors = frame.std_stderr or (None,) * 6
            for axis, std, se in zip(axes, frame.std, frame_errors, strict=True):
                if std is None:  # not identifiable: nothing to compare
                    continue
                unit = "m" if axis.startswith("v") else "rad"
                out.append(FleetParameter(f"sigma.{frame.name}.{axis}", frame.name, unit, std, se))
    after = result.fit.after.train.translation_rms_mm
    out.append(FleetParameter("rms_after_mm", None, "mm", after, needs_stderr=False))
    return out


MIN_SHARE = 0.5
"""A link column is compared when at least this share of it (``P_jj``, scaled) lies in the
subspace every robot identifies: below, its common-gauge value is mostly other columns."""


def link_parameters(
    outcomes: Sequence[RobotOutcome],
) -> tuple[dict[str, list[FleetParameter]], LinkGauge | None]:
    """Every robot's link corrections in the fleet's common gauge, by serial, and the gauge
    (None with fewer than two robots linearised again). A column is compared when it was
    pruned on no robot and at least :data:`MIN_SHARE` of it lies in the common gauge; its
    value and standard error are the projections of
    :func:`solver.fleet_gauge.common_gauge_values`."""
    units = [o for o in outcomes if o.result is not None and o.information is not None]
    if len(units) < 2:
        return {}, None
    assert units[0].result is not None
    columns = compared_link_columns(units[0].result)
    gauge = common_gauge([o.information for o in units if o.information is not None])
    pruned: dict[str, list[str]] = {}
    for o in units:
        assert o.result is not None
        for name in o.result.identifiability.pruned:
            pruned.setdefault(name, []).append(o.serial)
    left_out: dict[str, str] = {}
    for j, column in enumerate(columns):
        if column in pruned:
            left_out[column] = f"held at nominal (pruned) on {', '.join(pruned[column])}"
        elif gauge.share[j] < MIN_SHARE:
            left_out[column] = f"{gauge.share[j]:.1%} in the common gauge, below {MIN_SHARE:.0%}"
    compared = [j for j, column in enumerate(columns) if column not in left_out]
    out: dict[str, list[FleetParameter]] = {}
    for o in units:
        assert o.information is not None
        values, errors = common_gauge_values(gauge, o.information)
        out[o.serial] = [
            FleetParameter(
                f"link.{columns[j]}",
                columns[j].rsplit(".", 1)[0],
                "m" if columns[j].rsplit(".", 1)[1].startswith("t") else "rad",
                float(values[j]),
                float(errors[j]),
            )
            for j in compared
        ]
    report = LinkGauge(
        gauge.dimension,
        len(columns),
        DIRECTION_TOLERANCE,
        MIN_SHARE,
        [o.serial for o in units],
        {columns[j]: float(gauge.share[j]) for j in compared},
        left_out,
        {
            o.serial: o.information_error or "not linearised again"
            for o in outcomes
            if o.result is not None and o.information is None
        },
    )
    return out, report


def robust_z(values: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Median, scaled MAD and robust z-scores of values (n,); a fleet without spread gets the
    mean absolute deviation (×1.2533) as scale, and z = 0 if that is 0 too."""
    median = float(np.median(values))
    deviation = np.abs(values - median)
    scale = MAD_TO_SIGMA * float(np.median(deviation))
    if scale <= 0.0:
        scale = 1.2533 * float(np.mean(deviation))
    z = (values - median) / scale if scale > 0.0 else np.zeros_like(values)
    return median, scale, z


_NULL_DRAWS = 200_000
_NULL_VALUES = 40_000_000


@functools.lru_cache(maxsize=256)
def family_wise_z(n_robots: int, tail: float) -> float:
    """The |robust z| (:func:`robust_z`) that the largest of ``n_robots`` values drawn from one
    Gaussian exceeds with probability ``tail``: the (1 − tail) quantile of
    ``max_i |x_i − median(x)| / (1.4826 · MAD(x))`` over simulated fleets (fixed seed; at least
    100 exceedances expected, at most :data:`_NULL_VALUES` values drawn). With few robots the
    MAD scatters and the quantile is far beyond 3.5 (6 robots, tail 1e-3: ≈ 22)."""
    if n_robots < 3:
        return float("inf")
    draws = int(min(max(_NULL_DRAWS, 100.0 / tail), _NULL_VALUES // n_robots))
    rng = np.random.default_rng(20261125)
    largest = []
    chunk = max(1, 2_000_000 // n_robots)
    for start in range(0, draws, chunk):
        x = rng.standard_normal((min(chunk, draws - start), n_robots))
        deviation = np.abs(x - np.median(x, axis=1, keepdims=True))
        largest.append(deviation.max(axis=1) / (MAD_TO_SIGMA * np.median(deviation, axis=1)))
    return float(np.quantile(np.concatenate(largest), 1.0 - tail))


def summarise_fleet(
    outcomes: Sequence[RobotOutcome],
    robot: str,
    *,
    z_threshold: float = DEFAULT_Z_THRESHOLD,
    false_alarm: float = FALSE_ALARM,
) -> FleetReport:
    """Population spread and robust-z outliers over the calibrated robots (thresholds: the
    module docstring)."""
    done = [o for o in outcomes if o.result is not None]
    links, link_gauge = link_parameters(done)
    params = {
        o.serial: robot_parameters(o.result) + links.get(o.serial, [])
        for o in done
        if o.result is not None
    }
    other_gauge = {o.serial for o in done if o.serial not in links}
    table: dict[str, dict[str, FleetParameter]] = {}
    meta: dict[str, tuple[str | None, str]] = {}
    for serial, robot_values in params.items():
        for p in robot_values:
            table.setdefault(p.name, {})[serial] = p
            meta[p.name] = (p.joint, p.unit)
    population, outliers = [], []
    compared = max(1, sum(len(by_robot) >= 3 for by_robot in table.values()))
    for name, by_robot in table.items():
        serials = list(by_robot)
        values = np.array([by_robot[s].value for s in serials])
        # unknown standard error (e.g. σ at the boundary 0): deviation never significant
        stderr = np.array(
            [
                np.inf
                if by_robot[s].needs_stderr and by_robot[s].stderr is None
                else by_robot[s].stderr or 0.0
                for s in serials
            ]
        )
        median, scale, z = robust_z(values)
        threshold = max(z_threshold, family_wise_z(values.size, false_alarm / compared))
        joint, unit = meta[name]
        population.append(
            ParameterSpread(
                name,
                joint,
                unit,
                len(serials),
                median,
                scale,
                float(values.mean()),
                float(values.std(ddof=1)) if values.size > 1 else 0.0,
                float(values.min()),
                float(values.max()),
                threshold if np.isfinite(threshold) else None,
            )
        )
        if values.size >= 3:
            significant = np.abs(values - median) > SIGNIFICANCE * stderr
            outliers += [
                Outlier(s, name, joint, float(v), median, float(zi), threshold)
                for s, v, zi, sig in zip(serials, values, z, significant, strict=True)
                if abs(zi) > threshold and sig
            ]
    outliers.sort(key=lambda o: -abs(o.robust_z))
    robots = []
    for o in done:
        assert o.result is not None
        robots.append(
            RobotSummary(
                o.serial,
                o.source,
                o.result.dataset.n_samples,
                o.result.outliers.n_used,
                o.result.fit.after.train.translation_rms_mm,
                {p.name: p.value for p in params[o.serial]},
                o.serial in other_gauge,
            )
        )
    failures = {o.serial: o.error or "" for o in outcomes if o.result is None}
    return FleetReport(
        robot,
        len(outcomes),
        z_threshold,
        robots,
        population,
        outliers,
        failures,
        false_alarm,
        link_gauge=link_gauge,
    )


def calibrate_fleet(
    datasets: dict[str, str],
    robot: RobotDescription,
    options: CalibrationOptions,
    executor: Executor | None = None,
    *,
    marker: int | None = None,
    z_threshold: float = DEFAULT_Z_THRESHOLD,
) -> tuple[FleetReport, list[RobotOutcome]]:
    """Calibrate every robot (serial → dataset path) on ``executor`` and summarise the fleet;
    the options are checked against the robot before any robot starts."""
    pipeline.check_calibration(robot, options)
    items = sorted(datasets.items())
    outcomes = (executor or InProcessExecutor()).map(
        calibrate_one, FleetJob(robot, options, marker), items
    )
    return summarise_fleet(outcomes, robot.name, z_threshold=z_threshold), outcomes


def fleet_table(report: FleetReport, *, max_parameters: int | None = None) -> str:
    """Readable summary: robots, outliers first, then the population spread."""
    lines = [
        f"fleet of {report.n_robots} {report.robot} robots: {len(report.robots)} calibrated, "
        f"{len(report.failures)} failed",
        "",
        f"{'serial':<16} {'samples':>8} {'used':>8} {'RMS after mm':>13}",
    ]
    lines += [
        f"{r.serial:<16} {r.n_samples:>8} {r.n_used:>8} {r.rms_after_mm:>13.4f}"
        + ("  (not linearised again: link corrections not compared)" if r.gauge_differs else "")
        for r in report.robots
    ]
    lines += [f"{serial:<16} FAILED: {error}" for serial, error in report.failures.items()]
    lines += [
        "",
        f"outliers (|robust z| beyond the larger of {report.z_threshold:g} and the level a "
        f"fleet of healthy robots reaches with probability {report.false_alarm:g}, per "
        f"parameter): {len(report.outliers)}",
    ]
    if report.outliers:
        lines.append(
            f"{'serial':<16} {'joint':<22} {'parameter':<40} {'value':>12} {'median':>12} "
            f"{'z':>7} {'beyond':>7}"
        )
        lines += [
            f"{o.serial:<16} {o.joint or '-':<22} {o.parameter:<40} {o.value:>12.4g} "
            f"{o.median:>12.4g} {o.robust_z:>7.1f} {o.z_threshold:>7.1f}"
            for o in report.outliers
        ]
    lines += link_gauge_lines(report.link_gauge)
    shown = report.population[:max_parameters] if max_parameters else report.population
    lines += [
        "",
        "population spread",
        f"{'parameter':<40} {'unit':<8} {'n':>4} {'median':>12} {'MAD σ':>11} {'min':>12} "
        f"{'max':>12}",
    ]
    lines += [
        f"{p.parameter:<40} {p.unit:<8} {p.n_robots:>4} {p.median:>12.4g} {p.mad_sigma:>11.3g} "
        f"{p.min:>12.4g} {p.max:>12.4g}"
        for p in shown
    ]
    if max_parameters and len(report.population) > max_parameters:
        lines.append(f"... {len(report.population) - max_parameters} more in the JSON")
    return "\n".join(lines)


def link_gauge_lines(gauge: LinkGauge | None) -> list[str]:
    """The table's paragraph on the link corrections: the common gauge, the columns compared
    and those left out with the reason."""
    if gauge is None:
        return ["", "link corrections: not compared (fewer than two robots linearised again)"]
    lines = [
        "",
        f"link corrections in the gauge every robot identifies ({gauge.dimension} of "
        f"{gauge.n_columns} inner-link directions; {len(gauge.robots)} robots): "
        f"{len(gauge.compared)} compared, {len(gauge.left_out)} left out",
    ]
    if gauge.compared:
        lines.append(
            "  compared (share in the gauge): "
            + ", ".join(f"{name} ({share:.0%})" for name, share in gauge.compared.items())
        )
    lines += [f"  left out {name}: {reason}" for name, reason in gauge.left_out.items()]
    lines += [
        f"  robot {serial} not compared: {reason}"
        for serial, reason in gauge.robots_left_out.items()
    ]
    return lines


def fleet_verdict_line(report: FleetReport) -> str:
    """The one line ``kincal fleet`` ends with: how many robots calibrated, how many units are
    flagged (and which), at the fleet's family-wise false-alarm level."""
    flagged = sorted({o.serial for o in report.outliers})
    failed = f", {len(report.failures)} failed ({', '.join(report.failures)})"
    return (
        f"verdict: {len(report.robots)} of {report.n_robots} robots calibrated"
        f"{failed if report.failures else ''}; "
        + (
            f"{len(flagged)} flagged ({', '.join(flagged)}): inspect them"
            if flagged
            else "no robot flagged"
        )
        + f" (false-alarm probability {report.false_alarm:g} over the fleet; exit code 0)"
    )
