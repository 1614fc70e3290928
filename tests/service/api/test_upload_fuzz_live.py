"""The catalogue of hostile uploads of issue 18 against a real ``kincal serve`` process: every
answer is a 4xx problem, the server stays up, and its peak resident memory stays under 1 GB."""

from __future__ import annotations

import io
import json
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pandas as pd

from tests.service.api.conftest import fresh_database_url, recording_bytes
from tests.service.api.test_crash_recovery import Server
from tests.service.api.test_datasets import many_rows_parquet
from tests.service.api.test_robots import long_chain_urdf

GIB = 1 << 30


def _peak_rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


def _csv_rows_with(value: object) -> list[dict[str, object]]:
    rows = pd.read_csv(io.BytesIO(recording_bytes())).to_dict(orient="records")
    rows[2]["elbow_joint"] = value
    return rows


def test_hostile_uploads_are_4xx_and_the_server_stays_small(tmp_path: Path) -> None:
    with fresh_database_url(tmp_path) as url:
        env = {
            **os.environ,
            "KINCAL_DATA_DIR": str(tmp_path / "data"),
            "KINCAL_DATABASE_URL": url,
            "KINCAL_WORKERS": "0",
            "KINCAL_LOG_FORMAT": "json",
        }
        server = Server(env, tmp_path / "server.log")
        try:
            server.wait_live()
            base = server.url
            parquet = many_rows_parquet(5_000_000)
            broken = recording_bytes(".parquet")[:300]

            def upload(name: str, data: bytes) -> int:
                files = {"file": (name, data, "application/octet-stream")}
                return httpx.post(
                    f"{base}/api/v1/datasets", files=files, data={"robot": "ur10"}, timeout=120
                ).status_code

            def rows(value: object) -> int:
                body = {"robot": "ur10", "rows": _csv_rows_with(value)}
                return httpx.post(f"{base}/api/v1/datasets", json=body, timeout=60).status_code

            def robot(urdf: str, tip: str) -> int:
                body = {"name": "long", "base_frame": "l0", "tip_frame": tip, "urdf": urdf}
                return httpx.post(f"{base}/api/v1/robots", json=body, timeout=60).status_code

            def ranking_body() -> int:
                rows_text = ",".join(["[0.1,0.2,0.3,0.4,0.5,0.6]"] * 500_000)
                body = f'{{"calibration_id":"cal_x","joint_positions_rad":[{rows_text}]}}'
                return httpx.post(
                    f"{base}/api/v1/rankings",
                    content=body.encode(),
                    headers={"content-type": "application/json"},
                    timeout=60,
                ).status_code

            calls = [
                *(lambda: upload("big.parquet", parquet) for _ in range(3)),
                lambda: upload("cut.parquet", broken),
                lambda: upload("huge.json", json.dumps(_csv_rows_with(10**400)).encode()),
                lambda: rows(10**400),
                lambda: rows(1e308),
                lambda: upload("big.csv", pd.DataFrame(_csv_rows_with(2e244)).to_csv().encode()),
                lambda: robot(long_chain_urdf(4000), "l6"),
                lambda: robot(long_chain_urdf(200), "l200"),
                ranking_body,
            ]
            with ThreadPoolExecutor(4) as pool:
                statuses = list(pool.map(lambda call: call(), calls))
            assert all(400 <= s < 500 for s in statuses), statuses
            assert httpx.get(f"{base}/healthz").status_code == 200
            peak = _peak_rss_bytes(server.process.pid)
            print(f"server peak RSS {peak / (1 << 20):.0f} MiB; statuses {statuses}")
            assert peak < GIB
        finally:
            server.stop()
