"""Named simulation effects (``kincal simulate --effect``) and the paper-like Jaco2 scenario."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from schemas.dataset import PoseDataset
from schemas.robots import RobotDescription
from solver import lie
from solver.errors import ModelError
from solver.model import (
    ComplianceAxis,
    KinematicChain,
    build_chain,
    gravity_loads,
    sample_configurations,
)
from solver.simulate import (
    JointEffect,
    SimulatedRecording,
    SimulationSpec,
    look_at,
    simulate_recording,
)

EFFECTS = {
    "geometry": "per-link geometric errors (1 mm, 2 mrad standard deviation)",
    "compliance": "elastic 2nd and 3rd joints (5e-4 and 8e-4 rad/Nm)",
    "base_flex": "two virtual compliant axes at the first joint (2e-4 rad/Nm)",
    "random": "random rotations in every joint frame, 0.3 -> 2 mrad toward the end effector",
    "outliers": "10 % gross outliers (10 deg, 5 mm)",
    "camera": "unknown measurement frame: a camera 1.2 m away looking at the workspace",
    "marker": "unknown marker offset on the flange (about 6 cm)",
    # Hidden effects for `kincal discover` (DESIGN.md §2: discovery starts from the rigid model).
    "gear_error": "periodic transmission error of the 3rd joint, 2x per revolution (0.2 mrad)",
    "backlash": "1 mrad backlash of the 2nd joint, taken up by the sign of its gravity load",
    "floating_backlash": "2 mrad load-sign backlash of the 2nd joint, floating (random) where "
    "its load is in the lowest 10 %",
    "approach_backlash": "1 mrad backlash of the 3rd joint, taken up by the approach direction",
    "joint_scale": "2nd joint angle scaled by 1 + 5e-4 (gear ratio error)",
    "thermal_drift": "warm-up drift of the 2nd joint zero: 0.5 mrad, time constant 5 min",
    "tilted_base": "base tilted 2 deg about x (visible through joint compliance)",
    "payload": "undeclared 1 kg payload at the flange (visible through joint compliance)",
    "depth_scale": "the sensor's depth along its z axis reads 0.2 % long",
    "link_bending": "the link carrying the 3rd joint bends under its gravity moment: two virtual "
    "compliant axes at the 3rd joint (1e-4 rad/Nm)",
    "camera_drift": "the measurement frame drifts 1 mm and 1 mrad per hour (linear)",
    "quadratic_joint": "outside the discovery library: last joint off by 1e-4 rad x q^2 (on this "
    "full-revolution joint 99 % of it is harmonics 1-3, which discovery may name)",
    "gear_dent": "outside the discovery library: the 4th joint's gear has a local defect, "
    "0.4 mrad over about +-0.25 rad around q = 1 rad",
    "softening_spring": "outside the discovery library: 2nd joint deflects 1e-6 rad x tau|tau| "
    "(N.m)^2, a spring that softens under load",
    "blocked_order": "samples recorded in order of the first joint's angle (blocked acquisition)",
}
DEFAULT_EFFECTS = ("geometry", "compliance", "camera", "marker")
PAPER_EFFECTS = ("geometry", "compliance", "base_flex", "random", "outliers", "camera", "marker")


@dataclass(frozen=True)
class Scenario:
    chain: KinematicChain
    spec: SimulationSpec
    effects: tuple[str, ...]


def scenario(
    robot: RobotDescription,
    *,
    n_samples: int,
    seed: int,
    effects: Iterable[str] = DEFAULT_EFFECTS,
    noise_translation_mm: float = 0.05,
    noise_rotation_deg: float = 0.003,
) -> Scenario:
    """The true robot for a list of named effects (see :data:`EFFECTS`)."""
    chosen = tuple(dict.fromkeys(effects))
    unknown = [e for e in chosen if e not in EFFECTS]
    if unknown:
        raise ModelError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(EFFECTS)}")
    probe = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)
    first = probe.joint_names[0]
    third = probe.joint_names[min(2, probe.n_joints - 1)]
    chain = build_chain(
        robot.urdf_xml,
        robot.base_frame,
        robot.tip_frame,
        virtual_axes_at=[first] * ("base_flex" in chosen) + [third] * ("link_bending" in chosen),
    )
    compliance: dict[str, float] = {}
    if "compliance" in chosen:
        compliance |= dict(zip(chain.joint_names[1:3], (5e-4, 8e-4), strict=False))
    if "base_flex" in chosen:
        compliance |= {f"{first}.flex_a": 2e-4, f"{first}.flex_b": 2e-4}
    if "link_bending" in chosen:
        compliance |= {f"{third}.flex_a": 1e-4, f"{third}.flex_b": 1e-4}
    k = chain.n_joints
    perturbation = np.zeros((k, 6))
    if "random" in chosen:
        perturbation[:, 3:] = np.linspace(3e-4, 2e-3, k)[:, None]
    noise = np.r_[[noise_translation_mm * 1e-3] * 3, [np.radians(noise_rotation_deg)] * 3]
    spec = SimulationSpec(
        n_samples=n_samples,
        seed=seed,
        geometry_translation_m=1e-3 if "geometry" in chosen else 0.0,
        geometry_rotation_rad=2e-3 if "geometry" in chosen else 0.0,
        compliance_rad_per_nm=compliance,
        perturbation_sigma=perturbation,
        noise_sigma=noise,
        measurement_frame=_camera(chain) if "camera" in chosen else np.eye(4),
        tool_offset=marker_offset() if "marker" in chosen else np.eye(4),
        outlier_fraction=0.1 if "outliers" in chosen else 0.0,
        **_hidden(chain, chosen),
    )
    return Scenario(chain, spec, chosen)


def _hidden(chain: KinematicChain, chosen: tuple[str, ...]) -> dict[str, Any]:
    """SimulationSpec fields of the hidden effects (see :data:`EFFECTS`)."""
    names = chain.joint_names
    second, third = names[min(1, len(names) - 1)], names[min(2, len(names) - 1)]
    effects: list[JointEffect] = []
    if "gear_error" in chosen:
        effects.append(JointEffect(third, "gear_periodic", 2e-4, harmonic=2, phase_rad=0.3))
    if "backlash" in chosen:
        effects.append(JointEffect(second, "backlash_load", 1e-3))
    if "floating_backlash" in chosen:
        zone = _load_quantile(chain, names.index(second), 0.1)
        effects.append(JointEffect(second, "backlash_load", 2e-3, float_below_nm=zone))
    if "approach_backlash" in chosen:
        effects.append(JointEffect(third, "backlash_direction", 1e-3))
    if "joint_scale" in chosen:
        effects.append(JointEffect(second, "joint_scale", 5e-4))
    if "thermal_drift" in chosen:
        effects.append(JointEffect(second, "drift_warmup", 5e-4, time_constant_s=300.0))
    if "quadratic_joint" in chosen:
        effects.append(JointEffect(names[-1], "quadratic", 1e-4))
    if "gear_dent" in chosen:
        fourth = names[min(3, len(names) - 1)]
        effects.append(JointEffect(fourth, "bump", 4e-4, centre_rad=1.0, width_rad=0.25))
    if "softening_spring" in chosen:
        effects.append(JointEffect(second, "load_quadratic", 1e-6))
    out: dict[str, Any] = {"joint_effects": tuple(effects)}
    if "tilted_base" in chosen:
        out["gravity_base"] = lie.so3_exp(np.array([np.radians(2.0), 0.0, 0.0])) @ np.array(
            [0.0, 0.0, -9.81]
        )
    if "payload" in chosen:
        out["payload_kg"] = 1.0
    if "depth_scale" in chosen:
        out["depth_scale"] = 2e-3
    if "camera_drift" in chosen:
        per_axis = 1e-3 / 3600.0 / np.sqrt(3.0)  # 1 mm and 1 mrad per hour in total
        out["measurement_drift_per_s"] = np.full(6, per_axis)
    if "blocked_order" in chosen:
        out["order_by_joint"] = names[0]
    return out


def _load_quantile(chain: KinematicChain, joint: int, fraction: float) -> float:
    """``fraction`` quantile of |gravity torque| on a joint over its workspace (N·m)."""
    q = sample_configurations(chain, 500, np.random.default_rng(0))
    axis = ComplianceAxis(chain.joint_names[joint], joint, chain.joint_screws[joint, 3:], True)
    single = replace(chain, compliance_axes=(axis,))
    return float(np.quantile(np.abs(gravity_loads(single, q)[:, 0]), fraction))


def _camera(chain: KinematicChain) -> np.ndarray:
    """A camera about 1.2 m from the base, looking at the middle of the reachable space."""
    reach_m = float(np.sum(np.linalg.norm(chain.nominal_links[:, :3, 3], axis=1)))
    eye = np.array([0.9, -0.6, 0.5]) * max(reach_m, 0.5) / 1.0
    return look_at(eye, np.array([0.0, 0.0, 0.3 * reach_m]))


def marker_offset() -> np.ndarray:
    """The simulated marker in the flange frame (4, 4): 6 cm off, turned 0.62 rad."""
    marker = np.eye(4)
    marker[:3, :3] = lie.so3_exp(np.array([0.3, -0.2, 0.5]))
    marker[:3, 3] = [0.03, -0.02, 0.05]
    return marker


def recording_dataset(
    recording: SimulatedRecording, chain: KinematicChain, *, rotation: bool
) -> PoseDataset:
    """The measurements of a simulated recording in the dataset contract; without
    ``rotation`` the positions alone (no quaternion columns)."""
    pose = recording.measured_pose
    return PoseDataset(
        joint_names=chain.joint_names,
        joint_positions=recording.joint_positions,
        position_m=pose[:, :3, 3],
        quaternion_xyzw=lie.matrix_to_quaternion_xyzw(pose[:, :3, :3]) if rotation else None,
        sample_id=np.arange(1, pose.shape[0] + 1),
        time_s=recording.time_s,
        source="simulation",
    )


def truth_document(
    scn: Scenario, recording: SimulatedRecording, robot: RobotDescription
) -> dict[str, Any]:
    """JSON-ready ground truth (``--truth``): what a perfect calibration would find."""
    chain, spec = scn.chain, scn.spec
    return {
        "format": "kincal.truth/1",
        "robot": robot.name,
        "base_frame": robot.base_frame,
        "tip_frame": robot.tip_frame,
        "seed": spec.seed,
        "n_samples": spec.n_samples,
        "effects": list(scn.effects),
        "measurement_frame": spec.measurement_frame.tolist(),
        "tool_offset": spec.tool_offset.tolist(),
        "links": [
            {
                "link": name,
                "placement": recording.true_params.links[i].tolist(),
                "error_twist": recording.link_errors[i].tolist(),
            }
            for i, name in enumerate(chain.link_names)
        ],
        "compliance_rad_per_nm": {
            axis.name: float(recording.true_params.compliance_rad_per_nm[a])
            for a, axis in enumerate(chain.compliance_axes)
        },
        "perturbation_sigma": {
            name: recording.perturbation_sigma[i].tolist()
            for i, name in enumerate(chain.joint_names)
        },
        "noise_sigma": recording.noise_sigma.tolist(),
        "outlier_rows": [int(i) + 1 for i in recording.outliers],
        "hidden": {
            "joint_effects": [vars(e) for e in spec.joint_effects],
            "gravity_base_m_s2": np.asarray(spec.gravity_base).tolist(),
            "payload_kg": spec.payload_kg,
            "depth_scale": spec.depth_scale,
            "depth_axis": spec.depth_axis,
            "measurement_drift_per_s": None
            if spec.measurement_drift_per_s is None
            else np.asarray(spec.measurement_drift_per_s).tolist(),
            "order_by_joint": spec.order_by_joint,
        },
    }


def simulate(robot: RobotDescription, **kwargs: Any) -> tuple[Scenario, SimulatedRecording]:
    scn = scenario(robot, **kwargs)
    return scn, simulate_recording(scn.chain, scn.spec)
