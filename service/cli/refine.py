"""``posecal refine SEQ --out DIR``: silhouettes improved by model feedback (Izo–Grimson §7.1).

Two inputs:

- a sequence folder of PNG silhouettes (``rig.json`` + ``<camera>/NNNNNN.png``):
  no image is left to re-segment, so each silhouette is fused with the model's
  prior (:func:`estimator.prior.refine_silhouette`: holes the model explains
  are filled, blobs away from the body dropped);
- raw video, one file per camera (``SEQ/<camera>.mp4`` etc., ``rig.json``
  optional): background subtraction, estimate, priors, background subtraction
  again with the priors (:func:`capture.refine.refine_cameras`).

The output is a sequence folder (full-frame PNGs, or crops where the input was
crops) plus ``refine.json`` with the walk estimated from the input.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from . import CliError, CliFailure


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "refine",
        help="improve the silhouettes of a sequence folder (PNG silhouettes or raw video) with model feedback",
        description="Estimate the walk, render the model body in the estimated poses and viewpoints, "
        "register it onto each silhouette and use it as a foreground prior (paper section 7.1). "
        "PNG silhouettes are fused with the prior; raw videos (<camera>.mp4) are background-subtracted "
        "again with the prior.",
    )
    p.add_argument("sequence", metavar="SEQ", help="sequence folder (rig.json + <camera>/ PNGs, or <camera>.mp4 videos)")
    p.add_argument("--out", required=True, metavar="DIR", help="output sequence folder")
    p.add_argument("--model", help="appearance model file (default: the cached default model)")
    p.add_argument("--warmup", type=int, default=None,
                   help="videos: empty frames learned by the background model (default: min(100, frames/4))")
    p.set_defaults(func=run)


def _videos(folder: str) -> dict[str, str]:
    from service.intake import list_videos  # what a job accepts, the CLI accepts

    return {cam: str(path) for cam, path in list_videos(folder).items()}


def _has_png_cameras(folder: str) -> bool:
    try:
        with open(os.path.join(folder, "rig.json")) as fh:
            cams = json.load(fh).get("cameras", [])
    except (OSError, ValueError, AttributeError):
        return False
    return bool(cams) and all(os.path.isdir(os.path.join(folder, str(c))) for c in cams)


def run(args: argparse.Namespace) -> int:

    from .model import model_from_arg

    if not os.path.isdir(args.sequence):
        raise CliError(f"{args.sequence} is not a folder")
    if os.path.abspath(args.out) == os.path.abspath(args.sequence):
        raise CliError("--out must differ from SEQ (the input is not overwritten)")
    videos = _videos(args.sequence)
    pngs = _has_png_cameras(args.sequence)
    if not pngs and not videos:
        raise CliError(f"{args.sequence}: neither rig.json with per-camera PNG folders nor <camera>.mp4 videos")
    model = model_from_arg(args.model)
    if pngs:
        return _refine_pngs(args, model)
    return _refine_videos(args, model, videos)


def _refine_pngs(args: argparse.Namespace, model) -> int:
    from capture.refine import refine_sequence
    from estimator.prior import FEEDBACK
    from estimator.render import Renderer
    from estimator.sequence import SequenceError, read_sequence

    try:
        seq = read_sequence(args.sequence)
    except SequenceError as exc:
        raise CliError(str(exc)) from None
    config = FEEDBACK  # priors only from estimates that pass the trust test
    try:
        with Renderer(config.body) as renderer:
            refined = refine_sequence(seq, model, renderer=renderer, config=config)
    except ValueError as exc:  # input that reads but cannot be estimated
        raise CliFailure(f"{args.sequence}: {exc}") from None
    _write(args.out, refined, "silhouettes")
    print(f"wrote {args.out}: {seq.n_frames} frames, {len(seq.cameras)} cameras, "
          f"{refined.changed_pixels} pixels changed")
    return 0


def _refine_videos(args: argparse.Namespace, model, videos: dict[str, str]) -> int:
    import cv2

    from capture.refine import refine_videos
    from capture.segment import default_warmup
    from estimator.prior import FEEDBACK
    from estimator.render import Renderer

    counts, fps = {}, 0.0
    for cam, path in videos.items():
        cap = cv2.VideoCapture(path)
        if not cap.isOpened():
            raise CliError(f"video {path} cannot be opened")
        counts[cam] = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or 0
        fps = fps or float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        cap.release()
    n = min(counts.values())
    warmup = args.warmup if args.warmup is not None else default_warmup(n)
    truth = None
    truth_path = os.path.join(args.sequence, "truth.json")
    if os.path.exists(truth_path):
        with open(truth_path) as fh:
            truth = json.load(fh)
    config = FEEDBACK  # priors only from estimates that pass the trust test
    try:
        with Renderer(config.body) as renderer:
            refined = refine_videos(videos, model, renderer=renderer, warmup=warmup,
                                    fps=fps or 15.0, config=config, truth=truth)
    except ValueError as exc:  # input that reads but cannot be estimated
        raise CliFailure(f"{args.sequence}: {exc}") from None
    _write(args.out, refined, "video")
    print(f"wrote {args.out}: {n} frames (warm-up {warmup}), {len(videos)} cameras")
    for cam, note in sorted(refined.notes.items()):
        print(f"  {cam}: {note}")
    return 0


def _write(out: str, refined, kind: str) -> None:
    from estimator.sequence import write_sequence

    write_sequence(out, refined.sequence)
    _write_summary(out, refined.estimate, kind, refined.n_priors, refined.notes)


def _write_summary(out: str, estimate, kind: str, n_priors: int, notes: dict[str, str] | None = None) -> None:
    from service.exports import write_text

    summary = {"input": kind, "priors": n_priors, "estimate": estimate.to_result(),
               "notes": dict(sorted((notes or {}).items()))}
    write_text(Path(out) / "refine.json", json.dumps(summary))


__all__ = ["register", "run"]
