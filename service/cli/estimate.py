"""``posecal estimate SEQ --out result.json``: walking pose and camera viewpoints of a sequence."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import CliError, CliFailure, export_formats, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "estimate",
        help="estimate walking phase, 3D/2D joints and camera viewpoints of a sequence folder",
        description="Match every silhouette to the appearance model, fit each camera's viewpoint, "
        "decode the walking phase with the cyclic HMM and write the result (format: docs/FORMATS.md). "
        "A recording longer than a window is estimated window by window and cut into segments "
        "where the viewpoints change (the walker turned); the result lists them. "
        "The default appearance model is built and cached on first use (about two minutes). "
        "Exit codes: 0 done, 1 the estimate or an export could not be done, 2 bad arguments or input.",
    )
    p.add_argument("sequence", metavar="SEQ", help="sequence folder (rig.json + per-camera PNG silhouettes), "
                   "or a folder of videos, one per camera (<camera>.mp4, .avi, .mkv, .mov, .webm, .m4v; "
                   "synchronised from the walk, --sync): the walker is separated from the background first, learned "
                   "from the video, or <camera>.background.png (.jpg), an image of the empty scene beside "
                   "the video, where there is one (needed when the walker stays in the same place in "
                   "the image for most of the video; the result's notes say when)")
    p.add_argument("--warmup", type=positive_int, metavar="N",
                   help="videos: background frames at the start (default: a quarter, at most 100)")
    p.add_argument("--sync", choices=("auto", "off"), default="auto",
                   help="videos: 'auto' (default) finds each video's time offset from the walk and pairs "
                        "frames by time (cameras not started together, different frame rates; the offsets "
                        "are in the result's sequence.sync; frames paired by index are kept when they fit "
                        "as well); 'off' pairs frames by index (a hardware-synchronised rig)")
    p.add_argument("--feedback", choices=("on", "off"), default="on",
                   help="videos: 'on' (default) segments each video again with the model rendered from the "
                        "first estimate as a foreground prior (Izo-Grimson §7.1; cameras whose estimate is not "
                        "trusted get none) and estimates again: about twice the time, rig rotations 7.1 -> 6.2 "
                        "deg median on walkers composited into real footage (docs/ROBUSTNESS.md); 'off' keeps "
                        "the first estimate. Not with --keypoints")
    p.add_argument("--out", default="-", help="result JSON to write (default: standard output, the summary "
                                              "then goes to standard error)")
    p.add_argument("--model", help="appearance model file (default: the cached default model)")
    p.add_argument("--window", type=positive_int, default=20,
                   help="frames per window (default 20, about one gait cycle at 15 Hz)")
    p.add_argument("--hop", type=positive_int, default=10, help="frames between window starts (default 10)")
    p.add_argument("--posture", choices=("mnbp", "model"), default="mnbp",
                   help="frames[].joints2d: 'mnbp' (default) = the person's 2D posture measured on each "
                        "silhouette (Wang-Leow §3; model_joints2d keeps the model's placement); "
                        "'model' = the gait model placed on the silhouette (faster)")
    p.add_argument("--height", type=float, default=1.75, metavar="M",
                   help="the walker's stature in metres (default 1.75): the scale of the person's posture "
                        "(frames[].person_joints3d) and body segment lengths (body); silhouettes carry no "
                        "absolute scale")
    p.add_argument("--keypoints", metavar="PATH",
                   help="a detector's 2D keypoints of the same recording (OpenPose / Pose2Sim folders, MMPose or "
                        "MediaPipe files, as posecal selfcal reads them; frame numbers = the recording's frame "
                        "indices, for videos each video's own, put on the common timeline as its frames are; "
                        "cameras matched by name): the rig and the person's posture come from them instead of "
                        "from the postures measured on the silhouettes, which are then not measured")
    p.add_argument("--rounds", type=int, default=1, metavar="N",
                   help="rounds of posture and calibration (Wang-Leow §5; default 1): each further round "
                        "measures the 3D posture on all views at once with the calibrated cameras and "
                        "calibrates again (about 4 s per round for 2 cameras x 30 frames; it has not improved "
                        "the rig on our evaluations yet, docs/POSTURE.md)")
    e = p.add_argument_group("exports (docs/FORMATS.md, \"Exports\"); written after the result")
    e.add_argument("--export-calibration", metavar="PATH.toml|.yaml|.json",
                   help="the self-calibrated pinhole rig (the reference camera's frame, metres) as a Pose2Sim / "
                        "anipose calibration TOML or OpenCV's YAML / JSON, by the suffix; needs metric cameras "
                        "(full-frame silhouettes, rig.source self-calibration)")
    e.add_argument("--export-trc", metavar="PATH.trc", help="the 3D joints of every frame as an OpenSim TRC (Y up)")
    e.add_argument("--export-bvh", metavar="PATH.bvh", help="the 3D joints as a BVH skeleton (Y up, metres)")
    e.add_argument("--export-csv", metavar="PATH.csv",
                   help="the 3D joints as CSV: frame, time, <joint>_x/_y/_z (person frame, z up, metres)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from estimator.pipeline import tracks_from_sequence
    from estimator.sequence import SequenceError, read_sequence
    from estimator.sync import index_frames
    from estimator.mnbp import MNBPConfig
    from estimator.rig import RigConfig
    from estimator.windows import segment_walk

    from .model import model_from_arg

    try:
        rig = RigConfig(height_m=args.height, rounds=args.rounds)
    except ValueError as exc:  # --height or --rounds
        raise CliError(str(exc).replace("height_m", "--height").replace("rounds", "--rounds", 1)) from None
    exports = export_formats(args)
    videos = _videos(args.sequence)
    keypoints = None
    if args.keypoints is not None:
        if args.rounds != 1:
            raise CliError("--rounds refines the postures measured on the silhouettes; not with --keypoints")
        keypoints = _read_keypoints(args.keypoints)
        rig = RigConfig.for_keypoints(height_m=args.height)
    sequence = None
    if not videos:
        try:
            sequence = read_sequence(args.sequence)
        except SequenceError as exc:
            raise CliError(str(exc)) from None
    model = model_from_arg(args.model)
    with tqdm(total=100, desc="estimate", unit="%", file=sys.stderr, disable=None,
              bar_format="{l_bar}{bar}| {n:.0f}/100 [{elapsed}<{remaining}]") as bar:
        def progress(fraction: float) -> None:
            bar.update(100 * fraction - bar.n)

        try:
            # a detector's keypoints give the postures and the rig in place of the silhouettes
            feedback = bool(videos) and args.feedback == "on" and keypoints is None
            # progress: segmentation, estimate, then with feedback the second segmentation and estimate
            spans = [0.0, 0.3, 0.55, 0.7, 1.0] if feedback else [0.0, 0.5, 1.0, 1.0, 1.0] if videos else [0, 0, 1, 1, 1]
            if videos:
                tracks, info, decoding, timeline, first = _video_tracks(args, videos, model,
                                                                        lambda f: progress(spans[1] * f))
            else:
                tracks = tracks_from_sequence(sequence)
                timeline = index_frames({c: sequence.n_frames for c in tracks})
            per_camera = None if keypoints is None else _keypoints_on(keypoints, timeline)

            def estimate(tracks, start: float, stop: float):
                return segment_walk(tracks, model, length=args.window, hop=args.hop,
                                    posture=MNBPConfig() if args.posture == "mnbp" and keypoints is None else None,
                                    rig=rig, keypoints=per_camera,
                                    progress=lambda f: progress(start + (stop - start) * f))

            walk = estimate(tracks, spans[1], spans[2])
            fed = None
            if feedback:
                from service.worker import feedback_pass

                walk, fed, _ = feedback_pass(first, model, walk, lambda tracks: estimate(tracks, spans[3], spans[4]),
                                             progress=lambda f: progress(spans[2] + (spans[3] - spans[2]) * f))
                progress(1.0)
        except ValueError as exc:  # input that reads but cannot be estimated (e.g. no walker)
            raise CliFailure(f"{args.sequence}: {exc}") from None
    result = walk.to_result()
    if fed is not None:  # the worker module (slow to import) is loaded already on this path
        from service.worker import add_feedback

        add_feedback(result, fed)
    if videos:
        from service.worker import _mark_decoding

        result["sequence"] = info
        if "sync" in info:
            result["sync"] = info.pop("sync")
        _mark_decoding(result, decoding)
        shape = (info["frames"], len(tracks), None)
    else:
        result["sequence"] = {"fps": sequence.fps, "image_size": list(sequence.image_size),
                              "frames": sequence.n_frames}
        shape = (sequence.n_frames, len(sequence.cameras), sequence.truth)
    text = json.dumps(result, allow_nan=False)  # before anything is written: never half a result
    if args.out == "-":
        sys.stdout.write(text + "\n")
        with contextlib.redirect_stdout(sys.stderr):
            _summary(result, shape, "standard output")
    else:
        from service.exports import write_text

        write_text(Path(args.out), text)
        _summary(result, shape, args.out)
    _export(result, exports)
    return 0


def _read_keypoints(path: str):
    """The keypoints of ``--keypoints`` (:func:`service.keypoints_io.read_keypoints`); CliError if unreadable."""
    from service.keypoints_io import KeypointError, read_keypoints

    try:
        return read_keypoints([Path(path)])
    except KeypointError as exc:
        raise CliError(f"--keypoints: {exc}") from None


def _keypoints_on(kp, timeline: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per recording camera, its keypoints on the recording's timeline
    (:func:`service.keypoints_io.keypoints_on_timeline`); CliError when no camera or no frame matches."""
    from service.keypoints_io import KeypointError, keypoints_on_timeline

    try:
        return keypoints_on_timeline(kp, timeline)
    except KeypointError as exc:
        raise CliError(f"--keypoints: {exc}") from None


