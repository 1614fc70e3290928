"""The industrial_calibration YAML recording (ros-industrial/industrial_calibration's
kinematic-calibration examples) as a table of the dataset contract.

A YAML map keyed by time stamp (s); each entry holds ``target_joints`` (the joint readings of
the chain carrying the target, in chain order: rad, m for prismatic joints), ``camera_joints``
(the chain carrying the sensor; must be empty: kincal's measurement frame is fixed) and ``pose``:
``x, y, z`` (m) and ``qw, qx, qy, qz`` of the target in the sensor's frame. Rows come out sorted
by time stamp with columns ``t, q1..qk, x, y, z, qx, qy, qz, qw``.
"""

from __future__ import annotations

import math
from typing import IO, Any

import pandas as pd
import yaml

from solver.errors import DatasetError

POSE_KEYS = ("x", "y", "z", "qx", "qy", "qz", "qw")


def read_industrial_yaml(handle: IO[str], source: str) -> pd.DataFrame:
    """The recording as a table (see module docstring); one-line :class:`DatasetError`
    naming the time stamp and key otherwise."""
    try:
        document = yaml.safe_load(handle)
    except yaml.YAMLError as exc:
        raise DatasetError(f"{source}: not YAML ({str(exc).splitlines()[0]})") from exc
    if not isinstance(document, dict) or not document:
        raise DatasetError(
            f"{source}: expected a YAML map of time stamp -> {{target_joints, camera_joints, "
            "pose}} (industrial_calibration's kinematic calibration format)"
        )
    rows = [_row(stamp, entry, source) for stamp, entry in document.items()]
    counts = {len(row) for row in rows}
    if len(counts) != 1:
        raise DatasetError(
            f"{source}: entries have different numbers of target_joints; every entry must "
            "list the same joints"
        )
    frame = pd.DataFrame(rows).sort_values("t", kind="stable").reset_index(drop=True)
    return frame


def _row(stamp: Any, entry: Any, source: str) -> dict[str, float]:
    where = f"{source}: entry {stamp!r}"
    try:
        time_s = float(stamp)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: the key must be a time stamp (a number)") from None
    if not isinstance(entry, dict):
        raise DatasetError(f"{where}: expected target_joints, camera_joints and pose")
    if entry.get("camera_joints"):
        raise DatasetError(
            f"{where}: camera_joints is not empty: a sensor carried by a moving chain is not "
            "supported; kincal calibrates a fixed measurement frame (camera_joints: [])"
        )
    joints = entry.get("target_joints")
    pose = entry.get("pose")
    if not isinstance(joints, list) or not joints:
        raise DatasetError(f"{where}: target_joints must be a non-empty list of joint readings")
    if not isinstance(pose, dict) or any(key not in pose for key in POSE_KEYS):
        missing = [k for k in POSE_KEYS if not isinstance(pose, dict) or k not in pose]
        raise DatasetError(f"{where}: pose is missing {', '.join(missing)}")
    row = {"t": time_s}
    for i, value in enumerate(joints, start=1):
        row[f"q{i}"] = _number(value, f"{where}: target_joints[{i - 1}]")
    for key in POSE_KEYS:
        row[key] = _number(pose[key], f"{where}: pose.{key}")
    return row


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(f"{where}: must be a finite number, got {value!r}")
    return float(value)
