"""The calibration report as one self-contained HTML page (figures embedded as PNG data URIs).

Sections: fit statistics (before / after, train / held-out), residual distributions before and
after calibration (paper Fig. 4a), identifiability warnings (parameters removed by name,
compliance that is not significant), random effects as σ per frame (paper Fig. 4b) when the
result has covariances, the held-out table (paper Table II layout) and the coverage of the
predicted covariance on the held-out poses (expected vs observed share inside its ellipsoids).
"""

from __future__ import annotations

import base64
import html
import io
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from schemas.calibration import (
    CalibrationResult,
    CovarianceResult,
    ErrorStats,
    OutlierReport,
    PredictiveCovariance,
)
from service.render.page import html_page
from service.render.plots import coverage_figure, residual_histograms
from service.render.result_json import ResidualSample
from service.render.text import (
    AXES,
    compliance_status,
    parameter_count,
    predictive_lines,
    solver_line,
    table_ii,
    verdict_line,
)


def _verdict(result: CalibrationResult) -> list[str]:
    """The verdict first, where a reader looks, also when it is ok: the one line the CLI ends
    with (:func:`service.render.text.verdict_line`), then each reason with its fix."""
    verdict = result.verdict
    e = html.escape
    items = "".join(
        f"<li><b>{e(r.severity)}</b>: {e(r.message)}<br>fix: {e(r.fix)}</li>"
        for r in (verdict.reasons if verdict is not None else [])
    )
    status = "none" if verdict is None else verdict.status
    return [
        f"<h2>Verdict: {e(status)}</h2>",
        f'<p class="verdict">{e(verdict_line(verdict))}</p>',
        *([f"<ul>{items}</ul>"] if items else []),
    ]


def render_report(result: CalibrationResult, residuals: ResidualSample) -> str:
    """The HTML report of ``result``; ``residuals`` of (some of) the samples it used."""
    e = html.escape
    sections = [
        f"<h1>kincal calibration report: {e(result.robot.name)}</h1>",
        *_verdict(result),
        _overview(result),
        "<h2>Fit (mean and RMS error)</h2>",
        _fit_table(result),
        "<h2>Residuals before and after calibration (paper Fig. 4a)</h2>",
        _residual_figure(residuals),
        "<h2>Identifiability</h2>",
        _identifiability(result),
        "<h2>Joint compliance</h2>",
        _compliance(result),
        "<h2>Random effects: standard deviation per frame (paper Fig. 4b)</h2>",
        _random_effects(result.covariance),
    ]
    if result.evaluation is not None:
        table = table_ii(result.evaluation.splits, rotation=result.dataset.measures_rotation)
        sections += [
            "<h2>Held-out evaluation (paper Table II layout)</h2>",
            f"<p>{e(result.evaluation.protocol)}</p><pre>{e(table)}</pre>",
        ]
    if result.predictive is not None:
        sections += [
            "<h2>Predicted covariance on held-out poses (coverage)</h2>",
            _coverage(result.predictive),
        ]
    return html_page(f"kincal report: {result.robot.name}", sections)


def _coverage(predictive: PredictiveCovariance) -> str:
    """The coverage plot (expected vs observed share inside the predicted ellipsoids) and its
    numbers."""
    e = html.escape
    text = "".join(f"<p>{e(line)}</p>" for line in predictive_lines(predictive))
    coverage = predictive.coverage
    if coverage is None:
        return text
    figure = coverage_figure(
        np.array([c.level for c in coverage.curve]),
        np.array([c.observed for c in coverage.curve]),
        title=f"{coverage.n_heldout} held-out poses, {coverage.dimension}-D, "
        f"{coverage.n_splits} splits",
    )
    return (
        figure_img(figure, "Coverage: expected vs observed share inside the ellipsoid")
        + text
        + f"<p>{e(coverage.protocol)}</p>"
    )


