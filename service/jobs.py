"""The job store: batch jobs as rows of one SQL table (SQLAlchemy Core).

SQLAlchemy rather than :mod:`sqlite3`: the embedded default is a SQLite file,
but the same code runs against PostgreSQL when ``POSECAL_DB`` is a URL, and the
worker processes open their own engine on the same URL to write progress.

States: ``queued -> running -> done | failed``, and ``cancelled`` from queued or
running. :meth:`JobStore.requeue_interrupted` puts jobs left ``running`` by a
crash or restart back in the queue (a job interrupted ``max_attempts`` times
fails instead, with the reason). Each claim writes a new token (``claim``)
into the row; the worker writes progress, the result or the failure only
while the row is still ``running`` under its own token
(:meth:`JobStore.claimed`), so a cancelled, deleted or re-queued job tells its
worker to stop, and a worker orphaned by a crashed service cannot finish a
job the next service has re-queued.

The schema is versioned (:mod:`service.migrations`, Alembic): opening a store
upgrades its database, a database made by an older version included.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Engine

__all__ = ["ACTIVE", "STATES", "ClaimedJobs", "JobRow", "JobStore", "JobGone"]

STATES = ("queued", "running", "done", "failed", "cancelled")
ACTIVE = ("queued", "running")

_meta = sa.MetaData()
jobs_table = sa.Table(
    "jobs", _meta,
    sa.Column("id", sa.String(32), primary_key=True),
    sa.Column("state", sa.String(16), nullable=False, index=True),
    sa.Column("kind", sa.String(16), nullable=False),  # "sequence" | "videos"
    sa.Column("input_dir", sa.Text, nullable=False),
    sa.Column("options", sa.Text, nullable=False, default="{}"),
    sa.Column("progress", sa.Float, nullable=False, default=0.0),
    sa.Column("stage", sa.String(64), nullable=False, default=""),
    sa.Column("error", sa.Text),
    sa.Column("result", sa.Text),
    sa.Column("attempts", sa.Integer, nullable=False, default=0),
    sa.Column("claim", sa.String(32)),  # the token of the run that owns the row (None: nobody)
    sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    sa.Column("started_at", sa.DateTime(timezone=True)),
    sa.Column("finished_at", sa.DateTime(timezone=True)),
)


class JobGone(Exception):
    """The job is no longer running (cancelled or deleted): stop working on it."""


@dataclass(frozen=True)
class JobRow:
    """One stored job (a storage row; the API answers with :mod:`service.schemas`)."""

    id: str
    state: str
    kind: str
    input_dir: str
    options: dict[str, Any]
    progress: float
    stage: str
    error: str | None
    has_result: bool
    attempts: int
    claim: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _utc(value: datetime | None) -> datetime | None:
    # SQLite returns naive datetimes; everything stored is UTC.
    return value.replace(tzinfo=timezone.utc) if value is not None and value.tzinfo is None else value


_ROW_COLUMNS = [c for c in jobs_table.c if c.name != "result"]


class JobStore:
    """Create, claim, update and query jobs. Thread-safe (one engine, short transactions).

    ``migrate`` brings the database's schema up to date (the service does; the
    worker processes, which open the store after it, need not).
    """

    def __init__(self, url: str, *, migrate: bool = True) -> None:
        kwargs: dict[str, Any] = {}
        if url.startswith("sqlite"):
            # Several processes write one file: wait for the lock instead of failing.
            kwargs["connect_args"] = {"timeout": 30, "check_same_thread": False}
        self.url = url
        self.engine: Engine = sa.create_engine(url, **kwargs)
        if url.startswith("sqlite"):
            sa.event.listen(self.engine, "connect", _sqlite_pragmas)
        if migrate:
            from .migrations import upgrade

            upgrade(self.engine)

    def close(self) -> None:
        self.engine.dispose()

    # -- rows -------------------------------------------------------------------
    @staticmethod
    def _row(r: sa.Row) -> JobRow:
        m = r._mapping
        return JobRow(id=m["id"], state=m["state"], kind=m["kind"], input_dir=m["input_dir"],
                      options=json.loads(m["options"] or "{}"), progress=m["progress"],
                      stage=m["stage"], error=m["error"], has_result=bool(m["has_result"]),
                      attempts=m["attempts"], claim=m["claim"], created_at=_utc(m["created_at"]),
                      started_at=_utc(m["started_at"]), finished_at=_utc(m["finished_at"]))

    def _select(self):
        return sa.select(*_ROW_COLUMNS, (jobs_table.c.result.is_not(None)).label("has_result"))

    def create(self, *, kind: str, input_dir: str, options: dict[str, Any] | None = None,
               job_id: str | None = None) -> JobRow:
        job_id = job_id or uuid.uuid4().hex
        with self.engine.begin() as conn:
            conn.execute(jobs_table.insert().values(
                id=job_id, state="queued", kind=kind, input_dir=input_dir,
                options=json.dumps(options or {}), progress=0.0, stage="queued", attempts=0,
                created_at=_now()))
        return self.get(job_id)  # type: ignore[return-value]

    def get(self, job_id: str) -> JobRow | None:
        with self.engine.connect() as conn:
            r = conn.execute(self._select().where(jobs_table.c.id == job_id)).first()
        return None if r is None else self._row(r)

    def list(self, *, state: str | None = None, limit: int = 100, offset: int = 0) -> list[JobRow]:
        q = self._select().order_by(jobs_table.c.created_at.desc()).limit(limit).offset(offset)
        if state is not None:
            q = q.where(jobs_table.c.state == state)
        with self.engine.connect() as conn:
            return [self._row(r) for r in conn.execute(q)]

    def counts(self) -> dict[str, int]:
        """Number of jobs per state (every state present, 0 if none)."""
        q = sa.select(jobs_table.c.state, sa.func.count()).group_by(jobs_table.c.state)
        with self.engine.connect() as conn:
            found = dict(conn.execute(q).all())
        return {s: int(found.get(s, 0)) for s in STATES}

    def result(self, job_id: str) -> dict | None:
        with self.engine.connect() as conn:
            text = conn.execute(sa.select(jobs_table.c.result).where(jobs_table.c.id == job_id)).scalar()
        return None if text is None else json.loads(text)

    # -- transitions ------------------------------------------------------------------
    def claim_next(self) -> JobRow | None:
        """Atomically move the oldest queued job to ``running`` and return it."""
        with self.engine.begin() as conn:
            while True:
                job_id = conn.execute(
                    sa.select(jobs_table.c.id).where(jobs_table.c.state == "queued")
                    .order_by(jobs_table.c.created_at).limit(1)).scalar()
                if job_id is None:
                    return None
                done = conn.execute(
                    jobs_table.update().where(jobs_table.c.id == job_id, jobs_table.c.state == "queued")
                    .values(state="running", started_at=_now(), progress=0.0, stage="starting",
                            attempts=jobs_table.c.attempts + 1, claim=uuid.uuid4().hex))
                if done.rowcount == 1:
                    break
        return self.get(job_id)

    def requeue_interrupted(self, *, max_attempts: int | None = None) -> list[str]:
        """Jobs left ``running`` (the service stopped mid-job) go back to ``queued``, their
        claim withdrawn; one that has already run ``max_attempts`` times fails instead,
        with the reason. Returns the ids re-queued."""
        running = jobs_table.c.state == "running"
        with self.engine.begin() as conn:
            if max_attempts is not None:
                conn.execute(jobs_table.update().where(running, jobs_table.c.attempts >= max_attempts)
                             .values(state="failed", stage="failed", claim=None, finished_at=_now(),
                                     error=f"interrupted {max_attempts} times (the service stopped or "
                                           f"crashed while it ran): not retried (max_attempts = "
                                           f"{max_attempts})"))
            ids = list(conn.execute(sa.select(jobs_table.c.id).where(running)).scalars())
            if ids:
                conn.execute(jobs_table.update().where(jobs_table.c.id.in_(ids))
                             .values(state="queued", progress=0.0, stage="requeued after restart",
                                     started_at=None, claim=None))
        return ids

    def claimed(self, claim: str | None) -> "ClaimedJobs":
        """This store as the run holding ``claim`` writes to it (None: any run, as before claims)."""
        return ClaimedJobs(self, claim)

    def report(self, job_id: str, progress: float, stage: str, *, claim: str | None = None) -> None:
        """Progress of a running job; raises :class:`JobGone` if it is no longer running
        (or, with ``claim``, no longer held under that claim)."""
        with self.engine.begin() as conn:
            done = conn.execute(
                jobs_table.update().where(*self._owned(job_id, claim))
                .values(progress=float(min(max(progress, 0.0), 1.0)), stage=stage))
        if done.rowcount != 1:
            raise JobGone(job_id)

    def finish(self, job_id: str, result: dict, *, claim: str | None = None) -> bool:
        """Store the result of a running job; False if it was cancelled, deleted or re-queued meanwhile."""
        return self._end(job_id, claim, state="done", result=json.dumps(result), progress=1.0, stage="done")

    def fail(self, job_id: str, error: str, *, claim: str | None = None) -> bool:
        return self._end(job_id, claim, state="failed", error=error, stage="failed")

    @staticmethod
    def _owned(job_id: str, claim: str | None) -> list:
        where = [jobs_table.c.id == job_id, jobs_table.c.state == "running"]
        if claim is not None:
            where.append(jobs_table.c.claim == claim)
        return where

    def _end(self, job_id: str, claim: str | None, **values: Any) -> bool:
        with self.engine.begin() as conn:
            done = conn.execute(jobs_table.update().where(*self._owned(job_id, claim))
                                .values(finished_at=_now(), **values))
        return done.rowcount == 1

    def cancel(self, job_id: str) -> JobRow | None:
        """Cancel a queued or running job (no-op for finished ones); None if unknown."""
        with self.engine.begin() as conn:
            conn.execute(jobs_table.update()
                         .where(jobs_table.c.id == job_id, jobs_table.c.state.in_(ACTIVE))
                         .values(state="cancelled", stage="cancelled", finished_at=_now()))
        return self.get(job_id)

    def delete(self, job_id: str) -> JobRow | None:
        """Remove the row; returns what it was (None if unknown)."""
        row = self.get(job_id)
        if row is not None:
            with self.engine.begin() as conn:
                conn.execute(jobs_table.delete().where(jobs_table.c.id == job_id))
        return row


class ClaimedJobs:
    """A :class:`JobStore` as one run of a job writes to it: every write names the run's claim,
    and is refused once the job was cancelled, deleted or re-queued (another run holds it)."""

    def __init__(self, store: JobStore, claim: str | None) -> None:
        self.store, self.claim = store, claim

    def report(self, job_id: str, progress: float, stage: str) -> None:
        self.store.report(job_id, progress, stage, claim=self.claim)

    def finish(self, job_id: str, result: dict) -> bool:
        return self.store.finish(job_id, result, claim=self.claim)

    def fail(self, job_id: str, error: str) -> bool:
        return self.store.fail(job_id, error, claim=self.claim)


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")  # readers never block the writer
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()
