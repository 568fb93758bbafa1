"""``posecal selfcal TRACKS.json --out result.json``: camera self-calibration.

Reads 2D joint tracks of one walker in two or more views (docs/FORMATS.md,
"Self-calibration"), runs :func:`estimator.selfcal.self_calibrate` and
writes the rotation and scale of every camera relative to the first plus the
metric 3D joints per frame.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from estimator.joints import JOINT_INDEX, JOINT_NAMES, N_JOINTS
from estimator.selfcal import self_calibrate

from . import CliError

__all__ = ["load_tracks", "register", "result_to_json"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "selfcal",
        help="self-calibrate cameras from 2D joint tracks (Wang-Leow section 4)",
        description="Relative rotation and scale of two or more scaled orthographic cameras, "
        "and metric 3D joints, from 2D joint tracks of one walker (formats: docs/FORMATS.md).",
    )
    p.add_argument("tracks", type=Path, help="tracks JSON: {joint_names, cameras: {name: frames}}")
    p.add_argument("--out", type=Path, default=None, help="result JSON (default: stdout)")
    p.add_argument("--varying-scale", action="store_true",
                   help="camera scales change over time: one U per frame and a bundle "
                        "adjustment (section 4.3)")
    p.add_argument("--refine", action="store_true",
                   help="finish the closed form with the bundle adjustment (adds each "
                        "angle's posterior standard deviation, euler_xyz_std_deg, and scale_std; "
                        "--varying-scale always refines)")
    p.add_argument("--upright", action="store_true",
                   help="with --refine: the walker is upright with free arms (right angles "
                        "inside the trunk and shoulders as soft priors)")
    p.set_defaults(func=run)


def _point(value: Any, where: str) -> tuple[float, float]:
    if value is None:
        return (math.nan, math.nan)
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise CliError(f"{where}: expected [u, v] or null, got {value!r}")
    out = []
    for v in value:
        if v is None:
            return (math.nan, math.nan)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise CliError(f"{where}: coordinates must be numbers, got {v!r}")
        out.append(float(v))
    if not all(math.isfinite(v) for v in out):
        return (math.nan, math.nan)
    return out[0], out[1]


def load_tracks(doc: Any) -> tuple[list[str], np.ndarray]:
    """Parse a tracks document into camera names and an array (C, T, 13, 2), NaN = missing."""
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), dict):
        raise CliError('tracks must be a JSON object with "cameras": {name: [frames]}')
    names = doc.get("joint_names", list(JOINT_NAMES))
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise CliError('"joint_names" must be a list of strings')
    unknown = [n for n in names if n not in JOINT_INDEX]
    if unknown:
        raise CliError(f"unknown joint names {unknown}; expected names from {list(JOINT_NAMES)}")
    if len(set(names)) != len(names):
        raise CliError('"joint_names" has duplicates')
    cols = [JOINT_INDEX[n] for n in names]
    cams = doc["cameras"]
    if len(cams) < 2:
        raise CliError(f"need at least two cameras, got {len(cams)}")
    n_frames = {name: len(fr) if isinstance(fr, list) else -1 for name, fr in cams.items()}
    if any(n < 0 for n in n_frames.values()):
        raise CliError("each camera must map to a list of frames")
    if len(set(n_frames.values())) != 1:
        raise CliError(f"cameras have different frame counts: {n_frames}")
    t = next(iter(n_frames.values()))
    if t < 2:
        raise CliError(f"need at least two frames, got {t}")
    out = np.full((len(cams), t, N_JOINTS, 2), np.nan)
    for c, (cam, frames) in enumerate(cams.items()):
        for f, frame in enumerate(frames):
            if frame is None:
                continue
            if not isinstance(frame, list) or len(frame) != len(names):
                raise CliError(f"camera {cam!r} frame {f}: expected {len(names)} joints "
                               f"(one per joint_names entry), got "
                               f"{len(frame) if isinstance(frame, list) else type(frame).__name__}")
            for k, value in enumerate(frame):
                out[c, f, cols[k]] = _point(value, f"camera {cam!r} frame {f} joint {names[k]!r}")
    return list(cams), out


def _nullable(a: np.ndarray) -> list:
    return [None if not np.isfinite(p).all() else [float(v) for v in p] for p in a]


def result_to_json(result, cameras: list[str]) -> dict:
    """The calibration document of docs/FORMATS.md for a successful :class:`SelfCalibration`."""
    euler = result.euler_xyz_deg
    doc: dict[str, Any] = {
        "joint_names": list(JOINT_NAMES),
        "method": result.method,
        "reference_camera": cameras[0],
        "cameras": {
            name: {
                "rotation": result.rotations[c].tolist(),
                "euler_xyz_deg": euler[c].tolist(),
                "scale": float(result.scales[c]),
            }
            for c, name in enumerate(cameras) if c > 0
        },
        "reflection_confidence": result.reflection_confidence,
        "joints3d_frame": f"camera {cameras[0]!r}: x = image u, y = image v, z = viewing "
                          "direction; its pixels; origin at each frame's joint centroid",
        "frames": [{"index": i, "joints3d": _nullable(j)} for i, j in enumerate(result.joints3d)],
    }
    std = result.euler_xyz_std_deg
    for c, name in enumerate(cameras):
        if c == 0:
            continue
        cam = doc["cameras"][name]
        if std is not None:  # posterior standard deviations (bundle adjustment only)
            cam["euler_xyz_std_deg"] = _nullable(std[c:c + 1])[0]
        if result.scale_std is not None:  # null: the tracks do not determine it
            cam["scale_std"] = float(result.scale_std[c]) if np.isfinite(result.scale_std[c]) else None
        if result.frame_scales is not None:
            cam["frame_scales"] = result.frame_scales[:, c].tolist()
    return doc


def run(args: argparse.Namespace) -> int:
    try:
        doc = json.loads(Path(args.tracks).read_text())
    except FileNotFoundError:
        raise CliError(f"no such file: {args.tracks}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CliError(f"cannot read {args.tracks}: {exc}") from None
    cameras, tracks = load_tracks(doc)
    try:
        if args.upright and not args.refine:
            raise CliError("--upright needs --refine")
        result = self_calibrate(tracks, scales="varying" if args.varying_scale else "fixed",
                                refine=True if args.refine else None, upright=args.upright)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if not result:
        raise CliError(f"self-calibration failed: {result.reason}")
    text = json.dumps(result_to_json(result, cameras), indent=1)
    if args.out is None:
        sys.stdout.write(text + "\n")
    else:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0
