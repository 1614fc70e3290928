"""kincal next to FIGAROH 1.0.2 on the real recordings FIGAROH runs on (UR10e, TIAGo, TALOS):
the same rows and the same held-out splits, held-out error ± one standard error across splits,
and fit time (issue 15).

Rows: those kincal's default calibration keeps (its outlier rule), so both see the same data;
splits: kincal's own (:func:`solver.evaluation.split_indices` of those rows, seeds 1..S, 90 %
train). kincal's held-out errors are its default calibration's (``kincal calibrate`` with no
flags: geometry and joint compliance) and, on the same splits, those of the model FIGAROH fits
(geometry and frames: ``--fix compliance``); FIGAROH's come from
``benchmarks/figaroh_calibration_driver.py`` under FIGAROH's own interpreter
(``--figaroh-python``, a separate venv; never a kincal dependency): its
``full_params`` model, one Levenberg–Marquardt fit per split. Fit times: FIGAROH's
``initialize`` + ``solve`` per split; kincal's deterministic fit of the same training rows
(geometry and compliance, no covariance, no held-out), and its whole default run.

A last column checks where the two differ (docs/figaroh.md): kincal's fit restricted to the
parameters FIGAROH fitted on each split (:func:`figaroh_columns`), from kincal's closed-form
start, without kincal's physical-range rule (FIGAROH has none). Same rows, same parameters:
it reproduces FIGAROH's held-out errors, so the solvers, frames and residuals agree and the
gap of the "FIGAROH's model" column is which parameters each fits.

Usage (from the repository root): ``python -m benchmarks.figaroh_side_by_side
[--figaroh-python …/figaroh-venv/bin/python] [--seeds 10] [--only TALOS] [--write-results]``.
With ``--write-results`` also ``docs/results/figaroh_side_by_side.{json,md}``, the table
docs/figaroh.md includes. FIGAROH is not installed with kincal: without ``--figaroh-python``
kincal's columns are re-run and FIGAROH's are kept from the results file, each recording's
with the command and date of the run that produced them.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.design import figaroh_urdf
from benchmarks.results import Row, markdown_table, read_results, write_results
from schemas.calibration import CalibrationOptions
from schemas.robots import RobotDescription, example_robot_data_dir, load_robot
from service.app import calibrate as pipeline
from solver import lie
from solver.calibration import FitOptions
from solver.evaluation import split_indices
from solver.kinematics import forward_kinematics, parameter_names
from solver.measurement.pose import fit_deterministic, pose_measurement
from solver.model import KinematicChain, gravity_loads

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "data" / "real"
DRIVER = Path(__file__).resolve().parent / "figaroh_calibration_driver.py"


@dataclass(frozen=True)
class Recording:
    name: str
    urdf: str  # "data:<path under data/real>" or "erd:<path under example-robot-data>"
    base_frame: str
    tip_frame: str
    csv: str  # under data/real, FIGAROH's own layout
    full_pose: bool


RECORDINGS = (
    Recording(
        "UR10e",
        "data:figaroh_ur10_experiment/ur10e_robot.urdf",
        "base_link",
        "wrist_3_link",
        "figaroh_ur10_experiment/calibration.csv",
        True,
    ),
    Recording(
        "TIAGo",
        "erd:robots/tiago_description/robots/tiago.urdf",
        "base_footprint",
        "arm_tool_link",
        "figaroh_tiago_mocap/vicon/vicon_calibration_fc10_gripper3_base1.csv",
        False,
    ),
    Recording(
        "TALOS",
        "erd:robots/talos_data/robots/talos_full_v2.urdf",
        "base_link",
        "gripper_left_base_link",
        "figaroh_talos_left_arm_contact/talos_left_arm_02_10_contact.csv",
        False,
    ),
)


def urdf_path(recording: Recording) -> Path:
    kind, relative = recording.urdf.split(":", 1)
    return (DATA if kind == "data" else example_robot_data_dir()) / relative


def robot_of(recording: Recording) -> RobotDescription:
    return load_robot(
        recording.name.lower(),
        urdf_path=urdf_path(recording),
        base_frame=recording.base_frame,
        tip_frame=recording.tip_frame,
    )


@dataclass(frozen=True)
class SideBySide:
    name: str
    n_rows: int
    n_used: int
    kincal_mm: list[float]
    same_model_mm: list[float]
    figaroh_mm: list[float]
    kincal_fit_s: float
    kincal_run_s: float
    figaroh_fit_s: list[float]
    figaroh_parameters: int
    same_parameters_mm: list[float] | None = None
    kept: list[int] | None = None
    """The rows kincal's default calibration kept (0-based), which every fit uses."""


