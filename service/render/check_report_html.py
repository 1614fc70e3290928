"""The report of one check (``kincal check --report``) as a self-contained HTML page, its figure
embedded as a PNG data URI (no scripts, nothing loaded from elsewhere).

From the top: the verdict with its one-line reason and the advice (the lines ``kincal check``
prints), each pose's d² against the χ² limits the check tests it with
(:func:`service.render.plots.check_figure`), the per-pose table with the bad samples flagged,
the located change with its size, 95 % intervals and the candidates these poses cannot tell
apart from it, the candidate changes' score tests, and the smallest changes the check detects
and locates with its stated probability. Every sentence that the terminal also prints comes
from :mod:`service.render.text`, so the two say the same.
"""

from __future__ import annotations

import html

import numpy as np

from schemas.check import CheckResult
from service.render import text
from service.render.page import html_page
from service.render.plots import check_figure
from service.render.report_html import figure_img

CANDIDATES_SHOWN = 8
"""The report lists this many of the candidate changes' score tests, best first."""

_STYLE = """
tr.bad-sample td { background: #fdecec; } td.text, th.text { text-align: left; }
"""


def render_check_report(check: CheckResult) -> str:
    """The HTML report of ``check`` (a ``kincal.check/1`` document)."""
    e = html.escape
    holds = check.verdict == "holds"
    sections = [
        f"<h1>kincal check: {e(check.recording)}</h1>",
        f"<h2>Verdict: {e(check.verdict)}</h2>",
        f'<p class="{"ok" if holds else "warn"}" id="verdict">'
        f"{e(text.check_verdict_line(check))}</p>",
        f'<p id="advice">advice: {e(check.advice)}</p>',
        f'<p id="calibration-verdict">{e(text.used_calibration_line(check.calibration_verdict))}'
        "</p>",
        _overview(check),
        "<h2>Each pose's d² against the check's χ² limits</h2>",
        _figure(check),
        "<h2>Poses</h2>",
        _pose_table(check),
        "<h2>Located change</h2>",
        _located(check),
        "<h2>Smallest changes this check detects</h2>",
        _stated_sizes(check),
    ]
    return html_page(f"kincal check: {check.recording}", sections, _STYLE)


def _overview(check: CheckResult) -> str:
    e = html.escape
    calibration = check.calibration
    kind = "full poses" if check.dimension == 6 else "positions"
    rows = [
        ("Calibration", f"{calibration.robot}, created {calibration.created_utc}"),
        ("Recording", f"{check.recording}: {len(check.poses)} {kind}"),
        ("Level", f"{check.level:g} (family-wise probability of a false alarm when it holds)"),
        ("Created", f"{check.created_utc} by kincal {check.kincal_version}"),
    ]
    body = "".join(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in rows)
    return f'<table class="text">{body}</table>'


def _figure(check: CheckResult) -> str:
    """The figure and what its two limits are."""
    d = check.dimension
    g = check.global_test
    figure = check_figure(
        np.array([p.d2 for p in check.poses]),
        np.array([p.bad_sample for p in check.poses]),
        dof=d,
        pose_limit=check.max_threshold,
        global_test=None if g is None else (g.statistic, g.threshold, g.dof, g.n_poses),
    )
    n = len(check.poses)
    limits = []
    if check.max_threshold is not None:
        limits.append(
            f"One pose's limit {check.max_threshold:.1f} is the max-type test's: the χ²<sub>{d}"
            f"</sub> quantile at (1 − {check.level:g})<sup>1/{n}</sup> (Šidák over the {n} "
            "poses); a pose above it is far off."
        )
    if g is not None and check.global_critical_p is not None:
        limits.append(
            f"The global test's limit {g.threshold:.1f} is the χ²<sub>{g.dof}</sub> quantile "
            f"exceeded with probability {check.global_critical_p:.3g} (its share of the level "
            f"by the min-p rule), for the statistic Σ d² of the {g.n_poses} poses the verdict is "
            "on, under their joint covariance."
        )
    alt = "Each pose's d² against the one-pose limit; Σ d² against the global limit"
    return figure_img(figure, alt) + "".join(f"<p>{line}</p>" for line in limits)


