"""The job store: batch jobs as rows of one SQL table (SQLAlchemy Core).

SQLAlchemy rather than :mod:`sqlite3`: the embedded default is a SQLite file,
but the same code runs against PostgreSQL when ``POSECAL_DB`` is a URL, and the
worker processes open their own engine on the same URL to write progress.

States: ``queued -> running -> done | failed``, and ``cancelled`` from queued or
running. Each claim writes a new token (``claim``) into the row, with the
replica that claimed it (``replica``) and its lease (``heartbeat_at``, renewed
by that replica's runner while the job runs); the worker writes progress, the
result or the failure only while the row is still ``running`` under its own
token (:meth:`JobStore.claimed`), so a cancelled, deleted or re-queued job
tells its worker to stop, and a run whose job was re-queued can never finish
it: each job ends once.

Several replicas may share one database (PostgreSQL): :meth:`JobStore.claim_next`
takes the oldest queued row with ``FOR UPDATE SKIP LOCKED`` (two replicas never
take the same one); a replica that restarts re-queues the jobs it ran itself
(:meth:`JobStore.requeue_owned`), and every replica re-queues the jobs whose
lease expired, their replica dead or cut off (:meth:`JobStore.requeue_expired`).
A job interrupted ``max_attempts`` times fails instead, with the reason.
Leases are measured by the database server's clock (PostgreSQL), so the
replicas' own clocks need not agree.

The schema is versioned (:mod:`service.migrations`, Alembic): opening a store
upgrades its database, a database made by an older version included.
"""

from __future__ import annotations

import json
import logging
import uuid
from collections.abc import Collection
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Engine

__all__ = ["ACTIVE", "STATES", "ClaimedJobs", "JobRow", "JobStore", "JobGone"]

log = logging.getLogger(__name__)

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
    sa.Column("replica", sa.String(64)),  # the replica that claimed the row last (a done job: that finished it)
    sa.Column("heartbeat_at", sa.DateTime(timezone=True)),  # its lease, renewed while the job runs
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
    replica: str | None = None
    heartbeat_at: datetime | None = None


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _utc(value: datetime | None) -> datetime | None:
    # SQLite returns naive datetimes; everything stored is UTC.
    return value.replace(tzinfo=timezone.utc) if value is not None and value.tzinfo is None else value


_ROW_COLUMNS = [c for c in jobs_table.c if c.name != "result"]

