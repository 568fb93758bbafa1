"""``posecal capture``: run one capture agent; ``posecal router``: a Zenoh router.

Thin: parse arguments, build the Zenoh config with
:func:`capture.zconfig.config_from_args`, run :func:`capture.agent.main`.
Settings not given on the command line come from ``POSECAL_CAPTURE_*``
environment variables, then the defaults of :class:`capture.agent.AgentSettings`.
"""

from __future__ import annotations

import argparse

from . import CliError


def register(subparsers: argparse._SubParsersAction) -> None:
    from capture.zconfig import add_zenoh_arguments

    p = subparsers.add_parser(
        "capture", help="segment one camera and stream silhouettes over Zenoh",
        description="Segment the walker in one camera's frames and publish silhouettes on "
                    "posecal/<rig>/<camera>/silhouette. SPEC: a video file or image folder "
                    "(options after '?': loop=1, sync=index|time, fps=N for folders), "
                    "device:N[,width=W,height=H,fps=F], gst:PIPELINE, "
                    "genicam:CTI[,serial=S,trigger=1] or synthetic:k=v,...")
    p.add_argument("--rig", help="rig name (default: rig0)")
    p.add_argument("--camera", help="camera name (default: c0)")
    p.add_argument("--source", required=True, metavar="SPEC", help="frame source")
    p.add_argument("--fps", type=float, help="replay rate of recorded sources")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--warmup", type=int, metavar="N",
                   help="empty frames to learn the background from (default: 100)")
    p.add_argument("--stats-interval", type=float, metavar="S", help="seconds between stats lines")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_capture)

    r = subparsers.add_parser("router", help="run a Zenoh router (Python session)",
                              description="Route between agents and the service; "
                                          "listens on tcp/127.0.0.1:7447 unless --listen.")
    add_zenoh_arguments(r)
    r.set_defaults(func=run_router, mode="router")


def _settings(args: argparse.Namespace):
    from pydantic import ValidationError

    from capture.agent import AgentSettings
    from capture.segment import SegmentSettings

    given = {name: value for name, value in (
        ("rig", args.rig), ("camera", args.camera), ("source", args.source), ("fps", args.fps),
        ("max_frames", args.max_frames), ("stats_interval_s", args.stats_interval))
        if value is not None}
    try:
        settings = AgentSettings(**given)
        if args.warmup is not None:
            segment = SegmentSettings(**{**settings.segment.model_dump(),
                                         "warmup_frames": args.warmup})
            settings = settings.model_copy(update={"segment": segment})
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise CliError(f"invalid settings: {problems}") from None
    return settings


def _config(args: argparse.Namespace):
    from capture.zconfig import config_from_args

    try:
        return config_from_args(args)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def run_capture(args: argparse.Namespace) -> int:
    import zenoh

    from capture import agent
    from capture.sources import SourceError

    settings = _settings(args)
    conf = _config(args)
    try:
        agent.main(conf, settings)
    except SourceError as exc:
        raise CliError(str(exc)) from None
    except zenoh.ZError as exc:
        raise CliError(f"zenoh: {exc}") from None
    return 0


def run_router(args: argparse.Namespace) -> int:
    import zenoh

    from capture import router

    conf = _config(args)
    try:
        router.main(conf)
    except zenoh.ZError as exc:
        raise CliError(f"zenoh: {exc}") from None
    return 0
