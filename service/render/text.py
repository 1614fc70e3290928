"""Plain-text summaries: the paper's Table II layout and a calibration summary."""

from __future__ import annotations

from collections.abc import Sequence

from schemas.calibration import (
    CalibrationResult,
    ComplianceCalibration,
    CovarianceResult,
    HeldoutSplit,
    Identifiability,
    PredictiveCovariance,
    SolverReport,
    Verdict,
)
from schemas.check import CheckResult, LocatedChange, StatedSize
from schemas.ranking import RankingResult

METHOD_LABELS = {"before": "Init.", "calibrated": "Cal. Ours", "gp": "Cal. GP"}


def table_ii(splits: list[HeldoutSplit], *, rotation: bool) -> str:
    """Mean test-set error per seed (rows: method x {Trans. mm, Rot. deg}), like paper Table II;
    without ``rotation`` (a position recording) the Trans. rows only."""
    seeds = sorted({s.seed for s in splits})
    methods = [m for m in METHOD_LABELS if any(s.method == m for s in splits)]
    by_key = {(s.method, s.seed): s for s in splits}
    header = f"{'':<10}{'':<8}" + "".join(f"{seed:>8}" for seed in seeds) + f"{'mean':>9}"
    lines = ["Mean error on test set in mm / deg", header]
    for method in methods:
        rows = [("Trans.", "translation_mm")]
        if rotation:
            rows.append(("Rot.", "rotation_deg"))
        for r, (label, field) in enumerate(rows):
            values = [getattr(by_key[(method, seed)], field) for seed in seeds]
            name = METHOD_LABELS[method] if r == 0 else ""
            cells = "".join(f"{v:>8.2f}" for v in values)
            lines.append(f"{name:<10}{label:<8}{cells}{sum(values) / len(values):>9.2f}")
    return "\n".join(lines)


def summary(result: CalibrationResult) -> str:
    """A few lines a user reads after ``kincal calibrate``."""
    fit = result.fit
    lines = [
        f"robot {result.robot.name} ({result.robot.base_frame} -> {result.robot.tip_frame}), "
        f"{result.outliers.n_used} of {result.outliers.n_input} samples used "
        f"({len(result.outliers.removed_rows)} outliers removed), "
        f"{'full pose' if result.dataset.measures_rotation else 'position-only'}",
        parameter_count(result.identifiability),
        solver_line(result.solver),
    ]
    for phase_name, phase in (("before", fit.before), ("after", fit.after)):
        for split_name, stats in (("train", phase.train), ("held-out", phase.heldout)):
            if stats is None:
                continue
            rotation = (
                "" if stats.rotation_mean_deg is None else f", {stats.rotation_mean_deg:.3f} deg"
            )
            lines.append(
                f"  {phase_name:<6} {split_name:<9} mean error {stats.translation_mean_mm:.3f} mm"
                f"{rotation}"
            )
    if result.compliance:
        lines.append("compliance (rad/Nm, ± standard error):")
        lines += [
            f"  {c.axis:<28} "
            + (
                f"{c.value_rad_per_nm: .3e} ± {c.stderr_rad_per_nm:.1e}   "
                if c.estimated and c.stderr_rad_per_nm is not None
                else ""
            )
            + compliance_status(c)
            for c in result.compliance
        ]
    links = [name for name in result.identifiability.pruned if not name.startswith("compliance.")]
    if links:
        lines.append(
            f"link corrections fixed at nominal (standard error beyond any physical URDF error, "
            f"> 0.1 rad or > 5 cm): {', '.join(links)}"
        )
    if result.covariance is not None:
        lines += ["", *covariance_table(result.covariance)]
    if result.evaluation is not None:
        lines += [
            "",
            table_ii(result.evaluation.splits, rotation=result.dataset.measures_rotation),
        ]
    if result.predictive is not None:
        lines += ["", *predictive_lines(result.predictive)]
    return "\n".join(lines)


def predictive_lines(predictive: PredictiveCovariance) -> list[str]:
    """The model-error part and the held-out coverage of the predicted covariance."""
    lines = []
    error = predictive.model_error
    if error is not None:
        cells = [
            f"{axis} {1e3 * std:.3f} {'mrad' if _is_rotation(axis) else 'mm'}"
            for axis, std in zip(error.axes, error.std, strict=True)
        ]
        frame = "the measurement frame" if error.frame is None else f"the {error.frame}"
        lines.append(
            f"model error (σ along the axes of {frame}, from {error.n_residuals} "
            f"cross-validated residuals): {', '.join(cells)}"
        )
    coverage = predictive.coverage
    if coverage is None:
        lines.append(
            "predictive coverage: not measured (needs held-out splits whose training rows "
            "give covariances)"
        )
        return lines
    shares = ", ".join(
        f"{100 * c.observed:.0f} % in the {100 * c.level:.0f} %" for c in coverage.levels
    )
    noun = "poses" if error is None or error.frame is None else "rows"
    lines.append(
        f"predictive coverage on {coverage.n_heldout} held-out {noun} ({coverage.dimension}-D, "
        f"{coverage.n_splits} splits, every part from training rows only): {shares} ellipsoid; "
        f"mean Mahalanobis² {coverage.mean_mahalanobis_sq:.2f} (χ² mean "
        f"{coverage.chi2_mean:.0f})"
    )
    return lines


