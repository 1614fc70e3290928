"""Which columns of a table hold what: the measured pose (kincal contract layout), the joint
readings (URDF names or ``q1..qk``), and the one-line messages naming wrong columns."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.dataset.records import CONTRACT_COLUMNS, POSITION_COLUMNS, QUATERNION_COLUMNS
from solver.errors import DatasetError, JointColumnsError

QUATERNION_NORM_TOL = 1e-3
"""Largest accepted | |q| - 1 |; quaternions within it are re-normalised silently."""

_Q_STYLE = re.compile(r"^q([1-9][0-9]*)$")
_MAX_LISTED = 12


@dataclass(frozen=True)
class PoseColumns:
    """Which file columns hold the measured pose (contract or FIGAROH marker)."""

    position: tuple[str, str, str]
    orientation: tuple[str, ...]  # 4 quaternion columns, 3 rpy columns, or none
    is_rpy: bool
    used: frozenset[str]  # every column consumed or deliberately ignored by the pose

    @property
    def numeric(self) -> tuple[str, ...]:
        return (*self.position, *self.orientation)


def contract_pose_columns(columns: Sequence[str], source: str) -> PoseColumns:
    """Pose columns of the kincal layout: ``x,y,z`` and optionally all of ``qx,qy,qz,qw``."""
    missing = [c for c in POSITION_COLUMNS if c not in columns]
    if missing:
        raise DatasetError(
            f"{source}: missing position column(s) {listing(missing)}; the measured marker "
            f"position needs x,y,z (m, measurement frame), or FIGAROH-style x1,y1,z1"
        )
    quat = [c for c in QUATERNION_COLUMNS if c in columns]
    if quat and len(quat) < 4:
        absent = [c for c in QUATERNION_COLUMNS if c not in columns]
        raise DatasetError(
            f"{source}: column(s) {listing(quat)} present but {listing(absent)} missing; "
            f"give all four qx,qy,qz,qw (unit quaternion, scalar last) or none of them "
            f"for a position-only dataset"
        )
    orientation = QUATERNION_COLUMNS if quat else ()
    return PoseColumns(POSITION_COLUMNS, orientation, False, frozenset((*POSITION_COLUMNS, *quat)))


def unit_quaternions(quat: NDArray[np.float64], source: str) -> NDArray[np.float64]:
    """Quaternions (N, 4) scalar last, re-normalised within :data:`QUATERNION_NORM_TOL`."""
    norm = np.linalg.norm(quat, axis=1)
    bad = np.abs(norm - 1.0) > QUATERNION_NORM_TOL
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DatasetError(
            f"{source}: data row {row + 1}, columns qx,qy,qz,qw: quaternion is not unit-norm "
            f"(|q| = {norm[row]:.6g}, tolerance {QUATERNION_NORM_TOL:g}); write unit "
            f"quaternions, scalar last (qx,qy,qz,qw)"
        )
    # Rows already unit to rounding are kept bit-exact, so write → read round-trips exactly.
    unit_to_rounding = np.abs(norm - 1.0) <= 8 * np.finfo(np.float64).eps
    return quat / np.where(unit_to_rounding, 1.0, norm)[:, None]


def check_joint_names(joint_names: Sequence[str]) -> tuple[str, ...]:
    names = tuple(str(n) for n in joint_names)
    if not names or len(set(names)) != len(names):
        raise ValueError(f"joint_names must be non-empty and unique, got {names!r}")
    return names


def check_duplicates(columns: Sequence[str], source: str) -> None:
    dups = duplicates(columns)
    if dups:
        raise DatasetError(
            f"{source}: duplicate column name(s) {listing(dups)} in the header; "
            f"give each column once"
        )


def joint_columns(
    columns: Sequence[str],
    names: tuple[str, ...],
    ignored: set[str],
    pose_columns: frozenset[str],
    source: str,
) -> list[str]:
    """Columns holding the k joint readings, in chain order (URDF names or q1..qk)."""
    rest = [c for c in columns if c not in pose_columns and c not in CONTRACT_COLUMNS]
    by_name = [c for c in rest if c in names]
    free = [c for c in rest if c not in names and c not in ignored]
    q_style = [c for c in free if _Q_STYLE.match(c)]
    unknown = [c for c in free if not _Q_STYLE.match(c)]
    if by_name and q_style:
        raise JointColumnsError(
            f"{source}: mixes URDF joint columns ({listing(by_name)}) with q-style columns "
            f"({listing(q_style)}); name all joints one way: {listing(names)} "
            f"or q1..q{len(names)}"
        )
    if q_style:
        _check_q_style(q_style, names, source)
        joint_cols = [f"q{i}" for i in range(1, len(names) + 1)]
    else:
        _check_named(by_name, names, unknown, source)
        joint_cols = list(names)
    if unknown:
        hint = ""
        if any(c.startswith("Unnamed:") or not c for c in unknown):
            hint = " (an unnamed column usually means the file was saved with its index)"
        raise DatasetError(
            f"{source}: unknown column(s) {listing(unknown)}{hint}: not a joint of this robot "
            f"({listing(names)}) nor a kincal column ({listing(CONTRACT_COLUMNS)}); remove "
            f"them, or pass joints off the calibrated chain as other_joint_names"
        )
    return joint_cols


def _check_q_style(q_style: list[str], names: tuple[str, ...], source: str) -> None:
    k = len(names)
    found = sorted(int(_Q_STYLE.match(c).group(1)) for c in q_style)  # type: ignore[union-attr]
    if found == list(range(1, k + 1)):
        return
    missing = [f"q{i}" for i in range(1, k + 1) if i not in found]
    beyond = [f"q{i}" for i in found if i > k]
    parts = ([f"missing {listing(missing)}"] if missing else []) + (
        [f"{listing(beyond)} beyond the last joint"] if beyond else []
    )
    raise JointColumnsError(
        f"{source}: q-style joint columns {listing([f'q{i}' for i in found])} do not match the "
        f"robot's {k} joints ({'; '.join(parts)}); write exactly q1..q{k} for "
        f"{listing(names)} in chain order"
    )


def _check_named(
    by_name: list[str], names: tuple[str, ...], unknown: list[str], source: str
) -> None:
    missing = [n for n in names if n not in by_name]
    if not missing:
        return
    seen = f"; unrecognised column(s) present: {listing(unknown)}" if unknown else ""
    raise JointColumnsError(
        f"{source}: missing joint column(s) {listing(missing)}{seen}; expected one column per "
        f"joint named {listing(names)}, or q1..q{len(names)} in chain order"
    )


def duplicates(items: Sequence[str]) -> list[str]:
    return [item for item, count in Counter(items).items() if count > 1]


def listing(items: Sequence[Any]) -> str:
    shown = ",".join(str(i) for i in items[:_MAX_LISTED])
    more = f" (+{len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return shown + more


def one_line(obj: object) -> str:
    return " ".join(str(obj).split())
