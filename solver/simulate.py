"""Simulated recordings with known ground truth.

A "true robot" is the nominal chain with per-link geometric errors, joint compliance, virtual
compliant axes (base flex), random local perturbations ξ_i ~ N(0, Σ_i) (Eq. 7), measurement noise
ε ~ N(0, Σ_n) in the end-effector frame, an unknown measurement frame (camera/tracker) and an
unknown marker offset, plus gross outliers. For missing-physics discovery it can also hide joint
angle errors (gear, backlash, scale, drift, off-library shapes), a depth scale of the sensor, a
tilted gravity or an undeclared payload (``gravity_base``, ``payload_kg``), a drifting
measurement frame and a blocked acquisition order. Samples come in execution order with timestamps.
Everything random is drawn from one ``numpy.random.Generator`` seeded by ``spec.seed``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.arrays import FloatArray
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import (
    STANDARD_GRAVITY_BASE,
    ComplianceAxis,
    KinematicChain,
    gravity_loads,
    sample_configurations,
)

JointEffectKind = Literal[
    "gear_periodic",
    "backlash_load",
    "backlash_direction",
    "joint_scale",
    "drift_linear",
    "drift_warmup",
    "quadratic",
    "load_quadratic",
    "bump",
]


@dataclass(frozen=True)
class JointEffect:
    """A hidden error of one joint's angle: the robot is at ``q_read + δ_n`` (rad).

    ``gear_periodic``: δ = size·sin(harmonic·q + phase); ``backlash_load``: ±size/2 by the sign
    of the joint's gravity torque, uniform in the dead band where |τ| < ``float_below_nm``
    (backlash with nothing to take it up); ``backlash_direction``: read on the motor side, the
    link lags the motion by size/2, δ = −size/2·sign(q[n] − q[n−1]) (0 for the first sample);
    ``joint_scale``: size·q; ``drift_linear``:
    size·t (rad/s); ``drift_warmup``: size·(1 − exp(−t/T)). Outside the discovery library:
    ``quadratic``: size·q² (rad/rad²); ``load_quadratic``: size·τ·|τ| (rad/(N·m)², a spring
    that softens under load, τ the joint's gravity torque); ``bump``: size·exp(−½((q − c)/w)²)
    with c = ``centre_rad``, w = ``width_rad`` (a local gear defect, e.g. a dented tooth).
    """

    joint: str
    kind: JointEffectKind
    size: float
    harmonic: int = 1
    phase_rad: float = 0.0
    time_constant_s: float = 600.0
    float_below_nm: float = 0.0
    centre_rad: float = 0.0
    width_rad: float = 0.3


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
    joint_range_fraction: float | FloatArray = 1.0  # scalar or per joint (k,)
    sample_period_s: float = 4.0
    gravity_base: FloatArray = field(default_factory=lambda: STANDARD_GRAVITY_BASE.copy())
    payload_kg: float = 0.0
    # Hidden effects for missing-physics discovery (defaults: none, behaviour unchanged).
    joint_effects: tuple[JointEffect, ...] = ()
    depth_scale: float = 0.0  # the sensor's depth reading is off by this factor
    depth_axis: Literal["measurement_z", "marker_z"] = "measurement_z"
    # Linear drift of the measurement frame (camera/tracker), twist [v; w] per second (m, rad)
    # in the measurement frame: the sensor reports Exp(t·drift) · X.
    measurement_drift_per_s: FloatArray | None = None
    order_by_joint: str | None = None  # blocked acquisition: samples sorted by this joint


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
    joint_offsets_rad: FloatArray | None = None  # (N, k) hidden angle errors δ, if any


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
    q = sample_configurations(chain, spec.n_samples, rng, spec.joint_range_fraction)  # type: ignore[arg-type]
    if spec.order_by_joint is not None:
        q = q[np.argsort(q[:, chain.joint_names.index(spec.order_by_joint)], kind="stable")]
    loads = gravity_loads(chain, q, gravity_base=spec.gravity_base, payload_kg=spec.payload_kg)
    sigma_xi = (
        np.zeros((chain.n_joints, 6))
        if spec.perturbation_sigma is None
        else spec.perturbation_sigma
    )
    xi = rng.normal(size=(spec.n_samples, chain.n_joints, 6)) * sigma_xi
    time_s = spec.sample_period_s * np.arange(spec.n_samples, dtype=np.float64)
    offsets = _joint_offsets(chain, spec, q, time_s) if spec.joint_effects else None
    q_true = q if offsets is None else q + offsets
    mean_pose = _sensor(forward_kinematics(chain, params, q_true, loads), spec, time_s)
    true_pose = _sensor(
        forward_kinematics(chain, params, q_true, loads, perturbations=xi), spec, time_s
    )
    noise = rng.normal(size=(spec.n_samples, 6)) * spec.noise_sigma
    measured = true_pose @ lie.se3_exp(noise)
    n_outliers = round(spec.outlier_fraction * spec.n_samples)
    outliers = np.sort(rng.choice(spec.n_samples, size=n_outliers, replace=False))
    measured[outliers] = measured[outliers] @ lie.se3_exp(
        gross_error_twists(n_outliers, spec.outlier_translation_m, spec.outlier_rotation_rad, rng)
    )
    return SimulatedRecording(
        joint_positions=q,
        measured_pose=measured,
        time_s=time_s,
        true_params=params,
        link_errors=errors,
        perturbation_sigma=sigma_xi,
        noise_sigma=np.asarray(spec.noise_sigma, dtype=float),
        outliers=outliers,
        true_pose=true_pose,
        true_mean_pose=mean_pose,
        loads_nm=loads,
        joint_offsets_rad=offsets,
    )


def _joint_offsets(
    chain: KinematicChain, spec: SimulationSpec, q: FloatArray, time_s: FloatArray
) -> FloatArray:
    """Hidden joint-angle errors δ (N, k) of ``spec.joint_effects`` (see :class:`JointEffect`).

    Random parts (floating backlash) draw from their own stream, so the main stream and every
    recording without them stay exactly as before.
    """
    rng = np.random.default_rng([spec.seed, 1])
    offsets = np.zeros_like(q)
    for effect in spec.joint_effects:
        j = chain.joint_names.index(effect.joint)
        angle = q[:, j]
        if effect.kind == "gear_periodic":
            delta = effect.size * np.sin(effect.harmonic * angle + effect.phase_rad)
        elif effect.kind == "backlash_load":
            torque = _joint_torque(chain, spec, q, j)
            delta = 0.5 * effect.size * np.sign(torque)
            floating = np.abs(torque) < effect.float_below_nm
            delta[floating] = rng.uniform(-0.5, 0.5, size=int(floating.sum())) * effect.size
        elif effect.kind == "backlash_direction":
            delta = np.zeros_like(angle)
            delta[1:] = -0.5 * effect.size * np.sign(np.diff(angle))
        elif effect.kind == "joint_scale":
            delta = effect.size * angle
        elif effect.kind == "drift_linear":
            delta = effect.size * time_s
        elif effect.kind == "drift_warmup":
            delta = effect.size * (1.0 - np.exp(-time_s / effect.time_constant_s))
        elif effect.kind == "quadratic":
            delta = effect.size * angle**2
        elif effect.kind == "bump":
            delta = effect.size * np.exp(
                -0.5 * ((angle - effect.centre_rad) / effect.width_rad) ** 2
            )
        elif effect.kind == "load_quadratic":
            torque = _joint_torque(chain, spec, q, j)
            delta = effect.size * torque * np.abs(torque)
        else:
            raise ValueError(f"unknown joint effect {effect.kind!r}")
        offsets[:, j] += delta
    return offsets


def _joint_torque(chain: KinematicChain, spec: SimulationSpec, q: FloatArray, j: int) -> FloatArray:
    """Gravity torque on joint j's own axis (N,), N·m, as in paper Eq. (6)."""
    axis = ComplianceAxis(chain.joint_names[j], j, chain.joint_screws[j, 3:], is_joint_axis=True)
    single = replace(chain, compliance_axes=(axis,))
    return gravity_loads(single, q, gravity_base=spec.gravity_base, payload_kg=spec.payload_kg)[
        :, 0
    ]


def _sensor(pose: FloatArray, spec: SimulationSpec, time_s: FloatArray) -> FloatArray:
    """What the sensor reports for true poses: its frame drifted (if set), then the depth
    along its axis scaled (if set)."""
    if spec.measurement_drift_per_s is not None:
        drift = np.asarray(spec.measurement_drift_per_s, dtype=float)
        pose = lie.se3_exp(time_s[:, None] * drift[None, :]) @ pose
    if spec.depth_scale == 0.0:
        return pose
    out = pose.copy()
    out[:, :3, 3] += spec.depth_scale * depth_direction(pose, spec.depth_axis)
    return out


def depth_direction(pose: FloatArray, variant: str) -> FloatArray:
    """Position shift (n, 3), measurement frame, per unit depth scale: ``(zᵀp) z`` for the unit
    depth axis ``z`` and the positions ``p`` of ``pose`` (n, 4, 4), m.

    ``measurement_z``: the depth along the measurement frame's z (a fixed camera) is scaled.
    ``marker_z``: the depth along the marker frame's z (a camera on the flange looking at a
    fixed target, which is then the measurement frame) is scaled.
    """
    p, rotation = pose[:, :3, 3], pose[:, :3, :3]
    if variant == "measurement_z":
        shift = np.zeros_like(p)
        shift[:, 2] = p[:, 2]
        return shift
    depth = np.einsum("nji,nj->ni", rotation, p)[:, 2]
    return depth[:, None] * rotation[:, :, 2]


def gross_error_twists(
    n: int, translation_m: float, rotation_rad: float, rng: np.random.Generator
) -> FloatArray:
    """Local twists (n, 6), [v; w] in m and rad, of gross measurement errors: a translation of
    ``translation_m`` and a rotation of ``rotation_rad``, each in a random direction."""
    directions = rng.normal(size=(n, 2, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    return np.concatenate(
        [translation_m * directions[:, 0], rotation_rad * directions[:, 1]], axis=1
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
