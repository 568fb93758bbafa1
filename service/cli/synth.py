"""``posecal synth``: write a synthetic sequence folder with ground truth."""

from __future__ import annotations

import argparse
import os

from . import CliError, positive_int


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="render a synthetic multi-camera walking sequence with ground truth",
        description="Render a walker of random size and style (or driven by a BVH/AMC "
        "recording) seen by N fixed cameras, and write a sequence folder: rig.json, "
        "per-camera PNG silhouettes, truth.json and preview.png.",
    )
    p.add_argument("--out", required=True, help="sequence folder to write")
    p.add_argument("--cameras", type=positive_int, default=2, help="number of cameras (default 2)")
    p.add_argument("--frames", type=positive_int, default=40, help="frames per camera (default 40)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--fps", type=float, default=15.0, help="frame rate (default 15)")
    p.add_argument("--motion", help="drive the body with a .bvh or .amc recording")
    p.add_argument("--azimuths", type=_floats, help="camera azimuths in degrees, e.g. 30,120")
    p.add_argument("--elevations", type=_floats, help="camera elevations in degrees, e.g. 5,20")
    p.add_argument("--size", type=_floats, default=(640.0, 480.0), help="image width,height (default 640,480)")
    p.add_argument("--damage", help="damage the silhouettes as a real segmenter would: salt, blobs, holes, "
                   "cut_limb, shadow, side_shadow, low_wall, second_person, all, or kinds joined by '+' (truth.json "
                   "stays clean)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from estimator.damage import damage_sequence, parse_damage
    from estimator.mocap import read_motion
    from estimator.sequence import write_sequence
    from estimator.synth import SynthSpec, synthesize

    if len(args.size) != 2 or min(args.size) < 16:
        raise CliError(f"--size needs width,height of at least 16 pixels, got {args.size}")
    try:
        spec = SynthSpec(
            n_cameras=args.cameras,
            n_frames=args.frames,
            fps=args.fps,
            seed=args.seed,
            azimuths=args.azimuths,
            elevations=args.elevations,
            image_size=(int(args.size[0]), int(args.size[1])),
        )
        motion = read_motion(args.motion) if args.motion else None
        if args.damage:
            parse_damage(args.damage)
    except (ValueError, OSError) as exc:
        raise CliError(str(exc)) from None
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CliError(f"--out {args.out} exists and is not a folder")
    with tqdm(total=spec.n_cameras * spec.n_frames, desc="rendering", unit="frame", leave=False) as bar:
        try:
            seq = synthesize(spec, motion=motion, progress=lambda done, total: bar.update(done - bar.n))
        except ValueError as exc:
            raise CliError(str(exc)) from None
    if args.damage:
        seq.silhouettes = damage_sequence(seq.silhouettes, args.damage, seed=args.seed, truth=seq.truth)
        seq.truth["damage"] = args.damage
    write_sequence(args.out, seq)
    _write_preview(os.path.join(args.out, "preview.png"), seq)
    truth = seq.truth
    body, style = truth["body"], truth["style"]
    print(f"wrote {args.out}: {len(seq.cameras)} cameras x {seq.n_frames} frames at {seq.fps:g} fps, {seq.image_size[0]}x{seq.image_size[1]}")
    print(f"walker: height {body['height']:.2f} m, girth {body['girth']:.2f}; "
          f"stride {style['stride']:.2f}, leg lift {style['leg_lift']:.2f}, arm swing {style['arm_swing']:.2f}, "
          f"cadence {style['cadence']:.2f} cycles/s" + (f"; motion {truth['motion']}" if truth["motion"] else ""))
    for name, cam in truth["cameras"].items():
        print(f"  {name}: azimuth {cam['azimuth_deg']:6.1f} deg, elevation {cam['elevation_deg']:5.1f} deg, "
              f"distance {cam['distance_m']:.1f} m, focal {cam['focal_px']:.0f} px")
    print(f"phase: {truth['frames'][0]['phase']:.2f} -> {truth['frames'][-1]['phase']:.2f}; preview: {os.path.join(args.out, 'preview.png')}")
    return 0


def _write_preview(path: str, seq) -> None:
    """A contact sheet: up to 8 evenly spaced frames per camera, joints drawn in red."""
    import cv2
    import numpy as np

    rows = []
    picks = np.unique(np.linspace(0, seq.n_frames - 1, min(8, seq.n_frames)).round().astype(int))
    for cam in seq.cameras:
        tiles = []
        for k in picks:
            tile = cv2.cvtColor(seq.silhouettes[cam][k], cv2.COLOR_GRAY2BGR)
            for u, v in seq.truth["frames"][k]["joints2d"][cam]:
                cv2.circle(tile, (int(round(u)), int(round(v))), 3, (0, 0, 255), -1)
            cv2.putText(tile, f"{cam} #{k}", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 200, 255), 2)
            tiles.append(cv2.resize(tile, (tile.shape[1] // 2, tile.shape[0] // 2), interpolation=cv2.INTER_AREA))
        rows.append(np.hstack(tiles))
    cv2.imwrite(path, np.vstack(rows))
