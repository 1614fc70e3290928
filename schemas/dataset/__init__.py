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
``writers`` (arrays to files).
"""

from __future__ import annotations

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
    READ_SUFFIXES,
    SUFFIXES,
    ConfigurationSet,
    PoseDataset,
)
from schemas.dataset.validate import configurations_from_frame, dataset_from_frame
from schemas.dataset.writers import dataset_to_frame, write_dataset

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