def _export(result: dict, exports: dict[str, tuple[Path, str]]) -> None:
    """Write the exports of the result (:func:`service.exports.export_result`); one the result cannot
    give (no metric cameras, a joint never placed) fails the command (exit 1) once the others are written."""
    from service.exports import export_result, write_text

    failed = []
    for flag, (path, fmt) in exports.items():
        try:
            write_text(path, export_result(result, fmt, path.name))
        except ValueError as exc:
            failed.append(f"{flag} {path}: {exc}")
    if failed:
        raise CliFailure("; ".join(failed))


def _videos(path: str) -> dict[Path, int]:
    """The videos of a folder of one video per camera, with the frame count each one's header gives
    (0: none); empty for a sequence folder or anything else. Each must open and decode a frame:
    refused now (exit 2), not after the others' segmentation."""
    from service.intake import UploadError, list_videos, probe_video

    folder = Path(path)
    if not folder.is_dir() or (folder / "rig.json").exists():
        return {}
    try:
        return {video: probe_video(video, video.name, None)[1] for video in list_videos(folder).values()}
    except UploadError as exc:
        raise CliError(f"{path}: {exc}") from None


def _video_tracks(args: argparse.Namespace, videos: dict[Path, int], model, progress):
    """Each video's silhouettes (background subtraction, as REST jobs do) as camera tracks on one
    timeline (``--sync``), the input's ``sequence`` summary (with the ``sync`` block), each
    camera's decoded/announced frame counts, its own frame at each frame of the timeline, and
    what a feedback pass needs of the first (:class:`service.worker.FirstPass`)."""
    from service.worker import DamagedVideo, FirstPass, sync_shifted, sync_videos, video_tracks

    try:
        tracks, rates, info = video_tracks(Path(args.sequence), warmup=args.warmup,
                                           report=lambda f, _: progress(0.9 * f),
                                           options={"windows": {"length": args.window},
                                                    "header_frames": {p.stem: n for p, n in videos.items()}})
    except DamagedVideo as exc:
        raise CliError(f"{args.sequence}: {exc}") from None
    left_out = {c: d["left_out"] for c, d in info["decoding"].items() if "left_out" in d}
    for reason in left_out.values():  # the others go on; the result's notes say so too
        print(f"posecal estimate: warning: {reason}; left out, estimated from the other cameras", file=sys.stderr)
    try:
        tracks, fps, sync, timeline = sync_videos(tracks, rates, model, args.sync)
    except ValueError as exc:  # a camera without the walker
        raise CliFailure(f"{args.sequence}: synchronising the videos: {exc}") from None
    progress(1.0)
    frames = max(len(t.silhouettes) for t in tracks.values())
    size = next(iter(info["sizes"].values()))
    summary = {"fps": fps, "image_size": list(size), "frames": frames,
               "videos": [p.name for p in videos if p.stem not in left_out], "warmup": info["warmup"],
               **({"left_out": left_out} if left_out else {}), **({"sync": sync} if sync is not None else {})}
    first = FirstPass(Path(args.sequence), info["segmentations"], info["warmup"], sync_shifted(sync))
    return tracks, summary, info["decoding"], timeline, first


