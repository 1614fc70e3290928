"""Parsing of CLI flags shared by the commands: the calibration options as flags and as a TOML
configuration file, and the ranking flags as request models."""

from __future__ import annotations

import io
import json
import math
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli.generated_help import CALIBRATION
from solver.errors import KincalError

if TYPE_CHECKING:  # imported where used: ``kincal --help`` loads no pydantic model or numpy
    import pydantic

    from schemas.calibration import CalibrationOptions
    from schemas.ranking import RankingOptions, TargetRankingRequest


def numbers(text: str, option: str, count: int | None = None) -> list[float]:
    """Comma-separated finite numbers of a flag, with a one-line error naming the flag."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or (count is not None and len(values) != count):
        expected = f"{count} comma-separated numbers" if count else "comma-separated numbers"
        raise KincalError(f"{option} takes {expected}, got {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise KincalError(f"{option} must be finite numbers, got {text!r}")
    return values


# --- the calibration options as CLI flags and a TOML file -------------------------------------

CALIBRATION_FLAGS: dict[str, str] = {
    "free_parameters": "--free",
    "fixed_parameters": "--fix",
    "compliant_joints": "--compliant-joints",
    "virtual_axes_at": "--virtual-axes",
    "gravity_base_m_s2": "--gravity",
    "payload_kg": "--payload-kg",
    "payload_com_m": "--payload-com",
    "rotation_weight_m_per_rad": "--rotation-weight",
    "outlier_rule": "--outlier-rule",
    "outlier_level": "--outlier-level",
    "outlier_sigma": "--outlier-sigma",
    "max_iterations": "--max-iterations",
    "tolerance": "--tolerance",
    "rank_tolerance": "--rank-tolerance",
    "heldout": "--heldout",
    "heldout_method": "--heldout-method",
    "seeds": "--seeds",
    "train_fraction": "--train-fraction",
    "covariance": "--covariance",
    "covariance_solver": "--solver",
    "covariance_estimator": "--estimator",
    "covariance_frames": "--covariance-frames",
    "covariance_axes": "--covariance-axes",
    "noise_std": "--noise-std",
    "noise_covariance": "--noise-covariance",
    "measurement": "--measurement",
    "point_distance_m": "--point-distance",
}
"""The ``kincal calibrate`` flag of every field of :class:`CalibrationOptions` (the HTTP body
and a ``--config`` TOML file use the field names themselves); a test keeps this table, the
model and the command's flags in step."""


def option_help(field: str, extra: str = "") -> str:
    """A calibrate flag's help: the option's description, its config key and its default in
    words (from the model, through :mod:`service.cli.generated_help`)."""
    description, default, _ = CALIBRATION[field]
    return f"{description.rstrip('.')}{extra}. [config: {field}] [default: {default}]"


def option_choices(field: str) -> list[str] | None:
    """The values a calibration option takes, when it is a choice (None otherwise)."""
    return list(CALIBRATION[field][2]) or None


