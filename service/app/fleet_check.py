"""Fleet check mode (``kincal fleet CHECKS_DIR --check RESULTS_DIR``, issue 33): every unit's
check recording against its own calibration result, matched by unit name, each checked by
:func:`service.app.check.run_check` exactly as ``kincal check`` checks it.

Every pair is read and refused before any unit is checked (a unit with no result, no check
recording, or a check recording of another robot, measurement type or frames names the unit),
so a fleet is not stopped halfway.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from schemas.calibration import CalibrationResult
from schemas.check import CheckResult, FleetCheck, FleetCheckUnit
from schemas.dataset import PoseDataset
from schemas.dataset.paths import check_results_folder
from service import kincal_version
from service.app.check import read_check_recording, refuse_unsupported, run_check
from service.app.fleet import fleet_datasets
from service.render.text import check_size
from solver.errors import KincalError


@dataclass(frozen=True)
class UnitPair:
    """A unit's calibration result (read) and its check recording (read and checked)."""

    unit: str
    result_path: Path
    result: CalibrationResult
    recording: PoseDataset


def unit_results(results_dir: Path) -> dict[str, Path]:
    """The calibration results of a fleet, by unit: the ``<unit>.json`` files of
    ``results_dir`` (what ``kincal fleet --results-dir`` writes)."""
    check_results_folder(results_dir)
    return {p.stem: p for p in sorted(results_dir.glob("*.json")) if p.is_file()}


def fleet_check_pairs(
    checks_dir: Path,
    results_dir: Path,
    read_result: Callable[[Path], CalibrationResult],
) -> list[UnitPair]:
    """Each unit's result and check recording, matched by name (sorted), every one read and
    checked as ``kincal check`` checks it; :class:`KincalError` naming the units with no
    result or no check recording, or the unit whose recording the check refuses."""
    recordings = fleet_datasets(checks_dir)
    results = unit_results(results_dir)
    no_result = sorted(set(recordings) - set(results))
    no_recording = sorted(set(results) - set(recordings))
    if no_result:
        raise KincalError(
            f"unit(s) {', '.join(no_result)}: a check recording in {checks_dir} but no "
            f"calibration result <unit>.json in {results_dir}"
        )
    if no_recording:
        raise KincalError(
            f"unit(s) {', '.join(no_recording)}: a calibration result in {results_dir} but no "
            f"check recording in {checks_dir}"
        )
    pairs = []
    for unit, source in recordings.items():
        path = results[unit]
        try:
            result = read_result(path)
            refuse_unsupported(result, str(path))
            recording = read_check_recording(source, result, str(path))
        except KincalError as exc:
            raise KincalError(f"unit {unit}: {exc}") from exc
        pairs.append(UnitPair(unit, path, result, recording))
    return pairs


def run_fleet_check(pairs: list[UnitPair], *, level: float) -> FleetCheck:
    """Check every unit (:func:`service.app.check.run_check`) at family-wise ``level`` each."""
    units = []
    for pair in pairs:
        try:
            check = run_check(
                pair.result, pair.recording, level=level, result_name=str(pair.result_path)
            )
        except KincalError as exc:
            raise KincalError(f"unit {pair.unit}: {exc}") from exc
        units.append(FleetCheckUnit(unit=pair.unit, result=str(pair.result_path), check=check))
    verdicts = {v: [u.unit for u in units if u.check.verdict == v] for v in VERDICTS}
    return FleetCheck(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        level=level,
        fleet_false_alarm=1.0 - (1.0 - level) ** len(units),
        holds=verdicts["holds"],
        drifted=verdicts["drifted"],
        inconclusive=verdicts["inconclusive"],
        units=units,
    )


VERDICTS = ("holds", "drifted", "inconclusive")


def unit_line(unit: str, check: CheckResult, width: int) -> str:
    """One unit's line: verdict, Σ d² against its limit, the located change."""
    g = check.global_test
    statistic = "-" if g is None else f"{g.statistic:.1f} / {g.threshold:.1f}"
    located = "-"
    if check.located is not None:
        sizes = ", ".join(
            f"{c.name} {check_size(c.value, c.unit)}" for c in check.located.components
        )
        located = f"{check.located.name}: {sizes}"
    bad = [str(p.index) for p in check.poses if p.bad_sample]
    note = f"  (bad sample(s): pose {', '.join(bad)})" if bad else ""
    return f"{unit:<{width}}  {check.verdict:<12}  {statistic:>15}  {located}{note}"


def fleet_check_table(report: FleetCheck) -> str:
    """The header and one line per unit."""
    width = max([4] + [len(u.unit) for u in report.units])
    lines = [f"{'unit':<{width}}  {'verdict':<12}  {'Σ d² / limit':>15}  located change"]
    lines += [unit_line(u.unit, u.check, width) for u in report.units]
    return "\n".join(lines)


def fleet_check_verdict_line(report: FleetCheck) -> str:
    """The line ``kincal fleet --check`` ends with: how many units hold, drifted (named) or
    are inconclusive, at which family-wise level."""
    n = len(report.units)
    drifted = f" ({', '.join(report.drifted)})" if report.drifted else ""
    code = 3 if report.drifted else 0
    return (
        f"fleet check: {n} units: {len(report.holds)} hold, {len(report.drifted)} drifted"
        f"{drifted}, {len(report.inconclusive)} inconclusive; each unit at family-wise level "
        f"{report.level:g}, so a fleet of {n} units that all hold shows some drift with "
        f"probability {report.fleet_false_alarm:.2g} (exit code {code})"
    )
