"""Dataset files (CSV / Parquet / JSON, format by suffix) to tables and validated arrays."""

from __future__ import annotations

import csv
import io
import json
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import pandas as pd

from schemas.dataset.columns import check_duplicates, duplicates, one_line
from schemas.dataset.industrial import read_industrial_yaml
from schemas.dataset.paths import READ_SUFFIXES, check_dataset_path
from schemas.dataset.records import ConfigurationSet, PoseDataset
from schemas.dataset.validate import configurations_from_frame, dataset_from_frame
from solver.errors import DatasetError

Opener = Callable[[], IO[bytes]]


class TooManyRowsError(DatasetError):
    """A file holds more rows than the caller's limit (found before the rows are decoded)."""

    def __init__(self, source: str, n_rows: int, limit: int) -> None:
        super().__init__(
            f"{source}: {n_rows} samples is more than the limit of {limit}; split the recording"
        )
        self.n_rows = n_rows
        self.limit = limit


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


def read_frame(path: Path, source: str) -> pd.DataFrame:
    """The file as a table, unvalidated; reader failures become one-line :class:`DatasetError`."""
    suffix = check_dataset_path(path, source)
    return _frame(lambda: path.open("rb"), suffix, source, None)


def read_dataset_bytes(
    data: bytes,
    suffix: str,
    joint_names: Sequence[str],
    *,
    source: str,
    other_joint_names: Sequence[str] = (),
    max_rows: int | None = None,
) -> PoseDataset:
    """Like :func:`read_dataset` for a file's content held in memory (an upload; messages never
    show a server path). With ``max_rows``, a larger file raises :class:`TooManyRowsError`
    before its rows are decoded (Parquet: from its metadata; CSV: from its line count)."""
    if suffix not in READ_SUFFIXES:
        raise DatasetError(
            f"{source}: unsupported file type {suffix!r}; use one of {READ_SUFFIXES}"
        )
    frame = _frame(lambda: io.BytesIO(data), suffix, source, max_rows)
    return dataset_from_frame(
        frame, joint_names, source=source, other_joint_names=other_joint_names
    )


def _frame(open_binary: Opener, suffix: str, source: str, max_rows: int | None) -> pd.DataFrame:
    reader = {
        ".csv": _read_csv,
        ".parquet": _read_parquet,
        ".json": _read_json,
        ".yaml": _read_yaml,
        ".yml": _read_yaml,
    }[suffix]
    try:
        return reader(open_binary, source, max_rows)
    except DatasetError:
        raise
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{source}: not UTF-8 text ({exc.reason}); save it as UTF-8") from exc
    except Exception as exc:  # any reader failure becomes one line, never a pandas traceback
        raise DatasetError(
            f"{source}: cannot read as {suffix[1:]} ({type(exc).__name__}: {one_line(exc)}); "
            f"check that the file is a valid {suffix[1:]} file"
        ) from exc


def _text(open_binary: Opener) -> IO[str]:
    return io.TextIOWrapper(open_binary(), encoding="utf-8-sig", newline="")


def read_csv_header(path: Path, source: str) -> tuple[str, ...]:
    """The stripped column names of a CSV file's first row; refuses an empty or repeated one."""
    return _csv_header(lambda: path.open("rb"), source)


def _csv_header(open_binary: Opener, source: str) -> tuple[str, ...]:
    with _text(open_binary) as handle:
        header = next(csv.reader(handle), None)
    if not header or all(not cell.strip() for cell in header):
        raise DatasetError(
            f"{source}: file is empty; expected a header row such as "
            f"q1,...,qk,x,y,z,qx,qy,qz,qw followed by one row per measurement"
        )
    names = tuple(cell.strip() for cell in header)
    check_duplicates(names, source)
    return names


def _read_csv(open_binary: Opener, source: str, max_rows: int | None) -> pd.DataFrame:
    _csv_header(open_binary, source)
    try:
        with open_binary() as handle:
            frame = pd.read_csv(
                handle,
                encoding="utf-8-sig",
                skipinitialspace=True,
                low_memory=False,
                nrows=None if max_rows is None else max_rows + 1,
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
    if max_rows is not None and len(frame) > max_rows:
        with open_binary() as handle:
            lines = sum(chunk.count(b"\n") for chunk in iter(lambda: handle.read(1 << 20), b""))
        raise TooManyRowsError(source, max(lines - 1, len(frame)), max_rows)
    return frame.set_axis([str(c).strip() for c in frame.columns], axis=1)


MAX_DECODED_BYTES_PER_ROW = 4096
"""With a row limit, a Parquet file may decode to at most this much per allowed row (a row of
the contract is a few hundred bytes); a tiny file can otherwise unpack to gigabytes."""


def _read_parquet(open_binary: Opener, source: str, max_rows: int | None) -> pd.DataFrame:
    import pyarrow.parquet as pq

    with open_binary() as handle:
        parquet = pq.ParquetFile(handle)
        metadata = parquet.metadata
        if max_rows is not None:
            if metadata.num_rows > max_rows:
                raise TooManyRowsError(source, metadata.num_rows, max_rows)
            decoded = sum(
                metadata.row_group(g).total_byte_size for g in range(metadata.num_row_groups)
            )
            if decoded > max_rows * MAX_DECODED_BYTES_PER_ROW:
                raise DatasetError(
                    f"{source}: the file decodes to {decoded} bytes, more than "
                    f"{max_rows * MAX_DECODED_BYTES_PER_ROW} for at most {max_rows} rows; "
                    "keep only the contract's columns"
                )
        return parquet.read().to_pandas()


class _DuplicateKeyError(ValueError):
    pass


def _object_without_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        raise _DuplicateKeyError(duplicates([key for key, _ in pairs])[0])
    return obj


def _read_json(open_binary: Opener, source: str, max_rows: int | None) -> pd.DataFrame:
    try:
        with _text(open_binary) as handle:
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
    if max_rows is not None and len(rows) > max_rows:
        raise TooManyRowsError(source, len(rows), max_rows)
    return pd.DataFrame.from_records(rows)


def _read_yaml(open_binary: Opener, source: str, max_rows: int | None) -> pd.DataFrame:
    with _text(open_binary) as handle:
        frame = read_industrial_yaml(handle, source)
    if max_rows is not None and len(frame) > max_rows:
        raise TooManyRowsError(source, len(frame), max_rows)
    return frame
