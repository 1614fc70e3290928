"""Issue 29 through the user's path: ``kincal calibrate`` of the real FR3 recording with its
defaults (the one-step held-out evaluation) against ``--heldout-method exact`` (every split's
fits iterated to convergence from the nominal robot), same rows and splits: the held-out errors,
the coverage of the predicted ellipsoids and the verdict are the same to what the result
states, and the result says which method made them."""

from __future__ import annotations

from pathlib import Path

import pytest

from schemas.calibration import CalibrationResult
from tests.service.cli_support import REAL_RECORDINGS, real_calibration, run_ok


def test_the_one_step_heldout_evaluation_gives_the_exact_ones_numbers_on_the_fr3(
    tmp_path_factory: pytest.TempPathFactory, tmp_path: Path
) -> None:
    one = real_calibration(tmp_path_factory, "fr3")  # kincal calibrate with its defaults
    out = tmp_path / "exact.json"
    run_ok(["calibrate", *REAL_RECORDINGS["fr3"], "--heldout-method", "exact", "-o", out])
    exact = CalibrationResult.model_validate_json(out.read_bytes())
    assert one.options.heldout_method == "one-step" and exact.options.heldout_method == "exact"
    assert "one-step" in one.evaluation.protocol and "(exact)" in exact.evaluation.protocol
    for phase in ("before", "after"):
        a, b = getattr(one.fit, phase).heldout, getattr(exact.fit, phase).heldout
        assert a is not None and b is not None
        assert a.translation_mean_mm == pytest.approx(b.translation_mean_mm, rel=0.01)
        assert a.rotation_mean_deg == pytest.approx(b.rotation_mean_deg, rel=0.03)
    assert one.predictive is not None and exact.predictive is not None
    a_cov, b_cov = one.predictive.coverage, exact.predictive.coverage
    assert a_cov is not None and b_cov is not None and a_cov.n_heldout == b_cov.n_heldout
    for a_level, b_level in zip(a_cov.levels, b_cov.levels, strict=True):
        assert abs(a_level.observed - b_level.observed) <= 0.02, a_level.level
    assert a_cov.mean_mahalanobis_sq == pytest.approx(b_cov.mean_mahalanobis_sq, rel=0.05)
    assert one.verdict.status == exact.verdict.status == "ok"
