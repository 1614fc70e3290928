"""Covariance samples of the measurement models (solver.measurement.fit.covariance_samples):
for a full-pose measurement they must be the pose path's, so the covariance calibration of a
pose recording is the same whichever way it is read."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from solver import lie
from solver.calibration import FitOptions
from solver.covariance.estimate import estimate_from_samples
from solver.covariance.layout import make_layout
from solver.covariance.likelihood import ee_covariance_batch
from solver.covariance.samples import ArraySamples
from solver.kinematics import parameter_names
from solver.measurement import (
    FullPose,
    MeasurementRows,
    MultiMarker,
    PoseComponents,
    Position,
    fit_measurement,
)
from solver.measurement.fit import covariance_samples
from solver.predictive import prediction_point
from solver.simulate import SimulationSpec, simulate_recording
from solver.stream.sums import covariance_spec
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


# --- noise layouts other than a pose's: several markers, chosen components ------------------


def _perturbed_recording(n: int, seed: int, rotation_rad: float = 3e-4):  # type: ignore[no-untyped-def]
    """A Panda recording with per-row random joint-frame rotations (Eq. 7) and no sensor noise
    (the tests add their own, laid out as their measurement sees it)."""
    c = chain("panda")
    sigma = np.zeros((c.n_joints, 6))
    sigma[:, 3:] = rotation_rad
    spec = SimulationSpec(n_samples=n, seed=seed, perturbation_sigma=sigma, noise_sigma=np.zeros(6))
    return c, sigma, simulate_recording(c, spec)


MARKER_OFFSETS_M = np.array([[0.12, 0.0, 0.05], [-0.08, 0.12, 0.05], [0.0, -0.12, 0.15]])


def _marker_positions(pose: np.ndarray, noise_m: np.ndarray) -> np.ndarray:
    """Markers (N, m, 3) at MARKER_OFFSETS_M on the measured pose, plus ``noise_m`` (N, m, 3)."""
    return (
        pose[:, None, :3, 3] + np.einsum("nij,mj->nmi", pose[:, :3, :3], MARKER_OFFSETS_M) + noise_m
    )


def _markers_estimate(c, recording, positions):  # type: ignore[no-untyped-def]
    model = MultiMarker(len(MARKER_OFFSETS_M))
    rows = MeasurementRows.of(recording.joint_positions, recording.loads_nm, positions)
    fit = fit_measurement(c, model, rows, FitOptions())
    samples = covariance_samples(c, fit, rows, tuple(range(c.n_joints)))
    spec = covariance_spec(
        model.dim, list(c.joint_names), range(c.n_joints), noise_rows=model.noise_rows
    )
    return samples, estimate_from_samples(samples, spec.layout, estimator="reml")


def test_a_noise_layout_equal_to_the_default_gives_the_same_estimate() -> None:
    """The noise layout is only a placement: a position recording's default noise (rows 0..2)
    written out as ``noise_rows`` gives the same estimate. Diagonal Σ: every entry (REML).
    Full Σ (the default layout also carries the noise's rotation entries, which have no
    effect): the same convex moment solution's Σ_E and the same REML optimum, to the solvers'
    tolerances."""
    c, _, recording = _perturbed_recording(200, 3)
    pose = recording.measured_pose.copy()
    pose[:, :3, 3] += 5e-5 * np.random.default_rng(3).standard_normal((200, 3))
    rows = MeasurementRows.of(recording.joint_positions, recording.loads_nm, pose)
    fit = fit_measurement(c, Position(), rows, FitOptions())
    frames = (2, 4, 6)
    samples = covariance_samples(c, fit, rows, frames)
    names = [c.joint_names[f] for f in frames]

    def both(structure: str, estimator: str):  # type: ignore[no-untyped-def]
        default = make_layout(names, 3, structure=structure)  # type: ignore[arg-type]
        explicit = make_layout(
            names,
            3,
            structure=structure,  # type: ignore[arg-type]
            noise_rows={"noise": ((0, 1, 2, -1, -1, -1),)},
        )
        return (
            estimate_from_samples(samples, default, estimator=estimator),  # type: ignore[arg-type]
            estimate_from_samples(samples, explicit, estimator=estimator),  # type: ignore[arg-type]
        )

    a, b = both("diag", "reml")
    np.testing.assert_allclose(a.frame_covariances(), b.frame_covariances(), rtol=1e-6, atol=1e-14)
    np.testing.assert_allclose(a.residual_noise(), b.residual_noise(), rtol=1e-6, atol=1e-14)
    a, b = both("full", "moment")
    predicted = [e.ee_covariance(samples.frame_jacobians, include_noise=True) for e in (a, b)]
    assert np.abs(predicted[0] - predicted[1]).max() < 1e-3 * np.abs(predicted[0]).max()
    a, b = both("full", "reml")
    assert abs(a.solution.objective - b.solution.objective) < 1e-2  # NLL of 200 rows, ~ -9000


def test_a_pose_recording_read_as_three_markers_gives_the_pose_paths_covariances() -> None:
    """The same perturbed rows (noise 20 µm / 20 µrad on the pose) read as a pose and as three
    markers rigidly on it (12–19 cm from the flange): the markers' link covariances predict
    the same tip-pose scatter Σ_f A_f Σ_f A_fᵀ (pose Jacobians, random part) as the pose
    path's, mean trace of the translation and of the rotation rows each within 10 % (seeds
    5–7: within 4 % and 7 %), and both see the truth within 15 %."""
    c, sigma, recording = _perturbed_recording(400, 5)
    rng = np.random.default_rng(5)
    pose = recording.measured_pose @ lie.se3_exp(2e-5 * rng.standard_normal((400, 6)))
    rows = MeasurementRows.of(recording.joint_positions, recording.loads_nm, pose)
    pose_fit = fit_measurement(c, FullPose(), rows, FitOptions())
    frames = tuple(range(c.n_joints))
    pose_samples = covariance_samples(c, pose_fit, rows, frames)
    pose_estimate = estimate_from_samples(
        pose_samples, make_layout(list(c.joint_names), 6), estimator="reml"
    )
    _, markers = _markers_estimate(c, recording, _marker_positions(pose, np.zeros((400, 3, 3))))

    def scatter(frame_covariances: np.ndarray) -> np.ndarray:
        """Mean trace of the tip's translation (m²) and rotation (rad²) covariance."""
        predicted = ee_covariance_batch(pose_samples.frame_jacobians, frame_covariances)
        variances = np.diagonal(predicted, axis1=1, axis2=2)
        return np.array([variances[:, :3].sum(1).mean(), variances[:, 3:].sum(1).mean()])

    truth = scatter(np.stack([np.diag(s**2) for s in sigma]))
    from_pose = scatter(pose_estimate.frame_covariances())
    from_markers = scatter(markers.frame_covariances())
    assert np.all(np.abs(from_markers / from_pose - 1.0) < 0.10), (from_markers, from_pose)
    assert np.all(np.abs(from_pose / truth - 1.0) < 0.15), (from_pose, truth)
    assert np.all(np.abs(from_markers / truth - 1.0) < 0.15), (from_markers, truth)


