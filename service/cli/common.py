"""What the command groups of :mod:`service.cli` share: the typer application, the options
several commands take, reading and writing the documents they exchange, the executor flags."""

from __future__ import annotations

import json
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer

from schemas.robots import BUILTIN_ROBOTS, RobotDescription, load_robot, urdf_robot
from service.cli.flags import numbers, option_help
from solver.errors import KincalError, ModelError

if TYPE_CHECKING:  # imported where used: ``kincal --help`` stays light (docs/architecture.md)
    import pydantic

    from schemas.calibration import CalibrationResult
    from schemas.dataset.rosbag import BagRecording
    from schemas.discovery import FindingsResult
    from solver.executors import Executor
    from solver.model import KinematicChain

DocumentT = TypeVar("DocumentT", bound="pydantic.BaseModel")

# The help panels of ``kincal <command> --help``, in the order they are shown.
RECORDING = "Recording and robot"
MODEL = "Model"
MEASUREMENT = "Measurement"
OUTLIERS = "Outliers"
COVARIANCE = "Covariance"
HELDOUT = "Held-out"
EXECUTION = "Execution"
OUTPUT = "Output"
ROS_BAG = "ROS bag"

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
    help="Calibrate robot kinematics, including the randomness inside the chain.",
)


def _show_version(value: bool) -> None:
    if value:
        from service import kincal_version

        typer.echo(f"kincal {kincal_version()}")
        raise typer.Exit()


