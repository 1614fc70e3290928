"""One calibration's checks over time as one self-contained HTML page (issue 33).

An inline SVG chart drawn here from the stored checks — each check's global statistic Σ d²
against its time, on a log scale (a drift's statistic is often a hundred times its threshold),
with the threshold as a dashed line (it depends on each check's number of poses, so it is a
line through every check's own threshold, not one constant) and drifted checks marked — then a
table of the checks, newest first: time, dataset, poses, verdict, statistic, threshold and the
located change with its size. No scripts, no external resources: it renders under a
Content-Security-Policy of ``default-src 'none'``. Every string from the data is escaped.
"""

from __future__ import annotations

import datetime as dt
import html
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

from schemas.api import CheckSummary
from schemas.check import LocatedChange
from service.render.page import html_page
from service.render.text import located_sizes

WIDTH, HEIGHT = 720, 280
LEFT, RIGHT, TOP, BOTTOM = 64, 16, 28, 48
"""Margins of the plot area inside the SVG, px."""
X_PAD = 16
"""Space between the plot area's sides and the first and last check, px."""
SMALLEST = 1e-3
"""A statistic or threshold drawn at no less than this (the log scale has no 0)."""

_CHART_STYLE = """
svg.chart { display: block; max-width: 100%; height: auto; font: 12px system-ui, sans-serif; }
svg.chart .grid { stroke: #e3e3e3; } svg.chart .axis { stroke: #888; }
svg.chart .threshold { stroke: #e69500; stroke-width: 2; stroke-dasharray: 6 4; fill: none; }
svg.chart .holds { fill: #3a3; } svg.chart .drifted { fill: #c00; stroke: #600; stroke-width: 2; }
svg.chart .inconclusive { fill: #999; }
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


@dataclass(frozen=True)
class _Axes:
    """Time → x and log10 value → y of the plot area, px."""

    t_first: float
    t_span: float
    log_low: float
    log_high: float

    def x(self, created_at: dt.datetime) -> float:
        if self.t_span == 0:
            return (LEFT + WIDTH - RIGHT) / 2
        inner = WIDTH - LEFT - RIGHT - 2 * X_PAD
        return LEFT + X_PAD + (created_at.timestamp() - self.t_first) / self.t_span * inner

    def y(self, value: float) -> float:
        fraction = (math.log10(max(value, SMALLEST)) - self.log_low) / (
            self.log_high - self.log_low
        )
        return HEIGHT - BOTTOM - fraction * (HEIGHT - TOP - BOTTOM)


def _axes(entries: Sequence[CheckEntry]) -> _Axes:
    times = [c.summary.created_at.timestamp() for c in entries]
    values = [
        max(v, SMALLEST)
        for c in entries
        for v in (c.summary.statistic, c.summary.threshold)
        if v is not None
    ] or [1.0]
    low = math.floor(math.log10(min(values)))
    high = max(math.ceil(math.log10(max(values))), low + 1)
    return _Axes(min(times), max(times) - min(times), low, high)


def chart(entries: Sequence[CheckEntry]) -> str:
    """The SVG: decades of Σ d², the threshold line, one marker per check (oldest first)."""
    oldest_first = sorted(entries, key=lambda c: (c.summary.created_at, c.summary.id))
    axes = _axes(oldest_first)
    bottom, right = HEIGHT - BOTTOM, WIDTH - RIGHT
    parts = [
        f'<svg class="chart" width="{WIDTH}" '
        f'height="{HEIGHT}" viewBox="0 0 {WIDTH} {HEIGHT}" role="img" '
        'aria-label="Each check\'s statistic against time, with the threshold">'
    ]
    for decade in range(int(axes.log_low), int(axes.log_high) + 1):
        y = axes.y(10.0**decade)
        parts.append(
            f'<line class="grid" x1="{LEFT}" y1="{y:.1f}" x2="{right}" y2="{y:.1f}"/>'
            f'<text x="{LEFT - 6}" y="{y + 4:.1f}" text-anchor="end">{10.0**decade:g}</text>'
        )
    parts.append(
        f'<line class="axis" x1="{LEFT}" y1="{bottom}" x2="{right}" y2="{bottom}"/>'
        f'<text x="{LEFT}" y="{TOP - 10}">Σ d² (log scale)</text>'
    )
    parts += _time_labels(oldest_first, axes)
    parts.append(_threshold_line(oldest_first, axes))
    parts += [_marker(entry, axes) for entry in oldest_first]
    parts.append(_legend())
    parts.append("</svg>")
    return "".join(parts)


def _time_labels(oldest_first: Sequence[CheckEntry], axes: _Axes) -> list[str]:
    first, last = oldest_first[0].summary.created_at, oldest_first[-1].summary.created_at
    y = HEIGHT - BOTTOM + 18
    if axes.t_span == 0:
        return [f'<text x="{axes.x(first):.1f}" y="{y}" text-anchor="middle">{_when(first)}</text>']
    return [
        f'<text x="{axes.x(first):.1f}" y="{y}" text-anchor="start">{_when(first)}</text>',
        f'<text x="{axes.x(last):.1f}" y="{y}" text-anchor="end">{_when(last)}</text>',
    ]


def _threshold_line(oldest_first: Sequence[CheckEntry], axes: _Axes) -> str:
    """Each check's own threshold held flat from half-way to its neighbours (the plot's sides
    for the first and last): a step wherever the number of poses changes it."""
    points = [
        (axes.x(c.summary.created_at), axes.y(c.summary.threshold))
        for c in oldest_first
        if c.summary.threshold is not None
    ]
    if not points:
        return ""
    xs = [x for x, _ in points]
    edges = [float(LEFT), *((a + b) / 2 for a, b in pairwise(xs)), WIDTH - RIGHT]
    steps = []
    for i, (_, y) in enumerate(points):
        steps += [(edges[i], y), (edges[i + 1], y)]
    coordinates = " ".join(f"{x:.1f},{y:.1f}" for x, y in steps)
    return f'<polyline class="threshold" points="{coordinates}"/>'


def _marker(entry: CheckEntry, axes: _Axes) -> str:
    """A dot at the check's statistic (larger and red when it drifted); a grey triangle on the
    time axis for an inconclusive check, which has no statistic."""
    e = html.escape
    s = entry.summary
    x = axes.x(s.created_at)
    title = (
        f"<title>{e(_when(s.created_at))}: {e(s.verdict)}, Σ d² {_number(s.statistic)} "
        f"(threshold {_number(s.threshold)}); {e(located_text(entry))}</title>"
    )
    data = f'class="point {e(s.verdict)}" data-check-id="{e(s.id)}"'
    if s.statistic is None:
        bottom = HEIGHT - BOTTOM
        triangle = f"{x - 5:.1f},{bottom:.1f} {x + 5:.1f},{bottom:.1f} {x:.1f},{bottom - 9:.1f}"
        return f'<polygon {data} points="{triangle}">{title}</polygon>'
    radius = 7 if s.verdict == "drifted" else 4.5
    y = axes.y(s.statistic)
    return f'<circle {data} cx="{x:.1f}" cy="{y:.1f}" r="{radius}">{title}</circle>'


def _legend() -> str:
    y = HEIGHT - 10
    return (
        f'<circle class="holds" cx="{LEFT + 6}" cy="{y - 4}" r="4.5"/>'
        f'<text x="{LEFT + 16}" y="{y}">holds</text>'
        f'<circle class="drifted" cx="{LEFT + 76}" cy="{y - 4}" r="6"/>'
        f'<text x="{LEFT + 88}" y="{y}">drifted</text>'
        f'<line class="threshold" x1="{LEFT + 150}" y1="{y - 4}" x2="{LEFT + 180}" y2="{y - 4}"/>'
        f'<text x="{LEFT + 186}" y="{y}">threshold at the level</text>'
        f'<text x="{LEFT + 340}" y="{y}">▲ inconclusive (no test)</text>'
    )
