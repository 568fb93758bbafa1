"""Batch jobs with several replicas on one database (issue 21): claims with ``FOR UPDATE SKIP
LOCKED`` on a real PostgreSQL server (started here, :mod:`pg_server`), leases renewed by the
runner and re-queued when they expire, a restarted replica taking back only its own jobs,
and three ``posecal worker`` processes running 50 jobs, one of them killed and one frozen
mid-job: every job done exactly once.

The store-level tests run on SQLite as well. Without PostgreSQL's server binaries or driver
the PostgreSQL tests fail with the reason under CI (``CI`` or ``POSECAL_REQUIRE_PG`` set) and
are skipped elsewhere.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import itertools
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import psutil
import pytest
import sqlalchemy as sa

from conftest_service import small_model_path, wait_for, write_walk
from pg_server import PostgresServer, required, unavailable
from service.jobs import JobGone, JobStore, jobs_table
from service.metrics import Metrics
from service.migrations import current_revision, upgrade
from service.runner import JobRunner
from service.settings import Settings
from test_faults import _gone


@pytest.fixture(scope="module")
def pg():
    reason = unavailable()
    if reason is not None:
        if required():
            pytest.fail(f"PostgreSQL is required here (CI or POSECAL_REQUIRE_PG is set): {reason}")
        pytest.skip(reason)
    server = PostgresServer().start()
    yield server
    server.stop()


_databases = itertools.count()


@pytest.fixture
def pg_url(pg) -> str:
    """A fresh database on the module's server."""
    return pg.create_database(f"test_{os.getpid()}_{next(_databases)}")


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'jobs.db'}"
    return request.getfixturevalue("pg_url")


@pytest.fixture
def store(db_url):
    s = JobStore(db_url)
    yield s
    s.close()


def _jobs(store: JobStore, n: int) -> list[str]:
    return [store.create(kind="sequence", input_dir=f"/in/{i}").id for i in range(n)]


# ----------------------------------------------------------------------------- claims


def test_concurrent_claims_take_each_job_exactly_once(pg_url):
    """Six claimers (own connections, started together) drain 30 queued jobs."""
    first = JobStore(pg_url)
    ids = _jobs(first, 30)
    stores = [JobStore(pg_url, migrate=False) for _ in range(6)]
    start = threading.Barrier(len(stores))
    taken: list[list[str]] = [[] for _ in stores]

    def drain(k: int) -> None:
        start.wait(timeout=30)
        while (job := stores[k].claim_next(f"r{k}")) is not None:
            taken[k].append(job.id)

    threads = [threading.Thread(target=drain, args=(k,)) for k in range(len(stores))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads), "a claimer hung"
    claimed = [j for got in taken for j in got]
    assert sorted(claimed) == sorted(ids), collections.Counter(claimed).most_common(3)
    rows = {r.id: r for r in first.list(limit=100)}
    for k, got in enumerate(taken):
        assert all(rows[j].replica == f"r{k}" and rows[j].attempts == 1 for j in got)
    assert first.counts()["running"] == 30
    for s in (first, *stores):
        s.close()


def test_a_locked_job_is_skipped_not_waited_for(pg_url):
    """While another transaction holds the oldest queued row (a replica in the middle of claiming
    it), a claim takes the next one at once instead of waiting for the lock."""
    store = JobStore(pg_url)
    oldest, second = _jobs(store, 2)
    got: list = []
    with store.engine.connect() as holder:
        holder.begin()
        holder.execute(sa.text("SELECT id FROM jobs WHERE id = :id FOR UPDATE"), {"id": oldest})
        claimer = threading.Thread(target=lambda: got.append(store.claim_next("r1")), daemon=True)
        claimer.start()
        claimer.join(timeout=20)
        waited = claimer.is_alive()
        holder.rollback()
    claimer.join(timeout=20)
    assert not waited, "claim_next waited for the locked row (no SKIP LOCKED)"
    assert got[0].id == second and store.get(oldest).state == "queued"
    assert store.claim_next("r2").id == oldest
    store.close()


