"""Chunked reading of recordings larger than memory: plan the chunks of a file without loading
it, then read and validate one chunk at a time (in any process that sees the file)."""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from schemas.dataset.columns import check_joint_names, one_line
from schemas.dataset.paths import check_dataset_path
from schemas.dataset.readers import EXACT_FLOATS, read_csv_header, read_frame
from schemas.dataset.records import PoseDataset
from schemas.dataset.validate import dataset_from_frame
from solver.errors import DatasetError


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
    must be visible to them). Each chunk is checked like :func:`schemas.dataset.read_dataset`
    checks a file; messages name the chunk's rows, e.g. ``data.csv (rows 100001-200000): data
    row 5, ...`` (row numbers within the chunk). Not checked across chunks: ``sample_id``
    uniqueness and ``t`` ordering at chunk boundaries. JSON is one document and is read whole.
    """

    path: str
    source: str
    joint_names: tuple[str, ...]
    other_joint_names: tuple[str, ...]
    marker: int | None
    header: tuple[str, ...]
    refs: tuple[ChunkRef, ...]
    measures_rotation: bool
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
                f"{source}: cannot read ({type(exc).__name__}: {one_line(exc)}); check the file"
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
                **EXACT_FLOATS,
            )
            return frame
        frame = read_frame(path, self.source)
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
    suffix = check_dataset_path(path, source)
    header: tuple[str, ...] = ()
    if suffix == ".parquet":
        try:
            refs = _parquet_chunks(path, chunk_rows)
        except Exception as exc:  # pyarrow's errors become one line, never a traceback
            raise DatasetError(
                f"{source}: cannot read as parquet ({type(exc).__name__}: {one_line(exc)}); "
                "check that the file is a valid parquet file"
            ) from exc
    elif suffix == ".csv":
        header, refs = _csv_chunks(path, source, chunk_rows)
    else:
        n = len(read_frame(path, source))
        refs = tuple(ChunkRef(a, min(chunk_rows, n - a)) for a in range(0, n, chunk_rows))
    if not refs:
        raise DatasetError(f"{source}: no data rows (header only or empty); add measurements")
    plan = DatasetChunks(
        str(path.resolve()),
        source,
        check_joint_names(joint_names),
        tuple(other_joint_names),
        marker,
        header,
        refs,
        measures_rotation=True,
        has_payload=False,
    )
    first = plan.read(refs[0])
    return dataclasses.replace(
        plan, measures_rotation=first.measures_rotation, has_payload=first.payload_kg is not None
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
    names = read_csv_header(path, source)
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