def kincal_fit_seconds(recording: Recording, rows: np.ndarray) -> float:
    """Median wall time of kincal's deterministic fit (geometry + compliance) of ``rows``."""
    from schemas.dataset import read_dataset

    robot = robot_of(recording)
    options = CalibrationOptions(heldout=False, covariance="none", outlier_rule="none")
    setup = pipeline.check_calibration(robot, options)
    dataset = read_dataset(
        DATA / recording.csv,
        setup.chain.joint_names,
        other_joint_names=setup.chain.other_joint_names,
    ).subset(rows.tolist())
    times = []
    for _ in range(3):
        started = time.perf_counter()
        pipeline.calibrate_source(dataset, setup)
        times.append(time.perf_counter() - started)
    return float(np.median(times))


def same_model_heldout(recording: Recording, kept: np.ndarray, seeds: list[int]) -> list[float]:
    """kincal's held-out errors with FIGAROH's model (geometry and frames, no compliance:
    ``--fix compliance``) on the rows the default run kept, with no screening of its own: its
    splits of those rows are the default run's (and FIGAROH's)."""
    from schemas.dataset import read_dataset

    options = CalibrationOptions(
        seeds=seeds, outlier_rule="none", covariance="none", fixed_parameters=["compliance"]
    )
    setup = pipeline.check_calibration(robot_of(recording), options)
    chain = setup.chain
    dataset = read_dataset(
        DATA / recording.csv, chain.joint_names, other_joint_names=chain.other_joint_names
    ).subset(kept.tolist())
    result = pipeline.calibrate_source(dataset, setup).result
    assert result.evaluation is not None and result.outliers.n_used == kept.size
    by_seed = {
        s.seed: s.translation_mm for s in result.evaluation.splits if s.method == "calibrated"
    }
    return [by_seed[seed] for seed in seeds]


FIGAROH_COMPONENTS = {"px": "tx", "py": "ty", "pz": "tz", "phix": "rx", "phiy": "ry", "phiz": "rz"}
"""FIGAROH's names of a placement error's components (``d_px`` … ``d_phiz``, ``base_*``,
``pEE*``/``phiEE*``) and kincal's: both a correction right-multiplied on the placement, in
its own frame (translation m, rotation rad)."""


def figaroh_columns(chain: KinematicChain, names: list[str]) -> tuple[int, ...]:
    """kincal's columns (:func:`solver.kinematics.parameter_names`) of FIGAROH's ``full_params``
    parameters: ``d_<c>_<joint>`` is the joint's placement ``L_i``; ``base_<c>`` the unknown
    base frame, which kincal carries in ``L_1``; ``pEE<x>_1``/``phiEE<x>_1`` the marker in the
    tip frame, kincal's ``L_{k+1}``."""
    kincal = parameter_names(chain)
    first, tip = kincal[0].split(".")[0], kincal[6 * (chain.n_links - 1)].split(".")[0]
    columns = []
    for name in names:
        if name.startswith("base_"):
            link, component = first, FIGAROH_COMPONENTS[name.removeprefix("base_")]
        elif name.startswith(("pEE", "phiEE")):  # pEEx_1 → px, phiEEz_1 → phiz
            link, component = tip, FIGAROH_COMPONENTS[name.split("_")[0].replace("EE", "")]
        else:
            _, code, joint = name.split("_", 2)
            link, component = joint, FIGAROH_COMPONENTS[code]
        columns.append(kincal.index(f"{link}.{component}"))
    return tuple(sorted(columns))


FIGAROH_ROTATION_WEIGHT_M_PER_RAD = 0.1
"""FIGAROH's default cost divides position residuals by 1 mm and rotation residuals by 0.01 rad
(``apply_measurement_weighting``): 1 rad counts like 0.1 m (kincal's default: 1 m)."""


def same_parameters_heldout(
    recording: Recording,
    splits: list[dict[str, Any]],
    answers: list[dict[str, Any]],
) -> list[float]:
    """Per split, kincal's held-out error (mm) with exactly the parameters FIGAROH fitted on it
    (:func:`figaroh_columns`), its weighting of rotation rows, no compliance and no
    physical-range rule: kincal's Levenberg–Marquardt from its closed-form start on the split's
    training rows."""
    from schemas.dataset import read_dataset

    chain = pipeline.check_calibration(robot_of(recording), CalibrationOptions()).chain
    dataset = read_dataset(
        DATA / recording.csv, chain.joint_names, other_joint_names=chain.other_joint_names
    )
    q = dataset.joint_positions
    pose = lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw)
    loads = gravity_loads(chain, q)
    errors = []
    for split, answer in zip(splits, answers, strict=True):
        train, test = np.array(split["train"]), np.array(split["test"])
        options = FitOptions(
            rotation_weight_m_per_rad=FIGAROH_ROTATION_WEIGHT_M_PER_RAD,
            free_columns=figaroh_columns(chain, answer["names"]),
            non_negative_compliance=False,
        )
        fit = fit_deterministic(
            chain,
            q[train],
            pose[train],
            loads[train],
            measurement=pose_measurement(rotation=dataset.measures_rotation),
            options=options,
        )
        predicted = forward_kinematics(chain, fit.params, q[test], loads[test])
        errors.append(
            float(1e3 * np.linalg.norm(predicted[:, :3, 3] - pose[test, :3, 3], axis=1).mean())
        )
    return errors


