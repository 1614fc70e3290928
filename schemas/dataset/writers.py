"""Datasets to files in the contract layout (CSV / Parquet / JSON), exact to the last bit."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any, Literal

import pandas as pd

from schemas.dataset.paths import SUFFIXES
from schemas.dataset.records import (
    FLOAT_FIELD_OF_COLUMN,
    POSITION_COLUMNS,
    QUATERNION_COLUMNS,
    PoseDataset,
)
from solver.errors import DatasetError


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
    for column, name in FLOAT_FIELD_OF_COLUMN.items():
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
