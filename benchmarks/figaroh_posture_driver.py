"""FIGAROH 1.0.2's calibration posture selection, driven on a given candidate set.

Runs under a *separate* interpreter that has figaroh installed (never a kincal dependency);
``benchmarks/design.py`` writes the inputs and reads the answer. It imports nothing of kincal.

Usage (figaroh's python)::

    python benchmarks/figaroh_posture_driver.py REQUEST.json ANSWER.json

REQUEST.json: ``urdf`` (path; no meshes, no continuous joints: FIGAROH's candidate loader writes
one angle per joint into q, so the benchmark passes a copy with continuous joints made revolute),
``base_frame``, ``tool_frame``, ``candidates_yaml`` (FIGAROH's own candidate format:
``calibration_joint_names`` and ``calibration_joint_configurations``), ``poses`` (the
numbers K of poses wanted), ``seed`` and ``work_dir``.

What runs is FIGAROH's own pipeline (``figaroh.optimal.base_optimal_calibration``):
``BaseOptimalCalibration`` from a unified configuration (full pose measured, ``full_params``),
``initialize()`` (its base kinematic regressor and per-pose information matrices),
``calculate_optimal_configurations()`` (its D-optimal SOCP relaxation, ``Σw ≤ 1``, picos +
cvxopt, then its threshold rule ``w > 1e-5``), and its ``Detmax`` exchange algorithm for exactly
K poses. FIGAROH has no "choose K" option in its SOCP path; the answer reports both its own
selection (whatever size the threshold gives) and the K largest of its SOCP weights.
"""

from __future__ import annotations

import json
import logging
import random
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # FIGAROH's plot() calls plt.show()

import numpy as np
import yaml
from figaroh.optimal.base_optimal_calibration import (
    BaseOptimalCalibration,
    Detmax,
)
from figaroh.tools.robot import Robot


def unified_config(request: dict, path: Path) -> None:  # type: ignore[type-arg]
    config = {
        "meta": {"schema_version": "2.0"},
        "robot": {"name": "kincal_benchmark"},
        "tasks": {
            "calibration": {
                "type": "kinematic_calibration",
                "kinematics": {
                    "base_frame": request["base_frame"],
                    "tool_frame": request["tool_frame"],
                },
                "measurements": {
                    "markers": [{"measurable_dof": [True] * 6}],
                },
                "parameters": {"calibration_level": "full_params", "random_seed": 0},
                "data": {
                    "number_of_samples": 0,
                    "sample_configurations_file": request["candidates_yaml"],
                },
            }
        },
    }
    path.write_text(yaml.safe_dump(config))


def main(request_path: str, answer_path: str) -> None:
    logging.disable(logging.WARNING)
    request = json.loads(Path(request_path).read_text())
    work = Path(request["work_dir"])
    config = work / "figaroh_config.yaml"
    unified_config(request, config)
    robot = Robot(request["urdf"], package_dirs=str(work))
    started = time.perf_counter()
    optimal = BaseOptimalCalibration(robot, str(config))
    optimal.initialize()
    optimal.calculate_optimal_configurations(selection_method="threshold")
    socp_s = time.perf_counter() - started
    n = optimal.calib_config["NbSample"]
    weights = np.array(optimal.w_list, dtype=float)
    ranked = [int(i) for i in optimal.w_dict_sort]  # decreasing weight
    threshold = [int(i) for i in ranked if optimal.w_dict_sort[i] > optimal.eps_opt]
    random.seed(int(request["seed"]))  # Detmax starts from random.sample
    detmax: dict[str, list[int]] = {}
    detmax_s: dict[str, float] = {}
    for k in request["poses"]:
        started = time.perf_counter()
        detmax[str(k)] = run_detmax(optimal._subX_dict, int(k))
        detmax_s[str(k)] = time.perf_counter() - started
    answer = {
        # FIGAROH appends its base parameters to param_name at every regressor pass.
        "figaroh_base_parameters": len(dict.fromkeys(optimal.calib_config["param_name"])),
        "candidates": n,
        "socp_weights": weights.tolist(),
        "socp_weight_sum": float(weights.sum()),
        "threshold_selection": threshold,
        "ranking": ranked,
        "detmax": detmax,  # as FIGAROH left each set (its exchange can repeat a pose)
        "min_poses": int(optimal.minNbChosen),
        "socp_s": socp_s,
        "detmax_s": detmax_s,
    }
    Path(answer_path).write_text(json.dumps(answer))


def run_detmax(pool: dict, k: int) -> list[int]:  # type: ignore[type-arg]
    """FIGAROH's ``Detmax(pool, k).main_algo()``. It keeps its set in a local variable and
    returns only the criterion history; its last criterion evaluation is of the final set, so
    the set is read from the argument of that call (get_critD is wrapped, not changed)."""
    detmax = Detmax(pool, k)
    evaluate = detmax.get_critD
    last: list[list[int]] = [[]]

    def recording(subset: list[int]) -> float:
        last[0] = [int(i) for i in subset]
        return float(evaluate(subset))

    detmax.get_critD = recording  # type: ignore[method-assign]
    detmax.main_algo()
    return last[0]


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
