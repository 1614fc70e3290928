"""The markdown report (the prose around the tables, figure links) and the terminal headline."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from benchmarks.reproduce_paper.calibration import covariance_std
from benchmarks.reproduce_paper.known_noise import (
    KNOWN_NOISE_VARIANTS,
    NOISE_CONFIGURATIONS,
    NOISE_DETECTIONS,
    NOISE_SCREEN_MAD,
)
from benchmarks.reproduce_paper.paper import PAPER_SELECTION_MM, PAPER_TABLE_II, PAPER_WINS
from benchmarks.reproduce_paper.plots import runs_figure, sigma_figure
from benchmarks.reproduce_paper.selection import LABELS, Comparison, diagnostics
from benchmarks.reproduce_paper.simulation import CAMERA_NOISE
from benchmarks.reproduce_paper.study import StudyResult
from benchmarks.reproduce_paper.tables import (
    ablation_markdown,
    ci,
    known_noise_markdown,
    noise_experiment_markdown,
    per_recording_markdown,
    random_part_markdown,
    recording_share,
    reduction,
    selection_markdown,
    share,
    sigma_markdown,
    table_ii_markdown,
    table_iii_markdown,
)
from schemas.ranking import TaskPointWeights
from service.render import result_json


def known_noise_section(study: StudyResult) -> list[str]:
    """Report lines of the protocol variant (Σ_n measured separately)."""
    s, first = study.settings, study.first
    variant = study.known_noise
    robot = first.recording.true_robot
    dof = float(np.mean([e.kept.sum() - np.any(e.kept, axis=1).sum() for e in variant.experiments]))
    rotation_noise = float(np.mean(robot.noise_std[3:]))
    variance_error = float(np.sqrt(2 / dof) * (1e3 * rotation_noise) ** 2)
    largest_joint = float((1e3 * robot.perturbation_std.max()) ** 2)
    failure_m, failure_rad = robot.outlier_size
    measured, exact = variant.pooled["measured"], variant.pooled["true"]
    if exact.reduction_verdict == "met":
        reading = (
            "An exact Σ_n meets the bar, so the gap of the default is the camera noise's "
            "confusion with the perturbations, and a larger noise experiment would close it."
        )
    else:
        reading = (
            "Even the exact Σ_n does not meet the bar pooled (per recording in the table): the "
            "camera noise's confusion with the last joints is only part of the gap; the rest "
            "is the sampling error of the joint covariances estimated from "
            f"{first.result.outliers.n_used} residuals "
            "(see the larger recordings under *Where the gap to the oracle comes from*)."
        )
    return [
        "## Protocol variant: camera noise measured separately (paper §V-B)",
        "",
        "Everything above is the product default: Σ_n is estimated together with the "
        "perturbations from the recording. The paper also measured the camera noise "
        f"separately ({NOISE_CONFIGURATIONS} configurations × {NOISE_DETECTIONS} AprilTag "
        "detections, mean per configuration subtracted, σ per pose component), but only to "
        "validate the calibrated Σ_n. This variant goes one step further and gives that "
        "measured Σ_n to the calibration as known (`kincal calibrate --noise-std`, or the full "
        "matrix with `--noise-covariance FILE`), so that only the perturbations are estimated; "
        "everything else (recording, outlier removal, model, estimator, candidates, "
        "executions, oracle) is the same as above, and the candidates of every run are "
        "re-scored with the variant's covariances. It is not what the product does by "
        "default and not what the paper did.",
        "",
        f"Simulated noise experiment per recording: {NOISE_CONFIGURATIONS} configurations of "
        "the true robot, each standing still while the camera detects the marker "
        f"{NOISE_DETECTIONS} times: one draw of the joint perturbations ξ per configuration "
        "(the arm does not move), fresh camera noise per detection, and detector failures as "
        "often as in the recording (the paper does not mention any; they are screened "
        f"beforehand at {NOISE_SCREEN_MAD:.0f} robust σ, being {np.degrees(failure_rad):.0f} deg "
        f"/ {1e3 * failure_m:.0f} mm against {CAMERA_NOISE[1]} deg / {CAMERA_NOISE[0]} mm). "
        "Deviations in the end-effector frame of the configuration's "
        "median detection, configuration mean subtracted; σ = √diag of their sample "
        "covariance (degrees of freedom: kept detections − configurations):",
        "",
        noise_experiment_markdown(study),
        "",
        f"With {dof:.0f} degrees of freedom (mean over recordings) a measured σ_n is known "
        f"to about ±{100 / np.sqrt(2 * dof):.0f} % and its variance to "
        f"±{100 * np.sqrt(2 / dof):.0f} %: for the camera's rotation "
        f"({1e3 * rotation_noise:.2f} mrad) that is ±{variance_error:.1f} mrad², against "
        f"{largest_joint:.2f} mrad² for the largest joint perturbation "
        f"({np.sqrt(largest_joint):.2f} mrad).",
        "",
        "σ per frame calibrated on all kept samples of recording "
        f"{first.recording.seed}, with the measured Σ_n (σ per component) / with the true "
        "Σ_n (true value in parentheses; compare the table of Fig. 4b):",
        "",
        sigma_markdown(
            study,
            covariance_std(variant.results["measured"][0]),
            covariance_std(variant.results["true"][0]),
            noise_label="camera noise (given)",
        ),
        "",
        f"Manipulation experiment on the same {s.n_runs} runs per recording: share of the "
        "oracle's reduction with the default and with Σ_n given to the calibration: "
        f"*Σ_n measured* = {KNOWN_NOISE_VARIANTS['measured']}, the protocol variant; "
        f"*full* = {KNOWN_NOISE_VARIANTS['measured_full']}; *Σ_n true* = "
        f"{KNOWN_NOISE_VARIANTS['true']}. The oracle is the same; 95 % bootstrap intervals:",
        "",
        known_noise_markdown(study),
        "",
        f"Pooled share: default {share(study.pooled.share_of_oracle, study.pooled.share_ci)}, "
        f"Σ_n measured {share(measured.share_of_oracle, measured.share_ci)}, Σ_n true "
        f"{share(exact.share_of_oracle, exact.share_ci)} ({measured.reduction_verdict} / "
        f"{exact.reduction_verdict} for the 80 % bar). {reading}",
        "",
    ]


def docking_section(study: StudyResult) -> list[str]:
    """Report lines: the same runs scored with the docking task's own score."""
    docking, paper = study.docking, study.pooled
    weights = docking.options.weights
    assert isinstance(weights, TaskPointWeights)
    ours, oracle = docking.pooled.selections["ours"], docking.pooled.selections["oracle"]
    dock, paper_w = diagnostics(docking.runs), diagnostics(study.runs)
    grows = oracle.reduction_pct > paper.selections["oracle"].reduction_pct
    change = "grows" if grows else "changes"
    better = " (a better score for the task even with perfect covariances)" if grows else ""
    return [
        "## The docking task's own score (task point)",
        "",
        "The experiment measures the x-y error of the end-effector origin. The paper's W "
        "scores something else: it adds 0.1² × (roll and pitch variance in rad²) to 0.4² × "
        "(x and y variance in m²), and with the true covariances the rotational part is "
        f"{100 * docking.rotation_share:.0f} % of that score (median over all candidates). The "
        "product's task-point score (issue 4 item 1; `kincal rank --task-point "
        f"{','.join(f'{v:g}' for v in weights.point_m)} --task-weights "
        f"{','.join(f'{v:g}' for v in weights.axis_weights)}`, in m², no rad² mixed in) is "
        "Var(x) + Var(y) of the docking point in the end-effector frame: the quantity the "
        "experiment measures. The same candidates and executions, every method re-scored with "
        "it (ours: the same calibrated covariances; GP: its variances; oracle: true Σ):",
        "",
        selection_markdown(docking.pooled, paper_row=False),
        "",
        "Random part only:",
        "",
        random_part_markdown(docking.pooled),
        "",
        "Per recording:",
        "",
        per_recording_markdown(study, docking),
        "",
        f"With the task's own score the oracle's reduction {change} from "
        f"{paper.selections['oracle'].reduction_pct:.1f} % to {oracle.reduction_pct:.1f} %"
        f"{better}, and ours from "
        f"{paper.selections['ours'].reduction_pct:.1f} % to {ours.reduction_pct:.1f} %. "
        f"Ours picks the oracle's lowest-score approach in {100 * dock.same_low:.0f} % of the "
        f"runs and its highest in {100 * dock.same_high:.0f} % with the task's score, against "
        f"{100 * paper_w.same_low:.0f} % and {100 * paper_w.same_high:.0f} % with the paper's "
        f"W (agreement with the oracle's whole order of a run: mean Spearman ρ "
        f"{dock.agreement:.2f} and {paper_w.agreement:.2f}).",
        "",
    ]


