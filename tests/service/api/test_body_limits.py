"""Request body limits per route, applied before a body is read or parsed: 12 MB ranking bodies
used to be parsed in the request loop before the candidate limit was checked."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from service.api import rankings
from tests.service.api.conftest import AppFactory, assert_problem, upload_csv


def _chunks(total: int, size: int = 64 * 1024) -> Iterator[bytes]:
    for start in range(0, total, size):
        yield b" " * min(size, total - start)


@pytest.mark.parametrize(
    ("path", "limit", "setting"),
    [
        ("/api/v1/rankings", 4 * 1024 * 1024, "KINCAL_MAX_RANKING_REQUEST_BYTES"),
        ("/api/v1/calibrations", 256 * 1024, "KINCAL_MAX_SMALL_REQUEST_BYTES"),
        ("/api/v1/discoveries", 256 * 1024, "KINCAL_MAX_SMALL_REQUEST_BYTES"),
        ("/api/v1/robots", 4 * 1024 * 1024 + 64 * 1024, "KINCAL_MAX_URDF_BYTES"),
    ],
)
def test_bodies_over_the_route_limit_are_413_declared_or_streamed(
    client: TestClient, monkeypatch: pytest.MonkeyPatch, path: str, limit: int, setting: str
) -> None:
    parsed: list[int] = []
    monkeypatch.setattr(
        rankings.RankingCreate, "model_validate_json", lambda body: parsed.append(len(body))
    )
    json_header = {"content-type": "application/json"}
    declared = client.post(path, content=b" " * (limit + 1), headers=json_header)
    assert_problem(declared, 413, str(limit), setting)
    streamed = client.post(path, content=_chunks(limit + 1), headers=json_header)
    assert_problem(streamed, 413, str(limit), setting)
    assert parsed == []
    assert client.get("/healthz").status_code == 200


def test_a_dataset_upload_keeps_the_large_limit(make_client: AppFactory) -> None:
    client = make_client(max_small_request_bytes=1024)
    assert upload_csv(client).status_code == 201


def test_large_ranking_bodies_are_parsed_off_the_event_loop(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Up to INLINE_PARSE_BYTES the body is parsed in the loop; beyond it in a worker thread."""
    import threading

    threads: list[str] = []
    original = rankings.RankingCreate.model_validate_json

    def spy(body: bytes) -> object:
        threads.append(threading.current_thread().name)
        return original(body)

    monkeypatch.setattr(rankings.RankingCreate, "model_validate_json", spy)
    small = b'{"calibration_id": "cal_x", "joint_positions_rad": [[0, 0, 0, 0, 0, 0]]}'
    rows = ",".join(["[0.1,0.2,0.3,0.4,0.5,0.6]"] * 5000)
    large = f'{{"calibration_id": "cal_x", "joint_positions_rad": [{rows}]}}'.encode()
    assert len(small) <= rankings.INLINE_PARSE_BYTES < len(large)
    for body in (small, large):
        response = client.post(
            "/api/v1/rankings", content=body, headers={"content-type": "application/json"}
        )
        assert response.status_code == 404  # parsed, then the calibration is unknown
    loop_thread, other = threads
    assert loop_thread != other
