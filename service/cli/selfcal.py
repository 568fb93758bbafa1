"""``posecal selfcal INPUT --out result.json``: camera self-calibration.

Reads 2D joint tracks of one walker in two or more views (docs/FORMATS.md,
"Self-calibration"), or the keypoints of OpenPose, MMPose / RTMPose or
MediaPipe (:mod:`service.keypoints_io`), runs
:func:`estimator.selfcal.self_calibrate` and writes the rotation and scale of
every camera relative to the first plus the metric 3D joints per frame; with
``--image-size``, pinhole cameras, and on request the rig as a Pose2Sim /
anipose calibration TOML or an OpenCV YAML / JSON, and the joints as an OpenSim
TRC, a BVH or a CSV (:mod:`service.exports`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from scipy.spatial.transform import Rotation

from estimator.joints import JOINT_INDEX, JOINT_NAMES, N_JOINTS
from estimator.keypoints import SKELETONS
from estimator.epipolar import refine_from_starts
from estimator.perspective import KEYPOINT_SETTINGS, WEAK_PERSPECTIVE, PerspectiveConfig
from estimator.pinhole import floor_frame, image_height, triangulate
from estimator.rig import RigConfig, stature_scale
from estimator.selfcal import RIGID_LINKS, named_note, self_calibrate

from ..exports import bvh_text, csv_text, write_calibration, write_text, write_trc
from ..keypoints_io import KeypointError, Keypoints, match_cameras, read_keypoints, video_sizes
from . import CliError, CliFailure, export_formats, positive_int

__all__ = ["load_tracks", "register", "result_to_json"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "selfcal",
        help="self-calibrate cameras from 2D joint tracks (Wang-Leow section 4)",
        description="Relative rotation and scale of two or more scaled orthographic cameras, "
        "and metric 3D joints, from 2D joint tracks of one walker or from OpenPose, MMPose or MediaPipe "
        "keypoints; with --image-size pinhole cameras, a Pose2Sim / anipose calibration TOML or an OpenCV "
        "YAML / JSON, and the 3D joints as an OpenSim TRC, a BVH or a CSV (formats: docs/FORMATS.md). Exit "
        "codes: 0 done, 1 the calibration could not be done or is unreliable, 2 bad arguments or input.",
    )
    p.add_argument("tracks", type=Path, nargs="+", metavar="INPUT",
                   help="tracks JSON ({joint_names, cameras: {name: frames}}); or keypoints: a folder of "
                        "OpenPose <cam>_json folders (also under pose/, as Pose2Sim lays them out), a folder "
                        "of (or several) per-camera MMPose / RTMPose prediction or MediaPipe JSON files")
    p.add_argument("--out", type=Path, default=None, help="result JSON (default: stdout)")
    p.add_argument("--method", choices=("refined", "closed-form"), default="refined",
                   help="'refined' (default): the closed form, then the bundle adjustment with the "
                        "upright-walker priors (adds rotvec_covariance_rad2, euler_xyz_std_deg and "
                        "scale_std); with --image-size the closed form, then pinhole cameras adjusted from "
                        "it and from an epipolar start (the scaled-orthographic adjustment only where the "
                        "closed form fails, or with --refine); 'closed-form': the paper's closed form "
                        "alone (section 4.2), as published")
    p.add_argument("--image-size", metavar="W,H",
                   help="the cameras' image size in pixels (principal point at its centre): adds "
                        "pinhole cameras (rotation, focal length, centre per camera), exact where the "
                        "scaled orthographic model is not; default for a keypoint folder: each camera's "
                        "video beside it (videos/<cam>.mp4 in a Pose2Sim trial), if every camera has one")
    p.add_argument("--intrinsics", type=Path, metavar="CALIB.toml",
                   help="known intrinsics: each camera's 'matrix' (focal length, principal point) and 'size' "
                        "from a Pose2Sim / anipose calibration TOML (as --export-calibration writes it), matched "
                        "by camera name; the pinhole adjustment keeps them fixed (implies pinhole cameras)")
    p.add_argument("--focal", type=float, metavar="PX",
                   help="with --image-size: one known focal length in pixels for every camera, kept fixed")
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
    k = p.add_argument_group("keypoint input (docs/SELFCAL.md, \"Keypoint import\")")
    k.add_argument("--min-confidence", type=float, default=0.3, metavar="C",
                   help="keypoints below this confidence are missing (default 0.3)")
    k.add_argument("--skeleton", choices=sorted(SKELETONS),
                   help="the keypoint layout (default: from the keypoint count)")
    k.add_argument("--max-frames", type=positive_int, default=None, metavar="N",
                   help="calibrate on at most N frames, evenly spread (default 60 for keypoint input, every "
                        "frame of a tracks JSON); the exports hold every frame")
    e = p.add_argument_group("exports (need --image-size)")
    e.add_argument("--export-calibration", type=Path, metavar="PATH.toml|.yaml|.json",
                   help="the cameras (z-up world, metres) as a Pose2Sim / anipose calibration TOML (.toml) or "
                        "as OpenCV's cv2.FileStorage YAML (.yaml, .yml) or JSON (.json), by the suffix")
    e.add_argument("--export-trc", type=Path, metavar="PATH.trc",
                   help="the 3D joints of every frame as an OpenSim TRC (Y up, metres)")
    e.add_argument("--export-bvh", type=Path, metavar="PATH.bvh",
                   help="the 3D joints of every frame as a BVH skeleton (Y up, metres; bone lengths the "
                        "person's medians)")
    e.add_argument("--export-csv", type=Path, metavar="PATH.csv",
                   help="the 3D joints of every frame as CSV: frame, time, <joint>_x/_y/_z (z up, metres)")
    e.add_argument("--fps", type=float, default=15.0, help="the TRC's, BVH's and CSV's frame rate (default 15)")
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
                "rotvec": Rotation.from_matrix(result.rotations[c]).as_rotvec().tolist(),
                "quaternion_xyzw": Rotation.from_matrix(result.rotations[c]).as_quat(canonical=True).tolist(),
                "euler_xyz_deg": euler[c].tolist(),
                "scale": float(result.scales[c]),
            }
            for c, name in enumerate(cameras) if c > 0
        },
        "reflection_confidence": result.reflection_confidence,
        "start": result.start,
        "notes": [named_note(note, cameras) for note in result.notes],
        "joints3d_frame": f"camera {cameras[0]!r}: x = image u, y = image v, z = viewing "
                          "direction; its pixels; origin at each frame's joint centroid",
        "frames": [{"index": i, "joints3d": _nullable(j)} for i, j in enumerate(result.joints3d)],
    }
    std = result.euler_xyz_std_deg
    for c, name in enumerate(cameras):
        if c == 0:
            continue
        cam = doc["cameras"][name]
        if result.rotvec_cov is not None:  # the posterior (bundle adjustment only), radians^2
            cov = result.rotvec_cov[c]
            cam["rotvec_covariance_rad2"] = cov.tolist() if np.isfinite(cov).all() else None
        if std is not None:  # the same posterior as Euler angles' standard deviations (kept for compatibility)
            cam["euler_xyz_std_deg"] = _nullable(std[c:c + 1])[0]
        if result.scale_std is not None:  # null: the tracks do not determine it
            cam["scale_std"] = float(result.scale_std[c]) if np.isfinite(result.scale_std[c]) else None
        if result.frame_scales is not None:
            cam["frame_scales"] = result.frame_scales[:, c].tolist()
    return doc


def run(args: argparse.Namespace) -> int:
    size = _image_size(args.image_size)
    if args.focal is not None and args.intrinsics is not None:
        raise CliError("give --focal or --intrinsics, not both")
    if args.focal is not None and (size is None or not (math.isfinite(args.focal) and args.focal > 0)):
        raise CliError("--focal needs a positive focal length in pixels and --image-size W,H (the principal point "
                       "is the image centre)")
    intrinsics = _read_intrinsics(args.intrinsics) if args.intrinsics is not None else None
    if size is None and intrinsics is not None:
        size = next(iter(intrinsics.values()))[1]  # for reading normalised keypoints; per camera below
    cameras, tracks, keypoints = _read_input(args.tracks, args, size)
    if args.upright and not args.refine:
        raise CliError("--upright needs --refine (the default --method refined has it)")
    closed = args.method == "closed-form" and not args.refine
    if size is not None and (closed or args.varying_scale):
        raise CliError("--image-size, --intrinsics and --focal need the refined path with fixed scales (not "
                       "--method closed-form, not --varying-scale)")
    found = None  # without --image-size: the image sizes of the videos beside the keypoints, if any
    if size is None and keypoints is not None and len(args.tracks) == 1 and not (closed or args.varying_scale):
        found = video_sizes(args.tracks[0], cameras)
    sizes, pinhole_config = _pinhole_setup(cameras, size, args.focal, intrinsics, found)
    exports = export_formats(args)
    if exports and sizes is None:
        raise CliError("--export-calibration, --export-trc, --export-bvh and --export-csv need pinhole cameras: "
                       "give --image-size W,H (and the refined path, the default)")
    if args.fps <= 0:
        raise CliError(f"--fps must be positive, got {args.fps}")
    used = _calibration_frames(tracks.shape[1], args.max_frames or (60 if keypoints else None))
    try:
        rig = RigConfig(height_m=args.height)
        result = None
        if sizes is not None and not args.refine:
            # Pinhole cameras by default: the closed form is their start (with the epipolar one); the
            # scaled-orthographic bundle adjustment, 1-30 s, is only needed where the closed form fails.
            result = self_calibrate(tracks[:, used], refine=False, temporal_prior=True) or None
        if result is None:
            result = self_calibrate(tracks[:, used], scales="varying" if args.varying_scale else "fixed",
                                    refine=None if closed else True,
                                    upright=args.upright if args.refine else not closed)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if not result:
        raise CliFailure(f"self-calibration failed: {result.reason}")
    out = result_to_json(result, cameras)
    if found is not None:
        out["notes"].append("image sizes (no --image-size) from the videos beside the keypoints: " + ", ".join(
            f"{c} {w}x{h} ({path.name})" for c, ((w, h), path) in found.items()))
    if sizes is not None:
        times = used if keypoints is None else np.asarray(keypoints.frames)[used]  # for the smooth motion
        out, pin, k = _with_pinhole(out, result, tracks[:, used], cameras, sizes, rig, pinhole_config, times)
        if exports:
            _export(args, pin, k, tracks, keypoints, cameras, sizes, rig)
    if sizes is None and keypoints is not None:
        out["notes"].append(NO_IMAGE_SIZE)
    if len(cameras) == 2:
        out["notes"].append(TWO_CAMERAS)
    for note in out["notes"]:
        print(f"posecal selfcal: warning: {note}", file=sys.stderr)
    for frame, index in zip(out["frames"], used):  # indices into the input's frames
        frame["index"] = int(index)
        if keypoints is not None:
            frame["frame"] = keypoints.frames[index]
    if keypoints is not None:
        out["input"] = {"format": keypoints.format, "skeletons": keypoints.skeletons,
                        "min_confidence": args.min_confidence}
    text = json.dumps(out, indent=1, allow_nan=False)
    if args.out is None:
        sys.stdout.write(text + "\n")
    else:
        write_text(args.out, text + "\n")
    if not out.get("reliable", True):  # the computation ran on valid input and failed: exit 1, not 2
        print("posecal selfcal: error: the calibration is unreliable (the pinhole cameras do not fit the "
              "keypoints); it is written for inspection, with its notes", file=sys.stderr)
        return 1
    return 0


def _read_input(paths: list[Path], args: argparse.Namespace, size: tuple[int, int] | None
                ) -> tuple[list[str], np.ndarray, Keypoints | None]:
    """Camera names, tracks (C, T, 13, 2) and, for keypoint input, what was read."""
    if len(paths) == 1 and not paths[0].is_dir():
        try:
            doc = json.loads(Path(paths[0]).read_text())
        except FileNotFoundError:
            raise CliError(f"no such file: {paths[0]}") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise CliError(f"cannot read {paths[0]}: {exc}") from None
        if isinstance(doc, dict) and not {"instance_info", "predictions", "format", "frames"} & set(doc):
            cameras, tracks = load_tracks(doc)
            return cameras, tracks, None
    if not 0.0 <= args.min_confidence <= 1.0:
        raise CliError(f"--min-confidence must lie in [0, 1], got {args.min_confidence}")
    try:
        kp = read_keypoints(paths, min_confidence=args.min_confidence, image_size=size, skeleton=args.skeleton)
    except KeypointError as exc:
        raise CliError(str(exc)) from None
    return kp.cameras, kp.tracks, kp


def _calibration_frames(t: int, max_frames: int | None) -> np.ndarray:
    """Indices of the frames to calibrate on: all, or every k-th so that at most ``max_frames`` remain."""
    if max_frames is None or t <= max_frames:
        return np.arange(t)
    return np.arange(0, t, math.ceil(t / max_frames))


def _export(args: argparse.Namespace, pin, k: float, tracks: np.ndarray, keypoints: Keypoints | None,
            cameras: list[str], sizes: np.ndarray, rig: RigConfig) -> None:
    """Write the --export-* files: the pinhole rig in metres in a z-up world
    (:func:`estimator.pinhole.floor_frame`), every input frame triangulated."""
    cams = pin.cameras(k)
    weights = keypoints.confidence if keypoints is not None else None
    joints = triangulate(cams, tracks, weights)
    try:
        rotation, origin = floor_frame(joints, np.array([0.0, 0.0, 1.0]))
    except ValueError as exc:
        raise CliFailure(f"exports: {exc}") from None
    world = cams.moved(rotation, origin)
    if args.export_calibration is not None:
        write_calibration(args.export_calibration, cameras, sizes, world, metadata={
            "error": float(pin.rmse_px), "source": "posecal selfcal", "reference_camera": cameras[0],
            "stature_m": float(rig.height_m)})
    frames = keypoints.frames if keypoints is not None else None
    joints = (joints - origin) @ rotation.T
    if args.export_trc is not None:
        write_trc(args.export_trc, joints, args.fps, frames)
    if args.export_csv is not None:
        write_text(args.export_csv, csv_text(joints, args.fps, frames))
    if args.export_bvh is not None:
        try:
            write_text(args.export_bvh, bvh_text(joints, args.fps))
        except ValueError as exc:
            raise CliFailure(f"--export-bvh: {exc}") from None


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


def _read_intrinsics(path: Path) -> dict[str, tuple[np.ndarray, tuple[int, int]]]:
    """Per camera name, the intrinsics ``matrix`` (3, 3) and image ``size`` of a Pose2Sim / anipose
    calibration TOML (the layout :func:`service.exports.write_calibration_toml` writes)."""
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise CliError(f"--intrinsics: no such file: {path}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise CliError(f"--intrinsics: cannot read {path}: {exc}") from None
    out = {}
    for key, table in doc.items():
        if not isinstance(table, dict) or key == "metadata":
            continue
        name = str(table.get("name", key))
        try:
            matrix = np.array(table["matrix"], float)
            size = tuple(int(round(float(v))) for v in table["size"])
        except (KeyError, TypeError, ValueError):
            raise CliError(f"--intrinsics: {path}: camera {name!r} needs 'matrix' (3x3) and 'size' [W, H]") from None
        if matrix.shape != (3, 3) or not np.isfinite(matrix).all() or not (matrix[0, 0] > 0 and matrix[1, 1] > 0) \
                or len(size) != 2 or min(size) <= 0:
            raise CliError(f"--intrinsics: {path}: camera {name!r}: 'matrix' must be [[fx, 0, cx], [0, fy, cy], "
                           f"[0, 0, 1]] with fx, fy > 0 and 'size' [W, H] positive")
        out[name] = (matrix, size)
    if not out:
        raise CliError(f"--intrinsics: {path} has no camera table (with 'matrix' and 'size')")
    return out


NO_IMAGE_SIZE = ("no --image-size: the cameras are scaled orthographic, which people 2-5 m away are not; give the "
                 "videos' frame size (--image-size W,H) for pinhole cameras (on the Pose2Sim demo's keypoints: camera "
                 "pairs 13.1 deg off without it, 1.6 with it)")
"""The note of a keypoint calibration without the image size (docs/SELFCAL.md, "Real keypoints")."""

TWO_CAMERAS = ("two cameras: the rotation between two views of a person is weakly determined (on synthetic walks "
               "4-15 m away with 1-3 % keypoint noise, two-camera rigs from keypoints alone were 4.6-23.9 deg off in "
               "the median of a draw, three or four cameras 0.4-1.9 deg; the Pose2Sim demo's pairs at 2-4 m 4.9 deg); "
               "add a camera, or calibrate from the videos with these keypoints (posecal estimate VIDEOS --keypoints "
               "DIR), whose viewpoints settle it (2.4-6.7 deg)")
"""The note of a two-camera calibration (docs/SELFCAL.md, "Not done": two cameras from keypoints alone)."""


def _by_camera(tables: dict[str, Any], cameras: list[str]) -> dict[str, Any]:
    """``tables`` keyed also by the input's camera names (:func:`service.keypoints_io.match_cameras`)."""
    if all(c in tables for c in cameras):
        return tables
    return {**tables, **{c: tables[name] for c, name in match_cameras(tables, cameras).items()}}