# ----------------------------------------------------------------------------- leases


def test_expired_leases_are_requeued_and_the_old_run_cannot_finish(store):
    a, b = _jobs(store, 2)
    run_a, run_b = store.claim_next("r1"), store.claim_next("r2")
    assert (run_a.id, run_a.replica, run_b.id, run_b.replica) == (a, "r1", b, "r2")
    assert run_a.heartbeat_at is not None
    time.sleep(2.5)  # both leases (2 s) ran out; r2 renews its own, r1 (dead) does not
    assert store.renew([run_b.claim]) == 1
    assert store.requeue_expired(2.0, max_attempts=3) == [a]
    row = store.get(a)
    assert (row.state, row.claim, row.replica, row.stage) == ("queued", None, None, "requeued: its lease expired")
    assert store.get(b).state == "running"
    # The interrupted run of a is refused; its next run finishes it, once.
    rerun = store.claim_next("r2")
    assert rerun.id == a and rerun.attempts == 2 and rerun.claim != run_a.claim
    with pytest.raises(JobGone):
        store.claimed(run_a.claim).report(a, 0.9, "estimating")
    assert not store.claimed(run_a.claim).finish(a, {"run": 1})
    assert store.claimed(rerun.claim).finish(a, {"run": 2}) and store.result(a) == {"run": 2}
    assert not store.claimed(rerun.claim).finish(a, {"run": 3})
    assert store.get(a).replica == "r2"  # the replica that finished it
    assert store.renew([run_a.claim, rerun.claim]) == 0  # neither is running any more
    # A job whose lease ran out max_attempts times fails, with the reason.
    time.sleep(2.5)
    assert store.requeue_expired(2.0, max_attempts=1) == []
    row = store.get(b)
    assert row.state == "failed" and "max_attempts = 1" in row.error and row.claim is None
    assert not store.claimed(run_b.claim).finish(b, {"late": True})


def test_a_restarted_replica_requeues_only_its_own_jobs(store):
    a, b, c, d = _jobs(store, 4)
    store.claim_next("r1"), store.claim_next("r2"), store.claim_next()  # c: no replica (an older version)
    assert sorted(store.requeue_owned("r1", max_attempts=3)) == sorted([a, c])
    assert store.get(b).state == "running" and store.get(d).state == "queued"
    assert store.requeue_expired(60.0) == []  # b's lease is fresh
    # A running row of a version before leases (no heartbeat) counts as expired.
    with store.engine.begin() as conn:
        conn.execute(sa.text("UPDATE jobs SET heartbeat_at = NULL WHERE id = :id"), {"id": b})
    assert store.requeue_expired(60.0) == [b]


def test_an_older_database_upgrades_and_its_running_jobs_are_taken_back(db_url):
    """A database at revision 0002 (claims, no replicas) is upgraded; the job it left running
    has no replica and no lease: the first replica to start re-queues it."""
    engine = sa.create_engine(db_url)
    upgrade(engine, "0002")
    t = datetime(2024, 5, 1, tzinfo=timezone.utc)
    with engine.begin() as conn:  # the columns of 0002 only
        for i, state in enumerate(("running", "done")):
            conn.execute(jobs_table.insert().values(id=str(i) * 32, state=state, kind="sequence", input_dir="/x",
                                                    options="{}", progress=0.5, stage=state, attempts=1,
                                                    claim="c", created_at=t, started_at=t))
    engine.dispose()
    store = JobStore(db_url)
    assert current_revision(store.engine) == "0003"
    assert store.get("0" * 32).replica is None and store.get("1" * 32).state == "done"
    assert store.requeue_owned("any-replica", max_attempts=3) == ["0" * 32]
    assert store.get("0" * 32).attempts == 1 and store.get("1" * 32).state == "done"
    store.close()


