"""benchmarks/design.py runs on a tiny input (cannot rot): its table, the bound below every
design, the URDF it hands FIGAROH, and (when a FIGAROH interpreter is given) the driver."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from benchmarks import design, design_measurements

TINY = design.Settings(seeds=1, poses=(8,), candidates=60, heldout=40, calibrate=True)


def test_design_benchmark_table_on_a_tiny_input() -> None:
    robot = design.robots()["jaco2"]
    rows = design.compare_robot("jaco2", robot, TINY)
    assert {method for _, method in rows} >= {"random", "kincal-D", "kincal-I", "bound"}
    ((bound, _, _, _),) = rows[(8, "bound")]
    for method in ("random", "kincal-D", "kincal-I"):
        ((variance, sigma, error_mm, efficiency),) = rows[(8, method)]
        assert np.isfinite([variance, sigma, error_mm]).all() and error_mm > 0
        assert variance >= bound * (1 - 1e-9)  # no 8 poses go below the relaxation
        assert np.isnan(efficiency) if method == "random" else 0.0 < efficiency <= 1.0
    lines, results = design.compare(TINY, ["jaco2"], echo=lambda _: None)
    assert lines[0].startswith("robot") and any("kincal-D" in line for line in lines)
    assert "| Jaco2 | 8 |" in design.render_poses(results)
    assert "60 candidates" in design.timing(n_candidates=60, n_poses=8).line()


def test_sensor_volume_table_on_a_tiny_input() -> None:
    """The --volumes study: volumes at the reach's edge that the sampler fills, every design
    at or above the bound (repeats allowed, so below every 25-pose set), efficiencies ≤ 1."""
    robot = design.robots()["jaco2"]
    chain = design.robot_chain(robot)
    volumes = design.sensor_volumes(chain)
    assert set(volumes) == {"tracker box", "camera cone"}
    box = volumes["tracker box"]["box"]
    assert np.allclose(np.subtract(box["high_m"], box["low_m"]), 0.25)  # type: ignore[index]
    settings = design.Settings(seeds=1, candidates=60, heldout=40)
    for name, fields in volumes.items():
        (run,) = design.compare_volume(robot, fields, "position", settings)
        assert set(run) == set(design.VOLUME_COLUMNS), name
        for method in ("random25", "D", "I"):
            assert run[method] >= run["bound"] * (1 - 1e-9)
        assert 0.0 < run["D-eff"] <= 1.0 and 0.0 < run["I-eff"] <= 1.0
    lines, results = design.compare_volumes(
        design.Settings(seeds=1, candidates=60, heldout=40), ["x"], echo=lambda _: None
    )
    assert lines[0].startswith("robot") and len(lines) == 1 and results == []


def test_figaroh_gets_the_same_kinematics_without_continuous_joints() -> None:
    robot = design.robots()["jaco2"]
    chain = design.robot_chain(robot)
    root = ET.fromstring(design.figaroh_urdf(robot, chain))
    joints = {j.get("name"): j for j in root.findall("joint")}
    assert not list(root.iter("visual")) and not list(root.iter("collision"))
    for i, name in enumerate(chain.joint_names):
        assert joints[name].get("type") == "revolute"
        limit = joints[name].find("limit")
        assert limit is not None
        assert float(limit.get("lower", "nan")) == chain.lower_limits[i]
    copy = design.build_chain(ET.tostring(root).decode(), robot.base_frame, robot.tip_frame)
    q = design.sample_candidates(chain, 5, np.random.default_rng(0))
    np.testing.assert_allclose(design.tip_poses(copy, q), design.tip_poses(chain, q), atol=1e-12)


@pytest.mark.skipif(
    "KINCAL_FIGAROH_PYTHON" not in os.environ,
    reason="FIGAROH is not a kincal dependency: set KINCAL_FIGAROH_PYTHON to its interpreter",
)
def test_figaroh_driver_on_a_tiny_input() -> None:
    robot = design.robots()["ur10e"]
    chain = design.robot_chain(robot)
    q = design.sample_candidates(chain, 40, np.random.default_rng(0))
    answer = design.figaroh_designs(os.environ["KINCAL_FIGAROH_PYTHON"], robot, chain, q, [8], 0)
    assert answer["candidates"] == 40 and len(answer["ranking"]) == 40
    assert abs(answer["socp_weight_sum"] - 1.0) < 1e-6
    assert len(answer["detmax"]["8"]) == 8


def test_measurement_design_table_on_a_tiny_input() -> None:
    """benchmarks/design_measurements.py: the markers row (auto: first-order, the offsets as
    nuisance columns), its criterion below the bound, and Clarabel's LMI on the same
    relaxation agreeing with the first-order method."""
    row = design_measurements.run_case(design_measurements.CASES[1], 30, 10, 12)
    assert design_measurements.line(row).startswith("3 markers")
    assert row["nuisance"] > 0 and row["method"] == "first_order"
    assert row["value"] <= row["upper_bound"]
    small = row["small"]
    assert small["first_order_value"] == pytest.approx(small["clarabel_value"], rel=1e-4)
    assert "3 markers" in design_measurements.render([row])
