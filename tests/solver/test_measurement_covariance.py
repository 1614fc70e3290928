"""Covariance samples of the measurement models (solver.measurement.fit.covariance_samples):
for a full-pose measurement they must be the pose path's, so the covariance calibration of a
pose recording is the same whichever way it is read."""

from __future__ import annotations

import numpy as np

from solver.calibration import FitOptions
from solver.covariance.estimate import estimate_from_samples
from solver.covariance.layout import make_layout
from solver.covariance.samples import ArraySamples
from solver.kinematics import parameter_names
from solver.measurement import FullPose, MeasurementRows, fit_measurement
from solver.measurement.fit import covariance_samples
from solver.predictive import prediction_point
from solver.simulate import SimulationSpec, simulate_recording
from tests.conftest import chain


def test_a_pose_measurement_gives_the_pose_paths_samples_and_estimate() -> None:
    c = chain("panda")
    sigma = np.zeros((c.n_joints, 6))
    sigma[:, 3:] = 3e-4  # rad, every joint frame
    sigma[2, :3] = 2e-4  # m, one frame's translation
    recording = simulate_recording(
        c, SimulationSpec(n_samples=300, seed=4, perturbation_sigma=sigma)
    )
    rows = MeasurementRows.of(
        recording.joint_positions, recording.loads_nm, recording.measured_pose
    )
    fit = fit_measurement(c, FullPose(), rows, FitOptions())
    frames = (1, 3, 4, 6)  # a subset, out of the chain's order of columns on purpose
    mine = covariance_samples(c, fit, rows, frames)

    names = parameter_names(c)
    estimated = np.array([names.index(n) for n in fit.estimated], dtype=np.intp)
    point = prediction_point(
        c, fit.params, estimated, recording.joint_positions, recording.loads_nm, 6
    )
    reference = ArraySamples(
        fit.residuals, point.frame_jacobians[:, list(frames)], point.parameter_jacobian
    )
    np.testing.assert_allclose(np.abs(mine.residuals), np.abs(reference.residuals), atol=1e-15)
    # Eq. 12 uses A_f Σ_f A_fᵀ: the per-frame products must agree (a Jacobian's sign may not)
    for ours, theirs in zip(
        mine.frame_jacobians.transpose(1, 0, 2, 3),
        reference.frame_jacobians.transpose(1, 0, 2, 3),
        strict=True,
    ):
        np.testing.assert_allclose(
            ours @ ours.transpose(0, 2, 1), theirs @ theirs.transpose(0, 2, 1), atol=1e-12
        )

    layout = make_layout([c.joint_names[f] for f in frames], 6)
    a = estimate_from_samples(mine, layout, estimator="reml")
    b = estimate_from_samples(reference, layout, estimator="reml")
    np.testing.assert_allclose(a.theta, b.theta, rtol=1e-7, atol=1e-16)
    # and it sees the perturbation: frame 3's rotation σ near the truth (300 poses)
    rotation_std = np.sqrt(np.diag(a.frame_covariances()[1])[3:])
    assert np.all(np.abs(rotation_std - 3e-4) < 1.5e-4), rotation_std
