"""Held-out calibration error on the real recordings shipped in data/real (DESIGN.md §4).

Prints the paper's Table II layout per recording and a markdown summary (the README table).
Usage: ``python benchmarks/evaluate_real.py [--seeds 10] [--figures docs]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import solver  # noqa: F401  (BLAS defaults)
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import PoseDataset, read_dataset
from service import pipeline, result_json
from service.plots import residual_histograms
from service.report import table_ii
from service.robots import RobotDescription, example_robot_data_dir, load_robot

DATA = Path(__file__).resolve().parents[1] / "data" / "real"
RECORDINGS = {
    "FR3 eye-in-hand camera (philnad)": ("panda", "philnad_fr3_eye_in_hand/fr3_poses.csv"),
    "UR10e (FIGAROH UR10 experiment)": (
        "figaroh_ur10_experiment/ur10e_robot.urdf:base_link:wrist_3_link",
        "figaroh_ur10_experiment/calibration.csv",
    ),
    "TIAGo arm, Vicon gripper3/base1 (FIGAROH)": (
        "erd:robots/tiago_description/robots/tiago.urdf:base_footprint:arm_tool_link",
        "figaroh_tiago_mocap/vicon/vicon_calibration_fc10_gripper3_base1.csv",
    ),
    "TALOS torso + left arm (FIGAROH)": (
        "erd:robots/talos_data/robots/talos_full_v2.urdf:base_link:gripper_left_base_link",
        "figaroh_talos_left_arm_contact/talos_left_arm_02_10_contact.csv",
    ),
    "2-axis positioner, DH table (industrial_calibration)": (
        "dh:industrial_calibration_2axis_positioner/positioner_dh.yaml",
        "industrial_calibration_2axis_positioner/measurements.yaml",
    ),
}
"""Recording name -> (built-in robot, ``URDF:base:tip`` shipped beside the data, ``erd:URDF:base:
tip`` in example-robot-data, or ``dh:TABLE`` shipped beside the data; file).
The UR10 experiment's arm is a UR10e (its PROVENANCE.md): calibrating it against the
CB-series ``ur10`` measured the wrong model (11.6 mm before, against ~3.9 mm with the UR10e
URDF)."""


def robot_of(spec: str) -> RobotDescription:
    if ":" not in spec:
        return load_robot(spec)
    if spec.startswith("dh:"):
        return load_robot(dh_path=DATA / spec.removeprefix("dh:"))
    if spec.startswith("erd:"):
        urdf, base, tip = spec.removeprefix("erd:").split(":")
        path = example_robot_data_dir() / urdf
        return load_robot(path.stem, urdf_path=path, base_frame=base, tip_frame=tip)
    urdf, base, tip = spec.split(":")
    return load_robot("ur10e", urdf_path=DATA / urdf, base_frame=base, tip_frame=tip)


def evaluate(name: str, seeds: int) -> tuple[CalibrationResult, PoseDataset, float]:
    robot_spec, relative = RECORDINGS[name]
    robot = robot_of(robot_spec)
    options = CalibrationOptions(seeds=list(range(1, seeds + 1)))
    chain = result_json.chain_for(robot, options)
    dataset = read_dataset(
        DATA / relative, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    started = time.perf_counter()
    result = pipeline.calibrate(dataset, robot, options)
    return result, dataset, time.perf_counter() - started


def figure(result: CalibrationResult, dataset: PoseDataset, name: str, path: Path) -> Path:
    """Before/after residual histograms of the samples kept after outlier removal."""
    kept = dataset.subset(result.outliers.kept_indices())
    return residual_histograms(
        result_json.residuals(result, kept, baseline=True),
        result_json.residuals(result, kept),
        path,
        title=f"{name}: end-effector-frame residuals, nominal robot vs calibrated "
        f"({kept.n_samples} samples, all used for training)",
    )


def _errors(translation_mm: float, rotation_deg: float | None) -> str:
    rotation = "–" if rotation_deg is None else f"{rotation_deg:.3f}"
    return f"{translation_mm:.2f} / {rotation}"


def _verdict(result: CalibrationResult) -> str:
    verdict = result.verdict
    if verdict is None:
        return "–"
    failed = [r.code for r in verdict.reasons if r.severity == "failed"]
    return verdict.status + (f" ({', '.join(failed)})" if failed else "")


def main(seeds: int = 10, figures: Path | None = None) -> str:
    header = ["Recording", "Robot", "Samples (used)", "Before: held-out mm / deg"]
    header += ["Calibrated: held-out mm / deg", "Splits improved", "Verdict", "Time"]
    rows = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for name in RECORDINGS:
        result, dataset, elapsed = evaluate(name, seeds)
        assert result.evaluation is not None
        if figures is not None:
            figures.mkdir(parents=True, exist_ok=True)
            stem = RECORDINGS[name][1].split("/")[0]
            print("wrote", figure(result, dataset, name, figures / f"{stem}_residuals.png"))
        print(f"\n## {name}\n")
        print(table_ii(result.evaluation.splits, position_only=result.dataset.position_only))
        before, after = result.fit.before.heldout, result.fit.after.heldout
        assert before is not None and after is not None
        by = {(s.method, s.seed): s.translation_mm for s in result.evaluation.splits}
        seeds_run = sorted({s.seed for s in result.evaluation.splits})
        improved = sum(by[("calibrated", s)] < by[("before", s)] for s in seeds_run)
        rows.append(
            f"| {name} | {result.robot.name} "
            f"| {result.outliers.n_input} ({result.outliers.n_used}) "
            f"| {_errors(before.translation_mean_mm, before.rotation_mean_deg)} "
            f"| {_errors(after.translation_mean_mm, after.rotation_mean_deg)} "
            f"| {improved} of {len(seeds_run)} | {_verdict(result)} | {elapsed:.1f} s |"
        )
    table = "\n".join(rows)
    print("\n" + table)
    return table


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of train/test splits")
    parser.add_argument("--figures", type=Path, help="write residual histograms (PNG) here")
    arguments = parser.parse_args()
    main(arguments.seeds, arguments.figures)