# PostgreSQL connections (unless the URL sets them): an unreachable server fails in seconds, and a
# session left idle inside a transaction for 30 s (its process frozen or hung; ours take
# milliseconds) is ended, releasing its row locks, so that the other replicas can re-queue
# that replica's jobs.
_PG_CONNECT = {"connect_timeout": 10, "options": "-c idle_in_transaction_session_timeout=30000"}


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
        elif url.startswith("postgresql"):
            # An unreachable server fails in seconds; a connection the server dropped is replaced.
            kwargs["pool_pre_ping"] = True
            kwargs["connect_args"] = {k: v for k, v in _PG_CONNECT.items() if f"{k}=" not in url}
        self.url = url
        self.engine: Engine = sa.create_engine(url, **kwargs)
        if url.startswith("sqlite"):
            sa.event.listen(self.engine, "connect", _sqlite_pragmas)
        with self.engine.connect():  # the dialect learns the server's version on first connect
            pass
        if not self.engine.dialect.update_returning:  # claims and re-queues are UPDATE ... RETURNING
            raise RuntimeError(f"the job store needs UPDATE ... RETURNING (SQLite >= 3.35, PostgreSQL); "
                               f"{self.engine.dialect.name} here has none (SQLite "
                               f"{getattr(self.engine.dialect.dbapi, 'sqlite_version', '?')})")
        # Leases by the server's clock where there is a server (replicas on several hosts);
        # a SQLite file has one host, whose clock it is.
        self._server_clock = self.engine.dialect.name != "sqlite"
        if migrate:
            from .migrations import upgrade

            upgrade(self.engine)

    def close(self) -> None:
        self.engine.dispose()

    def _clock(self) -> Any:
        """Now, as leases are written and compared: the database server's ``now()``, or this host's."""
        return sa.func.now() if self._server_clock else _now()

    # -- rows -------------------------------------------------------------------
    @staticmethod
    def _row(r: sa.Row) -> JobRow:
        m = r._mapping
        return JobRow(id=m["id"], state=m["state"], kind=m["kind"], input_dir=m["input_dir"],
                      options=json.loads(m["options"] or "{}"), progress=m["progress"],
                      stage=m["stage"], error=m["error"], has_result=bool(m["has_result"]),
                      attempts=m["attempts"], claim=m["claim"], created_at=_utc(m["created_at"]),
                      started_at=_utc(m["started_at"]), finished_at=_utc(m["finished_at"]),
                      replica=m["replica"], heartbeat_at=_utc(m["heartbeat_at"]))

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
    def claim_next(self, replica: str | None = None) -> JobRow | None:
        """Atomically move the oldest queued job to ``running`` under a new claim, held by
        ``replica`` with a fresh lease, and return it (None: nothing queued).

        One ``UPDATE ... WHERE id = (SELECT ... FOR UPDATE SKIP LOCKED)``: on PostgreSQL,
        concurrent claims (other replicas) lock different rows and never wait for each
        other; SQLite ignores the lock clause and runs the statement alone (one writer).
        """
        oldest = (sa.select(jobs_table.c.id).where(jobs_table.c.state == "queued")
                  .order_by(jobs_table.c.created_at).limit(1).with_for_update(skip_locked=True))
        with self.engine.begin() as conn:
            # The row as this statement wrote it: read again afterwards, it may already hold
            # another replica's claim (this one stalled, its lease expired, the job moved on).
            row = conn.execute(
                jobs_table.update().where(jobs_table.c.id == oldest.scalar_subquery(),
                                          jobs_table.c.state == "queued")
                .values(state="running", started_at=_now(), progress=0.0, stage="starting",
                        attempts=jobs_table.c.attempts + 1, claim=uuid.uuid4().hex,
                        replica=replica, heartbeat_at=self._clock())
                .returning(*_ROW_COLUMNS, sa.literal(False).label("has_result"))).first()
        return None if row is None else self._row(row)

    def renew(self, claims: Collection[str]) -> int:
        """Renew the lease of the running jobs held under ``claims`` (one replica's runs);
        returns how many still are (a job cancelled or re-queued meanwhile is not renewed)."""
        if not claims:
            return 0
        with self.engine.begin() as conn:
            done = conn.execute(jobs_table.update()
                                .where(jobs_table.c.state == "running", jobs_table.c.claim.in_(list(claims)))
                                .values(heartbeat_at=self._clock()))
        return done.rowcount

    def requeue_owned(self, replica: str, *, max_attempts: int | None = None) -> list[str]:
        """The jobs ``replica`` left ``running`` go back to the queue: it restarted, so they run
        nowhere. Rows claimed without a replica (a version before replicas) count as its own."""
        mine = sa.or_(jobs_table.c.replica == replica, jobs_table.c.replica.is_(None))
        return self._requeue([mine], max_attempts=max_attempts, stage="requeued after restart")

    def requeue_expired(self, lease_s: float, *, max_attempts: int | None = None) -> list[str]:
        """The running jobs whose lease was not renewed for ``lease_s`` seconds go back to the
        queue: their replica died, hangs or lost the database."""
        expired = sa.or_(jobs_table.c.heartbeat_at.is_(None),
                         jobs_table.c.heartbeat_at < self._clock() - timedelta(seconds=lease_s))
        return self._requeue([expired], max_attempts=max_attempts, stage="requeued: its lease expired")

    def _requeue(self, where: list, *, max_attempts: int | None, stage: str) -> list[str]:
        """Running jobs matching ``where`` go back to ``queued``, their claim withdrawn (the
        interrupted run can no longer write); one that has already run ``max_attempts`` times
        fails instead, with the reason. Returns the ids re-queued.

        Each is one ``UPDATE ... RETURNING``, its rows picked ``FOR UPDATE SKIP LOCKED``: a row
        another transaction holds (its replica renewing it, another replica re-queuing it) is
        left for the next round rather than waited for, and the conditions are checked on
        the row as it is updated.
        """
        running = [jobs_table.c.state == "running", *where]

        def update(*more, **values) -> list[str]:
            picked = sa.select(jobs_table.c.id).where(*running, *more).with_for_update(skip_locked=True)
            return list(conn.execute(jobs_table.update().where(jobs_table.c.id.in_(picked), *running, *more)
                                     .values(**values).returning(jobs_table.c.id)).scalars())

        with self.engine.begin() as conn:
            if max_attempts is not None:
                failed = update(jobs_table.c.attempts >= max_attempts, state="failed", stage="failed",
                                claim=None, finished_at=_now(),
                                error=f"interrupted {max_attempts} times (the service stopped or crashed "
                                      f"while it ran): not retried (max_attempts = {max_attempts})")
                if failed:
                    log.warning("failed %d job(s) interrupted %d times: %s", len(failed), max_attempts,
                                ", ".join(failed))
            return update(state="queued", progress=0.0, stage=stage, started_at=None, claim=None,
                          replica=None, heartbeat_at=None)

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