AXES = ("x", "y", "z", "rx", "ry", "rz")


def _is_rotation(axis: str) -> bool:
    """A model-error axis in rad: rx..rz of a pose, or a chosen rotation component."""
    return axis.rsplit(".", 1)[-1] in ("rx", "ry", "rz")


def covariance_table(covariance: CovarianceResult) -> list[str]:
    """σ per frame and axis (paper Fig. 4b as text): mm and mrad, '*' = not identifiable alone,
    'n/i' = not identifiable (each listed below with the reason)."""
    solver = covariance.solver
    lines = [
        f"random perturbations, σ per frame ({covariance.estimator}, {solver.name}: "
        f"{solver.status}, {solver.time_s:.2f} s; mm and mrad; * = only a sum with other "
        "frames is identifiable; n/i = not identifiable):",
        f"  {'frame':<28}" + "".join(f"{axis:>9}" for axis in AXES),
    ]
    unseen = []
    for frame in [*covariance.frames, covariance.noise]:
        flags = frame.identifiable or (True,) * 6
        cells = [
            f"{'n/i':>8} " if std is None else f"{1e3 * std:8.3f}{' ' if ok else '*'}"
            for std, ok in zip(frame.std, flags, strict=True)
        ]
        lines.append(f"  {frame.name:<28}" + "".join(cells))
        unseen += [
            f"  {frame.name} {axis}: not identifiable ({reason})"
            for axis, reason in zip(AXES, frame.not_identifiable or (), strict=False)
            if reason is not None
        ]
    lines += unseen
    identifiability = covariance.identifiability
    lines.append(
        f"  identifiable covariance entries: rank {identifiability.rank} of "
        f"{identifiability.n_parameters}, condition number {identifiability.condition_number:.3g}"
    )
    lines += [f"  note: {text}" for text in identifiability.warnings]
    return lines


def ranking_summary(ranking: RankingResult) -> str:
    """One line for the terminal after ``kincal rank``."""
    if not ranking.ranking:
        return "no configuration to rank"
    best, worst = ranking.ranking[0], ranking.ranking[-1]
    what = "IK candidates" if ranking.target is not None else "configurations"
    return (
        f"ranked {ranking.n_configurations} {what}, best first, by the score tr(W Σ W^T): the "
        f"predicted task-relevant variance of the end effector in {ranking.score_unit} (lower "
        f"is better); best: index {best.index}, score {best.score:.4g} (RMS "
        f"{1e3 * best.score**0.5:.3g} mm); worst: index {worst.index}, score {worst.score:.4g} "
        f"(RMS {1e3 * worst.score**0.5:.3g} mm)"
    )


def verdict_text(verdict: Verdict) -> str:
    """The verdict's reasons, one block each: cause, then the fix."""
    lines = [f"verdict: {verdict.status}"]
    for reason in verdict.reasons:
        lines.append(f"  {reason.severity}: {reason.message}")
        lines.append(f"    fix: {reason.fix}")
    return "\n".join(lines)


VERDICT_MEANING = {
    "ok": "fit to use",
    "warning": "usable; read the reasons above",
    "failed": "do not use it; the reasons above say why and how to fix it",
}
"""What each verdict status means for the user, in the one-line verdict of every command."""


def verdict_codes(verdict: Verdict) -> str:
    """The verdict's reason codes, each once, in order: "few_equations, heldout_worse"."""
    return ", ".join(dict.fromkeys(r.code for r in verdict.reasons))


def verdict_line(verdict: Verdict | None) -> str:
    """The one-line verdict a command ends with, also when it is ok: status, the reasons'
    codes, what it means and the exit code."""
    if verdict is None:
        return "verdict: none (a result written before verdicts existed)"
    codes = verdict_codes(verdict)
    exit_code = 3 if verdict.status == "failed" else 0
    return (
        f"verdict: {verdict.status}{f' ({codes})' if codes else ''}: "
        f"{VERDICT_MEANING[verdict.status]} (exit code {exit_code})"
    )


