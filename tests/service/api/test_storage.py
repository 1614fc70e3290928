"""Storage: migrations equal the models, SQLite in WAL mode, atomic files, exclusive claims."""

from __future__ import annotations

import datetime as dt
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import text, update

from service.storage import repository
from service.storage.db import Database, alembic_config
from service.storage.files import FileStore
from service.storage.models import Base, Check, Job, utcnow
from tests.service.api.conftest import POSTGRES_URL


@pytest.fixture
def database(database_url: str) -> Iterator[Database]:
    db = Database(database_url)
    db.migrate()
    yield db
    db.dispose()


def _queue(database: Database, n: int, tenant_name: str = "t") -> list[str]:
    with database.session() as session:
        tenant = repository.ensure_tenant(session, tenant_name)
        ids = []
        for i in range(n):
            job = Job(
                id=repository.new_id("job"),
                tenant_id=tenant.id,
                kind="calibration",
                params={},
                state="queued",
                fraction=0.0,
                attempts=0,
                cancel_requested=False,
                artifacts={},
                created_at=utcnow() + dt.timedelta(milliseconds=i),
            )
            session.add(job)
            ids.append(job.id)
    return ids


def test_migrations_produce_exactly_the_models(database: Database) -> None:
    assert database.migrations_applied()
    with database.engine.connect() as connection:
        diff = compare_metadata(MigrationContext.configure(connection), Base.metadata)
    assert diff == []
    database.migrate()  # idempotent
    assert database.current_revision() == "0004"


@pytest.mark.skipif(POSTGRES_URL is not None, reason="SQLite-specific pragma")
def test_sqlite_runs_in_wal_mode_with_foreign_keys(database: Database) -> None:
    with database.engine.connect() as connection:
        assert connection.execute(text("PRAGMA journal_mode")).scalar() == "wal"
        assert connection.execute(text("PRAGMA foreign_keys")).scalar() == 1
        assert connection.execute(text("PRAGMA synchronous")).scalar() == 2  # FULL


def test_timestamps_come_back_timezone_aware_utc(database: Database) -> None:
    [job_id] = _queue(database, 1)
    with database.sessions() as session:
        job = session.get(Job, job_id)
        assert job is not None and job.created_at.tzinfo is not None
        assert job.created_at.utcoffset() == dt.timedelta(0)