def _summary(result: dict, shape: tuple[int, int, dict | None], where: str) -> None:
    """What was written, from ``shape`` = (frames, cameras, truth or None), and each camera's viewpoint
    and rotation (against the truth when the folder has one)."""
    n_frames, n_cameras, truth = shape
    print(f"wrote {where}: {n_frames} frames, {n_cameras} cameras")
    truth = truth or {}
    for name, cam in result["cameras"].items():
        if cam["azimuth_deg"] is None:
            print(f"  {name}: no silhouette, no viewpoint")
            continue
        line = f"  {name}: azimuth {cam['azimuth_deg']:6.1f} deg, elevation {cam['elevation_deg']:5.1f} deg (spread {cam['spread_deg']:.1f}, flip: {cam['flip']})"
        if name in truth.get("cameras", {}):
            t = truth["cameras"][name]
            line += f"   truth {t['azimuth_deg']:6.1f}, {t['elevation_deg']:5.1f}"
        print(line)
    if result.get("rig"):
        _print_rig(result["rig"], truth.get("cameras", {}))
    if len(result["segments"]) > 1:
        print(f"  the viewpoints changed: {len(result['segments'])} segments (cameras above: the longest)")
        for seg in result["segments"]:
            views = ", ".join(f"{n} {c['azimuth_deg']:.1f}" for n, c in seg.get("cameras", {}).items()
                              if c["azimuth_deg"] is not None)
            print(f"    frames {seg['first_index']}-{seg['last_index']}: {views or seg.get('error')}")


