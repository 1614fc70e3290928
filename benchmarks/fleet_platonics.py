"""``kincal fleet`` over the twelve platonics Panda folders (ball in socket, sockets 50 mm
apart): per robot the rows used, the training RMS, the joint compliances and the link
corrections fitted, the fleet's verdict (which unit stands out, at the fleet's family-wise
level) and the link corrections compared in the gauge every arm identifies (issue 31): per
compared column the share of it in that gauge, the fleet's median and MAD σ, the arms' median
standard error, and the deviation from the median a unit must exceed to be flagged. The same path as

    kincal fleet <folder of the Panda folders> --robot panda --config sockets.toml

with ``sockets.toml`` = ``measurement = "point"`` and ``point_distance_m = 0.05`` (held-out
splits off, the fleet default). With ``--write-results`` writes
``docs/results/fleet_platonics.{json,md}`` (docs/ball-in-socket.md includes the table;
tests/test_quoted_numbers.py re-runs panda_left and panda_right against it).

Usage: ``python -m benchmarks.fleet_platonics [--write-results] [--robots panda_1,...]``.
"""

from __future__ import annotations

import argparse

import numpy as np

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.platonics import DATA, SOCKET_DISTANCE_M, panda_folders
from benchmarks.results import Row, markdown_table, write_results
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.robots import load_robot
from service.app import fleet as fleet_mode

OPTIONS = CalibrationOptions(measurement="point", point_distance_m=SOCKET_DISTANCE_M, heldout=False)
COMPLIANT = ("panda_joint2", "panda_joint3", "panda_joint4", "panda_joint5", "panda_joint6")


def robot_row(serial: str, result: CalibrationResult) -> Row:
    """The numbers of one robot: compliance in rad/N·m (None: pruned or not estimated), link
    corrections fitted (twist components with a standard error) and the largest translation."""
    compliance = {
        c.joint: (c.value_rad_per_nm if c.estimated and not c.pruned else None)
        for c in result.compliance
        if c.kind == "joint"
    }
    fitted, largest, largest_name = 0, 0.0, "-"
    for link in result.links[1:-1]:  # the measurement frame and the tool are not corrections
        if link.correction_translation_m is None:
            continue
        errors = [*link.stderr_translation_m, *link.stderr_rotation_rad]
        fitted += sum(e is not None for e in errors)
        for axis, value, error in zip(
            "xyz", link.correction_translation_m, link.stderr_translation_m, strict=True
        ):
            if error is not None and abs(value) > largest:
                largest, largest_name = abs(value), f"{link.link.removeprefix('panda_')}.t{axis}"
    return {
        "robot": serial,
        "rows": result.outliers.n_input,
        "used": result.outliers.n_used,
        "train_rms_mm": result.fit.after.train.translation_rms_mm,
        "compliance_rad_per_nm": {joint: compliance.get(joint) for joint in COMPLIANT},
        "link_corrections": fitted,
        "largest_translation": largest_name,
        "largest_translation_mm": 1e3 * largest,
    }


def run(
    serials: list[str],
) -> tuple[list[Row], fleet_mode.FleetReport, list[fleet_mode.RobotOutcome]]:
    """Calibrate the robots as ``kincal fleet`` does; their rows, the fleet report and the
    robots' outcomes."""
    datasets = {serial: str(DATA / serial) for serial in serials}
    report, outcomes = fleet_mode.calibrate_fleet(datasets, load_robot("panda"), OPTIONS)
    rows = [robot_row(o.serial, o.result) for o in outcomes if o.result is not None]
    return rows, report, outcomes


def link_gauge_row(report: fleet_mode.FleetReport, outcomes: list[fleet_mode.RobotOutcome]) -> Row:
    """The link corrections in the common gauge: its dimension, per compared column its
    share, the fleet's median and MAD σ, the arms' median standard error in the gauge and
    the family-wise level (z) the deviation must exceed; the columns left out and why."""
    gauge = report.link_gauge
    assert gauge is not None
    links = fleet_mode.link_parameters(outcomes)[0]
    errors: dict[str, list[float]] = {}
    for parameters in links.values():
        for p in parameters:
            errors.setdefault(p.name, []).append(p.stderr or 0.0)
    spread = {p.parameter: p for p in report.population}
    return {
        "link_gauge": {
            "dimension": gauge.dimension,
            "n_columns": gauge.n_columns,
            "compared": [
                {
                    "column": column,
                    "share": share,
                    "median": spread[f"link.{column}"].median,
                    "mad_sigma": spread[f"link.{column}"].mad_sigma,
                    "median_stderr": float(np.median(errors[f"link.{column}"])),
                    "z_threshold": spread[f"link.{column}"].z_threshold,
                }
                for column, share in gauge.compared.items()
            ],
            "left_out": gauge.left_out,
            "same_arm": same_arm_differences(links),
        }
    }