def test_simulated_markers_recover_the_perturbations_and_the_markers_noise() -> None:
    """Three markers, each with isotropic position noise of 40 µm (the same Σ_n, independent
    across markers) on rows with per-row joint-frame rotations (2e-4 rad): the predicted marker
    covariance (Eq. 12 with blockdiag(Σ_n, Σ_n, Σ_n)) matches the truth's, mean trace within
    15 %, and the noise σ is within 15 % of the truth."""
    c, sigma, recording = _perturbed_recording(500, 11, rotation_rad=2e-4)
    rng = np.random.default_rng(11)
    noise_std_m = 4e-5
    noise = noise_std_m * rng.standard_normal((500, 3, 3))
    samples, estimate = _markers_estimate(
        c, recording, _marker_positions(recording.measured_pose, noise)
    )
    predicted = estimate.ee_covariance(samples.frame_jacobians, include_noise=True)
    true_noise = noise_std_m**2 * np.eye(9)
    true = ee_covariance_batch(
        samples.frame_jacobians, np.stack([np.diag(s**2) for s in sigma]), true_noise
    )
    ratio = np.trace(predicted, axis1=1, axis2=2).mean() / np.trace(true, axis1=1, axis2=2).mean()
    assert abs(ratio - 1.0) < 0.15, ratio
    assert estimate.noise is not None and estimate.layout.is_tied
    np.testing.assert_array_equal(estimate.noise.estimated, [True] * 3 + [False] * 3)
    rms = float(np.sqrt(np.mean(estimate.noise.std[:3] ** 2)))
    assert abs(rms / noise_std_m - 1.0) < 0.15, rms
    # blockdiag: each marker's 3×3 block is Σ_n, the blocks between markers are 0
    noise_rows = estimate.residual_noise()
    for j in range(3):
        block = noise_rows[3 * j : 3 * j + 3, 3 * j : 3 * j + 3]
        np.testing.assert_allclose(block, estimate.noise.covariance[:3, :3], atol=1e-20)
    assert not np.any(noise_rows[:3, 3:])
    # the perturbations dominate the scatter: the test can tell them from the noise
    assert np.trace(true - true_noise, axis1=1, axis2=2).mean() > np.trace(true_noise)


