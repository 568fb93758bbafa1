"""What the lifespan owns: store, process pools, Zenoh session, live windows, job runner, Rerun.

:meth:`Runtime.start` builds everything from one :class:`~service.settings.Settings`
and :meth:`Runtime.stop` closes it in reverse order. Jobs this replica
(``replica_id``) left running are re-queued at start (up to ``max_attempts``
runs); a job running at stop is interrupted (its worker is terminated) and
re-queued by the next start, or by another replica once its lease expires
(:class:`~service.runner.JobRunner`). Worker processes die with the service,
even when it is killed (:func:`service.worker.make_pool`). The store's schema is migrated at start.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from pathlib import Path

from .auth import ApiToken
from .jobs import JobStore
from .metrics import Metrics
from .runner import JobRunner
from .settings import Settings
from .worker import PinnedPools, WorkerPool, make_pinned_pools, make_pool

__all__ = ["Runtime", "make_storage", "resolve_model_path", "shutdown_pool"]

log = logging.getLogger(__name__)


def resolve_model_path(settings: Settings) -> Path:
    """The model file to load: ``model_path``, else the cached default (built if missing).

    The file is loaded once here, so a missing, foreign or outdated model fails the
    start with its reason (ValueError) rather than as a broken worker pool.
    """
    from estimator.appearance import load_model

    if settings.model_path is not None:
        if not Path(settings.model_path).is_file():
            raise FileNotFoundError(f"appearance model {settings.model_path} does not exist")
        load_model(settings.model_path)
        return Path(settings.model_path)
    import os

    from .cli.model import default_model_path, get_default_model

    if settings.cache_dir is not None:
        os.environ["POSECAL_CACHE"] = str(settings.cache_dir)
    path = default_model_path()
    if not path.exists():
        log.warning("building the default appearance model in %s (about 2 minutes, once)", path.parent)
        get_default_model(progress=False)
    return path


def make_storage(settings: Settings) -> None:
    """Create the upload folder and, for a SQLite database, its folder (by default both
    under :func:`service.settings.data_home`)."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    if "://" not in settings.db:
        Path(settings.db).expanduser().parent.mkdir(parents=True, exist_ok=True)


def shutdown_pool(pool: WorkerPool | PinnedPools | None) -> None:
    """Stop a pool now: queued calls are cancelled, running workers terminated."""
    if pool is not None:
        pool.terminate()


