"""Test data for the covariance solver, without the lead's simulator (no tests in here).

Per-sample frame Jacobians come from Pinocchio on the Kinova Jaco2 (j2s6s200) of
example-robot-data: the perturbation ξ_j of joint j acts right after the joint placement and
before the joint rotation, i.e. in the frame ``oM_parent · jointPlacement_j``. With
``B_j = (oM_parent · jointPlacement_j)^-1 · oMe`` its end-effector-frame Jacobian is
``A_j = Ad_{B_j}^-1`` (DESIGN.md §2), [v; w] order. Residuals are drawn from N(0, Σ_E(q)) (Eq. 12).

Test modules import it as ``from tests.solver import covariance_support as S``; its name does
not start with ``test_`` so pytest does not collect it. tests/service/test_covariance_pipeline.py
checks the same estimator through kincal's own model and simulator.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

JACO_EE_FRAME = "j2s6s200_end_effector"
TASK_WEIGHTS = np.diag([0.4, 0.4, 0.0, 0.1, 0.1, 0.0])
# Rotational σ (rad) of the six joint frames, growing toward the end-effector.
TRUE_ROTATION_STD_RAD = (
    np.array(
        [
            [0.5, 0.5, 0.6],
            [0.8, 0.7, 0.6],
            [1.2, 1.0, 0.9],
            [1.5, 1.6, 1.2],
            [2.2, 1.8, 2.0],
            [3.0, 2.6, 2.4],
        ]
    )
    * 1e-3
)
NOISE_STD = np.array([0.3e-3, 0.3e-3, 0.3e-3, 2e-3, 2e-3, 2e-3])  # m, m, m, rad, rad, rad


def find_kinova_urdf() -> Path:
    """The Jaco2 URDF shipped in example-robot-data (searched from the Pinocchio install)."""
    relative = Path("share/example-robot-data/robots/kinova_description/robots/kinova.urdf")
    for parent in Path(pin.__file__).resolve().parents:
        for candidate in (parent / "cmeel.prefix" / relative, parent / relative):
            if candidate.is_file():
                return candidate
    found = sorted(Path(sys.prefix).glob("**/kinova_description/robots/kinova.urdf"))
    if not found:
        raise FileNotFoundError("kinova.urdf of example-robot-data not found")
    return found[0]


@cache
def jaco_model() -> pin.Model:
    return pin.buildModelFromUrdf(str(find_kinova_urdf()))


def jaco_joint_names() -> tuple[str, ...]:
    model = jaco_model()
    return tuple(model.names[j] for j in range(1, model.njoints))


def jaco_frame_jacobians(n_samples: int, seed: int) -> FloatArray:
    """Ad_{B_j}^-1 for the 6 joint frames at random configurations, (N, 6, 6, 6)."""
    model = jaco_model()
    data = model.createData()
    ee_id = model.getFrameId(JACO_EE_FRAME)
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-np.pi, np.pi, size=(n_samples, model.nv))
    out = np.empty((n_samples, model.njoints - 1, 6, 6))
    for n in range(n_samples):
        q = _configuration(model, angles[n])
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacements(model, data)
        o_m_e = data.oMf[ee_id]
        for j in range(1, model.njoints):
            o_m_f = data.oMi[model.parents[j]] * model.jointPlacements[j]
            b_j = o_m_f.inverse() * o_m_e
            out[n, j - 1] = b_j.inverse().action
    return out


def _configuration(model: pin.Model, angles_rad: FloatArray) -> FloatArray:
    """Pinocchio q from one angle per joint: (cos, sin) pairs for continuous joints."""
    q = np.empty(model.nq)
    for j in range(1, model.njoints):
        joint = model.joints[j]
        angle = angles_rad[joint.idx_v]
        if joint.nq == 2:
            q[joint.idx_q : joint.idx_q + 2] = (np.cos(angle), np.sin(angle))
        else:
            q[joint.idx_q] = angle
    return q


def true_frame_covariances() -> FloatArray:
    """True Σ of the six joint frames, (6, 6, 6): rotational only, σ 0.5–3 mrad."""
    covs = np.zeros((6, 6, 6))
    for j in range(6):
        covs[j, 3:, 3:] = np.diag(TRUE_ROTATION_STD_RAD[j] ** 2)
    return covs


def sample_residuals(
    frame_jacobians: FloatArray,
    frame_covariances: FloatArray,
    noise_covariance: FloatArray,
    rng: np.random.Generator,
) -> FloatArray:
    """r_n ~ N(0, Σ_E(q_n)) (Eq. 12) by sampling every source, (N, d)."""
    n, n_frames, d, _ = frame_jacobians.shape
    sources = np.concatenate([frame_covariances, noise_covariance[None]], axis=0)
    eigval, eigvec = np.linalg.eigh(sources)
    root = eigvec * np.sqrt(np.clip(eigval, 0.0, None))[:, None, :]  # root @ root.T = Σ
    xi = np.einsum("fij,nfj->nfi", root, rng.standard_normal((n, n_frames + 1, 6)))
    jac = np.concatenate([frame_jacobians, np.broadcast_to(np.eye(6)[:d], (n, 1, d, 6))], axis=1)
    return np.einsum("nfdi,nfi->nd", jac, xi)


def task_scores(ee_covariances: FloatArray, weights: FloatArray = TASK_WEIGHTS) -> FloatArray:
    """Paper Eq. (22-23): tr(W Σ_E Wᵀ) per configuration, (N,)."""
    return np.einsum("ij,njk,ik->n", weights, ee_covariances, weights)


@dataclass(frozen=True)
class SimulatedCovarianceData:
    frame_jacobians: FloatArray  # (N, 6, d, 6)
    residuals: FloatArray  # (N, d), after the deterministic fit if one is simulated
    fit_jacobian: FloatArray | None  # (N, d, p)


def simulate_jaco(
    n_samples: int, seed: int, *, residual_dim: int = 6, deterministic_fit: bool = False
) -> SimulatedCovarianceData:
    """Jaco residuals with the true Σ; optionally after an OLS fit of the link corrections.

    The fit uses the link-correction Jacobians themselves (6 joint frames + a constant
    end-effector offset, 42 columns): r = (I - H) e with H the OLS hat matrix of the stacked
    Jacobian, as the deterministic calibration (Eq. 10) leaves it.
    """
    rng = np.random.default_rng(seed)
    jac = jaco_frame_jacobians(n_samples, seed)[:, :, :residual_dim]
    noise = np.diag(NOISE_STD**2)
    errors = sample_residuals(jac, true_frame_covariances(), noise, rng)
    if not deterministic_fit:
        return SimulatedCovarianceData(jac, errors, None)
    n, f, d, _ = jac.shape
    x = np.concatenate(
        [jac.transpose(0, 2, 1, 3).reshape(n, d, 6 * f), np.broadcast_to(np.eye(6)[:d], (n, d, 6))],
        axis=2,
    )
    stacked = x.reshape(n * d, -1)
    beta, *_ = np.linalg.lstsq(stacked, errors.reshape(-1), rcond=None)
    residuals = (errors.reshape(-1) - stacked @ beta).reshape(n, d)
    return SimulatedCovarianceData(jac, residuals, x)


def random_frame_jacobians(
    n_samples: int, n_frames: int, rng: np.random.Generator, *, residual_dim: int = 6
) -> FloatArray:
    """Ad^-1 of random transforms (lever arms up to ~0.7 m), (N, F, d, 6), for generic tests."""
    out = np.empty((n_samples, n_frames, 6, 6))
    for n in range(n_samples):
        for f in range(n_frames):
            rot = pin.exp3(rng.normal(size=3))
            out[n, f] = pin.SE3(rot, rng.uniform(-0.4, 0.4, 3)).inverse().action
    return out[:, :, :residual_dim]
