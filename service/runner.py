"""The job runner: claims queued jobs and runs them in the job process pool.

An asyncio task of the lifespan. It polls the store (so jobs queued before a
restart, or by another API instance on the same database, are picked up) and
is woken at once when a job is submitted. At most ``job_workers`` jobs run at a
time; each waits on a pool future, so the event loop stays free. A job runs
under the claim token its claim wrote (:meth:`JobStore.claim_next`): what a
run writes after the job was re-queued or cancelled is refused.
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
    """Run queued jobs with up to ``slots`` at a time."""

    def __init__(self, store: JobStore, pool: concurrent.futures.Executor | None, metrics: Metrics, *,
                 slots: int, rerun=None, poll_s: float = 1.0) -> None:
        self.store, self.pool, self.metrics, self.rerun = store, pool, metrics, rerun
        self.slots, self.poll_s = slots, poll_s
        self._wake = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        self._running: set[asyncio.Task] = set()
        self._task = asyncio.create_task(self._run(), name="job-runner") if pool is not None and slots > 0 else None

    def wake(self) -> None:
        """Tell the runner a job was queued (callable from any thread)."""
        self._loop.call_soon_threadsafe(self._wake.set)

    async def _run(self) -> None:
        while True:
            while len(self._running) < self.slots:
                job = await asyncio.to_thread(self.store.claim_next)
                if job is None:
                    break
                task = asyncio.create_task(self._run_one(job.id, job.kind, job.input_dir, job.options,
                                                         job.claim))
                self._running.add(task)
                task.add_done_callback(self._running.discard)
            self._wake.clear()
            try:
                await asyncio.wait_for(self._wake.wait(), timeout=self.poll_s)
            except TimeoutError:
                pass

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
            raise  # shutdown: the row stays "running" and is re-queued on the next start
        except Exception as exc:
            log.exception("job %s crashed", job_id)
            await asyncio.to_thread(self.store.fail, job_id, f"internal error: {type(exc).__name__}: {exc}",
                                    claim=claim)
        row = await asyncio.to_thread(self.store.get, job_id)
        if row is not None:
            self.metrics.jobs_finished.labels(row.state).inc()
        self.metrics.job_duration.observe(time.perf_counter() - t0)
        self._wake.set()

    async def close(self) -> None:
        tasks = [t for t in (self._task, *self._running) if t is not None]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
