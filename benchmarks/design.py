"""Calibration designs (issue 16): held-out error and predicted variance against the number of
poses, for random poses and kincal's designs, on simulated Jaco2, Panda and UR10e with
candidates in a working box; and the time of a D-optimal design of 10⁴ candidates, K = 30.

FIGAROH 1.0.2's posture selection runs only if a separate interpreter with figaroh is given
(``--figaroh-python``); it is never a kincal dependency. Usage::

    python benchmarks/design.py [--seeds 10] [--poses 15,25,50] [--figaroh-python PATH]
"""

from __future__ import annotations

import argparse
import subprocess
import time
from pathlib import Path

import numpy as np

from schemas.calibration import CalibrationOptions
from schemas.dataset import PoseDataset
from schemas.design import DesignOptions
from service import pipeline
from service.design import run_design
from service.robots import RobotDescription, load_robot
from solver import lie
from solver.design.candidates import Volume, WorkspaceBox, sample_candidates, tip_poses
from solver.kinematics import forward_kinematics
from solver.model import build_chain, gravity_loads
from solver.simulate import SimulationSpec, true_parameters

UR10E = Path(__file__).resolve().parents[1] / "data/real/figaroh_ur10_experiment/ur10e_robot.urdf"
NOISE = np.r_[[5e-5] * 3, [np.radians(0.003)] * 3]


def robots() -> dict[str, RobotDescription]:
    return {
        "jaco2": load_robot("kinova"),
        "panda": load_robot("panda"),
        "ur10e": load_robot("ur10e", urdf_path=UR10E, base_frame="base_link", tip_frame="tool0"),
    }


def working_box(robot: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
    chain = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)
    tips = tip_poses(chain, sample_candidates(chain, 4000, np.random.default_rng(0)))[:, :3, 3]
    return np.percentile(tips, 30, axis=0), np.percentile(tips, 70, axis=0)


def heldout_error_mm(
    robot: RobotDescription, q: np.ndarray, heldout: np.ndarray, seed: int
) -> float:
    """Simulate the true robot at q (noise as NOISE), calibrate with kincal's defaults (no
    covariance), return the mean translation error (mm) at ``heldout`` against the truth."""
    options = CalibrationOptions(covariance="none", heldout=False)
    setup = pipeline.check_calibration(robot, options)
    chain = setup.chain
    rng = np.random.default_rng(seed)
    params, _ = true_parameters(chain, SimulationSpec(n_samples=1, seed=seed), rng)
    truth = forward_kinematics(chain, params, q, gravity_loads(chain, q))
    measured = truth @ lie.se3_exp(rng.normal(size=(q.shape[0], 6)) * NOISE)
    dataset = PoseDataset(
        chain.joint_names, q, measured[:, :3, 3], lie.matrix_to_quaternion_xyzw(measured[:, :3, :3])
    )
    result = pipeline.calibrate(dataset, robot, options)
    from service.result_json import predict_poses

    predicted = predict_poses(result, heldout, None)
    expected = forward_kinematics(chain, params, heldout, gravity_loads(chain, heldout))
    return float(1e3 * np.mean(np.linalg.norm(predicted[:, :3, 3] - expected[:, :3, 3], axis=1)))


def compare(seeds: int, poses: list[int]) -> None:
    print("robot  K   method   held-out mm (median)  pred. variance ratio to random-K")
    for name, robot in robots().items():
        low, high = working_box(robot)
        chain = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)
        volume = Volume(box=WorkspaceBox(low, high))
        for k in poses:
            errors: dict[str, list[float]] = {"random": [], "design": []}
            variance: dict[str, list[float]] = {"random": [], "design": []}
            for seed in range(seeds):
                rng = np.random.default_rng([seed, 3])
                heldout = sample_candidates(chain, 200, rng, volume)
                options = DesignOptions(
                    n_poses=k, n_candidates=1000, seed=seed,
                    box={"low_m": tuple(low), "high_m": tuple(high)},
                    calibration=CalibrationOptions(covariance="none"),
                )  # fmt: skip
                designed = run_design(robot, options, task=heldout)
                q_design = np.array([p.joint_positions for p in designed.poses])
                q_random = sample_candidates(chain, k, rng, volume)
                random = run_design(
                    robot,
                    options.model_copy(update={"n_poses": k}),
                    candidates=q_random,
                    task=heldout,
                )
                variance["design"].append(designed.mean_pose_variance_m2)
                variance["random"].append(random.mean_pose_variance_m2)
                errors["design"].append(heldout_error_mm(robot, q_design, heldout, seed))
                errors["random"].append(heldout_error_mm(robot, q_random, heldout, seed))
            for method in ("random", "design"):
                ratio = np.median(variance[method]) / np.median(variance["random"])
                print(
                    f"{name:6} {k:3d} {method:8} {np.median(errors[method]):8.4f}"
                    f"              {ratio:.3f}"
                )


def timing() -> None:
    robot = load_robot("kinova")
    started = time.perf_counter()
    out = run_design(robot, DesignOptions(n_poses=30, n_candidates=10_000))
    print(
        f"D-optimal, 10^4 candidates, K=30: {time.perf_counter() - started:.1f} s total "
        f"(relaxation {out.criterion.elapsed_s:.1f} s, {out.criterion.iterations} iterations, "
        f"efficiency {out.criterion.efficiency:.3f})"
    )


def figaroh(python: str | None) -> None:
    if python is None:
        print("FIGAROH: not run (pass --figaroh-python /path/to/venv/bin/python)")
        return
    probe = subprocess.run(
        [python, "-c", "import figaroh, importlib.metadata as m; print(m.version('figaroh'))"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    print(f"FIGAROH: {probe.stdout.strip() or probe.stderr.strip().splitlines()[-1]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", default="15,25,50")
    parser.add_argument("--figaroh-python", default=None)
    parser.add_argument("--skip-timing", action="store_true")
    args = parser.parse_args()
    compare(args.seeds, [int(v) for v in args.poses.split(",")])
    if not args.skip_timing:
        timing()
    figaroh(args.figaroh_python)


if __name__ == "__main__":
    main()
