"""``posecal sync VIDEOS``: time offsets of unsynchronized recordings, from the walk itself."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from . import CliError, CliFailure, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sync",
        help="estimate the time offsets of cameras that were not started together (phones, webcams)",
        description="Each camera's walk is estimated alone (gait phase over its own frames); the phases, "
                    "the same in every view at the same instant, give each camera's offset to the reference "
                    "camera to a fraction of a frame, and the walker's changes of pace tell whole gait "
                    "cycles apart (docs/SYNC.md). Frame rates may differ. Prints the offsets as JSON "
                    "(docs/FORMATS.md, \"sync\"). posecal estimate and REST jobs on videos do this themselves "
                    "(--sync auto, the default). Exit codes: 0 done (an offset the walk cannot settle is "
                    "marked ambiguous, with a warning), 1 a camera could not be synchronised, 2 bad arguments "
                    "or input.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="a folder of videos, one per camera (<camera>.mp4, .avi, .mkv, .mov, .webm, .m4v), or "
                        "two or more sequence folders (rig.json + per-camera PNG silhouettes), each with its own "
                        "fps")
    p.add_argument("--reference", metavar="CAMERA", help="the camera whose clock the offsets are on (default: the "
                                                           "one that shows the walker longest)")
    p.add_argument("--max-offset", type=float, default=2.5, metavar="S",
                   help="largest offset searched either way, in seconds (default 2.5)")
    p.add_argument("--hint", action="append", default=[], metavar="CAMERA=SECONDS",
                   help="a rough offset known otherwise (a clap, the files' times; the reference's time of the "
                        "camera's first frame, to within 0.2 s): that camera is searched within 0.2 s of it, which settles "
                        "whole gait cycles when the walker's pace is too even to (repeatable)")
    p.add_argument("--warmup", type=positive_int, metavar="N",
                   help="videos: background frames at the start (default: a quarter, at most 100)")
    p.add_argument("--model", help="appearance model file (default: the cached default model)")
    p.add_argument("--out", default="-", help="JSON to write (default: standard output)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from estimator.sync import SyncConfig, camera_clock, synchronize

    from .model import model_from_arg

    try:
        config = SyncConfig(max_offset_s=args.max_offset, reference=args.reference, hints=_hints(args.hint))
    except ValueError as exc:
        raise CliError(f"--max-offset: {exc}") from None
    tracks, rates = _inputs(args)
    if len(tracks) < 2:
        raise CliError(f"{' '.join(args.inputs)}: {len(tracks)} camera(s); synchronisation needs two or more")
    for flag, names in (("--reference", [args.reference] if args.reference else []), ("--hint", config.hints or {})):
        unknown = [n for n in names if n not in tracks]
        if unknown:
            raise CliError(f"{flag} {', '.join(unknown)}: no such camera (cameras: {', '.join(tracks)})")
    model = model_from_arg(args.model)
    clocks = {}
    for name in tqdm(tracks, desc="phase per camera", unit="camera", file=sys.stderr, disable=None):
        try:
            clocks[name] = camera_clock(tracks[name], model, rates[name])
        except ValueError as exc:  # no walker in that camera
            raise CliFailure(f"camera {name}: {exc}") from None
    try:
        result = synchronize(clocks, config)
    except ValueError as exc:
        raise CliFailure(str(exc)) from None
    text = json.dumps(result.to_dict(), indent=1)
    if args.out == "-":
        print(text)
    else:
        from service.exports import write_text

        write_text(Path(args.out), text + "\n")
    for c, off in result.offsets_s.items():
        flag = "  AMBIGUOUS" if result.ambiguous[c] and c != result.reference else ""
        print(f"  {c}: {off:+.4f} s ({off * result.fps[c]:+.2f} frames at {result.fps[c]:g} fps){flag}",
              file=sys.stderr)
    for note in result.notes:
        print(f"warning: {note}", file=sys.stderr)
    unsynced = [c for c, off in result.offsets_s.items() if off != off]  # NaN
    if unsynced:
        raise CliFailure(f"camera(s) {', '.join(unsynced)} could not be synchronised (see the notes)")
    return 0


def _hints(items: list[str]) -> dict[str, float] | None:
    """``CAMERA=SECONDS`` items as a dict (CliError for a malformed one)."""
    hints = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            hints[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not name.strip():
            raise CliError(f"--hint {item!r}: expected CAMERA=SECONDS, e.g. c1=-0.8")
    return hints or None


def _inputs(args: argparse.Namespace):
    """Per camera its track (unpadded) and frame rate, from a video folder or sequence folders."""
    from estimator.pipeline import tracks_from_sequence
    from estimator.sequence import SequenceError, read_sequence

    from .estimate import _videos

    if len(args.inputs) == 1:
        videos = _videos(args.inputs[0])
        if not videos:
            raise CliError(f"{args.inputs[0]}: not a folder of videos (for sequence folders give two or more)")
        from service.worker import video_tracks

        with tqdm(total=100, desc="segment", unit="%", file=sys.stderr, disable=None,
                  bar_format="{l_bar}{bar}| {n:.0f}/100 [{elapsed}<{remaining}]") as bar:
            try:
                tracks, rates, _ = video_tracks(Path(args.inputs[0]), warmup=args.warmup,
                                                report=lambda f, _: bar.update(100 * f - bar.n))
            except ValueError as exc:
                raise CliError(str(exc)) from None
        return tracks, rates
    tracks, rates = {}, {}
    for path in args.inputs:
        try:
            seq = read_sequence(path)
        except SequenceError as exc:
            raise CliError(str(exc)) from None
        for name, track in tracks_from_sequence(seq).items():
            if name in tracks:
                raise CliError(f"camera {name} is in more than one input folder")
            tracks[name], rates[name] = track, seq.fps
    return tracks, rates
