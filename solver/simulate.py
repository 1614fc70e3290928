"""Simulated recordings with known ground truth.

A "true robot" is the nominal chain with per-link geometric errors, joint compliance, virtual
compliant axes (base flex), random local perturbations ξ_i ~ N(0, Σ_i) (Eq. 7), measurement noise
ε ~ N(0, Σ_n) in the end-effector frame, an unknown measurement frame (camera/tracker) and an
unknown marker offset, plus gross outliers. Samples come in execution order with timestamps.
Everything random is drawn from one ``numpy.random.Generator`` seeded by ``spec.seed``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import (
    STANDARD_GRAVITY_BASE,
    KinematicChain,
    gravity_loads,
    sample_configurations,
)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SimulationSpec:
    """What the true robot and the measurement look like.

    σ values are standard deviations: ``geometry_*`` of the per-link errors δ_i,
    ``perturbation_sigma`` (k, 6) of ξ_i per joint frame ([v; w], m and rad),
    ``noise_sigma`` (6,) of ε in the end-effector frame. ``compliance_rad_per_nm`` maps compliance
    axis names of the chain to true values (axes not named are rigid). ``measurement_frame``
    (4, 4) is the robot base in the measurement frame; ``tool_offset`` (4, 4) the marker in the
    tip frame. Outliers add a rotation of ``outlier_rotation_rad`` about a random axis and a
    translation of ``outlier_translation_m`` in a random direction.
    """

    n_samples: int
    seed: int
    geometry_translation_m: float = 1e-3
    geometry_rotation_rad: float = 2e-3
    compliance_rad_per_nm: dict[str, float] = field(default_factory=dict)
    perturbation_sigma: FloatArray | None = None
    noise_sigma: FloatArray = field(
        default_factory=lambda: np.array([5e-5, 5e-5, 5e-5, 5e-5, 5e-5, 5e-5])
    )
    measurement_frame: FloatArray = field(default_factory=lambda: np.eye(4))
    tool_offset: FloatArray = field(default_factory=lambda: np.eye(4))
    outlier_fraction: float = 0.0
    outlier_rotation_rad: float = np.radians(10.0)
    outlier_translation_m: float = 5e-3
    joint_range_fraction: float = 1.0
    sample_period_s: float = 4.0
    gravity_base: FloatArray = field(default_factory=lambda: STANDARD_GRAVITY_BASE.copy())
    payload_kg: float = 0.0


@dataclass(frozen=True)
class SimulatedRecording:
    """Measurements and the truth behind them.

    ``measured_pose`` (N, 4, 4): marker in the measurement frame; ``true_pose`` the same without
    noise and outliers but with the random perturbations; ``true_mean_pose`` without those too.
    """

    joint_positions: FloatArray
    measured_pose: FloatArray
    time_s: FloatArray
    true_params: ChainParameters
    link_errors: FloatArray  # (k+1, 6) δ_i
    perturbation_sigma: FloatArray  # (k, 6)
    noise_sigma: FloatArray  # (6,)
    outliers: NDArray[np.intp]
    true_pose: FloatArray
    true_mean_pose: FloatArray
    loads_nm: FloatArray


def true_parameters(
    chain: KinematicChain, spec: SimulationSpec, rng: np.random.Generator
) -> tuple[ChainParameters, FloatArray]:
    """Nominal links with errors δ_i, W folded into L_1 and the marker offset into L_{k+1}."""
    errors = np.concatenate(
        [
            rng.normal(0.0, spec.geometry_translation_m, size=(chain.n_links, 3)),
            rng.normal(0.0, spec.geometry_rotation_rad, size=(chain.n_links, 3)),
        ],
        axis=1,
    )
    links = chain.nominal_links @ lie.se3_exp(errors)
    links[0] = spec.measurement_frame @ links[0]
    links[-1] = links[-1] @ spec.tool_offset
    names = [axis.name for axis in chain.compliance_axes]
    unknown = set(spec.compliance_rad_per_nm) - set(names)
    if unknown:
        raise ValueError(f"unknown compliance axes {sorted(unknown)}; chain has {names}")
    compliance = np.array([spec.compliance_rad_per_nm.get(name, 0.0) for name in names])
    return ChainParameters(links, compliance), errors


def simulate_recording(chain: KinematicChain, spec: SimulationSpec) -> SimulatedRecording:
    """Draw a recording of ``spec.n_samples`` configurations from the true robot."""
    rng = np.random.default_rng(spec.seed)
    params, errors = true_parameters(chain, spec, rng)
    q = sample_configurations(chain, spec.n_samples, rng, spec.joint_range_fraction)
    loads = gravity_loads(chain, q, gravity_base=spec.gravity_base, payload_kg=spec.payload_kg)
    sigma_xi = (
        np.zeros((chain.n_joints, 6))
        if spec.perturbation_sigma is None
        else spec.perturbation_sigma
    )
    xi = rng.normal(size=(spec.n_samples, chain.n_joints, 6)) * sigma_xi
    mean_pose = forward_kinematics(chain, params, q, loads)
    true_pose = forward_kinematics(chain, params, q, loads, perturbations=xi)
    noise = rng.normal(size=(spec.n_samples, 6)) * spec.noise_sigma
    measured = true_pose @ lie.se3_exp(noise)
    n_outliers = round(spec.outlier_fraction * spec.n_samples)
    outliers = np.sort(rng.choice(spec.n_samples, size=n_outliers, replace=False))
    measured[outliers] = measured[outliers] @ lie.se3_exp(_gross_errors(spec, n_outliers, rng))
    return SimulatedRecording(
        joint_positions=q,
        measured_pose=measured,
        time_s=spec.sample_period_s * np.arange(spec.n_samples, dtype=np.float64),
        true_params=params,
        link_errors=errors,
        perturbation_sigma=sigma_xi,
        noise_sigma=np.asarray(spec.noise_sigma, dtype=float),
        outliers=outliers,
        true_pose=true_pose,
        true_mean_pose=mean_pose,
        loads_nm=loads,
    )


def _gross_errors(spec: SimulationSpec, n: int, rng: np.random.Generator) -> FloatArray:
    """Local twists of outliers: a fixed-size rotation and translation in random directions."""
    directions = rng.normal(size=(n, 2, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    return np.concatenate(
        [
            spec.outlier_translation_m * directions[:, 0],
            spec.outlier_rotation_rad * directions[:, 1],
        ],
        axis=1,
    )


def look_at(eye_m: FloatArray, target_m: FloatArray) -> FloatArray:
    """Robot base in the frame of a camera at ``eye`` looking at ``target`` (z forward), (4, 4).

    This is what L_1 carries for camera measurements."""
    forward = np.asarray(target_m, dtype=float) - np.asarray(eye_m, dtype=float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    camera_in_base = np.eye(4)
    camera_in_base[:3, :3] = np.column_stack([right, down, forward])
    camera_in_base[:3, 3] = eye_m
    return lie.inverse(camera_in_base)
