"""Held-out calibration error on the real recordings shipped in data/real (DESIGN.md §4),
each through the user's path: ``kincal calibrate`` with its defaults plus the flags the recording
needs (URDF/base/tip, measurement type, DH table); the exit code and verdict with it.

Prints the paper's Table II layout per recording and a markdown summary; with
``--write-results`` also ``docs/results/real_robots.{json,md}``, the table docs/real-robots.md
includes and the README quotes (its FR3 row). Usage: ``python -m benchmarks.evaluate_real
[--seeds 10] [--figures docs] [--write-results] [--recordings NAME,...]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.results import Row, dash, markdown_table, write_results
from schemas.calibration import CalibrationResult
from schemas.dataset import read_dataset
from schemas.robots import example_robot_data_dir
from service.render import result_json
from service.render.plots import residual_histograms
from service.render.text import table_ii

DATA = Path(__file__).resolve().parents[1] / "data" / "real"
ERD = "erd:"
"""Marks a path under example-robot-data (resolved on this machine)."""


@dataclass(frozen=True)
class Recording:
    """One recording and the ``kincal calibrate`` flags a user needs for it (robot or URDF with
    base/tip, measurement type, DH table); everything else is the CLI default (10 held-out
    splits of 90/10, seeds 1..10)."""

    path: str  # under data/real
    flags: str  # split at spaces
    figure: bool = True  # pose/position rows: before/after residual histograms


RECORDINGS = {
    "FR3 eye-in-hand camera (philnad)": Recording(
        "philnad_fr3_eye_in_hand/fr3_poses.csv", "--robot panda"
    ),
    "UR10e (FIGAROH UR10 experiment)": Recording(
        "figaroh_ur10_experiment/calibration.csv",
        "--urdf figaroh_ur10_experiment/ur10e_robot.urdf --base base_link --tip wrist_3_link",
    ),
    "TIAGo arm, Vicon gripper3/base1 (FIGAROH), relative-base, joint offsets": Recording(
        "figaroh_tiago_mocap/vicon/relative_encoder/vicon_calibration_fc10_gripper3_base1.csv",
        f"--urdf {ERD}robots/tiago_description/robots/tiago.urdf --base base_footprint "
        "--tip arm_tool_link --measurement relative-base --free joint_offsets",
        figure=False,
    ),
    "TALOS torso + left arm (FIGAROH)": Recording(
        "figaroh_talos_left_arm_contact/talos_left_arm_02_10_contact.csv",
        f"--urdf {ERD}robots/talos_data/robots/talos_full_v2.urdf --base base_link "
        "--tip gripper_left_base_link",
    ),
    "2-axis positioner, DH table (industrial_calibration)": Recording(
        "industrial_calibration_2axis_positioner/measurements.yaml",
        "--dh industrial_calibration_2axis_positioner/positioner_dh.yaml",
        figure=False,
    ),
    "platonics Panda ball in socket (panda_right), 50 mm sockets": Recording(
        "platonics_ball_socket/panda_right",
        "--robot panda --point-distance 0.05",
        figure=False,
    ),
}
"""Recording name -> file and flags. The UR10 experiment's arm is a UR10e (its PROVENANCE.md):
calibrating it against the CB-series ``ur10`` measured the wrong model (11.6 mm before, against
~3.9 mm with the UR10e URDF). The TIAGo Vicon file has 21 rows of 3 equations: a full geometric
calibration (33 identifiable parameters) fails few_equations, the joint offsets with the two
marker frames (14) do not (README, TIAGo)."""


def _resolve(flag_value: str) -> str:
    if flag_value.startswith(ERD):
        return str(example_robot_data_dir() / flag_value.removeprefix(ERD))
    candidate = DATA / flag_value
    return str(candidate) if "/" in flag_value and candidate.exists() else flag_value


def command(name: str, output: Path, seeds: int) -> list[str]:
    """The ``kincal calibrate`` command line of recording ``name``."""
    recording = RECORDINGS[name]
    kincal = Path(sys.executable).with_name("kincal")
    flags = [_resolve(f) for f in recording.flags.split()]
    seed_list = ",".join(str(s) for s in range(1, seeds + 1))
    return [
        str(kincal),
        "calibrate",
        str(DATA / recording.path),
        *flags,
        "--seeds",
        seed_list,
        "-o",
        str(output),
    ]


def evaluate(name: str, seeds: int, workdir: Path) -> tuple[CalibrationResult, int, float]:
    """Runs the user's command; the result document, the exit code and the wall time."""
    output = workdir / "result.json"
    started = time.perf_counter()
    done = subprocess.run(command(name, output, seeds), capture_output=True, text=True)
    elapsed = time.perf_counter() - started
    if not output.exists():
        raise RuntimeError(f"{name}: exit {done.returncode}\n{done.stderr}")
    return CalibrationResult.model_validate_json(output.read_text()), done.returncode, elapsed


