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


def test_ball_in_socket_covariances_recover_the_true_scatter() -> None:
    """Two sockets 50 mm apart, every configuration found for the robot perturbed by its own
    random joint-frame twists (Eq. 7; rotations 2e-4 rad) plus the ball's play (30 µm): the
    covariance calibration of the socket residuals (REML, the known distance pinning the
    scale) predicts the scatter the truth gives, mean tr Σ_E over the rows within 15 %."""
    from solver.covariance.likelihood import ee_covariance_batch
    from solver.measurement import FixedPoints, KnownDistance, ModelParameters
    from solver.measurement.simulate import configurations_at_points
    from solver.model import sample_configurations

    c = chain("panda")
    model = FixedPoints(2, (KnownDistance(0, 1, 0.05),))
    rng = np.random.default_rng(7)
    links = c.nominal_links.copy()
    links[-1][:3, 3] += np.array([0.01, -0.02, 0.12])  # the ball on the flange
    points = np.array([[0.5, 0.1, 0.3], [0.5, 0.15, 0.3]])
    truth = ModelParameters(links, np.zeros(len(c.compliance_axes)), points.reshape(-1))
    n, play_m, rotation_rad = 600, 3e-5, 2e-4
    sigma = np.zeros((c.n_joints, 6))
    sigma[:, 3:] = rotation_rad
    twists = rng.standard_normal((n, c.n_joints, 6)) * sigma
    group = np.arange(n) % 2
    targets = points[group] + play_m * rng.standard_normal((n, 3))
    start = sample_configurations(c, n, rng, 0.4)
    q = configurations_at_points(c, truth, targets, start, perturbations=twists)
    rows = MeasurementRows.of(q, np.zeros((n, len(c.compliance_axes))), None, group)
    fit = fit_measurement(c, model, rows, FitOptions())
    frames = tuple(range(c.n_joints))
    samples = covariance_samples(c, fit, rows, frames)
    estimate = estimate_from_samples(samples, make_layout(list(c.joint_names), 3), estimator="reml")
    predicted = ee_covariance_batch(
        samples.frame_jacobians, estimate.frame_covariances(), estimate.noise_covariance()
    )
    true_frames = np.stack([np.diag(s**2) for s in sigma])
    true = ee_covariance_batch(samples.frame_jacobians, true_frames, play_m**2 * np.eye(6))
    ratio = np.trace(predicted, axis1=1, axis2=2).mean() / np.trace(true, axis1=1, axis2=2).mean()
    assert abs(ratio - 1.0) < 0.15, ratio
    # the scatter is mostly the perturbations', not the play's: the test can tell them apart
    assert np.trace(true, axis1=1, axis2=2).mean() > 3 * 3 * play_m**2