def compare(recording: Recording, seeds: int, figaroh_python: str | None) -> SideBySide:
    """kincal (default and ``--fix compliance``) and, with ``figaroh_python``, FIGAROH and
    kincal on FIGAROH's parameters, on the same rows and splits of ``recording``."""
    robot = robot_of(recording)
    options = CalibrationOptions(seeds=list(range(1, seeds + 1)))
    setup = pipeline.check_calibration(robot, options)
    started = time.perf_counter()
    run = pipeline.calibrate_source(DATA / recording.csv, setup)
    kincal_run_s = time.perf_counter() - started
    result = run.result
    assert result.evaluation is not None
    kept = np.array(result.outliers.kept_indices())
    kincal_mm = {
        s.seed: s.translation_mm for s in result.evaluation.splits if s.method == "calibrated"
    }
    same_model_mm = same_model_heldout(recording, kept, options.seeds)
    splits = []
    for seed in options.seeds:
        train, test = split_indices(kept.size, seed, options.train_fraction)
        splits.append({"seed": seed, "train": kept[train].tolist(), "test": kept[test].tolist()})
    answer: list[dict[str, Any]] = []
    if figaroh_python is not None:
        answer = figaroh_answers(recording, robot, setup.chain, splits, figaroh_python)
    first_train = np.array(splits[0]["train"])
    return SideBySide(
        recording.name,
        result.outliers.n_input,
        result.outliers.n_used,
        [kincal_mm[seed] for seed in options.seeds],
        same_model_mm,
        [a["translation_mm"] for a in answer],
        kincal_fit_seconds(recording, first_train),
        kincal_run_s,
        [a["fit_s"] for a in answer],
        int(answer[0]["parameters"]) if answer else 0,
        same_parameters_heldout(recording, splits, answer) if answer else None,
        kept.tolist(),
    )


def figaroh_answers(
    recording: Recording,
    robot: RobotDescription,
    chain: KinematicChain,
    splits: list[dict[str, Any]],
    figaroh_python: str,
) -> list[dict[str, Any]]:
    """FIGAROH's ``full_params`` fit of each split (its held-out error, fit time, parameter
    names), through ``benchmarks/figaroh_calibration_driver.py`` under its own interpreter."""
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        (work / "robot.urdf").write_bytes(figaroh_urdf(robot, chain))
        request = {
            "urdf": str(work / "robot.urdf"),
            "base_frame": recording.base_frame,
            "tool_frame": recording.tip_frame,
            "measurable_dof": [True] * 6 if recording.full_pose else [True] * 3 + [False] * 3,
            "csv": str(DATA / recording.csv),
            "splits": splits,
            "work_dir": str(work),
        }
        (work / "request.json").write_text(json.dumps(request))
        subprocess.run(
            [figaroh_python, str(DRIVER), str(work / "request.json"), str(work / "answer.json")],
            check=True,
        )
        answers: list[dict[str, Any]] = json.loads((work / "answer.json").read_text())["splits"]
    return answers


def mean_se(values: list[float]) -> tuple[float, float]:
    array = np.asarray(values, dtype=float)
    return float(array.mean()), float(array.std(ddof=1) / np.sqrt(array.size))


def table(rows: list[SideBySide]) -> str:
    """The comparison table of ``rows`` (FIGAROH's columns from the same run)."""
    return render([result_row(row, "this run") for row in rows])


def result_row(row: SideBySide, figaroh_run: str) -> Row:
    """A results row: kincal's numbers per split and, when FIGAROH ran (``row.figaroh_mm``),
    FIGAROH's summary (held-out mean and standard error, median fit time, kincal on FIGAROH's
    parameters) with ``figaroh_run``, the command and date that produced it."""
    out: Row = {
        "robot": row.name,
        "rows": row.n_rows,
        "used": row.n_used,
        "kept": row.kept,
        "kincal_mm": row.kincal_mm,
        "same_model_mm": row.same_model_mm,
        "kincal_fit_s": row.kincal_fit_s,
        "kincal_run_s": row.kincal_run_s,
        "figaroh": None,
    }
    if row.figaroh_mm:
        same = None if row.same_parameters_mm is None else mean_se(row.same_parameters_mm)
        out["figaroh"] = {
            "run": figaroh_run,
            "held_out_mm": mean_se(row.figaroh_mm),
            "fit_s": float(np.median(row.figaroh_fit_s)),
            "parameters": row.figaroh_parameters,
            "same_parameters_mm": same,
        }
    return out


