"""σ of an axis the data cannot see (issue 13): :func:`unseen_axes` on constructed frame
Jacobians (the real FR3 case goes through ``kincal calibrate`` in
tests/service/test_not_identifiable_cli.py)."""

from __future__ import annotations

import numpy as np

from solver.covariance.identifiability import UNSEEN_RTOL, unseen_axes
from solver.covariance.layout import CovarianceLayout


def _layout(free: tuple[tuple[bool, ...], ...], noise: bool = True) -> CovarianceLayout:
    """Chain frames with these free axes, and an estimated noise frame (or a known Σ_n)."""
    names = tuple(f"frame{i}" for i in range(len(free)))
    if not noise:
        return CovarianceLayout(names, "diag", 6, free, None)
    return CovarianceLayout((*names, "noise"), "diag", 6, (*free, (True,) * 6), "noise")


def test_constant_silent_and_varying_axes() -> None:
    rng = np.random.default_rng(0)
    n = 50
    jacobians = rng.normal(size=(n, 1, 6, 6))  # every axis's effect varies
    jacobians[:, 0, :, 2] = np.array([0.1, 0.0, 0.0, 0.0, 0.3, 1.0])  # constant effect
    jacobians[:, 0, :, 4] = 0.0  # no effect at all
    # varying just above the threshold: seen
    jacobians[:, 0, :, 5] = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]) + 0.01 * rng.normal(
        size=(n, 6)
    )
    reasons = unseen_axes(jacobians, _layout(((True,) * 6,)))[0]
    assert reasons[2] is not None and "same at every configuration" in reasons[2]
    assert reasons[4] is not None and "no effect" in reasons[4]
    assert [r is None for r in reasons] == [True, True, False, True, False, True]
    # with a known Σ_n the level of a constant effect is seen; no effect is still no effect
    known = unseen_axes(jacobians, _layout(((True,) * 6,), noise=False))[0]
    assert [r is None for r in known] == [True, True, True, True, False, True]


def test_threshold_is_relative_rms_variation() -> None:
    """An effect u_n = u (1 + ε_n): the RMS variation of u uᵀ is ≈ 2·RMS(ε); just below and
    just above :data:`UNSEEN_RTOL`."""
    rng = np.random.default_rng(1)
    u = np.array([0.2, -0.1, 0.05, 0.3, 0.0, 1.0])
    eps = rng.normal(size=400)
    eps /= np.sqrt(np.mean(eps**2))
    for factor, seen in ((0.3, False), (3.0, True)):
        scale = 1.0 + 0.5 * factor * UNSEEN_RTOL * eps
        jacobians = np.zeros((400, 1, 6, 6))
        jacobians[:, 0, :, 0] = scale[:, None] * u
        jacobians[:, 0, :, 1] = rng.normal(size=(400, 6))
        reasons = unseen_axes(jacobians, _layout(((True,) * 6,)))[0]
        assert (reasons[0] is None) == seen, (factor, reasons[0])


def test_axes_not_estimated_are_not_reported() -> None:
    jacobians = np.zeros((10, 1, 6, 6))
    free = ((False, False, False, True, True, True),)
    reasons = unseen_axes(jacobians, _layout(free))[0]
    assert reasons[:3] == (None, None, None)
    assert all(r is not None for r in reasons[3:])
