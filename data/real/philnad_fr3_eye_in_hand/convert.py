"""Convert the upstream FR3 recording into the kincal dataset contract.

``fr3_calib_data.csv`` (upstream layout, see PROVENANCE.md) → ``fr3_poses.csv`` with columns
``sample_id,q1..q7,x,y,z,qx,qy,qz,qw``. The measured pose is ``cam_T`` = pose of the camera
frame expressed in the calibration-board frame: the board is the measurement frame, the camera
is the marker rigidly mounted on the flange. ``tcp_T`` (the controller's own forward
kinematics) is left out. Quaternions are scalar last with ``qw >= 0``; floats are written as
``repr`` (shortest text that round-trips to the same float64).

Usage: ``python convert.py`` (rewrite fr3_poses.csv) or ``python convert.py --check`` (exit 1 if
the committed file differs from a fresh conversion).
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "fr3_calib_data.csv"
TARGET = HERE / "fr3_poses.csv"
JOINTS = [f"q{i}" for i in range(1, 8)]
COLUMNS = ["sample_id", *JOINTS, "x", "y", "z", "qx", "qy", "qz", "qw"]
ORTHONORMAL_TOL = 1e-9


def board_T_camera(raw: pd.DataFrame) -> NDArray[np.float64]:
    """(N, 4, 4) camera pose in the board frame from the row-major ``cam_T00..cam_T33``."""
    cells = [f"cam_T{r}{c}" for r in range(4) for c in range(4)]
    board_T_cam = raw[cells].to_numpy(dtype=np.float64).reshape(-1, 4, 4)
    rotation = board_T_cam[:, :3, :3]
    drift = np.abs(rotation @ rotation.transpose(0, 2, 1) - np.eye(3)).max()
    if drift > ORTHONORMAL_TOL or np.any(np.linalg.det(rotation) < 0):
        raise ValueError(f"cam_T rotations are not proper rotations (|RRᵀ - I| = {drift:.2g})")
    if np.any(board_T_cam[:, 3] != [0.0, 0.0, 0.0, 1.0]):
        raise ValueError("cam_T last rows are not [0, 0, 0, 1]")
    return board_T_cam


def convert(raw: pd.DataFrame) -> pd.DataFrame:
    """Upstream table → kincal table (one row per sample, order kept)."""
    board_T_cam = board_T_camera(raw)
    quat_xyzw = Rotation.from_matrix(board_T_cam[:, :3, :3]).as_quat(canonical=True)
    out = pd.DataFrame({"sample_id": raw["sample"].to_numpy()})
    for name in JOINTS:
        out[name] = raw[name].to_numpy(dtype=np.float64)
    for i, name in enumerate(("x", "y", "z")):
        out[name] = board_T_cam[:, i, 3]
    for i, name in enumerate(("qx", "qy", "qz", "qw")):
        out[name] = quat_xyzw[:, i]
    return out[COLUMNS]


def to_csv_text(table: pd.DataFrame) -> str:
    """CSV text with ``repr`` floats (exact round trip) and integer sample ids."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for sample_id, *values in table[COLUMNS].itertuples(index=False):
        writer.writerow([int(sample_id), *(repr(float(v)) for v in values)])
    return buffer.getvalue()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with fr3_poses.csv only")
    args = parser.parse_args(argv)
    raw = pd.read_csv(SOURCE)  # pandas >= 3 parses floats exactly (round trip)
    text = to_csv_text(convert(raw))
    if args.check:
        same = TARGET.is_file() and TARGET.read_text(encoding="utf-8") == text
        print(f"{TARGET.name}: {'up to date' if same else 'differs from a fresh conversion'}")
        return 0 if same else 1
    TARGET.write_text(text, encoding="utf-8")
    print(f"wrote {TARGET.name}: {len(raw)} samples")
    return 0


if __name__ == "__main__":
    sys.exit(main())