def _print_rig(rig: dict, truth: dict) -> None:
    """Each camera's rotation from the reference (its angle, and its error when the folder has a truth)."""
    import numpy as np

    from estimator._selfcal_core import geodesic_deg
    from estimator.rig import rotations_from_viewpoints

    ref = rig["reference"]
    if len(rig["cameras"]) < 2:
        print(f"  rig: one camera ({ref}), no rotations to give")
        return
    print(f"  rig ({rig['source']}), rotations from {ref}:")
    for name, cam in rig["cameras"].items():
        if name == ref:
            continue
        if cam["rotation"] is None:
            print(f"    {name}: not in the rig")
            continue
        r = np.array(cam["rotation"])
        line = f"    {name}: {geodesic_deg(r, np.eye(3)):6.1f} deg, " + (
            "from its viewpoint only" if cam["scale"] is None else f"scale {cam['scale']:.3f}")
        if "focal_px" in cam:
            line += f", focal {cam['focal_px']:.0f} px, {np.linalg.norm(cam['centre_m']):.1f} m from {ref}"
        if name in truth and ref in truth:
            true = rotations_from_viewpoints([(truth[c]["azimuth_deg"], truth[c]["elevation_deg"])
                                              for c in (ref, name)])
            line += f"   off the truth by {geodesic_deg(r, true[1]):.1f} deg"
        print(line)
