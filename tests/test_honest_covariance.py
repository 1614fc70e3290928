"""Issue 13: the default outlier rule keeps clean data, catches detector failures, and the
covariances it leaves are unbiased — on recordings from a simulator that shares no formula with
kincal (:mod:`benchmarks.pinocchio_sim`), through ``kincal calibrate`` → ``kincal predict``
with their defaults (``--no-heldout``: the held-out splits do not touch the covariances).

The acceptance reads the published table (10 seeds, both sizes, with detector failures, and the
paper's 2σ rule for comparison: ``python -m benchmarks.honest_covariance --write-results``,
included by docs/covariance.md) and re-runs one seed per size, so a change that moves the numbers
fails here until the table is re-run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.honest_covariance import jaco2, run_one
from benchmarks.pinocchio_sim import PinocchioRobot, true_pose
from benchmarks.results import read_results
from tests.service.cli_support import run_ok


def _kincal(*args: str) -> None:
    run_ok(list(args))


def test_the_independent_simulator_agrees_with_pinocchio_and_the_dataset_frame() -> None:
    """Without errors, perturbations or a camera the simulated pose is Pinocchio's own tip
    placement relative to the base (so the simulator adds nothing of its own)."""
    import pinocchio as pin

    from benchmarks.pinocchio_sim import TrueRobot

    robot: PinocchioRobot = jaco2()
    k = len(robot.joint_ids)
    truth = TrueRobot(
        np.zeros((k, 6)), np.zeros((k, 6)), np.zeros(k), pin.SE3.Identity(), pin.SE3.Identity()
    )
    q = robot.sample_q(1, np.random.default_rng(0))[0]
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.configuration(q))
    want = data.oMf[robot.base_id].inverse() * data.oMf[robot.tip_id]
    got = true_pose(robot, truth, q, np.zeros((k, 6)))
    assert np.allclose(got.homogeneous, want.homogeneous, atol=1e-12)


DEFAULT_BARS = {119: 0.08, 2000: 0.02}
"""Issue 13's bar on the median task-score error of the default rule, per recording size."""


def _rows(rule_flags: list[str]) -> dict[int, dict[str, Any]]:
    """The published rows (docs/results/honest_covariance.json) of one outlier rule, by N."""
    _, rows = read_results("honest_covariance")
    return {row["n"]: row for row in rows if row["flags"] == rule_flags}


def test_default_covariances_are_unbiased_on_independent_data() -> None:
    """The published table (10 seeds at N = 119 and 2000, 2 % detector failures of 5 mm and
    10° in the recording, through ``kincal calibrate`` → ``kincal predict``): median
    task-score error (tr(WΣ_EWᵀ), paper W, Σ_n excluded, against finite-difference truth)
    within 8 % at N = 119 and 2 % at N = 2000; at most 1 % of the clean samples removed and at
    least 95 % of the failures caught in every run. The table is current: seed 0 is re-run at
    both sizes (below and tests/test_quoted_numbers.py), and the table is its seeds' summary."""
    rows = _rows([])
    assert sorted(rows) == sorted(DEFAULT_BARS)
    for n, limit in DEFAULT_BARS.items():
        row = rows[n]
        assert row["seeds"] >= 10 and row["gross_fraction"] == 0.02, n
        assert row["clean_removed_max"] <= 0.01, n
        assert row["gross_caught_min"] >= 0.95, n
        assert abs(row["task_error_median"]) <= limit, n


@pytest.mark.slow
def test_the_default_rule_row_holds_for_seed_0_at_2000_poses(tmp_path: Path) -> None:
    """Seed 0 of the default rule at N = 2000 re-run through ``kincal calibrate`` →
    ``kincal predict`` in process: clean samples removed and failures caught exactly, the
    task-score error within 0.0005 (the table shows 0.1 %)."""
    want = _rows([])[2000]["outcomes"][0]
    got = run_one(2000, 0, 0.02, [], tmp_path, _kincal)
    assert got.clean_removed == want["clean_removed"]
    assert got.gross_caught == want["gross_caught"]
    assert got.task_error == pytest.approx(want["task_error"], abs=0.0005)


def test_the_paper_rule_stays_available_by_name() -> None:
    """``--outlier-rule sigma`` is §V-A's 2σ rule: on clean independent data it removes about a
    fifth of the samples (each of 6 components cut at 2σ) and its covariances come out ~26 %
    low — why it is not the default (published rows, 3 seeds per size)."""
    rows = _rows(["--outlier-rule", "sigma"])
    assert sorted(rows) == [119, 2000]
    for row in rows.values():
        assert row["gross_fraction"] == 0.0
        assert 0.12 <= row["clean_removed_median"] <= 0.30
        assert row["task_error_median"] < -0.1
