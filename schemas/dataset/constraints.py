"""Recordings without a pose per row (issue 15): ball-in-socket folders and FIGAROH files read
with all their markers at once.

Ball in socket (the platonics layout, ``data/real/platonics_ball_socket/PROVENANCE.md``): a
robot folder holds one sub-folder per tool placement, each with headerless CSV files
``hole_<k>.csv`` of joint positions (rad, chain order, one configuration per row) recorded with
the ball in socket k; a placement folder (or a folder holding hole files and placement folders)
is read the same way. Every (placement, hole) file is its own unknown point.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from schemas.dataset.figaroh import figaroh_markers
from schemas.dataset.readers import read_csv_header, read_dataset
from solver.errors import DatasetError

HOLE_FILE = re.compile(r"^hole_([0-9]+)\.csv$")


@dataclass(frozen=True)
class SocketRecording:
    """Joint positions (N, k) rad of every hole file, ``socket`` (N,) the 0-based socket of
    each row, ``sockets`` the ``<placement>/hole_<k>`` name of each socket, and per placement
    the sockets of its holes (``holes[placement][hole] = socket``)."""

    source: str
    joint_positions: NDArray[np.float64]
    socket: NDArray[np.intp]
    sockets: tuple[str, ...]
    holes: dict[str, dict[int, int]]

    @property
    def n_samples(self) -> int:
        return int(self.joint_positions.shape[0])


def is_socket_folder(path: str | Path) -> bool:
    """A folder with hole_<k>.csv files in it or in its sub-folders."""
    folder = Path(path)
    return folder.is_dir() and any(_hole_files(folder))


def _hole_files(folder: Path) -> list[tuple[str, int, Path]]:
    """(placement, hole, file) of the folder's own hole files and its sub-folders'."""
    out = []
    for directory in [folder, *sorted(p for p in folder.iterdir() if p.is_dir())]:
        placement = "." if directory == folder else directory.name
        for file in sorted(directory.iterdir()):
            if match := HOLE_FILE.match(file.name):
                out.append((placement, int(match.group(1)), file))
    return out


def read_socket_folder(path: str | Path, joint_names: Sequence[str]) -> SocketRecording:
    """Every hole file of a ball-in-socket folder, checked: ``len(joint_names)`` finite numbers
    per row; :class:`DatasetError` naming the file, row and fix otherwise."""
    folder = Path(path)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a folder of hole_<k>.csv files")
    files = _hole_files(folder)
    if not files:
        raise DatasetError(
            f"{folder.name}: no hole_<k>.csv files in the folder or its placement sub-folders; "
            "a ball-in-socket recording holds one headerless CSV of joint positions per socket"
        )
    k = len(joint_names)
    blocks: list[NDArray[np.float64]] = []
    sockets: list[str] = []
    holes: dict[str, dict[int, int]] = {}
    for placement, hole, file in files:
        name = f"{placement}/{file.name}" if placement != "." else file.name
        try:
            table = pd.read_csv(file, header=None, dtype=float)
        except (ValueError, pd.errors.ParserError) as exc:
            raise DatasetError(
                f"{name}: not a headerless CSV of numbers ({one_line(exc)}); one joint "
                "configuration (rad) per row"
            ) from exc
        except pd.errors.EmptyDataError as exc:
            raise DatasetError(f"{name}: empty; record configurations in this socket") from exc
        values = table.to_numpy(dtype=float)
        if values.shape[1] != k:
            raise DatasetError(
                f"{name}: {values.shape[1]} columns but the chain has {k} joints "
                f"({', '.join(joint_names)}); give one column per joint, in chain order"
            )
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            row, column = bad[0]
            raise DatasetError(
                f"{name}: data row {row + 1}, column {column + 1}: not a finite number; "
                "fix or remove the row"
            )
        holes.setdefault(placement, {})[hole] = len(sockets)
        sockets.append(name.removesuffix(".csv"))
        blocks.append(values)
    socket = np.concatenate([np.full(b.shape[0], i, dtype=np.intp) for i, b in enumerate(blocks)])
    return SocketRecording(folder.name, np.concatenate(blocks), socket, tuple(sockets), holes)


def one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())


def figaroh_marker_count(path: str | Path) -> int:
    """Markers of a FIGAROH CSV file (0 for another file or layout)."""
    file = Path(path)
    if file.suffix.lower() != ".csv" or not file.is_file():
        return 0
    return len(figaroh_markers(read_csv_header(file, file.name)))


@dataclass(frozen=True)
class MarkerRecording:
    """Joint positions (N, k) rad and the positions (N, m, 3) m of every marker."""

    source: str
    joint_positions: NDArray[np.float64]
    marker_positions_m: NDArray[np.float64]


def read_all_markers(
    path: str | Path, joint_names: Sequence[str], other_joint_names: Sequence[str] = ()
) -> MarkerRecording:
    """Every marker of a FIGAROH file (each read and checked as :func:`read_dataset` reads one
    marker)."""
    file = Path(path)
    numbers = sorted(figaroh_markers(read_csv_header(file, file.name)))
    if len(numbers) < 2:
        raise DatasetError(
            f"{file.name}: measurement 'markers' needs a FIGAROH file with several markers "
            f"(x1,y1,z1,x2,...); found {len(numbers)}"
        )
    datasets = [
        read_dataset(file, joint_names, other_joint_names=other_joint_names, marker=m)
        for m in numbers
    ]
    return MarkerRecording(
        file.name,
        datasets[0].joint_positions,
        np.stack([d.position_m for d in datasets], axis=1),
    )
