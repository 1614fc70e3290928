"""The model outlier rule's Σ_E step for measurement types other than pose/position
(service.app.calibrate_measurement.screen_by_covariance): each row judged against its own predicted
covariance of Eq. 12, with the type's noise layout."""

from __future__ import annotations

import numpy as np

from schemas.calibration import CalibrationOptions
from service.app.calibrate_measurement import screen, screen_by_covariance
from solver.calibration import FitOptions
from solver.covariance.estimate import estimate_from_samples
from solver.measurement import MeasurementRows, MultiMarker, fit_measurement
from solver.measurement.fit import covariance_samples
from solver.stream.calibrate import CovarianceSettings
from solver.stream.sums import covariance_spec
from tests.solver.test_measurement_covariance import _marker_positions, _perturbed_recording


def test_a_marker_off_the_rigid_cluster_is_removed_by_the_sigma_e_step() -> None:
    """Three markers, per-row joint-frame rotations (2e-4 rad: ~0.3 mm of scatter per
    component) and 40 µm marker noise; in rows 7, 50 and 222 marker 1 alone is off by 0.4 mm.
    Per component that is inside the robust first step's threshold (the rigid scatter hides
    it), but the three markers no longer move as one body: against its own Σ_E (Eq. 12 with
    blockdiag(Σ_n, Σ_n, Σ_n)) each such row is far out. The Σ_E step removes exactly those
    rows."""
    c, _, recording = _perturbed_recording(300, 21, rotation_rad=2e-4)
    rng = np.random.default_rng(21)
    noise = 4e-5 * rng.standard_normal((300, 3, 3))
    bad = np.array([7, 50, 222])
    noise[bad, 0, 0] += 4e-4
    positions = _marker_positions(recording.measured_pose, noise)
    model = MultiMarker(3)
    rows = MeasurementRows.of(recording.joint_positions, recording.loads_nm, positions)
    options = CalibrationOptions()
    assert options.screening == "model"
    first = fit_measurement(c, model, rows, FitOptions())
    kept, _ = screen(model, first, options)
    assert kept[bad].all()  # the first step does not see them
    used = rows.take(np.flatnonzero(kept))
    fit = first if kept.all() else fit_measurement(c, model, used, FitOptions())
    spec = covariance_spec(
        model.dim, list(c.joint_names), range(c.n_joints), noise_rows=model.noise_rows
    )
    settings = CovarianceSettings(spec, "reml", "auto")
    estimate = estimate_from_samples(
        covariance_samples(c, fit, used, spec.frames), spec.layout, estimator="reml"
    )
    kept, refit, _, note = screen_by_covariance(
        c, rows, kept, fit, estimate, settings, options, FitOptions()
    )
    np.testing.assert_array_equal(np.flatnonzero(~kept), bad)
    assert refit.residuals.shape[0] == 297
    assert "Σ_E step" in note
