"""The job runner: claims queued jobs and runs them in the job process pool.

An asyncio task of the lifespan (``posecal serve``) or of ``posecal worker``.
It polls the store (so jobs queued before a restart, or by another replica on
the same database, are picked up) and is woken at once when a job is
submitted here. At most ``slots`` jobs run at a time; each waits on a pool
future, so the event loop stays free. A job runs under the claim token its
claim wrote (:meth:`JobStore.claim_next`): what a run writes after the job was
re-queued or cancelled is refused.

Leases: every ``lease_s / 3`` seconds the runner renews the lease of the jobs
it runs (from this task, not from the worker's progress reports: a stage may
run long without reporting) and re-queues the jobs of any replica whose lease
expired (:meth:`JobStore.requeue_expired`). Each job a run of this replica
finished is logged as ``job <id> done (replica <name>, attempt <n>)``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import time

from .jobs import JobStore
from .metrics import Metrics
from .worker import run_job

__all__ = ["JobRunner"]

log = logging.getLogger(__name__)


class JobRunner:
    """Run queued jobs with up to ``slots`` at a time as ``replica``, holding their leases.

    With no pool (or no slot) it claims nothing but still re-queues expired leases.
    """

    def __init__(self, store: JobStore, pool: concurrent.futures.Executor | None, metrics: Metrics, *,
                 slots: int, rerun=None, poll_s: float = 1.0, replica: str | None = None,
                 lease_s: float = 30.0, max_attempts: int | None = None) -> None:
        self.store, self.pool, self.metrics, self.rerun = store, pool, metrics, rerun
        self.slots = slots if pool is not None else 0
        self.poll_s, self.replica, self.lease_s, self.max_attempts = poll_s, replica, lease_s, max_attempts
        self.renew_s = lease_s / 3  # a lease survives two missed renewals
        self._wake = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        self._running: set[asyncio.Task] = set()
        self._claims: dict[str, str] = {}  # job id -> the claim its run here holds
        self._task = asyncio.create_task(self._run(), name="job-runner")

    def wake(self) -> None:
        """Tell the runner a job was queued (callable from any thread)."""
        self._loop.call_soon_threadsafe(self._wake.set)

    async def _run(self) -> None:
        next_renewal = 0.0
        while True:
            try:
                if self._loop.time() >= next_renewal:
                    next_renewal = self._loop.time() + self.renew_s
                    await self._keep_leases()
                await self._claim_jobs()
            except Exception as exc:  # the database unreachable for a while: try again at the next poll
                reason = (str(exc).strip().splitlines() or [""])[0]
                log.warning("job runner: the job store failed (%s: %s); retrying", type(exc).__name__, reason,
                            exc_info=log.isEnabledFor(logging.DEBUG))
            self._wake.clear()
            timeout = max(0.0, min(self.poll_s, next_renewal - self._loop.time()))
            try:
                await asyncio.wait_for(self._wake.wait(), timeout=timeout)
            except TimeoutError:
                pass

    async def _keep_leases(self) -> None:
        """Renew this replica's leases, then re-queue the jobs whose lease expired."""
        await asyncio.to_thread(self.store.renew, list(self._claims.values()))
        requeued = await asyncio.to_thread(self.store.requeue_expired, self.lease_s,
                                           max_attempts=self.max_attempts)
        if requeued:
            log.warning("re-queued %d job(s) whose lease expired (their replica stopped renewing it): %s",
                        len(requeued), ", ".join(requeued))

    async def _claim_jobs(self) -> None:
        while len(self._running) < self.slots:
            job = await asyncio.to_thread(self.store.claim_next, self.replica)
            if job is None:
                return
            log.info("job %s claimed (replica %s, attempt %d)", job.id, self.replica, job.attempts)
            self._claims[job.id] = job.claim
            task = asyncio.create_task(self._run_one(job.id, job.kind, job.input_dir, job.options, job.claim))
            self._running.add(task)
            task.add_done_callback(self._running.discard)

    async def _run_one(self, job_id: str, kind: str, input_dir: str, options: dict, claim: str | None) -> None:
        t0 = time.perf_counter()
        call = functools.partial(run_job, job_id, self.store.url, kind, input_dir, options,
                                 want_bundle=self.rerun is not None, claim=claim)
        try:
            # Submitted from a thread: after a worker died, submit starts a new pool.
            future = await asyncio.to_thread(self.pool.submit, call)
            bundles = await asyncio.wrap_future(future)
            if bundles and self.rerun is not None:
                for bundle in bundles:  # one per segment of the recording
                    await asyncio.to_thread(self.rerun.log_window, f"jobs/{job_id}", bundle)
        except asyncio.CancelledError:
            raise  # shutdown: the row stays "running", re-queued when this replica restarts or its lease expires
        except Exception as exc:
            log.exception("job %s crashed", job_id)
            await asyncio.to_thread(self.store.fail, job_id, f"internal error: {type(exc).__name__}: {exc}",
                                    claim=claim)
        finally:
            self._claims.pop(job_id, None)
        row = await asyncio.to_thread(self.store.get, job_id)
        if row is not None:
            self.metrics.jobs_finished.labels(row.state).inc()
            if row.claim != claim:
                log.warning("job %s: re-queued while this run held it (its lease expired); what the run "
                            "wrote since was refused", job_id)
            elif row.state == "done":  # the claim is this run's: this run wrote the result
                log.info("job %s done (replica %s, attempt %d)", job_id, self.replica, row.attempts)
        self.metrics.job_duration.observe(time.perf_counter() - t0)
        self._wake.set()

    async def close(self) -> None:
        tasks = [t for t in (self._task, *self._running) if t is not None]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