@app.callback()
def _kincal(
    version: Annotated[
        bool,
        typer.Option(
            "--version", is_eager=True, callback=_show_version, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    """Calibrate robot kinematics, including the randomness inside the chain (paper: Gerstewitz
    et al.). Start with `kincal calibrate RECORDING --robot NAME`; docs: docs/index.md."""


RobotOpt = Annotated[
    str | None,
    typer.Option(
        "--robot",
        help=f"Built-in robot: {', '.join(BUILTIN_ROBOTS)}.",
        rich_help_panel=RECORDING,
    ),
]
UrdfOpt = Annotated[
    Path | None,
    typer.Option("--urdf", help="A URDF file instead of --robot.", rich_help_panel=RECORDING),
]
BaseOpt = Annotated[
    str | None, typer.Option("--base", help="Base frame (with --urdf).", rich_help_panel=RECORDING)
]
TipOpt = Annotated[
    str | None, typer.Option("--tip", help="Tip frame (with --urdf).", rich_help_panel=RECORDING)
]
DhOpt = Annotated[
    Path | None,
    typer.Option(
        "--dh",
        help="A DH or modified-DH table (YAML, docs/dh.md) instead of --robot/--urdf, for "
        "devices without a URDF.",
        rich_help_panel=RECORDING,
    ),
]
_DATA_HELP = (
    "Dataset: CSV, Parquet, JSON or industrial_calibration YAML; or a folder of "
    "ball-in-socket hole_<k>.csv files"
)
DataArg = Annotated[
    Path, typer.Argument(help=f"{_DATA_HELP}.", metavar="RECORDING", show_default=False)
]
DataOrBagArg = Annotated[
    Path,
    typer.Argument(
        help=f"{_DATA_HELP}; or a ROS bag (.bag file, rosbag2 folder) with --joint-states and "
        "--measure (without --robot/--urdf/--dh, the URDF it carries on /robot_description is "
        "the robot).",
        metavar="RECORDING",
        show_default=False,
    ),
]
OutDirOpt = Annotated[
    Path | None,
    typer.Option(
        "--out-dir",
        help="Folder for every file this command writes that has no path of its own "
        "[default: out/<recording name>/].",
        rich_help_panel=OUTPUT,
        show_default=False,
    ),
]
MeasurementOpt = Annotated[
    str | None,
    typer.Option(
        help=option_help("measurement"),
        metavar="auto|pose|position|point|markers|relative-base|components:…|eye-on-head:…",
        rich_help_panel=MEASUREMENT,
    ),
]
PointDistanceOpt = Annotated[
    float | None, typer.Option(help=option_help("point_distance_m"), rich_help_panel=MEASUREMENT)
]
MarkerOpt = Annotated[
    int | None,
    typer.Option(help="FIGAROH files: which marker [default: all].", rich_help_panel=MEASUREMENT),
]
ExecutorOpt = Annotated[
    str | None,
    typer.Option(
        help="Where the passes over the data run: inprocess, processes (local, one per core) "
        "or dask. Default: local processes for a file of more than one chunk on a machine with "
        "several cores, else in this process. The numbers do not depend on it.",
        metavar="inprocess|processes|dask",
        rich_help_panel=EXECUTION,
    ),
]
DaskOpt = Annotated[
    str | None,
    typer.Option(
        "--dask",
        help="Dask scheduler address (tcp://host:8786), implies --executor dask; without it "
        "--executor dask uses KINCAL_DASK_ADDRESS or starts a local cluster.",
        rich_help_panel=EXECUTION,
    ),
]
ChunkRowsOpt = Annotated[
    int | None,
    typer.Option(
        min=1,
        help="Rows per streamed chunk [default: 65536; Parquet: row groups].",
        rich_help_panel=EXECUTION,
    ),
]
WorkersOpt = Annotated[
    int | None,
    typer.Option(
        min=1,
        help="Processes for --executor processes/local dask [default: cores].",
        rich_help_panel=EXECUTION,
    ),
]

JointStatesOpt = Annotated[
    str | None,
    typer.Option(
        "--joint-states",
        help="A ROS bag: the sensor_msgs/JointState topic (e.g. /joint_states).",
        metavar="TOPIC",
        rich_help_panel=ROS_BAG,
    ),
]
MeasureOpt = Annotated[
    str | None,
    typer.Option(
        "--measure",
        help="A ROS bag: the measured pose. tf:PARENT:CHILD (CHILD in PARENT, from /tf and "
        "/tf_static), pose:TOPIC (PoseStamped or TransformStamped), point:TOPIC "
        "(PointStamped: positions only) or calibration-data:TOPIC[:CAMERA[:CHAIN]] "
        "(robot_calibration's captures; no --joint-states).",
        metavar="SOURCE",
        rich_help_panel=ROS_BAG,
    ),
]
CaptureOpt = Annotated[
    str | None,
    typer.Option(
        "--capture",
        help="A ROS bag: a topic (any type) with one message per capture; each is a sample, "
        "the robot still for --still-window around it [default: one sample per still segment].",
        metavar="TOPIC",
        rich_help_panel=ROS_BAG,
    ),
]
StillToleranceOpt = Annotated[
    float,
    typer.Option(
        "--still-tolerance",
        min=0.0,
        help="A ROS bag: the robot holds still while every joint moves slower than this, "
        "rad/s (m/s).",
        rich_help_panel=ROS_BAG,
    ),
]
StillWindowOpt = Annotated[
    float,
    typer.Option(
        "--still-window",
        min=0.0,
        help="A ROS bag: shortest hold that makes a sample, s.",
        rich_help_panel=ROS_BAG,
    ),
]
ClockToleranceOpt = Annotated[
    float,
    typer.Option(
        "--clock-tolerance",
        min=0.0,
        help="A ROS bag: clock offset tolerated between the joint-state and measurement "
        "topics, s (measurements this close to a hold's ends are not used).",
        rich_help_panel=ROS_BAG,
    ),
]
STILL_TOLERANCE_RAD_S = 1e-3
STILL_WINDOW_S = 0.2
CLOCK_TOLERANCE_S = 0.02
"""The defaults of the three options above (``schemas.dataset.still.StillSettings``'s; a test
keeps them equal: that module imports numpy, which ``kincal --help`` must not)."""


def output_option(default_name: str, what: str) -> Any:
    """The ``-o/--output`` option of a command whose main file is ``default_name`` in the
    output folder."""
    return typer.Option(
        "-o",
        "--output",
        help=f"{what} [default: <out-dir>/{default_name}].",
        rich_help_panel=OUTPUT,
        show_default=False,
    )


# --- where a command writes, and saying what it wrote -------------------------------------------

OUT_ROOT = Path("out")
"""Commands write under ``out/<recording name>/`` unless told otherwise (``make demo``:
``out/demo``), so examples run in a checkout leave nothing in its root."""

_PREDICTION_COLUMNS = {"sample_id", "x", "y", "z", "qx", "qy", "qz", "qw"} | {
    f"cov_{i}{j}" for i in range(6) for j in range(6)
}


_CSV_KINDS = {"predictions": "predicted poses (kincal predict)", "recording": "a recording"}


def default_out_dir(recording: Path) -> Path:
    """``out/<name>/``: the recording's file name without its suffix, or its folder name."""
    name = recording.name if recording.is_dir() else recording.stem
    return OUT_ROOT / (name or "kincal")


def file_kind(path: Path) -> str | None:
    """What an existing output file holds, in words, when kincal can tell: the ``format`` of a
    kincal JSON document, or the kind of a CSV by its header; None otherwise."""
    try:
        if path.suffix == ".json":
            with path.open("rb") as handle:
                head = handle.read(4096).decode("utf-8", "replace")
            found = head.split('"format"', 1)
            if len(found) == 2:
                value = found[1].split('"', 2)
                return value[1] if len(value) == 3 else None
            if path.stat().st_size > 16 * 1024 * 1024:
                return None
            document = json.loads(path.read_bytes())  # "format" last (kincal fleet)
            found_format = document.get("format") if isinstance(document, dict) else None
            return found_format if isinstance(found_format, str) else None
        if path.suffix == ".csv":
            with path.open(encoding="utf-8", errors="replace") as handle:
                header = {c.strip() for c in handle.readline().split(",")}
            pose = {"x", "y", "z"}
            if "cov_00" in header or (pose <= header and header <= _PREDICTION_COLUMNS):
                return _CSV_KINDS["predictions"]
            return _CSV_KINDS["recording"] if pose <= header else "joint configurations"
    except (OSError, ValueError):
        return None
    return None


ResultOutDirOpt = Annotated[
    Path | None,
    typer.Option(
        "--out-dir",
        help="Folder for the output [default: the folder of RESULT].",
        rich_help_panel=OUTPUT,
        show_default=False,
    ),
]
"""``--out-dir`` of the commands that read a result (predict, rank, check)."""
ReportOpt = Annotated[
    Path | None,
    typer.Option(
        help="Also write the HTML report (figures embedded) to this file.",
        rich_help_panel=OUTPUT,
    ),
]
"""``--report`` of the commands that write an HTML report (calibrate, discover, check)."""


@dataclass
class Outputs:
    """The files of one command run: their paths are settled (and checked) before the work
    starts, and each is listed once written, so the user sees every file a command wrote.

    An existing file that holds another kind of document than the one a path will receive
    (another command's result) is never replaced: :class:`KincalError` before any work."""

    out_dir: Path
    written: list[tuple[Path, str, bool]] = field(default_factory=list)

    def path(self, given: Path | None, default_name: str, kind: str | None) -> Path:
        """``given`` or ``<out_dir>/<default_name>``, refused when it holds another kind."""
        path = given if given is not None else self.out_dir / default_name
        if path.is_dir():
            raise KincalError(f"{path} is a folder; give a file name for this output")
        if path.exists() and kind is not None:
            held = file_kind(path)
            if held is not None and held != kind:
                raise KincalError(
                    f"{path} already holds {held}; this command would replace it with {kind}: "
                    "give another output name (-o/--out-dir) or remove the file"
                )
        return path

    def write(self, path: Path, what: str, write: Callable[[Path], object]) -> None:
        """Write ``path`` atomically (a temporary file renamed) and remember it."""
        existed = path.exists()
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")  # same suffix: same format
        write(tmp)
        tmp.replace(path)
        self.written.append((path, what, existed))

    def write_text(self, path: Path, what: str, text: str) -> None:
        self.write(path, what, lambda p: p.write_text(text, encoding="utf-8"))

    def note(self, path: Path, what: str) -> None:
        """A file written by someone else on this command's behalf (e.g. a figure)."""
        self.written.append((path, what, False))

    def listing(self) -> str:
        """ "wrote:" and one line per file: path, what it holds, "(replaced)" if it existed."""
        lines = ["wrote:"]
        for path, what, replaced in self.written:
            lines.append(f"  {path}  {what}{' (replaced)' if replaced else ''}")
        return "\n".join(lines) if self.written else "wrote: nothing"


def refuse_options_outside(ctx: typer.Context, allowed: Collection[str], why: str) -> None:
    """:class:`KincalError` naming every option of the command that was given (on the command
    line or through the environment) although its mode takes only the parameters ``allowed``
    (Python names), with ``why`` they do not apply."""
    given = [
        param.opts[0]
        for param in ctx.command.params
        if param.name not in allowed and _given(ctx.get_parameter_source(param.name or ""))
    ]
    if given:
        raise KincalError(f"{', '.join(given)}: {why}; drop them")


def _given(source: Any) -> bool:
    """Whether click's ``ParameterSource`` of a value says the user gave it (typer vendors its
    own click, so the enum is compared by name)."""
    return source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP")


def out_dir_for(out_dir: Path | None, recording: Path | None, fallback: str) -> Path:
    """The output folder: ``--out-dir``, else ``out/<recording name>/``, else ``out/<fallback>``."""
    if out_dir is not None:
        return out_dir
    return default_out_dir(recording) if recording is not None else OUT_ROOT / fallback


def _robot(
    robot: str | None,
    urdf: Path | None,
    base: str | None,
    tip: str | None,
    dh: Path | None = None,
) -> RobotDescription:
    return load_robot(robot, urdf_path=urdf, base_frame=base, tip_frame=tip, dh_path=dh)


def robot_for(
    recording: Path,
    robot: str | None,
    urdf: Path | None,
    base: str | None,
    tip: str | None,
    dh: Path | None,
    *,
    to_stderr: bool = False,
) -> RobotDescription:
    """The robot of the robot options (--robot, --urdf, --dh); without one, the URDF a ROS bag
    ``recording`` carries (:func:`bag_robot`, said in one line, on stderr if ``to_stderr``);
    neither: :class:`KincalError` naming both fixes."""
    if robot is not None or urdf is not None or dh is not None:
        return _robot(robot, urdf, base, tip, dh)
    from schemas.dataset.paths import is_bag

    if not is_bag(recording):
        return _robot(robot, urdf, base, tip, dh)  # the error that names the robot options
    from schemas.dataset.rosbag import ROBOT_DESCRIPTION_TOPIC

    description = bag_robot(recording, base, tip, to_stderr=to_stderr)
    if description is None:
        raise KincalError(
            f"{recording.name}: no robot given and no URDF on {ROBOT_DESCRIPTION_TOPIC} in the "
            "bag; pass --robot NAME or --urdf FILE --base FRAME --tip FRAME, or record "
            f"{ROBOT_DESCRIPTION_TOPIC} (std_msgs/String) with the bag"
        )
    return description


def bag_robot(
    bag: Path, base: str | None, tip: str | None, *, to_stderr: bool = False
) -> RobotDescription | None:
    """The robot of the URDF the ROS bag ``bag`` carries on /robot_description (its last
    message), checked as a --urdf file is and built once by Pinocchio so that a bad one is
    refused naming the bag; ``base``/``tip`` as given, else the arm's (the root link, the link
    of the last joint before the tree branches). Says so in one line; None without the topic."""
    from schemas.dataset.rosbag import ROBOT_DESCRIPTION_TOPIC, read_robot_description
    from solver.model import build_chain

    urdf_xml = read_robot_description(bag)
    if urdf_xml is None:
        return None
    where = f"the URDF on {ROBOT_DESCRIPTION_TOPIC} in {bag.name}"
    try:
        description, outline = urdf_robot(urdf_xml, None, base, tip)
        chain = build_chain(urdf_xml, description.base_frame, description.tip_frame)
    except ModelError as exc:
        detail = str(exc).removeprefix("urdf: ")
        raise ModelError(f"{where}: {detail}, or pass --robot NAME / --urdf FILE instead") from exc
    typer.echo(
        f"robot: {where} ({outline.n_links} links; chain {description.base_frame} → "
        f"{description.tip_frame}, {len(chain.joint_names)} joints)",
        err=to_stderr,
    )
    return description


def _names(text: str | None) -> list[str] | None:
    return None if text is None else [n.strip() for n in text.split(",") if n.strip()]


def _vector3(text: str, option: str) -> tuple[float, float, float]:
    x, y, z = numbers(text, option, 3)
    return x, y, z


def _document_bytes(path: Path, what: str) -> bytes:
    """The bytes of a document (what: "calibration result"), read before its model is imported:
    a file that is not there is refused at once."""
    try:
        return path.read_bytes()
    except OSError as exc:
        raise KincalError(f"cannot read {what} {path}: {exc.strerror}") from exc


def _read_document(
    path: Path, data: bytes, model: type[DocumentT], what: str, producer: str
) -> DocumentT:
    """The JSON document of ``model`` in ``data`` (read from ``path``; producer: the command
    that writes it), with a one-line error naming the first bad field otherwise."""
    import pydantic

    try:
        return model.model_validate_json(data)
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise KincalError(
            f"{path} is not a kincal {what} ({where}: {first['msg']}); "
            f"pass the -o file of 'kincal {producer}'"
        ) from exc


def read_result(path: Path) -> CalibrationResult:
    """Load a result JSON written by ``kincal calibrate``, with a one-line error otherwise."""
    data = _document_bytes(path, "calibration result")
    from schemas.calibration import CalibrationResult

    return _read_document(path, data, CalibrationResult, "calibration result", "calibrate")


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
    data = _document_bytes(path, "findings file")
    from schemas.discovery import FindingsResult

    return _read_document(path, data, FindingsResult, "findings file", "discover")


def _integers(text: str, option: str) -> list[int]:
    values = numbers(text, option)
    if not all(v == int(v) for v in values):
        raise KincalError(f"{option} takes comma-separated integers, got {text!r}")
    return [int(v) for v in values]


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


def read_bag(
    bag: Path,
    joint_states: str | None,
    measure: str | None,
    still: tuple[float, float, float],
    chain: KinematicChain | None,
    capture: str | None = None,
) -> BagRecording:
    """The ROS bag ``bag`` as a recording (``schemas.dataset.rosbag``): ``still`` = tolerance
    rad/s, window s, clock tolerance s; ``chain``: the robot whose joints to match (None: every
    joint of the topic); ``capture``: the capture topic, if any."""
    from schemas.dataset.rosbag import MeasureSource, read_bag
    from schemas.dataset.still import StillSettings

    captures = measure is not None and measure.startswith("calibration-data:")
    if measure is None or (joint_states is None and not captures):
        raise KincalError(
            f"{bag.name} is a ROS bag: give --joint-states TOPIC and --measure SOURCE "
            "(e.g. --joint-states /joint_states --measure tf:camera_link:board), or --measure "
            "calibration-data:/calibration_data for robot_calibration's captures"
        )
    return read_bag(
        bag,
        joint_states,
        MeasureSource.parse(measure),
        joint_names=None if chain is None else chain.joint_names,
        other_joint_names=() if chain is None else chain.other_joint_names,
        settings=StillSettings(*still),
        capture=capture,
    )
