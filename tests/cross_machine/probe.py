"""The covariance estimates the cross-machine test compares, printed as JSON.

Run as ``python -m tests.cross_machine.probe [--perturb REL] [--calibrate-tiago FOLDER]`` in a
subprocess whose environment picks the BLAS kernel, its threads and numpy's SIMD dispatch
(tests/test_same_numbers.py): one process per setting computes both of the test's cases. The
first case is the one that ended differently on an AVX2-only CPU: the position recording of
tests/solver/test_measurement_covariance.py (200 Panda poses, random joint-frame rotations,
50 µm sensor noise), its noise written in the default and in an explicit layout, estimated
diagonal by REML (the default) and full by moments (Clarabel). ``--perturb`` multiplies every
measured coordinate and joint angle by 1 + REL·u, u uniform in [−1, 1] (seeded).
``--calibrate-tiago FOLDER``: also ``kincal calibrate`` with its defaults on the real 21-pose
TIAGo Vicon file (its values perturbed likewise), the result written to FOLDER/tiago.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

import solver  # noqa: F401  (BLAS threading defaults before numpy does work)
from solver.calibration import FitOptions
from solver.covariance.estimate import estimate_from_samples
from solver.covariance.layout import make_layout
from solver.measurement import MeasurementRows, Position, fit_measurement
from solver.measurement.fit import covariance_samples
from tests.conftest import REAL_DATA
from tests.solver.test_measurement_covariance import _perturbed_recording

TIAGO = REAL_DATA / "figaroh_tiago_mocap" / "vicon" / "vicon_calibration_fc10_gripper3_base1.csv"

CASES = (("diag", "reml"), ("full", "moment"))
"""The default estimator, and the full-Σ cone program; the full-Σ REML, 10 s more, is in
benchmarks/same_numbers.py."""


def estimates(
    perturb: float, cases: tuple[tuple[str, str], ...] = CASES, seed: int = 12
) -> dict[str, dict[str, object]]:
    """Per case: θ (m², rad²), Σ_E at the training rows (Eq. 12, m²) and the solver statuses;
    ``seed`` draws the perturbation's u."""
    c, _, recording = _perturbed_recording(200, 3)
    pose = recording.measured_pose.copy()
    pose[:, :3, 3] += 5e-5 * np.random.default_rng(3).standard_normal((200, 3))
    joints = recording.joint_positions.copy()
    if perturb:
        rng = np.random.default_rng(seed)
        pose[:, :3, 3] *= 1.0 + perturb * rng.uniform(-1.0, 1.0, (200, 3))
        joints *= 1.0 + perturb * rng.uniform(-1.0, 1.0, joints.shape)
    rows = MeasurementRows.of(joints, recording.loads_nm, pose)
    fit = fit_measurement(c, Position(), rows, FitOptions())
    frames = (2, 4, 6)
    samples = covariance_samples(c, fit, rows, frames)
    names = [c.joint_names[f] for f in frames]
    out: dict[str, dict[str, object]] = {}
    for structure, estimator in cases:
        for noise, placement in (("default", None), ("explicit", (0, 1, 2, -1, -1, -1))):
            layout = make_layout(
                names,
                3,
                structure=structure,  # type: ignore[arg-type]
                noise_rows=None if placement is None else {"noise": (placement,)},
            )
            found = estimate_from_samples(samples, layout, estimator=estimator)  # type: ignore[arg-type]
            out[f"{structure} {estimator} {noise}"] = {
                "theta": found.theta.tolist(),
                "ee_covariance": found.ee_covariance(
                    samples.frame_jacobians, include_noise=True
                ).tolist(),
                "moment_status": found.moment_solution.status,
                "status": found.solution.status,
                "objective": found.solution.objective,
            }
    return out


def calibrate_tiago(perturb: float, folder: Path) -> int:
    """``kincal calibrate`` of the TIAGo Vicon file (values × (1 + perturb·u)) as its console
    script runs it, into ``folder``/tiago.json; the exit code."""
    from schemas.robots import example_robot_data_dir
    from service.cli import main

    folder.mkdir(parents=True, exist_ok=True)
    recording = TIAGO
    if perturb:
        rows = pd.read_csv(TIAGO)
        rng = np.random.default_rng(12)
        rows = rows * (1.0 + perturb * rng.uniform(-1.0, 1.0, rows.shape))
        recording = folder / TIAGO.name
        rows.to_csv(recording, index=False, float_format="%.17g")
    urdf = example_robot_data_dir() / "robots/tiago_description/robots/tiago.urdf"
    sys.argv = ["kincal", "calibrate", str(recording), "--urdf", str(urdf), "--base"]
    sys.argv += ["base_footprint", "--tip", "arm_7_link", "-o", str(folder / "tiago.json")]
    stdout = sys.stdout
    sys.stdout = sys.stderr  # stdout carries the probe's JSON only
    try:
        main()
    except SystemExit as exc:
        return int(exc.code or 0)
    finally:
        sys.stdout = stdout
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--perturb", type=float, default=0.0)
    parser.add_argument("--calibrate-tiago", type=Path)
    args = parser.parse_args()
    found: dict[str, object] = {"estimates": estimates(args.perturb)}
    if args.calibrate_tiago is not None:
        found["tiago_exit"] = calibrate_tiago(args.perturb, args.calibrate_tiago)
    print(json.dumps(found))