class _HeldPool(concurrent.futures.Executor):
    """A job pool whose runs never start: each submit returns a future the test resolves (a
    run that reports nothing for as long as the test likes)."""

    def __init__(self) -> None:
        self.futures: list[concurrent.futures.Future] = []

    def submit(self, fn, /, *args, **kwargs) -> concurrent.futures.Future:
        self.futures.append(concurrent.futures.Future())
        return self.futures[-1]


def test_the_runner_holds_the_lease_of_a_silent_job_and_reaps_a_dead_one(store, caplog):
    """The lease is renewed by the runner itself, not by the run's progress reports: a job that
    says nothing for three leases stays with its replica; once that runner is gone, another
    replica's runner re-queues its job when the lease runs out."""
    caplog.set_level(logging.INFO, logger="service.runner")
    lease = 1.5

    async def scenario() -> None:
        pool = _HeldPool()
        mine = JobRunner(store, pool, Metrics(), slots=1, replica="r1", lease_s=lease, poll_s=0.1, max_attempts=3)
        other = JobRunner(store, None, Metrics(), slots=0, replica="r2", lease_s=lease, poll_s=0.1)
        job = store.create(kind="sequence", input_dir="/x").id
        mine.wake()
        await _until(lambda: pool.futures, "the job to be claimed")
        await asyncio.sleep(3 * lease)
        row = store.get(job)
        assert (row.state, row.replica, row.attempts) == ("running", "r1", 1), row
        assert store.claimed(row.claim).finish(job, {"ok": True})  # the run ends: its result is written
        pool.futures[0].set_result(None)
        await _until(lambda: f"job {job} done (replica r1, attempt 1)" in caplog.text, "the finish to be logged")
        # r1 dies while it runs a second job: r2 re-queues it once the lease runs out.
        second = store.create(kind="sequence", input_dir="/y").id
        mine.wake()
        await _until(lambda: len(pool.futures) == 2, "the second job to be claimed")
        await mine.close()
        await _until(lambda: store.get(second).state == "queued", "the dead replica's job to be re-queued",
                     timeout=30)
        assert store.get(second).attempts == 1 and "lease" in store.get(second).stage
        # The row changes as the reaper's transaction commits, a moment before the runner logs it.
        await _until(lambda: "re-queued 1 job(s) whose lease expired" in caplog.text, "the re-queue to be logged")
        await other.close()

    asyncio.run(scenario())


async def _until(predicate, what: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.05)


# ------------------------------------------------------------------------ the command line


def test_worker_and_serve_options(tmp_path, capsys):
    """``posecal worker`` refuses bad arguments and an unreachable database with exit 2 and the
    reason; ``--replica-id`` and ``--job-lease-s`` reach the settings (``posecal serve`` too)."""
    from service.cli import build_parser, main
    from service.cli.serve import settings_from_args
    from service.server import free_port

    common = ["--data-dir", str(tmp_path / "data"), "--model", str(small_model_path())]
    assert main(["worker", *common]) == 2
    assert "--db URL (or POSECAL_DB)" in capsys.readouterr().err
    assert main(["worker", "--db", str(tmp_path / "j.db"), *common, "--job-workers", "0"]) == 2
    assert "--job-workers must be at least 1" in capsys.readouterr().err
    assert main(["worker", "--db", str(tmp_path / "j.db"), *common, "--replica-id", "-bad name"]) == 2
    assert "replica_id" in capsys.readouterr().err
    closed = f"postgresql+psycopg://posecal:secret@127.0.0.1:{free_port()}/posecal"
    assert main(["worker", "--db", closed, *common]) == 2
    err = capsys.readouterr().err
    assert "cannot open the job database" in err and "refused" in err and "secret" not in err
    parser = build_parser()
    worker = settings_from_args(parser.parse_args(["worker", "--db", "x.db", "--replica-id", "w1",
                                                   "--job-lease-s", "5"]), live=False)
    assert (worker.replica_id, worker.job_lease_s, worker.live) == ("w1", 5.0, False)
    serve = settings_from_args(parser.parse_args(["serve", "--replica-id", "a", "--no-live"]))
    assert serve.replica_id == "a" and serve.job_lease_s == 30.0


