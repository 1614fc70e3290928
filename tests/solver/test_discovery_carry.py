"""Carrying a discovered model into the calibration: corrections undo what the simulator hid."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from solver import lie
from solver.discovery import DiscoveryData
from solver.discovery.carry import (
    applicable_at_new_configurations,
    configuration_corrections,
    correct_recording,
    corrected_configurations,
    is_correction,
    readings_for,
    undo_depth_scale,
)
from solver.discovery.features import FeatureBank, probe_chain
from solver.discovery.library import EFFECTS, library_term
from solver.measurement import FullPose
from solver.simulate import JointEffect, SimulationSpec, simulate_recording
from tests.conftest import chain

NOISELESS = np.zeros(6)


def _bank(recording: object) -> FeatureBank:
    rigid = dataclasses.replace(chain("kinova"), compliance_axes=())
    data = DiscoveryData(
        recording.joint_positions,  # type: ignore[attr-defined]
        recording.measured_pose,  # type: ignore[attr-defined]
        FullPose(),
        recording.time_s,  # type: ignore[attr-defined]
    )
    return FeatureBank(probe_chain(rigid), data)


def test_every_library_term_can_be_rebuilt_from_its_key() -> None:
    """findings.json stores (effect, joint, variant); the term must come back identical."""
    from solver.discovery.library import candidate_library, compliance_term

    recording = simulate_recording(chain("kinova"), SimulationSpec(n_samples=30, seed=2))
    bank = _bank(recording)
    library = candidate_library(bank.probe, bank, (compliance_term(bank.probe, 1, declared=True),))
    assert {t.effect for t in library} == set(EFFECTS)
    for term in library:
        rebuilt = library_term(
            bank.probe, term.effect, term.joint_index, term.variant, bank.clock_unit
        )
        assert rebuilt == term, term.key


@pytest.mark.parametrize(
    ("effect", "variant", "coefficients"),
    [
        (JointEffect("j2s6s200_joint_3", "gear_periodic", 3e-4, 2, 0.4), "h2", None),
        (JointEffect("j2s6s200_joint_2", "backlash_load", 1e-3), "load", [1e-3]),
        (JointEffect("j2s6s200_joint_3", "backlash_direction", 1e-3), "direction", [1e-3]),
        (JointEffect("j2s6s200_joint_2", "joint_scale", 5e-4), "", [5e-4]),
        (JointEffect("j2s6s200_joint_2", "drift_linear", 1e-6), "linear", [1e-6]),
    ],
)
def test_joint_angle_correction_is_the_hidden_offset(
    effect: JointEffect, variant: str, coefficients: list[float] | None
) -> None:
    """Corrected − read angles = the simulator's hidden offset δ (up to its mean, which the
    geometry absorbs), with the true coefficients."""
    truth = chain("kinova")
    spec = SimulationSpec(n_samples=40, seed=6, noise_sigma=NOISELESS, joint_effects=(effect,))
    recording = simulate_recording(truth, spec)
    bank = _bank(recording)
    j = truth.joint_names.index(effect.joint)
    kind = {"gear_periodic": "gear_periodic", "joint_scale": "joint_scale"}.get(
        effect.kind, "thermal_drift" if effect.kind.startswith("drift") else "backlash"
    )
    term = library_term(bank.probe, kind, j, variant, bank.clock_unit)
    values = (
        np.array(coefficients)
        if coefficients is not None
        else effect.size * np.array([np.cos(effect.phase_rad), np.sin(effect.phase_rad)])
    )
    corrected = correct_recording(bank, [(term, values)])
    assert corrected.applied == [term] and not corrected.skipped
    offsets = recording.joint_offsets_rad
    assert offsets is not None
    expected = offsets - offsets.mean(axis=0)
    change = corrected.joint_positions - recording.joint_positions
    np.testing.assert_allclose(change, expected, atol=1e-12)
    np.testing.assert_array_equal(corrected.measured_pose, recording.measured_pose)


@pytest.mark.parametrize("axis", ["measurement_z", "marker_z"])
def test_depth_scale_is_undone_exactly(axis: str) -> None:
    truth = chain("kinova")
    spec = SimulationSpec(n_samples=25, seed=8, noise_sigma=NOISELESS)
    plain = simulate_recording(truth, spec)
    scaled = simulate_recording(
        truth,
        dataclasses.replace(spec, depth_scale=3e-3, depth_axis=axis),  # type: ignore[arg-type]
    )
    assert np.abs(scaled.measured_pose - plain.measured_pose).max() > 1e-4
    np.testing.assert_allclose(
        undo_depth_scale(scaled.measured_pose, 3e-3, axis), plain.measured_pose, atol=1e-14
    )


def test_measurement_frame_drift_is_undone_up_to_a_constant_frame() -> None:
    truth = chain("kinova")
    drift = np.array([2e-6, -1e-6, 3e-6, 1e-6, 2e-6, -2e-6])  # per second
    spec = SimulationSpec(n_samples=30, seed=9, noise_sigma=NOISELESS)
    plain = simulate_recording(truth, spec)
    drifted = simulate_recording(truth, dataclasses.replace(spec, measurement_drift_per_s=drift))
    bank = _bank(drifted)
    term = library_term(
        bank.probe, "thermal_drift", None, "measurement_frame:linear", bank.clock_unit
    )
    assert is_correction(term)
    corrected = correct_recording(bank, [(term, drift)])
    constant = lie.se3_exp(drifted.time_s.mean() * drift)  # the centred feature's offset
    np.testing.assert_allclose(corrected.measured_pose, constant @ plain.measured_pose, atol=1e-12)


def test_calibration_terms_are_options_not_corrections() -> None:
    probe = probe_chain(chain("kinova"))
    for effect, j in [
        ("joint_compliance", 1),
        ("base_flex", 0),
        ("link_bending", 2),
        ("payload_mass", None),
        ("gravity_direction", None),
    ]:
        assert not is_correction(library_term(probe, effect, j, "", "s"))


@pytest.mark.parametrize(
    ("effect", "variant", "values", "applicable"),
    [
        (JointEffect("j2s6s200_joint_3", "gear_periodic", 3e-4, 2), "h2", [3e-4, 1e-4], True),
        (JointEffect("j2s6s200_joint_2", "backlash_load", 1e-3), "load", [1e-3], True),
        (JointEffect("j2s6s200_joint_2", "backlash_load", 1e-3), "load:2.5", [1e-3], True),
        (JointEffect("j2s6s200_joint_2", "joint_scale", 5e-4), "", [5e-4], True),
        (JointEffect("j2s6s200_joint_3", "backlash_direction", 1e-3), "direction", [1e-3], False),
        (JointEffect("j2s6s200_joint_2", "drift_linear", 1e-6), "linear", [1e-6], False),
    ],
)
def test_correction_at_single_configurations_equals_the_recording_correction(
    effect: JointEffect, variant: str, values: list[float], applicable: bool
) -> None:
    """Configuration by configuration, with the recording's feature means, the correction is
    what was undone on the recording (the same feature code); time and order terms refuse."""
    recording = simulate_recording(chain("kinova"), SimulationSpec(n_samples=40, seed=6))
    bank = _bank(recording)
    kind = {"gear_periodic": "gear_periodic", "joint_scale": "joint_scale"}.get(
        effect.kind, "thermal_drift" if effect.kind.startswith("drift") else "backlash"
    )
    j = bank.joint_names.index(effect.joint)
    term = library_term(bank.probe, kind, j, variant, bank.clock_unit)
    corrected = correct_recording(bank, [(term, np.array(values))])
    assert applicable_at_new_configurations(term) == applicable
    if not applicable:
        with pytest.raises(ValueError, match="more than the configuration"):
            configuration_corrections(term, np.array(values), corrected.feature_means)
        return
    axes = configuration_corrections(term, np.array(values), corrected.feature_means)
    q = recording.joint_positions
    gravity = bank.data.gravity_base
    one_by_one = np.vstack(
        [corrected_configurations(bank.probe, axes, q[n : n + 1], gravity, 0.0) for n in range(40)]
    )
    np.testing.assert_allclose(one_by_one, corrected.joint_positions, rtol=0, atol=1e-15)
    assert np.abs(one_by_one - q).max() > 1e-5
    np.testing.assert_allclose(
        corrected_configurations(
            bank.probe, axes, readings_for(bank.probe, axes, q, gravity, 0.0), gravity, 0.0
        ),
        q,
        rtol=0,
        atol=1e-15,
    )
