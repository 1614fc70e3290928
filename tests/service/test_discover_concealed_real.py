"""Issue 14 acceptance through the user's path: ``kincal discover`` on the shipped FR3 and
UR10e recordings, unmodified (nothing named) and with one effect concealed by the mechanism
simulator (:mod:`solver.mechanisms`, no library formula) at twice the detectability the
unmodified recording's report states (named, right joint, size within 25 %)."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks import concealed_real
from schemas.discovery import FindingsResult
from tests.service.cli_support import run_ok


def _write(path: Path, name: str, joint_positions: np.ndarray, poses: np.ndarray) -> None:
    """The recording as a kincal dataset CSV (q…, x y z, qx qy qz qw)."""
    original = (concealed_real.DATA / concealed_real.RECORDINGS[name].relative).read_text()
    header = original.splitlines()[0].split(",")
    joints = [c for c in header if c not in ("sample_id", "x", "y", "z", "qx", "qy", "qz", "qw")]
    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    rows = [",".join([*joints, "x", "y", "z", "qx", "qy", "qz", "qw"])]
    for q, pose, quat in zip(joint_positions, poses, quaternions, strict=True):
        rows.append(",".join(f"{v:.17g}" for v in [*q, *pose[:3, 3], *quat]))
    path.write_text("\n".join(rows) + "\n")


def _discover(path: Path, robot: str) -> FindingsResult:
    output = path.with_suffix(".json")
    with contextlib.redirect_stdout(io.StringIO()):
        run_ok(["discover", path, "--robot", robot, "--bootstrap", 0, "-o", output])
    return FindingsResult.model_validate_json(output.read_bytes())


def _stated(result: FindingsResult, effect: str, variant: str, joint: str) -> float:
    assert result.detectability is not None
    (size,) = [
        s.smallest
        for s in result.detectability.sizes
        if (s.effect, s.variant, s.joint) == (effect, variant, joint)
    ]
    assert size is not None
    return size


@pytest.fixture(scope="module")
def unmodified(tmp_path_factory: pytest.TempPathFactory) -> dict[str, FindingsResult]:
    folder = tmp_path_factory.mktemp("real")
    out = {}
    for name, robot in (("fr3", "panda"), ("ur10e", "ur10e")):
        base = concealed_real.baseline(name)
        path = folder / f"{name}.csv"
        _write(path, name, base.data.joint_positions, base.data.measured_pose)
        out[name] = _discover(path, robot)
    return out


def test_unmodified_real_recordings_name_nothing(unmodified: dict[str, FindingsResult]) -> None:
    for result in unmodified.values():
        assert result.findings == []
