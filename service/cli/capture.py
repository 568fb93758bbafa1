"""``posecal capture``: run one capture agent; ``posecal router``: a Zenoh router.

Thin: parse arguments, build the Zenoh config with
:func:`capture.zconfig.config_from_args` (and the Rerun view for ``--rerun``),
run :func:`capture.agent.main`.
Settings not given on the command line come from ``POSECAL_CAPTURE_*``
environment variables, then the defaults of :class:`capture.agent.AgentSettings`.
"""

from __future__ import annotations

import argparse
import logging

from . import CliError, CliFailure, positive_int

log = logging.getLogger(__name__)


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
    p.add_argument("--background", choices=("bootstrap", "warmup"),
                   help="how the background is learned: 'bootstrap' (default) = temporal median "
                        "of frames sampled over the first seconds of a file (live cameras: of "
                        "the first --warmup frames, preferring still pixels), the scene need "
                        "not be empty; 'warmup' = the paper's running average over the first "
                        "--warmup frames, which must be empty")
    p.add_argument("--background-image", metavar="FILE",
                   help="an image of the empty scene, the source's frame size: the background, where the "
                        "walker stays in the same place in the view (a treadmill, a walk straight at the "
                        "camera), which a background learned from the frames would hold")
    p.add_argument("--warmup", type=int, metavar="N",
                   help="start-up frames to learn the background from on live cameras, or "
                        "with --background warmup (default: 100)")
    p.add_argument("--stats-interval", type=float, metavar="S", help="seconds between stats lines")
    p.add_argument("--rerun", metavar="SINK",
                   help="show the camera in Rerun: raw frame, background model and silhouette "
                        "side by side (capture/<camera>/...): save:PATH, serve[:PORT] or "
                        "connect[:URL] (default: off)")
    p.add_argument("--rerun-every", type=positive_int, metavar="K",
                   help="log every K-th frame to Rerun (default: 10)")
    p.add_argument("--keypoints", metavar="PATH",
                   help="a pose detector's 2D keypoints of the same recording, sent with each frame's "
                        "silhouette so that the service calibrates the live rig from them (OpenPose / "
                        "Pose2Sim folders, MMPose or MediaPipe files, as posecal selfcal reads them; "
                        "this camera's by --camera; frame numbers = the source's frame indices)")
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

    def given(*pairs: tuple[str, object]) -> dict[str, object]:
        return {name: value for name, value in pairs if value is not None}

    agent = given(("rig", args.rig), ("camera", args.camera), ("source", args.source),
                  ("fps", args.fps), ("max_frames", args.max_frames),
                  ("stats_interval_s", args.stats_interval), ("rerun", args.rerun),
                  ("rerun_every", args.rerun_every), ("background_image", args.background_image))
    segment = given(("warmup_frames", args.warmup), ("background", args.background))
    try:
        settings = AgentSettings(**agent)
        if segment:
            merged = SegmentSettings(**{**settings.segment.model_dump(), **segment})
            settings = settings.model_copy(update={"segment": merged})
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


def _view(spec: str | None):
    """The Rerun log for ``--rerun`` (None when off); imported only when asked for."""
    from service.settings import parse_rerun_sink

    try:
        sink = parse_rerun_sink(spec)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if sink is None:
        return None
    from service.rerun_log import RerunLog

    view = RerunLog(sink)
    if view.uri:
        log.info("Rerun: connect a viewer with `rerun %s`", view.uri)
    return view


def _keypoints(path: str | None, camera: str):
    """``--keypoints``: this camera's joints per frame (:func:`service.keypoints_io.camera_keypoints`)."""
    if path is None:
        return None
    from pathlib import Path

    from service.keypoints_io import KeypointError, camera_keypoints, read_keypoints

    try:
        found = camera_keypoints(read_keypoints([Path(path)]), camera)
    except KeypointError as exc:
        raise CliError(f"--keypoints: {exc}") from None
    log.info("keypoints of %s on %d frames (%d-%d) from %s", camera, len(found), min(found, default=0),
             max(found, default=0), path)
    return found


def run_capture(args: argparse.Namespace) -> int:
    import zenoh

    from capture import agent
    from capture.sources import SourceError

    settings = _settings(args)
    conf = _config(args)
    keypoints = _keypoints(args.keypoints, settings.camera)
    view = _view(settings.rerun)
    try:
        agent.main(conf, settings, view=view, keypoints=keypoints)
    except SourceError as exc:
        raise CliError(str(exc)) from None
    except zenoh.ZError as exc:  # the configuration parsed: the session could not be run
        raise CliFailure(f"zenoh: {exc}") from None
    finally:
        if view is not None:
            view.close()
    return 0


def run_router(args: argparse.Namespace) -> int:
    import zenoh

    from capture import router

    conf = _config(args)
    try:
        router.main(conf)
    except zenoh.ZError as exc:  # the configuration parsed: the router could not be run
        raise CliFailure(f"zenoh: {exc}") from None
    return 0
