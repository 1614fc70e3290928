"""``kincal design``: which poses to record."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.dataset.paths import check_recording_path
from service.cli.common import (
    OUTPUT,
    BaseOpt,
    OutDirOpt,
    Outputs,
    PointDistanceOpt,
    RobotOpt,
    TipOpt,
    UrdfOpt,
    _robot,
    out_dir_for,
    output_option,
    read_result,
    refuse_options_outside,
)
from service.cli.flags import calibration_options, numbers, read_config
from solver.errors import KincalError

if TYPE_CHECKING:
    from schemas.calibration import CalibrationResult
    from schemas.design import DesignOptions, DesignResult

DesignOut = Annotated[Path | None, output_option("design.json", "The design JSON")]

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
    import pydantic

    from schemas.design import DesignOptions

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


def design(
    ctx: typer.Context,
    output: DesignOut = None,
    out_dir: OutDirOpt = None,
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
        Path | None,
        typer.Option(
            help="Also write the chosen configurations as CSV (joint columns) to this file.",
            rich_help_panel=OUTPUT,
        ),
    ] = None,
    check: Annotated[
        int | None,
        typer.Option(
            "--check",
            metavar="K",
            help="Check poses instead: the K candidates at which kincal check of --result "
            "states the smallest changes (written as a recording template, check_poses.csv).",
        ),
    ] = None,
) -> None:
    """Choose the K poses to record that tell the calibration most (D-, A-, E- or I-optimal
    design as a convex relaxation, rounded; the relaxation's bound is reported); with
    ``--check K``, the K check poses of a calibration (docs/check.md)."""
    # the files given are read or checked first: one that is not there is refused in ~0.2 s,
    # before the design machinery (SciPy, Pinocchio, cvxpy) loads
    if check is not None:
        refuse_options_outside(
            ctx,
            {"check", "result", "candidates", "n_candidates", "seed", "box", "cone"}
            | {"out_dir", "output", "poses_csv"},
            "--check designs check poses of --result; these belong to a calibration design",
        )
        if result is None:
            raise KincalError("--check K designs check poses of a calibration: give --result")
        calibration = read_result(result)
        if candidates is not None:
            check_recording_path(candidates)
        check_design(
            calibration,
            result,
            check,
            candidates,
            {
                "n_candidates": n_candidates,
                "seed": seed,
                "box": None if box is None else _box(box),
                "cone": None if cone is None else _cone(cone),
            },
            Outputs(out_dir if out_dir is not None else result.parent),
            output,
            poses_csv,
        )
        return
    outputs = Outputs(out_dir_for(out_dir, recording, "design"))
    path = outputs.path(output, "design.json", "kincal.design/1")
    csv_path = None if poses_csv is None else outputs.path(poses_csv, "", "joint configurations")
    if (result is None) != (recording is None):
        raise KincalError("a sequential design needs both --result and --recording")
    if result is not None and config is not None:
        raise KincalError("--result carries its calibration options; drop --config")
    calibrated = None if result is None else read_result(result)
    config_values = None if config is None else read_config(config)
    for source in (recording, candidates, task):
        if source is not None:
            check_recording_path(source)
    from service.app import design as designs

    recorded = None
    if calibrated is not None and recording is not None:
        from service.app.preflight import check_recording
        from service.render.result_json import result_chain

        check_recording(recording, result_chain(calibrated)[0])
        description, recorded = designs.recorded_design(calibrated, recording)
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
                config_values,
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
        from schemas.dataset import read_configurations

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
    outputs.write_text(
        path, f"design of {len(out.poses)} poses", out.model_dump_json(indent=1) + "\n"
    )
    if csv_path is not None:
        import pandas as pd

        frame = pd.DataFrame([pose.joint_positions for pose in out.poses], columns=out.joint_names)
        outputs.write(
            csv_path,
            f"the {len(out.poses)} chosen configurations",
            lambda p: frame.to_csv(p, index=False, float_format="%.17g"),
        )
    typer.echo(design_summary(out))
    typer.echo(outputs.listing())
    c = out.criterion
    typer.echo(
        f"verdict: {len(out.poses)} poses chosen, {100 * c.efficiency:.1f} % of the relaxation's "
        f"bound ({c.status}): record them, then kincal calibrate (exit code 0)"
    )


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


def check_design(
    calibration: CalibrationResult,
    result_path: Path,
    n_poses: int,
    candidates: Path | None,
    values: dict[str, object],
    outputs: Outputs,
    output: Path | None,
    poses_csv: Path | None,
) -> None:
    """``kincal design --check K`` of ``calibration`` (read from ``result_path``): choose,
    write (the JSON and the recording template), print the stated sizes."""
    import pandas as pd

    from schemas.design import CHECK_DESIGN_FORMAT
    from service.app.check_design import run_check_design
    from service.render.result_json import result_chain
    from service.render.text import stated_sizes_line

    path = outputs.path(output, "check_design.json", CHECK_DESIGN_FORMAT)
    csv_path = outputs.path(poses_csv, "check_poses.csv", "joint configurations")
    given = None
    if candidates is not None:
        from schemas.dataset import read_configurations

        chain, _ = result_chain(calibration)
        given = read_configurations(
            candidates, chain.joint_names, other_joint_names=chain.other_joint_names
        ).joint_positions
    out = run_check_design(
        calibration,
        _design_options(values),
        n_poses,
        candidates=given,
        result_name=str(result_path),
    )
    outputs.write_text(
        path, f"check design of {len(out.poses)} poses", out.model_dump_json(indent=1) + "\n"
    )
    frame = pd.DataFrame([pose.joint_positions for pose in out.poses], columns=out.joint_names)
    outputs.write(
        csv_path,
        f"the {len(out.poses)} check poses (recording template: add the measured columns)",
        lambda p: frame.to_csv(p, index=False, float_format="%.17g"),
    )
    typer.echo(
        f"{len(out.poses)} check poses chosen from {out.candidates} candidates: largest size "
        f"over its scale {out.worst_relative_size:.3g} (median of {out.random_draws} random "
        f"sets of {len(out.poses)}: {out.random_worst_relative_size:.3g})"
    )
    typer.echo(stated_sizes_line(out.stated_sizes, out.power))
    typer.echo(outputs.listing())
    typer.echo(
        f"verdict: record the {len(out.poses)} poses of {csv_path} (add the measured columns), "
        f"then kincal check {result_path} RECORDING (exit code 0)"
    )
