"""Configuration ranking (paper Eq. 12, 22–23): exactness against a literal per-configuration
reference, ordering properties, the vectorised gravity, and a Monte Carlo check that the score
predicts the task error of simulated executions."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import scipy.linalg
from hypothesis import given
from hypothesis import strategies as st

from solver import lie
from solver.errors import SolverError
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import KinematicChain, gravity_loads, sample_configurations
from solver.ranking import (
    PAPER_WEIGHTS,
    RandomEffects,
    TaskMetric,
    UncertaintyModel,
    ee_covariance,
    ranking_order,
    score_configurations,
)
from tests.conftest import chain


def _calibrated(c: KinematicChain, seed: int) -> ChainParameters:
    rng = np.random.default_rng(seed)
    twists = rng.normal(scale=[2e-3] * 3 + [5e-3] * 3, size=(c.n_links, 6))
    return ChainParameters(
        c.nominal_links @ lie.se3_exp(twists), rng.uniform(2e-4, 2e-3, len(c.compliance_axes))
    )


def _effects(c: KinematicChain, seed: int, *, full: bool) -> RandomEffects:
    rng = np.random.default_rng(seed)
    if full:
        factors = rng.normal(scale=1e-3, size=(c.n_joints + 1, 6, 6))
        noise = rng.normal(scale=1e-4, size=(6, 6))
        return RandomEffects(factors @ factors.transpose(0, 2, 1), noise @ noise.T)
    std = rng.uniform(0.0, 2e-3, size=(c.n_joints + 1, 6))
    std[1] = 0.0  # a frame without randomness is skipped by the fast path
    return RandomEffects.from_std(std, rng.uniform(1e-5, 1e-4, 6))


METRICS = {
    "paper": TaskMetric.pose_weights(),
    "paper+noise, 1 rad = 0.1 m": TaskMetric.pose_weights(
        PAPER_WEIGHTS, rotation_scale_m_per_rad=0.1, include_noise=True
    ),
    "full W": TaskMetric.pose_weights(np.random.default_rng(7).normal(size=(6, 6))),
    "task point": TaskMetric.task_point([0.01, -0.02, 0.05], [1.0, 2.0, 0.5]),
}


# --- the literal reference: Eq. (7) and Eq. (12) per configuration, scipy expm, no solver.lie --


def _hat(twist: np.ndarray) -> np.ndarray:
    out = np.zeros((4, 4))
    w = twist[3:]
    out[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    out[:3, 3] = twist[:3]
    return out


def _ad(x: np.ndarray) -> np.ndarray:
    """Paper Eq. (5)."""
    r, t = x[:3, :3], x[:3, 3]
    t_hat = _hat(np.r_[0.0, 0.0, 0.0, t])[:3, :3]
    return np.block([[r, t_hat @ r], [np.zeros((3, 3)), r]])


def _reference_ee_covariance(
    c: KinematicChain,
    params: ChainParameters,
    effects: RandomEffects,
    q: np.ndarray,
    loads: np.ndarray,
) -> np.ndarray:
    """Σ_E(q) - Σ_n for one configuration, Eq. (12) term by term."""
    factors = []  # factor i (after L_i): V_i · Exp(s_i q̃_i)
    for i in range(c.n_joints):
        angle = q[i]
        factor = np.eye(4)
        for a, axis in enumerate(c.compliance_axes):
            if axis.joint_index != i:
                continue
            deflection = params.compliance_rad_per_nm[a] * loads[a]
            if axis.is_joint_axis:
                angle = angle + deflection
            else:
                factor = factor @ scipy.linalg.expm(
                    _hat(np.r_[0.0, 0.0, 0.0, axis.axis]) * deflection
                )
        factors.append(factor @ scipy.linalg.expm(_hat(c.joint_screws[i]) * angle))
    sigma = np.zeros((6, 6))
    for j in range(c.n_links):
        after = np.eye(4)  # B_j: everything after L_j
        for i in range(j, c.n_joints):
            after = after @ factors[i] @ params.links[i + 1]
        jacobian = np.linalg.inv(_ad(after))
        sigma += jacobian @ effects.frame_covariances[j] @ jacobian.T
    return sigma


@pytest.mark.parametrize("name", ["kinova", "panda", "ur10"])
@pytest.mark.parametrize("full", [False, True], ids=["diagonal Σ", "full Σ"])
def test_batch_score_equals_literal_per_configuration_reference(name: str, full: bool) -> None:
    c = chain(name, virtual_first=True)
    params, effects = _calibrated(c, 1), _effects(c, 2, full=full)
    model = UncertaintyModel.build(c, params, effects)
    q = sample_configurations(c, 12, np.random.default_rng(3))
    payload = np.linspace(0.0, 1.5, 12)
    loads = gravity_loads(c, q, payload_kg=payload)  # Pinocchio RNEA
    reference = np.array(
        [_reference_ee_covariance(c, params, effects, q[n], loads[n]) for n in range(12)]
    )
    batch = ee_covariance(model, q, payload_kg=payload, include_noise=False)
    assert np.abs(batch - reference).max() <= 1e-12 * np.abs(reference).max()
    for label, metric in METRICS.items():
        noise = effects.noise_covariance if metric.include_noise else 0.0
        m = metric.matrix
        expected = np.array([np.trace(m @ (s + noise) @ m.T) for s in reference])
        scores = score_configurations(model, q, metric, payload_kg=payload, chunk_size=5)
        assert np.abs(scores.score - expected).max() <= 1e-12 * np.abs(expected).max(), label
        diag = np.diagonal(reference + noise, axis1=1, axis2=2)
        assert np.abs(scores.ee_variance - diag).max() <= 1e-12 * diag.max(), label


@given(st.permutations(list(range(10))))
def test_ranking_is_invariant_to_candidate_order(permutation: list[int]) -> None:
    c = chain("kinova", virtual_first=True)
    model = UncertaintyModel.build(c, _calibrated(c, 4), _effects(c, 5, full=False))
    q = sample_configurations(c, 10, np.random.default_rng(6))
    shuffled = q[permutation]
    base = score_configurations(model, q, TaskMetric.pose_weights())
    moved = score_configurations(model, shuffled, TaskMetric.pose_weights())
    assert np.array_equal(moved.score, base.score[permutation])
    assert np.array_equal(shuffled[moved.order()], q[base.order()])


@pytest.mark.parametrize("label", sorted(METRICS))
def test_scores_do_not_depend_on_position_in_the_batch(label: str) -> None:
    """Every metric path (diagonal W, full W and task point use different code) with full Σ:
    reversing the candidates and splitting them into chunks of 3 permutes the scores exactly,
    and a candidate repeated in another chunk gets exactly its score."""
    c = chain("kinova", virtual_first=True)
    model = UncertaintyModel.build(c, _calibrated(c, 23), _effects(c, 24, full=True))
    q = sample_configurations(c, 10, np.random.default_rng(25))
    metric = METRICS[label]
    base = score_configurations(model, q, metric)
    reverse = np.arange(10)[::-1]
    moved = score_configurations(model, q[reverse], metric, chunk_size=3)
    assert np.array_equal(moved.score, base.score[reverse])
    assert np.array_equal(moved.ee_variance, base.ee_variance[reverse])
    assert np.array_equal(q[reverse][moved.order()], q[base.order()])
    repeated = score_configurations(model, np.concatenate([q, q[[9, 0, 4]]]), metric, chunk_size=4)
    assert np.array_equal(repeated.score[10:], base.score[[9, 0, 4]])


def test_duplicates_get_equal_scores_and_ties_keep_input_order() -> None:
    c = chain("panda", virtual_first=True)
    model = UncertaintyModel.build(c, _calibrated(c, 7), _effects(c, 8, full=True))
    q = sample_configurations(c, 7, np.random.default_rng(9))
    q = np.concatenate([q, q[[3, 3, 0]]])
    scores = score_configurations(model, q, TaskMetric.pose_weights())
    assert scores.score[7] == scores.score[8] == scores.score[3]
    assert scores.score[9] == scores.score[0]
    order = scores.order().tolist()
    assert order.index(3) < order.index(7) < order.index(8)
    assert ranking_order(np.array([2.0, 1.0, 2.0, 1.0])).tolist() == [1, 3, 0, 2]


def test_zero_weights_give_equal_zero_scores() -> None:
    c = chain("ur10")
    model = UncertaintyModel.build(c, _calibrated(c, 10), _effects(c, 11, full=True))
    q = sample_configurations(c, 20, np.random.default_rng(12))
    for metric in (
        TaskMetric.pose_weights(np.zeros(6)),
        TaskMetric.pose_weights(np.zeros((6, 6))),
        TaskMetric.task_point([0, 0, 0.1], [0] * 3),
    ):
        scores = score_configurations(model, q, metric)
        assert np.all(scores.score == 0.0)
        assert np.all(scores.ee_variance > 0.0)  # the covariance itself is not zero


def test_best_configuration_is_the_argmin() -> None:
    c = chain("kinova")
    model = UncertaintyModel.build(c, _calibrated(c, 13), _effects(c, 14, full=False))
    q = sample_configurations(c, 50, np.random.default_rng(15))
    scores = score_configurations(model, q, TaskMetric.pose_weights())
    assert scores.best() == int(np.argmin(scores.score)) == int(scores.order()[0])
    assert np.all(np.diff(scores.score[scores.order()]) >= 0.0)


def test_task_point_score_is_the_variance_of_that_point() -> None:
    """δp = v + w × p: a twist ξ of the end effector moves the point p (EE frame) that much."""
    point = np.array([0.02, -0.01, 0.05])
    metric = TaskMetric.task_point(point, [1.0, 0.0, 0.0])  # only the x coordinate
    rng = np.random.default_rng(16)
    for twist in rng.normal(scale=1e-6, size=(5, 6)):
        moved = (lie.se3_exp(twist) @ np.r_[point, 1.0])[:3] - point
        assert np.isclose((metric.matrix @ twist)[0], moved[0], rtol=1e-5, atol=1e-15)
    origin = TaskMetric.task_point([0.0, 0.0, 0.0], [0.3, 0.2, 0.1])
    same = TaskMetric.pose_weights(np.sqrt([0.3, 0.2, 0.1, 0.0, 0.0, 0.0]))
    assert np.allclose(origin.quadratic_form, same.quadratic_form, atol=1e-15)


def test_bad_weights_and_covariances_are_solver_errors() -> None:
    with pytest.raises(SolverError, match="non-negative"):
        TaskMetric.pose_weights([0.4, 0.4, 0.0, -0.1, 0.1, 0.0])
    with pytest.raises(SolverError, match="6 numbers or a 6×6"):
        TaskMetric.pose_weights([0.4, 0.4, 0.1])
    with pytest.raises(SolverError, match="positive semi-definite"):
        RandomEffects(np.array([np.diag([1e-6, 0, 0, -1e-6, 0, 0])]), np.zeros((6, 6)))
    c = chain("kinova")
    with pytest.raises(SolverError, match="frame covariances"):
        UncertaintyModel.build(
            c, ChainParameters.nominal(c), RandomEffects(np.zeros((2, 6, 6)), np.zeros((6, 6)))
        )


def test_timings_split_gravity_jacobians_and_score() -> None:
    c = chain("kinova", virtual_first=True)
    model = UncertaintyModel.build(c, _calibrated(c, 17), _effects(c, 18, full=False))
    timings: dict[str, float] = {}
    q = sample_configurations(c, 300, np.random.default_rng(19))
    score_configurations(model, q, TaskMetric.pose_weights(), timings=timings, chunk_size=100)
    assert {"gravity", "jacobians", "score"} <= set(timings)
    assert all(v >= 0.0 for v in timings.values())


# --- Monte Carlo: the score predicts the task error of executions on the true robot ---------


def test_lowest_score_configuration_has_the_lowest_monte_carlo_task_error() -> None:
    """True Σ_j: a wobbling base (2 mrad, like the paper's flexing base plate) plus random
    joint-frame rotations growing toward the hand. Over configurations from folded to
    outstretched, the one with the lowest predicted EE x-y variance lands more precisely than
    the one with the highest, and the predicted variances match the simulated ones."""
    c = chain("kinova", virtual_first=True)
    params = _calibrated(c, 20)
    std = np.zeros((c.n_joints, 6))
    std[:, 3:] = np.linspace(2e-4, 1e-3, c.n_joints)[:, None]
    std[0, 3:] = 2e-3
    effects = RandomEffects.from_std(std, np.full(6, 1e-4))
    model = UncertaintyModel.build(c, params, effects)
    q = sample_configurations(c, 400, np.random.default_rng(21), range_fraction=0.8)
    metric = TaskMetric.task_point([0.0, 0.0, 0.05], [1.0, 1.0, 0.0])  # docking plane x-y
    scores = score_configurations(model, q, metric)
    best, worst = scores.best(), int(scores.order()[-1])
    assert scores.score[worst] > 3.0 * scores.score[best]  # the case has a clear difference
    rng = np.random.default_rng(22)
    draws = 4000
    empirical, docking_error = {}, {}
    for n in (best, worst):
        configs = np.repeat(q[n : n + 1], draws, axis=0)
        loads = gravity_loads(c, q[n : n + 1]).repeat(draws, axis=0)
        xi = rng.normal(size=(draws, c.n_joints, 6)) * std
        mean = forward_kinematics(c, params, configs[:1], loads[:1])[0]
        executed = forward_kinematics(c, params, configs, loads, perturbations=xi)
        point = executed @ np.r_[0.0, 0.0, 0.05, 1.0]
        local = (lie.inverse(mean) @ point[..., None])[:, :3, 0] - [0.0, 0.0, 0.05]
        empirical[n] = float(np.mean(np.sum(local[:, :2] ** 2, axis=1)))
        docking_error[n] = float(np.mean(np.linalg.norm(local[:, :2], axis=1)))
        # 4000 draws: relative standard error of a variance ≈ √(2/4000) ≈ 2 %.
        assert np.isclose(empirical[n], scores.score[n], rtol=0.1)
    assert empirical[best] < empirical[worst] / 3.0
    # The task error itself (mean x-y distance, paper §V-C), not only its second moment.
    assert docking_error[best] < docking_error[worst] / 1.5


# --- vectorised gravity (solver.gravity) against Pinocchio's RNEA ------------------------------


@pytest.mark.parametrize("virtual", [False, True], ids=["joint axes", "with virtual axes"])
def test_vectorised_gravity_equals_pinocchio(builtin_name: str, virtual: bool) -> None:
    c = chain(builtin_name, virtual_first=virtual)
    model = StaticGravityModel.from_chain(c)
    rng = np.random.default_rng(23)
    q = sample_configurations(c, 200, rng)
    q[0] = 0.0
    payload = rng.uniform(0.0, 3.0, 200)
    for gravity in (np.array([0.0, 0.0, -9.81]), np.array([1.2, -0.7, -9.6])):
        expected = gravity_loads(c, q, gravity_base=gravity, payload_kg=payload)
        got = static_gravity_loads(model, q, gravity_base=gravity, payload_kg=payload)
        assert np.abs(got - expected).max() < 1e-10
    assert np.abs(static_gravity_loads(model, q) - gravity_loads(c, q)).max() < 1e-10


@pytest.mark.parametrize("label", sorted(METRICS))
def test_small_and_large_batches_score_identically(label: str) -> None:
    """Small batches (a ranking request) take the fused numpy paths, large ones the row-by-row
    loops (lie.FUSED_MAX_ELEMENTS): the same arithmetic, so the same bits either way.

    Deflections stay below 1e-2 rad: lie.cos_sin picks its series or libm for a whole array,
    so above that a sample's last bit can depend on its chunk-mates (not this test's subject).
    """
    c = chain("panda", virtual_first=True)
    params = _calibrated(c, 31)
    compliance = params.compliance_rad_per_nm * 1e-2
    compliance[[0, 3]] = 0.0  # joints whose loads are skipped
    model = UncertaintyModel.build(
        c, ChainParameters(params.links, compliance), _effects(c, 32, full=True)
    )
    q = sample_configurations(c, 2 * lie.FUSED_MAX_ELEMENTS, np.random.default_rng(33))
    payload = np.linspace(0.0, 2.0, q.shape[0])
    metric = METRICS[label]
    large = score_configurations(model, q, metric, payload_kg=payload)
    small = score_configurations(model, q, metric, payload_kg=payload, chunk_size=100)
    assert np.array_equal(large.score, small.score)
    assert np.array_equal(large.ee_variance, small.ee_variance)


def test_score_plans_are_reused_per_metric_and_bounded() -> None:
    c = chain("ur10")
    model = UncertaintyModel.build(c, _calibrated(c, 34), _effects(c, 35, full=False))
    first = model.score_plan(TaskMetric.pose_weights())
    assert model.score_plan(TaskMetric.pose_weights()) is first
    assert model.score_plan(TaskMetric.pose_weights(include_noise=True)) is not first
    for scale in np.linspace(0.1, 10.0, 200):
        model.score_plan(TaskMetric.pose_weights(rotation_scale_m_per_rad=scale))
    assert len(model._plans) <= 64


def test_gravity_loads_of_selected_joints_only() -> None:
    c = chain("kinova", virtual_first=True)
    model = StaticGravityModel.from_chain(c)
    q = sample_configurations(c, 30, np.random.default_rng(36))
    full = static_gravity_loads(model, q, payload_kg=0.7)
    picked = {1, 3}
    part = static_gravity_loads(model, q, payload_kg=0.7, joints=picked)
    at = np.isin(model.axis_joint, list(picked))
    assert np.array_equal(part[:, at], full[:, at])
    assert not np.any(part[:, ~at])
    assert not np.any(static_gravity_loads(model, q, joints=()))


# --- batch-last SE(3) helpers added to solver.lie for this hot path ----------------------------


@given(
    st.sampled_from(["z", "-y", "x", "oblique"]),
    st.floats(-7.0, 7.0, allow_nan=False),
    st.floats(-3.0, 3.0, allow_nan=False),
)
def test_batch_last_rotation_and_screw_exp_match_pinocchio(
    axis_name: str, angle: float, pitch: float
) -> None:
    axis = {
        "z": np.array([0.0, 0.0, 1.0]),
        "-y": np.array([0.0, -1.0, 0.0]),
        "x": np.array([1.0, 0.0, 0.0]),
        "oblique": np.array([0.48, -0.6, 0.64]),
    }[axis_name]
    rotation = pin.exp3(axis * angle)
    x = np.random.default_rng(0).normal(size=(3, 4, 1))
    cos, sin = lie.cos_sin(np.array([angle]))
    assert np.allclose(lie.rotate_batch_last(x, axis, cos, sin)[..., 0], rotation @ x[..., 0])
    for screw in (
        np.r_[0.0, 0.0, 0.0, axis],
        np.r_[axis, 0.0, 0.0, 0.0],
        np.r_[pitch * axis, axis],
    ):
        expected = pin.exp6(screw * angle).homogeneous
        assert np.allclose(lie.screw_exp(screw, np.array([angle]))[0], expected, atol=1e-12)
        motion = lie.ScrewMotion.of(screw, np.array([angle - 1e-3])).advanced(np.array([1e-3]))
        moved = motion.rotate(np.eye(3)[:, :, None])[..., 0]
        assert np.allclose(moved, expected[:3, :3], atol=1e-12)


def _row_by_row_reference(matrix: np.ndarray, x: np.ndarray) -> np.ndarray:
    """combine_rows' definition, literally: first used column times its coefficient, then
    ``+= m[p, j] * x[j]`` in column order; zero coefficients skipped, empty rows 0."""
    out = np.zeros((matrix.shape[0], *x.shape[1:]))
    for p, row in enumerate(matrix):
        used = [j for j in range(row.size) if row[j] != 0.0]
        if used:
            out[p] = x[used[0]] * row[used[0]]
            for j in used[1:]:
                out[p] += row[j] * x[j]
    return out


@given(
    st.integers(1, 6),
    st.integers(1, 6),
    st.floats(0.0, 1.0),
    st.sampled_from([5, 3 * lie.FUSED_MAX_ELEMENTS]),
    st.integers(0, 2**32 - 1),
)
def test_row_combination_is_the_row_by_row_sum_bit_for_bit(
    rows: int, columns: int, zeros: float, n: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    matrix = rng.normal(size=(rows, columns))
    matrix[rng.random(matrix.shape) < zeros] = 0.0
    x = rng.normal(size=(columns, 2, n))
    expected = _row_by_row_reference(matrix, x)
    assert np.array_equal(lie.RowCombination.of(matrix)(x), expected)
    assert np.array_equal(lie.combine_rows(matrix, x[:, 0]), expected[:, 0])


@pytest.mark.parametrize("n", [7, 2 * lie.FUSED_MAX_ELEMENTS])
def test_cos_sin_rows_equal_cos_sin_of_each_row(n: int) -> None:
    rng = np.random.default_rng(37)
    angles = np.stack([rng.uniform(-3, 3, n), rng.uniform(-1e-3, 1e-3, n), np.zeros(n)])
    cos, sin = lie.cos_sin_rows(angles)
    for r, row in enumerate(angles):
        expected_cos, expected_sin = lie.cos_sin(row)
        assert np.array_equal(cos[r], expected_cos) and np.array_equal(sin[r], expected_sin)


def test_adjoint_inverse_in_place_and_applied() -> None:
    x = lie.se3_exp(np.random.default_rng(1).normal(size=(5, 6)))
    twist = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    out = np.full((5, 2, 6, 6), np.nan)
    lie.adjoint_inverse(x, out=out[:, 1])
    reference = np.linalg.inv(lie.adjoint(x))
    assert np.allclose(out[:, 1], reference, atol=1e-12) and np.isnan(out[:, 0]).all()
    assert np.allclose(lie.adjoint_inverse_apply(x, twist), reference @ twist, atol=1e-12)
    small = np.array([1e-3, -5e-4, 0.0])
    cos, sin = lie.cos_sin(small)
    assert np.array_equal(cos, cos) and np.allclose(cos, np.cos(small), rtol=0, atol=1e-18)
    assert np.allclose(sin, np.sin(small), rtol=1e-15, atol=0)


# --- benchmarks/ranking_throughput.py smoke test (tiny N, so it cannot rot) ---------------------


def test_throughput_benchmark_runs_and_matches_the_per_configuration_reference() -> None:
    from benchmarks import ranking_throughput

    rows, reference = ranking_throughput.run(("kinova",), (200,), repeats=1, reference_n=40)
    assert [(r.robot, r.structure, r.n) for r in rows] == [
        ("kinova", "diag", 200),
        ("kinova", "full", 200),
    ]
    assert all(r.total_per_s > 0 and min(r.stage_per_s.values()) > 0 for r in rows)
    full_rate, bare_rate, mismatch = reference["kinova"]
    assert full_rate > 0 and bare_rate > 0 and mismatch < 1e-12
    text = ranking_throughput.table(rows, reference)
    assert text.count("| kinova |") == 2 and "per-configuration Pinocchio" in text
