"""The batched ranking score (paper Eq. 12, 22–23) against the equations, one configuration at a
time, over random chains, configurations, covariance structures and task weights."""

from __future__ import annotations

from functools import cache

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from solver import lie
from solver.kinematics import ChainParameters
from solver.model import KinematicChain, sample_configurations
from solver.ranking import (
    RandomEffects,
    TaskMetric,
    UncertaintyModel,
    ee_covariance,
    score_configurations,
)
from tests.conftest import chain

FloatArray = np.ndarray


@cache
def _chain(name: str) -> KinematicChain:
    return chain(name, virtual_first=True)


def _frame_covariance(rng: np.random.Generator, kind: str) -> FloatArray:
    """One Σ_j (6, 6): zero, diagonal with some zero entries, translation or rotation only, or
    full of random rank (the scoring skips zero blocks and terms: every pattern is exercised)."""
    cov = np.zeros((6, 6))
    if kind == "diagonal":
        std = rng.uniform(0.0, 2e-3, 6) * (rng.random(6) < 0.7)
        cov[np.arange(6), np.arange(6)] = std**2
    elif kind in ("translation", "rotation"):
        block = slice(0, 3) if kind == "translation" else slice(3, 6)
        factor = rng.normal(scale=1e-3, size=(3, 3))
        cov[block, block] = factor @ factor.T
    elif kind == "full":
        factor = rng.normal(scale=1e-3, size=(6, int(rng.integers(1, 7))))
        cov = factor @ factor.T
    return cov


def _metric(rng: np.random.Generator, kind: str) -> TaskMetric:
    if kind == "diagonal weights":
        weights = rng.uniform(0.0, 1.0, 6) * (rng.random(6) < 0.8)
        scale = float(rng.uniform(0.05, 2.0))
        return TaskMetric.pose_weights(
            weights, rotation_scale_m_per_rad=scale, include_noise=bool(rng.integers(2))
        )
    if kind == "full W":
        return TaskMetric.pose_weights(rng.normal(size=(6, 6)))
    return TaskMetric.task_point(rng.normal(scale=0.1, size=3), rng.uniform(0.0, 2.0, 3))


@settings(max_examples=40, deadline=None)
@given(
    name=st.sampled_from(["kinova", "panda", "ur10"]),
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 30),
    frame_kinds=st.lists(
        st.sampled_from(["zero", "diagonal", "translation", "rotation", "full"]),
        min_size=8,
        max_size=8,
    ),
    metric_kind=st.sampled_from(["diagonal weights", "full W", "task point"]),
    chunk_size=st.integers(1, 12),
)
def test_batched_score_equals_the_equations_per_configuration(
    name: str, seed: int, n: int, frame_kinds: list[str], metric_kind: str, chunk_size: int
) -> None:
    """Reference: for each configuration alone, Σ_E from the chain evaluation's link Jacobians
    (Eq. 12, :func:`ee_covariance`), then ``tr(M Σ_E M^T)`` (Eq. 22–23) and ``diag Σ_E``."""
    rng = np.random.default_rng(seed)
    c = _chain(name)
    twists = rng.normal(scale=[2e-3] * 3 + [5e-3] * 3, size=(c.n_links, 6))
    compliance = rng.uniform(2e-4, 2e-3, len(c.compliance_axes))
    compliance *= rng.random(compliance.size) < 0.6  # some axes without compliance
    params = ChainParameters(c.nominal_links @ lie.se3_exp(twists), compliance)
    frames = np.array([_frame_covariance(rng, kind) for kind in frame_kinds[: c.n_joints + 1]])
    noise = rng.normal(scale=1e-4, size=(6, 6))
    model = UncertaintyModel.build(c, params, RandomEffects(frames, noise @ noise.T))
    metric = _metric(rng, metric_kind)
    q = sample_configurations(c, n, rng)
    payload = rng.uniform(0.0, 2.0, n)

    scores = score_configurations(model, q, metric, payload_kg=payload, chunk_size=chunk_size)

    m = metric.matrix
    expected_score, expected_variance = np.empty(n), np.empty((n, 6))
    for i in range(n):
        sigma = ee_covariance(
            model, q[i : i + 1], payload_kg=payload[i], include_noise=metric.include_noise
        )[0]
        expected_score[i] = np.trace(m @ sigma @ m.T)
        expected_variance[i] = np.diag(sigma)
    score_scale = max(np.abs(expected_score).max(), 1e-300)
    assert np.abs(scores.score - expected_score).max() <= 1e-12 * score_scale
    variance_scale = max(np.abs(expected_variance).max(), 1e-300)
    assert np.abs(scores.ee_variance - expected_variance).max() <= 1e-12 * variance_scale
    whole = score_configurations(model, q, metric, payload_kg=payload)
    assert np.array_equal(scores.score, whole.score)
    assert np.array_equal(scores.ee_variance, whole.ee_variance)
