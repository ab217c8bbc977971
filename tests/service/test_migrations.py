"""The service refuses an unmigrated database, and `drop db upgrade` fixes it; upgrading keeps recorded jobs whole."""
from __future__ import annotations

import json
from contextlib import contextmanager
from typing import Iterator

import pytest
from sqlalchemy import inspect, text
from sqlalchemy.exc import IntegrityError

from app.cli import main
from app.main import NotMigrated, create_app
from kernel.db import upgrade
from kernel.job_state import JobStatus
from kernel.settings import Settings

from .backends import database


def test_unmigrated_database_is_refused_until_upgrade(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DROP_DATA_DIR", str(tmp_path))
    settings = Settings()
    with pytest.raises(NotMigrated, match="drop db upgrade"):
        create_app(settings)
    assert main(["api"]) == 2 and "drop db upgrade" in capsys.readouterr().err
    assert main(["worker"]) == 2 and "drop db upgrade" in capsys.readouterr().err
    assert main(["db", "upgrade"]) == 0
    assert create_app(settings).state.settings is settings
    assert main(["token", "create", "--name", "carol"]) == 0
    token = capsys.readouterr().out.strip().splitlines()[-1]
    assert token.startswith("drop_") and len(token) > 40


def _old_database(tmp_path, revision: str, url: str | None = None):
    """A database (SQLite unless `url`) migrated only up to `revision`, holding one owner: where an upgrade finds
    recorded rows."""
    from alembic import command

    from kernel.db import alembic_config, make_engine

    url = url or f"sqlite:///{tmp_path / 'old.db'}"
    command.upgrade(alembic_config(url), revision)
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO owners (id, name, created_at) VALUES ('own_1', 'old', CURRENT_TIMESTAMP)"))
    return url, engine


def test_upgrade_fills_best_epoch_and_final_score_of_recorded_jobs(tmp_path):
    url, engine = _old_database(tmp_path, "0001")
    with engine.begin() as conn:
        for job_id in ("job_evaluated", "job_queued"):
            conn.execute(text(
                "INSERT INTO jobs (id, owner_id, algorithm, env, preset, overrides, seed, config, status, attempts, "
                "max_attempts, max_runtime_s, created_at) VALUES (:id, 'own_1', 'drop', 'hopper', 'smoke', '{}', 0, "
                "'{}', 'succeeded', 1, 3, 600, CURRENT_TIMESTAMP)"), {"id": job_id})
        for epoch, score in ((4, 2.0), (1, 6.0), (2, 1.0), (3, 6.0)):  # inserted out of order: epochs decide
            conn.execute(text("INSERT INTO job_evaluations (job_id, epoch, mean_return, normalized_score, created_at) "
                              "VALUES ('job_evaluated', :epoch, 0, :score, CURRENT_TIMESTAMP)"),
                         {"epoch": epoch, "score": score})
    upgrade(url)
    with engine.connect() as conn:
        rows = {r.id: (r.best_epoch, r.final_score)
                for r in conn.execute(text("SELECT id, best_epoch, final_score FROM jobs"))}
    engine.dispose()
    assert rows == {"job_evaluated": (1, 3.0), "job_queued": (None, None)}


def test_upgrade_fills_the_decoded_size_of_recorded_datasets(tmp_path):
    url, engine = _old_database(tmp_path, "0003")
    with engine.begin() as conn:
        conn.execute(text(
            "INSERT INTO datasets (id, owner_id, name, format, sha256, size_bytes, path, env, obs_dim, act_dim, "
            "report, created_at) VALUES ('ds_1', 'own_1', 'lazy', 'hdf5', '', 7000, '/x', 'hopper', 11, 3, "
            "'{\"transitions\": 1000000}', CURRENT_TIMESTAMP)"))
    upgrade(url)
    with engine.connect() as conn:
        decoded = conn.execute(text("SELECT decoded_bytes FROM datasets")).scalar_one()
    engine.dispose()
    assert decoded == 1_000_000 * (2 * 11 + 3 + 2) * 4


def _job_row(conn, job_id: str, status: str) -> None:
    conn.execute(text(
        "INSERT INTO jobs (id, owner_id, algorithm, env, preset, overrides, seed, config, status, attempts, "
        "max_attempts, max_runtime_s, created_at) VALUES (:id, 'own_1', 'drop', 'hopper', 'smoke', '{}', 0, '{}', "
        ":status, 1, 3, 600, CURRENT_TIMESTAMP)"), {"id": job_id, "status": status})


def _refuses(engine, status: str) -> bool:
    try:
        with engine.begin() as conn:
            conn.execute(text("UPDATE jobs SET status = :status WHERE id = 'job_1'"), {"status": status})
    except IntegrityError:
        return True
    return False


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_job_status_check_keeps_recorded_jobs_and_downgrades(backend, tmp_path):
    """Migration 0005 holds jobs.status to JobStatus on both backends; on SQLite, where batch mode recreates the jobs
    table, the rows that refer to a job (its events) survive both ways."""
    from alembic import command

    from kernel.db import alembic_config

    with database() if backend == "postgresql" else _no_database() as pg_url:
        url, engine = _old_database(tmp_path, "0004", pg_url)
        with engine.begin() as conn:
            _job_row(conn, "job_1", "succeeded")
            conn.execute(text("INSERT INTO job_events (job_id, type, message, created_at) "
                              "VALUES ('job_1', 'status', 'succeeded', CURRENT_TIMESTAMP)"))
        upgrade(url)
        assert _refuses(engine, "bogus")
        with engine.begin() as conn:
            for status in JobStatus:  # the statuses written out in the migration are the enum's
                _job_row(conn, f"job_{status.value}", status.value)
        command.downgrade(alembic_config(url), "0004")
        assert not _refuses(engine, "bogus")
        with engine.begin() as conn:
            conn.execute(text("UPDATE jobs SET status = 'succeeded' WHERE id = 'job_1'"))
        upgrade(url)
        with engine.connect() as conn:
            events = conn.execute(text("SELECT count(*) FROM job_events WHERE job_id = 'job_1'")).scalar_one()
            jobs = conn.execute(text("SELECT count(*) FROM jobs")).scalar_one()
        engine.dispose()
    assert (events, jobs) == (1, 1 + len(JobStatus))


@contextmanager
def _no_database() -> Iterator[None]:
    yield None


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_models_describe_the_migrated_schema(backend, tmp_path):
    """kernel/models.py and migrations/ are two descriptions of one schema: a column, index or type added to one and
    not the other is a diff here (alembic's autogenerate comparison; it does not compare CHECK constraints)."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from kernel.db import make_engine
    from kernel.models import Base

    with database() if backend == "postgresql" else _no_database() as pg_url:
        url = pg_url or f"sqlite:///{tmp_path / 'head.db'}"
        upgrade(url)
        engine = make_engine(url)
        with engine.connect() as conn:
            diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata)
        engine.dispose()
    assert diff == []


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_row_ids_count_past_32_bits_after_0006(backend, tmp_path):
    """Events, metrics and evaluations recorded before 0006 keep their ids, and new rows are numbered past 2^31 (on
    PostgreSQL the sequence was an int4 one, which refused to go there)."""
    columns = {"job_events": "(job_id, type, message, created_at) VALUES ('job_1', 'status', '', CURRENT_TIMESTAMP)",
               "job_metrics": "(job_id, name, step, value, created_at) VALUES ('job_1', 'x', 0, 0, CURRENT_TIMESTAMP)",
               "job_evaluations": "(job_id, epoch, mean_return, normalized_score, created_at) "
                                  "VALUES ('job_1', 1, 0, 0, CURRENT_TIMESTAMP)"}
    with database() if backend == "postgresql" else _no_database() as pg_url:
        url, engine = _old_database(tmp_path, "0005", pg_url)
        with engine.begin() as conn:
            _job_row(conn, "job_1", "succeeded")
            for table, values in columns.items():
                conn.execute(text(f"INSERT INTO {table} {values}"))
        upgrade(url)
        ids = {}
        with engine.begin() as conn:
            for table, values in columns.items():
                if backend == "postgresql":
                    conn.execute(text(f"SELECT setval('{table}_id_seq', {2**31})"))
                else:  # the rowid counts on from the largest id
                    conn.execute(text(f"INSERT INTO {table} (id, {values.removeprefix('(')}"
                                      .replace("VALUES (", f"VALUES ({2**31}, ")))
                conn.execute(text(f"INSERT INTO {table} {values}"))
                ids[table] = sorted(conn.execute(text(f"SELECT id FROM {table}")).scalars())
        engine.dispose()
    for table, found in ids.items():
        assert found[0] == 1 and found[-1] == 2**31 + 1, (table, found)


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_recorded_jobs_keep_their_dynamics_through_0009(backend, tmp_path):
    """0009 replaces jobs.result (the engine's report, server paths in it) by jobs.dynamics, which the API shows: a
    recorded job's ensemble moves over less its path, a job without one stays without, and the downgrade puts it
    back."""
    from alembic import command

    from kernel.db import alembic_config

    fit = {"epochs": 3, "holdout_mse": [0.5, 0.4], "elites": [1], "seconds": 2.0, "stopped_by": "max_epochs",
           "cache_key": "ab" * 32, "from_cache": False}
    with database() if backend == "postgresql" else _no_database() as pg_url:
        url, engine = _old_database(tmp_path, "0008", pg_url)
        with engine.begin() as conn:
            for job_id in ("job_trained", "job_queued", "job_uncached"):
                _job_row(conn, job_id, "succeeded")
            conn.execute(text("UPDATE jobs SET result = :result WHERE id = 'job_trained'"), {"result": json.dumps(
                {"status": "completed", "policy": {"last": {"torchscript": "/srv/x/policy.pt"}},
                 "dynamics": {**fit, "cache_path": "/srv/drop/models/abab.pt"}})})
            conn.execute(text("UPDATE jobs SET result = :result WHERE id = 'job_uncached'"), {"result": json.dumps(
                {"dynamics": {k: v for k, v in fit.items() if k not in ("cache_key", "from_cache")}})})
        upgrade(url)
        with engine.connect() as conn:
            upgraded = {r.id: _loaded(r.dynamics) for r in conn.execute(text("SELECT id, dynamics FROM jobs"))}
            columns = {c["name"] for c in inspect(conn).get_columns("jobs")}
        command.downgrade(alembic_config(url), "0008")
        with engine.connect() as conn:
            downgraded = {r.id: _loaded(r.result) for r in conn.execute(text("SELECT id, result FROM jobs"))}
        engine.dispose()
    unkeyed = {**fit, "cache_key": None, "from_cache": None}  # a job of before the model cache: null, as documented
    assert upgraded == {"job_trained": fit, "job_queued": None, "job_uncached": unkeyed} and "result" not in columns
    assert downgraded == {"job_trained": {"dynamics": fit}, "job_queued": None, "job_uncached": {"dynamics": unkeyed}}


def _loaded(value):
    """A JSON column's value as text (SQLite, and a textual SELECT) or already parsed (PostgreSQL's json)."""
    return json.loads(value) if isinstance(value, str) else value
