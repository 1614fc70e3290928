"""Missing-physics discovery on recordings where exactly one effect was hidden (issue 5).

Each recording comes from a Kinova Jaco2 with geometric errors, an unknown camera and marker,
0.05 mm / 0.003° noise and ONE hidden effect; discovery starts from the rigid model. It must
name the effect and the joint, recover the size within its confidence interval (and 20 %),
and bring the held-out error to within 10 % of the true model's.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np
import pytest

from solver import lie
from solver.calibration import pose_errors
from solver.discovery import DiscoveryData, DiscoveryOptions, DiscoveryResult, discover
from solver.measurement import FullPose
from solver.model import KinematicChain
from solver.simulate import JointEffect, SimulationSpec, look_at, simulate_recording
from tests.conftest import chain

N = 200
OPTIONS = DiscoveryOptions(seed=0, bootstrap=20, detectability=False)  # sizes: test_detectability
J = chain("kinova").joint_names


def _spec(seed: int, **hidden: Any) -> SimulationSpec:
    marker = np.eye(4)
    marker[:3, :3] = lie.so3_exp(np.array([0.3, -0.2, 0.5]))
    marker[:3, 3] = [0.03, -0.02, 0.05]
    return SimulationSpec(
        n_samples=N,
        seed=seed,
        noise_sigma=np.r_[[5e-5] * 3, [np.radians(0.003)] * 3],
        measurement_frame=look_at(np.array([0.9, -0.6, 0.5]), np.array([0.0, 0.0, 0.25])),
        tool_offset=marker,
        **hidden,
    )


@dataclasses.dataclass(frozen=True)
class Case:
    hidden: dict[str, Any]
    effect: str
    joint: int | None
    truth: dict[str, float]
    declared: tuple[int, ...] = ()  # joints the user's model already treats as compliant
    virtual_first: bool = False


CASES = {
    "joint_compliance": Case(
        {"compliance_rad_per_nm": {J[1]: 1e-4}},
        "joint_compliance",
        1,
        {"compliance_rad_per_nm": 1e-4},
    ),
    "gear_periodic": Case(
        {"joint_effects": (JointEffect(J[2], "gear_periodic", 2e-4, harmonic=2, phase_rad=0.3),)},
        "gear_periodic",
        2,
        {"amplitude_rad": 2e-4, "phase_rad": 0.3},
    ),
    "backlash": Case(
        {"joint_effects": (JointEffect(J[1], "backlash_load", 1e-3),)},
        "backlash",
        1,
        {"backlash_rad": 1e-3},
    ),
    "joint_scale": Case(
        {"joint_effects": (JointEffect(J[1], "joint_scale", 5e-4),)},
        "joint_scale",
        1,
        {"scale_error": 5e-4},
    ),
    "thermal_drift": Case(
        {"joint_effects": (JointEffect(J[1], "drift_linear", 1e-6),)},
        "thermal_drift",
        1,
        {"drift_rad_per_s": 1e-6},
    ),
    "base_flex": Case(
        {"compliance_rad_per_nm": {f"{J[0]}.flex_a": 5e-5, f"{J[0]}.flex_b": 3e-5}},
        "base_flex",
        0,
        {"flex_a_rad_per_nm": 5e-5, "flex_b_rad_per_nm": 3e-5},
        virtual_first=True,
    ),
    "gravity_direction": Case(
        {
            "compliance_rad_per_nm": {J[1]: 5e-4, J[2]: 5e-4},
            "gravity_base": lie.so3_exp(np.array([np.radians(2.0), 0.0, 0.0]))
            @ np.array([0.0, 0.0, -9.81]),
        },
        "gravity_direction",
        None,
        {"tilt_x_rad": np.radians(2.0), "tilt_y_rad": 0.0},
        declared=(1, 2),
    ),
}


def _truth_chain(case: Case) -> KinematicChain:
    return chain("kinova", case.virtual_first)


@functools.cache
def _run(name: str, seed: int = 1) -> tuple[DiscoveryResult, float]:
    """Discovery result and the true model's mean held-out translation error (mm)."""
    case = CASES[name]
    truth = _truth_chain(case)
    recording = simulate_recording(truth, _spec(seed, **case.hidden))
    axes = tuple(
        a for a in truth.compliance_axes if a.is_joint_axis and a.joint_index in case.declared
    )
    model = dataclasses.replace(truth, compliance_axes=axes)
    data = DiscoveryData(
        recording.joint_positions, recording.measured_pose, FullPose(), recording.time_s
    )
    result = discover(model, data, OPTIONS)
    oracle = pose_errors(recording.true_mean_pose, recording.measured_pose, rotation=True)
    return result, float(oracle[0].mean())


@pytest.mark.parametrize("name", sorted(CASES))
def test_hidden_effect_is_named_with_its_joint(name: str) -> None:
    result, _ = _run(name)
    case = CASES[name]
    named = [(f.estimate.term.effect, f.estimate.term.joint_index) for f in result.findings]
    assert named == [(case.effect, case.joint)], [f.explanation for f in result.findings]
    assert not result.ambiguous and not result.unexplained


@pytest.mark.parametrize("name", sorted(CASES))
def test_hidden_effect_size_is_inside_its_confidence_interval(name: str) -> None:
    result, _ = _run(name)
    estimate = result.findings[0].estimate
    for key, true_value in CASES[name].truth.items():
        value, error = estimate.parameters[key], estimate.stderr[key]
        assert abs(value - true_value) <= 3.0 * error, (key, value, error, true_value)
        assert _within_20_percent(value, true_value, CASES[name].truth), (key, value, true_value)


def _within_20_percent(value: float, true_value: float, truth: dict[str, float]) -> bool:
    """Within 20 % of the true value; a zero component (no magnitude of its own) within 20 %
    of the case's largest true parameter."""
    scale = abs(true_value) if true_value != 0.0 else max(abs(v) for v in truth.values())
    return abs(value - true_value) <= 0.2 * scale


@pytest.mark.parametrize("name", sorted(CASES))
def test_heldout_error_reaches_the_true_model(name: str) -> None:
    result, oracle_mm = _run(name)
    assert result.heldout_after.translation_mm < 0.9 * result.heldout_before.translation_mm
    assert result.heldout_after.translation_mm < 1.10 * oracle_mm


@pytest.mark.parametrize("name", ["joint_compliance", "gear_periodic", "backlash"])
@pytest.mark.parametrize("seed", [2, 3])
def test_issue_acceptance_effects_hold_on_other_recordings(name: str, seed: int) -> None:
    """Issue 5's three named cases on further seeds: right effect and joint, magnitude within
    20 %, held-out error within 10 % of the true model's."""
    result, oracle_mm = _run(name, seed)
    case = CASES[name]
    named = [(f.estimate.term.effect, f.estimate.term.joint_index) for f in result.findings]
    assert named == [(case.effect, case.joint)], [f.explanation for f in result.findings]
    for key, true_value in case.truth.items():
        value = result.findings[0].estimate.parameters[key]
        assert _within_20_percent(value, true_value, case.truth), (key, value, true_value)
    assert result.heldout_after.translation_mm < 1.10 * oracle_mm
