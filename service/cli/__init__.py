"""``kincal`` command line (DESIGN.md §3). Every bad input ends in one line and exit code 2."""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import sys
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import pandas as pd
import pydantic
import typer

from schemas.calibration import CalibrationResult
from schemas.dataset import read_configurations, write_dataset
from schemas.design import DesignOptions, DesignResult
from schemas.robots import BUILTIN_ROBOTS, RobotDescription, load_robot
from service.app import calibrate as pipeline
from service.app import simulate as scenarios
from service.cli.flags import (
    CALIBRATION_FLAGS,
    calibration_options,
    numbers,
    option_help,
    ranking_options_from_flags,
    read_config,
    target_request,
)
from service.render import result_json
from service.render.text import ranking_summary, summary, verdict_text
from solver import lie
from solver.errors import KincalError
from solver.executors import Executor

if TYPE_CHECKING:
    from schemas.discovery import FindingsResult

DocumentT = TypeVar("DocumentT", bound=pydantic.BaseModel)

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    help="Calibrate robot kinematics, including the randomness inside the chain.",
)

RobotOpt = Annotated[
    str | None, typer.Option("--robot", help=f"Built-in robot: {', '.join(BUILTIN_ROBOTS)}.")
]
UrdfOpt = Annotated[Path | None, typer.Option("--urdf", help="A URDF file instead of --robot.")]
BaseOpt = Annotated[str | None, typer.Option("--base", help="Base frame (with --urdf).")]
TipOpt = Annotated[str | None, typer.Option("--tip", help="Tip frame (with --urdf).")]
DhOpt = Annotated[
    Path | None,
    typer.Option(
        "--dh",
        help="A DH or modified-DH table (YAML, docs/dh.md) instead of --robot/--urdf, for "
        "devices without a URDF.",
    ),
]
OutputOpt = Annotated[Path, typer.Option("-o", "--output", help="Output file.")]
MeasurementOpt = Annotated[str | None, typer.Option(help=option_help("measurement"))]
PointDistanceOpt = Annotated[float | None, typer.Option(help=option_help("point_distance_m"))]
ExecutorOpt = Annotated[
    str | None,
    typer.Option(
        help="Where the passes over the data run: inprocess, processes (local, one per core) "
        "or dask. Default: local processes for a file of more than one chunk on a machine with "
        "several cores, else in this process. The numbers do not depend on it."
    ),
]
DaskOpt = Annotated[
    str | None,
    typer.Option(
        "--dask",
        help="Dask scheduler address (tcp://host:8786), implies --executor dask; without it "
        "--executor dask uses KINCAL_DASK_ADDRESS or starts a local cluster.",
    ),
]
ChunkRowsOpt = Annotated[
    int | None, typer.Option(min=1, help="Rows per streamed chunk [65536; Parquet: row groups].")
]
WorkersOpt = Annotated[
    int | None, typer.Option(min=1, help="Processes for --executor processes/local dask [cores].")
]


def _robot(
    robot: str | None,
    urdf: Path | None,
    base: str | None,
    tip: str | None,
    dh: Path | None = None,
) -> RobotDescription:
    return load_robot(robot, urdf_path=urdf, base_frame=base, tip_frame=tip, dh_path=dh)


def _names(text: str | None) -> list[str] | None:
    return None if text is None else [n.strip() for n in text.split(",") if n.strip()]


def _vector3(text: str, option: str) -> tuple[float, float, float]:
    x, y, z = numbers(text, option, 3)
    return x, y, z