def test_each_queued_job_is_claimed_exactly_once_by_concurrent_claimers(
    database: Database,
) -> None:
    ids = _queue(database, 12)
    claimed: list[str] = []
    lock = threading.Lock()

    def claimer(name: str) -> None:
        while True:
            with database.session() as session:
                job = repository.claim_next_job(session, name, ["calibration"])
            if job is None:
                return
            with lock:
                claimed.append(job.id)

    threads = [threading.Thread(target=claimer, args=(f"r{i}",)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(claimed) == sorted(ids)
    with database.sessions() as session:
        assert all(session.get(Job, i).attempts == 1 for i in ids)  # type: ignore[union-attr]


def test_claims_take_the_oldest_job_of_a_known_kind(database: Database) -> None:
    first, _ = _queue(database, 2)
    with database.session() as session:
        assert repository.claim_next_job(session, "r", ["discovery"]) is None
        job = repository.claim_next_job(session, "r", ["calibration"])
        assert job is not None and job.id == first


def test_jobs_of_an_instance_or_with_expired_leases_are_requeued(database: Database) -> None:
    mine, theirs, fresh = _queue(database, 3)
    with database.session() as session:
        for runner in ("me", "other", "other"):
            repository.claim_next_job(session, runner, ["calibration"])
        stale = utcnow() - dt.timedelta(seconds=120)
        session.execute(update(Job).where(Job.id == theirs).values(heartbeat_at=stale))
    with database.session() as session:
        assert repository.requeue_jobs_of_runner(session, "me") == [mine]
        assert repository.requeue_expired_leases(session, lease_s=30) == [theirs]
    with database.sessions() as session:
        states = {i: session.get(Job, i).state for i in (mine, theirs, fresh)}  # type: ignore[union-attr]
    assert states == {mine: "queued", theirs: "queued", fresh: "running"}


def test_a_finished_job_is_not_overwritten_by_a_runner_that_lost_it(database: Database) -> None:
    [job_id] = _queue(database, 1)
    with database.session() as session:
        repository.claim_next_job(session, "old", ["calibration"])
        repository.requeue_jobs_of_runner(session, "old")
        repository.claim_next_job(session, "new", ["calibration"])
    with database.session() as session:
        assert repository.finish_job(session, job_id, "old", "succeeded") is None
        done = repository.finish_job(session, job_id, "new", "succeeded", artifacts={"a": "b"})
        assert done is not None and done.state == "succeeded" and done.artifacts == {"a": "b"}


def test_atomic_write_never_leaves_a_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = FileStore(tmp_path)
    store.write("tenants/t/result.json", b"old")

    def crash(*args: object) -> None:
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="disk gone"):
        store.write("tenants/t/result.json", b"new" * 1000)
    monkeypatch.undo()
    assert store.read("tenants/t/result.json") == b"old"
    assert [p.name for p in (tmp_path / "tenants" / "t").iterdir()] == ["result.json"]
    store.write("tenants/t/result.json", b"new")
    assert store.read("tenants/t/result.json") == b"new"


def test_file_store_refuses_paths_outside_the_data_folder(tmp_path: Path) -> None:
    store = FileStore(tmp_path / "data")
    with pytest.raises(ValueError, match="leaves the data folder"):
        store.path("../outside.txt")


def test_the_latest_check_per_calibration_for_the_most_recently_checked(
    database: Database,
) -> None:
    """What the check gauges show: one row per calibration, its newest check, and only the
    ``limit`` calibrations checked most recently (bounded label cardinality)."""
    calibrations = _queue(database, 3)
    start = utcnow()
    times = {  # calibration -> minutes of its checks
        calibrations[0]: (0, 5),
        calibrations[1]: (1, 2),
        calibrations[2]: (3,),
    }
    with database.session() as session:
        tenant = repository.ensure_tenant(session, "t")
        for calibration_id, minutes in times.items():
            for minute in minutes:
                session.add(
                    Check(
                        id=f"chk_{calibration_id[-6:]}_{minute}",
                        tenant_id=tenant.id,
                        calibration_id=calibration_id,
                        dataset_id="ds_x",
                        dataset_name="check.csv",
                        level=0.05,
                        n_poses=10,
                        verdict="holds",
                        statistic=float(minute),
                        threshold=81.6,
                        located=None,
                        document_path="tenants/x/checks/x.json",
                        created_at=start + dt.timedelta(minutes=minute),
                    )
                )
    with database.sessions() as session:
        latest = repository.latest_checks(session, 2)
        page, count = repository.list_checks(
            session, tenant.id, calibrations[0], offset=0, limit=10
        )
    assert [(c.calibration_id, c.statistic) for c in latest] == [
        (calibrations[0], 5.0),
        (calibrations[2], 3.0),
    ]
    assert count == 2 and [c.statistic for c in page] == [5.0, 0.0]  # newest first


def test_migration_0004_keeps_each_datasets_meaning_when_the_flag_turns_round(
    database_url: str,
) -> None:
    """A database written before issue 35 stored ``position_only``; after the upgrade its rows
    say ``measures_rotation``, the negation, and the downgrade gives the old values back."""
    db = Database(database_url)

    def to_revision(revision: str) -> None:
        with db.engine.begin() as connection:
            config = alembic_config(db.url)
            config.attributes["connection"] = connection
            move = (
                command.upgrade if revision >= (db.current_revision() or "") else command.downgrade
            )
            move(config, revision)

    to_revision("0003")
    columns = (
        "id, tenant_id, name, robot, base_frame, tip_frame, joint_names, n_samples, {flag}, "
        "content_sha256, data_path, size_bytes, created_at"
    )
    with db.engine.begin() as connection:
        connection.execute(
            text("INSERT INTO tenants (id, name, created_at) VALUES ('t1', 't', :at)"),
            {"at": utcnow()},
        )
        for dataset_id, position_only in (("poses", False), ("positions", True)):
            connection.execute(
                text(
                    f"INSERT INTO datasets ({columns.format(flag='position_only')}) VALUES "
                    "(:id, 't1', :id, 'panda', 'b', 't', '[]', 3, :flag, :id, 'p', 1, :at)"
                ),
                {"id": dataset_id, "flag": position_only, "at": utcnow()},
            )

    def flags(column: str) -> dict[str, bool]:
        with db.engine.connect() as connection:
            rows = connection.execute(text(f"SELECT id, {column} FROM datasets")).all()
        return {dataset_id: bool(value) for dataset_id, value in rows}

    db.migrate()
    assert db.current_revision() == "0004"
    assert flags("measures_rotation") == {"poses": True, "positions": False}
    to_revision("0003")
    assert flags("position_only") == {"poses": False, "positions": True}
    db.dispose()
