"""solver.check: the tests of ``kincal check`` (issue 33) on simulated check poses."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from solver import check as C
from solver import lie
from solver.kinematics import ChainParameters, evaluate_chain, forward_kinematics, pose_residuals
from solver.model import KinematicChain, sample_configurations
from tests.conftest import chain as builtin_chain

N_POSES = 10


def random_covariance(rng: np.random.Generator, n: int, d: int, p: int = 8) -> np.ndarray:
    """A joint covariance like a calibration's: SPD blocks per pose (mm², mrad² scale) plus a
    parameter part shared by every pose."""
    scale = np.r_[np.full(3, 1e-3), np.full(d - 3, 2e-3)][:d]
    blocks = []
    for _ in range(n):
        a = rng.normal(size=(d, d)) * scale
        blocks.append(a @ a.T + np.diag(scale**2) * 0.1)
    jacobian = rng.normal(size=(n, d, p)) * 0.3
    parameters = np.diag(rng.uniform(0.1, 1.0, p)) * 1e-6
    return C.joint_covariance(np.array(blocks), jacobian, parameters)


def draw(rng: np.random.Generator, covariance: np.ndarray, n: int, d: int) -> np.ndarray:
    factor = np.linalg.cholesky(covariance)
    return (factor @ rng.normal(size=n * d)).reshape(n, d)


def panda_at(n: int, seed: int) -> tuple[KinematicChain, ChainParameters, np.ndarray, np.ndarray]:
    chain = builtin_chain("panda")
    params = ChainParameters.nominal(chain)
    q = sample_configurations(chain, n, np.random.default_rng(seed))
    loads = np.zeros((n, len(chain.compliance_axes)))
    return chain, params, q, loads


def sizes_at(model: C.DriftModel) -> dict[str, float]:
    """The stated sizes at the check's critical p-values."""
    return {s.name: s.size for s in C.stated_sizes(model)}


def panda_check(seed: int, d: int = 6) -> tuple[np.ndarray, list[C.Candidate], C.DriftModel]:
    """A joint covariance, the candidates and the drift model at 10 random Panda poses."""
    chain, params, q, loads = panda_at(N_POSES, seed)
    evaluation = evaluate_chain(chain, params, q, loads)
    rng = np.random.default_rng(seed)
    covariance = random_covariance(rng, N_POSES, d)
    candidates = C.candidates_at(chain, evaluation.link_jacobians[:, :, :d], q)
    return covariance, candidates, C.DriftModel.build(covariance, candidates, 0.05)


@pytest.mark.parametrize("d", [6, 3])
def test_exact_model_false_alarm_rate_is_the_level(d: int) -> None:
    """Residuals drawn from the predictive covariance itself, at 10 Panda poses with their
    candidate changes: the check says drifted in about the level's share of draws (issue 33:
    within ±2 points)."""
    covariance, _candidates, model = panda_check(7, d)
    rng = np.random.default_rng(8)
    draws = 600
    alarms = sum(
        C.pose_verdict(draw(rng, covariance, N_POSES, d), model, 0.05).verdict == "drifted"
        for _ in range(draws)
    )
    assert 0.03 <= alarms / draws <= 0.07


def test_global_statistic_is_chi2_with_shared_parameter_part() -> None:
    """Σ d² under the joint covariance has mean n·d even when the parameter part correlates
    the poses (the sum of per-pose d² alone would not be χ²_{n·d})."""
    rng = np.random.default_rng(3)
    covariance = random_covariance(rng, N_POSES, 6)
    statistics = [
        C.global_test(draw(rng, covariance, N_POSES, 6).ravel(), covariance, 0.05).statistic
        for _ in range(3000)
    ]
    assert np.mean(statistics) == pytest.approx(60.0, rel=0.03)
    assert np.var(statistics) == pytest.approx(120.0, rel=0.15)


def test_one_far_pose_is_a_bad_sample_and_the_rest_decide() -> None:
    covariance, _candidates, model = panda_check(11)
    residuals = draw(np.random.default_rng(12), covariance, N_POSES, 6)
    clean = C.pose_verdict(residuals, model, 0.05)
    assert clean.verdict == "holds" and clean.bad_samples.size == 0
    residuals[4, :3] += 0.008  # 8 mm off, like the FR3's bad rows
    tests = C.pose_verdict(residuals, model, 0.05)
    assert tests.verdict == "holds"
    assert tests.bad_samples.tolist() == [4]
    assert 4 not in tests.used
    assert "pose(s) 5 far off" in tests.reason


