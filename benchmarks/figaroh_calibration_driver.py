"""FIGAROH 1.0.2's geometric calibration on given train/test splits of a recording.

Runs under a *separate* interpreter that has figaroh installed (never a kincal dependency);
``benchmarks/figaroh_side_by_side.py`` writes the inputs and reads the answer. It imports nothing
of kincal.

Usage (figaroh's python)::

    python benchmarks/figaroh_calibration_driver.py REQUEST.json ANSWER.json

REQUEST.json: ``urdf`` (path; no meshes, continuous joints made revolute), ``base_frame``,
``tool_frame``, ``measurable_dof`` (six booleans, FIGAROH's marker measurability), ``csv`` (the
recording in FIGAROH's own CSV layout: ``x1, y1, z1[, phix1, phiy1, phiz1]`` and one column per
active joint), ``splits`` (``seed``, ``train`` and ``test`` row indices of that CSV) and
``work_dir``.

What runs per split is FIGAROH's own pipeline: ``BaseCalibration`` from a unified configuration
(``calibration_level: full_params``: every joint placement, the unknown base frame and marker,
``known_baseframe``/``known_tipframe`` False; training rows as ``source_file``, test rows as
``validation_data_file``),
``initialize()`` (its base-parameter selection by QR of the kinematic regressor) and
``solve(method="lm", max_iterations=1)`` — one Levenberg–Marquardt fit, no outlier exclusion
between fits, so FIGAROH sees exactly the rows kincal does. The fit time is ``initialize`` +
``solve``. The held-out error is FIGAROH's own validation residual
(``_compute_validation_metrics``: calibrated forward kinematics against the test rows), as the
mean over test rows of the position error norm, in mm: kincal's held-out statistic. The answer
also names the parameters FIGAROH fitted (``names``, its ``param_name``).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pandas as pd
import yaml
from figaroh.calibration.base_calibration import BaseCalibration
from figaroh.tools.robot import Robot


def config_file(request: dict, train: Path, test: Path, path: Path) -> None:  # type: ignore[type-arg]
    config = {
        "meta": {"schema_version": "2.0"},
        "robot": {"name": "kincal_side_by_side"},
        "tasks": {
            "calibration": {
                "type": "kinematic_calibration",
                "kinematics": {
                    "base_frame": request["base_frame"],
                    "tool_frame": request["tool_frame"],
                },
                "measurements": {"markers": [{"measurable_dof": request["measurable_dof"]}]},
                "parameters": {"calibration_level": "full_params", "random_seed": 0},
                "data": {
                    "number_of_samples": 0,
                    "source_file": str(train),
                    "validation_data_file": str(test),
                },
            }
        },
    }
    path.write_text(yaml.safe_dump(config))


def heldout_mean_mm(metrics: dict) -> float:  # type: ignore[type-arg]
    """Mean over test rows of the position error norm (mm) from FIGAROH's residuals."""
    per_dof = metrics["error_fitted_per_dof"]  # scaled: mm for position components
    position = [np.asarray(v) for k, v in per_dof.items() if k.endswith("(mm)")]
    return float(np.mean(np.sqrt(np.sum(np.square(position), axis=0))))


def main(request_path: str, answer_path: str) -> None:
    logging.disable(logging.WARNING)
    request = json.loads(Path(request_path).read_text())
    work = Path(request["work_dir"])
    frame = pd.read_csv(request["csv"])
    robot = Robot(request["urdf"], package_dirs=str(work))
    answers = []
    for split in request["splits"]:
        seed = split["seed"]
        train, test = work / f"train_{seed}.csv", work / f"test_{seed}.csv"
        frame.iloc[split["train"]].to_csv(train, index=False)
        frame.iloc[split["test"]].to_csv(test, index=False)
        config = work / f"config_{seed}.yaml"
        config_file(request, train, test, config)
        with contextlib.redirect_stdout(io.StringIO()):
            started = time.perf_counter()
            calibration = BaseCalibration(robot, str(config))
            # the measurement frame and the marker are unknown (FIGAROH's examples set these
            # in their robot subclasses)
            calibration.calib_config["known_baseframe"] = False
            calibration.calib_config["known_tipframe"] = False
            calibration.initialize()
            calibration.solve(method="lm", max_iterations=1, enable_logging=False)
            fit_s = time.perf_counter() - started
            metrics = calibration._compute_validation_metrics()
        assert metrics is not None and metrics["validation_source"] == "validation_data"
        answers.append(
            {
                "seed": seed,
                "n_train": len(split["train"]),
                "n_test": len(split["test"]),
                "translation_mm": heldout_mean_mm(metrics),
                "fit_s": fit_s,
                "parameters": len(calibration.calib_config["param_name"]),
                "names": list(calibration.calib_config["param_name"]),
                "status": calibration.STATUS,
            }
        )
    Path(answer_path).write_text(json.dumps({"splits": answers}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
