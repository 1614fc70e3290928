"""Measurement datasets: files (CSV / Parquet / JSON) to plain arrays, with one-line errors.

Contract (DESIGN.md §3 "Dataset"): one row per measurement, rows in execution order;
joint columns named after the URDF joints (or ``q1..qk`` in chain order), rad (m for prismatic
joints); the measured marker/tool position ``x,y,z`` (m, measurement frame) and optionally its
orientation as a unit quaternion ``qx,qy,qz,qw`` (scalar LAST); optional ``sample_id``,
``t`` (s, non-decreasing), ``temperature_c``, ``payload_kg``. ``sample_id`` is kept as read: in
CSV, ids that look like integers come back as integers.

FIGAROH adapter: a file with ``x1,y1,z1`` (and optionally ``phix1,phiy1,phiz1``, roll-pitch-yaw
in rad, ``R = Rz(yaw)·Ry(pitch)·Rx(roll)`` as in ``pin.rpy.rpyToMatrix``) is read as marker 1.
Files with several markers need ``marker=N``; one dataset holds one marker.

Every problem raises :class:`solver.errors.DatasetError` with ONE line
``<file>: data row R, column C: <problem>; <fix>``. Rows are numbered from 1 = first data row
(the header is not counted).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from solver.errors import DatasetError

POSITION_COLUMNS = ("x", "y", "z")
QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw")
OPTIONAL_FLOAT_COLUMNS = ("t", "temperature_c", "payload_kg")
CONTRACT_COLUMNS = (*POSITION_COLUMNS, *QUATERNION_COLUMNS, "sample_id", *OPTIONAL_FLOAT_COLUMNS)
SUFFIXES = (".csv", ".parquet", ".json")
QUATERNION_NORM_TOL = 1e-3
"""Largest accepted | |q| - 1 |; quaternions within it are re-normalised silently."""

_Q_STYLE = re.compile(r"^q([1-9][0-9]*)$")
_FIGAROH = re.compile(r"^(x|y|z|phix|phiy|phiz)([0-9]+)$")
_MAX_LISTED = 12
# pandas < 3 parses CSV floats to within 1 ulp unless asked; pandas 3 is exact and deprecates it.
_EXACT_FLOATS: dict[str, str] = (
    {"float_precision": "round_trip"} if int(pd.__version__.split(".")[0]) < 3 else {}
)


@dataclass(frozen=True, eq=False)
class PoseDataset:
    """Joint readings and measured marker poses, as arrays, rows in execution order.

    ``joint_positions[n, i]`` is joint ``joint_names[i]`` (chain order) in rad (m if prismatic);
    ``position_m[n]`` and ``quaternion_xyzw[n]`` are the marker pose in the measurement frame
    (unit quaternion, scalar last). ``quaternion_xyzw is None`` marks a position-only dataset.
    """

    joint_names: tuple[str, ...]
    joint_positions: NDArray[np.float64]
    position_m: NDArray[np.float64]
    quaternion_xyzw: NDArray[np.float64] | None
    sample_id: NDArray[Any] | None = None
    time_s: NDArray[np.float64] | None = None
    temperature_c: NDArray[np.float64] | None = None
    payload_kg: NDArray[np.float64] | None = None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        for name in ("joint_positions", "position_m", "quaternion_xyzw", *_ROW_FLOAT_FIELDS):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, np.asarray(value, dtype=np.float64))
        if self.sample_id is not None:
            object.__setattr__(self, "sample_id", np.asarray(self.sample_id))
        self._check_shapes()

    def _check_shapes(self) -> None:
        n, k = self.joint_positions.shape if self.joint_positions.ndim == 2 else (-1, -1)
        if k != len(self.joint_names):
            raise DatasetError(
                f"{self.source}: joint_positions has shape {self.joint_positions.shape} but "
                f"there are {len(self.joint_names)} joint names; expected (N, "
                f"{len(self.joint_names)})"
            )
        expected: dict[str, tuple[int, ...]] = {"position_m": (n, 3), "quaternion_xyzw": (n, 4)}
        expected |= {name: (n,) for name in ("sample_id", *_ROW_FLOAT_FIELDS)}
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and value.shape != shape:
                raise DatasetError(
                    f"{self.source}: {name} has shape {value.shape}, expected {shape} "
                    f"(N = {n} samples)"
                )

    @property
    def n_samples(self) -> int:
        """Number of measurements N."""
        return int(self.joint_positions.shape[0])

    @property
    def n_joints(self) -> int:
        """Number of calibrated joints k."""
        return len(self.joint_names)

    @property
    def is_position_only(self) -> bool:
        """True when no orientation was measured (3-D residuals only)."""
        return self.quaternion_xyzw is None

    def subset(self, indices: Sequence[int] | NDArray[Any]) -> PoseDataset:
        """Rows ``indices`` (integers or a boolean mask), kept in execution (file) order."""
        idx = np.asarray(indices)
        idx = np.flatnonzero(idx) if idx.dtype == bool else np.sort(idx.astype(np.intp))
        if idx.size > 1 and np.any(np.diff(idx) == 0):
            raise ValueError("subset: duplicate row indices")
        picked: dict[str, Any] = {
            f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[idx]
            for f in fields(self)
            if f.name not in ("joint_names", "source")
        }
        return PoseDataset(joint_names=self.joint_names, source=self.source, **picked)


_ROW_FLOAT_FIELDS = ("time_s", "temperature_c", "payload_kg")
_FLOAT_FIELD_OF_COLUMN = dict(zip(OPTIONAL_FLOAT_COLUMNS, _ROW_FLOAT_FIELDS, strict=True))


# ---------------------------------------------------------------------------------------------
# Reading


def read_dataset(
    path: str | Path,
    joint_names: Sequence[str],
    *,
    other_joint_names: Sequence[str] = (),
    marker: int | None = None,
    source: str | None = None,
) -> PoseDataset:
    """Read a CSV / Parquet / JSON dataset (format by suffix) and validate it.

    ``joint_names``: the calibrated chain's URDF joints, in chain order; ``other_joint_names``:
    URDF joints off the chain whose columns are accepted and ignored; ``marker``: which FIGAROH
    marker to use when the file has several; ``source``: name used in messages (default: the
    file name).
    """
    path = Path(path)
    source = source or path.name
    frame = _read_frame(path, source)
    return dataset_from_frame(
        frame, joint_names, source=source, other_joint_names=other_joint_names, marker=marker
    )


def _read_frame(path: Path, source: str) -> pd.DataFrame:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise DatasetError(
            f"{source}: unsupported file type {path.suffix or '(no suffix)'!r}; "
            f"save it as one of {', '.join(SUFFIXES)}"
        )
    if not path.is_file():
        problem = "is a directory" if path.is_dir() else "file not found"
        raise DatasetError(f"{source}: {problem} ({path}); check the path")
    reader = {".csv": _read_csv, ".parquet": _read_parquet, ".json": _read_json}[suffix]
    try:
        return reader(path, source)
    except DatasetError:
        raise
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{source}: not UTF-8 text ({exc.reason}); save it as UTF-8") from exc
    except Exception as exc:  # any reader failure becomes one line, never a pandas traceback
        raise DatasetError(
            f"{source}: cannot read as {suffix[1:]} ({type(exc).__name__}: {_one_line(exc)}); "
            f"check that the file is a valid {suffix[1:]} file"
        ) from exc


def _read_csv(path: Path, source: str) -> pd.DataFrame:
    with path.open(newline="", encoding="utf-8-sig") as handle:
        header = next(csv.reader(handle), None)
    if not header or all(not cell.strip() for cell in header):
        raise DatasetError(
            f"{source}: file is empty; expected a header row such as "
            f"q1,...,qk,x,y,z,qx,qy,qz,qw followed by one row per measurement"
        )
    _check_duplicates([cell.strip() for cell in header], source)
    try:
        frame = pd.read_csv(
            path,
            encoding="utf-8-sig",
            skipinitialspace=True,
            low_memory=False,
            **_EXACT_FLOATS,
        )
    except pd.errors.ParserError as exc:
        match = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", str(exc))
        if match is None:
            raise
        fields_expected, line, seen = (int(g) for g in match.groups())
        raise DatasetError(
            f"{source}: data row {line - 1} (line {line}) has {seen} values but the header has "
            f"{fields_expected} columns; make every row match the header"
        ) from exc
    return frame.set_axis([str(c).strip() for c in frame.columns], axis=1)


def _read_parquet(path: Path, source: str) -> pd.DataFrame:
    return pd.read_parquet(path)


class _DuplicateKeyError(ValueError):
    pass


def _object_without_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        raise _DuplicateKeyError(_duplicates([key for key, _ in pairs])[0])
    return obj


def _read_json(path: Path, source: str) -> pd.DataFrame:
    try:
        with path.open(encoding="utf-8-sig") as handle:
            document = json.load(handle, object_pairs_hook=_object_without_duplicates)
    except _DuplicateKeyError as exc:
        raise DatasetError(
            f"{source}: column {exc.args[0]!r} appears twice in one row object; "
            f"give each column once"
        ) from exc
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{source}: malformed JSON ({exc}); fix the JSON syntax") from exc
    rows = document.get("samples") if isinstance(document, dict) else document
    if not isinstance(rows, list):
        raise DatasetError(
            f"{source}: expected a JSON array of row objects or an object with key "
            f"'samples' holding that array; found {type(document).__name__}"
            + (" without key 'samples'" if isinstance(document, dict) else "")
        )
    not_objects = [i for i, row in enumerate(rows) if not isinstance(row, dict)][:1]
    if not_objects:
        raise DatasetError(
            f"{source}: data row {not_objects[0] + 1} is not a JSON object; write each row as "
            f'{{"column": value, ...}}'
        )
    if not rows:
        return pd.DataFrame()
    return pd.DataFrame.from_records(rows)


# ---------------------------------------------------------------------------------------------
# Validation


def dataset_from_frame(
    frame: pd.DataFrame,
    joint_names: Sequence[str],
    *,
    source: str,
    other_joint_names: Sequence[str] = (),
    marker: int | None = None,
) -> PoseDataset:
    """Validate a table of measurements (columns as in the contract) and return its arrays.

    Same checks as :func:`read_dataset`; ``source`` names the table in error messages.
    """
    names = _check_joint_names(joint_names)
    columns = [str(c).strip() for c in frame.columns]
    _check_duplicates(columns, source)
    frame = frame.set_axis(columns, axis=1)
    if len(frame) == 0:
        raise DatasetError(f"{source}: no data rows (header only or empty); add measurements")
    pose = _PoseColumns.detect(columns, source, marker)
    joint_cols = _joint_columns(columns, names, set(other_joint_names), pose.used, source)
    extra = [c for c in OPTIONAL_FLOAT_COLUMNS if c in columns]
    block = _finite_block(frame, [*joint_cols, *pose.numeric, *extra], source)
    k, p = len(joint_cols), len(pose.numeric)
    position, orientation = block[:, k : k + 3], block[:, k + 3 : k + p]
    optional = {_FLOAT_FIELD_OF_COLUMN[c]: block[:, k + p + i] for i, c in enumerate(extra)}
    if "time_s" in optional:
        _check_time(optional["time_s"], source)
    return PoseDataset(
        joint_names=names,
        joint_positions=block[:, :k],
        position_m=position,
        quaternion_xyzw=pose.quaternion_xyzw(orientation, source),
        sample_id=_sample_ids(frame, source) if "sample_id" in columns else None,
        source=source,
        **optional,
    )


@dataclass(frozen=True, eq=False)
class ConfigurationSet:
    """Joint configurations without measurements (input of ``predict`` and ``rank``).

    ``joint_positions`` (N, k) in chain order, rad (m if prismatic); ``payload_kg`` (N,) if the
    file has that column.
    """

    joint_names: tuple[str, ...]
    joint_positions: NDArray[np.float64]
    payload_kg: NDArray[np.float64] | None = None
    sample_id: NDArray[Any] | None = None
    source: str = "<memory>"

    @property
    def n_samples(self) -> int:
        return int(self.joint_positions.shape[0])


def read_configurations(
    path: str | Path,
    joint_names: Sequence[str],
    *,
    other_joint_names: Sequence[str] = (),
    source: str | None = None,
) -> ConfigurationSet:
    """Read joint configurations (CSV / Parquet / JSON). Measured-pose columns, if present,
    are ignored, so a recorded dataset is also a valid configuration file."""
    path = Path(path)
    source = source or path.name
    return configurations_from_frame(
        _read_frame(path, source), joint_names, source=source, other_joint_names=other_joint_names
    )


def configurations_from_frame(
    frame: pd.DataFrame,
    joint_names: Sequence[str],
    *,
    source: str,
    other_joint_names: Sequence[str] = (),
) -> ConfigurationSet:
    """Validate a table of joint configurations, same column rules as datasets."""
    names = _check_joint_names(joint_names)
    columns = [str(c).strip() for c in frame.columns]
    _check_duplicates(columns, source)
    frame = frame.set_axis(columns, axis=1)
    if len(frame) == 0:
        raise DatasetError(f"{source}: no data rows (header only or empty); add configurations")
    pose_like = frozenset(c for c in columns if c in CONTRACT_COLUMNS or _FIGAROH.match(c))
    joint_cols = _joint_columns(columns, names, set(other_joint_names), pose_like, source)
    extra = ["payload_kg"] if "payload_kg" in columns else []
    block = _finite_block(frame, [*joint_cols, *extra], source)
    k = len(joint_cols)
    return ConfigurationSet(
        joint_names=names,
        joint_positions=block[:, :k],
        payload_kg=block[:, k] if extra else None,
        sample_id=_sample_ids(frame, source) if "sample_id" in columns else None,
        source=source,
    )


def _check_joint_names(joint_names: Sequence[str]) -> tuple[str, ...]:
    names = tuple(str(n) for n in joint_names)
    if not names or len(set(names)) != len(names):
        raise ValueError(f"joint_names must be non-empty and unique, got {names!r}")
    return names


def _check_duplicates(columns: Sequence[str], source: str) -> None:
    dups = _duplicates(columns)
    if dups:
        raise DatasetError(
            f"{source}: duplicate column name(s) {_listing(dups)} in the header; "
            f"give each column once"
        )


@dataclass(frozen=True)
class _PoseColumns:
    """Which file columns hold the measured pose (contract or FIGAROH marker)."""

    position: tuple[str, str, str]
    orientation: tuple[str, ...]  # 4 quaternion columns, 3 rpy columns, or none
    is_rpy: bool
    used: frozenset[str]  # every column consumed or deliberately ignored by the pose

    @property
    def numeric(self) -> tuple[str, ...]:
        return (*self.position, *self.orientation)

    @classmethod
    def detect(cls, columns: Sequence[str], source: str, marker: int | None) -> _PoseColumns:
        markers: dict[int, set[str]] = {}
        for c in columns:
            if match := _FIGAROH.match(c):
                markers.setdefault(int(match.group(2)), set()).add(match.group(1))
        if not markers:
            return cls._contract(columns, source)
        return cls._figaroh(columns, markers, source, marker)

    @classmethod
    def _contract(cls, columns: Sequence[str], source: str) -> _PoseColumns:
        missing = [c for c in POSITION_COLUMNS if c not in columns]
        if missing:
            raise DatasetError(
                f"{source}: missing position column(s) {_listing(missing)}; the measured marker "
                f"position needs x,y,z (m, measurement frame), or FIGAROH-style x1,y1,z1"
            )
        quat = [c for c in QUATERNION_COLUMNS if c in columns]
        if quat and len(quat) < 4:
            absent = [c for c in QUATERNION_COLUMNS if c not in columns]
            raise DatasetError(
                f"{source}: column(s) {_listing(quat)} present but {_listing(absent)} missing; "
                f"give all four qx,qy,qz,qw (unit quaternion, scalar last) or none of them "
                f"for a position-only dataset"
            )
        orientation = QUATERNION_COLUMNS if quat else ()
        return cls(POSITION_COLUMNS, orientation, False, frozenset((*POSITION_COLUMNS, *quat)))

    @classmethod
    def _figaroh(
        cls, columns: Sequence[str], markers: dict[int, set[str]], source: str, marker: int | None
    ) -> _PoseColumns:
        clash = [c for c in (*POSITION_COLUMNS, *QUATERNION_COLUMNS) if c in columns]
        if clash:
            raise DatasetError(
                f"{source}: both kincal pose column(s) {_listing(clash)} and FIGAROH marker "
                f"columns (x1,y1,z1,...) are present; keep only one of the two layouts"
            )
        numbers = sorted(markers)
        if marker is None and len(numbers) > 1:
            raise DatasetError(
                f"{source}: FIGAROH file has {len(numbers)} markers ({_listing(numbers)}) but a "
                f"dataset holds one marker; pass marker=N (e.g. read_dataset(..., marker="
                f"{numbers[0]})) or split the file into one file per marker, each with the "
                f"joint columns and that marker's x/y/z (and phix/phiy/phiz) columns"
            )
        m = numbers[0] if marker is None else marker
        if m not in markers:
            raise DatasetError(
                f"{source}: marker {m} not in the file (markers found: {_listing(numbers)}); "
                f"choose one of them"
            )
        missing = [f"{a}{m}" for a in ("x", "y", "z") if a not in markers[m]]
        if missing:
            raise DatasetError(
                f"{source}: FIGAROH marker {m} lacks column(s) {_listing(missing)}; a marker "
                f"needs x{m},y{m},z{m} (m)"
            )
        rpy = [f"{a}{m}" for a in ("phix", "phiy", "phiz") if a in markers[m]]
        if rpy and len(rpy) < 3:
            absent = [f"{a}{m}" for a in ("phix", "phiy", "phiz") if a not in markers[m]]
            raise DatasetError(
                f"{source}: FIGAROH marker {m} has {_listing(rpy)} but not {_listing(absent)}; "
                f"give roll-pitch-yaw phix{m},phiy{m},phiz{m} (rad) together, or none"
            )
        used = frozenset(c for c in columns if _FIGAROH.match(c))
        position = (f"x{m}", f"y{m}", f"z{m}")
        return cls(position, tuple(rpy), bool(rpy), used)

    def quaternion_xyzw(
        self, orientation: NDArray[np.float64], source: str
    ) -> NDArray[np.float64] | None:
        """Unit quaternions (N, 4) scalar last, from the orientation block, or None."""
        if not self.orientation:
            return None
        if self.is_rpy:
            return rpy_to_quaternion_xyzw(orientation)
        return _unit_quaternions(orientation, source)


def rpy_to_quaternion_xyzw(rpy_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """Roll-pitch-yaw (N, 3) rad → quaternions (N, 4) ``x,y,z,w``; R = Rz(yaw)·Ry(pitch)·Rx(roll).

    Same convention as ``pin.rpy.rpyToMatrix`` (FIGAROH). Scipy's lower-case ``"xyz"`` is
    extrinsic, which composes to exactly that product.
    """
    rotation = Rotation.from_euler("xyz", np.asarray(rpy_rad, dtype=np.float64))
    return rotation.as_quat(scalar_first=False)


def _joint_columns(
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
        raise DatasetError(
            f"{source}: mixes URDF joint columns ({_listing(by_name)}) with q-style columns "
            f"({_listing(q_style)}); name all joints one way: {_listing(names)} "
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
            f"{source}: unknown column(s) {_listing(unknown)}{hint}: not a joint of this robot "
            f"({_listing(names)}) nor a kincal column ({_listing(CONTRACT_COLUMNS)}); remove "
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
    parts = ([f"missing {_listing(missing)}"] if missing else []) + (
        [f"{_listing(beyond)} beyond the last joint"] if beyond else []
    )
    raise DatasetError(
        f"{source}: q-style joint columns {_listing([f'q{i}' for i in found])} do not match the "
        f"robot's {k} joints ({'; '.join(parts)}); write exactly q1..q{k} for "
        f"{_listing(names)} in chain order"
    )


def _check_named(
    by_name: list[str], names: tuple[str, ...], unknown: list[str], source: str
) -> None:
    missing = [n for n in names if n not in by_name]
    if not missing:
        return
    seen = f"; unrecognised column(s) present: {_listing(unknown)}" if unknown else ""
    raise DatasetError(
        f"{source}: missing joint column(s) {_listing(missing)}{seen}; expected one column per "
        f"joint named {_listing(names)}, or q1..q{len(names)} in chain order"
    )


def _finite_block(frame: pd.DataFrame, columns: list[str], source: str) -> NDArray[np.float64]:
    """(N, len(columns)) float64 array; names the first non-numeric / missing / infinite cell."""
    block = np.column_stack([_numeric_column(frame[c], c, source) for c in columns])
    bad = ~np.isfinite(block)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        col = int(np.flatnonzero(bad[row])[0])
        missing = np.isnan(block[row, col])
        problem = "value is missing (empty, null or NaN)" if missing else "value is infinite"
        raise DatasetError(
            f"{source}: data row {row + 1}, column {columns[col]}: {problem}; every used column "
            f"needs a finite number in every row (fix or delete the row)"
        )
    return block


def _numeric_column(series: pd.Series, name: str, source: str) -> NDArray[np.float64]:
    is_bool = pd.api.types.is_bool_dtype(series)
    if pd.api.types.is_numeric_dtype(series) and not is_bool:
        return series.to_numpy(dtype=np.float64, na_value=np.nan)
    try:
        numbers = pd.to_numeric(series, errors="coerce")
    except (TypeError, ValueError):  # nested values, e.g. lists in JSON
        numbers = pd.Series([_to_float(v) for v in series], index=series.index)
    rejected = series.notna().to_numpy() & (is_bool or numbers.isna().to_numpy())
    if rejected.any():
        row = int(np.flatnonzero(rejected)[0])
        shown = _one_line(repr(series.iloc[row]))[:40]
        raise DatasetError(
            f"{source}: data row {row + 1}, column {name}: {shown} is not a number; write a "
            f"plain decimal number (units: rad or m)"
        )
    return numbers.to_numpy(dtype=np.float64, na_value=np.nan)


def _to_float(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return np.nan


def _unit_quaternions(quat: NDArray[np.float64], source: str) -> NDArray[np.float64]:
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


def _check_time(time_s: NDArray[np.float64], source: str) -> None:
    back = np.flatnonzero(np.diff(time_s) < 0)
    if back.size:
        row = int(back[0]) + 2
        raise DatasetError(
            f"{source}: data row {row}, column t: time goes backwards ({float(time_s[row - 1])!r} "
            f"after {float(time_s[row - 2])!r} in data row {row - 1}); rows must be in execution "
            f"order with non-decreasing t (s)"
        )


def _sample_ids(frame: pd.DataFrame, source: str) -> NDArray[Any]:
    ids = frame["sample_id"]
    missing = ids.isna().to_numpy()
    if missing.any():
        row = int(np.flatnonzero(missing)[0])
        raise DatasetError(
            f"{source}: data row {row + 1}, column sample_id: value is missing; give every row "
            f"a sample_id or drop the column"
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


# ---------------------------------------------------------------------------------------------
# Chunked reading (recordings larger than memory)


@dataclass(frozen=True)
class ChunkRef:
    """Rows ``first_row`` .. ``first_row + n_rows - 1`` (0-based) of a dataset file.

    Parquet: ``row_groups`` to read and the slice ``[skip, skip + n_rows)`` of their rows.
    CSV: the bytes ``[byte_start, byte_stop)`` holding exactly these rows (no header).
    """

    first_row: int
    n_rows: int
    row_groups: tuple[int, ...] = ()
    skip: int = 0
    byte_start: int = 0
    byte_stop: int = 0


@dataclass(frozen=True)
class DatasetChunks:
    """A dataset file cut into chunks that are read and validated one at a time.

    Picklable (worker processes and Dask workers read their own chunks from ``path``, which
    must be visible to them). Each chunk is checked like :func:`read_dataset` checks a file;
    messages name the chunk's rows, e.g. ``data.csv (rows 100001-200000): data row 5, ...``
    (row numbers within the chunk). Not checked across chunks: ``sample_id`` uniqueness and
    ``t`` ordering at chunk boundaries. JSON is one document and is read whole.
    """

    path: str
    source: str
    joint_names: tuple[str, ...]
    other_joint_names: tuple[str, ...]
    marker: int | None
    header: tuple[str, ...]
    refs: tuple[ChunkRef, ...]
    position_only: bool
    has_payload: bool

    @property
    def n_rows(self) -> int:
        return sum(ref.n_rows for ref in self.refs)

    def read(self, ref: ChunkRef) -> PoseDataset:
        """The chunk ``ref`` as a validated :class:`PoseDataset`."""
        source = f"{self.source} (rows {ref.first_row + 1}-{ref.first_row + ref.n_rows})"
        try:
            frame = self._frame(ref)
        except DatasetError:
            raise
        except Exception as exc:  # one line, as read_dataset does
            raise DatasetError(
                f"{source}: cannot read ({type(exc).__name__}: {_one_line(exc)}); check the file"
            ) from exc
        return dataset_from_frame(
            frame,
            self.joint_names,
            source=source,
            other_joint_names=self.other_joint_names,
            marker=self.marker,
        )

    def _frame(self, ref: ChunkRef) -> pd.DataFrame:
        path = Path(self.path)
        suffix = path.suffix.lower()
        if suffix == ".parquet":
            import pyarrow.parquet as pq

            table = pq.ParquetFile(path).read_row_groups(list(ref.row_groups))
            return table.slice(ref.skip, ref.n_rows).to_pandas()
        if suffix == ".csv":
            with path.open("rb") as handle:
                handle.seek(ref.byte_start)
                raw = handle.read(ref.byte_stop - ref.byte_start)
            frame = pd.read_csv(
                io.BytesIO(raw),
                header=None,
                names=list(self.header),
                skipinitialspace=True,
                low_memory=False,
                **_EXACT_FLOATS,
            )
            return frame
        frame = _read_frame(path, self.source)
        return frame.iloc[ref.first_row : ref.first_row + ref.n_rows]


def plan_dataset_chunks(
    path: str | Path,
    joint_names: Sequence[str],
    *,
    chunk_rows: int,
    other_joint_names: Sequence[str] = (),
    marker: int | None = None,
    source: str | None = None,
) -> DatasetChunks:
    """Cut a dataset file into chunks of about ``chunk_rows`` rows without loading it.

    Parquet chunks are whole row groups (several small ones joined up to ``chunk_rows``; a
    larger group is sliced, so memory is bounded by the largest row group: write big
    recordings with row groups of ~10⁵ rows). CSV is indexed once by line offsets. The first
    chunk is read and validated here, so a wrong file fails before any work starts.
    """
    path = Path(path)
    source = source or path.name
    if chunk_rows < 1:
        raise DatasetError(f"{source}: chunk_rows must be positive, got {chunk_rows}")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise DatasetError(
            f"{source}: unsupported file type {path.suffix or '(no suffix)'!r}; "
            f"save it as one of {', '.join(SUFFIXES)}"
        )
    if not path.is_file():
        problem = "is a directory" if path.is_dir() else "file not found"
        raise DatasetError(f"{source}: {problem} ({path}); check the path")
    header: tuple[str, ...] = ()
    if suffix == ".parquet":
        try:
            refs = _parquet_chunks(path, chunk_rows)
        except Exception as exc:  # pyarrow's errors become one line, never a traceback
            raise DatasetError(
                f"{source}: cannot read as parquet ({type(exc).__name__}: {_one_line(exc)}); "
                "check that the file is a valid parquet file"
            ) from exc
    elif suffix == ".csv":
        header, refs = _csv_chunks(path, source, chunk_rows)
    else:
        n = len(_read_frame(path, source))
        refs = tuple(ChunkRef(a, min(chunk_rows, n - a)) for a in range(0, n, chunk_rows))
    if not refs:
        raise DatasetError(f"{source}: no data rows (header only or empty); add measurements")
    plan = DatasetChunks(
        str(path.resolve()),
        source,
        _check_joint_names(joint_names),
        tuple(other_joint_names),
        marker,
        header,
        refs,
        position_only=False,
        has_payload=False,
    )
    first = plan.read(refs[0])
    return dataclasses.replace(
        plan, position_only=first.is_position_only, has_payload=first.payload_kg is not None
    )


def _parquet_chunks(path: Path, chunk_rows: int) -> tuple[ChunkRef, ...]:
    import pyarrow.parquet as pq

    metadata = pq.ParquetFile(path).metadata
    refs: list[ChunkRef] = []
    groups: list[int] = []
    rows = 0
    first_row = 0
    for g in range(metadata.num_row_groups):
        size = metadata.row_group(g).num_rows
        if groups and rows + size > chunk_rows:
            refs.append(ChunkRef(first_row, rows, tuple(groups)))
            first_row += rows
            groups, rows = [], 0
        if not groups and size > chunk_rows:  # one big group: slice it
            refs += [
                ChunkRef(first_row + a, min(chunk_rows, size - a), (g,), skip=a)
                for a in range(0, size, chunk_rows)
            ]
            first_row += size
            continue
        groups.append(g)
        rows += size
    if groups:
        refs.append(ChunkRef(first_row, rows, tuple(groups)))
    return tuple(ref for ref in refs if ref.n_rows)


def _csv_chunks(
    path: Path, source: str, chunk_rows: int
) -> tuple[tuple[str, ...], tuple[ChunkRef, ...]]:
    """Header and byte ranges of ``chunk_rows`` lines each (blank lines count as rows here and
    are skipped when read)."""
    with path.open(newline="", encoding="utf-8-sig") as handle:
        header = next(csv.reader(handle), None)
    if not header or all(not cell.strip() for cell in header):
        raise DatasetError(
            f"{source}: file is empty; expected a header row such as "
            f"q1,...,qk,x,y,z,qx,qy,qz,qw followed by one row per measurement"
        )
    names = tuple(cell.strip() for cell in header)
    _check_duplicates(list(names), source)
    line_ends = []
    offset = 0
    with path.open("rb") as handle:
        while block := handle.read(1 << 24):
            ends = np.flatnonzero(np.frombuffer(block, dtype=np.uint8) == ord("\n"))
            line_ends.append(ends + offset)
            offset += len(block)
    ends = np.concatenate(line_ends) if line_ends else np.zeros(0, dtype=np.intp)
    size = offset
    starts = np.concatenate([[0], ends + 1])  # start of every line
    starts = starts[starts < size]
    data_starts = starts[1:]  # line 0 is the header
    refs = []
    for a in range(0, data_starts.size, chunk_rows):
        b = min(a + chunk_rows, data_starts.size)
        stop = int(data_starts[b]) if b < data_starts.size else size
        refs.append(ChunkRef(a, b - a, byte_start=int(data_starts[a]), byte_stop=stop))
    return names, tuple(refs)


# ---------------------------------------------------------------------------------------------
# Writing


def dataset_to_frame(
    ds: PoseDataset, *, joint_column_style: Literal["names", "q"] = "names"
) -> pd.DataFrame:
    """The dataset as a contract table: sample_id, joints, x,y,z, qx..qw, t, temperature_c,
    payload_kg (absent optional fields are left out)."""
    if joint_column_style not in ("names", "q"):
        raise ValueError(f"joint_column_style must be 'names' or 'q', got {joint_column_style!r}")
    q_cols = [f"q{i + 1}" for i in range(ds.n_joints)]
    joint_cols = ds.joint_names if joint_column_style == "names" else q_cols
    data: dict[str, Any] = {} if ds.sample_id is None else {"sample_id": ds.sample_id}
    data |= {c: ds.joint_positions[:, i] for i, c in enumerate(joint_cols)}
    data |= {c: ds.position_m[:, i] for i, c in enumerate(POSITION_COLUMNS)}
    if ds.quaternion_xyzw is not None:
        data |= {c: ds.quaternion_xyzw[:, i] for i, c in enumerate(QUATERNION_COLUMNS)}
    for column, name in _FLOAT_FIELD_OF_COLUMN.items():
        if getattr(ds, name) is not None:
            data[column] = getattr(ds, name)
    return pd.DataFrame(data)


def write_dataset(
    ds: PoseDataset,
    path: str | Path,
    *,
    joint_column_style: Literal["names", "q"] = "names",
) -> None:
    """Write ``ds`` in the contract layout; format by suffix (.csv, .parquet, .json).

    Floats are written at full precision, so reading the file back gives identical arrays. JSON
    is an array of row objects (stdlib json: fine for thousands of rows, slow for millions;
    prefer Parquet, then CSV, for large recordings).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise DatasetError(
            f"{path.name}: unsupported file type {path.suffix or '(no suffix)'!r}; "
            f"use one of {', '.join(SUFFIXES)}"
        )
    frame = dataset_to_frame(ds, joint_column_style=joint_column_style)
    if suffix == ".csv":
        _write_csv(frame, path)
    elif suffix == ".parquet":
        frame.to_parquet(path, index=False)
    else:
        rows = frame.to_dict(orient="records")
        path.write_text(json.dumps(rows, allow_nan=False), encoding="utf-8")


def _write_csv(frame: pd.DataFrame, path: Path) -> None:
    """CSV with shortest round-trip floats; Arrow's writer is ~15x faster than pandas'."""
    import pyarrow as pa
    import pyarrow.csv as pa_csv

    try:
        table = pa.Table.from_pandas(frame, preserve_index=False)
    except (pa.ArrowInvalid, pa.ArrowTypeError):  # e.g. sample ids mixing int and str
        frame.to_csv(path, index=False)
        return
    with path.open("w", newline="", encoding="utf-8") as handle:
        csv.writer(handle, lineterminator="\n").writerow(frame.columns)
    options = pa_csv.WriteOptions(include_header=False, quoting_style="needed")
    with pa.OSFile(str(path), "ab") as sink:
        pa_csv.write_csv(table, sink, options)


# ---------------------------------------------------------------------------------------------
# Message helpers


def _duplicates(items: Sequence[str]) -> list[str]:
    return [item for item, count in Counter(items).items() if count > 1]


def _listing(items: Sequence[Any]) -> str:
    shown = ",".join(str(i) for i in items[:_MAX_LISTED])
    more = f" (+{len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return shown + more


def _one_line(obj: object) -> str:
    return " ".join(str(obj).split())
