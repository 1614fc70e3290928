"""A robot given by a Denavit–Hartenberg table (YAML), for devices without a URDF (docs/dh.md).

Example (the two-axis positioner of data/real/industrial_calibration_2axis_positioner)::

    name: positioner
    convention: dh            # dh: classic, Rz(θ+q)·Tz(d)·Tx(a)·Rx(α); mdh: Craig's modified
    base_frame: base_link     # default base_link
    tip_frame: tool0          # default tool0
    base: {xyz_m: [2.2, 0.0, 1.6], rpy_rad: [1.5707963267948966, 0.0, 0.0]}   # optional
    joints:
      - {name: j1, d_m: 0.0, theta_rad: 0.0, a_m: 0.0, alpha_rad: -1.5707963267948966}
      - {name: j2, d_m: -0.475, theta_rad: -1.5707963267948966, a_m: 0.0, alpha_rad: 0.0}

``type`` is ``revolute`` (default) or ``prismatic``; ``lower``/``upper`` the joint limits (rad
or m; default ±π for revolute joints, required for prismatic ones). For ``mdh`` a row's
``a_m``/``alpha_rad`` are Craig's ``a_{i-1}``/``alpha_{i-1}`` (the link before the joint).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import pinocchio as pin
import pydantic
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from solver.dh import DhRow, dh_urdf
from solver.errors import ModelError

Vector3 = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Placement(_Strict):
    """A constant transform: translation (m), then fixed-axis roll-pitch-yaw (rad, URDF's)."""

    xyz_m: Vector3 = (0.0, 0.0, 0.0)
    rpy_rad: Vector3 = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = pin.rpy.rpyToMatrix(*self.rpy_rad)
        out[:3, 3] = self.xyz_m
        return out


class DhJoint(_Strict):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    type: Literal["revolute", "prismatic"] = "revolute"
    a_m: float = 0.0
    alpha_rad: float = 0.0
    d_m: float = 0.0
    theta_rad: float = 0.0
    lower: float | None = None
    upper: float | None = None

    @model_validator(mode="after")
    def _limits(self) -> DhJoint:
        if self.type == "prismatic" and (self.lower is None or self.upper is None):
            raise ValueError(f"prismatic joint {self.name!r} needs lower and upper limits (m)")
        lower = -math.pi if self.lower is None else self.lower
        upper = math.pi if self.upper is None else self.upper
        if not lower < upper:
            raise ValueError(f"joint {self.name!r}: lower {lower} must be below upper {upper}")
        return self

    def row(self) -> DhRow:
        return DhRow(
            self.name,
            self.type,
            self.a_m,
            self.alpha_rad,
            self.d_m,
            self.theta_rad,
            -math.pi if self.lower is None else self.lower,
            math.pi if self.upper is None else self.upper,
        )


class DhRobot(_Strict):
    """A DH / modified-DH robot description (the YAML file of ``kincal calibrate --dh``)."""

    name: str = Field("dh_robot", min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    convention: Literal["dh", "mdh"]
    base_frame: str = Field("base_link", min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    tip_frame: str = Field("tool0", min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    base: Placement = Placement()
    tool: Placement = Placement()
    joints: list[DhJoint] = Field(min_length=1)

    def urdf(self) -> str:
        """The table as URDF text (:func:`solver.dh.dh_urdf`)."""
        return dh_urdf(
            self.name,
            [joint.row() for joint in self.joints],
            self.convention,
            self.base.matrix(),
            self.tool.matrix(),
            base_frame=self.base_frame,
            tip_frame=self.tip_frame,
        )


def parse_dh_robot(text: str, source: str) -> DhRobot:
    """A :class:`DhRobot` from YAML text; :class:`ModelError` naming the field otherwise."""
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ModelError(f"{source}: not YAML ({str(exc).splitlines()[0]})") from exc
    try:
        return DhRobot.model_validate(document)
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "document"
        raise ModelError(
            f"{source}: {where}: {first['msg']}; see docs/dh.md for the DH table format"
        ) from exc
