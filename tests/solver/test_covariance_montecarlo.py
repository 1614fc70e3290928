"""Monte Carlo acceptance check of Eq. (12) against the actual chain product (Eq. 7).

At a fixed configuration q, 10^5 sets of perturbations ξ_j ~ N(0, Σ_j) (full, correlated Σ_j
of realistic size: 0.5–3 mrad, 0.05–0.3 mm) and noise ε ~ N(0, Σ_n) are pushed through
:func:`solver.kinematics.forward_kinematics` (the simulator's own perturbation path: Exp(ξ_j)
right after L_j) and the noise is applied in the end-effector frame as the simulator does. The
residuals ``r = Log(X_mean⁻¹ X_perturbed)`` come from the product's
:func:`solver.kinematics.pose_residuals`. Their sample covariance must match Σ_E(q) of Eq. (12)
from both :func:`solver.ranking.ee_covariance` and
:func:`solver.covariance.likelihood.ee_covariance_batch` within 3 %.

Measure: whiten by Σ_E = LLᵀ and take ``‖L⁻¹ S L⁻ᵀ − I‖_F / ‖I‖_F`` (scale-free, so metres and
radians do not swamp each other); its sampling spread at 10^5 draws is ≈ √(42/N)/√6 ≈ 0.8 %, and
the second-order terms of Exp/Log are O(σ) ≈ 10⁻³ relative. Entry-wise, every
``|S_ab − Σ_ab| / √(Σ_aa Σ_bb)`` must be below 3 % too. The check discriminates: base-frame
residuals, a transposed adjoint or Ad_B instead of Ad_B⁻¹ miss by far more (asserted below).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest

from solver import lie
from solver.covariance.likelihood import ee_covariance_batch
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    pose_residuals,
    position_residuals,
)
from solver.model import KinematicChain, gravity_loads, sample_configurations
from solver.ranking import RandomEffects, UncertaintyModel, ee_covariance
from tests.conftest import chain as builtin_chain

N_DRAWS = 100_000
TOLERANCE = 0.03


@dataclass(frozen=True)
class Draws:
    """One configuration, its truth and 10^5 simulated measurements."""

    chain: KinematicChain
    params: ChainParameters
    q: np.ndarray  # (1, k) rad
    frame_covariances: np.ndarray  # (k, 6, 6) m², m·rad, rad²
    noise_covariance: np.ndarray  # (6, 6)
    mean_pose: np.ndarray  # (1, 4, 4) X_0E without perturbations
    measured_pose: np.ndarray  # (N, 4, 4) with perturbations and noise


def random_covariance(
    rng: np.random.Generator, translation_std_m: float, rotation_std_rad: float
) -> np.ndarray:
    """A full, correlated 6×6 Σ with per-axis σ around the given sizes (m, rad)."""
    std = np.r_[np.full(3, translation_std_m), np.full(3, rotation_std_rad)]
    std *= rng.uniform(0.5, 1.5, 6)
    factor = rng.normal(size=(6, 6))
    cov = factor @ factor.T + 3.0 * np.eye(6)
    correlation = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    return correlation * np.outer(std, std)


def sample_gaussian(rng: np.random.Generator, covariance: np.ndarray, n: int) -> np.ndarray:
    """n draws of N(0, Σ) for Σ (..., 6, 6): shape (n, ..., 6)."""
    root = np.linalg.cholesky(covariance)
    white = rng.standard_normal((n, *covariance.shape[:-1]))
    return np.einsum("...ij,n...j->n...i", root, white)


@cache
def draws(robot: str, config_seed: int) -> Draws:
    """Geometry errors and compliance as in a calibrated robot; σ grow towards the tip."""
    chain = builtin_chain(robot, virtual_first=robot == "panda")
    rng = np.random.default_rng(config_seed)
    k = chain.n_joints
    twists = rng.normal(scale=[1e-3] * 3 + [2e-3] * 3, size=(chain.n_links, 6))
    params = ChainParameters(
        chain.nominal_links @ lie.se3_exp(twists),
        rng.uniform(1e-4, 5e-4, len(chain.compliance_axes)),
    )
    rotation_std = np.linspace(5e-4, 3e-3, k)
    translation_std = np.linspace(5e-5, 3e-4, k)
    frames = np.stack(
        [random_covariance(rng, translation_std[j], rotation_std[j]) for j in range(k)]
    )
    noise = random_covariance(rng, 1e-4, 5e-4)
    q = sample_configurations(chain, 1, rng, 0.8)
    loads = np.repeat(gravity_loads(chain, q), N_DRAWS, axis=0)
    xi = sample_gaussian(rng, frames, N_DRAWS)  # (N, k, 6), ξ_j right after L_j
    perturbed = forward_kinematics(
        chain, params, np.repeat(q, N_DRAWS, axis=0), loads, perturbations=xi
    )
    measured = perturbed @ lie.se3_exp(sample_gaussian(rng, noise, N_DRAWS))  # ε in EE frame
    mean = forward_kinematics(chain, params, q, loads[:1])
    return Draws(chain, params, q, frames, noise, mean, measured)


def sample_covariance(residuals: np.ndarray) -> np.ndarray:
    centred = residuals - residuals.mean(axis=0)
    return centred.T @ centred / (residuals.shape[0] - 1)


def whitened_error(sample: np.ndarray, predicted: np.ndarray) -> float:
    """``‖L⁻¹ S L⁻ᵀ − I‖_F / ‖I‖_F`` with ``predicted = L Lᵀ``."""
    inv_root = np.linalg.inv(np.linalg.cholesky(predicted))
    white = inv_root @ sample @ inv_root.T
    identity = np.eye(predicted.shape[0])
    return float(np.linalg.norm(white - identity) / np.linalg.norm(identity))


def correlation_scale_error(sample: np.ndarray, predicted: np.ndarray) -> float:
    """``max_ab |S_ab − Σ_ab| / √(Σ_aa Σ_bb)``: per entry, relative to its natural scale."""
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    return float(np.max(np.abs(sample - predicted) / scale))


def eq12_by_hand(jacobians: np.ndarray, draws_: Draws) -> np.ndarray:
    """Σ_n + Σ_j J_j Σ_j J_jᵀ for given (k, 6, 6) Jacobians (used for the wrong variants)."""
    return draws_.noise_covariance + np.einsum(
        "jab,jbc,jdc->ad", jacobians, draws_.frame_covariances, jacobians
    )


CASES = [("kinova", 11), ("kinova", 12), ("panda", 21)]


@pytest.mark.parametrize(("robot", "config_seed"), CASES)
def test_eq12_equals_the_sample_covariance_of_simulated_poses(robot: str, config_seed: int):
    d = draws(robot, config_seed)
    k = d.chain.n_joints
    residuals = pose_residuals(np.broadcast_to(d.mean_pose, d.measured_pose.shape), d.measured_pose)
    sample = sample_covariance(residuals)
    # The mean residual is second order in σ: negligible against the spread.
    assert np.all(np.abs(residuals.mean(axis=0)) < 0.05 * np.sqrt(np.diag(sample)))

    model = UncertaintyModel.build(
        d.chain, d.params, RandomEffects(d.frame_covariances, d.noise_covariance)
    )
    from_ranking = ee_covariance(model, d.q)[0]
    loads = gravity_loads(d.chain, d.q)
    jac = evaluate_chain(d.chain, d.params, d.q, loads).link_jacobians[:, :k]  # (1, k, 6, 6)
    from_batch = ee_covariance_batch(jac, d.frame_covariances, d.noise_covariance)[0]
    np.testing.assert_allclose(from_batch, from_ranking, rtol=1e-10, atol=1e-18)

    for predicted in (from_ranking, from_batch):
        assert whitened_error(sample, predicted) < TOLERANCE
        assert correlation_scale_error(sample, predicted) < TOLERANCE

    # Position-only residuals R_modelᵀ(p_measured − p_model) follow the top-left 3×3 block.
    position = position_residuals(
        np.broadcast_to(d.mean_pose, d.measured_pose.shape), d.measured_pose
    )
    position_prediction = ee_covariance_batch(
        jac[:, :, :3], d.frame_covariances, d.noise_covariance
    )[0]
    assert whitened_error(sample_covariance(position), position_prediction) < TOLERANCE


@pytest.mark.parametrize(("robot", "config_seed"), CASES[:2])
def test_the_check_rejects_wrong_frames_and_wrong_adjoints(robot: str, config_seed: int):
    """Base-frame residuals, Ad_Bᵀ-type Jacobians and Ad_B (not its inverse) all fail by far."""
    d = draws(robot, config_seed)
    k = d.chain.n_joints
    loads = gravity_loads(d.chain, d.q)
    jac = evaluate_chain(d.chain, d.params, d.q, loads).link_jacobians[0, :k]  # J_j = Ad_{B_j}⁻¹
    right = eq12_by_hand(jac, d)
    ee_residuals = lie.se3_log(lie.inverse(d.mean_pose) @ d.measured_pose)
    base_residuals = lie.se3_log(d.measured_pose @ lie.inverse(d.mean_pose))
    assert whitened_error(sample_covariance(ee_residuals), right) < TOLERANCE
    assert whitened_error(sample_covariance(base_residuals), right) > 10 * TOLERANCE
    sample = sample_covariance(ee_residuals)
    transposed = eq12_by_hand(jac.transpose(0, 2, 1), d)
    not_inverted = eq12_by_hand(np.linalg.inv(jac), d)
    for wrong in (transposed, not_inverted):
        assert whitened_error(sample, wrong) > 10 * TOLERANCE
