"""Issue 13: the default outlier rule keeps clean data, catches detector failures, and the
covariances it leaves are unbiased — on recordings from a simulator that shares no formula with
kincal (:mod:`benchmarks.pinocchio_sim`), through ``kincal calibrate`` → ``kincal predict``
with their defaults (``--no-heldout``: the held-out splits do not touch the covariances).

The full table (10 seeds, both sizes, with and without detector failures, and the paper's 2σ
rule for comparison) is ``python -m benchmarks.honest_covariance --write-results``;
docs/covariance.md includes it.
"""

from __future__ import annotations

import statistics
from pathlib import Path

import numpy as np
import pytest

from benchmarks.honest_covariance import jaco2, run_one
from benchmarks.pinocchio_sim import PinocchioRobot, true_pose
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


@pytest.mark.parametrize("n, seeds, limit", [(119, 10, 0.08), (2000, 4, 0.02)])
def test_default_covariances_are_unbiased_on_independent_data(
    n: int, seeds: int, limit: float, tmp_path: Path
) -> None:
    """Median task-score error (tr(WΣ_EWᵀ), paper W, Σ_n excluded, against finite-difference
    truth) within 8 % at N = 119 and 2 % at N = 2000, with 2 % detector failures (5 mm, 10°)
    in the recording; at most 1 % of the clean samples removed and at least 95 % of the
    failures caught in every run. (The paper's 2σ rule removed ~21 % of clean samples and came
    out ~26 % low here.)"""
    outcomes = [run_one(n, seed, 0.02, [], tmp_path, _kincal) for seed in range(seeds)]
    assert max(o.clean_removed for o in outcomes) <= 0.01
    assert min(o.gross_caught or 0.0 for o in outcomes) >= 0.95
    assert abs(statistics.median(o.task_error for o in outcomes)) <= limit


def test_the_paper_rule_stays_available_by_name(tmp_path: Path) -> None:
    """``--outlier-rule sigma`` is §V-A's 2σ rule: on clean independent data it removes about a
    fifth of the samples (each of 6 components cut at 2σ) — why it is not the default."""
    outcome = run_one(300, 0, 0.0, ["--outlier-rule", "sigma"], tmp_path, _kincal)
    assert 0.12 <= outcome.clean_removed <= 0.30
