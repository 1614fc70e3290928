"""Tables (pandas) to validated arrays: every cell checked, each problem one line naming the
file, the data row (1 = first data row) and the column, with the fix."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from schemas.dataset.columns import (
    PoseColumns,
    check_duplicates,
    check_joint_names,
    contract_pose_columns,
    joint_columns,
    one_line,
    unit_quaternions,
)
from schemas.dataset.figaroh import (
    FIGAROH_COLUMN,
    figaroh_markers,
    figaroh_pose_columns,
    rpy_to_quaternion_xyzw,
)
from schemas.dataset.records import (
    CONTRACT_COLUMNS,
    FLOAT_FIELD_OF_COLUMN,
    OPTIONAL_FLOAT_COLUMNS,
    ConfigurationSet,
    PoseDataset,
)
from schemas.limits import (
    MAX_JOINT_POSITION,
    MAX_PAYLOAD_KG,
    MAX_POSITION_M,
    MAX_TIME_S,
    TEMPERATURE_RANGE_C,
)
from solver.errors import DatasetError

Range = tuple[float, float, str]  # lowest, highest, unit
JOINT_RANGE: Range = (-MAX_JOINT_POSITION, MAX_JOINT_POSITION, "rad (m if prismatic)")
POSITION_RANGE: Range = (-MAX_POSITION_M, MAX_POSITION_M, "m")
ANGLE_RANGE: Range = (-MAX_JOINT_POSITION, MAX_JOINT_POSITION, "rad")
QUATERNION_RANGE: Range = (-1e4, 1e4, "")  # beyond overflow's reach; the norm check says more
OPTIONAL_RANGES: dict[str, Range] = {
    "t": (-MAX_TIME_S, MAX_TIME_S, "s"),
    "temperature_c": (*TEMPERATURE_RANGE_C, "°C"),
    "payload_kg": (0.0, MAX_PAYLOAD_KG, "kg"),
}


def dataset_from_frame(
    frame: pd.DataFrame,
    joint_names: Sequence[str],
    *,
    source: str,
    other_joint_names: Sequence[str] = (),
    marker: int | None = None,
) -> PoseDataset:
    """Validate a table of measurements (columns as in the contract) and return its arrays.

    Same checks as :func:`schemas.dataset.read_dataset`; ``source`` names the table in error
    messages.
    """
    names = check_joint_names(joint_names)
    columns = [str(c).strip() for c in frame.columns]
    check_duplicates(columns, source)
    frame = frame.set_axis(columns, axis=1)
    if len(frame) == 0:
        raise DatasetError(f"{source}: no data rows (header only or empty); add measurements")
    pose = _pose_columns(columns, source, marker)
    joint_cols = joint_columns(columns, names, set(other_joint_names), pose.used, source)
    extra = [c for c in OPTIONAL_FLOAT_COLUMNS if c in columns]
    orientation_range = ANGLE_RANGE if pose.is_rpy else QUATERNION_RANGE
    ranges = [JOINT_RANGE] * len(joint_cols) + [POSITION_RANGE] * len(pose.position)
    ranges += [orientation_range] * len(pose.orientation) + [OPTIONAL_RANGES[c] for c in extra]
    block = _finite_block(frame, [*joint_cols, *pose.numeric, *extra], ranges, source)
    k, p = len(joint_cols), len(pose.numeric)
    position, orientation = block[:, k : k + 3], block[:, k + 3 : k + p]
    optional = {FLOAT_FIELD_OF_COLUMN[c]: block[:, k + p + i] for i, c in enumerate(extra)}
    if "time_s" in optional:
        _check_time(optional["time_s"], source)
    return PoseDataset(
        joint_names=names,
        joint_positions=block[:, :k],
        position_m=position,
        quaternion_xyzw=_quaternion_xyzw(pose, orientation, source),
        sample_id=_sample_ids(frame, source) if "sample_id" in columns else None,
        source=source,
        **optional,
    )


def configurations_from_frame(
    frame: pd.DataFrame,
    joint_names: Sequence[str],
    *,
    source: str,
    other_joint_names: Sequence[str] = (),
) -> ConfigurationSet:
    """Validate a table of joint configurations, same column rules as datasets."""
    names = check_joint_names(joint_names)
    columns = [str(c).strip() for c in frame.columns]
    check_duplicates(columns, source)
    frame = frame.set_axis(columns, axis=1)
    if len(frame) == 0:
        raise DatasetError(f"{source}: no data rows (header only or empty); add configurations")
    pose_like = frozenset(c for c in columns if c in CONTRACT_COLUMNS or FIGAROH_COLUMN.match(c))
    joint_cols = joint_columns(columns, names, set(other_joint_names), pose_like, source)
    extra = ["payload_kg"] if "payload_kg" in columns else []
    ranges = [JOINT_RANGE] * len(joint_cols) + [OPTIONAL_RANGES[c] for c in extra]
    block = _finite_block(frame, [*joint_cols, *extra], ranges, source)
    k = len(joint_cols)
    return ConfigurationSet(
        joint_names=names,
        joint_positions=block[:, :k],
        payload_kg=block[:, k] if extra else None,
        sample_id=_sample_ids(frame, source) if "sample_id" in columns else None,
        source=source,
    )


def _pose_columns(columns: Sequence[str], source: str, marker: int | None) -> PoseColumns:
    markers = figaroh_markers(columns)
    if not markers:
        return contract_pose_columns(columns, source)
    return figaroh_pose_columns(columns, markers, source, marker)


def _quaternion_xyzw(
    pose: PoseColumns, orientation: NDArray[np.float64], source: str
) -> NDArray[np.float64] | None:
    """Unit quaternions (N, 4) scalar last, from the orientation block, or None."""
    if not pose.orientation:
        return None
    if pose.is_rpy:
        return rpy_to_quaternion_xyzw(orientation)
    return unit_quaternions(orientation, source)


def _finite_block(
    frame: pd.DataFrame, columns: list[str], ranges: list[Range], source: str
) -> NDArray[np.float64]:
    """(N, len(columns)) float64 array; names the first non-numeric, missing, infinite or
    out-of-range cell (``ranges[j]`` bounds column j)."""
    block = np.column_stack([_numeric_column(frame[c], c, source) for c in columns])
    low = np.array([r[0] for r in ranges])
    high = np.array([r[1] for r in ranges])
    with np.errstate(invalid="ignore"):
        bad = np.isnan(block) | (block < low) | (block > high)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        col = int(np.flatnonzero(bad[row])[0])
        value = block[row, col]
        shown = _shown(frame[columns[col]].iloc[row])
        lowest, highest, unit = ranges[col]
        if np.isnan(value):
            problem = "value is missing (empty, null or NaN)"
        elif np.isinf(value):
            problem = f"value is infinite or beyond a float ({shown})"
        else:
            problem = f"value {shown} is out of range"
        raise DatasetError(
            f"{source}: data row {row + 1}, column {columns[col]}: {problem}; every used column "
            f"needs a number from {lowest:g} to {highest:g}{' ' + unit if unit else ''} in every "
            f"row (fix or delete the row)"
        )
    return block


def _shown(cell: Any) -> str:
    """A cell as a user wrote it, at most 24 characters."""
    text = f"{float(cell):g}" if isinstance(cell, float | np.floating) else one_line(cell)
    return text if len(text) <= 24 else text[:23] + "…"


def _numeric_column(series: pd.Series, name: str, source: str) -> NDArray[np.float64]:
    is_bool = pd.api.types.is_bool_dtype(series)
    if pd.api.types.is_numeric_dtype(series) and not is_bool:
        return series.to_numpy(dtype=np.float64, na_value=np.nan)
    try:
        numbers = pd.to_numeric(series, errors="coerce")
    except (TypeError, ValueError, OverflowError):  # nested values (JSON lists), huge integers
        numbers = pd.Series([_to_float(v) for v in series], index=series.index, dtype=float)
    rejected = series.notna().to_numpy() & (is_bool or numbers.isna().to_numpy())
    if rejected.any():
        row = int(np.flatnonzero(rejected)[0])
        shown = one_line(repr(series.iloc[row]))[:40]
        raise DatasetError(
            f"{source}: data row {row + 1}, column {name}: {shown} is not a number; write a "
            f"plain decimal number (units: rad or m)"
        )
    return numbers.to_numpy(dtype=np.float64, na_value=np.nan)


def _to_float(value: Any) -> float:
    try:
        return float(value)
    except OverflowError:  # an integer beyond float64: as good as infinite
        return -np.inf if value < 0 else np.inf
    except (TypeError, ValueError):
        return np.nan


def _check_time(time_s: NDArray[np.float64], source: str) -> None:
    back = np.flatnonzero(np.diff(time_s) < 0)
    if back.size:
        row = int(back[0]) + 2
        raise DatasetError(
            f"{source}: data row {row}, column t: time goes backwards ({float(time_s[row - 1])!r} "
            f"after {float(time_s[row - 2])!r} in data row {row - 1}); rows must be in execution "
            f"order with non-decreasing t (s)"
        )


MAX_SAMPLE_ID_CHARS = 256
_INT64 = np.iinfo(np.int64)


def _is_sample_id(value: Any) -> bool:
    if isinstance(value, str):
        return len(value) <= MAX_SAMPLE_ID_CHARS
    if isinstance(value, bool | np.bool_):
        return False
    if isinstance(value, int | np.integer):
        return bool(_INT64.min <= value <= _INT64.max)
    return isinstance(value, float | np.floating) and bool(np.isfinite(value))


def _sample_ids(frame: pd.DataFrame, source: str) -> NDArray[Any]:
    ids = frame["sample_id"]
    missing = ids.isna().to_numpy()
    if missing.any():
        row = int(np.flatnonzero(missing)[0])
        raise DatasetError(
            f"{source}: data row {row + 1}, column sample_id: value is missing; give every row "
            f"a sample_id or drop the column"
        )
    if ids.dtype == object or pd.api.types.is_bool_dtype(ids):
        for row, value in enumerate(ids):
            if not _is_sample_id(value):
                raise DatasetError(
                    f"{source}: data row {row + 1}, column sample_id: {_shown(value)} is not a "
                    f"sample id; write an integer (|n| < 2^63) or a text of at most "
                    f"{MAX_SAMPLE_ID_CHARS} characters"
                )
    dup = ids.duplicated().to_numpy()
    if dup.any():
        row = int(np.flatnonzero(dup)[0])
        first = int(np.flatnonzero((ids == ids.iloc[row]).to_numpy())[0])
        raise DatasetError(
            f"{source}: data row {row + 1}, column sample_id: {ids.iloc[row]!r} already used in "
            f"data row {first + 1}; sample ids must be unique"
        )
    values = ids.to_numpy()
    return values.astype(object) if values.dtype.kind not in "iuf" else values