def read_config(path: Path) -> dict[str, Any]:
    """The calibration options of a TOML file: the fields of :class:`CalibrationOptions` as
    top-level keys (a ``[calibration]`` table is accepted too); a one-line error otherwise."""
    try:
        document = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise KincalError(f"cannot read config {path}: {exc.strerror}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise KincalError(f"{path} is not TOML ({exc}); --config takes a TOML file") from exc
    table = document.get("calibration", document)
    if not isinstance(table, dict):
        raise KincalError(f"{path}: [calibration] must be a table of options")
    unknown = [key for key in table if key not in CALIBRATION_FLAGS]
    if unknown:
        raise KincalError(
            f"{path}: unknown option(s) {', '.join(unknown)}; the options are "
            f"{', '.join(CALIBRATION_FLAGS)}"
        )
    return dict(table)


def calibration_options(
    config: dict[str, Any] | None,
    flags: dict[str, Any],
    defaults: dict[str, Any] | None = None,
) -> CalibrationOptions:
    """The options of a config file (or none) overridden by the flags given (``None`` values
    are flags not given), on top of a command's own ``defaults`` where it differs from the
    model's; a one-line error naming the option and its flag otherwise."""
    import pydantic

    from schemas.calibration import CalibrationOptions

    values = {**(defaults or {}), **(config or {})}
    values.update({name: value for name, value in flags.items() if value is not None})
    try:
        return CalibrationOptions.model_validate(values)
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        loc = [str(p) for p in first["loc"]]
        name = loc[0] if loc else ""
        where = ".".join(loc) or "options"
        flag = CALIBRATION_FLAGS.get(name)
        hint = f" ({flag})" if flag else ""
        raise KincalError(f"option {where}{hint}: {first['msg']}") from exc


# --- ``kincal rank`` flags -> request models --------------------------------------------------


def read_weight_matrix(path: Path) -> list[list[float]]:
    """A 6×6 W from a JSON file (nested list) or a text file of 6 rows of 6 numbers."""
    import numpy as np

    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise KincalError(f"cannot read weight matrix {path}: {exc.strerror}") from exc
    try:
        matrix = np.array(json.loads(text), dtype=float)
    except (ValueError, TypeError):
        try:
            matrix = np.loadtxt(io.StringIO(text.replace(",", " ")), ndmin=2)
        except ValueError as exc:
            raise KincalError(f"{path}: not a 6×6 matrix of numbers ({exc})") from exc
    if matrix.shape != (6, 6) or not np.all(np.isfinite(matrix)):
        raise KincalError(
            f"{path}: weight matrix must be 6×6 finite numbers, got shape {matrix.shape}"
        )
    return matrix.tolist()


def ranking_options_from_flags(
    *,
    weights: str | None,
    weight_matrix: Path | None,
    rotation_scale_m_per_rad: float,
    task_point: str | None,
    task_weights: str | None,
    include_noise: bool,
    top: int | None,
    uncertainty: str = "random_effects",
) -> RankingOptions:
    """``kincal rank`` flags -> :class:`RankingOptions` (exclusive choices checked)."""
    import pydantic

    from schemas.ranking import RankingOptions

    if task_point is not None and (weights is not None or weight_matrix is not None):
        raise KincalError("--task-point replaces --weights/--weight-matrix; give one of them")
    if weights is not None and weight_matrix is not None:
        raise KincalError("give --weights or --weight-matrix, not both")
    if task_weights is not None and task_point is None:
        raise KincalError("--task-weights needs --task-point x,y,z")
    document: dict[str, object]
    if task_point is not None:
        document = {"kind": "task_point", "point_m": numbers(task_point, "--task-point", 3)}
        if task_weights is not None:
            document["axis_weights"] = numbers(task_weights, "--task-weights", 3)
    else:
        document = {"kind": "pose", "rotation_scale_m_per_rad": rotation_scale_m_per_rad}
        if weights is not None:
            document["diagonal"] = numbers(weights, "--weights", 6)
        if weight_matrix is not None:
            document["matrix"] = read_weight_matrix(weight_matrix)
    try:
        return RankingOptions.model_validate(
            {
                "weights": document,
                "include_noise": include_noise,
                "top": top,
                "uncertainty": uncertainty.replace("-", "_"),
            }
        )
    except pydantic.ValidationError as exc:
        raise KincalError(_flag_error(exc)) from exc


def target_request(
    target: str,
    options: RankingOptions,
    *,
    n_candidates: int,
    seed: int,
    free_axis: str,
    payload_kg: float,
) -> TargetRankingRequest:
    """``--target x,y,z,qx,qy,qz,qw`` and friends -> :class:`TargetRankingRequest`."""
    import pydantic

    from schemas.ranking import TargetRankingRequest

    values = numbers(target, "--target", 7)
    try:
        return TargetRankingRequest.model_validate(
            {
                "target": {"position_m": values[:3], "quaternion_xyzw": values[3:]},
                "n_candidates": n_candidates,
                "seed": seed,
                "free_axis": free_axis,
                "payload_kg": payload_kg,
                "options": options,
            }
        )
    except pydantic.ValidationError as exc:
        raise KincalError(_flag_error(exc)) from exc


def _flag_error(exc: pydantic.ValidationError) -> str:
    first = exc.errors()[0]
    where = ".".join(str(p) for p in first["loc"])
    names = {
        "weights.pose.diagonal": "--weights",
        "weights.pose.matrix": "--weight-matrix",
        "weights.pose.rotation_scale_m_per_rad": "--rotation-scale",
        "weights.task_point.point_m": "--task-point",
        "weights.task_point.axis_weights": "--task-weights",
        "target": "--target",
        "free_axis": "--free-axis",
        "n_candidates": "--n-candidates",
        "payload_kg": "--payload-kg",
        "top": "--top",
    }
    flag = next((f for key, f in names.items() if where.startswith(key)), where)
    return f"{flag}: {first['msg']}"
