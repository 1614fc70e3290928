"""Check poses (:mod:`solver.design.check_poses`): the information from per-pose sums by
Woodbury is the check's whitened ``ÃᵀÃ`` under its joint covariance, a part's separation is
never above its own information, and the chosen poses are distinct and beat the median random
set of as many poses on the criterion."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solver import check as C
from solver.design import check_poses as P
from solver.kinematics import evaluate_chain
from tests.solver.test_check import panda_at

PARAMETERS = 8


def panda_parts(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[C.Candidate]]:
    """At n random Panda poses: a random SPD local part (n, 6, 6), parameter Jacobian
    (n, 6, p), Cov(θ̂) (p, p) and the candidates."""
    chain, params, q, loads = panda_at(n, seed)
    evaluation = evaluate_chain(chain, params, q, loads)
    rng = np.random.default_rng(seed)
    roots = rng.normal(size=(n, 6, 6)) * 1e-3
    local = roots @ roots.transpose(0, 2, 1) + 1e-6 * np.eye(6)
    jacobian = rng.normal(size=(n, 6, PARAMETERS))
    root = rng.normal(size=(PARAMETERS, PARAMETERS)) * 1e-3
    candidates = C.candidates_at(chain, evaluation.link_jacobians, q)
    return local, jacobian, root @ root.T, candidates


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 10_000))
def test_woodbury_information_is_the_checks_whitened_gram(seed: int) -> None:
    local, jacobian, covariance, candidates = panda_parts(12, seed)
    terms = P.CheckPoseTerms.build(local, jacobian, covariance, candidates, 5, 0.05)
    rows = np.sort(np.random.default_rng(seed).choice(12, 5, replace=False))
    white = C.whitening(C.joint_covariance(local[rows], jacobian[rows], covariance))
    columns = white @ np.concatenate([c.jacobian[rows] for c in candidates], axis=2).reshape(30, -1)
    expected = columns.T @ columns
    information = terms.information(*terms.sums(rows))
    np.testing.assert_allclose(information, expected, atol=1e-8 * np.abs(expected).max())
    own = [np.linalg.eigvalsh(information[np.ix_(p.columns, p.columns)])[0] for p in terms.parts]
    assert np.all(terms.weakest(information) <= np.array(own) * (1 + 1e-9))


def test_the_chosen_poses_are_distinct_and_beat_the_median_random_set() -> None:
    local, jacobian, covariance, candidates = panda_parts(40, 3)
    terms = P.CheckPoseTerms.build(local, jacobian, covariance, candidates, 6, 0.05)
    scales = P.part_scales(terms)
    chosen = P.choose_check_poses(terms, 6, scales)
    assert np.unique(chosen).size == 6
    rng = np.random.default_rng(0)
    draws = np.stack([rng.choice(40, 6, replace=False) for _ in range(50)])
    random = P.worst_relative_size(terms, draws, scales)
    assert float(P.worst_relative_size(terms, chosen, scales)) < float(np.median(random))