@pytest.mark.parametrize("structure", ["diag", "full"])
def test_tied_noise_statistics_and_gradients_match_brute_force(structure: str) -> None:
    """A noise shared by two placements (two markers): the moment statistics (Eq. 14) equal
    ``Σ_n K_nᵀK_n`` with K_n built entry by entry from ``Σ_E(e_p)`` of Eq. (12) written out
    with both placements, and the ML and REML gradients equal central differences of their
    NLLs."""
    from solver.covariance.layout import vech_w
    from solver.covariance.likelihood import (
        fisher_information_ml,
        fisher_information_reml,
        fit_basis_transform,
        gaussian_nll,
        restricted_nll,
        theta_gradient,
    )
    from solver.covariance.statistics import build_moment_statistics

    rng = np.random.default_rng(2)
    n, d = 30, 6
    layout = make_layout(
        ["a", "b"],
        d,
        structure=structure,  # type: ignore[arg-type]
        noise_rows={"noise": ((0, 1, 2, -1, -1, -1), (3, 4, 5, -1, -1, -1))},
    )
    jacobians = rng.standard_normal((n, 2, d, 6))
    residuals = rng.standard_normal((n, d))
    placement = np.zeros((2, d, 6))
    for k in range(2):
        placement[k, 3 * k : 3 * k + 3, :3] = np.eye(3)

    def sigma_e(theta: np.ndarray) -> np.ndarray:  # Eq. (12), every placement written out
        covs = layout.frame_covariances(theta)
        chain_part = np.einsum("nfia,fab,nfjb->nij", jacobians, covs[:2], jacobians)
        return chain_part + sum(u @ covs[2] @ u.T for u in placement)

    design = np.stack([vech_w(sigma_e(e)) for e in np.eye(layout.n_params)], axis=2)  # (n, D, Q)
    stats = build_moment_statistics(residuals, jacobians, layout)
    z = vech_w(residuals[:, :, None] * residuals[:, None, :])
    np.testing.assert_allclose(stats.gram, np.einsum("ndp,ndq->pq", design, design), rtol=1e-10)
    np.testing.assert_allclose(stats.cross, np.einsum("ndp,nd->p", design, z), rtol=1e-10)

    theta = np.where(layout.is_variance, 0.5 + rng.random(layout.n_params), 0.05)
    samples = ArraySamples(residuals, jacobians, rng.standard_normal((n, d, 4)))
    transform = fit_basis_transform(samples)
    for nll in (
        lambda t: gaussian_nll(t, samples, layout),
        lambda t: restricted_nll(t, samples, transform, layout),
    ):
        gradient = theta_gradient(layout, nll(theta)[1])
        step = 1e-6
        numeric = [
            (nll(theta + step * e)[0] - nll(theta - step * e)[0]) / (2 * step)
            for e in np.eye(layout.n_params)
        ]
        np.testing.assert_allclose(gradient, numeric, rtol=1e-5, atol=1e-6)
    # the expected information (standard errors): ½ tr(V⁻¹V_p V⁻¹V_q), and with P for REML
    big = scipy.linalg.block_diag(*sigma_e(theta))
    parts = [scipy.linalg.block_diag(*sigma_e(e)) for e in np.eye(layout.n_params)]
    inverse = np.linalg.inv(big)
    x = samples.fit_jacobian.reshape(n * d, -1)
    projector = inverse - inverse @ x @ np.linalg.solve(x.T @ inverse @ x, x.T @ inverse)
    for matrix, info in (
        (inverse, fisher_information_ml(theta, jacobians, layout)),
        (projector, fisher_information_reml(theta, jacobians, samples.fit_jacobian, layout)),
    ):
        brute = np.array([[0.5 * np.trace(matrix @ a @ matrix @ b) for b in parts] for a in parts])
        np.testing.assert_allclose(info, brute, rtol=1e-8, atol=1e-12)


