"""Figures: paper Fig. 4b (σ per frame) and Fig. 6 (observed error of the chosen approaches)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from benchmarks.reproduce_paper.paper import PAPER_RUNS
from benchmarks.reproduce_paper.selection import LABELS, picked_errors
from benchmarks.reproduce_paper.study import StudyResult

_FRAME_COMPONENTS = (("x", "y", "z"), ("roll", "pitch", "yaw"))


def sigma_figure(study: StudyResult, path: Path) -> Path:
    """Paper Fig. 4b: σ per frame (joints, then the camera noise), translation in mm and
    rotation in mrad; bars = calibrated on all kept samples, dots = per split, black = true."""
    names = [*(f"joint {i + 1}" for i in range(study.first.recording.true_robot.chain.n_joints))]
    names.append("noise")
    true = np.vstack(
        [
            study.first.recording.true_robot.perturbation_std,
            study.first.recording.true_robot.noise_std,
        ]
    )
    figure = Figure(figsize=(11.0, 6.2), layout="constrained")
    axes = figure.subplots(2, 1)
    x = np.arange(len(names))
    width = 0.26
    colors = ("tab:blue", "tab:orange", "tab:green")
    for panel, (ax, components) in enumerate(zip(axes, _FRAME_COMPONENTS, strict=True)):
        for c, component in enumerate(components):
            column = 3 * panel + c
            offset = (c - 1) * width
            ax.bar(
                x + offset,
                1e3 * study.sigma_full[:, column],
                width,
                color=colors[c],
                alpha=0.75,
                label=f"{component}: calibrated (all kept samples)",
            )
            if study.sigma_splits is not None:
                for split in study.sigma_splits:
                    ax.plot(x + offset, 1e3 * split[:, column], ".", color=colors[c], ms=3)
            ax.plot(x + offset, 1e3 * true[:, column], "_", color="black", ms=14, mew=2)
        ax.plot([], [], "_", color="black", ms=14, mew=2, label="true σ")
        if study.sigma_splits is not None:
            ax.plot([], [], ".", color="grey", label="per split (training set)")
        ax.set_xticks(x, names)
        unit = "mm" if panel == 0 else "mrad"
        ax.set_ylabel(f"σ {'translation' if panel == 0 else 'rotation'} [{unit}]")
        ax.legend(fontsize=7, ncol=2)
    figure.suptitle(
        "Calibrated standard deviations of the random perturbations (paper Fig. 4b), "
        f"simulated Jaco2, recording {study.first.recording.seed}",
        fontsize=10,
    )
    figure.savefig(path, dpi=110)
    return path


def runs_figure(study: StudyResult, path: Path) -> Path:
    """Paper Fig. 6: observed x-y error of the lowest- and highest-score approach per run
    (first 10 runs), ours and the oracle."""
    runs = study.first.runs[:PAPER_RUNS]
    x = np.arange(1, len(runs) + 1)
    figure = Figure(figsize=(8.0, 3.6), layout="constrained")
    ax = figure.subplots()
    for method, marker in (("ours", "o"), ("oracle", "s")):
        picked = picked_errors(runs, method, "error_mm")
        ax.plot(
            x - 0.1,
            picked[:, 0],
            marker,
            color="tab:green",
            mfc="none" if method == "oracle" else None,
            label=f"{LABELS[method]}: lowest score",
        )
        ax.plot(
            x + 0.1,
            picked[:, 1],
            marker,
            color="tab:red",
            mfc="none" if method == "oracle" else None,
            label=f"{LABELS[method]}: highest score",
        )
    ax.set_xticks(x)
    ax.set_xlabel("run")
    ax.set_ylabel("mean x-y error [mm]")
    ax.legend(fontsize=7, ncol=2)
    figure.suptitle("Observed docking error of the chosen approaches (paper Fig. 6)", fontsize=10)
    figure.savefig(path, dpi=110)
    return path
