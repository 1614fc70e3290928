"""``kincal fleet``: one calibration per robot serial, compared."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from service.cli.flags import calibration_options, option_help, read_config
from solver.errors import KincalError

if TYPE_CHECKING:
    pass
from service.cli.common import (
    BaseOpt,
    DaskOpt,
    OutputOpt,
    RobotOpt,
    TipOpt,
    UrdfOpt,
    WorkersOpt,
    _executor,
    _names,
    _robot,
    _write_json,
)


def fleet(
    directory: Annotated[
        Path,
        typer.Argument(
            help="Folder with one dataset per robot: files (file name = serial) or "
            "ball-in-socket sub-folders (folder name = serial)."
        ),
    ],
    output: OutputOpt,
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML file of calibration options, as for kincal calibrate."),
    ] = None,
    compliant_joints: Annotated[
        str | None, typer.Option(help=option_help("compliant_joints", "; comma-separated"))
    ] = None,
    rigid: Annotated[
        bool, typer.Option(help="No joint compliance at all (compliant_joints = []).")
    ] = False,
    outlier_rule: Annotated[str | None, typer.Option(help=option_help("outlier_rule"))] = None,
    outlier_sigma: Annotated[float | None, typer.Option(help=option_help("outlier_sigma"))] = None,
    covariance: Annotated[str | None, typer.Option(help=option_help("covariance"))] = None,
    estimator: Annotated[str | None, typer.Option(help=option_help("covariance_estimator"))] = None,
    heldout: Annotated[
        bool | None,
        typer.Option(
            "--heldout/--no-heldout", help="Held-out splits per robot (slower; off for fleets)."
        ),
    ] = None,
    z_threshold: Annotated[
        float, typer.Option(min=0.0, help="Robust z-score beyond which a robot is an outlier.")
    ] = 3.5,
    results_dir: Annotated[
        Path | None, typer.Option(help="Also write each robot's result JSON here.")
    ] = None,
    marker: Annotated[int | None, typer.Option(help="FIGAROH files: which marker.")] = None,
    executor: Annotated[
        str | None,
        typer.Option(help="Run robots inprocess (default), on local processes or on dask."),
    ] = None,
    dask: DaskOpt = None,
    workers: WorkersOpt = None,
) -> None:
    """Calibrate every robot of a fleet (one dataset per serial) in parallel; summarise the
    population spread of each parameter and flag robots that are outliers (e.g. a worn
    joint)."""
    from service.app import fleet as fleet_mode

    description = _robot(robot, urdf, base, tip)
    if rigid and compliant_joints is not None:
        raise KincalError("give --rigid or --compliant-joints, not both")
    options = calibration_options(
        None if config is None else read_config(config),
        {
            "compliant_joints": [] if rigid else _names(compliant_joints),
            "outlier_rule": outlier_rule,
            "outlier_sigma": outlier_sigma,
            "heldout": heldout,
            "covariance": covariance,
            "covariance_estimator": estimator,
        },
        defaults={"heldout": False},
    )
    datasets = fleet_mode.fleet_datasets(directory)
    chosen = _executor(executor, dask, workers)
    with chosen or contextlib.nullcontext():
        report, outcomes = fleet_mode.calibrate_fleet(
            datasets, description, options, chosen, marker=marker, z_threshold=z_threshold
        )
    _write_json(output, report.to_json())
    if results_dir is not None:
        for outcome in outcomes:
            if outcome.result is not None:
                _write_json(
                    results_dir / f"{outcome.serial}.json",
                    outcome.result.model_dump_json(indent=1),
                )
    typer.echo(fleet_mode.fleet_table(report))
    typer.echo(f"\nfleet summary written to {output}")


# --- designs (issue 16) ----------------------------------------------------------------------
