"""FIGAROH adapter: a file with ``x1,y1,z1`` (and optionally ``phix1,phiy1,phiz1``, roll-pitch-yaw
in rad, ``R = Rz(yaw)·Ry(pitch)·Rx(roll)`` as in ``pin.rpy.rpyToMatrix``) is read as marker 1.
Files with several markers need ``marker=N``; one dataset holds one marker."""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from schemas.dataset.columns import PoseColumns, listing
from schemas.dataset.records import POSITION_COLUMNS, QUATERNION_COLUMNS
from solver.errors import DatasetError

FIGAROH_COLUMN = re.compile(r"^(x|y|z|phix|phiy|phiz)([0-9]+)$")


def figaroh_markers(columns: Sequence[str]) -> dict[int, set[str]]:
    """Marker number → the FIGAROH axes (``x``, ``phix``, ...) the columns give for it."""
    markers: dict[int, set[str]] = {}
    for c in columns:
        if match := FIGAROH_COLUMN.match(c):
            markers.setdefault(int(match.group(2)), set()).add(match.group(1))
    return markers


def figaroh_pose_columns(
    columns: Sequence[str], markers: dict[int, set[str]], source: str, marker: int | None
) -> PoseColumns:
    """Pose columns of one FIGAROH marker (``marker``, or the only one in the file)."""
    clash = [c for c in (*POSITION_COLUMNS, *QUATERNION_COLUMNS) if c in columns]
    if clash:
        raise DatasetError(
            f"{source}: both kincal pose column(s) {listing(clash)} and FIGAROH marker "
            f"columns (x1,y1,z1,...) are present; keep only one of the two layouts"
        )
    numbers = sorted(markers)
    if marker is None and len(numbers) > 1:
        raise DatasetError(
            f"{source}: FIGAROH file has {len(numbers)} markers ({listing(numbers)}) but a "
            f"dataset holds one marker; pass marker=N (e.g. read_dataset(..., marker="
            f"{numbers[0]})) or split the file into one file per marker, each with the "
            f"joint columns and that marker's x/y/z (and phix/phiy/phiz) columns"
        )
    m = numbers[0] if marker is None else marker
    if m not in markers:
        raise DatasetError(
            f"{source}: marker {m} not in the file (markers found: {listing(numbers)}); "
            f"choose one of them"
        )
    missing = [f"{a}{m}" for a in ("x", "y", "z") if a not in markers[m]]
    if missing:
        raise DatasetError(
            f"{source}: FIGAROH marker {m} lacks column(s) {listing(missing)}; a marker "
            f"needs x{m},y{m},z{m} (m)"
        )
    rpy = [f"{a}{m}" for a in ("phix", "phiy", "phiz") if a in markers[m]]
    if rpy and len(rpy) < 3:
        absent = [f"{a}{m}" for a in ("phix", "phiy", "phiz") if a not in markers[m]]
        raise DatasetError(
            f"{source}: FIGAROH marker {m} has {listing(rpy)} but not {listing(absent)}; "
            f"give roll-pitch-yaw phix{m},phiy{m},phiz{m} (rad) together, or none"
        )
    used = frozenset(c for c in columns if FIGAROH_COLUMN.match(c))
    position = (f"x{m}", f"y{m}", f"z{m}")
    return PoseColumns(position, tuple(rpy), bool(rpy), used)


def rpy_to_quaternion_xyzw(rpy_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """Roll-pitch-yaw (N, 3) rad → quaternions (N, 4) ``x,y,z,w``; R = Rz(yaw)·Ry(pitch)·Rx(roll).

    Same convention as ``pin.rpy.rpyToMatrix`` (FIGAROH). Scipy's lower-case ``"xyz"`` is
    extrinsic, which composes to exactly that product.
    """
    from scipy.spatial.transform import Rotation  # 0.4 s to import: only for RPY files

    rotation = Rotation.from_euler("xyz", np.asarray(rpy_rad, dtype=np.float64))
    return rotation.as_quat(scalar_first=False)