def test_plane_contact_covariances_recover_the_true_scatter() -> None:
    """A plane contact (tz, rx, ry in the plane's frame) with per-row joint-frame rotations
    (3e-4 rad) and the contact's own noise (0.2 mm, 0.5 mrad: about a third of each
    component's variance): the covariance of the three components predicted by Eq. 12 (noise
    of the chosen components only, measurement frame) matches the truth's, mean variance
    within 15 % for the height and for the tilts (seeds 13, 15, 16: within 9 %). The height's
    noise is not told apart from the base frame's vertical play (both constant in the plane's
    frame): the rule splits them, the prediction is what the data fix."""
    c, sigma, recording = _perturbed_recording(500, 13)
    rng = np.random.default_rng(13)
    noise_std = np.array([2e-4, 5e-4, 5e-4])  # tz m, rx ry rad
    pose = recording.measured_pose.copy()
    pose[:, 2, 3] += noise_std[0] * rng.standard_normal(500)
    tilt = np.zeros((500, 3))
    tilt[:, :2] = noise_std[1:] * rng.standard_normal((500, 2))
    pose[:, :3, :3] = lie.so3_exp(tilt) @ pose[:, :3, :3]  # Log(R_m Rᵀ) = the tilt
    model = PoseComponents(("tz", "rx", "ry"))
    rows = MeasurementRows.of(recording.joint_positions, recording.loads_nm, pose)
    fit = fit_measurement(c, model, rows, FitOptions())
    samples = covariance_samples(c, fit, rows, tuple(range(c.n_joints)))
    spec = covariance_spec(
        model.dim, list(c.joint_names), range(c.n_joints), noise_rows=model.noise_rows
    )
    estimate = estimate_from_samples(samples, spec.layout, estimator="reml")
    predicted = estimate.ee_covariance(samples.frame_jacobians, include_noise=True)
    true = ee_covariance_batch(
        samples.frame_jacobians, np.stack([np.diag(s**2) for s in sigma]), None
    ) + np.diag(noise_std**2)
    for rows_of in ([0], [1, 2]):
        p = np.diagonal(predicted, axis1=1, axis2=2)[:, rows_of].mean()
        t = np.diagonal(true, axis1=1, axis2=2)[:, rows_of].mean()
        assert abs(p / t - 1.0) < 0.15, (rows_of, p, t)
    assert estimate.noise is not None
    assert list(estimate.noise.estimated) == [False, False, True, True, True, False]


@settings(max_examples=8, deadline=None)
@given(
    n_markers=st.integers(1, 3),
    structure=st.sampled_from(["diag", "full"]),
    estimator=st.sampled_from(["moment", "reml"]),
    seed=st.integers(0, 2**16),
)
def test_tied_noise_estimates_are_positive_semidefinite(
    n_markers: int, structure: str, estimator: str, seed: int
) -> None:
    """Whatever the residuals (here: Gaussian with a random, unrelated covariance), every Σ_f,
    the shared Σ_n and the Σ_E predicted with the markers' blockdiag noise are PSD."""
    rng = np.random.default_rng(seed)
    d, n = 3 * n_markers, 60
    layout = make_layout(
        ["a", "b"],
        d,
        structure=structure,  # type: ignore[arg-type]
        noise_rows={"noise": MultiMarker(n_markers).noise_rows["noise"]},
    )
    mixing = rng.standard_normal((d, d))
    samples = ArraySamples(
        rng.standard_normal((n, d)) @ mixing.T * 1e-3,
        1e-2 * rng.standard_normal((n, 2, d, 6)),
        rng.standard_normal((n, d, 2)),
    )
    estimate = estimate_from_samples(
        samples,
        layout,
        estimator=estimator,  # type: ignore[arg-type]
        standard_errors=False,
    )
    tolerance = 1e-12
    for covariance in [*estimate.frame_covariances(), estimate.noise_covariance()]:
        assert np.linalg.eigvalsh(covariance).min() >= -tolerance * max(1.0, covariance.max())
    predicted = estimate.ee_covariance(samples.frame_jacobians, include_noise=True)
    assert np.linalg.eigvalsh(predicted).min() >= -1e-15
