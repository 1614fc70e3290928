"""The study's results files (``--write-results``): ``docs/results/reproduce_paper_*.{json,md}``,
the tables docs/reproduce_paper.md includes (:func:`study_rows` makes the rows from a
:class:`StudyResult`, one ``render_*`` per file makes its table from the rows alone).

Units as the study's: σ in m and rad (shown in mm and mrad), errors in mm and deg, reductions in
per cent, shares and correlations as fractions; every interval is a 95 % bootstrap interval
(two-level over recordings and runs for the pooled rows).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from benchmarks.reproduce_paper.calibration import TableII, covariance_std
from benchmarks.reproduce_paper.known_noise import KNOWN_NOISE_VARIANTS
from benchmarks.reproduce_paper.paper import PAPER_SELECTION_MM, PAPER_TABLE_III, PAPER_WINS
from benchmarks.reproduce_paper.selection import (
    LABELS,
    METHODS,
    Comparison,
    Selection,
    diagnostics,
    picked_errors,
)
from benchmarks.reproduce_paper.study import StudyResult
from benchmarks.reproduce_paper.tables import COMPONENT_HEADER, ci, table_ii_markdown
from benchmarks.results import Row, markdown_table, write_results

PREFIX = "reproduce_paper_"
SCORES = {"paper": "paper's W", "docking": "docking task's own score"}
"""The two scores every approach is ranked by: the paper's W and the task point's x-y variance."""
NO_SHARE = "– (oracle's reduction not above 0)"


def _interval(values: tuple[float, float]) -> list[float]:
    return [float(values[0]), float(values[1])]


def _selection(selection: Selection) -> Row:
    return {
        "low_mm": selection.low_mm,
        "high_mm": selection.high_mm,
        "reduction_pct": selection.reduction_pct,
        "reduction_ci": _interval(selection.reduction_ci),
        "wins": selection.wins,
        "mean_pearson": selection.mean_pearson,
        "pearson_ci": _interval(selection.pearson_ci),
    }


def _comparison(comparison: Comparison) -> Row:
    """The numbers of a comparison that the tables show (the oracle's, ours and the shares)."""
    return {
        "runs": comparison.n_runs,
        "oracle_reduction_pct": comparison.selections["oracle"].reduction_pct,
        "oracle_reduction_ci": _interval(comparison.selections["oracle"].reduction_ci),
        "ours_reduction_pct": comparison.selections["ours"].reduction_pct,
        "ours_reduction_ci": _interval(comparison.selections["ours"].reduction_ci),
        "ours_mean_pearson": comparison.selections["ours"].mean_pearson,
        "share": comparison.share_of_oracle,
        "share_ci": _interval(comparison.share_ci),
        "random_share": comparison.random_share,
        "random_share_ci": _interval(comparison.random_share_ci),
        "pearson_gap": comparison.pearson_gap,
        "pearson_gap_ci": _interval(comparison.pearson_gap_ci),
        "reduction_verdict": comparison.reduction_verdict,
        "correlation_verdict": comparison.correlation_verdict,
    }


def recording_rows(study: StudyResult) -> list[Row]:
    """Per recording: its samples and what the 2σ rule removed (injected outliers and good
    samples), the samples used, and the covariance estimator."""
    rows = []
    for s in study.recordings:
        outliers = s.result.outliers
        injected = set(s.recording.outlier_rows.tolist())
        removed = set((np.array(outliers.removed_rows, dtype=int) - 1).tolist())
        covariance = s.result.covariance
        rows.append(
            {
                "recording": s.recording.seed,
                "samples": outliers.n_input,
                "injected": len(injected),
                "removed": len(removed),
                "injected_removed": len(injected & removed),
                "good_removed": len(removed - injected),
                "used": outliers.n_used,
                "estimator": covariance.estimator if covariance is not None else "none",
            }
        )
    return rows


def table_ii_rows(study: StudyResult) -> list[Row]:
    table = study.table
    return [
        {
            "method": method,
            "seeds": list(table.seeds),
            "translation_mm": [errors[s][0] for s in table.seeds],
            "rotation_deg": [errors[s][1] for s in table.seeds],
        }
        for method, errors in table.errors.items()
    ]


def sigma_rows(study: StudyResult) -> list[Row]:
    """Per frame (joints, then the camera noise): σ calibrated by the product default, with the
    measured Σ_n given, with the true Σ_n given, and the true σ (m and rad)."""
    robot = study.first.recording.true_robot
    true = np.vstack([robot.perturbation_std, robot.noise_std])
    variants = study.known_noise.results
    columns = {
        "default": study.sigma_full,
        "noise_measured": covariance_std(variants["measured"][0]),
        "noise_true": covariance_std(variants["true"][0]),
    }
    names = [*robot.chain.joint_names, "camera noise"]
    return [
        {
            "frame": name,
            "true": true[f].tolist(),
            **{key: [float(v) for v in sigma[f]] for key, sigma in columns.items()},
        }
        for f, name in enumerate(names)
    ]


def selection_rows(study: StudyResult) -> list[Row]:
    """Lowest- vs highest-score picks per score, set of runs and method, with the random part
    (each execution's distance from its configuration's own mean) where computed."""
    sets: list[tuple[str, str, Comparison]] = [
        ("paper", "first", study.paper),
        ("paper", "all", study.pooled),
        ("docking", "all", study.docking.pooled),
    ]
    rows = []
    for score, runs, comparison in sets:
        for method in METHODS:
            random = comparison.scatter.get(method) if runs == "all" else None
            rows.append(
                {
                    "score": score,
                    "runs": runs,
                    "n_runs": comparison.n_runs,
                    "method": method,
                    **_selection(comparison.selections[method]),
                    "random": None if random is None else _selection(random),
                }
            )
    return rows


def comparison_rows(study: StudyResult) -> list[Row]:
    """Per score and recording (then all recordings pooled): the oracle's and our reductions,
    the share of the oracle's, the Pearson gap to the GP and the systematic error (calibrated
    model vs true robot) at the oracle's lowest- and highest-score picks."""
    rows = []
    scorings = {
        "paper": (study.per_recording, study.pooled, study.runs),
        "docking": (study.docking.per_recording, study.docking.pooled, study.docking.runs),
    }
    for score, (per_recording, pooled, all_runs) in scorings.items():
        items: list[tuple[int | None, Comparison, list]] = [  # type: ignore[type-arg]
            (s.recording.seed, c, [r for r in all_runs if r.recording == s.recording.seed])
            for s, c in zip(study.recordings, per_recording, strict=True)
        ]
        if len(study.recordings) > 1:
            items.append((None, pooled, list(all_runs)))
        for recording, comparison, runs in items:
            bias = picked_errors(runs, "oracle", "bias_mm").mean(axis=0)
            rows.append(
                {
                    "score": score,
                    "recording": recording,
                    **_comparison(comparison),
                    "oracle_bias_mm": [float(bias[0]), float(bias[1])],
                }
            )
    return rows


def table_iii_rows(study: StudyResult) -> list[Row]:
    return [
        {
            "method": method,
            "pearson": [float(v) for v in study.paper.selections[method].pearson],
            "mean_pearson_all": study.pooled.selections[method].mean_pearson,
            "pearson_ci_all": _interval(study.pooled.selections[method].pearson_ci),
            "runs_all": study.pooled.n_runs,
        }
        for method in METHODS
    ]


def noise_rows(study: StudyResult) -> list[Row]:
    """The simulated noise experiment per recording (detections kept, gross errors drawn and
    screened, good detections screened, σ per component, m and rad), then the true σ."""
    rows: list[Row] = []
    for s, e in zip(study.recordings, study.known_noise.experiments, strict=True):
        rows.append(
            {
                "recording": s.recording.seed,
                "kept": int(e.kept.sum()),
                "detections": int(e.kept.size),
                "gross": int(e.gross.sum()),
                "gross_screened": int((e.gross & ~e.kept).sum()),
                "good_screened": int((~e.gross & ~e.kept).sum()),
                "std": [float(v) for v in e.std],
            }
        )
    true = study.first.recording.true_robot.noise_std
    rows.append({"recording": None, "std": [float(v) for v in true]})
    return rows


def known_noise_rows(study: StudyResult) -> list[Row]:
    """Per recording and pooled (paper's W): the default's comparison and, per way of giving
    Σ_n to the calibration (``KNOWN_NOISE_VARIANTS``), that variant's."""
    variant = study.known_noise
    items: list[tuple[int | None, int | None, Comparison]] = [
        (s.recording.seed, i, study.per_recording[i]) for i, s in enumerate(study.recordings)
    ]
    if len(study.recordings) > 1:
        items.append((None, None, study.pooled))
    rows = []
    for recording, i, default in items:
        rows.append(
            {
                "recording": recording,
                "default": _comparison(default),
                **{
                    v: _comparison(variant.pooled[v] if i is None else variant.per_recording[v][i])
                    for v in KNOWN_NOISE_VARIANTS
                },
            }
        )
    return rows


def ablation_rows(study: StudyResult) -> list[Row]:
    """The first recording's candidates re-scored with other covariances (paper's W and the
    docking score), after the product default's own row."""
    first = study.per_recording[0], study.docking.per_recording[0]
    entries = [(f"ours (product default), N = {study.settings.n_samples}", *first)]
    entries += [(a.label, a.comparison, a.docking) for a in study.ablations]
    return [
        {"covariances": label, "paper": _comparison(c), "docking": _comparison(d)}
        for label, c, d in entries
    ]


def acceptance_rows(study: StudyResult) -> list[Row]:
    """Issue 4's two acceptance points (reduction share ≥ 80 % of the oracle's; our score
    correlates with the observed error better than the GP's) per way of scoring, pooled."""
    scorings = [
        ("docking", study.docking.pooled),
        ("paper", study.pooled),
        ("paper's W, Σ_n measured separately (§V-B)", study.known_noise.pooled["measured"]),
    ]
    return [{"scoring": name, **_comparison(c)} for name, c in scorings]


def diagnostics_rows(study: StudyResult) -> list[Row]:
    """Why the comparison is hard, per score over all runs (:func:`diagnostics`), and the share
    of the paper's W that is rotation (the docking score has none)."""
    rows = []
    for score, runs in (("paper", study.runs), ("docking", study.docking.runs)):
        d = diagnostics(runs)
        rows.append(
            {
                "score": score,
                "runs": len(runs),
                "spread": list(d.spread),
                "agreement": d.agreement,
                "same_low": d.same_low,
                "same_high": d.same_high,
                "bias_mm": d.bias_mm,
                "scatter_mm": d.scatter_mm,
            }
        )
    rows[0]["rotation_share"] = study.docking.rotation_share
    return rows


def _pct(value: float, interval: list[float], digits: int = 1) -> str:
    return f"{value:.{digits}f} % {ci((interval[0], interval[1]))}"


def _share(value: float, interval: list[float], digits: int = 0) -> str:
    return f"{100 * value:.{digits}f} % {ci((interval[0], interval[1]), 100, digits)}"


def _recording_share(c: Row) -> str:
    """The share, or a dash where the oracle's own reduction is not above zero."""
    if c["oracle_reduction_ci"][0] <= 0.0:
        return NO_SHARE
    return _share(c["share"], c["share_ci"])


def _recording(recording: int | None) -> str:
    return "**all (two-level bootstrap)**" if recording is None else str(recording)


def render_recordings(rows: list[Row]) -> str:
    """Per recording: samples, removed by the 2σ rule (of them injected outliers, good
    samples), used, and the covariance estimator."""
    return markdown_table(
        (
            "recording", "samples", "removed (2σ rule)", "injected outliers removed",
            "good samples removed", "used", "covariances",
        ),
        [
            (
                r["recording"], r["samples"], r["removed"],
                f"{r['injected_removed']} of {r['injected']}", r["good_removed"], r["used"],
                f"`{r['estimator']}`",
            )
            for r in rows
        ],
    )  # fmt: skip


def render_table_ii(rows: list[Row]) -> str:
    """Paper Table II (mm and deg to 0.01 per split, their mean, the paper's mean)."""
    seeds = tuple(rows[0]["seeds"])
    errors = {
        r["method"]: {
            s: (t, d) for s, t, d in zip(seeds, r["translation_mm"], r["rotation_deg"], strict=True)
        }
        for r in rows
    }
    return table_ii_markdown(TableII(seeds, errors))


def render_sigma(rows: list[Row]) -> str:
    """σ per frame, "default / Σ_n measured / Σ_n true (true σ)", in mm and mrad to 0.01."""
    keys = ("default", "noise_measured", "noise_true")
    cells = [
        (
            r["frame"],
            *(
                " / ".join(f"{1e3 * r[k][c]:.2f}" for k in keys) + f" ({1e3 * r['true'][c]:.2f})"
                for c in range(6)
            ),
        )
        for r in rows
    ]
    return markdown_table(("frame", *COMPONENT_HEADER), cells)


RUN_SETS = {"first": "the first {n} runs of recording 1 (the paper's protocol)", "all": "all {n}"}


def render_selection(rows: list[Row]) -> str:
    """Per score, set of runs and method: mean observed error of the lowest- and highest-score
    picks (mm, to 0.001), the reduction and its interval, the runs where the low pick was
    better, mean Pearson r; then the same on the random part of the error. The paper's own row
    (LRU2, ours; published numbers) follows the paper-protocol rows."""
    cells = []
    for r in rows:
        random = r["random"]
        cells.append(
            (
                SCORES[r["score"]],
                RUN_SETS[r["runs"]].format(n=r["n_runs"]),
                LABELS[r["method"]],
                f"{r['low_mm']:.3f}",
                f"{r['high_mm']:.3f}",
                _pct(r["reduction_pct"], r["reduction_ci"]),
                f"{r['wins']} of {r['n_runs']}",
                f"{r['mean_pearson']:.2f} {ci(tuple(r['pearson_ci']), digits=2)}",  # type: ignore[arg-type]
                "–" if random is None else _pct(random["reduction_pct"], random["reduction_ci"]),
                "–" if random is None else f"{random['mean_pearson']:.2f}",
            )
        )
        if r["runs"] == "first" and r["method"] == METHODS[-1]:
            low, high = PAPER_SELECTION_MM
            cells.append(
                (
                    SCORES["paper"], "the paper's 10 runs", "paper (LRU2, ours)",
                    f"{low:.3f}", f"{high:.3f}", f"{100 * (1 - low / high):.1f} %",
                    f"{PAPER_WINS} of 10", f"{np.mean(PAPER_TABLE_III['ours']):.2f}", "–", "–",
                )
            )  # fmt: skip
    header = (
        "score", "runs", "method", "lowest-score mm", "highest-score mm", "reduction [95 % CI]",
        "low better in", "mean Pearson r [95 % CI]", "random part: reduction",
        "random part: mean r",
    )  # fmt: skip
    return markdown_table(header, cells)


def render_comparisons(rows: list[Row]) -> str:
    """Per score and recording (then pooled): the oracle's and our reductions, the share of the
    oracle's (a dash where the oracle's reduction is not above zero), on the random part, the
    Pearson gap ours − GP, the systematic error at the oracle's picks (mm, to 0.001)."""
    cells = [
        (
            SCORES[r["score"]],
            _recording(r["recording"]),
            r["runs"],
            _pct(r["oracle_reduction_pct"], r["oracle_reduction_ci"]),
            _pct(r["ours_reduction_pct"], r["ours_reduction_ci"]),
            _recording_share(r),
            _share(r["random_share"], r["random_share_ci"]),
            f"{r['pearson_gap']:.2f} {ci(tuple(r['pearson_gap_ci']), digits=2)}",  # type: ignore[arg-type]
            "{:.3f} / {:.3f}".format(*r["oracle_bias_mm"]),
        )
        for r in rows
    ]
    header = (
        "score", "recording", "runs", "oracle reduction", "ours reduction", "share of oracle",
        "share, random part", "Pearson r ours − GP",
        "systematic error at oracle's lowest / highest mm",
    )  # fmt: skip
    return markdown_table(header, cells)


def render_table_iii(rows: list[Row]) -> str:
    """Paper Table III: Pearson r per run of the first 10 (to 0.01), their mean and the mean
    over all runs; the paper's rows (published numbers) below."""
    runs = len(rows[0]["pearson"])
    header = ["run", *map(str, range(1, runs + 1)), "mean", f"mean over all {rows[0]['runs_all']}"]
    cells = [
        [
            LABELS[r["method"]],
            *(f"{v:.2f}" for v in r["pearson"]),
            f"{np.nanmean(r['pearson']):.2f}",
            f"{r['mean_pearson_all']:.2f} {ci(tuple(r['pearson_ci_all']), digits=2)}",  # type: ignore[arg-type]
        ]
        for r in rows
    ]
    for method in ("ours", "gp"):
        paper = PAPER_TABLE_III[method]
        cells.append(
            [f"paper: {LABELS[method]}", *(f"{v:.2f}" for v in paper), f"{np.mean(paper):.2f}", "–"]
        )
    return markdown_table(header, cells)


def render_noise(rows: list[Row]) -> str:
    """The noise experiment per recording, σ per component in mm and mrad (to 0.01)."""
    cells = []
    for r in rows:
        sigma = [f"{1e3 * v:.2f}" for v in r["std"]]
        if r["recording"] is None:
            cells.append(("true", "–", "–", "–", *sigma))
            continue
        cells.append(
            (
                r["recording"],
                f"{r['kept']} of {r['detections']}",
                f"{r['gross']} / {r['gross_screened']}",
                r["good_screened"],
                *sigma,
            )
        )
    header = (
        "recording", "detections kept", "gross errors drawn / screened",
        "good detections screened", *COMPONENT_HEADER,
    )  # fmt: skip
    return markdown_table(header, cells)


def render_known_noise(rows: list[Row]) -> str:
    """Per recording and pooled: the oracle's reduction, the default's share, the reduction
    with the measured Σ_n and the share of every way of giving Σ_n."""
    cells = [
        (
            _recording(r["recording"]),
            r["default"]["runs"],
            _pct(r["default"]["oracle_reduction_pct"], r["default"]["oracle_reduction_ci"]),
            _recording_share(r["default"]),
            _pct(r["measured"]["ours_reduction_pct"], r["measured"]["ours_reduction_ci"]),
            *(_recording_share(r[v]) for v in KNOWN_NOISE_VARIANTS),
        )
        for r in rows
    ]
    header = (
        "recording", "runs", "oracle reduction", "default: share", "Σ_n measured: reduction",
        "Σ_n measured: share", "full: share", "Σ_n true: share",
    )  # fmt: skip
    return markdown_table(header, cells)


def render_ablations(rows: list[Row]) -> str:
    """The first recording's candidates re-scored with other covariances: reduction, share of
    the oracle's (also on the random part), mean Pearson r (paper's W) and the share with the
    docking score."""
    cells = [
        (
            r["covariances"],
            _pct(r["paper"]["ours_reduction_pct"], r["paper"]["ours_reduction_ci"]),
            _share(r["paper"]["share"], r["paper"]["share_ci"]),
            _share(r["paper"]["random_share"], r["paper"]["random_share_ci"]),
            f"{r['paper']['ours_mean_pearson']:.2f}",
            _share(r["docking"]["share"], r["docking"]["share_ci"]),
        )
        for r in rows
    ]
    header = (
        "covariances scoring the same candidates", "reduction", "share of oracle",
        "share, random part", "mean Pearson r", "docking score: share of oracle",
    )  # fmt: skip
    return markdown_table(header, cells)


def render_acceptance(rows: list[Row]) -> str:
    """Issue 4's acceptance points per scoring: the share of the oracle's reduction (to 0.1 %,
    also on the random part) and the Pearson gap ours − GP, each with its verdict."""
    cells = [
        (
            SCORES.get(r["scoring"], r["scoring"]),
            _pct(r["ours_reduction_pct"], r["ours_reduction_ci"]),
            _pct(r["oracle_reduction_pct"], r["oracle_reduction_ci"]),
            _share(r["share"], r["share_ci"], 1),
            _share(r["random_share"], r["random_share_ci"], 1),
            f"**{r['reduction_verdict']}**",
            f"{r['pearson_gap']:.2f} {ci(tuple(r['pearson_gap_ci']), digits=2)}",  # type: ignore[arg-type]
            f"**{r['correlation_verdict']}**",
        )
        for r in rows
    ]
    header = (
        "scored with", "ours reduction", "oracle reduction", "share of oracle",
        "share, random part", "share ≥ 80 %", "Pearson r ours − GP", "gap > 0",
    )  # fmt: skip
    return markdown_table(header, cells)


def render_diagnostics(rows: list[Row]) -> str:
    """Per score over all runs: the spread of the approaches' true x-y σ (largest/smallest,
    median and 10–90 %), agreement of ours with the oracle (mean Spearman ρ, same lowest and
    highest pick), the systematic and random parts of the observed error (mm), and for the
    paper's W the share of the oracle's score that is roll and pitch variance."""
    cells = [
        (
            SCORES[r["score"]],
            r["runs"],
            "{:.2f} ({:.2f}–{:.2f})".format(*r["spread"]),
            f"{r['agreement']:.2f}",
            f"{100 * r['same_low']:.0f} %",
            f"{100 * r['same_high']:.0f} %",
            f"{r['bias_mm']:.2f}",
            f"{r['scatter_mm']:.2f}",
            f"{100 * r['rotation_share']:.0f} %" if "rotation_share" in r else "–",
        )
        for r in rows
    ]
    header = (
        "score", "runs", "true σ largest / smallest, median (10–90 %)",
        "Spearman ρ ours vs oracle", "same lowest pick", "same highest pick",
        "systematic part mm", "random part mm", "rotation's share of the score (oracle, median)",
    )  # fmt: skip
    return markdown_table(header, cells)


TABLES: dict[str, tuple[Callable[[StudyResult], list[Row]], Callable[[list[Row]], str]]] = {
    "recordings": (recording_rows, render_recordings),
    "table_ii": (table_ii_rows, render_table_ii),
    "sigma": (sigma_rows, render_sigma),
    "selection": (selection_rows, render_selection),
    "comparisons": (comparison_rows, render_comparisons),
    "table_iii": (table_iii_rows, render_table_iii),
    "noise": (noise_rows, render_noise),
    "known_noise": (known_noise_rows, render_known_noise),
    "ablations": (ablation_rows, render_ablations),
    "acceptance": (acceptance_rows, render_acceptance),
    "diagnostics": (diagnostics_rows, render_diagnostics),
}
"""Each results file (``reproduce_paper_<key>``): its rows from the study, its table."""

RENDER = {PREFIX + key: render for key, (_, render) in TABLES.items()}
"""The renderer of every results file the study writes, by file name."""


def study_rows(study: StudyResult) -> dict[str, list[Row]]:
    """Every results file's rows, by file name."""
    return {PREFIX + key: rows(study) for key, (rows, _) in TABLES.items()}


def write_study_results(study: StudyResult, command: str) -> list[Path]:
    """``docs/results/reproduce_paper_*.{json,md}`` of ``study`` (``command`` recorded)."""
    written: list[Path] = []
    for name, rows in study_rows(study).items():
        written += write_results(name, command, rows, RENDER[name])
    return written
