"""``posecal estimate SEQ --out result.json``: walking pose and camera viewpoints of a sequence."""

from __future__ import annotations

import argparse
import json
import os

from . import CliError, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "estimate",
        help="estimate walking phase, 3D/2D joints and camera viewpoints of a sequence folder",
        description="Match every silhouette to the appearance model, fit each camera's viewpoint, "
        "decode the walking phase with the cyclic HMM and write the result (format: docs/FORMATS.md). "
        "A recording longer than a window is estimated window by window and cut into segments "
        "where the viewpoints change (the walker turned); the result lists them. "
        "The default appearance model is built and cached on first use (about two minutes).",
    )
    p.add_argument("sequence", metavar="SEQ", help="sequence folder (rig.json + per-camera PNG silhouettes)")
    p.add_argument("--out", required=True, help="result JSON to write")
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from estimator.pipeline import tracks_from_sequence
    from estimator.sequence import SequenceError, read_sequence
    from estimator.mnbp import MNBPConfig
    from estimator.rig import RigConfig
    from estimator.windows import segment_walk

    from .model import model_from_arg

    try:
        rig = RigConfig(height_m=args.height)
    except ValueError as exc:
        raise CliError(f"--height: {exc}") from None
    try:
        sequence = read_sequence(args.sequence)
    except SequenceError as exc:
        raise CliError(str(exc)) from None
    model = model_from_arg(args.model)
    try:
        walk = segment_walk(tracks_from_sequence(sequence), model, length=args.window, hop=args.hop,
                            posture=MNBPConfig() if args.posture == "mnbp" else None, rig=rig)
    except ValueError as exc:
        raise CliError(f"{args.sequence}: {exc}") from None
    result = walk.to_result()
    result["sequence"] = {"fps": sequence.fps, "image_size": list(sequence.image_size), "frames": sequence.n_frames}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, allow_nan=False)
    print(f"wrote {args.out}: {sequence.n_frames} frames, {len(sequence.cameras)} cameras")
    truth = sequence.truth or {}
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
    return 0


def _print_rig(rig: dict, truth: dict) -> None:
    """Each camera's rotation from the reference (its angle, and its error when the folder has a truth)."""
    import numpy as np

    from estimator._selfcal_core import geodesic_deg
    from estimator.rig import rotations_from_viewpoints

    ref = rig["reference"]
    print(f"  rig ({rig['source']}), rotations from {ref}:")
    for name, cam in rig["cameras"].items():
        if name == ref:
            continue
        if cam["rotation"] is None:
            print(f"    {name}: not in the rig")
            continue
        r = np.array(cam["rotation"])
        line = f"    {name}: {geodesic_deg(r, np.eye(3)):6.1f} deg, scale {cam['scale']:.3f}"
        if "focal_px" in cam:
            line += f", focal {cam['focal_px']:.0f} px, {np.linalg.norm(cam['centre_m']):.1f} m from {ref}"
        if name in truth and ref in truth:
            true = rotations_from_viewpoints([(truth[c]["azimuth_deg"], truth[c]["elevation_deg"])
                                              for c in (ref, name)])
            line += f"   off the truth by {geodesic_deg(r, true[1]):.1f} deg"
        print(line)
