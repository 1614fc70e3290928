"""``kincal discover``: the physics a recording shows and the model lacks."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import pydantic
import typer

from service.cli.flags import CALIBRATION_FLAGS
from solver.errors import KincalError

if TYPE_CHECKING:
    pass
from service.cli.common import (
    BaseOpt,
    DataArg,
    MeasurementOpt,
    OutputOpt,
    PointDistanceOpt,
    RobotOpt,
    TipOpt,
    UrdfOpt,
    _names,
    _robot,
    _vector3,
    _write_json,
    _write_text,
)


def discover(
    data: DataArg,
    output: OutputOpt,
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    compliant_joints: Annotated[
        str | None, typer.Option(help="Joints your model already treats as elastic.")
    ] = None,
    virtual_axes: Annotated[
        str | None, typer.Option(help="Joints your model already gives virtual flex axes.")
    ] = None,
    gravity: Annotated[str, typer.Option(help="Gravity in the base frame, m/s².")] = "0,0,-9.81",
    payload_kg: Annotated[float, typer.Option(min=0.0, help="Payload if not in the data.")] = 0.0,
    payload_com: Annotated[str, typer.Option(help="Payload centre in the tip frame, m.")] = "0,0,0",
    alpha: Annotated[float, typer.Option(help="Family-wise error rate per step.")] = 0.01,
    seed: Annotated[int, typer.Option(min=0, help="Folds, bootstrap, pose pool.")] = 0,
    max_terms: Annotated[int, typer.Option(min=0, help="At most this many terms.")] = 6,
    effects: Annotated[
        str | None, typer.Option(help="Comma-separated library effects (default: all).")
    ] = None,
    folds: Annotated[int, typer.Option(help="K of the held-out check.")] = 5,
    bootstrap: Annotated[int, typer.Option(min=0, help="Bootstrap replicates.")] = 50,
    detectability: Annotated[
        bool,
        typer.Option(
            help="State the smallest detectable size of each term left out (a report only; "
            "--no-detectability saves most of a small recording's run)."
        ),
    ] = True,
    noise_mm: Annotated[float | None, typer.Option(help="Sensor noise σ (mm), for χ².")] = None,
    noise_deg: Annotated[float | None, typer.Option(help="Sensor noise σ (deg).")] = None,
    measurement: MeasurementOpt = None,
    point_distance: PointDistanceOpt = None,
    marker: Annotated[int | None, typer.Option(help="FIGAROH files: which marker.")] = None,
    plots: Annotated[bool, typer.Option(help="Write a PNG per finding next to -o.")] = True,
    report: Annotated[
        Path | None, typer.Option(help="Also write the HTML report (figures embedded).")
    ] = None,
) -> None:
    """Find what the model leaves out, name the physics, model it, show the held-out gain."""
    from schemas.discovery import DiscoveryOptions
    from service.app import discover as discovery

    description = _robot(robot, urdf, base, tip)
    try:
        options = DiscoveryOptions(
            compliant_joints=_names(compliant_joints) or [],
            virtual_axes_at=_names(virtual_axes) or [],
            gravity_base_m_s2=_vector3(gravity, "--gravity"),
            payload_kg=payload_kg,
            payload_com_m=_vector3(payload_com, "--payload-com"),
            alpha=alpha,
            seed=seed,
            max_terms=max_terms,
            effects=_names(effects) or list(discovery.EFFECTS),  # type: ignore[arg-type]
            folds=folds,
            bootstrap=bootstrap,
            detectability=detectability,
            sensor_sigma_mm=noise_mm,
            sensor_sigma_deg=noise_deg,
            measurement=measurement or "auto",
            point_distance_m=point_distance,
        )
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        flag = CALIBRATION_FLAGS.get(str(first["loc"][0]))
        raise KincalError(
            f"option {first['loc'][0]}{f' ({flag})' if flag else ''}: {first['msg']} "
            f"(got {first.get('input')!r})"
        ) from exc
    plot_dir = output.resolve().parent if plots else None
    findings = discovery.discover_source(
        data, description, options, plot_dir, output.stem, marker=marker
    )
    _write_json(output, findings.model_dump_json(indent=1))
    typer.echo(discovery.summary(findings))
    typer.echo(f"\nfindings written to {output}")
    figures = [f.plot for f in findings.findings if f.plot is not None and plot_dir is not None]
    for name in figures:
        typer.echo(f"figure written to {output.parent / name}")
    if report is not None:
        from service.app.discovery_html import render_discovery_report

        assert plot_dir is not None or not figures
        embedded = {name: (output.parent / name).read_bytes() for name in figures}
        _write_text(report, render_discovery_report(findings, embedded))
        typer.echo(f"report written to {report}")
