"""benchmarks/check.py runs on a tiny input (cannot rot): one draw on the UR10e recording, its
concealed changes at the sizes the check states, and its table."""

from __future__ import annotations

import numpy as np

from benchmarks import check
from service.app.check import check_arrays


def test_check_benchmark_on_one_draw() -> None:
    row = check.run("UR10e", 1, timing=False)
    assert row["rows"] == 23 and row["check_poses"] == 4 and row["draws"] == 1
    assert row["false_alarms"] in (0, 1)
    joints = [c for c in row["changes"] if c.endswith(" offset")]
    assert len(joints) == 6  # every joint's offset of the UR10e
    assert {"base translation", "base rotation", "tool translation"} <= set(row["changes"])
    for counts in row["changes"].values():
        assert 0 <= counts["located"] <= counts["named"] <= 1
        assert counts["located"] <= counts["flagged"] <= 1
    table = check.render([row]).splitlines()
    assert table[0].startswith("| Recording | Check poses | Draws | False alarms")
    assert len(table) == 2 + len(row["changes"])


def test_concealed_joint_offset_moves_the_reading_not_the_pose() -> None:
    dataset = check.read_recording(check.CHECKED["UR10e"])
    changed = check.conceal_joint(dataset, 2, 0.001)
    np.testing.assert_allclose(changed.joint_positions[:, 2], dataset.joint_positions[:, 2] - 0.001)
    np.testing.assert_array_equal(changed.position_m, dataset.position_m)


def test_a_tool_bump_concealed_in_positions_is_the_checks_tool_candidate(tmp_path) -> None:
    """On TALOS (positions only, no measured tool orientation) the concealed tool bump changes
    the check's residuals by exactly its tool candidate's columns times the bump — not by a
    move in the measurement frame, which is the base candidate's change."""
    recording = check.CHECKED["TALOS"]
    dataset = check.read_recording(recording)
    assert dataset.quaternion_xyzw is None
    result = check.calibrate(recording, dataset, tmp_path)
    twist = np.array([0.002, -0.001, 0.003, 0.0, 0.0, 0.0])
    changed = check.conceal_frame(result, dataset, "tool", twist)
    before, after = check_arrays(result, dataset), check_arrays(result, changed)
    tool = next(c for c in before.candidates if c.kind == "tool")
    expected = tool.jacobian[:, :, :3] @ twist[:3]
    np.testing.assert_allclose(after.residuals - before.residuals, expected, atol=1e-12)
