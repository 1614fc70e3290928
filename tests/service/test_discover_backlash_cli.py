"""Issue 14 acceptance through ``kincal discover``: motor-side backlash (the link lags the
reading against the motion; gravity pushes it ahead along its torque) of 1 mrad by approach
direction and 2 mrad by load, N = 300, is named on the right joint with its size within 20 %,
on both simulators — the fast one (:mod:`solver.simulate`, which shares the library's
formulas) and the mechanism one (:mod:`solver.mechanisms`: a dead band between motor and
link, where load and motion history decide where the link rests; no library formula)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.discovery import FindingsResult
from service.app.simulate import marker_offset
from solver.mechanisms import DeadBand, MechanismSpec, simulate_mechanisms
from solver.simulate import JointEffect, SimulationSpec, look_at, simulate_recording
from tests.conftest import chain
from tests.service.cli_support import discover_ok, write_recording

KINOVA = chain("kinova")
J = KINOVA.joint_names
CAMERA = look_at(np.array([0.9, -0.6, 0.5]), np.array([0.0, 0.0, 0.25]))
NOISE = np.r_[[5e-5] * 3, [np.radians(0.003)] * 3]  # 50 µm, 0.003° per axis
N = 300
BACKLASH = {
    # name: (chain joint index, size rad, fast-simulator effect, dead band's holding friction N·m)
    "direction": (3, 1e-3, "backlash_direction", np.inf),
    "load": (1, 2e-3, "backlash_load", 0.0),
}


def _discovered(tmp_path: Path, simulator: str, name: str) -> FindingsResult:
    """The recording of ``simulator`` with that backlash, seed 0, through ``kincal discover
    --robot kinova`` (the built-in robot, nothing declared elastic) with its defaults."""
    joint, size, kind, holding = BACKLASH[name]
    if simulator == "fast":
        spec = SimulationSpec(
            N,
            0,
            noise_sigma=NOISE,
            measurement_frame=CAMERA,
            tool_offset=marker_offset(),
            joint_effects=(JointEffect(J[joint], kind, size),),  # type: ignore[arg-type]
        )
        recording = simulate_recording(KINOVA, spec)
        q, pose, t = recording.joint_positions, recording.measured_pose, recording.time_s
    else:
        mechanism = MechanismSpec(
            N,
            0,
            joints=(DeadBand(J[joint], size, holding_nm=holding),),
            measurement_frame=CAMERA,
            tool_offset=marker_offset(),
            noise_sigma=NOISE,
        )
        simulated = simulate_mechanisms(KINOVA, mechanism)
        q, pose, t = simulated.joint_positions, simulated.measured_pose, simulated.time_s
    path = tmp_path / f"{simulator}_{name}.csv"
    write_recording(path, q, pose, t)
    # --no-detectability: the sizes it leaves out change nothing discovery names
    # (test_discovery_is_deterministic_given_a_seed)
    return discover_ok(path, ["--robot", "kinova", "--no-detectability"])


@pytest.mark.parametrize("simulator", ["fast", "mechanism"])
@pytest.mark.parametrize("name", sorted(BACKLASH))
def test_motor_side_backlash_is_named_with_its_joint_and_size(
    tmp_path: Path, simulator: str, name: str
) -> None:
    joint, size, _, _ = BACKLASH[name]
    result = _discovered(tmp_path, simulator, name)
    named = [(f.effect, f.joint, f.variant) for f in result.findings]
    assert [n[:2] for n in named] == [("backlash", J[joint])], named
    assert named[0][2].startswith(name)
    value = result.findings[0].parameters["backlash_rad"]
    assert abs(value - size) <= 0.2 * size, value
    assert not result.ambiguous
    assert not any("wrong sign" in u.explanation for u in result.unexplained)