def _share_verdict(comparison: Comparison, per_recording: Sequence[Comparison]) -> str:
    """The reduction-share acceptance point: pooled share, verdict, random part, per recording."""
    shares = ", ".join(recording_share(c).split(" [")[0] for c in per_recording)
    return (
        f"share {share(comparison.share_of_oracle, comparison.share_ci, 1)} → "
        f"**{comparison.reduction_verdict}** (on the random part: "
        f"{share(comparison.random_share, comparison.random_share_ci, 1)}). Per recording: "
        f"{shares}."
    )


def acceptance_points(comparison: Comparison, per_recording: Sequence[Comparison]) -> list[str]:
    """Issue 4's two acceptance points on pooled runs (``comparison``), report bullets."""
    ours, oracle = comparison.selections["ours"], comparison.selections["oracle"]
    return [
        f"- **Reduction ≥ 80 % of the oracle's:** ours {reduction(ours)}, oracle "
        f"{reduction(oracle)}; {_share_verdict(comparison, per_recording)}",
        f"- **Our score correlates with the observed error better than the GP's:** mean Pearson "
        f"r {ours.mean_pearson:.2f} vs {comparison.selections['gp'].mean_pearson:.2f}, gap "
        f"{comparison.pearson_gap:.2f} {ci(comparison.pearson_gap_ci, digits=2)} → "
        f"**{comparison.correlation_verdict}**.",
    ]


