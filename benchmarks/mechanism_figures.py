"""Figures of docs/discovery_physics.md: each mechanism of solver.mechanisms against the
library term it should be named as (issue 14).

For each mechanism, the deflection it produces (mechanism simulator, no library formula) is
plotted against the variable that drives it, with the library feature times the true size on
top: the signs and shapes agree where the points follow the line.

Usage: ``python benchmarks/mechanism_figures.py [--out docs/discovery_physics.png]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from schemas.robots import load_robot
from solver.discovery.features import approach_lag, deadzone_sign
from solver.mechanisms import (
    DeadBand,
    ElasticJoint,
    GearTrain,
    JointMechanism,
    MechanismSpec,
    Robot,
    gear_harmonic_amplitude,
    simulate_mechanisms,
)
from solver.model import build_chain


def figure(path: Path) -> Path:
    """Four panels: backlash by approach, by load, elastic joint, gear error."""
    robot = load_robot("kinova")
    chain = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)
    names = chain.joint_names
    cases: list[tuple[str, JointMechanism, int]] = [
        ("backlash by approach (joint 4, 1 mrad)", DeadBand(names[3], 1e-3, np.inf), 3),
        ("backlash by load (joint 2, 2 mrad)", DeadBand(names[1], 2e-3), 1),
        ("elastic joint (joint 2, 2e-5 rad/N·m)", ElasticJoint(names[1], 2e-5), 1),
        ("gear, 3-lobed pitch curve (joint 3)", GearTrain(names[2], trilobe_m=1.5e-5), 2),
    ]
    plot = Figure(figsize=(13, 3.4), layout="constrained")
    axes = plot.subplots(1, 4)
    for ax, (title, mechanism, j) in zip(axes, cases, strict=True):
        recording = simulate_mechanisms(chain, MechanismSpec(150, 1, joints=(mechanism,)))
        q = recording.joint_positions
        deflection = (recording.link_positions - q)[:, j] * 1e3
        robot_model = Robot(chain)
        torque = []
        for row in recording.link_positions:
            robot_model.update(row)
            torque.append(robot_model.joint_torque(j))
        tau = np.array(torque)
        if isinstance(mechanism, DeadBand) and np.isinf(mechanism.holding_nm):
            driver = -2.0 * approach_lag(q)[:, j]
            library = approach_lag(q)[:, j] * mechanism.backlash_rad * 1e3
            label = "approach direction sign(Δq)"
        elif isinstance(mechanism, DeadBand):
            driver, label = tau, "gravity torque τ [N·m]"
            library = deadzone_sign(tau, 0.0) * mechanism.backlash_rad * 1e3
        elif isinstance(mechanism, ElasticJoint):
            driver, label = tau, "gravity torque τ [N·m]"
            library = mechanism.compliance_rad_per_nm * tau * 1e3
        else:
            assert isinstance(mechanism, GearTrain)
            driver, label = q[:, j], "joint reading [rad]"
            amplitude = gear_harmonic_amplitude(mechanism, 3)
            library = np.full_like(driver, np.nan)
            title = f"gear, 3-lobed pitch curve (joint 3): h3 {amplitude * 1e3:.2f} mrad"
        order = np.argsort(driver)
        ax.scatter(driver, deflection, s=8, color="tab:blue", label="mechanism: link − reading")
        ax.plot(driver[order], library[order], color="black", lw=1.0, label="library term × size")
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(label)
        ax.set_ylabel("link − reading [mrad]")
        ax.axhline(0.0, color="grey", lw=0.5)
    axes[0].legend(fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    plot.savefig(path, dpi=90)
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/discovery_physics.png"))
    print(figure(parser.parse_args().out))
