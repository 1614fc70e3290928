"""/docs (Swagger UI) and /redoc render in a real browser with no network beyond the service:
their assets come from the installed fastapi-offline package, not a CDN. Needs Debian's
chromium (``apt-get install chromium``); skipped, saying so, where it is absent."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.service.api.conftest import make_settings, uvicorn_in_thread

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install -y chromium)"
)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[str]:
    """The app under uvicorn on a free loopback port, in a thread of this process."""
    with uvicorn_in_thread(make_settings(tmp_path, f"sqlite:///{tmp_path / 'kincal.db'}")) as url:
        yield url


def rendered_dom(url: str, profile: Path) -> str:
    """The page's DOM after its scripts ran (virtual time lets the spec fetch finish)."""
    assert CHROMIUM is not None
    command = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        "--virtual-time-budget=20000",
        "--dump-dom",
        url,
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_docs_pages_reference_no_other_host(served: str) -> None:
    for page in ("/docs", "/redoc"):
        html = httpx.get(served + page).text
        assert "http://" not in html and "https://" not in html, html


def test_swagger_ui_renders_every_operation_offline(served: str, tmp_path: Path) -> None:
    dom = rendered_dom(f"{served}/docs", tmp_path / "profile")
    assert 'class="swagger-ui' in dom
    paths = httpx.get(f"{served}/openapi.json").json()["paths"]
    for path in paths:
        assert f'data-path="{path}"' in dom, f"{path} not rendered"
    assert dom.count('class="opblock-summary-method"') == sum(len(ops) for ops in paths.values())


def test_redoc_renders_the_operations_offline(served: str, tmp_path: Path) -> None:
    dom = rendered_dom(f"{served}/redoc", tmp_path / "profile")
    assert "redoc-wrap" in dom or "api-content" in dom, dom[:2000]
    for path in ("/api/v1/datasets", "/api/v1/rankings", "/api/v1/calibrations"):
        assert path in dom
