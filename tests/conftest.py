"""Shared fixtures: built-in robots and their chains are built once per test session."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import pytest
from hypothesis import settings

import solver  # noqa: F401  (BLAS threading defaults before numpy loads)
from service.robots import BUILTIN_ROBOTS, RobotDescription, load_robot
from solver.model import KinematicChain, build_chain

REPO = Path(__file__).resolve().parents[1]
REAL_DATA = REPO / "data" / "real"

settings.register_profile("ci", deadline=None, max_examples=40, derandomize=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@functools.cache
def robot(name: str) -> RobotDescription:
    return load_robot(name)


@functools.cache
def chain(name: str, virtual_first: bool = False) -> KinematicChain:
    description = robot(name)
    probe = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    return build_chain(
        description.urdf_xml,
        description.base_frame,
        description.tip_frame,
        virtual_axes_at=[probe.joint_names[0]] if virtual_first else [],
    )


@pytest.fixture(params=sorted(BUILTIN_ROBOTS))
def builtin_name(request: pytest.FixtureRequest) -> str:
    return str(request.param)
