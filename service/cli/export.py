"""``kincal export`` and ``kincal dh-urdf``: a calibration (or a DH table) in the formats a
robot controller or the HTTP service reads."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.robots import load_robot
from solver.errors import KincalError

if TYPE_CHECKING:
    pass
from service.cli.common import OutputOpt, _write_text, read_result


def dh_urdf_command(
    table: Annotated[Path, typer.Argument(help="DH or modified-DH table (YAML, docs/dh.md).")],
    output: OutputOpt,
) -> None:
    """Write the URDF kincal builds from a DH table (e.g. to upload the robot to the HTTP
    service, POST /api/v1/robots, with the table's base and tip frames)."""
    description = load_robot(dh_path=table)
    _write_text(output, description.urdf_xml)
    typer.echo(
        f"wrote {output} (base frame {description.base_frame}, tip frame {description.tip_frame})"
    )


def export_command(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result JSON.")],
    output: OutputOpt,
    format: Annotated[
        str,
        typer.Option(
            "--format",
            help="urdf (the robot's URDF, calibrated joint origins), offsets-yaml / "
            "offsets-csv (joint-offset table), dh / mdh (DH or modified-DH table, the YAML of "
            "calibrate --dh), pal-master (PAL's master_calibration.yaml).",
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
    from service.render import exports

    if format not in exports.FORMATS:
        raise KincalError(f"--format {format!r}: choose one of {', '.join(exports.FORMATS)}")
    result = read_result(result_path)
    verdict = result.verdict
    if verdict is not None and verdict.status == "failed" and not force:
        causes = "; ".join(r.message for r in verdict.reasons if r.severity == "failed")
        raise KincalError(
            f"{result_path}: the calibration's verdict is failed ({causes}); nothing written "
            "(--force exports it anyway)"
        )
    chosen: exports.ExportFormat = format  # type: ignore[assignment]
    _write_text(output, exports.export(result, chosen, measurement_frame=measurement_frame))
    for line in exports.not_expressed(result) + exports.offsets_not_exact(result, chosen):
        typer.echo(f"not expressed: {line}", err=True)
    typer.echo(f"wrote {format} to {output}")
