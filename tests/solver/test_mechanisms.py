"""The mechanism-level simulator (solver.mechanisms) and the sign conventions it checks (issue 14).

The simulator shares no formula with the discovery library, so agreement between them is
evidence that the library's signs and shapes are the mechanisms' own.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from solver.mechanisms import (
    Concealment,
    DeadBand,
    ElasticJoint,
    GearTrain,
    Robot,
    _JointSide,
    conceal,
    gear_harmonic_amplitude,
)
from solver.model import gravity_loads, sample_configurations
from tests.conftest import chain

KINOVA = chain("kinova")
J = KINOVA.joint_names


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
