"""The damped step rule of Eq. (10) (Levenberg–Marquardt, issue 13)."""

from __future__ import annotations

import itertools

import numpy as np

from solver.calibration import (
    FitOptions,
    NormalEquations,
    damped_step,
    normal_equations,
    predicted_decrease,
)
from solver.kinematics import ChainParameters, forward_kinematics
from solver.measurement import FullPose
from solver.measurement.pose import fit_deterministic, initial_parameters
from solver.model import gravity_loads, sample_configurations
from tests.conftest import chain


def _normal(seed: int) -> NormalEquations:
    rng = np.random.default_rng(seed)
    design = rng.normal(size=(40, 5)) * np.array([1.0, 10.0, 1e-3, 3.0, 0.1])
    return normal_equations(design, rng.normal(size=40))


def test_undamped_step_is_the_least_squares_solution() -> None:
    normal = _normal(0)
    expected = np.linalg.solve(normal.gram, normal.cross)
    assert np.allclose(damped_step(normal, 0.0), expected, rtol=1e-10, atol=0.0)


def test_damped_step_solves_the_marquardt_equation() -> None:
    normal = _normal(1)
    damping = 0.7
    step = damped_step(normal, damping)
    lhs = (normal.gram + damping * np.diag(np.diag(normal.gram))) @ step
    assert np.allclose(lhs, normal.cross, rtol=1e-10, atol=1e-12)
    # more damping: a shorter step with a smaller, still positive, predicted decrease
    steps = [damped_step(normal, lam) for lam in (0.0, 0.1, 10.0, 1e4)]
    scaled = [np.linalg.norm(s * np.sqrt(np.diag(normal.gram))) for s in steps]
    assert all(a > b for a, b in itertools.pairwise(scaled))
    decreases = [predicted_decrease(normal, s) for s in steps]
    assert all(a > b > 0.0 for a, b in itertools.pairwise(decreases))
    # very large damping: the scaled gradient D⁻¹ Aᵀy / λ
    assert np.allclose(steps[-1] * 1e4, normal.cross / np.diag(normal.gram), rtol=1e-3)


def test_far_start_converges_to_the_exact_robot() -> None:
    """Noiseless UR10 poses, started with every link rotated by up to 0.25 rad and moved by
    up to 5 cm: the damped iteration reaches the exact robot within the default iteration
    limit, and the undamped step there is zero (a stationary point, the one Gauss–Newton
    would stop at)."""
    c = chain("ur10")
    rng = np.random.default_rng(4)
    q = sample_configurations(c, 150, rng)
    loads = gravity_loads(c, q)
    truth = ChainParameters(c.nominal_links, np.zeros(len(c.compliance_axes)))
    twists = np.hstack(
        [rng.uniform(-0.05, 0.05, (c.n_links, 3)), rng.uniform(-0.05, 0.05, (c.n_links, 3))]
    )
    truth = truth.with_link_corrections(twists * 0.2)
    measured = forward_kinematics(c, truth, q, loads)
    start = initial_parameters(c, q, measured, measurement=FullPose())
    bad = np.hstack(
        [rng.uniform(-0.05, 0.05, (c.n_links, 3)), rng.uniform(-0.25, 0.25, (c.n_links, 3))]
    )
    start = ChainParameters(start.with_link_corrections(bad).links, start.compliance_rad_per_nm)
    fit = fit_deterministic(
        c, q, measured, loads, measurement=FullPose(), start=start, options=FitOptions()
    )
    assert fit.converged and fit.iterations < FitOptions().max_iterations
    predicted = forward_kinematics(c, fit.params, q, loads)
    assert np.abs(predicted - measured).max() < 1e-9


def test_implausible_link_components_are_pruned_to_nominal() -> None:
    """Inner-link components whose standard error is beyond any physical URDF error are
    fixed at their nominal value; the measurement frame (L_1) and the tool (L_{k+1}) never."""
    from solver import lie
    from solver.calibration import (
        PLAUSIBLE_LINK_ROTATION_RAD,
        PLAUSIBLE_LINK_TRANSLATION_M,
        implausible_columns,
        without_columns,
    )

    c = chain("kinova")
    rng = np.random.default_rng(2)
    params = ChainParameters(c.nominal_links, np.zeros(len(c.compliance_axes)))
    params = params.with_link_corrections(rng.normal(scale=0.05, size=(c.n_links, 6)))
    last = 6 * (c.n_links - 1)
    keep = np.array([0, 5, 6, 9, 13, last - 1, last + 3], dtype=np.intp)
    big_t, big_r = 2 * PLAUSIBLE_LINK_TRANSLATION_M, 2 * PLAUSIBLE_LINK_ROTATION_RAD
    stderr = np.array([big_t, big_r, big_t, big_r, 0.5 * big_t, big_r, big_r])
    # L_1 (0, 5) and the tool (last + 3) may be anywhere; 13 (ty of L_3) is plausible
    assert implausible_columns(c, params, keep, stderr).tolist() == [6, 9, last - 1]
    fixed = without_columns(c, params, np.array([6, 9, last - 1], dtype=np.intp))
    for link, components in ((1, [0, 3]), (c.n_links - 2, [5])):
        correction = lie.se3_log(lie.inverse(c.nominal_links[link]) @ fixed.links[link])
        before = lie.se3_log(lie.inverse(c.nominal_links[link]) @ params.links[link])
        assert np.allclose(correction[components], 0.0, atol=1e-12)
        others = [i for i in range(6) if i not in components]
        assert np.allclose(correction[others], before[others], atol=1e-12)
    untouched = [i for i in range(c.n_links) if i not in (1, c.n_links - 2)]
    assert np.array_equal(fixed.links[untouched], params.links[untouched])
