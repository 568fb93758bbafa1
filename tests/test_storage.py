"""Where the service keeps its state (issue 19, "State in the right places"): the data home,
never the working directory; and schema migrations that upgrade a database made by an
older version, keeping its jobs."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

import sqlalchemy as sa

from conftest_service import ServerThread, small_model_path
from service.jobs import JobStore
from service.migrations import current_revision
from service.settings import Settings, data_home


def _clear_env(monkeypatch) -> None:
    for var in ("POSECAL_DATA", "POSECAL_DB", "POSECAL_DATA_DIR", "XDG_DATA_HOME"):
        monkeypatch.delenv(var, raising=False)


def test_state_defaults_to_the_data_home_and_explicit_settings_win(tmp_path, monkeypatch):
    _clear_env(monkeypatch)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert data_home() == tmp_path / "home" / ".local" / "share" / "posecal"
    monkeypatch.setenv("XDG_DATA_HOME", "relative/ignored")  # XDG: relative paths are invalid
    assert data_home() == tmp_path / "home" / ".local" / "share" / "posecal"
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    s = Settings()
    assert Path(s.db) == tmp_path / "xdg" / "posecal" / "posecal.db"
    assert s.data_dir == tmp_path / "xdg" / "posecal" / "jobs"
    monkeypatch.setenv("POSECAL_DATA", str(tmp_path / "own"))
    assert Settings().data_dir == tmp_path / "own" / "jobs"
    explicit = Settings(db=str(tmp_path / "x.db"), data_dir=tmp_path / "uploads")
    assert explicit.db == str(tmp_path / "x.db") and explicit.data_dir == tmp_path / "uploads"
    monkeypatch.setenv("POSECAL_DB", "postgresql+psycopg://u@h/posecal")
    assert Settings().db_url == "postgresql+psycopg://u@h/posecal"


def test_the_service_writes_nothing_into_its_working_directory(tmp_path, monkeypatch):
    """Issue 19: the service wrote posecal.db and posecal-data/ wherever it was started."""
    _clear_env(monkeypatch)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    settings = Settings(model_path=small_model_path(), live=False, job_workers=0)
    with ServerThread(settings) as srv:
        assert srv.client.get("/v1/jobs").status_code == 200
    assert list(cwd.iterdir()) == []
    home = tmp_path / "xdg" / "posecal"
    assert (home / "posecal.db").is_file() and (home / "jobs").is_dir()


_OLD_COLUMNS = ("id", "state", "kind", "input_dir", "options", "progress", "stage", "error", "result",
                "attempts", "created_at", "started_at", "finished_at")
_NEW_COLUMNS = ("claim", "replica", "heartbeat_at")  # 0002: the run's claim; 0003: its replica and lease
HEAD = "0003"


def _old_database(path: Path) -> None:
    """A job database as the service made it before migrations: ``create_all`` of the
    previous jobs table (no ``claim`` column, no ``alembic_version`` table), three jobs."""
    meta = sa.MetaData()
    table = sa.Table(
        "jobs", meta,
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("state", sa.String(16), nullable=False, index=True),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("input_dir", sa.Text, nullable=False),
        sa.Column("options", sa.Text, nullable=False, default="{}"),
        sa.Column("progress", sa.Float, nullable=False, default=0.0),
        sa.Column("stage", sa.String(64), nullable=False, default=""),
        sa.Column("error", sa.Text),
        sa.Column("result", sa.Text),
        sa.Column("attempts", sa.Integer, nullable=False, default=0),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True)),
        sa.Column("finished_at", sa.DateTime(timezone=True)),
    )
    engine = sa.create_engine(f"sqlite:///{path}")
    meta.create_all(engine)
    t = datetime(2024, 5, 1, tzinfo=timezone.utc)
    rows = [dict(id="a" * 32, state="done", result=json.dumps({"frames": [], "notes": ["old"]}), progress=1.0,
                 attempts=1, finished_at=t),
            dict(id="b" * 32, state="running", result=None, progress=0.4, attempts=1, finished_at=None),
            dict(id="c" * 32, state="queued", result=None, progress=0.0, attempts=0, finished_at=None)]
    with engine.begin() as conn:
        for i, row in enumerate(rows):
            conn.execute(table.insert().values(kind="sequence", input_dir=f"/old/{row['id']}",
                                               options=json.dumps({"cameras": ["c0", "c1"]}),
                                               stage=row["state"], error=None,
                                               created_at=t.replace(minute=i), started_at=t, **row))
    engine.dispose()


def test_an_old_database_is_upgraded_on_start_and_keeps_its_jobs(tmp_path):
    """Issue 19: the job table was made with create_all, so a new column broke an existing
    database. Now a database of the previous layout is migrated at start (Alembic)."""
    db = tmp_path / "old.db"
    _old_database(db)
    settings = Settings(db=str(db), data_dir=tmp_path / "data", model_path=small_model_path(),
                        live=False, job_workers=0)
    with ServerThread(settings) as srv:
        jobs = {j["id"]: j for j in srv.client.get("/v1/jobs").json()["jobs"]}
        assert {j: v["state"] for j, v in jobs.items()} == {
            "a" * 32: "done", "b" * 32: "queued", "c" * 32: "queued"}  # b: interrupted, re-queued
        assert jobs["a" * 32]["cameras"] == ["c0", "c1"] and jobs["b" * 32]["attempts"] == 1
        assert srv.client.get(f"/v1/jobs/{'a' * 32}/result").json()["notes"] == ["old"]
    engine = sa.create_engine(f"sqlite:///{db}")
    columns = [c["name"] for c in sa.inspect(engine).get_columns("jobs")]
    assert columns == [*_OLD_COLUMNS, *_NEW_COLUMNS]
    assert current_revision(engine) == HEAD
    engine.dispose()
    # Opening it again is a no-op; a new database is made at the same revision.
    store = JobStore(settings.db_url)
    assert len(store.list()) == 3 and current_revision(store.engine) == HEAD
    store.close()
    fresh = JobStore(f"sqlite:///{tmp_path / 'new.db'}")
    assert current_revision(fresh.engine) == HEAD
    assert [c["name"] for c in sa.inspect(fresh.engine).get_columns("jobs")] == [*_OLD_COLUMNS, *_NEW_COLUMNS]
    fresh.close()
