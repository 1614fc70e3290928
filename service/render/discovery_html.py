"""The discovery report as one self-contained HTML page (figures embedded as PNG data URIs).

Sections: held-out error of the user's model and of the discovered one, each finding with its
residuals-before/after figure (:func:`service.render.findings.finding_figure`), ambiguous effects
with the poses that would separate them, unexplained structure, random effects, what the
measurement cannot see (library effects left out with the reason, and terms whose effect
cancels in what is measured; shown only when there are any), the smallest detectable size of
every library term left out, the search steps and the ``kincal calibrate`` options that carry
the discovered model.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping

from schemas.discovery import ErrorPair, FindingsResult, Health
from service.render.findings import detectability_groups, display_size
from service.render.page import html_page
from service.render.report_html import png_img


def render_discovery_report(findings: FindingsResult, plots: Mapping[str, bytes]) -> str:
    """The HTML report of ``findings``; ``plots`` maps each ``finding.plot`` name to its PNG."""
    e = html.escape
    sections = [
        f"<h1>kincal discovery report: {e(findings.robot.name)}</h1>",
        _overview(findings),
        "<h2>Held-out error: your model vs the discovered model</h2>",
        _heldout(findings),
        "<h2>Findings</h2>",
        _findings(findings, plots),
        "<h2>Ambiguous effects</h2>",
        _ambiguous(findings),
        "<h2>Unexplained structure</h2>",
        _unexplained(findings),
        "<h2>Random effects (for the covariance calibration)</h2>",
        _random_effects(findings),
        *_unseen(findings),
        "<h2>Smallest detectable effects</h2>",
        _detectability(findings),
        "<h2>Residual health before and after</h2>",
        _health(findings),
        "<h2>Search steps</h2>",
        _steps(findings),
        "<h2>Calibrate with the discovered model</h2>",
        _calibrate_options(findings),
    ]
    return html_page(f"kincal discovery: {findings.robot.name}", sections)


def _overview(findings: FindingsResult) -> str:
    e = html.escape
    rows = [
        (
            "Robot",
            f"{findings.robot.name} ({findings.robot.base_frame} → {findings.robot.tip_frame})",
        ),
        (
            "Dataset",
            f"{findings.dataset.source}: {findings.dataset.n_samples} samples, "
            f"{len(findings.outliers.removed_rows)} gross outliers left out",
        ),
        ("Library", f"{findings.n_candidates} candidate terms tested at the first step"),
        ("Created", f"{findings.created_utc} by kincal {findings.kincal_version}"),
        ("Time", f"{findings.elapsed_s:.1f} s"),
    ]
    body = "".join(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _cell(value: float | None, digits: int) -> str:
    """A table cell: ``value`` with ``digits`` decimals, or a dash where there is none."""
    return "<td>–</td>" if value is None else f"<td>{value:.{digits}f}</td>"


def _pair_cells(pair: ErrorPair) -> str:
    return f"<td>{pair.trans_mm:.3f}</td>{_cell(pair.rot_deg, 4)}"


def _heldout(findings: FindingsResult) -> str:
    heldout = findings.heldout
    header = "<tr><th>model</th><th>mean mm</th><th>mean deg</th></tr>"
    rows = (
        f"<tr><td>your model</td>{_pair_cells(heldout.before)}</tr>"
        f"<tr><td>discovered</td>{_pair_cells(heldout.after)}</tr>"
    )
    return f"<p>{html.escape(heldout.protocol)}</p><table>{header}{rows}</table>"


def _plus_minus(stderr: float | None) -> str:
    """`` ± σ`` for an estimated parameter; nothing for a fixed one (e.g. a harmonic number)."""
    return "" if stderr is None or not math.isfinite(stderr) else f" ± {stderr:.2g}"


def _findings(findings: FindingsResult, plots: Mapping[str, bytes]) -> str:
    e = html.escape
    if not findings.findings:
        return '<p class="ok">No library effect is missing from your model.</p>'
    parts = []
    for f in findings.findings:
        parameters = ", ".join(
            f"{e(name)} = {value:.4g}{_plus_minus(f.stderr.get(name))}"
            for name, value in f.parameters.items()
        )
        stability = "–" if f.stability is None else f"{f.stability:.0%}"
        parts.append(
            f"<h3>{e(f.effect)}{'' if f.joint is None else ' at ' + e(f.joint)} "
            f"({e(f.variant)})</h3><p>{e(f.explanation)}</p>"
            f"<table><tr><th>parameters</th><td>{parameters}</td></tr>"
            f"<tr><th>p-value</th><td>{f.p_value:.3g}</td></tr>"
            f"<tr><th>absorbed by the rest of the model</th><td>{f.absorbed_fraction:.0%}</td></tr>"
            f"<tr><th>bootstrap stability</th><td>{stability}</td></tr>"
            f"<tr><th>held-out mm without → with</th><td>{f.heldout.before.trans_mm:.3f} → "
            f"{f.heldout.after.trans_mm:.3f}</td></tr></table>"
        )
        if f.plot is not None and f.plot in plots:
            parts.append(
                png_img(plots[f.plot], f"Residuals before and after adding {f.explanation}")
            )
    return "".join(parts)


def _ambiguous(findings: FindingsResult) -> str:
    e = html.escape
    if not findings.ambiguous:
        return "<p>None: every accepted effect is attributable.</p>"
    parts = []
    for a in findings.ambiguous:
        poses = ""
        if a.separating_poses:
            names = list(dict.fromkeys(name for pose in a.separating_poses for name in pose))
            header = "".join(f"<th>{e(name)}</th>" for name in names)
            rows = "".join(
                "<tr>" + "".join(_cell(pose.get(name), 3) for name in names) + "</tr>"
                for pose in a.separating_poses
            )
            poses = f"<p>Poses (rad) that would separate them:</p><table><tr>{header}</tr>{rows}"
            poses += "</table>"
        parts.append(f'<p class="warn">{e(a.explanation)}</p>{poses}')
    return "".join(parts)


def _unseen(findings: FindingsResult) -> list[str]:
    """What the measurement cannot see, as a heading and its tables; nothing when it sees every
    library term: the effects left out of the search (``measurement.left_out``, each
    ``"effect: reason"``) and the terms whose effect cancels in what is measured
    (``measurement.not_candidates``), which are neither tested nor sized."""
    measurement = findings.measurement
    if measurement is None or not (measurement.left_out or measurement.not_candidates):
        return []
    e = html.escape
    parts = [
        "<h2>What this measurement cannot see</h2>",
        f"<p>Measured: {e(measurement.type)} (residuals in the {e(measurement.frame)}). "
        "The terms below are not tested and have no detectable size: nothing can be named "
        "for them from this recording.</p>",
    ]
    if measurement.left_out:
        rows = []
        for line in measurement.left_out:
            effect, separator, reason = line.partition(": ")
            if not separator:
                effect, reason = "", line
            rows.append(f"<tr><td><code>{e(effect)}</code></td><td>{e(reason)}</td></tr>")
        parts.append(
            '<p>Library effects left out of the search:</p><table class="text">'
            "<tr><th>effect</th><th>why this measurement cannot see it</th></tr>"
            f"{''.join(rows)}</table>"
        )
    if measurement.not_candidates:
        rows = [
            f"<tr><td><code>{e(u.description)}</code></td><td>{u.remaining_fraction:.1g}</td>"
            f"<td>{e(u.reason)}</td></tr>"
            for u in measurement.not_candidates
        ]
        parts.append(
            "<p>Not candidates: library terms whose effect cancels in what is measured.</p>"
            '<table class="text"><tr><th>term</th><th>share of its column left</th>'
            "<th>reason</th></tr>"
            f"{''.join(rows)}</table>"
        )
    return parts


def _detectability(findings: FindingsResult) -> str:
    """Per library term left out, the smallest size this recording would have detected."""
    e = html.escape
    detectability = findings.detectability
    if detectability is None:
        return "<p>Not computed: the discovery ran with detectability turned off.</p>"
    if not detectability.sizes:
        return "<p>No library term is left out of the model.</p>"
    joints = list(findings.robot.joint_names)
    groups = detectability_groups(detectability)
    header = "<tr><th>term</th>" + "".join(f"<th>{e(j)}</th>" for j in joints)
    header += "<th>whole robot / sensor</th></tr>"
    rows = []
    for label, sizes in groups.items():
        by_joint = {
            s.joint: display_size(s.smallest, s.parameter, s.reason, s.separated_from)
            for s in sizes
        }
        cells = "".join(f"<td>{e(by_joint.get(j, ''))}</td>" for j in [*joints, None])
        rows.append(f"<tr><th>{e(label)}</th>{cells}</tr>")
    intro = (
        f"An effect of the size shown would have been found with probability "
        f"{detectability.power:.0%} (score test at {detectability.level:.2g} per term: the "
        "first Holm step; calibrated by adding the effect to this recording's own residuals), "
        "and told apart from the library term named after it (the joint test with that term "
        "fitted too; below that size discovery would report the two ambiguous). "
        "Where nothing is named, nothing larger than this is missing; a blank cell is a term "
        "the recording cannot test (or one already in the model), '–' one it cannot detect "
        "at any size, with the reason."
    )
    return f"<p>{e(intro)}</p><table>{header}{''.join(rows)}</table>"


def _unexplained(findings: FindingsResult) -> str:
    if not findings.unexplained:
        return "<p>None found.</p>"
    return "".join(
        f'<p class="warn">{html.escape(u.explanation)}</p>' for u in findings.unexplained
    )


def _random_effects(findings: FindingsResult) -> str:
    if not findings.random_effects:
        return "<p>No joint shows more scatter than the rest.</p>"
    return "".join(f"<p>{html.escape(r.explanation)}</p>" for r in findings.random_effects)


def _health_row(label: str, health: Health) -> str:
    return (
        f"<tr><td>{label}</td><td>{health.n_parameters}</td>"
        f"{_cell(health.rms_translation_mm, 3)}{_cell(health.rms_rotation_deg, 4)}"
        f"{_cell(health.chi2_per_dof, 2)}<td>{len(health.dependences)}</td></tr>"
    )


def _health(findings: FindingsResult) -> str:
    header = (
        "<tr><th>model</th><th>parameters</th><th>RMS mm</th><th>RMS deg</th><th>χ²/dof</th>"
        "<th>residual dependences</th></tr>"
    )
    rows = _health_row("your model", findings.health.before) + _health_row(
        "discovered", findings.health.after
    )
    return f"<table>{header}{rows}</table>"


def _steps(findings: FindingsResult) -> str:
    e = html.escape
    if not findings.steps:
        return "<p>No step: nothing was significant.</p>"
    header = (
        "<tr><th>step</th><th>candidate</th><th>action</th><th>p-value</th>"
        "<th>held-out mm before</th><th>after</th></tr>"
    )
    rows = "".join(
        f"<tr><td>{s.step}</td><td>{e(s.candidate)}</td><td>{e(s.action)}</td>"
        f"<td>{'–' if s.p_value is None else f'{s.p_value:.3g}'}</td>"
        f"{_cell(s.heldout_before_mm, 3)}"
        f"{_cell(s.heldout_after_mm, 3)}</tr>"
        for s in findings.steps
    )
    return f"<table>{header}{rows}</table>"


def _calibrate_options(findings: FindingsResult) -> str:
    e = html.escape
    model = findings.model
    options = {
        "compliant_joints": model.calibrate_compliant_joints,
        "virtual_axes_at": model.calibrate_virtual_axes_at,
        "gravity_base_m_s2": list(model.calibrate_gravity_base_m_s2),
        "payload_kg": model.calibrate_payload_kg,
    }
    lines = "\n".join(f"  {name}: {value}" for name, value in options.items())
    carried = (
        f'<p class="warn">Not representable in calibrate (yet): {e(", ".join(model.not_carried))}'
        "</p>"
        if model.not_carried
        else ""
    )
    corrections = (
        "<p>Undone on the recording at their discovered values by <code>kincal calibrate "
        f"--model findings.json</code> (not by these options): {e(', '.join(model.corrections))}"
        "</p>"
        if model.corrections
        else ""
    )
    return (
        "<p>Options for <code>POST /api/v1/calibrations</code> (or <code>kincal calibrate</code>)"
        f" that carry the discovered model:</p><pre>{e(lines)}</pre>{corrections}{carried}"
    )
