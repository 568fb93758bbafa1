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

from scipy.spatial.transform import Rotation

from estimator.joints import JOINT_INDEX, JOINT_NAMES, N_JOINTS
from estimator.perspective import perspective_refine
from estimator.rig import RigConfig, stature_scale
from estimator.selfcal import RIGID_LINKS, self_calibrate

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
    p.add_argument("--method", choices=("refined", "closed-form"), default="refined",
                   help="'refined' (default): the closed form, then the bundle adjustment with the "
                        "upright-walker priors (adds euler_xyz_std_deg and scale_std), then pinhole "
                        "cameras when --image-size is given; 'closed-form': the paper's closed form "
                        "alone (section 4.2), as published")
    p.add_argument("--image-size", metavar="W,H",
                   help="the cameras' image size in pixels (principal point at its centre): adds "
                        "pinhole cameras after the refined path (rotation, focal length, centre per "
                        "camera), exact where the scaled orthographic model is not")
    p.add_argument("--height", type=float, default=1.75, metavar="M",
                   help="with --image-size: the walker's stature in metres, the scale of the camera "
                        "centres and the 3D joints (default 1.75)")
    p.add_argument("--varying-scale", action="store_true",
                   help="camera scales change over time: one U per frame and a bundle "
                        "adjustment (section 4.3)")
    p.add_argument("--refine", action="store_true",
                   help="the bundle adjustment without the upright priors (unless --upright); "
                        "the default --method refined has both")
    p.add_argument("--upright", action="store_true", help="with --refine: the upright-walker priors")
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
    size = _image_size(args.image_size)
    if args.upright and not args.refine:
        raise CliError("--upright needs --refine (the default --method refined has it)")
    closed = args.method == "closed-form" and not args.refine
    if size is not None and (closed or args.varying_scale):
        raise CliError("--image-size needs the refined path with fixed scales (not --method closed-form, "
                       "not --varying-scale)")
    try:
        rig = RigConfig(height_m=args.height)
        result = self_calibrate(tracks, scales="varying" if args.varying_scale else "fixed",
                                refine=None if closed else True,
                                upright=args.upright if args.refine else not closed)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if not result:
        raise CliError(f"self-calibration failed: {result.reason}")
    out = result_to_json(result, cameras)
    if size is not None:
        out = _with_pinhole(out, result, tracks, cameras, size, rig)
    text = json.dumps(out, indent=1, allow_nan=False)
    if args.out is None:
        sys.stdout.write(text + "\n")
    else:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


def _image_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise CliError(f"--image-size: expected W,H in pixels, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise CliError(f"--image-size: expected positive W,H, got {text!r}")
    return w, h


def _with_pinhole(doc: dict, result, tracks: np.ndarray, cameras: list[str], size: tuple[int, int],
                  rig: RigConfig) -> dict:
    """The calibration with pinhole cameras (:func:`estimator.perspective.perspective_refine`)
    after the refined scaled-orthographic one: rotations, focal lengths and centres per
    camera, 3D joints in metres at the stature (:func:`estimator.rig.stature_scale`)."""
    pin = perspective_refine(tracks, np.tile(np.array(size, float), (len(cameras), 1)), result.rotations,
                             result.scales, list(RIGID_LINKS))
    k = stature_scale(pin.joints3d, rig.height_m)
    if not np.isfinite(k):
        raise CliError("the pinhole adjustment gave a body without length")
    euler = Rotation.from_matrix(pin.rotations).as_euler("xyz", degrees=True)
    doc = dict(doc, method=result.method + "+pinhole",
               joints3d_frame=f"camera {cameras[0]!r}: x right, y down, z forward (its optical axis); metres at a "
                              f"stature of {rig.height_m} m; origin at that camera's centre",
               frames=[{"index": i, "joints3d": _nullable(j * k)} for i, j in enumerate(pin.joints3d)],
               reprojection_rms_px=round(pin.rmse_px, 3),
               scaled_orthographic={name: {"rotation": doc["cameras"][name]["rotation"],
                                           "scale": doc["cameras"][name]["scale"]} for name in cameras[1:]},
               reference_focal_px=float(pin.focal_px[0]))
    cams = {}
    for c, name in enumerate(cameras[1:], 1):
        cams[name] = {"rotation": pin.rotations[c].tolist(), "euler_xyz_deg": euler[c].tolist(),
                      "scale": float(pin.scales[c]), "focal_px": float(pin.focal_px[c]),
                      "centre_m": (pin.centres[c] * k).tolist()}
    doc["cameras"] = cams
    return doc
