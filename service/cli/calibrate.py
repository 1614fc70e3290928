"""``kincal simulate`` and ``kincal calibrate``: a recording in, a calibration result out.

Heavy modules (the calibration pipeline, pandas, Pinocchio) are imported inside the commands:
``kincal calibrate --help`` answers without them, and a recording the pre-flight checks refuse
(:mod:`service.app.preflight`) is refused before the pipeline is loaded."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.dataset.paths import check_recording_path
from service.cli.common import (
    CLOCK_TOLERANCE_S,
    COVARIANCE,
    HELDOUT,
    MODEL,
    OUTLIERS,
    OUTPUT,
    RECORDING,
    STILL_TOLERANCE_RAD_S,
    STILL_WINDOW_S,
    BaseOpt,
    CaptureOpt,
    ChunkRowsOpt,
    ClockToleranceOpt,
    DaskOpt,
    DataOrBagArg,
    DhOpt,
    ExecutorOpt,
    JointStatesOpt,
    MarkerOpt,
    MeasurementOpt,
    MeasureOpt,
    OutDirOpt,
    Outputs,
    PointDistanceOpt,
    ReportOpt,
    RobotOpt,
    StillToleranceOpt,
    StillWindowOpt,
    TipOpt,
    UrdfOpt,
    WorkersOpt,
    _executor,
    _integers,
    _names,
    _robot,
    _vector3,
    out_dir_for,
    output_option,
    read_bag,
    read_findings,
    read_noise_covariance,
    robot_for,
)
from service.cli.flags import (
    CALIBRATION_FLAGS,
    calibration_options,
    numbers,
    option_choices,
    option_help,
    read_config,
)
from service.cli.generated_help import DEFAULT_EFFECTS, SIMULATE_EFFECTS
from solver.errors import KincalError

if TYPE_CHECKING:
    from schemas.dataset import PoseDataset
    from service.app.calibrate import CalibrationRun

RESULT_KIND = "kincal.calibration/1"


def simulate(
    output: Annotated[
        Path,
        typer.Option(
            "-o",
            "--output",
            help="The recording to write (.csv, .parquet or .json).",
            rich_help_panel=OUTPUT,
        ),
    ],
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
            + "; ".join(f"{k}: {v}" for k, v in SIMULATE_EFFECTS.items())
            + f". [default: {', '.join(DEFAULT_EFFECTS)}]",
        ),
    ] = None,
    noise_mm: Annotated[float, typer.Option(min=0.0, help="Measurement noise σ, mm.")] = 0.05,
    noise_deg: Annotated[float, typer.Option(min=0.0, help="Measurement noise σ, deg.")] = 0.003,
    rotation: Annotated[
        bool,
        typer.Option(
            help="Write the orientation columns (qx, qy, qz, qw); --no-rotation writes a "
            "position-only recording."
        ),
    ] = True,
    truth: Annotated[Path | None, typer.Option(help="Also write the ground truth JSON.")] = None,
) -> None:
    """Simulate a recording with known ground truth and write it in the dataset contract."""
    from schemas.dataset import write_dataset
    from service.app import simulate as scenarios

    description = _robot(robot if urdf is None else None, urdf, base, tip)
    scn, recording = scenarios.simulate(
        description,
        n_samples=n,
        seed=seed,
        effects=effect or scenarios.DEFAULT_EFFECTS,
        noise_translation_mm=noise_mm,
        noise_rotation_deg=noise_deg,
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=rotation)
    outputs = Outputs(output.parent)
    outputs.write(
        outputs.path(output, output.name, "a recording"),
        f"recording, {n} samples ({', '.join(scn.effects)})",
        lambda path: write_dataset(dataset, path),
    )
    if truth is not None:
        document = json.dumps(scenarios.truth_document(scn, recording, description), indent=1)
        outputs.write_text(outputs.path(truth, truth.name, None), "ground truth", document + "\n")
    typer.echo(outputs.listing())


def _calibration_flag(
    field: str, extra: str = "", panel: str = MODEL, *decls: str
) -> typer.models.OptionInfo:
    """A flag of a calibration option: its help (description, config key, default) and, for a
    choice, its values."""
    choices = option_choices(field)
    return typer.Option(
        *decls,
        help=option_help(field, extra),
        rich_help_panel=panel,
        metavar=None if choices is None else "|".join(choices),
        show_default=False,
    )


ResultOut = Annotated[Path | None, output_option("calibration.json", "The result JSON")]


def calibrate(
    data: DataOrBagArg,
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    dh: DhOpt = None,
    config: Annotated[
        Path | None,
        typer.Option(
            help="TOML file of calibration options (the config keys named below); flags given "
            "as well override it.",
            rich_help_panel=RECORDING,
        ),
    ] = None,
    joint_states: JointStatesOpt = None,
    measure: MeasureOpt = None,
    capture: CaptureOpt = None,
    still_tolerance: StillToleranceOpt = STILL_TOLERANCE_RAD_S,
    still_window: StillWindowOpt = STILL_WINDOW_S,
    clock_tolerance: ClockToleranceOpt = CLOCK_TOLERANCE_S,
    compliant_joints: Annotated[
        str | None, _calibration_flag("compliant_joints", "; comma-separated")
    ] = None,
    rigid: Annotated[
        bool,
        typer.Option(
            help="No joint compliance at all (compliant_joints = []).", rich_help_panel=MODEL
        ),
    ] = False,
    free: Annotated[str | None, _calibration_flag("free_parameters", "; comma-separated")] = None,
    fix: Annotated[str | None, _calibration_flag("fixed_parameters", "; comma-separated")] = None,
    virtual_axes: Annotated[
        str | None, _calibration_flag("virtual_axes_at", "; comma-separated")
    ] = None,
    gravity: Annotated[str | None, _calibration_flag("gravity_base_m_s2")] = None,
    payload_kg: Annotated[float | None, _calibration_flag("payload_kg")] = None,
    payload_com: Annotated[str | None, _calibration_flag("payload_com_m")] = None,
    model: Annotated[
        Path | None,
        typer.Option(
            "--model",
            help="findings.json of 'kincal discover': calibrate the discovered model (its "
            "compliance, flex axes, gravity and payload; its other named terms undone on the "
            "recording at their discovered values and recorded in the result, so that predict "
            "and rank apply them). Replaces --compliant-joints, --rigid, "
            "--virtual-axes, --gravity, --payload-kg and --payload-com.",
            rich_help_panel=MODEL,
        ),
    ] = None,
    rotation_weight: Annotated[float | None, _calibration_flag("rotation_weight_m_per_rad")] = None,
    max_iterations: Annotated[int | None, _calibration_flag("max_iterations")] = None,
    tolerance: Annotated[float | None, _calibration_flag("tolerance")] = None,
    rank_tolerance: Annotated[float | None, _calibration_flag("rank_tolerance")] = None,
    measurement: MeasurementOpt = None,
    point_distance: PointDistanceOpt = None,
    marker: MarkerOpt = None,
    outlier_rule: Annotated[str | None, _calibration_flag("outlier_rule", "", OUTLIERS)] = None,
    outlier_level: Annotated[float | None, _calibration_flag("outlier_level", "", OUTLIERS)] = None,
    outlier_sigma: Annotated[
        float | None, _calibration_flag("outlier_sigma", "; 0 disables", OUTLIERS)
    ] = None,
    covariance: Annotated[str | None, _calibration_flag("covariance", "", COVARIANCE)] = None,
    solver: Annotated[str | None, _calibration_flag("covariance_solver", "", COVARIANCE)] = None,
    estimator: Annotated[
        str | None, _calibration_flag("covariance_estimator", "", COVARIANCE)
    ] = None,
    covariance_frames: Annotated[
        str | None, _calibration_flag("covariance_frames", "; comma-separated", COVARIANCE)
    ] = None,
    covariance_axes: Annotated[
        str | None, _calibration_flag("covariance_axes", "", COVARIANCE)
    ] = None,
    noise_std: Annotated[
        str | None, _calibration_flag("noise_std", "; x,y,z,rx,ry,rz", COVARIANCE)
    ] = None,
    noise_covariance: Annotated[
        Path | None,
        _calibration_flag("noise_covariance", "; a JSON file holding the 6×6 array", COVARIANCE),
    ] = None,
    heldout: Annotated[
        bool | None,
        _calibration_flag("heldout", "", HELDOUT, "--heldout/--no-heldout"),
    ] = None,
    heldout_method: Annotated[str | None, _calibration_flag("heldout_method", "", HELDOUT)] = None,
    seeds: Annotated[str | None, _calibration_flag("seeds", "; comma-separated", HELDOUT)] = None,
    train_fraction: Annotated[
        float | None, _calibration_flag("train_fraction", "", HELDOUT)
    ] = None,
    executor: ExecutorOpt = None,
    dask: DaskOpt = None,
    chunk_rows: ChunkRowsOpt = None,
    workers: WorkersOpt = None,
    output: ResultOut = None,
    out_dir: OutDirOpt = None,
    export_urdf_to: Annotated[
        Path | None,
        typer.Option(
            "--export-urdf",
            help="Also write the calibrated URDF (a file name; not when the verdict is failed).",
            rich_help_panel=OUTPUT,
        ),
    ] = None,
    force_urdf: Annotated[
        bool,
        typer.Option(
            help="Write --export-urdf even when the calibration's verdict is failed.",
            rich_help_panel=OUTPUT,
        ),
    ] = False,
    report: ReportOpt = None,
    show_options: Annotated[
        bool,
        typer.Option(
            help="Print the options the calibration would run with (config file, flags and "
            "--model merged, checked against the robot) as JSON, and stop.",
            rich_help_panel=OUTPUT,
        ),
    ] = False,
) -> None:
    """Calibrate geometry, joint compliance (paper Eq. 8–10) and the covariances of the random
    perturbations (Eq. 13–17) from recorded poses.

    Checks the recording first (units, joint limits, constant joints, repeated rows, enough
    rows: exit code 2 with the fix), then writes the result JSON (and the files asked for) to
    -o/--out-dir, lists every file written and ends with the verdict: exit code 0 when it is ok
    or a warning, 3 when it failed."""
    check_recording_path(data)
    description = robot_for(data, robot, urdf, base, tip, dh, to_stderr=show_options)
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
            "heldout_method": heldout_method,
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
        from service.app import discover_carry

        given = [
            "--rigid" if rigid and name == "compliant_joints" else CALIBRATION_FLAGS[name]
            for name in discover_carry.model_options_set(options)
        ]
        if given:
            raise KincalError(
                f"--model sets the model; do not also pass {', '.join(given)} "
                "(run kincal discover with them instead)"
            )
        findings = read_findings(model)
    outputs = Outputs(out_dir_for(out_dir, data, "calibration"))
    result_path = outputs.path(output, "calibration.json", RESULT_KIND)
    report_path = None if report is None else outputs.path(report, "report.html", None)
    urdf_path = None if export_urdf_to is None else outputs.path(export_urdf_to, "", None)
    source: Path | PoseDataset = data
    if not show_options:
        bag = (joint_states, measure, (still_tolerance, still_window, clock_tolerance), capture)
        source = bag_source(data, description, options, *bag)
        try:
            preflight(source, description, options, marker)
        except KincalError:
            if _robot_may_refuse(options, findings):
                from service.app import calibrate as pipeline

                # an option the robot refuses (a sensor joint, pose components) explains a
                # recording read the wrong way: name it first
                pipeline.check_calibration(description, options, findings)
            raise
    from service.app import calibrate as pipeline

    setup = pipeline.check_calibration(description, options, findings)
    if show_options:
        typer.echo(setup.options.model_dump_json(indent=1))
        return
    stream = pipeline.StreamOptions()
    if chunk_rows is not None:
        stream = pipeline.StreamOptions(chunk_rows=chunk_rows)
    chosen = _executor(executor, dask, workers)
    with chosen or contextlib.nullcontext():
        run = pipeline.calibrate_source(
            source,
            setup,
            executor=chosen,
            stream=stream,
            marker=marker,
            name=None if source is data else data.name,
        )
    for note in run.notes:
        typer.echo(f"--model: {note}")
    outputs.write_text(
        result_path, "calibration result", run.result.model_dump_json(indent=1) + "\n"
    )
    if report_path is not None:
        outputs.write_text(report_path, "HTML report", run.report_html())
    finish(run, outputs, urdf_path, force_urdf)


def _robot_may_refuse(options: object, findings: object) -> bool:
    """Whether ``options`` set anything that only the calibration's own checks
    (``check_calibration``: covariance frames, a measurement's sensor joint or pose components, a
    carried discovery) can refuse; with the defaults the pre-flight error stands alone and the
    pipeline (~1.4 s of imports) is not loaded to say so."""
    from schemas.calibration import CalibrationOptions

    assert isinstance(options, CalibrationOptions)
    return (
        findings is not None
        or options.covariance_frames is not None
        or options.measurement not in ("auto", "pose", "position")
    )


def bag_source(
    data: Path,
    description: object,
    options: object,
    joint_states: str | None,
    measure: str | None,
    still: tuple[float, float, float],
    capture: str | None,
) -> Path | PoseDataset:
    """``data`` itself, or the recording a ROS bag holds (its synchronisation report printed);
    the bag options without a bag are refused."""
    from schemas.dataset.paths import is_bag

    if not is_bag(data):
        if joint_states is not None or measure is not None or capture is not None:
            raise KincalError(
                f"--joint-states, --measure and --capture read a ROS bag; {data.name} is not one "
                "(a .bag file or a rosbag2 folder)"
            )
        return data
    from schemas.calibration import CalibrationOptions
    from schemas.robots import RobotDescription
    from service.render.chain import chain_for

    assert isinstance(description, RobotDescription) and isinstance(options, CalibrationOptions)
    chain = chain_for(description, options)
    recording = read_bag(data, joint_states, measure, still, chain, capture)
    typer.echo(recording.report())
    return recording.dataset


def preflight(
    data: Path | PoseDataset, description: object, options: object, marker: int | None
) -> None:
    """The pre-flight checks of :mod:`service.app.preflight` on ``data`` for the robot, before
    the calibration pipeline is imported."""
    from schemas.calibration import CalibrationOptions
    from schemas.robots import RobotDescription
    from service.app.preflight import check_recording
    from service.render.chain import chain_for

    assert isinstance(description, RobotDescription) and isinstance(options, CalibrationOptions)
    check_recording(data, chain_for(description, options), options, marker=marker)


def finish(run: CalibrationRun, outputs: Outputs, urdf_path: Path | None, force_urdf: bool) -> None:
    """The summary, the URDF when asked and allowed, the files written and the one-line
    verdict; exit code 3 when the verdict is failed."""
    from service.render.text import summary, verdict_line, verdict_text

    verdict = run.result.verdict
    failed = verdict is not None and verdict.status == "failed"
    if urdf_path is not None and not (failed and not force_urdf):
        outputs.write_text(urdf_path, "calibrated URDF", run.urdf())
    typer.echo(summary(run.result))
    typer.echo(f"\n{execution_summary(run)}")
    if verdict is not None and verdict.reasons:
        typer.echo(verdict_text(verdict), err=failed)
    typer.echo(outputs.listing())
    if urdf_path is not None and failed and not force_urdf:
        typer.echo(f"not written: {urdf_path} (the verdict is failed; --force-urdf writes it)")
    typer.echo(verdict_line(verdict), err=failed)
    if failed:
        raise typer.Exit(3)


def execution_summary(run: CalibrationRun) -> str:
    """Where and how long: "ran on processes (2 worker(s)) in 12.3 s, 8 passes over the data
    (read 2.4 s, ...)"."""
    stages = {k: v for k, v in run.timings.items() if k != "passes"}
    parts = ", ".join(f"{name} {seconds:.2f} s" for name, seconds in stages.items())
    passes = int(run.timings.get("passes", 0))
    return (
        f"ran on {run.execution} in {sum(stages.values()):.2f} s, {passes} passes over the "
        f"data ({parts})"
    )
