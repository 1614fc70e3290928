"""``kincal discover``: the physics a recording shows and the model lacks."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Annotated

import typer

from schemas.dataset.paths import check_recording_path
from service.cli.common import (
    EXECUTION,
    OUTPUT,
    BaseOpt,
    DaskOpt,
    DataArg,
    DhOpt,
    MarkerOpt,
    MeasurementOpt,
    OutDirOpt,
    Outputs,
    PointDistanceOpt,
    ReportOpt,
    RobotOpt,
    TipOpt,
    UrdfOpt,
    WorkersOpt,
    _executor,
    _names,
    _robot,
    _vector3,
    out_dir_for,
    output_option,
)
from service.cli.flags import CALIBRATION_FLAGS
from service.cli.generated_help import DISCOVERY_EFFECTS
from solver.errors import KincalError

FindingsOut = Annotated[Path | None, output_option("findings.json", "The findings JSON")]


def discover(
    data: DataArg,
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    dh: DhOpt = None,
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
    marker: MarkerOpt = None,
    output: FindingsOut = None,
    out_dir: OutDirOpt = None,
    plots: Annotated[
        bool, typer.Option(help="Write a PNG per finding next to -o.", rich_help_panel=OUTPUT)
    ] = True,
    report: ReportOpt = None,
    executor: Annotated[
        str | None,
        typer.Option(
            help="Where the smallest detectable sizes are computed (most of a run's time): "
            "inprocess, processes (local, one per core) or dask. Default: in this process. "
            "The findings do not depend on it.",
            metavar="inprocess|processes|dask",
            rich_help_panel=EXECUTION,
        ),
    ] = None,
    workers: WorkersOpt = None,
    dask: DaskOpt = None,
) -> None:
    """Find what the model leaves out, name the physics, model it, show the held-out gain."""
    check_recording_path(data)
    import pydantic

    from schemas.discovery import DiscoveryOptions

    description = _robot(robot, urdf, base, tip, dh)
    outputs = Outputs(out_dir_for(out_dir, data, "discovery"))
    output = outputs.path(output, "findings.json", "kincal.findings/1")
    report_path = None if report is None else outputs.path(report, "findings.html", None)
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
            effects=_names(effects) or list(DISCOVERY_EFFECTS),  # type: ignore[arg-type]
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
    preflight_discovery(data, description, options.measurement, marker)
    from service.app import discover as discovery
    from service.render.findings import summary

    plot_dir = output.resolve().parent if plots else None
    if plot_dir is not None:
        plot_dir.mkdir(parents=True, exist_ok=True)
    from solver.executors import preload_in_workers

    preload_in_workers("solver.discovery.detectability")  # what local workers import once
    with _executor(executor, dask, workers) or contextlib.nullcontext() as pool:
        findings = discovery.discover_source(
            data, description, options, plot_dir, output.stem, marker=marker, executor=pool
        )
    outputs.write_text(output, "findings", findings.model_dump_json(indent=1) + "\n")
    figures = [f.plot for f in findings.findings if f.plot is not None and plot_dir is not None]
    for name in figures:
        outputs.note(output.parent / name, "figure of a finding")
    if report_path is not None:
        from service.render.discovery_html import render_discovery_report

        assert plot_dir is not None or not figures
        embedded = {name: (output.parent / name).read_bytes() for name in figures}
        outputs.write_text(report_path, "HTML report", render_discovery_report(findings, embedded))
    typer.echo(summary(findings))
    typer.echo(outputs.listing())
    typer.echo(findings_line(findings))


def preflight_discovery(
    data: Path, description: object, measurement: str, marker: int | None
) -> None:
    """The pre-flight checks (:mod:`service.app.preflight`) before discovery's fits."""
    from schemas.robots import RobotDescription
    from service.app.preflight import check_recording
    from solver.model import build_chain

    assert isinstance(description, RobotDescription)
    chain = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    check_recording(data, chain, marker=marker, measurement=measurement)


def findings_line(findings: object) -> str:
    """The one-line verdict of a discovery: what it named, or that nothing is missing."""
    from schemas.discovery import FindingsResult

    assert isinstance(findings, FindingsResult)
    named = len(findings.findings)
    parts = [f"{named} effect(s) named"] if named else ["nothing named"]
    if findings.ambiguous:
        parts.append(f"{len(findings.ambiguous)} ambiguous")
    if findings.unexplained:
        parts.append(f"{len(findings.unexplained)} unexplained")
    if named:
        advice = "calibrate with --model on the findings file to carry them"
    elif findings.unexplained:
        advice = "read the unexplained structure above"
    elif findings.ambiguous:
        advice = "the data cannot tell the ambiguous terms apart (see above)"
    else:
        advice = "the model describes the recording"
    return f"verdict: {', '.join(parts)}: {advice} (exit code 0)"
