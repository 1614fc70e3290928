"""benchmarks/check.py runs on a tiny input (cannot rot): one draw on the UR10e recording, its
concealed changes at the sizes the check states, and its table."""

from __future__ import annotations

import numpy as np

from benchmarks import check


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