def render(rows: list[Row]) -> str:
    """The table of ``docs/results/figaroh_side_by_side.md``: per recording the rows (used),
    held-out mean position error ± one standard error over the splits (mm, to 0.01) of kincal's
    default calibration, of kincal with FIGAROH's model (``--fix compliance``) and of FIGAROH,
    whether each kincal column is within FIGAROH + 1 SE, kincal's fit time (to 0.001 s) and
    FIGAROH's (median over splits, to 0.01 s), their ratio, kincal's whole default run (to 0.1
    s), and kincal's fit on FIGAROH's parameters. FIGAROH's columns are "–" for a recording it
    did not run on."""
    header = [
        "Robot",
        "Rows (used)",
        "kincal default: held-out mm",
        "kincal, FIGAROH's model (`--fix compliance`)",
        "FIGAROH `full_params`",
        "≤ FIGAROH + 1 SE (default / same model)",
        "kincal fit s",
        "FIGAROH fit s",
        "Speed-up",
        "kincal default run s",
        "kincal, FIGAROH's parameters",
    ]
    cells = []
    for row in rows:
        k_mean, k_se = mean_se(row["kincal_mm"])
        s_mean, s_se = mean_se(row["same_model_mm"])
        figaroh = row["figaroh"]
        mine = [
            row["robot"],
            f"{row['rows']} ({row['used']})",
            f"{k_mean:.2f} ± {k_se:.2f}",
            f"{s_mean:.2f} ± {s_se:.2f}",
        ]
        if figaroh is None:
            theirs = ["–"] * 4
            same = "–"
        else:
            f_mean, f_se = figaroh["held_out_mm"]
            holds = " / ".join("yes" if m <= f_mean + f_se else "no" for m in (k_mean, s_mean))
            theirs = [
                f"{f_mean:.2f} ± {f_se:.2f}",
                holds,
                f"{figaroh['fit_s']:.2f}",
                f"{figaroh['fit_s'] / row['kincal_fit_s']:.0f}×",
            ]
            same = "–"
            if figaroh["same_parameters_mm"] is not None:
                same = "{:.2f} ± {:.2f}".format(*figaroh["same_parameters_mm"])
        cells.append(
            [
                *mine,
                theirs[0],
                theirs[1],
                f"{row['kincal_fit_s']:.3f}",
                theirs[2],
                theirs[3],
                f"{row['kincal_run_s']:.1f}",
                same,
            ]
        )
    return markdown_table(header, cells)


def main(
    figaroh_python: str | None,
    seeds: int = 10,
    only: list[str] | None = None,
    *,
    write: str | None = None,
) -> str:
    """Run the comparison and print its table. ``write``: the command line to record in
    ``docs/results/figaroh_side_by_side.json`` (written with its table when given); without
    ``figaroh_python`` each recording keeps FIGAROH's columns from that file, with the run
    they came from."""
    recorded: dict[str, Any] = {}
    if figaroh_python is None and write is not None:
        recorded = {r["robot"]: r["figaroh"] for r in read_results("figaroh_side_by_side")[1]}
    rows = []
    for recording in RECORDINGS:
        if only and recording.name not in only:
            continue
        row = compare(recording, seeds, figaroh_python)
        print(
            f"{row.name}: kincal {np.round(row.kincal_mm, 2).tolist()}\n"
            f"  kincal --fix compliance {np.round(row.same_model_mm, 2).tolist()}\n"
            f"  FIGAROH {np.round(row.figaroh_mm, 2).tolist()} "
            f"({row.figaroh_parameters} parameters)\n"
            f"  kincal, FIGAROH's parameters "
            f"{np.round(row.same_parameters_mm or [], 2).tolist()}",
            flush=True,
        )
        result = result_row(row, f"{write} ({datetime.date.today().isoformat()})")
        if figaroh_python is None:
            result["figaroh"] = recorded.get(row.name)
        rows.append(result)
    text = render(rows)
    print("\n" + text)
    if write is not None:
        for path in write_results("figaroh_side_by_side", write, rows, render):
            print(f"wrote {path}")
    return text


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--figaroh-python",
        default=None,
        help="python of a venv with figaroh (without it: kincal's columns only, and with "
        "--write-results FIGAROH's columns kept from the results file's recorded run)",
    )
    parser.add_argument("--seeds", type=int, default=10, help="number of held-out splits")
    parser.add_argument("--only", action="append", help="robot name (repeatable)")
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/figaroh_side_by_side.{json,md} (docs/figaroh.md)",
    )
    arguments = parser.parse_args()
    command = " ".join(["python -m benchmarks.figaroh_side_by_side", *sys.argv[1:]])
    main(
        arguments.figaroh_python,
        arguments.seeds,
        arguments.only,
        write=command if arguments.write_results else None,
    )
