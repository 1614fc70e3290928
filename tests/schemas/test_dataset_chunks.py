"""Chunked reading of dataset files gives the rows read_dataset gives, chunk by chunk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from schemas.dataset import (
    PoseDataset,
    dataset_to_frame,
    plan_dataset_chunks,
    read_dataset,
    write_dataset,
)
from solver.errors import DatasetError

JOINTS = ("j1", "j2", "j3")


def _dataset(n: int, *, rotation: bool = True) -> PoseDataset:
    rng = np.random.default_rng(7)
    quaternion = rng.normal(size=(n, 4))
    quaternion /= np.linalg.norm(quaternion, axis=1, keepdims=True)
    return PoseDataset(
        joint_names=JOINTS,
        joint_positions=rng.uniform(-3, 3, size=(n, 3)),
        position_m=rng.normal(size=(n, 3)),
        quaternion_xyzw=quaternion if rotation else None,
        sample_id=np.arange(n) + 100,
        payload_kg=rng.uniform(0, 2, size=n),
    )


def _concatenated(path: Path, chunk_rows: int) -> tuple[PoseDataset, int]:
    plan = plan_dataset_chunks(path, JOINTS, chunk_rows=chunk_rows)
    parts = [plan.read(ref) for ref in plan.refs]
    assert [ref.first_row for ref in plan.refs] == list(
        np.cumsum([0] + [ref.n_rows for ref in plan.refs[:-1]])
    )
    assert plan.n_rows == sum(p.n_samples for p in parts)
    whole = PoseDataset(
        joint_names=JOINTS,
        joint_positions=np.concatenate([p.joint_positions for p in parts]),
        position_m=np.concatenate([p.position_m for p in parts]),
        quaternion_xyzw=np.concatenate([p.quaternion_xyzw for p in parts])  # type: ignore[misc]
        if plan.measures_rotation
        else None,
        payload_kg=np.concatenate([p.payload_kg for p in parts]),  # type: ignore[misc]
    )
    return whole, len(plan.refs)


def _same(a: PoseDataset, b: PoseDataset) -> bool:
    quaternions = (a.quaternion_xyzw is None and b.quaternion_xyzw is None) or np.array_equal(
        a.quaternion_xyzw, b.quaternion_xyzw
    )
    return (
        np.array_equal(a.joint_positions, b.joint_positions)
        and np.array_equal(a.position_m, b.position_m)
        and quaternions
        and np.array_equal(a.payload_kg, b.payload_kg)
    )


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".json"])
@pytest.mark.parametrize("rotation", [True, False])
def test_chunks_concatenate_to_the_whole_file(tmp_path: Path, suffix: str, rotation: bool) -> None:
    path = tmp_path / f"data{suffix}"
    write_dataset(_dataset(1003, rotation=rotation), path)
    whole, n_chunks = _concatenated(path, 250)
    assert _same(whole, read_dataset(path, JOINTS))
    assert n_chunks == 5  # Parquet: one row group of 1003 rows, sliced


def test_parquet_row_groups_are_joined_up_to_the_chunk_size(tmp_path: Path) -> None:
    path = tmp_path / "groups.parquet"
    table = pa.Table.from_pandas(dataset_to_frame(_dataset(1000)), preserve_index=False)
    pq.write_table(table, path, row_group_size=100)
    plan = plan_dataset_chunks(path, JOINTS, chunk_rows=350)
    assert [ref.n_rows for ref in plan.refs] == [300, 300, 300, 100]
    assert all(len(ref.row_groups) == ref.n_rows // 100 for ref in plan.refs)
    whole, _ = _concatenated(path, 350)
    assert _same(whole, read_dataset(path, JOINTS))


def test_a_bad_row_names_its_chunk(tmp_path: Path) -> None:
    path = tmp_path / "bad.csv"
    write_dataset(_dataset(40), path)
    lines = path.read_text().splitlines()
    cells = lines[33].split(",")
    cells[2] = "oops"
    lines[33] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    plan = plan_dataset_chunks(path, JOINTS, chunk_rows=10)
    with pytest.raises(DatasetError, match=r"bad\.csv \(rows 31-40\): data row 3, column j2"):
        plan.read(plan.refs[3])


def test_the_first_chunk_is_checked_when_planning(tmp_path: Path) -> None:
    path = tmp_path / "nojoints.csv"
    path.write_text("x,y,z\n1,2,3\n")
    with pytest.raises(DatasetError, match="missing joint column"):
        plan_dataset_chunks(path, JOINTS, chunk_rows=10)
