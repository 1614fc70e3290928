"""``kincal predict`` and ``kincal rank``: what a calibration result predicts at new
configurations."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.dataset.paths import check_recording_path
from service.cli.common import (
    Outputs,
    ResultOutDirOpt,
    _prediction_note,
    output_option,
    read_result,
)
from service.cli.flags import ranking_options_from_flags, target_request
from solver.errors import KincalError

if TYPE_CHECKING:
    from schemas.dataset import ConfigurationSet
    from solver.model import KinematicChain

PredictionsOut = Annotated[Path | None, output_option("predictions.csv", "The predictions CSV")]
RankingOut = Annotated[Path | None, output_option("ranking.json", "The ranking JSON")]


def _configurations(configs: Path, chain: KinematicChain) -> ConfigurationSet:
    """The configurations file, read for ``chain`` and checked like a recording's joints
    (radians, within the limits: :func:`service.app.preflight.check_configurations`)."""
    from schemas.dataset import read_configurations
    from service.app.preflight import check_configurations

    configurations = read_configurations(
        configs, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    check_configurations(configurations.joint_positions, chain, configs.name)
    return configurations


def predict(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result JSON.")],
    configs: Annotated[Path, typer.Argument(help="Configurations: joint columns (+ payload_kg).")],
    output: PredictionsOut = None,
    out_dir: ResultOutDirOpt = None,
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
    check_recording_path(configs)
    outputs = Outputs(out_dir if out_dir is not None else result_path.parent)
    path = outputs.path(output, "predictions.csv", "predicted poses (kincal predict)")
    result = read_result(result_path)
    import pandas as pd

    from service.render import result_json
    from service.render.text import used_calibration_line
    from solver import lie

    _prediction_note(result)
    chain, _ = result_json.result_chain(result)
    configurations = _configurations(configs, chain)
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
    extra = " and covariances" if result.covariance is not None else ""
    outputs.write(
        path,
        f"{len(frame)} predicted poses{extra}",
        lambda p: frame.to_csv(p, index=False, float_format="%.17g"),
    )
    typer.echo(outputs.listing())
    typer.echo(used_calibration_line(result.verdict))


def rank(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result with covariance.")],
    output: RankingOut = None,
    out_dir: ResultOutDirOpt = None,
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
    if configs is not None:
        check_recording_path(configs)
    outputs = Outputs(out_dir if out_dir is not None else result_path.parent)
    path = outputs.path(output, "ranking.json", "kincal.ranking/1")
    result = read_result(result_path)
    from service.app import rank as ranking
    from service.render.text import ranking_summary, used_calibration_line

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
        configurations = _configurations(configs, model.chain)
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
    outputs.write_text(
        path, f"ranking of {out.n_configurations}", out.model_dump_json(indent=1) + "\n"
    )
    typer.echo(ranking_summary(out))
    typer.echo(outputs.listing())
    typer.echo(used_calibration_line(result.verdict))
