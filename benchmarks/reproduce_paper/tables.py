"""The report's markdown tables."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from benchmarks.reproduce_paper.calibration import TableII
from benchmarks.reproduce_paper.docking import TaskScoring
from benchmarks.reproduce_paper.known_noise import KNOWN_NOISE_VARIANTS
from benchmarks.reproduce_paper.paper import (
    PAPER_SELECTION_MM,
    PAPER_TABLE_II,
    PAPER_TABLE_III,
    PAPER_WINS,
)
from benchmarks.reproduce_paper.selection import (
    LABELS,
    METHODS,
    Comparison,
    Selection,
    picked_errors,
)
from benchmarks.reproduce_paper.study import StudyResult
from service.render.text import METHOD_LABELS
from solver.arrays import FloatArray

COMPONENT_HEADER = ("x mm", "y mm", "z mm", "roll mrad", "pitch mrad", "yaw mrad")
"""Columns of a σ per pose component ([v; w] of a frame), printed in mm and mrad."""
SELECTION_HEADER = ("score", "lowest-score mm", "highest-score mm", "reduction", "95 % CI")
"""The first columns of a lowest- vs highest-score selection table (:func:`_selection_cells`)."""


def ci(interval: tuple[float, float], scale: float = 1.0, digits: int = 0) -> str:
    """``[low, high]`` of a 95 % interval, times ``scale``, with ``digits`` decimals."""
    return f"[{scale * interval[0]:.{digits}f}, {scale * interval[1]:.{digits}f}]"


def reduction(selection: Selection) -> str:
    """A selection's reduction with its 95 % interval, "12.3 % [4, 20]"."""
    return f"{selection.reduction_pct:.1f} % {ci(selection.reduction_ci)}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A pipe table: the ``header`` cells, then one line per row of formatted cells."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def table_ii_markdown(table: TableII) -> str:
    """Paper Table II layout, with the paper's means for comparison."""
    header = ["", "", *map(str, table.seeds), "mean", "paper mean"]
    rows = []
    for method, label in METHOD_LABELS.items():
        if method not in table.errors:
            continue
        for i, quantity in enumerate(("Trans. mm", "Rot. deg")):
            values = [table.errors[method][s][i] for s in table.seeds]
            paper = float(np.mean(PAPER_TABLE_II[method][i]))
            rows.append(
                [
                    label if i == 0 else "",
                    quantity,
                    *(f"{v:.2f}" for v in values),
                    f"**{np.mean(values):.2f}**",
                    f"{paper:.2f}",
                ]
            )
    return markdown_table(header, rows)


def sigma_markdown(
    study: StudyResult, *sigmas: FloatArray, noise_label: str = "camera noise"
) -> str:
    """σ per frame, "first / second / … (true)": mm for x, y, z; mrad for roll, pitch, yaw.
    Each of ``sigmas`` is (k + 1, 6), joints then noise; by default the product default's on all
    kept samples of the first recording."""
    sigmas = sigmas or (study.sigma_full,)
    robot = study.first.recording.true_robot
    true = np.vstack([robot.perturbation_std, robot.noise_std])
    names = [*robot.chain.joint_names, noise_label]
    header = ["frame", *COMPONENT_HEADER]
    rows = [
        [
            name,
            *(
                " / ".join(f"{1e3 * sigma[f, c]:.2f}" for sigma in sigmas)
                + f" ({1e3 * true[f, c]:.2f})"
                for c in range(6)
            ),
        ]
        for f, name in enumerate(names)
    ]
    return markdown_table(header, rows)


def noise_experiment_markdown(study: StudyResult) -> str:
    """Per recording: the noise experiment's detections and its σ per component."""
    header = [
        "recording",
        "detections kept",
        "gross errors drawn / screened",
        "good detections screened",
        *COMPONENT_HEADER,
    ]
    rows = []
    for s, e in zip(study.recordings, study.known_noise.experiments, strict=True):
        rows.append(
            [
                str(s.recording.seed),
                f"{int(e.kept.sum())} of {e.kept.size}",
                f"{int(e.gross.sum())} / {int((e.gross & ~e.kept).sum())}",
                str(int((~e.gross & ~e.kept).sum())),
                *(f"{1e3 * v:.2f}" for v in e.std),
            ]
        )
    true = study.first.recording.true_robot.noise_std
    rows.append(["true", "–", "–", "–", *(f"{1e3 * v:.2f}" for v in true)])
    return markdown_table(header, rows)


def known_noise_markdown(study: StudyResult) -> str:
    """Per recording and pooled: share of the oracle's reduction, the default and every way of
    giving Σ_n (``KNOWN_NOISE_VARIANTS``), and the measured variant's reduction."""
    variant = study.known_noise
    header = [
        "recording",
        "runs",
        "oracle reduction",
        "default: share",
        "Σ_n measured: reduction",
        "Σ_n measured: share",
        "full: share",
        "Σ_n true: share",
    ]
    items: list[tuple[str, int | None, Comparison]] = [
        (str(s.recording.seed), i, study.per_recording[i]) for i, s in enumerate(study.recordings)
    ]
    if len(study.recordings) > 1:
        items.append(("**all (two-level bootstrap)**", None, study.pooled))
    rows = []
    for name, i, default in items:
        known = {
            v: (variant.pooled[v] if i is None else variant.per_recording[v][i])
            for v in KNOWN_NOISE_VARIANTS
        }
        o, m = default.selections["oracle"], known["measured"].selections["ours"]
        rows.append(
            [
                name,
                str(default.n_runs),
                reduction(o),
                recording_share(default),
                reduction(m),
                *(recording_share(known[v]) for v in KNOWN_NOISE_VARIANTS),
            ]
        )
    return markdown_table(header, rows)


