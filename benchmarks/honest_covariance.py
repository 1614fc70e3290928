"""Are kincal's default covariances honest on data it did not make? (issue 13)

Recordings of a Kinova Jaco2 from :mod:`benchmarks.pinocchio_sim` (Pinocchio only, no kincal
formula), clean or with 1 % detector failures (5 mm and 10° in the marker frame), go through the
user's path: ``kincal calibrate DATA --robot kinova`` with default options (``--no-heldout``:
the held-out splits do not touch the covariances) and ``kincal predict --part random-effects
--no-noise`` (Σ_E of Eq. 12 alone) on 40 new
configurations. Per seed it reports

* the share of clean samples the outlier rule removed and of detector failures it caught;
* the task-score error: mean over the configurations of the predicted ``tr(W Σ_E W^T)`` (paper
  weights ``W = diag(0.4, 0.4, 0, 0.1, 0.1, 0)``, Σ_n excluded, as ``kincal rank`` scores) against
  the truth from finite differences of Pinocchio's forward kinematics, relative.

Usage: ``python -m benchmarks.honest_covariance [--sizes 119,2000] [--seeds 10] [--flags ...]``
(extra ``kincal calibrate`` flags, e.g. ``--flags=--outlier-rule=sigma`` for the paper's rule).
``python -m benchmarks.honest_covariance --write-results`` runs the settings docs/covariance.md
quotes (:data:`PAGE_SETTINGS`: the default rule with 2 % detector failures, 10 seeds; the
paper's 2σ rule on clean data, 3 seeds; N = 119 and 2000) and writes
``docs/results/honest_covariance.{json,md}``, each seed's outcome with the table.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.pinocchio_sim import (
    PinocchioRobot,
    draw_true_robot,
    simulate,
    true_ee_covariance,
    write_configurations,
    write_dataset,
)
from benchmarks.results import Row, markdown_table, percent, write_results
from schemas.calibration import CalibrationResult
from schemas.robots import load_robot

PAPER_W = np.diag([0.4, 0.4, 0.0, 0.1, 0.1, 0.0])
N_CONFIGURATIONS = 40


@functools.cache
def jaco2() -> PinocchioRobot:
    description = load_robot("kinova")
    return PinocchioRobot.from_urdf(
        description.urdf_xml, description.base_frame, description.tip_frame
    )


def perturbation_std(k: int) -> np.ndarray:
    """Backlash- and bearing-like play: mostly rotation (rad), a little translation (m)."""
    return np.tile([2e-5, 2e-5, 2e-5, 8e-4, 8e-4, 4e-4], (k, 1))


def task_score(covariance: np.ndarray) -> np.ndarray:
    """tr(W Σ Wᵀ) (n,) of covariances (n, 6, 6) with the paper's W."""
    return np.einsum("ij,njk,ik->n", PAPER_W, covariance, PAPER_W)


@dataclass(frozen=True)
class Outcome:
    n: int
    seed: int
    clean_removed: float
    gross_caught: float | None
    task_error: float


Kincal = Callable[..., None]
"""Runs one ``kincal`` command line (a fresh process here; the tests run it in process)."""


def kincal(*args: str) -> None:
    command = [str(Path(sys.executable).with_name("kincal")), *args]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode not in (0, 3):
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stdout}\n{done.stderr}")


def run_one(
    n: int,
    seed: int,
    gross_fraction: float,
    flags: list[str],
    folder: Path,
    kincal: Kincal = kincal,
) -> Outcome:
    robot = jaco2()
    rng = np.random.default_rng(seed)
    k = len(robot.joint_ids)
    truth = draw_true_robot(robot, rng, perturbation_std=perturbation_std(k))
    recording = simulate(robot, truth, n, rng, gross_fraction=gross_fraction)
    data = write_dataset(robot, recording, folder / f"jaco2_{n}_{seed}.csv")
    result_path = folder / f"result_{n}_{seed}.json"
    kincal(
        "calibrate", str(data), "--robot", "kinova", "--no-heldout", "-o", str(result_path), *flags
    )
    q_new = robot.sample_q(N_CONFIGURATIONS, rng)
    configs = write_configurations(robot, q_new, folder / f"configs_{n}_{seed}.csv")
    poses = folder / f"poses_{n}_{seed}.csv"
    kincal(
        "predict",
        str(result_path),
        str(configs),
        "--part",
        "random-effects",
        "--no-noise",
        "-o",
        str(poses),
    )
    predicted = pd.read_csv(poses)[[f"cov_{i}{j}" for i in range(6) for j in range(6)]]
    predicted_cov = predicted.to_numpy().reshape(-1, 6, 6)
    true_cov = np.array([true_ee_covariance(robot, truth, q) for q in q_new])
    task_error = float(task_score(predicted_cov).mean() / task_score(true_cov).mean() - 1.0)
    result = CalibrationResult.model_validate_json(result_path.read_text())
    removed = {r - 1 for r in result.outliers.removed_rows}
    gross = set(recording.gross.tolist())
    clean_removed = len(removed - gross) / (n - len(gross))
    caught = len(removed & gross) / len(gross) if gross else None
    return Outcome(n, seed, clean_removed, caught, task_error)