@dataclass
class Runtime:
    settings: Settings
    model_path: Path
    store: JobStore
    metrics: Metrics
    job_pool: WorkerPool | None
    live_pool: PinnedPools | None
    runner: JobRunner
    feedback_pool: WorkerPool | None = None
    rig_pool: WorkerPool | None = None
    session: object | None = None
    replicas: object | None = None  # service.replicas.Replicas: which replica estimates which rig
    live: object | None = None
    rerun: object | None = None
    api_tokens: tuple[ApiToken, ...] = ()  # accepted REST bearer tokens and scopes (empty: open)

    @classmethod
    async def start(cls, settings: Settings) -> "Runtime":
        api_tokens = settings.api_tokens()  # a bad token file fails the start, with its reason
        make_storage(settings)
        store = await asyncio.to_thread(JobStore, settings.db_url)  # migrates the schema
        # An unreachable database fails the start before the model is built or loaded.
        pools: tuple = (None, None, None, None)
        session = replicas = None
        try:
            model_path = await asyncio.to_thread(resolve_model_path, settings)
            # Feedback priors and the live rig's postures run in processes of their own, so that
            # they never hold up the next window's estimate, at the lowest priority (nice 19):
            # where the cores are short (16 cameras x 30 fps need ~6 cores of priors,
            # docs/SCALING.md) the viewpoints go first and the priors and the rig, newest window
            # first, take what is left. (At nice 5 and 10 they took a quarter of the estimate's
            # cores there: p95 664 -> 453 ms; 2 agents x 15 fps get their priors in time as often.)
            pools = await asyncio.gather(
                asyncio.to_thread(make_pool, settings.job_workers, model_path) if settings.job_workers else _none(),
                asyncio.to_thread(make_pinned_pools, settings.live_workers, model_path) if settings.live else _none(),
                asyncio.to_thread(make_pool, 1, None, renderer=True, nice=_BACKGROUND)  # rendering needs no model
                if settings.live and settings.feedback else _none(),
                asyncio.to_thread(make_pool, 1, None, nice=_BACKGROUND) if settings.live and settings.live_rig else _none())
            job_pool, live_pool, feedback_pool, rig_pool = pools
            # Join the other replicas once the pools are up (the others hand this replica its
            # rigs as soon as it is seen) and before touching jobs: a replica whose id is taken
            # (ReplicaConflict) must not re-queue the running jobs of the one that holds it.
            session, replicas = await asyncio.to_thread(_join, settings)
            requeued = await asyncio.to_thread(store.requeue_owned, settings.replica_id,
                                               max_attempts=settings.max_attempts)
            if requeued:
                log.info("re-queued %d job(s) this replica (%s) left running: %s", len(requeued),
                         settings.replica_id, ", ".join(requeued))
            metrics = Metrics()
            metrics.watch_jobs(store.counts)
            rerun = None
            if settings.rerun_sink is not None:
                from .rerun_log import RerunLog

                rerun = RerunLog(settings.rerun_sink)
                if rerun.uri:
                    log.info("Rerun: connect a viewer with `rerun %s`", rerun.uri)
            runner = JobRunner(store, job_pool, metrics, slots=settings.job_workers,
                               rerun=rerun if settings.rerun_jobs else None, replica=settings.replica_id,
                               lease_s=settings.job_lease_s, max_attempts=settings.max_attempts)
            rt = cls(settings, model_path, store, metrics, job_pool, live_pool, runner,
                     feedback_pool=feedback_pool, rig_pool=rig_pool, session=session, replicas=replicas,
                     rerun=rerun, api_tokens=api_tokens)
            if settings.live:
                from .live import LiveService

                rt.live = LiveService(session, live_pool, settings, metrics, rerun=rerun,
                                      feedback_pool=feedback_pool, rig_pool=rig_pool, replicas=replicas)
        except BaseException:  # a failed start leaves nothing running
            for closing in (replicas, session):
                if closing is not None:
                    closing.close()
            for pool in pools:
                shutdown_pool(pool)
            store.close()
            raise
        return rt

    async def stop(self) -> None:
        if self.replicas is not None:  # leave first: the others take this replica's rigs at once
            await asyncio.to_thread(self.replicas.close)
        await self.runner.close()
        if self.live is not None:
            await asyncio.to_thread(self.live.close)
        if self.session is not None:
            await asyncio.to_thread(self.session.close)
        await asyncio.to_thread(shutdown_pool, self.job_pool)
        await asyncio.to_thread(shutdown_pool, self.live_pool)
        await asyncio.to_thread(shutdown_pool, self.feedback_pool)
        await asyncio.to_thread(shutdown_pool, self.rig_pool)
        if self.rerun is not None:
            await asyncio.to_thread(self.rerun.close)
        self.store.close()


_BACKGROUND = 19  # nice of the priors' and the live rig's processes


async def _none() -> None:
    return None


def _join(settings: Settings) -> tuple[object | None, object | None]:
    """The live path's Zenoh session and this replica's membership among the others
    (None, None without live windows); ReplicaConflict if another live replica has our id."""
    if not settings.live:
        return None, None
    import zenoh

    from capture.zconfig import build_config

    conf = build_config(mode=settings.zenoh_mode, connect=settings.zenoh_connect,
                        listen=settings.zenoh_listen, config_file=settings.zenoh_config,
                        multicast=settings.zenoh_multicast, access=settings.zenoh_access,
                        lease_s=settings.replica_lease_s if settings.replicas else None)
    session = zenoh.open(conf)
    if not settings.replicas:
        return session, None
    from .replicas import Replicas

    try:
        return session, Replicas(session, settings.replica_id, lease_s=settings.replica_lease_s)
    except BaseException:
        session.close()
        raise
