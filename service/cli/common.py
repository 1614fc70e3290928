"""What the command groups of :mod:`service.cli` share: the typer application, the options
several commands take, reading and writing the documents they exchange, the executor flags."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import pydantic
import typer

from schemas.calibration import CalibrationResult
from schemas.robots import BUILTIN_ROBOTS, RobotDescription, load_robot
from service.cli.flags import numbers, option_help
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
DataArg = Annotated[
    Path,
    typer.Argument(
        help="Dataset: CSV, Parquet, JSON or industrial_calibration YAML; or a folder of "
        "ball-in-socket hole_<k>.csv files."
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
