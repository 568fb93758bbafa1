"""``posecal worker``: a replica that only runs batch jobs (no REST, no Zenoh).

It claims jobs from the database the service replicas share and runs them in
its job processes, as ``posecal serve`` does (the same
:class:`~service.runtime.Runtime`, without the live path), holding their
leases; the uploads are read from the shared data directory. SIGTERM or
SIGINT stops it: its running jobs are interrupted and re-queued when it starts
again under the same ``--replica-id``, or by another replica once their lease
expires (docs/SERVICE.md, "Jobs on PostgreSQL, several replicas").
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
from typing import TYPE_CHECKING

from . import CliError
from .serve import add_job_arguments, settings_from_args

if TYPE_CHECKING:
    from service.settings import Settings

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "worker", help="run batch jobs from a shared database (no REST, no Zenoh)",
        description="Claim queued jobs from the job database that the `posecal serve` replicas share "
                    "and run them; the uploads are read from the shared data directory (mounted at "
                    "the same path on every replica). Stops on SIGTERM or SIGINT.")
    add_job_arguments(p, worker=True)
    p.add_argument("--job-lease-s", type=float, metavar="S",
                   help="a running job whose replica has not renewed its lease for S seconds is "
                        "re-queued (default: $POSECAL_JOB_LEASE_S, else 30)")
    p.set_defaults(func=run_worker)


def run_worker(args: argparse.Namespace) -> int:
    from .model import model_from_arg

    # No defaults here: a worker alone on a database in its own data home would run nothing.
    for dest, option, variable in (("db", "--db URL", "POSECAL_DB"),
                                   ("data_dir", "--data-dir DIR", "POSECAL_DATA_DIR")):
        if getattr(args, dest) is None and variable not in os.environ:
            raise CliError(f"give {option} (or {variable}): what the replicas share")
    if args.job_workers is not None and args.job_workers < 1:
        raise CliError(f"--job-workers must be at least 1 for a worker, got {args.job_workers}")
    settings = settings_from_args(args, live=False, rerun=None)
    if settings.model_path is not None:  # a bad --model is a usage error, before anything starts
        model_from_arg(str(settings.model_path))
    return asyncio.run(_serve_jobs(settings))


async def _serve_jobs(settings: "Settings") -> int:
    """Start the runtime (store, job pool, runner), run until SIGTERM or SIGINT, stop it."""
    import sqlalchemy as sa

    from service.runtime import Runtime

    where = sa.engine.make_url(settings.db_url).render_as_string(hide_password=True)
    try:
        runtime = await Runtime.start(settings)
    except (sa.exc.SQLAlchemyError, ModuleNotFoundError) as exc:
        reason = str(getattr(exc, "orig", None) or exc).strip().splitlines()[0]
        if isinstance(exc, ModuleNotFoundError):
            reason += " (PostgreSQL needs the driver: pip install 'posecal[postgres]')"
        raise CliError(f"cannot open the job database {where}: {reason}") from None
    except (OSError, ValueError) as exc:  # the data directory, the model
        raise CliError(str(exc)) from None
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    log.info("worker %s: running jobs from %s with %d process(es), uploads in %s, lease %g s",
             settings.replica_id, where, settings.job_workers, settings.data_dir, settings.job_lease_s)
    try:
        await stop.wait()
    finally:
        log.info("worker %s: stopping (running jobs are interrupted and re-queued)", settings.replica_id)
        await runtime.stop()
    return 0