def test_a_bad_sample_does_not_hide_a_drift() -> None:
    """A joint offset and one pose 8 mm off: that pose is set aside, and the others still
    show the offset."""
    covariance, candidates, model = panda_check(11)
    offset = next(c for c in candidates if c.name == "panda_joint2 offset")
    residuals = draw(np.random.default_rng(12), covariance, N_POSES, 6)
    residuals += offset.jacobian[:, :, 0] * 0.003  # about twice the stated size
    residuals[4, :3] += 0.008
    tests = C.pose_verdict(residuals, model, 0.05)
    assert tests.verdict == "drifted"
    assert tests.drift is not None and tests.drift.located.best is not None
    assert tests.drift.located.best.candidate.name == "panda_joint2 offset"


def test_a_shift_of_every_pose_is_drift_not_bad_samples() -> None:
    covariance, _candidates, model = panda_check(11)
    residuals = draw(np.random.default_rng(12), covariance, N_POSES, 6)
    residuals[:, :3] += 0.004
    tests = C.pose_verdict(residuals, model, 0.05)
    assert tests.verdict == "drifted"
    assert tests.bad_samples.size == 0


def test_too_few_poses_are_inconclusive() -> None:
    covariance, candidates, _model = panda_check(1)
    rows = np.arange(2)
    two = C.subset_covariance(covariance, rows, 6)
    residuals = draw(np.random.default_rng(2), two, 2, 6)
    small = C.DriftModel.build(two, C.subset_candidates(candidates, rows), 0.05)
    verdict = C.pose_verdict(residuals, small, 0.05)
    assert verdict.verdict == "inconclusive"


# --- candidates at a real chain ---------------------------------------------------------------


@given(st.integers(0, 6), st.integers(0, 1000))
@settings(max_examples=10)
def test_joint_offset_column_is_the_residual_of_a_shifted_joint(joint: int, seed: int) -> None:
    """A joint standing δ further than its reading moves the residual by ``J_j S_j δ``."""
    chain, params, q, loads = panda_at(4, seed)
    evaluation = evaluate_chain(chain, params, q, loads)
    columns = C.joint_offset_columns(evaluation.link_jacobians, chain.joint_screws)
    delta_rad = 1e-6
    moved = q.copy()
    moved[:, joint] += delta_rad
    measured = forward_kinematics(chain, params, moved, loads)
    residual = pose_residuals(evaluation.pose, measured)
    np.testing.assert_allclose(residual / delta_rad, columns[:, :, joint], atol=1e-5)


@given(st.integers(0, 5), st.integers(0, 1000))
@settings(max_examples=10)
def test_base_columns_are_a_move_of_the_robot_base(axis: int, seed: int) -> None:
    """The robot base moved by δ along its own axes, ``T_mb ← T_mb Exp(δ)``."""
    chain, params, q, loads = panda_at(4, seed)
    rng = np.random.default_rng(seed)
    base = lie.se3_exp(rng.normal(size=6) * 0.3)  # the measurement frame → robot base
    params = ChainParameters(params.links.copy(), params.compliance_rad_per_nm)
    params.links[0] = base @ chain.nominal_links[0]
    evaluation = evaluate_chain(chain, params, q, loads)
    columns = C.base_columns(evaluation.link_jacobians, chain.nominal_links[0])
    delta = np.zeros(6)
    delta[axis] = 1e-6
    moved = ChainParameters(params.links.copy(), params.compliance_rad_per_nm)
    moved.links[0] = base @ lie.se3_exp(delta) @ chain.nominal_links[0]
    measured = forward_kinematics(chain, moved, q, loads)
    residual = pose_residuals(evaluation.pose, measured)
    np.testing.assert_allclose(residual / 1e-6, columns[:, :, axis], atol=1e-5)


