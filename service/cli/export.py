"""``kincal export`` and ``kincal dh-urdf``: a calibration (or a DH table) in the formats a
robot controller or the HTTP service reads."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from schemas.robots import load_robot
from service.cli.common import OUTPUT, Outputs, read_result
from solver.errors import KincalError

OutputFile = Annotated[
    Path, typer.Option("-o", "--output", help="The file to write.", rich_help_panel=OUTPUT)
]


def dh_urdf_command(
    table: Annotated[Path, typer.Argument(help="DH or modified-DH table (YAML, docs/dh.md).")],
    output: OutputFile,
) -> None:
    """Write the URDF kincal builds from a DH table (e.g. to upload the robot to the HTTP
    service, POST /api/v1/robots, with the table's base and tip frames)."""
    description = load_robot(dh_path=table)
    outputs = Outputs(output.parent)
    outputs.write_text(
        outputs.path(output, output.name, None),
        f"URDF (base frame {description.base_frame}, tip frame {description.tip_frame})",
        description.urdf_xml,
    )
    typer.echo(outputs.listing())


def export_command(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result JSON.")],
    output: OutputFile,
    format: Annotated[
        str,
        typer.Option(
            "--format",
            help="urdf (the robot's URDF, calibrated joint origins), offsets-yaml / "
            "offsets-csv (joint-offset table), dh / mdh (DH or modified-DH table, the YAML of "
            "calibrate --dh), pal-master (PAL's master_calibration.yaml), ur-kinematics (Universal "
            "Robots' kinematics YAML for ur_description and the UR driver).",
        ),
    ] = "urdf",
    measurement_frame: Annotated[
        bool,
        typer.Option(
            help="urdf, dh, mdh: also write the measurement frame (root) and the marker (tip) "
            "as extra links / base and tool transforms."
        ),
    ] = False,
    force: Annotated[
        bool, typer.Option(help="Export even when the calibration's verdict is failed.")
    ] = False,
) -> None:
    """Write a calibration in a format a robot controller uses (docs/exports.md). Each
    reproduces kincal's calibrated forward kinematics where the format can express it; what it
    cannot (gravity-dependent compliance; link geometry in an offsets table) is printed."""
    result = read_result(
        result_path
    )  # a result that is not there: refused before the exporters load
    from service.render import exports

    if format not in exports.FORMATS:
        raise KincalError(f"--format {format!r}: choose one of {', '.join(exports.FORMATS)}")
    verdict = result.verdict
    if verdict is not None and verdict.status == "failed" and not force:
        causes = "; ".join(r.message for r in verdict.reasons if r.severity == "failed")
        raise KincalError(
            f"{result_path}: the calibration's verdict is failed ({causes}); nothing written "
            "(--force exports it anyway)"
        )
    chosen: exports.ExportFormat = format  # type: ignore[assignment]
    outputs = Outputs(output.parent)
    outputs.write_text(
        outputs.path(output, output.name, None),
        f"{format} export",
        exports.export(result, chosen, measurement_frame=measurement_frame),
    )
    for line in exports.not_expressed(result) + exports.offsets_not_exact(result, chosen):
        typer.echo(f"not expressed: {line}", err=True)
    typer.echo(outputs.listing())
    from service.render.text import verdict_line

    typer.echo(f"calibration {verdict_line(verdict)}")