def _selection_cells(method: str, selection: Selection) -> list[str]:
    """A method's label, mean error of its lowest- and highest-score picks, reduction, CI."""
    return [
        LABELS[method],
        f"{selection.low_mm:.3f}",
        f"{selection.high_mm:.3f}",
        f"{selection.reduction_pct:.1f} %",
        ci(selection.reduction_ci),
    ]


def selection_markdown(comparison: Comparison, *, paper_row: bool) -> str:
    header = [
        *SELECTION_HEADER,
        "low better in",
        "mean Pearson r",
        "95 % CI",
    ]
    rows = []
    for method in METHODS:
        s = comparison.selections[method]
        rows.append(
            [
                *_selection_cells(method, s),
                f"{s.wins} of {comparison.n_runs}",
                f"{s.mean_pearson:.2f}",
                ci(s.pearson_ci, digits=2),
            ]
        )
    if paper_row:
        low, high = PAPER_SELECTION_MM
        rows.append(
            [
                "paper (LRU2, ours)",
                f"{low:.3f}",
                f"{high:.3f}",
                f"{100 * (1 - low / high):.1f} %",
                "–",
                f"{PAPER_WINS} of 10",
                f"{np.mean(PAPER_TABLE_III['ours']):.2f}",
                "–",
            ]
        )
    return markdown_table(header, rows)


def random_part_markdown(comparison: Comparison) -> str:
    header = [*SELECTION_HEADER, "mean Pearson r"]
    rows = [
        [*_selection_cells(m, s), f"{s.mean_pearson:.2f}"] for m, s in comparison.scatter.items()
    ]
    return markdown_table(header, rows)


def share(value: float, interval: tuple[float, float], digits: int = 0) -> str:
    return f"{100 * value:.{digits}f} % {ci(interval, 100, digits)}"


def recording_share(comparison: Comparison) -> str:
    """The share, or a dash where the oracle's own reduction is not above zero (a ratio to
    nothing)."""
    if comparison.selections["oracle"].reduction_ci[0] <= 0.0:
        return "– (oracle's reduction not above 0)"
    return share(comparison.share_of_oracle, comparison.share_ci)


def per_recording_markdown(study: StudyResult, scoring: TaskScoring | None = None) -> str:
    """Per recording and pooled: reductions, share of the oracle's, Pearson gap and the
    systematic error at the oracle's picks; the paper's W, or ``scoring``'s score."""
    per_recording = study.per_recording if scoring is None else scoring.per_recording
    pooled = study.pooled if scoring is None else scoring.pooled
    all_runs = study.runs if scoring is None else scoring.runs
    header = [
        "recording",
        "runs",
        "oracle reduction",
        "ours reduction",
        "share of oracle",
        "share, random part",
        "Pearson r ours − GP",
        "systematic error at oracle's lowest / highest mm",
    ]
    rows = []
    items = [
        (str(s.recording.seed), c, [r for r in all_runs if r.recording == s.recording.seed])
        for s, c in zip(study.recordings, per_recording, strict=True)
    ]
    if len(study.recordings) > 1:
        items.append(("**all (two-level bootstrap)**", pooled, list(all_runs)))
    for name, c, runs in items:
        o, u = c.selections["oracle"], c.selections["ours"]
        bias = picked_errors(runs, "oracle", "bias_mm").mean(axis=0)
        rows.append(
            [
                name,
                str(c.n_runs),
                reduction(o),
                reduction(u),
                recording_share(c),
                share(c.random_share, c.random_share_ci),
                f"{c.pearson_gap:.2f} {ci(c.pearson_gap_ci, digits=2)}",
                f"{bias[0]:.3f} / {bias[1]:.3f}",
            ]
        )
    return markdown_table(header, rows)


def table_iii_markdown(study: StudyResult) -> str:
    """Paper Table III: per run (first 10) Pearson r of score vs observed error."""
    runs = study.paper.n_runs
    header = ["run", *map(str, range(1, runs + 1)), "mean", f"mean over all {study.pooled.n_runs}"]
    rows = []
    for method in METHODS:
        r = study.paper.selections[method].pearson
        pooled = study.pooled.selections[method]
        rows.append(
            [
                LABELS[method],
                *(f"{v:.2f}" for v in r),
                f"{np.nanmean(r):.2f}",
                f"{pooled.mean_pearson:.2f} {ci(pooled.pearson_ci, digits=2)}",
            ]
        )
    for method in ("ours", "gp"):
        paper = PAPER_TABLE_III[method]
        rows.append(
            [f"paper: {LABELS[method]}", *(f"{v:.2f}" for v in paper), f"{np.mean(paper):.2f}", "–"]
        )
    return markdown_table(header, rows)


def ablation_markdown(study: StudyResult) -> str:
    header = [
        "covariances scoring the same candidates",
        "reduction",
        "share of oracle",
        "share, random part",
        "mean Pearson r",
        "docking score: share of oracle",
    ]
    first = study.per_recording[0], study.docking.per_recording[0]
    entries = [(f"ours (product default), N = {study.settings.n_samples}", *first)]
    entries += [(a.label, a.comparison, a.docking) for a in study.ablations]
    rows = []
    for label, c, docking in entries:
        s = c.selections["ours"]
        rows.append(
            [
                label,
                reduction(s),
                share(c.share_of_oracle, c.share_ci),
                share(c.random_share, c.random_share_ci),
                f"{s.mean_pearson:.2f}",
                share(docking.share_of_oracle, docking.share_ci),
            ]
        )
    return markdown_table(header, rows)