@given(st.integers(0, 6), st.integers(0, 1000))
@settings(max_examples=15)
def test_score_test_locates_a_concealed_joint_offset(joint: int, seed: int) -> None:
    """An offset three times the stated size on one joint is flagged and located to that
    joint, its 95 % interval holding the true size."""
    covariance, candidates, model = panda_check(seed)
    sizes = sizes_at(model)
    name = f"panda_joint{joint + 1} offset"
    offset_rad = 3.0 * sizes[name]
    offset = next(c for c in candidates if c.name == name)
    rng = np.random.default_rng(seed + 1)
    residuals = draw(rng, covariance, N_POSES, 6) + offset.jacobian[:, :, 0] * offset_rad
    assert C.pose_verdict(residuals, model, 0.05).verdict == "drifted"
    located = model.tests(residuals).located
    assert located.best is not None
    names = {located.best.candidate.name, *(t.candidate.name for t in located.alternatives)}
    assert name in names
    if located.best.candidate.name == name:  # its estimate within 4σ (a 95 % interval
        sigma = np.sqrt(located.best.covariance[0, 0])  # misses one example in 20)
        assert abs(located.best.estimate[0] - offset_rad) <= 4.0 * sigma


def test_nothing_located_without_a_change() -> None:
    covariance, _candidates, model = panda_check(5)
    residuals = draw(np.random.default_rng(6), covariance, N_POSES, 6)
    located = model.tests(residuals).located
    assert located.best is None
    assert all(t.adjusted > 0.05 for t in located.tests)


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("panda_joint2 offset", "panda_joint2 offset"),
        ("base translation", "base frame"),
        ("tool rotation", "tool frame"),
    ],
)
def test_stated_size_is_detected_and_located_90_percent_of_the_time(
    name: str, expected: str
) -> None:
    """The promise against Monte Carlo through the whole verdict: a change of the stated size
    along its worst direction is called drifted, and located to its candidate, in at least
    90 % of draws (2 points of Monte Carlo slack)."""
    covariance, candidates, model = panda_check(21)
    stated = sizes_at(model)
    kind, _, part = name.partition(" ")
    candidate = next(c for c in candidates if c.name == name or c.kind == kind)
    columns = candidate.jacobian
    if part in ("translation", "rotation"):
        columns = columns[:, :, :3] if part == "translation" else columns[:, :, 3:]
    white = C.whitening(covariance)
    direction = C.worst_direction(white @ columns.reshape(N_POSES * 6, -1))
    shift = (columns @ direction) * stated[name]
    rng = np.random.default_rng(22)
    draws = 300
    detected = located = 0
    for _ in range(draws):
        tests = C.pose_verdict(draw(rng, covariance, N_POSES, 6) + shift, model, 0.05)
        detected += tests.verdict == "drifted"
        best = None if tests.drift is None else tests.drift.located.best
        located += (
            tests.verdict == "drifted" and best is not None and (best.candidate.name == expected)
        )
    assert detected / draws >= 0.88
    assert located / draws >= 0.88


def test_global_power_formula_against_monte_carlo() -> None:
    """The global test alone at a non-centrality of :func:`detectable_noncentrality` rejects
    in 90 % of draws."""
    covariance, candidates, _model = panda_check(21)
    white = C.whitening(covariance)
    offset = next(c for c in candidates if c.name == "panda_joint4 offset").jacobian[:, :, 0]
    noncentrality = C.detectable_noncentrality(white.shape[0], 0.025)
    shift = offset * np.sqrt(noncentrality) / np.linalg.norm(white @ offset.ravel())
    rng = np.random.default_rng(23)
    draws = 3000
    detected = sum(
        C.global_test(
            (draw(rng, covariance, N_POSES, 6) + shift).ravel(), covariance, 0.025
        ).rejects
        for _ in range(draws)
    )
    assert detected / draws == pytest.approx(0.9, abs=0.02)


def test_noncentrality_gives_the_power() -> None:
    """``chndtrinc`` is solved for the right tail: at λ the test at 5 % on 60 dof has 90 %
    power (checked against the non-central χ² of scipy.stats)."""
    import scipy.stats

    dof = 60
    noncentrality = C.detectable_noncentrality(dof, 0.05, 0.9)
    threshold = scipy.stats.chi2.ppf(0.95, dof)
    assert scipy.stats.ncx2.sf(threshold, dof, noncentrality) == pytest.approx(0.9, abs=1e-6)


def test_log_survival_ranks_where_p_values_underflow() -> None:
    assert C.chi2_log_survival(30.0, 1) == pytest.approx(np.log(C.chi2_survival(30.0, 1)))
    assert C.chi2_log_survival(2000.0, 1) < C.chi2_log_survival(2000.0, 6) < 0.0