def used_calibration_line(verdict: Verdict | None) -> str:
    """The verdict of the calibration a prediction, ranking or check used, in one line (the
    command's own exit code is its own: the calibration's reasons are in its result file)."""
    if verdict is None:
        return "calibration verdict: none (a result written before verdicts existed)"
    codes = verdict_codes(verdict)
    line = f"calibration verdict: {verdict.status}{f' ({codes})' if codes else ''}"
    if verdict.status == "ok":
        return f"{line}: fit to use"
    return f"{line}: see verdict.reasons in its result file for why and how to fix it"


def parameter_count(identifiability: Identifiability) -> str:
    """How many parameters the fit estimated and where the others went, adding up to the
    total (CLI summary and HTML report)."""
    i = identifiability
    other = i.n_parameters - i.rank - len(i.removed) - len(i.pruned) - len(i.fixed)
    parts = [f"{len(i.removed)} not identifiable from these poses"]
    if i.pruned:
        parts.append(f"{len(i.pruned)} fixed at a physical value (see below)")
    if i.fixed:
        parts.append(f"{len(i.fixed)} held by --free/--fix")
    if other:
        parts.append(f"{other} otherwise not estimated")
    return (
        f"parameters: {i.rank} estimated of {i.n_parameters} ({', '.join(parts)}); "
        f"condition number {i.condition_number:.3g}"
    )


def solver_line(solver: SolverReport) -> str:
    """The deterministic fit's status: its iterations are the final fit's, which starts from
    the warm start's solution (0 iterations: that solution was already optimal)."""
    return (
        f"Levenberg-Marquardt: {solver.status}; the final fit took {solver.iterations} "
        f"iteration(s) from the warm start's solution ({solver.time_s:.2f} s)"
    )


def compliance_status(compliance: ComplianceCalibration) -> str:
    """What became of a compliant axis, in the same words in the CLI and the HTML report."""
    if compliance.pruned:
        return (
            "fixed at 0: estimated negative (no spring deflects against its load) or not "
            "identifiable in any physical range (standard error > 0.01 rad/N·m)"
        )
    if not compliance.estimated:
        return "not identifiable from these poses: kept at 0"
    if compliance.significant:
        return "significant"
    return "not significant (within 2 standard errors of 0)"


def check_size(value: float | None, unit: str) -> str:
    """A check's size in display units: mm, mrad, or ppm for a scale (``unit``: m, rad, 1)."""
    if value is None:
        return "not detectable"
    if unit == "m":
        return f"{value * 1000:.2f} mm"
    if unit == "rad":
        return f"{value * 1000:.2f} mrad"
    return f"{value * 1e6:.0f} ppm"


def located_sizes(located: LocatedChange) -> str:
    """Each component of a located change with its 95 % interval, in the CLI and the page."""
    return ", ".join(
        f"{c.name} {check_size(c.value, c.unit)} [{check_size(c.low95, c.unit)}, "
        f"{check_size(c.high95, c.unit)}]"
        for c in located.components
    )


BAD_SAMPLE = "bad sample: re-measure"
"""How the CLI table and the HTML report flag a pose set aside as a bad sample."""


def check_verdict_line(check: CheckResult) -> str:
    """The line ``kincal check`` ends with, the top of its report: the verdict and why."""
    return f"check: {check.verdict}: {check.reason}"


def check_pose_limit(check: CheckResult) -> str:
    """The max-type test's per-pose limit, as the per-pose table's header says it."""
    return "" if check.max_threshold is None else f"one pose's limit {check.max_threshold:.1f}"


def check_located_lines(check: CheckResult) -> list[str]:
    """The located change with its 95 % intervals and the candidates these poses cannot tell
    apart from it (or that none is significant), in the CLI and the report."""
    located = check.located
    if located is None:
        if check.verdict == "drifted":
            return ["located: no single candidate change is significant"]
        return []
    lines = [
        f"located: {located.name}: {located_sizes(located)} "
        f"(95 %; adjusted p = {located.adjusted_p_value:.2g})"
    ]
    if located.indistinguishable_from:
        lines.append(
            "these check poses cannot tell it apart from: "
            + ", ".join(located.indistinguishable_from)
        )
    return lines


def check_sizes_line(check: CheckResult) -> str | None:
    """The stated sizes: the smallest change of each kind the check detects and locates with
    its power ("detected only" where it is not located that often)."""
    if not check.stated_sizes:
        return None
    return stated_sizes_line(check.stated_sizes, check.power)


def stated_sizes_line(stated: Sequence[StatedSize], power: float) -> str:
    """Stated sizes in one line, as ``kincal check`` and ``kincal design --check`` print them."""
    sizes = ", ".join(
        f"{s.name} {check_size(s.size, s.unit)}{'' if s.located else ' (detected only)'}"
        for s in stated
    )
    return f"detected and located with {power:.0%} probability: {sizes}"
