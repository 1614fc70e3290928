"""Figures for reports and the README (matplotlib's object API: no display, no global state)."""

from __future__ import annotations

import datetime as dt
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.dates import AutoDateLocator, ConciseDateFormatter, date2num
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import NullFormatter, StrMethodFormatter
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


SMALLEST_D2 = 1e-3
"""A d² or Σ d² drawn at no less than this (the log scale has no 0)."""
LIMIT_COLOUR = "tab:orange"
BAD_COLOUR = "#c00000"


def log_scale(ax: Axes, values: list[float]) -> None:
    """A log y axis over the whole decades around ``values`` (at least one; 1 to 10 without
    values), labelled 1, 10, 100 ..., with room above the largest so no marker is cut."""
    shown = [max(v, SMALLEST_D2) for v in values] or [1.0]
    low = np.floor(np.log10(min(shown)))
    high = max(np.ceil(np.log10(max(shown))), low + 1.0)
    if np.log10(max(shown)) > high - 0.05:
        high += 1.0
    ax.set_yscale("log")
    ax.set_ylim(float(10.0**low), float(10.0**high))
    ax.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def check_figure(
    d2: NDArray[np.float64],
    bad_sample: NDArray[np.bool_],
    *,
    dof: int,
    pose_limit: float | None,
    global_test: tuple[float, float, int, int] | None,
) -> Figure:
    """A check's poses against the χ² quantiles it tests them with (``kincal check``'s report):
    left, each pose's ``d2`` (n,) (a χ²_``dof`` variable when the calibration holds, log scale)
    with the max-type test's per-pose limit ``pose_limit`` (the Šidák quantile; None when the
    check has too few poses), the ``bad_sample`` (n,) poses set aside marked; right, the
    global test's statistic against its threshold, ``global_test`` = (statistic, threshold,
    degrees of freedom, poses used) or None."""
    figure = Figure(figsize=(8.4, 3.4), layout="constrained")
    poses_ax, global_ax = figure.subplots(
        1, 2, width_ratios=(5, 1.2), squeeze=True, gridspec_kw={"wspace": 0.08}
    )
    number = np.arange(1, d2.size + 1)
    shown = np.maximum(d2, SMALLEST_D2)
    good = ~bad_sample
    poses_ax.plot(number[good], shown[good], "o", color="tab:blue", label="pose")
    if bad_sample.any():
        poses_ax.plot(
            number[bad_sample],
            shown[bad_sample],
            "X",
            markersize=10,
            color=BAD_COLOUR,
            label="bad sample (set aside)",
        )
    if pose_limit is not None:
        poses_ax.axhline(
            pose_limit,
            color=LIMIT_COLOUR,
            linestyle="--",
            label=f"one pose's limit {pose_limit:.1f} (χ²$_{{{dof}}}$, Šidák)",
        )
    log_scale(poses_ax, [*d2, *([] if pose_limit is None else [pose_limit])])
    poses_ax.set_xlabel("check pose")
    poses_ax.set_ylabel(f"d² (χ²$_{{{dof}}}$ if it holds)")
    if d2.size <= 30:
        poses_ax.set_xticks(number)
    poses_ax.legend(fontsize=8, loc="best")
    if global_test is None:
        global_ax.set_axis_off()
        global_ax.text(0.5, 0.5, "no global test\n(too few poses)", ha="center", va="center")
        return figure
    statistic, threshold, global_dof, used = global_test
    global_ax.bar(
        [0.0],
        [statistic],
        width=0.6,
        color=BAD_COLOUR if statistic > threshold else "tab:blue",
    )
    global_ax.axhline(threshold, color=LIMIT_COLOUR, linestyle="--")
    global_ax.set_ylim(0.0, 1.15 * max(statistic, threshold))
    global_ax.set_xlim(-0.6, 0.6)
    global_ax.set_xticks([0.0], [f"{used} poses"])
    global_ax.set_title(
        f"global: Σ d² {statistic:.1f}\nχ²$_{{{global_dof}}}$ limit {threshold:.1f}", fontsize=9
    )
    return figure


POINT_STYLES: dict[str, dict[str, Any]] = {
    "holds": {"marker": "o", "color": "#33aa33", "markersize": 6},
    "drifted": {
        "marker": "o",
        "color": BAD_COLOUR,
        "markersize": 11,
        "markeredgecolor": "#600000",
        "markeredgewidth": 1.5,
    },
    "inconclusive": {"marker": "^", "color": "0.6", "markersize": 8},
}
"""A check's point on the checks page by its verdict (an inconclusive check: on the time axis)."""
LEGEND_LABELS = {"holds": "holds", "drifted": "drifted", "inconclusive": "inconclusive (no test)"}


def checks_over_time_figure(
    times: list[dt.datetime],
    statistics: list[float | None],
    thresholds: list[float | None],
    verdicts: list[str],
) -> Figure:
    """A calibration's checks over time (the service's checks page), oldest first: each
    check's global statistic Σ d² (log scale: a drift's is often a hundred times its
    threshold), a larger red dot when it drifted, a grey triangle on the time axis for an
    inconclusive check (no statistic), and the threshold as a dashed step line (each check's
    own, held flat half-way to its neighbours: it depends on the number of poses). The
    artists carry SVG ids: ``check-<i>`` for the i-th check's point, ``threshold`` for the
    line, ``plot-area`` for the axes' background."""
    figure = Figure(figsize=(7.6, 3.0), layout="constrained")
    ax = figure.subplots()
    ax.patch.set_gid("plot-area")
    days = date2num(times)  # matplotlib's dates: days, UTC
    span = float(days[-1] - days[0])
    pad = 0.04 * span if span > 0.0 else 1.0 / 24.0
    left, right = float(days[0]) - pad, float(days[-1]) + pad
    for i, (day, statistic, verdict) in enumerate(zip(days, statistics, verdicts, strict=True)):
        style = POINT_STYLES[verdict if statistic is not None else "inconclusive"]
        if statistic is None:
            on_axis: dict[str, Any] = {"transform": ax.get_xaxis_transform(), "clip_on": False}
            ax.plot([day], [0.0], linestyle="none", gid=f"check-{i}", **style, **on_axis)
        else:
            value = max(statistic, SMALLEST_D2)
            ax.plot([day], [value], linestyle="none", gid=f"check-{i}", **style)
    tested = [(d, t) for d, t in zip(days, thresholds, strict=True) if t is not None]
    if tested:
        edges = [left, *((a + b) / 2 for (a, _), (b, _) in pairwise(tested)), right]
        xs = [x for i in range(len(tested)) for x in (edges[i], edges[i + 1])]
        ys = [max(t, SMALLEST_D2) for _, t in tested for _ in range(2)]
        ax.plot(xs, ys, color=LIMIT_COLOUR, linestyle="--", linewidth=2, gid="threshold")
    log_scale(ax, [v for v in (*statistics, *thresholds) if v is not None])
    ax.set_xlim(left, right)
    locator = AutoDateLocator(tz=dt.UTC)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(ConciseDateFormatter(locator, tz=dt.UTC))
    ax.set_ylabel("Σ d² (log scale)")
    ax.set_xlabel("check time (UTC)")
    ax.grid(True, which="major", axis="y", color="0.9")
    handles = [
        Line2D([], [], linestyle="none", label=LEGEND_LABELS[verdict], **style)
        for verdict, style in POINT_STYLES.items()
    ]
    handles.insert(
        2, Line2D([], [], color=LIMIT_COLOUR, linestyle="--", label="threshold at the level")
    )
    ax.legend(handles=handles, fontsize=8, loc="best")
    return figure