def report_markdown(study: StudyResult, sigma_png: str, runs_png: str) -> str:
    """The whole report; figure links relative to the report's folder."""
    s, first, pooled = study.settings, study.first, study.pooled
    result = first.result
    injected = set(first.recording.outlier_rows.tolist())
    removed = set((np.array(result.outliers.removed_rows, dtype=int) - 1).tolist())
    covariance = result.covariance
    estimator = covariance.estimator if covariance is not None else "none"
    d = diagnostics(first.runs)
    variant = study.known_noise.pooled["measured"]
    paper_width = float(np.subtract(*study.paper.selections["ours"].reduction_ci[::-1]))
    paper_reduction = 100 * (1 - PAPER_SELECTION_MM[0] / PAPER_SELECTION_MM[1])
    total_runs = pooled.n_runs
    seeds = ", ".join(str(r.recording.seed) for r in study.recordings)
    out = [
        "# Paper reproduction on a simulated LRU2-like Jaco2 (issue 4)",
        "",
        "Generated by `python -m benchmarks.reproduce_paper` "
        f"(kincal {result_json.kincal_version()}): {s.n_recordings} recording(s) of {s.n_samples} "
        f"samples (seeds {seeds}), {s.n_runs} manipulation runs per recording × "
        f"{s.n_approaches} approaches × {s.n_executions} executions, {len(s.splits)} held-out "
        f"splits, {s.bootstrap} bootstrap resamples. Everything is simulated and seeded; the "
        "study and its parameters are described in the package's docstring.",
        "",
        f"Recording {first.recording.seed}: {result.outliers.n_input} samples, "
        f"{len(removed)} removed by the 2σ rule ({len(injected & removed)} of {len(injected)} "
        f"injected outliers, {len(removed - injected)} good samples), {result.outliers.n_used} "
        f"used; covariances estimated with `{estimator}` (the product default).",
        "",
        "## Table II: mean held-out error (recording "
        f"{first.recording.seed}, 90/10 splits after outlier removal)",
        "",
        table_ii_markdown(study.table),
        "",
        "The paper's robot had much larger unmodelled errors "
        f"({np.mean(PAPER_TABLE_II['calibrated'][0]):.2f} mm after calibration); the "
        "simulated one has exactly the modelled effects, so after ours only the random "
        "perturbations, the camera noise and the estimation error of "
        f"{result.outliers.n_used} samples remain. "
        'The GP of ref. [13] is fitted to the residuals of the "before" model per split.',
        "",
        "## Fig. 4b: standard deviations of the random perturbations",
        "",
        f"![σ per frame, calibrated and true]({sigma_png})",
        "",
        "Calibrated on all kept samples of recording "
        f"{first.recording.seed} (true value in parentheses):",
        "",
        sigma_markdown(study),
        "",
        "## Manipulation experiment (§V-C)",
        "",
        f"Per run: a pre-grasp pose, {s.n_approaches} distinct approach configurations reaching "
        "it on the "
        "calibrated model (IK branches, rotations about the end-effector z axis), each executed "
        f"{s.n_executions} times on the true robot; observed error = mean x-y docking error in "
        "the end-effector frame. Scores: ours (calibrated covariances, Eq. 22–23 with the paper's "
        "W), the GP's predictive variances on diag Σ_E, and the oracle (true Σ, true geometry).",
        "",
        f"### The paper's protocol: the first {study.paper.n_runs} runs of recording "
        f"{first.recording.seed}",
        "",
        selection_markdown(study.paper, paper_row=True),
        "",
        f"At this size the 95 % interval of our reduction is {paper_width:.0f} percentage points "
        "wide: ten runs cannot resolve the differences the simulated robot allows (the paper's "
        f"{PAPER_WINS} of 10 and {paper_reduction:.0f} % are one such 10-run draw, on a robot "
        "with larger errors).",
        "",
        f"![lowest- vs highest-score error per run]({runs_png})",
        "",
        f"### All {total_runs} runs ({s.n_recordings} recording(s) × {s.n_runs})",
        "",
        selection_markdown(pooled, paper_row=False),
        "",
        "Random part only (x-y distance of each execution from the configuration's own mean "
        "pose; removes the calibrated model's systematic error, which no score can see):",
        "",
        random_part_markdown(pooled),
        "",
        "Per recording (share of oracle = our reduction / the oracle's; 95 % bootstrap intervals):",
        "",
        per_recording_markdown(study),
        "",
        "The systematic part (calibrated model vs true robot) is unknown to every score; where it "
        "happens to be larger at the low-uncertainty approaches it cancels the random part's "
        "benefit in the observed error, and the share of the oracle's (then tiny) reduction is "
        "meaningless for that recording.",
        "",
        "## Table III: correlation of the score with the observed x-y error (Pearson r per run)",
        "",
        table_iii_markdown(study),
        "",
        *docking_section(study),
        *known_noise_section(study),
        "## Acceptance (issue 4)",
        "",
        "Scored with the docking task's own score (task point, the product's recommendation "
        "for a task that measures a position):",
        "",
        *acceptance_points(study.docking.pooled, study.docking.per_recording),
        "",
        "Scored with the paper's W (as published; the tables above):",
        "",
        *acceptance_points(pooled, study.per_recording),
        f"- *Protocol variant, Σ_n measured separately (paper §V-B, not the product default):* "
        f"reduction {reduction(variant.selections['ours'])}; "
        f"{_share_verdict(variant, study.known_noise.per_recording['measured'])}",
        "",
        '"met" / "not met" need the whole 95 % interval (two-level bootstrap over recordings '
        'and runs) on one side of the bar; otherwise "not demonstrated".',
        "",
        "## Where the gap to the oracle comes from",
        "",
        f"Candidates and observed errors of recording {first.recording.seed}'s {s.n_runs} runs, "
        "re-scored with other covariances:",
        "",
        ablation_markdown(study),
        "",
        f"- The approaches of one pre-grasp pose differ little in true x-y σ: largest/smallest "
        f"= {d.spread[0]:.2f} (median; 10–90 %: {d.spread[1]:.2f}–{d.spread[2]:.2f}). The "
        "oracle's reduction is bounded by that spread, and small errors in calibrated "
        "covariances re-order such candidates.",
        f"- Our score vs the oracle's within a run: mean Spearman ρ {d.agreement:.2f}; ours "
        f"picks the oracle's lowest in {100 * d.same_low:.0f} % and its highest in "
        f"{100 * d.same_high:.0f} % of runs.",
        f"- Observed error = systematic part (calibrated model vs true robot, mean "
        f"{d.bias_mm:.2f} mm) + random part (mean {d.scatter_mm:.2f} mm); the systematic part is "
        "the same for every score and makes the lowest-vs-highest comparison noisy (the paper's "
        "10 runs cannot resolve it).",
        "",
        "## Timings",
        "",
        ", ".join(f"{stage}: {seconds:.0f} s" for stage, seconds in study.timings_s.items())
        + " (wall clock on a shared machine).",
        "",
    ]
    return "\n".join(out)


