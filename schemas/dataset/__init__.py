"""Measurement datasets: files (CSV / Parquet / JSON) to plain arrays, with one-line errors.

Contract (DESIGN.md §3 "Dataset"): one row per measurement, rows in execution order;
joint columns named after the URDF joints (or ``q1..qk`` in chain order), rad (m for prismatic
joints); the measured marker/tool position ``x,y,z`` (m, measurement frame) and optionally its
orientation as a unit quaternion ``qx,qy,qz,qw`` (scalar LAST); optional ``sample_id``,
``t`` (s, non-decreasing), ``temperature_c``, ``payload_kg``. ``sample_id`` is kept as read: in
CSV, ids that look like integers come back as integers.

Every problem raises :class:`solver.errors.DatasetError` with ONE line
``<file>: data row R, column C: <problem>; <fix>``. Rows are numbered from 1 = first data row
(the header is not counted).

Modules by concern: ``records`` (the arrays and the contract's column names), ``columns``
(which columns hold what), ``figaroh`` (the FIGAROH marker adapter), ``validate`` (tables to
checked arrays), ``readers`` (files to tables), ``chunks`` (recordings larger than memory),
``writers`` (arrays to files), ``paths`` (which files, judged from the path alone: loaded
without pandas, so that a command refuses a missing file at once).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from schemas.dataset.paths import READ_SUFFIXES, SUFFIXES
from solver.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from schemas.dataset.chunks import ChunkRef, DatasetChunks, plan_dataset_chunks
    from schemas.dataset.columns import QUATERNION_NORM_TOL
    from schemas.dataset.figaroh import rpy_to_quaternion_xyzw
    from schemas.dataset.readers import (
        TooManyRowsError,
        read_configurations,
        read_dataset,
        read_dataset_bytes,
    )
    from schemas.dataset.records import (
        CONTRACT_COLUMNS,
        OPTIONAL_FLOAT_COLUMNS,
        POSITION_COLUMNS,
        QUATERNION_COLUMNS,
        ConfigurationSet,
        PoseDataset,
    )
    from schemas.dataset.validate import configurations_from_frame, dataset_from_frame
    from schemas.dataset.writers import dataset_to_frame, write_dataset

_HOME = {
    "ChunkRef": "chunks",
    "DatasetChunks": "chunks",
    "plan_dataset_chunks": "chunks",
    "QUATERNION_NORM_TOL": "columns",
    "rpy_to_quaternion_xyzw": "figaroh",
    "TooManyRowsError": "readers",
    "read_configurations": "readers",
    "read_dataset": "readers",
    "read_dataset_bytes": "readers",
    "CONTRACT_COLUMNS": "records",
    "OPTIONAL_FLOAT_COLUMNS": "records",
    "POSITION_COLUMNS": "records",
    "QUATERNION_COLUMNS": "records",
    "ConfigurationSet": "records",
    "PoseDataset": "records",
    "configurations_from_frame": "validate",
    "dataset_from_frame": "validate",
    "dataset_to_frame": "writers",
    "write_dataset": "writers",
}
"""Each public name's module, imported on first use: the readers load pandas (0.2 s), and a
command must be able to refuse a missing file (:mod:`schemas.dataset.paths`) without it."""


__getattr__ = lazy_exports(__name__, _HOME)


__all__ = [
    "CONTRACT_COLUMNS",
    "OPTIONAL_FLOAT_COLUMNS",
    "POSITION_COLUMNS",
    "QUATERNION_COLUMNS",
    "QUATERNION_NORM_TOL",
    "READ_SUFFIXES",
    "SUFFIXES",
    "ChunkRef",
    "ConfigurationSet",
    "DatasetChunks",
    "PoseDataset",
    "TooManyRowsError",
    "configurations_from_frame",
    "dataset_from_frame",
    "dataset_to_frame",
    "plan_dataset_chunks",
    "read_configurations",
    "read_dataset",
    "read_dataset_bytes",
    "rpy_to_quaternion_xyzw",
    "write_dataset",
]