def _pinhole_setup(cameras: list[str], size: tuple[int, int] | None, focal: float | None,
                   intrinsics: dict[str, tuple[np.ndarray, tuple[int, int]]] | None,
                   found: dict[str, tuple[tuple[int, int], Path]] | None = None
                   ) -> tuple[np.ndarray | None, PerspectiveConfig]:
    """Image sizes (C, 2) and the pinhole adjustment's settings: focal lengths and principal points
    fixed when known (``--focal``, ``--intrinsics``), free otherwise; the sizes from ``--image-size``,
    else from the videos ``found`` beside the keypoints, else None (scaled-orthographic cameras)."""
    if intrinsics is None:
        if size is not None:
            sizes = np.tile(np.array(size, float), (len(cameras), 1))
        else:
            sizes = None if found is None else np.array([found[c][0] for c in cameras], float)
        return sizes, PerspectiveConfig(focal_px=focal, **KEYPOINT_SETTINGS)
    intrinsics = _by_camera(intrinsics, cameras)
    missing = [c for c in cameras if c not in intrinsics]
    if missing:
        raise CliError(f"--intrinsics has no camera {', '.join(map(repr, missing))} (it has "
                       f"{', '.join(map(repr, intrinsics))}); camera names must match the input's")
    mats = np.stack([intrinsics[c][0] for c in cameras])
    sizes = np.array([intrinsics[c][1] for c in cameras], float)
    return sizes, PerspectiveConfig(focal_px=tuple(float(f) for f in (mats[:, 0, 0] + mats[:, 1, 1]) / 2),
                                    principal_px=tuple((float(u), float(v)) for u, v in mats[:, :2, 2]),
                                    **KEYPOINT_SETTINGS)


