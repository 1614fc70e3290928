"""``kincal simulate`` and ``kincal calibrate``: a recording in, a calibration result out."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.dataset import write_dataset
from service.app import calibrate as pipeline
from service.app import simulate as scenarios
from service.cli.flags import (
    CALIBRATION_FLAGS,
    calibration_options,
    numbers,
    option_help,
    read_config,
)
from service.render.text import summary, verdict_text
from solver.errors import KincalError

if TYPE_CHECKING:
    pass
from service.cli.common import (
    BaseOpt,
    ChunkRowsOpt,
    DaskOpt,
    DataArg,
    DhOpt,
    ExecutorOpt,
    MeasurementOpt,
    OutputOpt,
    PointDistanceOpt,
    RobotOpt,
    TipOpt,
    UrdfOpt,
    WorkersOpt,
    _executor,
    _integers,
    _names,
    _robot,
    _vector3,
    _write_json,
    _write_text,
    read_findings,
    read_noise_covariance,
)


def simulate(
    output: OutputOpt,
    robot: RobotOpt = "kinova",
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    n: Annotated[int, typer.Option("--n", min=1, help="Number of configurations.")] = 154,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 1,
    effect: Annotated[
        list[str] | None,
        typer.Option(
            "--effect",
            help="Repeatable. "
            + "; ".join(f"{k}: {v}" for k, v in scenarios.EFFECTS.items())
            + f". Default: {', '.join(scenarios.DEFAULT_EFFECTS)}.",
        ),
    ] = None,
    noise_mm: Annotated[float, typer.Option(min=0.0, help="Measurement noise σ, mm.")] = 0.05,
    noise_deg: Annotated[float, typer.Option(min=0.0, help="Measurement noise σ, deg.")] = 0.003,
    position_only: Annotated[bool, typer.Option(help="Write positions only.")] = False,
    truth: Annotated[Path | None, typer.Option(help="Also write the ground truth JSON.")] = None,
) -> None:
    """Simulate a recording with known ground truth and write it in the dataset contract."""
    description = _robot(robot if urdf is None else None, urdf, base, tip)
    scn, recording = scenarios.simulate(
        description,
        n_samples=n,
        seed=seed,
        effects=effect or scenarios.DEFAULT_EFFECTS,
        noise_translation_mm=noise_mm,
        noise_rotation_deg=noise_deg,
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, position_only=position_only)
    write_dataset(dataset, output)
    if truth is not None:
        _write_json(
            truth, json.dumps(scenarios.truth_document(scn, recording, description), indent=1)
        )
    typer.echo(f"wrote {n} samples ({', '.join(scn.effects)}) to {output}")


def calibrate(
    data: DataArg,
    output: OutputOpt,
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    dh: DhOpt = None,
    config: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of calibration options (the option names in [brackets] below as "
            "keys); flags given as well override it."
        ),
    ] = None,
    compliant_joints: Annotated[
        str | None, typer.Option(help=option_help("compliant_joints", "; comma-separated"))
    ] = None,
    rigid: Annotated[
        bool, typer.Option(help="No joint compliance at all (compliant_joints = []).")
    ] = False,
    free: Annotated[
        str | None, typer.Option(help=option_help("free_parameters", "; comma-separated"))
    ] = None,
    fix: Annotated[
        str | None, typer.Option(help=option_help("fixed_parameters", "; comma-separated"))
    ] = None,
    virtual_axes: Annotated[
        str | None, typer.Option(help=option_help("virtual_axes_at", "; comma-separated"))
    ] = None,
    gravity: Annotated[str | None, typer.Option(help=option_help("gravity_base_m_s2"))] = None,
    payload_kg: Annotated[float | None, typer.Option(help=option_help("payload_kg"))] = None,
    payload_com: Annotated[str | None, typer.Option(help=option_help("payload_com_m"))] = None,
    rotation_weight: Annotated[
        float | None, typer.Option(help=option_help("rotation_weight_m_per_rad"))
    ] = None,
    outlier_rule: Annotated[
        str | None, typer.Option(help=option_help("outlier_rule", "; model|sigma|none"))
    ] = None,
    outlier_level: Annotated[float | None, typer.Option(help=option_help("outlier_level"))] = None,
    outlier_sigma: Annotated[
        float | None, typer.Option(help=option_help("outlier_sigma", "; 0 disables"))
    ] = None,
    max_iterations: Annotated[int | None, typer.Option(help=option_help("max_iterations"))] = None,
    tolerance: Annotated[float | None, typer.Option(help=option_help("tolerance"))] = None,
    rank_tolerance: Annotated[
        float | None, typer.Option(help=option_help("rank_tolerance"))
    ] = None,
    heldout: Annotated[
        bool | None, typer.Option("--heldout/--no-heldout", help=option_help("heldout"))
    ] = None,
    seeds: Annotated[
        str | None, typer.Option(help=option_help("seeds", "; comma-separated"))
    ] = None,
    train_fraction: Annotated[
        float | None, typer.Option(help=option_help("train_fraction"))
    ] = None,
    covariance: Annotated[str | None, typer.Option(help=option_help("covariance"))] = None,
    solver: Annotated[str | None, typer.Option(help=option_help("covariance_solver"))] = None,
    estimator: Annotated[str | None, typer.Option(help=option_help("covariance_estimator"))] = None,
    covariance_frames: Annotated[
        str | None, typer.Option(help=option_help("covariance_frames", "; comma-separated"))
    ] = None,
    covariance_axes: Annotated[
        str | None, typer.Option(help=option_help("covariance_axes"))
    ] = None,
    noise_std: Annotated[
        str | None, typer.Option(help=option_help("noise_std", "; x,y,z,rx,ry,rz"))
    ] = None,
    noise_covariance: Annotated[
        Path | None,
        typer.Option(help=option_help("noise_covariance", "; a JSON file holding the 6×6 array")),
    ] = None,
    measurement: MeasurementOpt = None,
    point_distance: PointDistanceOpt = None,
    marker: Annotated[int | None, typer.Option(help="FIGAROH files: which marker.")] = None,
    executor: ExecutorOpt = None,
    dask: DaskOpt = None,
    chunk_rows: ChunkRowsOpt = None,
    workers: WorkersOpt = None,
    export_urdf_to: Annotated[
        Path | None, typer.Option("--export-urdf", help="Also write the calibrated URDF.")
    ] = None,
    force_urdf: Annotated[
        bool,
        typer.Option(help="Write --export-urdf even when the calibration's verdict is failed."),
    ] = False,
    report: Annotated[
        Path | None, typer.Option(help="Also write the HTML report (figures embedded).")
    ] = None,
    model: Annotated[
        Path | None,
        typer.Option(
            "--model",
            help="findings.json of 'kincal discover': calibrate the discovered model (its "
            "compliance, flex axes, gravity and payload; its other named terms undone on the "
            "recording at their discovered values and recorded in the result, so that predict "
            "and rank apply them). Replaces --compliant-joints, --rigid, "
            "--virtual-axes, --gravity, --payload-kg and --payload-com.",
        ),
    ] = None,
    show_options: Annotated[
        bool,
        typer.Option(
            help="Print the options the calibration would run with (config file, flags and "
            "--model merged, checked against the robot) as JSON, and stop."
        ),
    ] = False,
) -> None:
    """Calibrate geometry, joint compliance (paper Eq. 8–10) and the covariances of the random
    perturbations (Eq. 13–17) from recorded poses."""
    description = _robot(robot, urdf, base, tip, dh)
    if rigid and compliant_joints is not None:
        raise KincalError("give --rigid or --compliant-joints, not both")
    options = calibration_options(
        None if config is None else read_config(config),
        {
            "compliant_joints": [] if rigid else _names(compliant_joints),
            "virtual_axes_at": _names(virtual_axes),
            "gravity_base_m_s2": None if gravity is None else _vector3(gravity, "--gravity"),
            "payload_kg": payload_kg,
            "payload_com_m": None
            if payload_com is None
            else _vector3(payload_com, "--payload-com"),
            "rotation_weight_m_per_rad": rotation_weight,
            "outlier_rule": outlier_rule,
            "outlier_level": outlier_level,
            "outlier_sigma": outlier_sigma,
            "max_iterations": max_iterations,
            "tolerance": tolerance,
            "rank_tolerance": rank_tolerance,
            "heldout": heldout,
            "seeds": None if seeds is None else _integers(seeds, "--seeds"),
            "train_fraction": train_fraction,
            "covariance": covariance,
            "covariance_solver": solver,
            "covariance_estimator": estimator,
            "covariance_frames": _names(covariance_frames),
            "covariance_axes": covariance_axes,
            "noise_std": None if noise_std is None else numbers(noise_std, "--noise-std", 6),
            "noise_covariance": None
            if noise_covariance is None
            else read_noise_covariance(noise_covariance),
            "measurement": measurement,
            "point_distance_m": point_distance,
            "free_parameters": _names(free),
            "fixed_parameters": _names(fix),
        },
    )
    findings = None
    if model is not None:
        from service.app import discover as discovery

        given = [
            "--rigid" if rigid and name == "compliant_joints" else CALIBRATION_FLAGS[name]
            for name in discovery.model_options_set(options)
        ]
        if given:
            raise KincalError(
                f"--model sets the model; do not also pass {', '.join(given)} "
                "(run kincal discover with them instead)"
            )
        findings = read_findings(model)
    setup = pipeline.check_calibration(description, options, findings)
    if show_options:
        typer.echo(setup.options.model_dump_json(indent=1))
        return
    stream = pipeline.StreamOptions()
    if chunk_rows is not None:
        stream = pipeline.StreamOptions(chunk_rows=chunk_rows)
    chosen = _executor(executor, dask, workers)
    with chosen or contextlib.nullcontext():
        run = pipeline.calibrate_source(data, setup, executor=chosen, stream=stream, marker=marker)
    for note in run.notes:
        typer.echo(f"--model: {note}")
    _write_json(output, run.result.model_dump_json(indent=1))
    if report is not None:
        _write_text(report, run.report_html())
    verdict = run.result.verdict
    failed = verdict is not None and verdict.status == "failed"
    if export_urdf_to is not None and not (failed and not force_urdf):
        _write_text(export_urdf_to, run.urdf())
    typer.echo(summary(run.result))
    typer.echo(f"\n{execution_summary(run)}")
    typer.echo(f"result written to {output}")
    if verdict is not None and verdict.reasons:
        typer.echo(verdict_text(verdict), err=failed)
    if failed:
        unwritten = " no URDF written (--force-urdf writes it);" if export_urdf_to else ""
        typer.echo(
            f"calibration failed: the result is written and marked (verdict);{unwritten} "
            "exit code 3",
            err=True,
        )
        raise typer.Exit(3)


def execution_summary(run: pipeline.CalibrationRun) -> str:
    """Where and how long: "ran on processes (2 worker(s)) in 12.3 s, 8 passes over the data
    (read 2.4 s, ...)"."""
    stages = {k: v for k, v in run.timings.items() if k != "passes"}
    parts = ", ".join(f"{name} {seconds:.2f} s" for name, seconds in stages.items())
    passes = int(run.timings.get("passes", 0))
    return (
        f"ran on {run.execution} in {sum(stages.values()):.2f} s, {passes} passes over the "
        f"data ({parts})"
    )
