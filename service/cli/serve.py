"""``posecal serve``: the estimator service (REST jobs, live windows from Zenoh, Rerun).

Options given here override ``POSECAL_*`` environment variables, which override
the defaults of :class:`service.settings.Settings`.
"""

from __future__ import annotations

import argparse

from . import CliError, CliFailure


def register(subparsers: argparse._SubParsersAction) -> None:
    from capture.zconfig import add_zenoh_arguments

    p = subparsers.add_parser(
        "serve", help="run the estimator service (REST API, live windows, Rerun)",
        description="Serve the REST API, estimate sliding windows of the silhouettes streamed on "
                    "posecal/*/*/silhouette, publish posecal/<rig>/estimate and log to Rerun. "
                    "Zenoh: the service listens on tcp/127.0.0.1:7447 (where agents connect by "
                    "default) unless --listen is given.")
    p.add_argument("--host", default="127.0.0.1", help="HTTP bind address (default: 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="HTTP port (default: 8000)")
    p.add_argument("--rerun", metavar="SINK",
                   help="save:PATH (.rrd file) | serve[:PORT] (gRPC on 127.0.0.1) | connect[:URL]")
    add_job_arguments(p)
    p.add_argument("--window", type=int, metavar="N", help="frames per live window (default: 20)")
    p.add_argument("--hop", type=int, metavar="N", help="frames between windows (default: 10)")
    p.add_argument("--no-live", action="store_true", help="REST jobs only: no Zenoh subscription")
    p.add_argument("--no-feedback", action="store_true",
                   help="do not send silhouette priors back to the capture agents (section 7.1)")
    p.add_argument("--api-token-file", metavar="PATH",
                   help="bearer tokens, one per line ('#' comments), 'TOKEN' or 'TOKEN SCOPE' (read, "
                        "submit, admin): every /v1 route then needs 'Authorization: Bearer <token>' "
                        "(docs/SERVICE.md, Access)")
    p.add_argument("--insecure", action="store_true",
                   help="allow --host beyond loopback without API tokens (anyone who reaches the port "
                        "can list, submit and delete jobs)")
    p.add_argument("--no-live-rig", action="store_true",
                   help="do not calibrate the live rigs from postures (GET /v1/rigs/{rig}/calibration); "
                        "saves a low-priority process")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_serve)


def add_job_arguments(p: argparse.ArgumentParser, *, worker: bool = False) -> None:
    """The options of the job store and its runner, shared by ``posecal serve`` and ``posecal
    worker`` (which has no defaults for the database and the uploads: the replicas' shared ones)."""
    p.add_argument("--db", metavar="PATH|URL", help="SQLite file or SQLAlchemy URL, e.g. "
                   "postgresql+psycopg://user@host/posecal " + (
                       "(required, or $POSECAL_DB)" if worker else "(default: posecal.db in $POSECAL_DATA, "
                       "else $XDG_DATA_HOME/posecal, else ~/.local/share/posecal)"))
    p.add_argument("--data-dir", metavar="DIR", help="where job uploads are kept, shared by the replicas "
                   "at the same path " + ("(required, or $POSECAL_DATA_DIR)" if worker else
                                          "(default: jobs/ in that same directory)"))
    p.add_argument("--model", metavar="PATH", help="appearance model (default: the cached default model)")
    p.add_argument("--job-workers", type=int, metavar="N", help="job processes (default: 1)")
    p.add_argument("--replica-id", metavar="NAME", help="this replica's name among those sharing the "
                   "database: the owner of the jobs it runs, stable across restarts (default: "
                   "$POSECAL_REPLICA_ID, else the host name)")


# Settings given by options of the same value: (setting, option's dest); options a parser lacks are skipped.
_OPTIONS = (("rerun", "rerun"), ("db", "db"), ("data_dir", "data_dir"), ("model_path", "model"),
            ("window_length", "window"), ("window_hop", "hop"), ("job_workers", "job_workers"),
            ("replica_id", "replica_id"), ("job_lease_s", "job_lease_s"), ("zenoh_connect", "connect"),
            ("zenoh_listen", "listen"), ("zenoh_config", "zenoh_config"), ("api_token_file", "api_token_file"))


def settings_from_args(args: argparse.Namespace, **fixed):
    """:class:`~service.settings.Settings` from the command line (and the environment), with
    ``fixed`` settings on top (``posecal worker``: no live path)."""
    from pydantic import ValidationError

    from service.settings import Settings

    given = {name: value for name, dest in _OPTIONS if (value := getattr(args, dest, None)) is not None}
    if getattr(args, "no_live", False):
        given["live"] = False
    if getattr(args, "no_feedback", False):
        given["feedback"] = False
    if getattr(args, "no_live_rig", False):
        given["live_rig"] = False
    if getattr(args, "mode", "peer") != "peer":
        given["zenoh_mode"] = args.mode
    if getattr(args, "multicast", False):
        given["zenoh_multicast"] = True
    given.update(fixed)
    try:
        return Settings(**given)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise CliError(f"invalid settings: {problems}") from None


def check_exposure(host: str, settings, insecure: bool) -> None:
    """Refuse (exit 2) to listen beyond loopback without API tokens, unless ``insecure``."""
    import ipaddress

    try:
        tokens = settings.api_tokens()
    except ValueError as exc:  # an unreadable or empty token file
        raise CliError(str(exc)) from None
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: not known to be loopback
        loopback = False
    if not loopback and not tokens and not insecure:
        raise CliError(f"--host {host} listens beyond this machine without API tokens: give "
                       "--api-token-file (or POSECAL_API_TOKEN), or --insecure to do it anyway")


def run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.app import create_app
    from service.settings import get_settings

    from .model import model_from_arg

    settings = settings_from_args(args)
    check_exposure(args.host, settings, args.insecure)
    if settings.model_path is not None:  # a bad --model is a CLI error (exit 2), before uvicorn starts
        model_from_arg(str(settings.model_path))
    app = create_app()
    app.dependency_overrides[get_settings] = lambda: settings
    try:
        uvicorn.run(app, host=args.host, port=args.port, log_level="info")
    except SystemExit as exc:  # uvicorn exits 3 when it cannot start (a port taken): 1 here, with the reason
        if exc.code in (0, None):
            raise
        raise CliFailure(f"the server did not start on {args.host}:{args.port} (the log above says why)") from None
    return 0
