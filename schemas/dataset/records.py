"""The arrays a dataset file becomes: measurements (:class:`PoseDataset`) and configurations
without measurements (:class:`ConfigurationSet`), and the contract's column names."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from solver.errors import DatasetError

if TYPE_CHECKING:
    from solver.measurement.models import FullPose

POSITION_COLUMNS = ("x", "y", "z")
QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw")
OPTIONAL_FLOAT_COLUMNS = ("t", "temperature_c", "payload_kg")
CONTRACT_COLUMNS = (*POSITION_COLUMNS, *QUATERNION_COLUMNS, "sample_id", *OPTIONAL_FLOAT_COLUMNS)
ROW_FLOAT_FIELDS = ("time_s", "temperature_c", "payload_kg")
FLOAT_FIELD_OF_COLUMN = dict(zip(OPTIONAL_FLOAT_COLUMNS, ROW_FLOAT_FIELDS, strict=True))
"""Optional float column of the file → :class:`PoseDataset` field."""


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
        for name in ("joint_positions", "position_m", "quaternion_xyzw", *ROW_FLOAT_FIELDS):
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
        expected |= {name: (n,) for name in ("sample_id", *ROW_FLOAT_FIELDS)}
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
    def measures_rotation(self) -> bool:
        """Whether the rows measured the marker's orientation (quaternion columns: 6-D
        residuals) or its position alone (3-D residuals)."""
        return self.quaternion_xyzw is not None

    @property
    def measurement_model(self) -> FullPose:
        """What the rows measure, as the model the pose paths take (issue 35):
        :class:`~solver.measurement.FullPose` with quaternion columns, else
        :class:`~solver.measurement.Position`. Imported on first use, so reading a file
        (the pre-flight checks) does not load the chain maths."""
        from solver.measurement.pose import pose_measurement

        return pose_measurement(rotation=self.quaternion_xyzw is not None)

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