def _pose_table(check: CheckResult) -> str:
    e = html.escape
    header = (
        "<tr><th>pose</th><th>sample id</th><th>d²</th><th>mm</th><th>mrad</th>"
        '<th class="text"></th></tr>'
    )
    rows = []
    for pose in check.poses:
        mrad = "–" if pose.rotation_mrad is None else f"{pose.rotation_mrad:.2f}"
        flag = text.BAD_SAMPLE if pose.bad_sample else ""
        rows.append(
            f'<tr class="pose{" bad-sample" if pose.bad_sample else ""}" '
            f'data-pose="{pose.index}"><td>{pose.index}</td>'
            f"<td>{e(pose.sample_id or '–')}</td><td>{pose.d2:.2f}</td>"
            f"<td>{pose.translation_mm:.2f}</td><td>{mrad}</td>"
            f'<td class="text">{e(flag)}</td></tr>'
        )
    limit = text.check_pose_limit(check)
    caption = f"<p>d² of each pose under its total predictive covariance; {e(limit)}.</p>"
    return (caption if limit else "") + f"<table>{header}{''.join(rows)}</table>"


def _located(check: CheckResult) -> str:
    e = html.escape
    lines = text.check_located_lines(check)
    if not lines:
        why = "too few poses for a test" if check.verdict == "inconclusive" else "no drift"
        return f'<p id="located">No change located: {why}.</p>'
    parts = [f'<p id="located">{e(lines[0])}</p>']
    parts += [f'<p class="indistinct">{e(line)}</p>' for line in lines[1:]]
    located = check.located
    if located is not None:
        rows = "".join(
            f"<tr><td>{e(c.name)}</td><td>{e(text.check_size(c.value, c.unit))}</td>"
            f"<td>{e(text.check_size(c.low95, c.unit))}</td>"
            f"<td>{e(text.check_size(c.high95, c.unit))}</td></tr>"
            for c in located.components
        )
        parts.append(
            "<table><tr><th>component</th><th>size</th><th>95 % low</th><th>95 % high</th>"
            f"</tr>{rows}</table>"
        )
    if check.candidates:
        parts.append(_candidates(check))
    return "".join(parts)


def _candidates(check: CheckResult) -> str:
    """The best candidate changes' score tests."""
    e = html.escape
    rows = "".join(
        f"<tr><td>{e(c.name)}</td><td>{c.statistic:.2f}</td><td>{c.dof}</td>"
        f"<td>{c.p_value:.2g}</td><td>{c.adjusted_p_value:.2g}</td></tr>"
        for c in check.candidates[:CANDIDATES_SHOWN]
    )
    significant = (
        ""
        if check.candidate_critical_p is None
        else (f"; significant below p = {check.candidate_critical_p:.2g}")
    )
    return (
        f"<p>The candidate changes' score tests, best {CANDIDATES_SHOWN} of "
        f"{len(check.candidates)}{e(significant)}:</p>"
        "<table><tr><th>candidate</th><th>statistic</th><th>dof</th><th>p</th>"
        f"<th>adjusted p</th></tr>{rows}</table>"
    )


def _stated_sizes(check: CheckResult) -> str:
    e = html.escape
    line = text.check_sizes_line(check)
    if line is None:
        return "<p>None stated: too few poses for a test.</p>"
    rows = "".join(
        f"<tr><td>{e(s.name)}</td><td>{e(text.check_size(s.size, s.unit))}</td>"
        f"<td>{'located' if s.located else 'detected only'}</td></tr>"
        for s in check.stated_sizes
    )
    return (
        f'<p id="stated-sizes">{e(line)}</p>'
        "<p>The smallest change of each kind these poses detect and locate with that "
        "probability at the check's level, along its worst direction (docs/check.md).</p>"
        f"<table><tr><th>change</th><th>size</th><th></th></tr>{rows}</table>"
    )