def _with_pinhole(doc: dict, result, tracks: np.ndarray, cameras: list[str], sizes: np.ndarray,
                  rig: RigConfig, config: PerspectiveConfig, frame_times: np.ndarray | None = None
                  ) -> tuple[dict, Any, float]:
    """The calibration with pinhole cameras (:func:`estimator.epipolar.refine_from_starts`: the
    bundle adjustment from the refined scaled-orthographic rig and from the epipolar start, the
    better kept): rotations, focal lengths and centres per camera, 3D joints in metres at the
    stature (:func:`estimator.rig.stature_scale`); ``frame_times``: the frames' numbers."""
    pin, start = refine_from_starts(tracks, sizes, result.rotations, result.scales, list(RIGID_LINKS),
                                    config=config, frame_times=frame_times)
    k = stature_scale(pin.joints3d, rig.height_m)
    if not np.isfinite(k):
        raise CliFailure("the pinhole adjustment gave a body without length")
    rot = Rotation.from_matrix(pin.rotations)
    euler, rotvec = rot.as_euler("xyz", degrees=True), rot.as_rotvec()
    fit = _fit_notes(pin, tracks)
    doc = dict(doc, method=result.method + "+pinhole",
               joints3d_frame=f"camera {cameras[0]!r}: x right, y down, z forward (its optical axis); metres at a "
                              f"stature of {rig.height_m} m; origin at that camera's centre",
               frames=[{"index": i, "joints3d": _nullable(j * k)} for i, j in enumerate(pin.joints3d)],
               reprojection_rms_px=round(pin.rmse_px, 3),
               reprojection_median_px=round(pin.median_px, 3),
               pinhole_start=start,
               pinhole_upright=pin.upright,
               scaled_orthographic={name: {"rotation": doc["cameras"][name]["rotation"],
                                           "scale": doc["cameras"][name]["scale"]} for name in cameras[1:]},
               reference_focal_px=float(pin.focal_px[0]),
               intrinsics="given" if config.focal_px is not None else "estimated",
               notes=doc["notes"] + _focal_notes(pin, cameras) + fit + (
                   ["the walker shows little perspective: the pinhole adjustment held its body upright in every "
                    "frame (trunk across the hips and shoulders, upper arms across the shoulders)"]
                   if pin.upright else []),
               reliable=not fit)
    cams = {}
    for c, name in enumerate(cameras[1:], 1):
        cams[name] = {"rotation": pin.rotations[c].tolist(),
                      "rotvec": rotvec[c].tolist(),
                      "quaternion_xyzw": rot[c].as_quat(canonical=True).tolist(),
                      "euler_xyz_deg": euler[c].tolist(),
                      "scale": float(pin.scales[c]), "focal_px": float(pin.focal_px[c]),
                      "centre_m": (pin.centres[c] * k).tolist()}
    doc["cameras"] = cams
    return doc, pin, k


