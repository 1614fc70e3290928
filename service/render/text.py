"""Plain-text summaries: the paper's Table II layout and a calibration summary."""

from __future__ import annotations

from schemas.calibration import (
    CalibrationResult,
    CovarianceResult,
    HeldoutSplit,
    PredictiveCovariance,
    Verdict,
)
from schemas.ranking import RankingResult

METHOD_LABELS = {"before": "Init.", "calibrated": "Cal. Ours", "gp": "Cal. GP"}


def table_ii(splits: list[HeldoutSplit], *, position_only: bool) -> str:
    """Mean test-set error per seed (rows: method x {Trans. mm, Rot. deg}), like paper Table II."""
    seeds = sorted({s.seed for s in splits})
    methods = [m for m in METHOD_LABELS if any(s.method == m for s in splits)]
    by_key = {(s.method, s.seed): s for s in splits}
    header = f"{'':<10}{'':<8}" + "".join(f"{seed:>8}" for seed in seeds) + f"{'mean':>9}"
    lines = ["Mean error on test set in mm / deg", header]
    for method in methods:
        rows = [("Trans.", "translation_mm")]
        if not position_only:
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
        f"{'position-only' if result.dataset.position_only else 'full pose'}",
        f"identifiable parameters: {result.identifiability.rank} of "
        f"{result.identifiability.n_parameters} "
        f"({len(result.identifiability.removed)} removed as unidentifiable)",
        f"Levenberg-Marquardt: {result.solver.status} after {result.solver.iterations} iterations "
        f"({result.solver.time_s:.2f} s)",
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
    estimated = [c for c in result.compliance if c.estimated]
    if estimated:
        lines.append("compliance (rad/Nm, ± standard error):")
        lines += [
            f"  {c.axis:<28} {c.value_rad_per_nm: .3e} ± {c.stderr_rad_per_nm:.1e}"
            + ("" if c.significant else "   not significant (within 2 standard errors of 0)")
            for c in estimated
        ]
    lines += [
        f"  {c.axis:<28} fixed at 0: negative (no spring deflects against its load) or not "
        "identified in any physical range"
        for c in result.compliance
        if c.pruned
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
            table_ii(result.evaluation.splits, position_only=result.dataset.position_only),
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
    best = ranking.ranking[0]
    what = "IK candidates" if ranking.target is not None else "configurations"
    return (
        f"ranked {ranking.n_configurations} {what}; best: index {best.index}, score "
        f"{best.score:.4g} {ranking.score_unit} (worst {ranking.ranking[-1].score:.4g})"
    )


def verdict_text(verdict: Verdict) -> str:
    """The verdict's reasons, one block each: cause, then the fix."""
    lines = [f"verdict: {verdict.status}"]
    for reason in verdict.reasons:
        lines.append(f"  {reason.severity}: {reason.message}")
        lines.append(f"    fix: {reason.fix}")
    return "\n".join(lines)
