"""The checks page's renderer on made-up rows, for what the service test does not reach: an
inconclusive check (no statistic: a triangle on the time axis), one check alone (no time
span), thresholds that differ between checks (a step), and a page of the newest only. The
chart is matplotlib's SVG; :func:`points` finds each check's point in it by its element id."""

from __future__ import annotations

import datetime as dt
import re

from schemas.api import CheckLinks, CheckSummary
from service.render.checks_html import CheckEntry, render_checks_page

T0 = dt.datetime(2026, 12, 1, 8, 0, tzinfo=dt.UTC)


def entry(day: int, verdict: str, statistic: float | None, threshold: float | None) -> CheckEntry:
    check_id = f"chk_{day}"
    return CheckEntry(
        CheckSummary(
            id=check_id,
            calibration_id="cal_x",
            dataset_id="ds_x",
            dataset_name=f"day {day}.csv",
            created_at=T0 + dt.timedelta(days=day),
            level=0.05,
            n_poses=10,
            verdict=verdict,  # type: ignore[arg-type]
            statistic=statistic,
            threshold=threshold,
            located=None,
            links=CheckLinks(self=f"/c/{check_id}", calibration="/c", dataset="/d"),
        )
    )


def points(page: str) -> dict[str, dict[str, float | str]]:
    """The chart's points by check id: verdict, centre ``x``, ``y`` (SVG units, y down) and
    ``size`` (half the height of its marker)."""
    markers = {
        name: abs(float(size))
        for name, size in re.findall(r'<path id="(m[0-9a-f]+)" d="M 0 (-?[\d.]+)', page)
    }
    found: dict[str, dict[str, float | str]] = {}
    pattern = r'<g id="check-\d+" class="point ([a-z]+)" data-check-id="([^"]*)">.*?<use ([^>]*)>'
    for verdict, check_id, use in re.findall(pattern, page, re.S):
        attributes = dict(re.findall(r'([a-z:]+)="([^"]*)"', use))
        found[check_id] = {
            "verdict": verdict,
            "x": float(attributes["x"]),
            "y": float(attributes["y"]),
            "size": markers[attributes["xlink:href"].lstrip("#")],
        }
    return found


def plot_area(page: str) -> tuple[float, float, float]:
    """The axes' left and right x and bottom y, SVG units."""
    found = re.search(r'<g id="plot-area">\s*<path d="M ([\d.]+) ([\d.]+)\s*L ([\d.]+)', page)
    assert found
    return float(found.group(1)), float(found.group(3)), float(found.group(2))


def threshold_line(page: str) -> list[tuple[float, float]]:
    found = re.search(r'<g id="threshold">\s*<path d="([^"]*)"', page)
    assert found
    numbers = [float(v) for v in re.findall(r"-?[\d.]+", found.group(1))]
    return list(zip(numbers[::2], numbers[1::2], strict=True))


def test_an_inconclusive_check_is_a_triangle_on_the_time_axis() -> None:
    entries = [entry(2, "inconclusive", None, None), entry(1, "holds", 50.0, 79.1)]
    page = render_checks_page("cal_x", entries, count=2, how_to_check="")
    found = points(page)
    assert found["chk_2"]["verdict"] == "inconclusive" and found["chk_1"]["verdict"] == "holds"
    assert abs(float(found["chk_2"]["y"]) - plot_area(page)[2]) < 0.01  # on the time axis
    assert re.search(r'<path id="m[0-9a-f]+" d="M 0 -[\d.]+\s*L ', page)  # a triangle
    assert "<td>–</td><td>–</td>" in page  # no statistic, no threshold
    assert "<title>2026-12-03 08:00:00 UTC: inconclusive, Σ d² – (threshold –); –</title>" in page


def test_one_check_alone_sits_in_the_middle() -> None:
    page = render_checks_page("cal_x", [entry(0, "holds", 50.0, 79.1)], count=1, how_to_check="")
    left, right, _ = plot_area(page)
    assert abs(float(points(page)["chk_0"]["x"]) - (left + right) / 2) < 0.01
    assert "1 check." in page


def test_a_threshold_that_changes_is_a_step_and_a_long_history_says_what_is_shown() -> None:
    entries = [entry(1, "holds", 40.0, 44.0), entry(0, "holds", 50.0, 79.1)]  # newest first
    page = render_checks_page("cal_x", entries, count=5, how_to_check="")
    ys = [y for _, y in threshold_line(page)]
    assert len(ys) == 4 and ys[0] == ys[1] < ys[2] == ys[3]  # 79.1 first (higher), then 44
    assert "the newest 2 of 5 checks" in page


def test_the_chart_is_inline_svg_naming_no_other_host() -> None:
    entries = [entry(1, "drifted", 400.0, 79.1), entry(0, "holds", 50.0, 79.1)]
    page = render_checks_page("cal_x", entries, count=2, how_to_check="")
    assert page.count("<svg") == 1 and "<?xml" not in page and "<!DOCTYPE svg" not in page
    assert "http://" not in page and "https://" not in page and "<script" not in page
    found = points(page)
    assert found["chk_1"]["size"] > found["chk_0"]["size"]  # a drift is marked
    assert found["chk_1"]["y"] < found["chk_0"]["y"] and found["chk_1"]["x"] > found["chk_0"]["x"]