def same_arm_differences(links: dict[str, list[fleet_mode.FleetParameter]]) -> list[Row]:
    """Each arm recorded twice (``panda_2`` and ``panda_2_clean``, …): the largest difference
    of a compared link column between its two recordings, in their combined standard errors
    (about 2 if the common gauge and its standard errors are honest)."""
    out: list[Row] = []
    for first in sorted(links):
        for second in sorted(s for s in links if s.startswith(first + "_")):
            pairs = zip(links[first], links[second], strict=True)
            worst = max(
                abs(a.value - b.value) / float(np.hypot(a.stderr or 0.0, b.stderr or 0.0))
                for a, b in pairs
            )
            out.append({"arm": first, "recordings": [first, second], "max_difference_se": worst})
    return out


def _compliance(value: float | None) -> str:
    return "–" if value is None else f"{1e5 * value:.1f}"


def render(rows: list[Row]) -> str:
    """The per-robot table (compliance in 10⁻⁵ rad/N·m, – = fixed at 0 or not identified) and
    the fleet's line, which the last row carries."""
    body = [
        (
            r["robot"],
            f"{r['rows']} ({r['used']})",
            f"{r['train_rms_mm']:.3f}",
            *(_compliance(r["compliance_rad_per_nm"][j]) for j in COMPLIANT),
            f"{r['link_corrections']} (largest translation {r['largest_translation']} "
            f"{r['largest_translation_mm']:.1f} mm)",
        )
        for r in rows
        if "robot" in r
    ]
    header = ("robot", "rows (used)", "train RMS mm", "C2", "C3", "C4", "C5", "C6")
    table = markdown_table((*header, "link corrections fitted"), body)
    fleet = [r for r in rows if "fleet" in r]
    links = [r["link_gauge"] for r in rows if "link_gauge" in r]
    return (
        table
        + ("\n\n" + fleet[0]["fleet"] if fleet else "")
        + ("\n\n" + render_link_gauge(links[0]) if links else "")
    )


def render_link_gauge(gauge: Row) -> str:
    """The compared link columns (mm and mrad; "flagged beyond" = z × MAD σ, also in the
    arms' median standard errors) and the columns left out."""
    body = []
    for c in gauge["compared"]:
        scale, unit = (
            (1e3, "mm") if c["column"].rsplit(".", 1)[1].startswith("t") else (1e3, "mrad")
        )
        beyond = c["z_threshold"] * c["mad_sigma"]
        body.append(
            (
                c["column"].removeprefix("panda_"),
                f"{100 * c['share']:.0f} %",
                f"{scale * c['median']:+.3f} {unit}",
                f"{scale * c['mad_sigma']:.3f} {unit}",
                f"{scale * c['median_stderr']:.3f} {unit}",
                f"{c['mad_sigma'] / c['median_stderr']:.1f}",
                f"{c['z_threshold']:.1f}",
                f"{scale * beyond:.2f} {unit} ({beyond / c['median_stderr']:.0f} SE)",
            )
        )
    header = (
        "link column",
        "share in gauge",
        "fleet median",
        "fleet MAD σ",
        "median SE",
        "MAD σ / SE",
        "z level",
        "flagged beyond",
    )
    left_out = "; ".join(
        f"{name.removeprefix('panda_')}: {reason}" for name, reason in gauge["left_out"].items()
    )
    same = ", ".join(
        f"{' / '.join(r['recordings'])} {r['max_difference_se']:.1f}" for r in gauge["same_arm"]
    )
    return (
        f"Link corrections compared in the gauge every arm identifies ({gauge['dimension']} "
        f"of {gauge['n_columns']} inner-link directions):\n\n"
        + markdown_table(header, body)
        + f"\n\nLeft out: {left_out}.\n\nThe same arm recorded twice, largest difference of "
        f"a compared column in combined standard errors: {same}."
    )


def fleet_row(report: fleet_mode.FleetReport) -> Row:
    """The fleet's verdict and its nearest unit, as a row of the results."""
    rms = {r.serial: r.rms_after_mm for r in report.robots}
    median = float(np.median(list(rms.values())))
    nearest = max(rms, key=lambda serial: rms[serial])
    return {
        "fleet": f"{fleet_mode.fleet_verdict_line(report)}. Largest training RMS: {nearest} "
        f"({rms[nearest]:.3f} mm against a median of {median:.3f} mm)."
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", help="comma-separated robot folders (default: every Panda)")
    parser.add_argument(
        "--write-results", action="store_true", help="write docs/results/fleet_platonics.*"
    )
    arguments = parser.parse_args()
    serials = arguments.robots.split(",") if arguments.robots else panda_folders()
    rows, report, outcomes = run(serials)
    rows += [fleet_row(report), link_gauge_row(report, outcomes)]
    print(fleet_mode.fleet_table(report, max_parameters=10))
    print("\n" + render(rows))
    if arguments.write_results:
        command = "python -m benchmarks.fleet_platonics --write-results"
        for path in write_results("fleet_platonics", command, rows, render):
            print("wrote", path)


if __name__ == "__main__":
    main()