def _overview(result: CalibrationResult) -> str:
    e = html.escape
    robot, outliers, solver = result.robot, result.outliers, result.solver
    rows = [
        (
            "Robot",
            f"{robot.name} ({robot.base_frame} → {robot.tip_frame}), "
            f"{len(robot.joint_names)} joints, URDF sha256 {robot.urdf_sha256[:12]}…",
        ),
        (
            "Dataset",
            f"{result.dataset.source}: {result.dataset.n_samples} samples, "
            f"{'full pose' if result.dataset.measures_rotation else 'position only'}",
        ),
        ("Outliers", _outlier_text(outliers)),
        *(
            []
            if result.measurement is None
            else [
                (
                    "Measurement",
                    f"{result.measurement.type} (residual in the "
                    f"{result.measurement.frame}); " + "; ".join(result.measurement.notes),
                )
            ]
        ),
        ("Solver", solver_line(solver)),
        ("Verdict", verdict_line(result.verdict)),
        ("Created", f"{result.created_utc} by kincal {result.kincal_version}"),
    ]
    body = "".join(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _fit_table(result: CalibrationResult) -> str:
    header = (
        "<tr><th>model</th><th>data</th><th>samples</th><th>mean mm</th><th>RMS mm</th>"
        "<th>mean deg</th><th>RMS deg</th></tr>"
    )
    rows = []
    for model, phase in (("before", result.fit.before), ("calibrated", result.fit.after)):
        for split, stats in (("train", phase.train), ("held-out", phase.heldout)):
            if stats is not None:
                rows.append(_stats_row(model, split, stats))
    return f"<table>{header}{''.join(rows)}</table>"


def _stats_row(model: str, split: str, stats: ErrorStats) -> str:
    def cell(value: float | None, digits: int) -> str:
        return "–" if value is None else f"{value:.{digits}f}"

    return (
        f"<tr><td>{model}</td><td>{split}</td><td>{stats.n_samples}</td>"
        f"<td>{cell(stats.translation_mean_mm, 3)}</td><td>{cell(stats.translation_rms_mm, 3)}</td>"
        f"<td>{cell(stats.rotation_mean_deg, 4)}</td><td>{cell(stats.rotation_rms_deg, 4)}</td>"
        "</tr>"
    )


def _residual_figure(residuals: ResidualSample) -> str:
    with tempfile.TemporaryDirectory() as folder:
        path = residual_histograms(
            residuals.before,
            residuals.after,
            Path(folder) / "residuals.png",
            title=f"End-effector-frame residuals of {residuals.description}: "
            "nominal robot (frame and tool fitted) vs calibrated",
        )
        png = path.read_bytes()
    return png_img(png, "Histograms of residual components before and after calibration")


def _identifiability(result: CalibrationResult) -> str:
    ident = result.identifiability
    e = html.escape
    summary = f"<p>{e(parameter_count(ident))}.</p>"
    if not ident.removed:
        return summary + '<p class="ok">Every parameter was identifiable from this data.</p>'
    names = ", ".join(f"<code>{e(name)}</code>" for name in ident.removed)
    return summary + (
        f'<p class="warn">{len(ident.removed)} parameter(s) could not be identified from this '
        f"data and were kept at their nominal values: {names}. Some are redundant by "
        "construction (e.g. the compliance of a vertical joint, which gravity never loads); "
        "others need configurations that excite them.</p>"
    )


def _compliance(result: CalibrationResult) -> str:
    e = html.escape
    if not result.compliance:
        return "<p>No compliant axes in this model.</p>"
    rows = []
    for c in result.compliance:
        verdict = e(compliance_status(c))
        if c.estimated and not c.significant:
            verdict = f'<span class="warn">{verdict}</span>'
        stderr = "–" if c.stderr_rad_per_nm is None else f"{c.stderr_rad_per_nm:.2e}"
        rows.append(
            f"<tr><td>{e(c.axis)}</td><td>{c.kind}</td><td>{c.value_rad_per_nm:.3e}</td>"
            f"<td>{stderr}</td><td>{verdict}</td></tr>"
        )
    header = "<tr><th>axis</th><th>kind</th><th>rad/Nm</th><th>± std. err.</th><th></th></tr>"
    return f"<table>{header}{''.join(rows)}</table>"


def _random_effects(covariance: CovarianceResult | None) -> str:
    if covariance is None:
        return "<p>This result has no random-effect covariances (that stage did not run).</p>"
    e = html.escape
    frames = [*covariance.frames, covariance.noise]
    names = [frame.name for frame in frames]
    std = np.array([frame.std for frame in frames], dtype=float)  # (frames, 6) m and rad
    figure = Figure(figsize=(max(6.0, 0.9 * len(frames) + 2), 5.0), layout="constrained")
    top, bottom = figure.subplots(2, 1, sharex=True)
    x = np.arange(len(frames))
    for axis, block, unit, scale, labels in (
        (top, std[:, :3], "mm", 1e3, ("tx", "ty", "tz")),
        (bottom, std[:, 3:], "mrad", 1e3, ("rx", "ry", "rz")),
    ):
        for j, label in enumerate(labels):
            axis.bar(x + (j - 1) * 0.27, block[:, j] * scale, width=0.27, label=label)
        axis.set_ylabel(f"σ [{unit}]")
        axis.legend(fontsize=8, ncols=3)
    bottom.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    figure.suptitle(
        f"Standard deviation of each frame's random twist ({covariance.structure} Σ, "
        f"{covariance.estimator})",
        fontsize=10,
    )
    warnings = "".join(f'<p class="warn">{e(w)}</p>' for w in covariance.identifiability.warnings)
    fixed = ", ".join(e(f) for f in covariance.identifiability.fixed)
    unseen = "".join(
        f"<li>{e(frame.name)} {axis}: not identifiable ({e(reason)})</li>"
        for frame in frames
        for axis, reason in zip(AXES, frame.not_identifiable or (), strict=False)
        if reason is not None
    )
    return (
        figure_img(figure, "Standard deviation per frame")
        + (
            f"<p>σ not shown (the data cannot see these axes):</p><ul>{unseen}</ul>"
            if unseen
            else ""
        )
        + (f"<p>Fixed entries: {fixed}</p>" if fixed else "")
        + warnings
    )


def figure_img(figure: Figure, alt: str) -> str:
    """``figure`` as an ``<img>`` of its PNG (110 dpi) embedded as a data URI."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    return png_img(buffer.getvalue(), alt)


def png_img(png: bytes, alt: str) -> str:
    encoded = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{encoded}">'


def _outlier_text(outliers: OutlierReport) -> str:
    """Which rule screened the samples and what it removed."""
    removed = f"{len(outliers.removed_rows)} removed"
    if outliers.rule == "none":
        return f"rule disabled, {outliers.n_used} used"
    if outliers.rule == "sigma":
        return f"{removed} by the {outliers.sigma}σ rule, {outliers.n_used} used"
    return f"{removed} by the model rule (level {outliers.level}), {outliers.n_used} used"
