"""Service settings: one class, read from the environment (prefix ``KINCAL_``).

Every field can be set as ``KINCAL_<FIELD>`` (e.g. ``KINCAL_DATABASE_URL``,
``KINCAL_MAX_REQUEST_BYTES``). Defaults give a single-user service on 127.0.0.1 with SQLite in the
user's data folder.
"""

from __future__ import annotations

import ipaddress
import os
import re
import socket
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from schemas.urdf_outline import DEFAULT_MAX_URDF_JOINTS
from solver.errors import KincalError

MiB = 1024 * 1024


def default_data_dir() -> Path:
    """``$XDG_DATA_HOME/kincal`` (``~/.local/share/kincal``)."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "kincal"


MAX_DEFAULT_WEB_PROCESSES = 4


def default_web_processes() -> int:
    """One request process per CPU this process may run on, at most 4 (each takes ~370 MB
    resident, most of it the imports: numpy, Pinocchio, pandas)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, MAX_DEFAULT_WEB_PROCESSES))


class Settings(BaseSettings):
    """Everything the HTTP service, its job runner and ``kincal keys`` are configured with."""

    model_config = SettingsConfigDict(env_prefix="KINCAL_", extra="ignore")

    host: str = Field("127.0.0.1", description="Interface to bind; keyless mode only on loopback.")
    port: int = Field(8000, ge=1, le=65535)
    data_dir: Path = Field(
        default_factory=default_data_dir,
        description="Uploaded datasets/URDFs and job artifacts (and the SQLite file by default).",
    )
    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL, e.g. postgresql+psycopg://user:pw@host/db; "
        "default sqlite:///<data_dir>/kincal.db (WAL mode).",
    )
    allow_keyless_localhost: bool = Field(
        True,
        description="When bound to a loopback address, requests without X-API-Key act as "
        "tenant 'local'. Never applies on any other address.",
    )
    web_processes: int = Field(
        default_factory=default_web_processes,
        ge=1,
        le=64,
        description="Request processes of kincal serve, sharing the port (default: one per "
        "CPU, at most 4); jobs run in one more process, whatever this is.",
    )
    workers: int = Field(
        1, ge=0, le=64, description="Job worker processes (0: accept jobs but run none here)."
    )
    worker_start_method: Literal["forkserver", "spawn"] = Field(
        "forkserver",
        description="How worker processes start: forkserver (imports paid once, fast restarts) "
        "or spawn (each worker imports everything itself).",
    )
    instance_name: str = Field(
        default_factory=socket.gethostname,
        min_length=1,
        max_length=200,  # jobs.runner_id is VARCHAR(200); PostgreSQL enforces it, SQLite not
        description="Identifies this service instance in job leases; unique per instance that "
        "shares a database.",
    )
    job_max_attempts: int = Field(
        3, ge=1, description="A job whose worker died this many times is marked failed."
    )
    job_lease_s: float = Field(
        30.0,
        gt=0,
        description="Running jobs of another instance without a heartbeat for this "
        "long are re-queued.",
    )
    job_heartbeat_s: float = Field(5.0, gt=0)
    job_poll_s: float = Field(0.5, gt=0, description="How often idle workers look for jobs.")
    shutdown_grace_s: float = Field(
        10.0,
        ge=0,
        description="On shutdown, running jobs get this long to finish; the rest are re-queued.",
    )
    max_request_bytes: int = Field(
        16 * MiB, ge=1024, description="Largest request body (a dataset upload)."
    )
    max_ranking_request_bytes: int = Field(
        4 * MiB,
        ge=1024,
        description="Largest body of a ranking request (10 000 candidates of 7 joints by name "
        "take ~2.5 MB); refused before it is parsed.",
    )
    max_small_request_bytes: int = Field(
        256 * 1024,
        ge=1024,
        description="Largest body of the other requests (calibration and discovery options, "
        "cancellations, GETs).",
    )
    max_rows: int = Field(100_000, ge=1, description="Most samples in one dataset.")
    max_bag_messages: int = Field(
        2_000_000,
        ge=1,
        description="Most messages an uploaded ROS bag may hold on the topics read (joint "
        "states, measurement, capture), counted from its index before any is decoded.",
    )
    max_joints: int = Field(32, ge=1, description="Most joints in a calibrated chain.")
    max_urdf_bytes: int = Field(2 * MiB, ge=1024, description="Largest uploaded URDF.")
    max_urdf_joints: int = Field(
        DEFAULT_MAX_URDF_JOINTS,
        ge=1,
        le=2000,  # Pinocchio's recursive URDF reader overflows its stack near 4000
        description="Most <joint> elements in an uploaded URDF (counted before it is parsed).",
    )
    max_ranking_candidates: int = Field(
        10_000, ge=1, description="Most configurations scored by one ranking request."
    )
    result_cache_size: int = Field(64, ge=1, description="Calibration results kept in memory.")
    api_key_cache_s: float = Field(
        30.0,
        ge=0,
        description="How long a verified API key is trusted without a DB lookup "
        "(upper bound on how long a revoked key keeps working).",
    )
    dask_address: str | None = Field(
        None,
        description="Dask scheduler (tcp://host:8786). When set, the service's calibration "
        "jobs run streamed on this cluster (each job reads it from its worker's environment; "
        "the cluster's workers must see the data folder at the same path), and kincal "
        "calibrate/fleet --executor dask use it; None: jobs run in the worker process, "
        "--executor dask starts a local cluster.",
    )
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    log_format: Literal["json", "text"] = "json"

    @field_validator("dask_address")
    @classmethod
    def _dask_address(cls, value: str | None) -> str | None:
        return dask_address(value) if value else None  # empty: not set

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    @property
    def resolved_database_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir / 'kincal.db'}"

    @property
    def bound_to_loopback(self) -> bool:
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    @property
    def keyless(self) -> bool:
        """Requests without a key are accepted (as tenant 'local')."""
        return self.allow_keyless_localhost and self.bound_to_loopback


DASK_ADDRESS = re.compile(r"^(?:[a-z][a-z0-9+.-]*://)?(?:\[[0-9a-fA-F:.]+\]|[^\s/:\[\]]+):\d{1,5}$")
"""A Dask scheduler address: optional scheme (tcp://, tls://, ucx://), host or [IPv6], port."""


def dask_address(value: str) -> str:
    """``value`` if it is a scheduler address (``tcp://host:8786``), else a ValueError naming
    the form (Dask's own message for a missing port is a traceback-only ValueError)."""
    if not DASK_ADDRESS.match(value.strip()):
        raise ValueError(
            f"{value!r} is not a Dask scheduler address; give scheme://host:port, e.g. "
            "tcp://127.0.0.1:8786"
        )
    return value.strip()


def load_settings(**overrides: object) -> Settings:
    """``Settings(**overrides)`` from the environment; an invalid ``KINCAL_*`` value is a
    :class:`KincalError` naming the variable, its value and what it must be (not a traceback)."""
    try:
        return Settings(**overrides)  # type: ignore[arg-type]
    except ValidationError as exc:
        problems = []
        for error in exc.errors():
            name = "KINCAL_" + "_".join(str(part) for part in error["loc"]).upper()
            problems.append(f"{name}={error.get('input')!r}: {error['msg']}")
        raise KincalError(
            "invalid setting " + "; ".join(problems) + " (kincal serve --help lists the settings "
            "with their defaults)"
        ) from exc
