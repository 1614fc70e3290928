"""Dataset files (CSV / Parquet / JSON, format by suffix) to tables and validated arrays."""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from schemas.dataset.columns import check_duplicates, duplicates, one_line
from schemas.dataset.records import SUFFIXES, ConfigurationSet, PoseDataset
from schemas.dataset.validate import configurations_from_frame, dataset_from_frame
from solver.errors import DatasetError

# pandas < 3 parses CSV floats to within 1 ulp unless asked; pandas 3 is exact and deprecates it.
EXACT_FLOATS: dict[str, str] = (
    {"float_precision": "round_trip"} if int(pd.__version__.split(".")[0]) < 3 else {}
)


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
    frame = read_frame(path, source)
    return dataset_from_frame(
        frame, joint_names, source=source, other_joint_names=other_joint_names, marker=marker
    )


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
        read_frame(path, source), joint_names, source=source, other_joint_names=other_joint_names
    )


def check_dataset_path(path: Path, source: str) -> str:
    """The lower-case suffix of a dataset file that exists; a one-line error otherwise."""
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise DatasetError(
            f"{source}: unsupported file type {path.suffix or '(no suffix)'!r}; "
            f"save it as one of {', '.join(SUFFIXES)}"
        )
    if not path.is_file():
        problem = "is a directory" if path.is_dir() else "file not found"
        raise DatasetError(f"{source}: {problem} ({path}); check the path")
    return suffix


def read_frame(path: Path, source: str) -> pd.DataFrame:
    """The file as a table, unvalidated; reader failures become one-line :class:`DatasetError`."""
    suffix = check_dataset_path(path, source)
    reader = {".csv": _read_csv, ".parquet": _read_parquet, ".json": _read_json}[suffix]
    try:
        return reader(path, source)
    except DatasetError:
        raise
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{source}: not UTF-8 text ({exc.reason}); save it as UTF-8") from exc
    except Exception as exc:  # any reader failure becomes one line, never a pandas traceback
        raise DatasetError(
            f"{source}: cannot read as {suffix[1:]} ({type(exc).__name__}: {one_line(exc)}); "
            f"check that the file is a valid {suffix[1:]} file"
        ) from exc


def read_csv_header(path: Path, source: str) -> tuple[str, ...]:
    """The stripped column names of a CSV file's first row; refuses an empty or repeated one."""
    with path.open(newline="", encoding="utf-8-sig") as handle:
        header = next(csv.reader(handle), None)
    if not header or all(not cell.strip() for cell in header):
        raise DatasetError(
            f"{source}: file is empty; expected a header row such as "
            f"q1,...,qk,x,y,z,qx,qy,qz,qw followed by one row per measurement"
        )
    names = tuple(cell.strip() for cell in header)
    check_duplicates(names, source)
    return names


def _read_csv(path: Path, source: str) -> pd.DataFrame:
    read_csv_header(path, source)
    try:
        frame = pd.read_csv(
            path,
            encoding="utf-8-sig",
            skipinitialspace=True,
            low_memory=False,
            **EXACT_FLOATS,
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
        raise _DuplicateKeyError(duplicates([key for key, _ in pairs])[0])
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
