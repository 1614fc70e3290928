"""The checks page (issue 33): one calibration's checks over time as HTML served by the service
with no CDN. The real FR3 recording calibrated through the service once, its 10 held-out rows
checked as recorded (holds; the dataset under a hostile name) and with joint 3 reading 2 mrad
off (drifted, located). The page shows both checks' values in its table and its chart
(matplotlib's SVG, inline), escapes the name, is 404 for another tenant and an unknown
calibration, says so when there is no check, and renders in headless Chromium with nothing but
the service to load from."""

from __future__ import annotations

import io
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from service.api import create_app
from service.settings import Settings
from tests.service.api.conftest import (
    assert_problem,
    client_api,
    fresh_database_url,
    make_settings,
    new_key,
    uvicorn_in_thread,
)
from tests.service.api.test_checks import calibrated_service
from tests.service.api.test_docs_browser import CHROMIUM, rendered_dom
from tests.service.test_checks_html import points

URL = "/api/v1/calibrations"
HOSTILE = '<script>alert("x")</script> & <b>bold</b>.csv'


def report_url(calibration_id: str) -> str:
    return f"{URL}/{calibration_id}/checks/report"


@dataclass
class Page:
    """A calibration with two checks (held, drifted) on a database whose app has stopped."""

    settings: Settings
    calibration_id: str
    held: dict[str, Any]
    drifted: dict[str, Any]


def upload(client: TestClient, data: bytes, name: str) -> str:
    response = client.post(
        "/api/v1/datasets",
        files={"file": ("check.csv", io.BytesIO(data), "text/csv")},
        data={"robot": "panda", "name": name},
    )
    assert response.status_code in (200, 201), response.text
    return str(response.json()["id"])


@pytest.fixture(scope="module")
def checked(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Page]:
    folder = tmp_path_factory.mktemp("checks_page")
    with fresh_database_url(folder) as url:
        with calibrated_service(folder, url) as service:
            client, api, calibration_id = service.client, service.api, service.calibration_id
            as_recorded = service.held.to_csv(index=False, float_format="%.17g").encode()
            held = api.check(calibration_id, upload(client, as_recorded, HOSTILE))
            moved = service.held.copy()
            moved["q3"] += 0.002  # joint 3 reads 2 mrad off
            data = moved.to_csv(index=False, float_format="%.17g").encode()
            drifted = api.check(calibration_id, upload(client, data, "drifted.csv"))
        yield Page(make_settings(folder, url, workers=0), calibration_id, held, drifted)


@pytest.fixture(scope="module")
def client(checked: Page) -> Iterator[TestClient]:
    with TestClient(create_app(checked.settings), raise_server_exceptions=False) as client:
        yield client


def test_the_page_shows_each_check_in_the_table_and_the_chart(
    checked: Page, client: TestClient
) -> None:
    held, drifted = checked.held, checked.drifted
    assert held["verdict"] == "holds" and drifted["verdict"] == "drifted"
    response = client.get(report_url(checked.calibration_id))
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "text/html; charset=utf-8"
    assert "default-src 'none'" in response.headers["content-security-policy"]
    page = response.text
    assert "<script" not in page.replace("&lt;script", "")  # no scripts of its own
    assert "http://" not in page and "https://" not in page  # nothing from another host
    assert "2 checks" in page
    for check in (held, drifted):
        row = re.search(
            rf'<tr class="check {check["verdict"]}" data-check-id="{check["id"]}">'
            r"(.*?)</tr>",
            page,
        )
        assert row, check["id"]
        cells = row.group(1)
        assert f"<td>{check['statistic']:.2f}</td><td>{check['threshold']:.2f}</td>" in cells
        assert f"<td>{check['n_poses']}</td><td>{check['verdict']}</td>" in cells
    located = drifted["check"]["located"]
    assert located["name"] == "panda_joint3 offset"
    value_mrad = located["components"][0]["value"] * 1000
    assert f"panda_joint3 offset: {located['components'][0]['name']} {value_mrad:.2f} mrad" in page
    markers = points(page)
    assert set(markers) == {held["id"], drifted["id"]}
    assert markers[held["id"]]["verdict"] == "holds"
    assert markers[drifted["id"]]["verdict"] == "drifted"
    assert float(markers[drifted["id"]]["size"]) > float(markers[held["id"]]["size"])  # marked
    # the drift's Σ d² is above the threshold, the held check's below: higher on the chart
    assert float(markers[drifted["id"]]["y"]) < float(markers[held["id"]]["y"])
    assert float(markers[drifted["id"]]["x"]) > float(markers[held["id"]]["x"])  # later
    assert '<g id="threshold">' in page


def test_a_hostile_dataset_name_is_escaped(checked: Page, client: TestClient) -> None:
    page = client.get(report_url(checked.calibration_id)).text
    assert checked.held["dataset_name"] == HOSTILE
    assert HOSTILE not in page and "<b>bold" not in page
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; &lt;b&gt;bold" in page


def test_another_tenant_and_an_unknown_calibration_are_404(
    checked: Page, client: TestClient
) -> None:
    theirs = {"X-API-Key": new_key(client, "other-lab")}
    assert_problem(client.get(report_url(checked.calibration_id), headers=theirs), 404)
    assert_problem(client.get(report_url("cal_nope")), 404, "cal_nope")


def test_a_calibration_without_checks_gets_a_page_that_says_so(client: TestClient) -> None:
    dataset_id = client_api(client).datasets()["data"][-1]["id"]
    queued = client.post(URL, json={"dataset_id": dataset_id}).json()  # no workers: queued
    response = client.get(report_url(queued["id"]))
    assert response.status_code == 200, response.text
    assert 'id="no-checks"' in response.text and "<svg" not in response.text
    assert f"POST {URL}/{queued['id']}/checks" in response.text


@pytest.fixture
def served(checked: Page, client: TestClient) -> Iterator[str]:
    """The app on the same database under uvicorn on a free loopback port, in a thread of this
    process (as in test_docs_browser.py)."""
    with uvicorn_in_thread(checked.settings) as url:
        yield url


@pytest.mark.skipif(
    CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install -y chromium)"
)
def test_the_page_renders_in_headless_chromium(checked: Page, served: str, tmp_path: Path) -> None:
    url = served + report_url(checked.calibration_id)
    assert httpx.get(url).status_code == 200
    dom = rendered_dom(url, tmp_path / "profile")
    assert "<svg" in dom and '<g id="threshold">' in dom
    for check in (checked.held, checked.drifted):
        assert f'<tr class="check {check["verdict"]}" data-check-id="{check["id"]}">' in dom
        assert f'data-check-id="{check["id"]}"' in dom.split("</svg>")[0]  # its point
    assert set(points(dom)) == {checked.held["id"], checked.drifted["id"]}
    assert "<script" not in dom  # the hostile name stayed text
    assert "&lt;script&gt;" in dom