def write_report(study: StudyResult, out: Path, figures: Path | None = None) -> Path:
    """``out/reproduce_paper.md`` and the two PNGs (in ``figures``, default ``out``)."""
    figures = figures or out
    out.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    sigma = sigma_figure(study, figures / "reproduce_paper_sigma.png")
    runs = runs_figure(study, figures / "reproduce_paper_runs.png")
    report = out / "reproduce_paper.md"
    text = report_markdown(
        study,
        Path(os.path.relpath(sigma, out)).as_posix(),
        Path(os.path.relpath(runs, out)).as_posix(),
    )
    report.write_text(text, encoding="utf-8")
    return report


def _reductions(comparison: Comparison) -> str:
    return ", ".join(f"{LABELS[m]} {reduction(s)}" for m, s in comparison.selections.items())


def headline(study: StudyResult) -> str:
    """A few lines for the terminal (and the README)."""
    ours, before = study.table.mean("calibrated"), study.table.mean("before")
    gp = "GP –"
    if "gp" in study.table.errors:
        gp = "GP {:.2f} / {:.2f}".format(*study.table.mean("gp"))
    p, k, d = study.pooled, study.known_noise.pooled["measured"], study.docking.pooled
    return "\n".join(
        [
            f"Table II mean (mm / deg): before {before[0]:.2f} / {before[1]:.2f}, ours "
            f"{ours[0]:.2f} / {ours[1]:.2f}, {gp}",
            f"paper's W: reduction lowest vs highest score: {_reductions(p)}",
            f"share of the oracle's reduction: {share(p.share_of_oracle, p.share_ci)} "
            f"({p.reduction_verdict}); random part {share(p.random_share, p.random_share_ci)}",
            f"mean Pearson r: ours {p.selections['ours'].mean_pearson:.2f}, GP "
            f"{p.selections['gp'].mean_pearson:.2f}, gap {p.pearson_gap:.2f} "
            f"{ci(p.pearson_gap_ci, digits=2)} ({p.correlation_verdict})",
            f"variant with Σ_n measured separately (§V-B): share of the oracle's reduction "
            f"{share(k.share_of_oracle, k.share_ci)} ({k.reduction_verdict}); random part "
            f"{share(k.random_share, k.random_share_ci)}",
            f"docking task's own score (task point): reduction {_reductions(d)}",
            f"docking score: share of the oracle's reduction "
            f"{share(d.share_of_oracle, d.share_ci)} ({d.reduction_verdict}); mean Pearson r "
            f"ours {d.selections['ours'].mean_pearson:.2f}, GP "
            f"{d.selections['gp'].mean_pearson:.2f}, gap {d.pearson_gap:.2f} "
            f"{ci(d.pearson_gap_ci, digits=2)} ({d.correlation_verdict})",
        ]
    )
