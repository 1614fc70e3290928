"""One calibration's checks over time as one self-contained HTML page (issue 33).

A chart drawn with matplotlib and inlined as SVG (:func:`service.render.plots.
checks_over_time_figure`: each check's global statistic Σ d² against its time, on a log scale,
with each check's own threshold as a dashed step line and drifted checks marked) — then a
table of the checks, newest first: time, dataset, poses, verdict, statistic, threshold and the
located change with its size. No scripts, no external resources: it renders under a
Content-Security-Policy of ``default-src 'none'``. Every string from the data is escaped.
"""

from __future__ import annotations

import datetime as dt
import html
import io
import re
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from schemas.api import CheckSummary
from schemas.check import LocatedChange
from service.render.page import html_page
from service.render.text import located_sizes

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_DRAWING = threading.Lock()
"""One chart drawn at a time: the service draws pages in worker threads, and matplotlib's font
caches (text is drawn as paths) are not thread-safe."""
SVG_METADATA = ("Creator", "Date", "Format", "Type")
"""matplotlib's SVG metadata, left out (its RDF names other hosts)."""

_CHART_STYLE = """
svg.chart { display: block; max-width: 100%; height: auto; }
tr.drifted td { background: #fdecec; } td.text, th.text { text-align: left; }
"""


@dataclass(frozen=True)
class CheckEntry:
    """A stored check as the page shows it: its summary row and, for a drift, the located
    change of its document (sizes and 95 % intervals)."""

    summary: CheckSummary
    located: LocatedChange | None = None


def render_checks_page(
    calibration_id: str, entries: Sequence[CheckEntry], *, count: int, how_to_check: str
) -> str:
    """The page of ``entries`` (newest first); ``count`` is how many checks the calibration has
    (more than shown when the page holds only the newest); ``how_to_check`` tells a reader with
    none how to make one."""
    e = html.escape
    title = f"kincal checks: {calibration_id}"
    sections = [f"<h1>Checks of calibration {e(calibration_id)}</h1>"]
    if not entries:
        sections.append(
            f'<p class="ok" id="no-checks">No checks of this calibration yet. {e(how_to_check)}</p>'
        )
        return html_page(title, sections, _CHART_STYLE)
    shown = (
        f"{count} check{'' if count == 1 else 's'}"
        if count == len(entries)
        else f"the newest {len(entries)} of {count} checks"
    )
    sections += [
        f"<p>{e(shown)}. Each check tests a few new poses against the calibration's predictive "
        "covariance; its global statistic Σ d² is compared with the χ² threshold at its level, "
        "which depends on its number of poses (<code>kincal check</code>, docs/check.md).</p>",
        "<h2>Statistic over time</h2>",
        chart(entries),
        "<h2>Checks, newest first</h2>",
        table(entries),
    ]
    return html_page(title, sections, _CHART_STYLE)


def _when(created_at: dt.datetime) -> str:
    return created_at.astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _number(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def located_text(entry: CheckEntry) -> str:
    """The located change with its size, or what the row knows of it."""
    located = entry.located
    if located is not None:
        text = f"{located.name}: {located_sizes(located)} (95 %)"
        if located.indistinguishable_from:
            text += "; not told apart from " + ", ".join(located.indistinguishable_from)
        return text
    if entry.summary.located is not None:
        return entry.summary.located
    return (
        "no single candidate change is significant" if entry.summary.verdict == "drifted" else "–"
    )


def table(entries: Sequence[CheckEntry]) -> str:
    e = html.escape
    header = (
        '<tr><th>Time</th><th>Check</th><th class="text">Dataset</th><th>Poses</th>'
        "<th>Verdict</th><th>Σ d²</th><th>Threshold</th><th>Level</th>"
        '<th class="text">Located change</th></tr>'
    )
    rows = []
    for entry in entries:
        s = entry.summary
        rows.append(
            f'<tr class="check {e(s.verdict)}" data-check-id="{e(s.id)}">'
            f"<td>{e(_when(s.created_at))}</td>"
            f'<td><a href="{e(s.links.self)}">{e(s.id)}</a></td>'
            f'<td class="text">{e(s.dataset_name)}</td>'
            f"<td>{s.n_poses}</td><td>{e(s.verdict)}</td>"
            f"<td>{_number(s.statistic)}</td><td>{_number(s.threshold)}</td><td>{s.level:g}</td>"
            f'<td class="text">{e(located_text(entry))}</td></tr>'
        )
    return f'<table class="checks">{header}{"".join(rows)}</table>'


def chart(entries: Sequence[CheckEntry]) -> str:
    """The chart as inline SVG drawn by matplotlib (:func:`service.render.plots.
    checks_over_time_figure`, imported here: a request process loads matplotlib with its
    first page, not at start), every check's point a group ``<g id="check-<i>" class="point
    <verdict>" data-check-id="...">`` (oldest first) with a ``<title>`` saying what it is."""
    from service.render.plots import checks_over_time_figure

    oldest_first = sorted(entries, key=lambda c: (c.summary.created_at, c.summary.id))
    with _DRAWING:
        figure = checks_over_time_figure(
            [c.summary.created_at for c in oldest_first],
            [c.summary.statistic for c in oldest_first],
            [c.summary.threshold for c in oldest_first],
            [c.summary.verdict for c in oldest_first],
        )
        svg = inline_svg(figure, "Each check's statistic against time, with the threshold")
    for i, entry in enumerate(oldest_first):
        svg = svg.replace(f'<g id="check-{i}">', _point_group(i, entry), 1)
    return svg


def inline_svg(figure: Figure, label: str) -> str:
    """``figure`` as an ``<svg class="chart">`` element to put in an HTML page: no XML
    prologue, document type or metadata, no namespace declarations (an HTML parser puts
    ``<svg>`` in its namespace), so the page names no other host."""
    buffer = io.StringIO()
    figure.savefig(buffer, format="svg", metadata=dict.fromkeys(SVG_METADATA))
    svg = buffer.getvalue()
    svg = svg[svg.index("<svg") :]
    svg = re.sub(r' xmlns(:xlink)?="[^"]*"', "", svg, count=2)
    return svg.replace(
        "<svg ", f'<svg class="chart" role="img" aria-label="{html.escape(label)}" ', 1
    )


def _point_group(index: int, entry: CheckEntry) -> str:
    e = html.escape
    s = entry.summary
    title = (
        f"{_when(s.created_at)}: {s.verdict}, Σ d² {_number(s.statistic)} "
        f"(threshold {_number(s.threshold)}); {located_text(entry)}"
    )
    return (
        f'<g id="check-{index}" class="point {e(s.verdict)}" data-check-id="{e(s.id)}">'
        f"<title>{e(title)}</title>"
    )