def figure(result: CalibrationResult, name: str, path: Path) -> Path:
    """Before/after residual histograms of the samples kept after outlier removal."""
    recording = RECORDINGS[name]
    chain, _ = result_json.result_chain(result)
    dataset = read_dataset(
        DATA / recording.path, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    kept = dataset.subset(result.outliers.kept_indices())
    return residual_histograms(
        result_json.residuals(result, kept, baseline=True),
        result_json.residuals(result, kept),
        path,
        title=f"{name}: end-effector-frame residuals, nominal robot vs calibrated "
        f"({kept.n_samples} samples, all used for training)",
    )


HEADER = (
    "Recording",
    "Robot",
    "Flags beyond the defaults",
    "Samples (used)",
    "Before: held-out mm / deg",
    "Calibrated: held-out mm / deg",
    "Splits improved",
    "Exit",
    "Verdict",
)


def result_row(name: str, result: CalibrationResult, code: int) -> Row:
    """The numbers of one recording's calibration, as the results file keeps them."""
    before, after = result.fit.before.heldout, result.fit.after.heldout
    assert before is not None and after is not None and result.evaluation is not None
    by = {(s.method, s.seed): s.translation_mm for s in result.evaluation.splits}
    seeds_run = sorted({s.seed for s in result.evaluation.splits})
    return {
        "recording": name,
        "robot": result.robot.name,
        "flags": RECORDINGS[name].flags.replace(ERD, ""),
        "samples": result.outliers.n_input,
        "used": result.outliers.n_used,
        "before_mm": before.translation_mean_mm,
        "before_deg": before.rotation_mean_deg,
        "after_mm": after.translation_mean_mm,
        "after_deg": after.rotation_mean_deg,
        "improved": sum(by[("calibrated", s)] < by[("before", s)] for s in seeds_run),
        "splits": len(seeds_run),
        "exit": code,
        "verdict": _verdict(result),
    }


def render(rows: list[Row]) -> str:
    """The markdown table of the rows (held-out mean errors: mm to 2 decimals, deg to 3)."""
    return markdown_table(
        HEADER,
        [
            (
                r["recording"],
                r["robot"],
                f"`{r['flags']}`",
                f"{r['samples']} ({r['used']})",
                f"{r['before_mm']:.2f} / {dash(r['before_deg'], 3)}",
                f"{r['after_mm']:.2f} / {dash(r['after_deg'], 3)}",
                f"{r['improved']} of {r['splits']}",
                r["exit"],
                r["verdict"],
            )
            for r in rows
        ],
    )


def _verdict(result: CalibrationResult) -> str:
    verdict = result.verdict
    if verdict is None:
        return "–"
    codes = [r.code for r in verdict.reasons if r.severity == verdict.status]
    return verdict.status + (f" ({', '.join(codes)})" if codes else "")


def main(
    seeds: int = 10,
    figures: Path | None = None,
    *,
    write: bool = False,
    names: list[str] | None = None,
) -> list[Row]:
    rows: list[Row] = []
    for name, recording in RECORDINGS.items():
        if names is not None and name not in names:
            continue
        with tempfile.TemporaryDirectory() as workdir:
            result, code, elapsed = evaluate(name, seeds, Path(workdir))
        assert result.evaluation is not None
        if figures is not None and recording.figure:
            figures.mkdir(parents=True, exist_ok=True)
            stem = recording.path.split("/")[0]
            print("wrote", figure(result, name, figures / f"{stem}_residuals.png"))
        print(f"\n## {name}\n\n    " + " ".join(command(name, Path("out.json"), seeds)) + "\n")
        print(table_ii(result.evaluation.splits, rotation=result.dataset.measures_rotation))
        print(f"wall time {elapsed:.1f} s")
        rows.append(result_row(name, result, code))
    print("\n" + render(rows))
    if write:
        line = f"python -m benchmarks.evaluate_real --seeds {seeds} --write-results"
        for path in write_results("real_robots", line, rows, render):
            print("wrote", path)
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of train/test splits")
    parser.add_argument("--figures", type=Path, help="write residual histograms (PNG) here")
    parser.add_argument(
        "--write-results", action="store_true", help="write docs/results/real_robots.{json,md}"
    )
    parser.add_argument("--recordings", help="comma-separated recording names (default: all)")
    arguments = parser.parse_args()
    main(
        arguments.seeds,
        arguments.figures,
        write=arguments.write_results,
        names=None if arguments.recordings is None else arguments.recordings.split(","),
    )