@dataclass(frozen=True)
class Setting:
    """One line of the page's table per size: the outlier rule (its label and ``kincal
    calibrate`` flags), the share of detector failures simulated and the number of seeds."""

    rule: str
    flags: tuple[str, ...]
    gross_fraction: float
    seeds: int


PAGE_SETTINGS = (
    Setting("model (default)", (), 0.02, 10),
    Setting("paper's 2σ (`--outlier-rule sigma`)", ("--outlier-rule", "sigma"), 0.0, 3),
)
PAGE_SIZES = (119, 2000)


def setting_row(setting: Setting, outcomes: list[Outcome]) -> Row:
    """The numbers of one line of ``docs/results/honest_covariance``: the setting, each seed's
    outcome and the summaries the table shows (shares and errors as fractions)."""
    errors = [o.task_error for o in outcomes]
    removed = [o.clean_removed for o in outcomes]
    caught = [o.gross_caught for o in outcomes if o.gross_caught is not None]
    q1, q2, q3 = (float(v) for v in np.percentile(errors, [25, 50, 75]))
    return {
        "n": outcomes[0].n,
        "rule": setting.rule,
        "flags": list(setting.flags),
        "gross_fraction": setting.gross_fraction,
        "seeds": len(outcomes),
        "clean_removed_median": statistics.median(removed),
        "clean_removed_max": max(removed),
        "gross_caught_min": min(caught) if caught else None,
        "task_error_median": q2,
        "task_error_q1": q1,
        "task_error_q3": q3,
        "outcomes": [
            {
                "seed": o.seed,
                "clean_removed": o.clean_removed,
                "gross_caught": o.gross_caught,
                "task_error": o.task_error,
            }
            for o in outcomes
        ],
    }


def render(rows: list[Row]) -> str:
    """The table of ``docs/results/honest_covariance.md`` (clean samples removed to 0.01 %,
    failures caught to 1 %, task-score error to 0.1 %)."""

    def rule(row: Row) -> str:
        if row["gross_fraction"]:
            failures = percent(row["gross_fraction"], 0)
            return f"{row['rule']}, {failures} detector failures, {row['seeds']} seeds"
        return f"{row['rule']}, clean data, {row['seeds']} seeds"

    return markdown_table(
        (
            "N",
            "rule",
            "clean samples removed (median, max)",
            "failures caught (min)",
            "task-score error tr(WΣ_EWᵀ) (median, IQR)",
        ),
        [
            (
                r["n"],
                rule(r),
                f"{percent(r['clean_removed_median'], 2)}, {percent(r['clean_removed_max'], 2)}",
                "–" if r["gross_caught_min"] is None else percent(r["gross_caught_min"], 0),
                f"{percent(r['task_error_median'], 1, signed=True)} "
                f"({percent(r['task_error_q1'], 1, signed=True)[:-2]} … "
                f"{percent(r['task_error_q3'], 1, signed=True)})",
            )
            for r in rows
        ],
    )


def write_page_results() -> list[Row]:
    """Every :data:`PAGE_SETTINGS` at every :data:`PAGE_SIZES` (rows by setting, then size),
    written to ``docs/results/honest_covariance.{json,md}``."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for setting in PAGE_SETTINGS:
            for n in PAGE_SIZES:
                outcomes = [
                    run_one(n, seed, setting.gross_fraction, list(setting.flags), Path(tmp))
                    for seed in range(setting.seeds)
                ]
                rows.append(setting_row(setting, outcomes))
                print(render([rows[-1]]).splitlines()[-1], flush=True)
    command = "python -m benchmarks.honest_covariance --write-results"
    for path in write_results("honest_covariance", command, rows, render):
        print("wrote", path)
    return rows


def main(sizes: list[int], seeds: int, gross_fraction: float, flags: list[str]) -> str:
    lines = [
        f"flags: {' '.join(flags) or '(defaults)'}; detector failures: {gross_fraction:.0%}",
        "",
        "| N | seeds | clean removed (median, max) | failures caught (min) "
        "| task-score error (median, IQR) |",
        "|---|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            outcomes = [run_one(n, s, gross_fraction, flags, Path(tmp)) for s in range(seeds)]
            errors = [o.task_error for o in outcomes]
            removed = [o.clean_removed for o in outcomes]
            caught = [o.gross_caught for o in outcomes if o.gross_caught is not None]
            q1, q2, q3 = np.percentile(errors, [25, 50, 75])
            lines.append(
                f"| {n} | {seeds} | {statistics.median(removed):.2%}, {max(removed):.2%} | "
                + (f"{min(caught):.0%}" if caught else "–")
                + f" | {q2:+.1%} ({q1:+.1%} … {q3:+.1%}) |"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="119,2000")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--gross-fraction", type=float, default=0.0)
    parser.add_argument("--flags", default="", help="extra kincal calibrate flags, space separated")
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="run the page's settings (the other options are ignored) and write "
        "docs/results/honest_covariance.{json,md}",
    )
    args = parser.parse_args()
    if args.write_results:
        write_page_results()
        raise SystemExit(0)
    print(
        main(
            [int(s) for s in args.sizes.split(",")],
            args.seeds,
            args.gross_fraction,
            args.flags.split(),
        )
    )