# ------------------------------------------------------ three worker replicas, 50 jobs, one killed

N_JOBS, LEASE_S, FRAMES = 50, 3, 20
DONE = re.compile(r"job ([0-9a-f]{32}) done \(replica (\S+), attempt (\d+)\)")
CLAIMED = re.compile(r"job ([0-9a-f]{32}) claimed \(replica (\S+), attempt (\d+)\)")
LOST = re.compile(r"job ([0-9a-f]{32}): re-queued while this run held it")


def _worker(name: str, url: str, data: Path, log: Path) -> subprocess.Popen:
    """``posecal worker`` as replica ``name``, in a process group of its own."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYOPENGL_PLATFORM": "egl"}
    cmd = [sys.executable, "-m", "service.cli", "worker", "--db", url, "--data-dir", str(data),
           "--model", str(small_model_path()), "--replica-id", name, "--job-lease-s", str(LEASE_S),
           "--job-workers", "1"]
    with open(log, "ab") as out:
        return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                cwd=data.parent)


def _started(proc: subprocess.Popen, log: Path, name: str) -> bool:
    if proc.poll() is not None:
        raise AssertionError(f"worker {name} exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
    return f"worker {name}: running jobs" in log.read_text()


def _freeze_while_running(proc: subprocess.Popen, name: str, store: JobStore) -> list[str]:
    """Stop replica ``name`` (SIGSTOP to its process group) at a moment it holds running jobs;
    returns their ids, the replica left frozen."""
    def caught() -> list[str]:
        if not any(j.replica == name for j in store.list(state="running")):
            return []
        os.killpg(proc.pid, signal.SIGSTOP)
        held = [j.id for j in store.list(state="running") if j.replica == name]
        if not held:  # it finished in between: let it go on
            os.killpg(proc.pid, signal.SIGCONT)
        return held

    return wait_for(caught, timeout=120, interval=0.02, what=f"replica {name} to run a job")


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        pass


def test_three_worker_replicas_run_every_job_exactly_once(pg_url, tmp_path):
    """Issue 21: 3 ``posecal worker`` replicas on one PostgreSQL database and one shared upload
    directory, 50 jobs. Replica r0 is killed (SIGKILL) while it runs a job, replica r1 is frozen
    (SIGSTOP) while it runs one until another replica has claimed it, then goes on. Every job
    ends done, finished by exactly one run (each runner logs the jobs its own claim finished);
    the killed and frozen replicas' jobs by another replica, at a later attempt; what the
    frozen run writes after it wakes up is refused."""
    store = JobStore(pg_url)
    data, seq = tmp_path / "shared", write_walk(tmp_path / "walk", n_frames=FRAMES, seed=1, image_size=(320, 240))
    names = ("r0", "r1", "r2")
    logs = {n: tmp_path / f"{n}.log" for n in names}
    procs = {n: _worker(n, pg_url, data, logs[n]) for n in names}
    try:
        for n in names:
            wait_for(lambda n=n: _started(procs[n], logs[n], n), timeout=180, interval=0.2, what=f"worker {n}")
        options = {"cameras": ["c0", "c1"], "n_frames": FRAMES, "posture": "model", "height_m": 1.75,
                   "windows": Settings(db=pg_url, data_dir=data).segment_options()}
        ids = []
        for k in range(N_JOBS):  # staged as the REST intake does: a folder per job in the shared directory
            job_id = f"{k:032x}"
            shutil.copytree(seq, data / job_id / "walk")
            ids.append(store.create(kind="sequence", input_dir=str(data / job_id / "walk"), options=options,
                                    job_id=job_id).id)

        # Both while the queue is still long: r1 hangs mid-job (frozen) ...
        frozen = _freeze_while_running(procs["r1"], "r1", store)
        # ... and r0 crashes mid-job: its main process is killed; its pool worker must die with it.
        killed = _freeze_while_running(procs["r0"], "r0", store)
        children = [p.pid for p in psutil.Process(procs["r0"].pid).children(recursive=True)]
        os.kill(procs["r0"].pid, signal.SIGKILL)
        procs["r0"].wait(timeout=30)
        try:
            os.killpg(procs["r0"].pid, signal.SIGCONT)  # what is left of it may run (and see its parent gone)
        except ProcessLookupError:
            pass
        wait_for(lambda: _gone(children), timeout=20, interval=0.1, what="r0's pool workers to die with it")

        # r1 wakes up once another replica has claimed its job (its lease ran out) and goes on with
        # its run, which may now try to write while the other one runs the job.
        wait_for(lambda: all(store.get(j).replica not in (None, "r1") for j in frozen), timeout=120,
                 interval=0.05, what="another replica to claim the frozen replica's job")
        os.killpg(procs["r1"].pid, signal.SIGCONT)

        def all_done() -> bool:
            counts = store.counts()
            assert counts["failed"] == 0, [(j.id, j.error) for j in store.list(state="failed")]
            return counts["done"] == N_JOBS

        wait_for(all_done, timeout=240, interval=0.5, what=f"{N_JOBS} jobs done ({store.counts()})")
        wait_for(lambda: set(frozen) <= set(LOST.findall(logs["r1"].read_text())), timeout=60, interval=0.2,
                 what="r1's woken run to find its job taken")
        for n in ("r1", "r2"):
            children = [p.pid for p in psutil.Process(procs[n].pid).children(recursive=True)]
            procs[n].send_signal(signal.SIGTERM)
            assert procs[n].wait(timeout=60) == 0, logs[n].read_text()[-3000:]
            wait_for(lambda: _gone(children), timeout=20, interval=0.1, what=f"{n}'s pool workers to stop")
    finally:
        for proc in procs.values():
            _kill_group(proc)

    text = {n: logs[n].read_text() for n in names}
    finishes = [(m.group(1), n, int(m.group(3))) for n in names for m in DONE.finditer(text[n])]
    per_job = collections.Counter(j for j, _, _ in finishes)
    assert set(per_job.values()) == {1}, per_job.most_common(3)
    rows = {j: store.get(j) for j in ids}
    # r0 was killed at any moment of its loop: a job its run had finished (the result written by its pool
    # worker) may have lost its log line, written by the main process after it; every other run logs its own.
    unlogged = sorted(set(ids) - set(per_job))
    assert set(per_job) <= set(ids) and not set(unlogged) & set(killed), (unlogged, killed)
    for job_id in unlogged:
        assert (rows[job_id].state, rows[job_id].replica) == ("done", "r0"), (job_id, rows[job_id])
        assert len(store.result(job_id)["frames"]) == FRAMES
    for job_id, replica, attempt in finishes:
        row = rows[job_id]
        assert (row.state, row.replica, row.attempts) == ("done", replica, attempt), (row, replica, attempt)
        assert len(store.result(job_id)["frames"]) == FRAMES
    finished_by = {j: r for j, r, _ in finishes}
    for job_id in killed:
        assert finished_by[job_id] != "r0" and rows[job_id].attempts >= 2, rows[job_id]
    for job_id in frozen:
        assert finished_by[job_id] != "r1" and rows[job_id].attempts >= 2, rows[job_id]
    # Every run was a claim in some replica's log: as many as the job's attempts (r0 may have
    # died between claiming its job and logging the claim).
    claims = collections.Counter(m.group(1) for n in names for m in CLAIMED.finditer(text[n]))
    for job_id, row in rows.items():
        assert row.attempts - (job_id in killed) <= claims[job_id] <= row.attempts, (job_id, claims[job_id], row)
    print(json.dumps({"finished_by": collections.Counter(finished_by.values()), "killed": killed,
                      "frozen": frozen, "attempts": collections.Counter(r.attempts for r in rows.values())}))
    store.close()
