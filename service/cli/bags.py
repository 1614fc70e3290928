"""``kincal import``: a ROS bag in, an ordinary recording out (docs/ros.md). rosbags, numpy
and pandas are imported inside the command."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

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
    out_dir_for,
    output_option,
    read_bag,
)


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

    With a robot (--robot/--urdf/--dh) the joint-state names are matched to its chain joints
    and the columns are named by them; without, every joint of the topic is written. Prints the
    samples kept and the holds and messages dropped, per reason."""
    from schemas.dataset import write_dataset

    chain = None
    if robot is not None or urdf is not None or dh is not None:
        from schemas.calibration import CalibrationOptions
        from service.render.chain import chain_for

        chain = chain_for(_robot(robot, urdf, base, tip, dh), CalibrationOptions())
    still = (still_tolerance, still_window, clock_tolerance)
    recording = read_bag(bag, joint_states, measure, still, chain, capture)
    outputs = Outputs(out_dir_for(out_dir, bag, "import"))
    path = outputs.path(output, "recording.parquet", "a recording")
    outputs.write(
        path,
        f"recording, {recording.dataset.n_samples} samples",
        lambda target: write_dataset(recording.dataset, target),
    )
    typer.echo(recording.report())
    typer.echo(outputs.listing())
