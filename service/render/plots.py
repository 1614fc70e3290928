"""Figures for reports and the README (matplotlib's object API: no display, no global state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

DEG_PER_RAD = 180.0 / np.pi
# Residual components [v; w]: name, unit, scale from m or rad.
COMPONENTS: tuple[tuple[str, str, float], ...] = (
    ("x", "mm", 1e3),
    ("y", "mm", 1e3),
    ("z", "mm", 1e3),
    ("roll", "deg", DEG_PER_RAD),
    ("pitch", "deg", DEG_PER_RAD),
    ("yaw", "deg", DEG_PER_RAD),
)


def residual_histograms(
    before: NDArray[np.float64], after: NDArray[np.float64], path: Path, *, title: str
) -> Path:
    """Paper Fig. 4a: distribution of each residual component before and after calibration.

    ``before``/``after`` (N, 6 or 3): end-effector-frame residuals [v; w] in m and rad.
    """
    d = before.shape[1]
    figure = Figure(figsize=(2.6 * d, 2.8), layout="constrained")
    axes = figure.subplots(1, d, squeeze=False)[0]
    for i, ax in enumerate(axes):
        name, unit, scale = COMPONENTS[i]
        values_before, values_after = before[:, i] * scale, after[:, i] * scale
        edges = np.histogram_bin_edges(np.r_[values_before, values_after], bins=25)
        ax.hist(values_before, bins=edges, alpha=0.55, label="before", color="tab:red")
        ax.hist(values_after, bins=edges, alpha=0.65, label="calibrated", color="tab:blue")
        ax.set_xlabel(f"{name} [{unit}]")
        ax.set_yticks([])
    axes[0].legend(fontsize=8)
    figure.suptitle(title, fontsize=10)
    figure.savefig(path, dpi=110)
    return path


def coverage_figure(
    expected: NDArray[np.float64], observed: NDArray[np.float64], *, title: str
) -> Figure:
    """Coverage of a predicted covariance (issue 13): the share of held-out poses inside the
    predicted α-ellipsoid (``observed``) against α (``expected``), with the diagonal a right
    covariance would follow."""
    figure = Figure(figsize=(4.6, 4.2), layout="constrained")
    ax = figure.subplots()
    ax.plot([0.0, 1.0], [0.0, 1.0], color="0.6", linestyle="--", label="ideal")
    ax.plot(expected, observed, marker="o", markersize=4, color="tab:blue", label="held-out")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_xlabel("expected share inside the predicted ellipsoid")
    ax.set_ylabel("observed share of held-out poses")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title, fontsize=9)
    return figure
