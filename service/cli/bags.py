"""``kincal import``: a ROS bag in, an ordinary recording out (docs/ros.md). rosbags, numpy
and pandas are imported inside the command."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from schemas.dataset.paths import bag_location
from service.cli.common import (
    CLOCK_TOLERANCE_S,
    STILL_TOLERANCE_RAD_S,
    STILL_WINDOW_S,
    BaseOpt,
    CaptureOpt,
    ClockToleranceOpt,
    DhOpt,
    JointStatesOpt,
    MeasureOpt,
    OutDirOpt,
    Outputs,
    RobotOpt,
    StillToleranceOpt,
    StillWindowOpt,
    TipOpt,
    UrdfOpt,
    _robot,
    bag_robot,
    out_dir_for,
    output_option,
    read_bag,
)
from solver.errors import KincalError


def import_command(
    bag: Annotated[
        Path,
        typer.Argument(
            help="A ROS 1 .bag file or a rosbag2 folder (sqlite3 or MCAP storage).",
            metavar="BAG",
            show_default=False,
        ),
    ],
    robot: RobotOpt = None,
    urdf: UrdfOpt = None,
    base: BaseOpt = None,
    tip: TipOpt = None,
    dh: DhOpt = None,
    joint_states: JointStatesOpt = None,
    measure: MeasureOpt = None,
    capture: CaptureOpt = None,
    still_tolerance: StillToleranceOpt = STILL_TOLERANCE_RAD_S,
    still_window: StillWindowOpt = STILL_WINDOW_S,
    clock_tolerance: ClockToleranceOpt = CLOCK_TOLERANCE_S,
    output: Annotated[
        Path | None, output_option("recording.parquet", "The recording (.csv, .parquet, .json)")
    ] = None,
    out_dir: OutDirOpt = None,
) -> None:
    """Turn a ROS bag into a recording: one sample per hold of the robot (joint states still
    for --still-window) or per --capture message, joints and measured pose averaged over it.

    With a robot (--robot/--urdf/--dh; without them, the URDF the bag carries on
    /robot_description, then written next to the recording) the joint-state names are matched
    to its chain joints and the columns are named by them; without, every joint of the topic is
    written. Prints the samples kept and the holds and messages dropped, per reason."""
    bag_location(bag, bag.name)
    from schemas.dataset import write_dataset
    from schemas.dataset.rosbag import ROBOT_DESCRIPTION_TOPIC

    recorded = robot is None and urdf is None and dh is None
    description = bag_robot(bag, base, tip) if recorded else _robot(robot, urdf, base, tip, dh)
    if description is None and (base is not None or tip is not None):
        raise KincalError(
            f"--base and --tip name frames of a robot: give --robot or --urdf (no URDF on "
            f"{ROBOT_DESCRIPTION_TOPIC} in {bag.name})"
        )
    outputs = Outputs(out_dir_for(out_dir, bag, "import"))
    path = outputs.path(output, "recording.parquet", "a recording")
    urdf_path = None
    if recorded and description is not None:
        urdf_path = _urdf_path(outputs, path.with_suffix(".urdf"), description.urdf_xml)
    chain = None
    if description is not None:
        from schemas.calibration import CalibrationOptions
        from service.render.chain import chain_for

        chain = chain_for(description, CalibrationOptions())
    still = (still_tolerance, still_window, clock_tolerance)
    recording = read_bag(bag, joint_states, measure, still, chain, capture)
    outputs.write(
        path,
        f"recording, {recording.dataset.n_samples} samples",
        lambda target: write_dataset(recording.dataset, target),
    )
    typer.echo(recording.report())
    if urdf_path is not None and description is not None:
        outputs.write_text(
            urdf_path, f"the robot's URDF (from {ROBOT_DESCRIPTION_TOPIC})", description.urdf_xml
        )
    typer.echo(outputs.listing())
    if urdf_path is not None and description is not None:
        typer.echo(
            f"next: kincal calibrate {path} --urdf {urdf_path} --base "
            f"{description.base_frame} --tip {description.tip_frame}"
        )


def _urdf_path(outputs: Outputs, path: Path, urdf_xml: str) -> Path:
    """Where the bag's URDF goes (next to the recording), refused before any work when a file
    there holds another text (a URDF of the user's is never replaced by the bag's)."""
    path = outputs.path(path, "", None)
    if path.exists() and path.read_bytes() != urdf_xml.encode("utf-8"):
        raise KincalError(
            f"{path} already holds another file; this command would replace it with the "
            "bag's URDF: give another output name (-o/--out-dir) or remove the file"
        )
    return path
