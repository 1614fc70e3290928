"""Which files kincal reads, judged from the path alone (no pandas, numpy or rosbags): a
command refuses a missing file or an unknown format before it loads anything heavy."""

from __future__ import annotations

from pathlib import Path

from solver.errors import DatasetError

SUFFIXES = (".csv", ".parquet", ".json")
"""The formats kincal writes and reads."""
READ_SUFFIXES = (*SUFFIXES, ".yaml", ".yml")
"""What the readers take: the writable formats and industrial_calibration's YAML recordings."""
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
"""A ROS 1 bag file, or a storage file inside a rosbag2 folder."""


def is_bag(path: Path) -> bool:
    """A ROS 1 bag file, a rosbag2 folder (``metadata.yaml``) or a storage file inside one."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


def check_dataset_path(path: Path, source: str) -> str:
    """The lower-case suffix of a dataset file that exists; a one-line error otherwise."""
    suffix = path.suffix.lower()
    if suffix not in READ_SUFFIXES:
        raise DatasetError(
            f"{source}: unsupported file type {path.suffix or '(no suffix)'!r}; "
            f"save it as one of {', '.join(READ_SUFFIXES)}"
        )
    if not path.is_file():
        problem = "is a directory" if path.is_dir() else "file not found"
        raise DatasetError(f"{source}: {problem} ({path}); check the path")
    return suffix


def bag_location(path: Path, source: str) -> Path:
    """What a ROS bag reader opens: a ROS 1 ``.bag`` file or a rosbag2 folder (a storage file
    inside one stands for its folder); a one-line error when it is not there."""
    if path.is_file() and path.suffix.lower() in (".mcap", ".db3"):
        if not (path.parent / "metadata.yaml").is_file():
            raise DatasetError(
                f"{source}: no metadata.yaml next to it; pass the rosbag2 folder that holds it"
            )
        path = path.parent
    if not path.exists():
        raise DatasetError(f"{source}: file not found ({path}); check the path")
    return path


def check_recording_path(path: Path) -> None:
    """A recording argument that can be read, as far as its path tells: a ROS bag that is
    there (:func:`bag_location`) or a dataset file (:func:`check_dataset_path`); one line
    naming the file otherwise. A folder (rosbag2, ball-in-socket) is left to its reader."""
    if is_bag(path):
        bag_location(path, path.name)
    elif not path.is_dir():
        check_dataset_path(path, path.name)


def check_fleet_folder(folder: Path) -> None:
    """A fleet's folder of datasets (one per robot serial, :func:`service.app.fleet.
    fleet_datasets`) that is a folder; one line otherwise."""
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a folder; pass a folder with one dataset per robot")


def check_results_folder(folder: Path) -> None:
    """The folder of a fleet's calibration results (``kincal fleet --check``) that is a
    folder; one line otherwise."""
    if not folder.is_dir():
        raise DatasetError(
            f"--check {folder}: not a folder; give the folder of the units' results "
            "(<unit>.json, as kincal fleet --results-dir writes them)"
        )