def _write_json(path: Path, document: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(document + "\n", encoding="utf-8")
    tmp.replace(path)


def _read_document(path: Path, model: type[DocumentT], what: str, producer: str) -> DocumentT:
    """A JSON document of ``model`` from ``path`` (what: "calibration result"; producer: the
    command that writes it), with a one-line error naming the first bad field otherwise."""
    try:
        return model.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise KincalError(f"cannot read {what} {path}: {exc.strerror}") from exc
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise KincalError(
            f"{path} is not a kincal {what} ({where}: {first['msg']}); "
            f"pass the -o file of 'kincal {producer}'"
        ) from exc


def read_result(path: Path) -> CalibrationResult:
    """Load a result JSON written by ``kincal calibrate``, with a one-line error otherwise."""
    return _read_document(path, CalibrationResult, "calibration result", "calibrate")


def read_noise_covariance(path: Path) -> object:
    """The JSON of ``--noise-covariance`` (checked by :class:`CalibrationOptions`), with a
    one-line error if it cannot be read."""
    try:
        return json.loads(path.read_bytes())
    except OSError as exc:
        raise KincalError(f"cannot read noise covariance {path}: {exc.strerror}") from exc
    except ValueError as exc:
        raise KincalError(
            f"{path} is not JSON ({exc}); --noise-covariance takes a 6×6 JSON array"
        ) from exc


def read_findings(path: Path) -> FindingsResult:
    """Load a findings JSON written by ``kincal discover``, with a one-line error otherwise."""
    from schemas.discovery import FindingsResult

    return _read_document(path, FindingsResult, "findings file", "discover")


@app.command()
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


@app.command()
def calibrate(
    data: Annotated[
        Path,
        typer.Argument(
            help="Dataset: CSV, Parquet, JSON or industrial_calibration YAML; or a folder of "
            "ball-in-socket hole_<k>.csv files."
        ),
    ],
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


def _integers(text: str, option: str) -> list[int]:
    values = numbers(text, option)
    if not all(v == int(v) for v in values):
        raise KincalError(f"{option} takes comma-separated integers, got {text!r}")
    return [int(v) for v in values]


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")


def _prediction_note(result: CalibrationResult) -> None:
    """Say once (stderr) which carried corrections a prediction cannot apply."""
    if result.model_corrections is None:
        return
    from service.render.corrections import prediction_note

    note = prediction_note(result)
    if note is not None:
        typer.echo(note, err=True)


@app.command("dh-urdf")
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


@app.command("export")
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


@app.command()
def predict(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result JSON.")],
    configs: Annotated[Path, typer.Argument(help="Configurations: joint columns (+ payload_kg).")],
    output: OutputOpt,
    noise: Annotated[
        bool,
        typer.Option(
            "--noise/--no-noise",
            help="Include the measurement noise Σ_n in the predicted covariance.",
        ),
    ] = True,
    part: Annotated[
        str,
        typer.Option(
            help="Which covariance the cov_ columns hold: total (Σ_E + Σ_n + parameter "
            "estimation + model error), random-effects (Σ_E of Eq. 12 + Σ_n), noise (Σ_n), "
            "parameters (J_θ Cov(θ̂) J_θᵀ) or model-error."
        ),
    ] = "total",
) -> None:
    """Predicted marker pose (x,y,z,qx,qy,qz,qw; measurement frame) per configuration and,
    when the result has covariances, the predicted 6×6 EE covariance (cov_00..cov_55, row-major,
    EE frame, [v; w], m and rad): by default the total, Σ_E (Eq. 12) + Σ_n + the
    parameter-estimation part + the model-error part (docs/predictive.md)."""
    result = read_result(result_path)
    _prediction_note(result)
    chain, _ = result_json.result_chain(result)
    configurations = read_configurations(
        configs, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    pose = result_json.predict_poses(
        result, configurations.joint_positions, configurations.payload_kg
    )
    frame = pd.DataFrame(pose[:, :3, 3], columns=["x", "y", "z"])
    frame[["qx", "qy", "qz", "qw"]] = lie.matrix_to_quaternion_xyzw(pose[:, :3, :3])
    chosen = part.replace("-", "_")
    if result.covariance is not None:
        from service.app import rank as ranking  # lazy: pulls in scikit-learn

        if chosen not in ranking.PREDICTION_PARTS:
            raise KincalError(
                f"--part {part!r}: choose one of "
                + ", ".join(p.replace("_", "-") for p in ranking.PREDICTION_PARTS)
            )
        if result.predictive is None and chosen in ("total", "parameters", "model_error"):
            typer.echo(
                f"note: {result_path} {ranking.no_predictive(result)}; its parameter and "
                "model-error parts are left out (zero)",
                err=True,
            )
        not_applicable = ranking.not_applicable_note(result)
        if not_applicable is not None and chosen in ("total", "model_error"):
            typer.echo(f"note: {not_applicable}", err=True)
        covariance = ranking.predicted_covariance(
            result,
            configurations.joint_positions,
            configurations.payload_kg,
            part=chosen,
            include_noise=noise,
        )
        names = [f"cov_{i}{j}" for i in range(6) for j in range(6)]
        frame[names] = covariance.reshape(len(frame), 36)
    if configurations.sample_id is not None:
        frame.insert(0, "sample_id", configurations.sample_id)
    output.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(output, index=False, float_format="%.17g")
    extra = " with covariances" if result.covariance is not None else ""
    typer.echo(f"wrote {len(frame)} predicted poses{extra} to {output}")


@app.command()
def rank(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result with covariance.")],
    output: OutputOpt,
    configs: Annotated[
        Path | None,
        typer.Argument(metavar="CONFIGS", help="Configurations: joint columns (+ payload_kg)."),
    ] = None,
    weights: Annotated[
        str | None, typer.Option(help="W diagonal for vx,vy,vz,wx,wy,wz [0.4,0.4,0,0.1,0.1,0].")
    ] = None,
    weight_matrix: Annotated[
        Path | None, typer.Option(help="Full 6×6 W: JSON, or 6 rows of 6 numbers.")
    ] = None,
    rotation_scale: Annotated[float, typer.Option(help="Metres that 1 rad counts as.")] = 1.0,
    task_point: Annotated[
        str | None, typer.Option(help="Score the position of this EE-frame point x,y,z (m).")
    ] = None,
    task_weights: Annotated[str | None, typer.Option(help="Task point weights wx,wy,wz.")] = None,
    include_noise: Annotated[bool, typer.Option(help="Add the measurement noise Σ_n.")] = False,
    target: Annotated[
        str | None,
        typer.Option(
            help="Rank IK candidates for the pose x,y,z,qx,qy,qz,qw instead, in the "
            "measurement frame (the frame of the recording and of kincal predict); write "
            "--target=-0.2,... when it starts with a minus sign."
        ),
    ] = None,
    n_candidates: Annotated[int, typer.Option(help="IK candidates wanted.")] = 16,
    seed: Annotated[int, typer.Option(help="IK random seed.")] = 0,
    free_axis: Annotated[str, typer.Option(help="IK: auto, x, y, z or none.")] = "auto",
    payload_kg: Annotated[float | None, typer.Option(help="Payload (default: result's).")] = None,
    top: Annotated[int | None, typer.Option(help="Keep only the best N entries.")] = None,
    uncertainty: Annotated[
        str,
        typer.Option(
            help="Covariance scored: random-effects (Σ_E of Eq. 12, the paper's score) or "
            "total (+ parameter-estimation and model-error parts)."
        ),
    ] = "random-effects",
) -> None:
    """Rank configurations by predicted task uncertainty tr(W Σ_E Wᵀ), best first (Eq. 22–23)."""
    from service.app import rank as ranking

    result = read_result(result_path)
    if result.covariance is None:
        raise KincalError(f"{result_path} {ranking.NO_COVARIANCE}")
    if (configs is None) == (target is None):
        raise KincalError("give exactly one of CONFIGS (a configurations file) and --target")
    options = ranking_options_from_flags(
        weights=weights,
        weight_matrix=weight_matrix,
        rotation_scale_m_per_rad=rotation_scale,
        task_point=task_point,
        task_weights=task_weights,
        include_noise=include_noise,
        top=top,
        uncertainty=uncertainty,
    )
    _prediction_note(result)
    model = ranking.uncertainty_model(result)
    if configs is not None:
        chain = model.chain
        configurations = read_configurations(
            configs, chain.joint_names, other_joint_names=chain.other_joint_names
        )
        payload = configurations.payload_kg if payload_kg is None else payload_kg
        out = ranking.rank_configurations(
            result, configurations.joint_positions, options, payload_kg=payload, model=model
        )
    else:
        request = target_request(
            target or "",
            options,
            n_candidates=n_candidates,
            seed=seed,
            free_axis=free_axis,
            payload_kg=result.options.payload_kg if payload_kg is None else payload_kg,
        )
        out = ranking.rank_target(result, request, model=model)
        if not out.ranking:
            raise KincalError(ranking.NO_IK_SOLUTION)
    _write_json(output, out.model_dump_json(indent=1))
    typer.echo(ranking_summary(out))


@app.command()
def discover(
    data: Annotated[
        Path,
        typer.Argument(
            help="Dataset: CSV, Parquet, JSON or industrial_calibration YAML; or a folder of "
            "ball-in-socket hole_<k>.csv files."
        ),
    ],
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


@app.command()
def demo(
    output_dir: Annotated[Path, typer.Option(help="Where the demo writes its files.")] = Path(
        "out/demo"
    ),
) -> None:
    """Simulate a Jaco2 recording like the paper's, calibrate it, print Table II."""
    from service.cli.demo import run_demo

    run_demo(output_dir, echo=typer.echo)


def _settings_epilog() -> str:
    """Every service setting as the environment variable that sets it, with its default."""
    from service.settings import Settings

    lines = ["Settings (environment variables, [default]):"]
    for name, field in Settings.model_fields.items():
        default = "computed" if field.default_factory is not None else repr(field.default)
        lines.append(f"KINCAL_{name.upper()} [{default}]")
        if field.description:
            lines.append(f"    {field.description}")
    return "\b\n" + "\n".join(lines)  # \b: click keeps these lines as they are


@app.command(epilog=_settings_epilog())
def serve(
    host: Annotated[
        str | None, typer.Option(help="Interface [127.0.0.1; keyless only on loopback].")
    ] = None,
    port: Annotated[int | None, typer.Option(min=1, max=65535, help="Port [8000].")] = None,
) -> None:
    """Run the HTTP service (other settings: the KINCAL_* environment variables below)."""
    from service.jobs.supervisor import run_server

    raise typer.Exit(run_server(host=host, port=port))


keys_app = typer.Typer(no_args_is_help=True, help="API keys of the HTTP service.")
app.add_typer(keys_app, name="keys")


@keys_app.command("create")
def keys_create(
    tenant: Annotated[str, typer.Option(help="Tenant the key acts for (created if new).")],
) -> None:
    """Create an API key: printed once, only its SHA-256 is stored."""
    from service.security import create_key

    key_id, key = create_key(tenant)
    typer.echo(key)
    typer.echo(f"key {key_id} for tenant {tenant}; it is not shown again", err=True)


@keys_app.command("revoke")
def keys_revoke(key_id: Annotated[str, typer.Argument(help="The key id (kc_<id>_...).")]) -> None:
    """Revoke an API key (services stop accepting it within KINCAL_API_KEY_CACHE_S)."""
    from service.security import revoke_key

    if not revoke_key(key_id):
        raise KincalError(f"no active key with id {key_id!r}")
    typer.echo(f"revoked key {key_id}")


# --- streaming and fleets (issue 7) ------------------------------------------------------


def _executor(kind: str | None, dask: str | None, workers: int | None) -> Executor | None:
    """The executor asked for (None: the calibration chooses): ``--dask ADDRESS`` (or
    KINCAL_DASK_ADDRESS with ``--executor dask``) reaches a running cluster; ``dask`` alone
    starts a local one; ``--workers`` alone means local processes."""
    from service.settings import dask_address, load_settings
    from solver.executors import EXECUTOR_KINDS, make_executor

    if kind is None and dask is None and workers is None:
        return None
    name = "dask" if dask is not None and kind is None else kind or "processes"
    if name not in EXECUTOR_KINDS:
        raise KincalError(f"--executor {name!r}: choose one of {', '.join(EXECUTOR_KINDS)}")
    if dask is not None and name != "dask":
        raise KincalError(f"--dask needs --executor dask (got --executor {name})")
    if dask is not None:
        try:
            dask = dask_address(dask)
        except ValueError as exc:
            raise KincalError(f"--dask: {exc}") from None
    address = dask or (load_settings().dask_address if name == "dask" else None)
    return make_executor(name, n_workers=workers, dask_address=address)  # type: ignore[arg-type]


@app.command()
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


DESIGN_FLAGS = {
    "n_poses": "--poses",
    "criterion": "--criterion",
    "stage": "--stage",
    "measurement": "--measurement",
    "n_candidates": "--n-candidates",
    "seed": "--seed",
    "box": "--box",
    "cone": "--cone",
    "min_spacing_rad": "--min-spacing",
    "noise_mm": "--noise-mm",
    "noise_deg": "--noise-deg",
    "prior_perturbation_deg": "--prior-perturbation-deg",
    "method": "--method",
    "allow_repeats": "--allow-repeats",
    "marker_offsets_m": "--marker-offsets",
    "calibration": "--config",
}


def _design_options(values: dict[str, object]) -> DesignOptions:
    """DesignOptions from flags, with a one-line error naming the flag."""
    try:
        return DesignOptions.model_validate({k: v for k, v in values.items() if v is not None})
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        field = str(first["loc"][0]) if first["loc"] else ""
        flag = DESIGN_FLAGS.get(field, field or "options")
        raise KincalError(f"{flag}: {first['msg']}") from exc


def _box(text: str) -> dict[str, object]:
    values = numbers(text, "--box", 6)
    return {"low_m": values[:3], "high_m": values[3:]}


def _offsets(text: str) -> list[list[float]]:
    values = numbers(text, "--marker-offsets")
    if len(values) % 3:
        raise KincalError(
            f"--marker-offsets takes x,y,z (m) of each marker, 3 numbers per marker; got "
            f"{len(values)} numbers"
        )
    return [values[i : i + 3] for i in range(0, len(values), 3)]


def _cone(text: str) -> dict[str, object]:
    values = numbers(text, "--cone")
    if len(values) not in (9, 10):
        raise KincalError(
            "--cone takes apex x,y,z, axis x,y,z, half-angle deg, near m, far m "
            f"[, max incidence deg]: 9 or 10 numbers, got {len(values)}"
        )
    cone: dict[str, object] = {
        "apex_m": values[:3],
        "axis": values[3:6],
        "half_angle_deg": values[6],
        "near_m": values[7],
        "far_m": values[8],
    }
    if len(values) == 10:
        cone["max_incidence_deg"] = values[9]
    return cone


@app.command()
def design(
    output: OutputOpt,
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    poses: Annotated[int | None, typer.Option(help="Poses to choose, K [25].")] = None,
    criterion: Annotated[
        str | None,
        typer.Option(
            help="D (log det of the information) [default], A (mean parameter variance), E "
            "(worst direction) or I (predicted pose variance over the task configurations)."
        ),
    ] = None,
    stage: Annotated[
        str | None, typer.Option(help="geometry [default], covariance or both.")
    ] = None,
    measurement: Annotated[
        str | None,
        typer.Option(
            help="What each row will measure, as for kincal calibrate: pose [default], "
            "position, point (ball in socket: --candidates recorded in the sockets), markers "
            "(--marker-offsets), relative-base, components:<tx,ty,tz,rx,ry,rz subset> or "
            "eye-on-head:<joint> (docs/design.md, Measurement types)."
        ),
    ] = None,
    point_distance: PointDistanceOpt = None,
    marker_offsets: Annotated[
        str | None,
        typer.Option(
            help="Measurement markers: each marker's expected offset from the tip frame, "
            "x,y,z m per marker, all comma-separated (3 numbers per marker)."
        ),
    ] = None,
    candidates: Annotated[
        Path | None,
        typer.Option(
            help="Candidate configurations (joint columns; a recording works too; measurement "
            "point: a folder of hole_<k>.csv files or a file with a socket column)."
        ),
    ] = None,
    n_candidates: Annotated[
        int | None, typer.Option(help="Candidates drawn within the joint limits [2000].")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Seed of the drawn candidates [0].")] = None,
    box: Annotated[
        str | None,
        typer.Option(help="Workspace box of the tip, base frame: xmin,ymin,zmin,xmax,ymax,zmax m."),
    ] = None,
    cone: Annotated[
        str | None,
        typer.Option(
            help="Sensor view cone, base frame: apex x,y,z (m), axis x,y,z, half-angle (deg), "
            "near, far (m)[, max incidence of the tip's z axis (deg)]."
        ),
    ] = None,
    min_spacing: Annotated[
        float | None, typer.Option(help="Least joint-space distance between poses, rad [0].")
    ] = None,
    noise_mm: Annotated[float | None, typer.Option(help="Sensor noise σ, mm [0.05].")] = None,
    noise_deg: Annotated[float | None, typer.Option(help="Sensor noise σ, deg [0.003].")] = None,
    prior_perturbation_deg: Annotated[
        float | None,
        typer.Option(help="Covariance stage: assumed joint-frame perturbation σ, deg [0.05]."),
    ] = None,
    method: Annotated[
        str | None, typer.Option(help="auto [default], clarabel or first_order.")
    ] = None,
    allow_repeats: Annotated[bool, typer.Option(help="Allow a candidate more than once.")] = False,
    task: Annotated[
        Path | None,
        typer.Option(
            help="Task configurations (criterion I and the reported pose variance) "
            "[500 drawn in the working volume]."
        ),
    ] = None,
    result: Annotated[
        Path | None,
        typer.Option(
            help="Sequential design: the calibration result of --recording; the next poses "
            "add to what it holds."
        ),
    ] = None,
    recording: Annotated[
        Path | None, typer.Option(help="The recording --result was calibrated from.")
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML file of calibration options (as for kincal calibrate)."),
    ] = None,
    poses_csv: Annotated[
        Path | None, typer.Option(help="Also write the chosen configurations as CSV.")
    ] = None,
) -> None:
    """Choose the K poses to record that tell the calibration most (D-, A-, E- or I-optimal
    design as a convex relaxation, rounded; the relaxation's bound is reported)."""
    from service.app import design as designs

    if (result is None) != (recording is None):
        raise KincalError("a sequential design needs both --result and --recording")
    recorded = None
    if result is not None and recording is not None:
        if config is not None:
            raise KincalError("--result carries its calibration options; drop --config")
        description, recorded = designs.recorded_design(read_result(result), recording)
    else:
        description = _robot(robot, urdf, base, tip)
    options = _design_options(
        {
            "n_poses": poses,
            "criterion": criterion,
            "stage": stage,
            "measurement": measurement,
            "n_candidates": n_candidates,
            "seed": seed,
            "box": None if box is None else _box(box),
            "cone": None if cone is None else _cone(cone),
            "min_spacing_rad": min_spacing,
            "noise_mm": noise_mm,
            "noise_deg": noise_deg,
            "prior_perturbation_deg": prior_perturbation_deg,
            "method": method,
            "allow_repeats": allow_repeats or None,
            "marker_offsets_m": None if marker_offsets is None else _offsets(marker_offsets),
            "calibration": None
            if config is None and point_distance is None
            else calibration_options(
                None if config is None else read_config(config),
                {"point_distance_m": point_distance},
            ).model_dump(),
        }
    )
    model = designs.design_model(description, options, recorded)
    chain = model.chain
    given, sockets = None, None
    if candidates is not None:
        given, sockets = designs.read_candidates(candidates, model)
    task_q = None
    if task is not None:
        task_q = read_configurations(
            task, chain.joint_names, other_joint_names=chain.other_joint_names
        ).joint_positions
    out = designs.run_design(
        description,
        options,
        candidates=given,
        task=task_q,
        recorded=recorded,
        model=model,
        sockets=sockets,
    )
    _write_json(output, out.model_dump_json(indent=1))
    if poses_csv is not None:
        frame = pd.DataFrame([pose.joint_positions for pose in out.poses], columns=out.joint_names)
        poses_csv.parent.mkdir(parents=True, exist_ok=True)
        frame.to_csv(poses_csv, index=False, float_format="%.17g")
    typer.echo(design_summary(out))
    typer.echo(f"design written to {output}")


def design_summary(out: DesignResult) -> str:
    """A few lines: poses, criterion against its bound, predicted errors."""
    c = out.criterion
    worst = max(out.parameters, key=lambda p: p.relative_to_noise)
    lines = [
        f"{len(out.poses)} poses chosen from {out.candidates} candidates "
        f"({c.name}-optimal, relaxation by {c.method}: {c.status}, {c.iterations} iterations)",
        f"criterion {c.value:.6g}, relaxation bound {c.upper_bound:.6g}: efficiency "
        f"{100 * c.efficiency:.1f} %",
        f"predicted parameter part of the pose variance {out.mean_pose_variance_m2:.3g} m² "
        f"(mean over {out.task_configurations} task configurations); worst parameter "
        f"{worst.name}: σ {worst.standard_error:.3g} {worst.unit} "
        f"({worst.relative_to_noise:.3g} × noise)",
    ]
    if out.covariance is not None:
        cov = out.covariance
        lines.append(
            f"covariance statistics: rank {cov.rank} of {cov.n_entries} (all candidates: "
            f"{cov.candidate_rank}), {len(cov.unidentifiable)} quantities identifiable only in "
            "combination"
        )
    if out.measurement is not None:
        nuisance = out.measurement.nuisance_parameters
        lines.append(
            f"measurement {out.measurement.type}: standard errors of the chain parameters"
            + (
                f" with its {len(nuisance)} own unknowns profiled out ({', '.join(nuisance)})"
                if nuisance
                else " (no unknowns of its own)"
            )
        )
    if out.sequential is not None and out.sequential.unidentifiable_before:
        lines.append(
            "the recording alone leaves unidentified: "
            + ", ".join(out.sequential.unidentifiable_before)
        )
    lines += [f"note: {note}" for note in out.notes]
    return "\n".join(lines)


def _full_summaries(command: Any) -> None:  # typer's (vendored) click.Command
    """``kincal --help`` lists each command with its docstring's whole first paragraph; click
    would cut it at the first full stop ("(paper Eq.") or at 45 characters."""
    for sub in getattr(command, "commands", {}).values():
        if not sub.short_help and sub.help:
            sub.short_help = " ".join(inspect.cleandoc(sub.help).split("\n\n")[0].split())
        _full_summaries(sub)


def main() -> None:
    """Entry point: domain errors become one line on stderr and exit code 2.

    Usage errors (unknown option, missing argument) are typer's, also exit code 2.
    """
    try:
        command = typer.main.get_command(app)
        _full_summaries(command)
        command()
    except KincalError as exc:
        typer.echo(f"kincal: error: {exc}", err=True)
        sys.exit(2)
    except Exception as exc:  # a bug, not bad input: keep it short unless asked
        if os.environ.get("KINCAL_DEBUG"):
            traceback.print_exc()
        typer.echo(
            f"kincal: internal error: {type(exc).__name__}: {exc} "
            "(set KINCAL_DEBUG=1 for the traceback and please report it)",
            err=True,
        )
        sys.exit(1)