FOCAL_LOG_STD = 0.03
"""A free focal length whose posterior log standard deviation exceeds this (about 3 %) is reported. The
Laplace posterior is optimistic where the focal length is weakly determined (a walker 40 m away, 3 px of
noise: 3 % posterior, 10-25 % actual error; docs/SELFCAL.md), hence the low threshold."""


FIT_SHARE = 0.05
"""A pinhole fit whose median reprojection distance exceeds this share of the walker's median image height
is reported. The median, not the rms: reweighting leaves the gross outliers unfitted, and their share of
the rms flagged right rigs (1-3 % noise and 5 % outliers at 2.5-4 m: rms 0.028-0.051 of the height,
median 0.012-0.023 on 20 rigs all within 5.4 deg); a wrong rig (another basin, joints no body explains)
leaves 10 % or more."""


def _fit_notes(pin, tracks: np.ndarray) -> list[str]:
    """A warning when the pinhole cameras do not fit the tracks (a wrong basin, not noise)."""
    height = image_height(tracks)
    if not (np.isfinite(height) and pin.median_px > FIT_SHARE * height):
        return []
    return [f"the pinhole cameras fit the keypoints poorly (median reprojection error {pin.median_px:.1f} px, "
            f"{100 * pin.median_px / height:.0f} % of the walker's image height): the rig is probably wrong"]


def _focal_notes(pin, cameras: list[str]) -> list[str]:
    """Warnings for focal lengths the tracks hardly constrain: the walker shows little perspective in
    every camera (:meth:`PerspectiveRig.depth_spread` below ``WEAK_PERSPECTIVE``), or a camera's
    posterior is wide (:attr:`PerspectiveRig.focal_log_std`)."""
    if pin.focal_log_std is None:
        return []
    spread = float(np.nanmax(pin.depth_spread()))
    if spread < WEAK_PERSPECTIVE:
        return [f"the walker shows little perspective (its depth varies by {100 * spread:.0f} % of its distance at "
                "most): focal lengths and distances are poorly determined (their ratio is not); give --focal or "
                "--intrinsics"]
    return [f"camera {name!r}: the focal length is poorly determined ({pin.focal_px[c]:.0f} px, posterior std "
            f"about {100 * pin.focal_log_std[c]:.0f} %): focal length and distance trade off when the walker shows "
            "little perspective; give --focal or --intrinsics"
            for c, name in enumerate(cameras) if pin.focal_log_std[c] > FOCAL_LOG_STD]
