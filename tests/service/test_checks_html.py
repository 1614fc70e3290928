"""The checks page's renderer on made-up rows, for what the service test does not reach: an
inconclusive check (no statistic: a triangle on the time axis), one check alone (no time
span), thresholds that differ between checks (a step), and a page of the newest only."""

from __future__ import annotations

import datetime as dt
import re

from schemas.api import CheckLinks, CheckSummary
from service.render.checks_html import LEFT, RIGHT, WIDTH, CheckEntry, render_checks_page

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


def test_an_inconclusive_check_is_a_triangle_on_the_time_axis() -> None:
    entries = [entry(2, "inconclusive", None, None), entry(1, "holds", 50.0, 79.1)]
    page = render_checks_page("cal_x", entries, count=2, how_to_check="")
    assert re.search(r'<polygon class="point inconclusive" data-check-id="chk_2"', page)
    assert re.search(r'<circle class="point holds" data-check-id="chk_1"', page)
    assert "<td>–</td><td>–</td>" in page  # no statistic, no threshold


def test_one_check_alone_sits_in_the_middle() -> None:
    page = render_checks_page("cal_x", [entry(0, "holds", 50.0, 79.1)], count=1, how_to_check="")
    assert f'cx="{(LEFT + WIDTH - RIGHT) / 2:.1f}"' in page
    assert "1 check." in page


def test_a_threshold_that_changes_is_a_step_and_a_long_history_says_what_is_shown() -> None:
    entries = [entry(1, "holds", 40.0, 44.0), entry(0, "holds", 50.0, 79.1)]  # newest first
    page = render_checks_page("cal_x", entries, count=5, how_to_check="")
    found = re.search(r'<polyline class="threshold" points="([^"]*)"', page)
    assert found
    ys = [float(p.split(",")[1]) for p in found.group(1).split()]
    assert len(ys) == 4 and ys[0] == ys[1] < ys[2] == ys[3]  # 79.1 first (higher), then 44
    assert "the newest 2 of 5 checks" in page
