"""``kincal fleet``: one calibration per robot serial, compared."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.dataset.paths import check_fleet_folder, check_results_folder
from service.cli.check import EXIT_DRIFTED
from service.cli.common import (
    COVARIANCE,
    EXECUTION,
    HELDOUT,
    MODEL,
    OUTLIERS,
    OUTPUT,
    RECORDING,
    BaseOpt,
    DaskOpt,
    MarkerOpt,
    OutDirOpt,
    Outputs,
    RobotOpt,
    TipOpt,
    UrdfOpt,
    WorkersOpt,
    _executor,
    _names,
    _robot,
    out_dir_for,
    output_option,
    read_result,
    refuse_options_outside,
)
from service.cli.flags import calibration_options, option_help, read_config
from solver.errors import KincalError

if TYPE_CHECKING:
    from schemas.robots import RobotDescription

FleetOut = Annotated[Path | None, output_option("fleet.json", "The fleet summary JSON")]


def fleet(
    ctx: typer.Context,
    directory: Annotated[
        Path,
        typer.Argument(
            help="Folder with one dataset per robot: files (file name = serial) or "
            "ball-in-socket sub-folders (folder name = serial); with --check, one check "
            "recording per unit."
        ),
    ],
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    config: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of calibration options, as for kincal calibrate.",
            rich_help_panel=RECORDING,
        ),
    ] = None,
    compliant_joints: Annotated[
        str | None,
        typer.Option(
            help=option_help("compliant_joints", "; comma-separated"), rich_help_panel=MODEL
        ),
    ] = None,
    rigid: Annotated[
        bool,
        typer.Option(
            help="No joint compliance at all (compliant_joints = []).", rich_help_panel=MODEL
        ),
    ] = False,
    outlier_rule: Annotated[
        str | None, typer.Option(help=option_help("outlier_rule"), rich_help_panel=OUTLIERS)
    ] = None,
    outlier_sigma: Annotated[
        float | None, typer.Option(help=option_help("outlier_sigma"), rich_help_panel=OUTLIERS)
    ] = None,
    covariance: Annotated[
        str | None, typer.Option(help=option_help("covariance"), rich_help_panel=COVARIANCE)
    ] = None,
    estimator: Annotated[
        str | None,
        typer.Option(help=option_help("covariance_estimator"), rich_help_panel=COVARIANCE),
    ] = None,
    heldout: Annotated[
        bool | None,
        typer.Option(
            "--heldout/--no-heldout",
            help="Held-out splits per robot (slower) [default: off for fleets].",
            rich_help_panel=HELDOUT,
        ),
    ] = None,
    z_threshold: Annotated[
        float,
        typer.Option(
            min=0.0,
            help="Robust z-score beyond which a robot is an outlier (at least the family-wise "
            "level of the fleet's size).",
            rich_help_panel=OUTLIERS,
        ),
    ] = 3.5,
    marker: MarkerOpt = None,
    executor: Annotated[
        str | None,
        typer.Option(
            help="Run robots inprocess (default), on local processes or on dask.",
            metavar="inprocess|processes|dask",
            rich_help_panel=EXECUTION,
        ),
    ] = None,
    dask: DaskOpt = None,
    workers: WorkersOpt = None,
    output: FleetOut = None,
    out_dir: OutDirOpt = None,
    results_dir: Annotated[
        Path | None,
        typer.Option(
            help="Also write each robot's result JSON (<serial>.json) in this folder.",
            rich_help_panel=OUTPUT,
        ),
    ] = None,
    check: Annotated[
        Path | None,
        typer.Option(
            "--check",
            metavar="RESULTS_DIR",
            help="Check mode: each unit's check recording in DIRECTORY against its "
            "calibration result <unit>.json in this folder, as kincal check (exit 3 if any "
            "drifted).",
        ),
    ] = None,
    level: Annotated[
        float,
        typer.Option(
            help="With --check: each unit's family-wise probability of a false alarm when it holds."
        ),
    ] = 0.05,
) -> None:
    """Calibrate every robot of a fleet (one dataset per serial) in parallel; summarise the
    population spread of each parameter and flag robots that are outliers (e.g. a worn
    joint). With ``--check RESULTS_DIR``: check every unit's calibration instead
    (docs/check.md)."""
    check_fleet_folder(directory)  # a folder that is not there is refused before the imports
    if check is not None:
        check_results_folder(check)
    from service.app import fleet as fleet_mode

    if check is not None:
        refuse_options_outside(
            ctx,
            {"directory", "check", "level", "output", "out_dir"},
            "--check checks each unit against its result; these belong to calibrating a fleet",
        )
        fleet_check(directory, check, level, output, out_dir)
        return
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
    outputs = Outputs(out_dir_for(out_dir, None, f"{directory.resolve().name}_fleet"))
    path = outputs.path(output, "fleet.json", fleet_mode.FLEET_FORMAT)
    datasets = fleet_mode.fleet_datasets(directory)
    preflight_fleet(datasets, description, options, marker)
    chosen = _executor(executor, dask, workers)
    with chosen or contextlib.nullcontext():
        report, outcomes = fleet_mode.calibrate_fleet(
            datasets, description, options, chosen, marker=marker, z_threshold=z_threshold
        )
    outputs.write_text(path, f"fleet summary of {len(outcomes)} robots", report.to_json() + "\n")
    if results_dir is not None:
        for outcome in outcomes:
            if outcome.result is not None:
                outputs.write_text(
                    outputs.path(
                        results_dir / f"{outcome.serial}.json", "", "kincal.calibration/1"
                    ),
                    f"calibration result of {outcome.serial}",
                    outcome.result.model_dump_json(indent=1) + "\n",
                )
    typer.echo(fleet_mode.fleet_table(report))
    typer.echo(outputs.listing())
    typer.echo(fleet_mode.fleet_verdict_line(report))


def fleet_check(
    checks_dir: Path,
    results_dir: Path,
    level: float,
    output: Path | None,
    out_dir: Path | None,
) -> None:
    """``kincal fleet CHECKS_DIR --check RESULTS_DIR``: one line per unit, the fleet summary,
    the JSON of every check; exit 3 if any unit drifted."""
    from schemas.check import FLEET_CHECK_FORMAT
    from service.app import fleet_check as checks

    if not 0.0 < level < 1.0:
        raise KincalError(f"--level {level}: give a probability between 0 and 1, e.g. 0.05")
    outputs = Outputs(out_dir_for(out_dir, None, f"{checks_dir.resolve().name}_fleet"))
    path = outputs.path(output, "fleet_check.json", FLEET_CHECK_FORMAT)
    pairs = checks.fleet_check_pairs(checks_dir, results_dir, read_result)
    report = checks.run_fleet_check(pairs, level=level)
    outputs.write_text(
        path, f"checks of {len(report.units)} units", report.model_dump_json(indent=1) + "\n"
    )
    typer.echo(checks.fleet_check_table(report))
    typer.echo(outputs.listing())
    typer.echo(checks.fleet_check_verdict_line(report))
    if report.drifted:
        raise typer.Exit(EXIT_DRIFTED)


def preflight_fleet(
    datasets: object, description: RobotDescription, options: object, marker: int | None
) -> None:
    """Every robot's recording through the pre-flight checks before any robot is fitted: a
    fleet refused halfway would have wasted the robots before it."""
    from schemas.calibration import CalibrationOptions
    from service.app.preflight import check_recording
    from service.render.chain import chain_for
    from solver.errors import DatasetError

    assert isinstance(options, CalibrationOptions)
    chain = chain_for(description, options)
    assert isinstance(datasets, dict)
    for serial, source in datasets.items():
        try:
            check_recording(source, chain, options, marker=marker)
        except DatasetError as exc:
            raise DatasetError(f"robot {serial}: {exc}") from exc


# --- designs (issue 16) ----------------------------------------------------------------------
