"""The mechanism-level simulator (solver.mechanisms) and the sign conventions it checks (issue 14).

The simulator shares no formula with the discovery library, so agreement between them is
evidence that the library's signs and shapes are the mechanisms' own.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from service.scenarios import marker_offset
from solver.discovery import DiscoveryData, DiscoveryOptions, DiscoveryResult, discover
from solver.mechanisms import (
    Concealment,
    DeadBand,
    ElasticJoint,
    GearTrain,
    MechanismSpec,
    Robot,
    _JointSide,
    conceal,
    gear_harmonic_amplitude,
    simulate_mechanisms,
)
from solver.model import gravity_loads, sample_configurations
from solver.simulate import JointEffect, SimulationSpec, look_at, simulate_recording
from tests.conftest import chain

KINOVA = chain("kinova")
J = KINOVA.joint_names
CAMERA = look_at(np.array([0.9, -0.6, 0.5]), np.array([0.0, 0.0, 0.25]))
NOISE = np.r_[[5e-5] * 3, [np.radians(0.003)] * 3]


def test_gravity_torque_from_the_masses_equals_the_calibration_model_torque() -> None:
    """Summed from body masses (mechanisms) and from Pinocchio's RNEA (solver.model): the same
    torque, sign included, about every joint axis."""
    q = sample_configurations(KINOVA, 6, np.random.default_rng(3))
    robot = Robot(KINOVA)
    mine = []
    for row in q:
        robot.update(row)
        mine.append([robot.joint_torque(i) for i in range(KINOVA.n_joints)])
    np.testing.assert_allclose(mine, gravity_loads(KINOVA, q), atol=1e-9)


@given(
    st.floats(1e-4, 1e-2),
    st.lists(st.floats(-1.0, 1.0), min_size=2, max_size=25),
)
def test_dead_band_keeps_the_link_within_half_the_backlash_and_lags_large_moves(
    backlash: float, motions: list[float]
) -> None:
    side = _JointSide(KINOVA, (DeadBand(J[3], backlash, holding_nm=np.inf),))
    motor = np.cumsum(motions)
    previous = None
    for position in motor:
        link = side.link_angle(3, float(position), 0.0, 0.0, commit=True)
        assert abs(link - position) <= 0.5 * backlash + 1e-15
        if previous is not None and abs(position - previous) > backlash:
            assert link == pytest.approx(position - 0.5 * backlash * np.sign(position - previous))
        previous = position


def test_dead_band_under_load_rests_on_the_side_gravity_pushes() -> None:
    side = _JointSide(KINOVA, (DeadBand(J[1], 2e-3),))
    assert side.link_angle(1, 0.3, 0.0, 4.0, commit=True) == pytest.approx(0.301)
    assert side.link_angle(1, 0.3, 0.0, -4.0, commit=True) == pytest.approx(0.299)


@pytest.mark.parametrize("harmonic", [1, 2, 3])
def test_gear_pitch_curve_lobes_give_their_harmonic_of_transmission_error(harmonic: int) -> None:
    """A pitch curve off-round by a (m) in h lobes rolls a transmission error of a/(h r) rad
    at harmonic h (first order in a/r)."""
    radius, lobe = 0.05, 2e-6
    shape = {1: "runout_m", 2: "ovality_m", 3: "trilobe_m"}[harmonic]
    gear = GearTrain(J[2], pitch_radius_m=radius, **{shape: lobe})  # type: ignore[arg-type]
    assert gear_harmonic_amplitude(gear, harmonic) == pytest.approx(
        lobe / (harmonic * radius), rel=1e-2
    )


def test_conceal_inverts_the_joint_mechanisms_sample_by_sample() -> None:
    """Readings concealed for a link path put the links back on that path through the forward
    mechanisms, history included."""
    mechanisms = (
        DeadBand(J[1], 2e-3, holding_nm=2.0),
        ElasticJoint(J[2], 5e-5),
        GearTrain(J[3], trilobe_m=3e-6, pitch_error_rad=2e-5),
    )
    links = sample_configurations(KINOVA, 20, np.random.default_rng(1))
    poses = np.tile(np.eye(4), (20, 1, 1))
    readings, _ = conceal(
        KINOVA, links, poses, np.arange(20.0), np.eye(4), Concealment(joints=mechanisms)
    )
    assert np.max(np.abs(readings - links)) > 1e-4
    side = _JointSide(KINOVA, mechanisms)
    robot = Robot(KINOVA)
    for n in range(20):
        robot.update(links[n])
        for c in (1, 2, 3):
            link = side.link_angle(c, float(readings[n, c]), float(n), robot.joint_torque(c), True)
            assert link == pytest.approx(links[n, c], abs=1e-10)


# --- acceptance: motor-side backlash on both simulators (issue 14) -------------------------

N = 300
BACKLASH = {
    # name: (joint, size, fast-simulator effect kind, dead band holding friction)
    "direction": (3, 1e-3, "backlash_direction", np.inf),
    "load": (1, 2e-3, "backlash_load", 0.0),
}


@functools.cache
def _backlash_run(simulator: str, name: str, seed: int) -> DiscoveryResult:
    joint, size, kind, holding = BACKLASH[name]
    if simulator == "fast":
        spec = SimulationSpec(
            N,
            seed,
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
            seed,
            joints=(DeadBand(J[joint], size, holding_nm=holding),),
            measurement_frame=CAMERA,
            tool_offset=marker_offset(),
            noise_sigma=NOISE,
        )
        simulated = simulate_mechanisms(KINOVA, mechanism)
        q, pose, t = simulated.joint_positions, simulated.measured_pose, simulated.time_s
    rigid = dataclasses.replace(KINOVA, compliance_axes=())
    return discover(
        rigid,
        DiscoveryData(q, pose, False, t),
        DiscoveryOptions(seed=seed, bootstrap=10, detectability=False),
    )


@pytest.mark.parametrize("simulator", ["fast", "mechanism"])
@pytest.mark.parametrize("name", sorted(BACKLASH))
def test_motor_side_backlash_is_named_with_its_joint_and_size(simulator: str, name: str) -> None:
    """Motor-side backlash (the link lags the reading against the motion; gravity pushes it
    ahead along its torque) of 1 mrad by approach direction and 2 mrad by load, N = 300: named
    on the right joint, size within 20 %, on both simulators."""
    joint, size, _, _ = BACKLASH[name]
    result = _backlash_run(simulator, name, 0)
    named = [
        (f.estimate.term.effect, f.estimate.term.joint_index, f.estimate.term.variant)
        for f in result.findings
    ]
    assert [n[:2] for n in named] == [("backlash", joint)], [f.explanation for f in result.findings]
    assert named[0][2].startswith(name)
    value = result.findings[0].estimate.parameters["backlash_rad"]
    assert abs(value - size) <= 0.2 * size, value
    assert not result.ambiguous and not any(
        "wrong sign" in u.explanation for u in result.unexplained
    )
