"""Files the peers read: calibrations, and the 3D joints as TRC, BVH and CSV (docs/FORMATS.md, "Exports").

Written by hand (no TOML writer is installed; the layouts are small), except the
OpenCV files, which ``cv2.FileStorage`` writes itself:

- calibration TOML, as Pose2Sim's ``calibration.toml_write`` writes it and
  aniposelib's ``CameraGroup.load`` reads it: one table per camera with
  ``name``, ``size`` [W, H], ``matrix`` (3x3 intrinsics), ``distortions``
  (k1, k2, p1, p2), ``rotation`` (Rodrigues vector, world to camera),
  ``translation`` (``x_cam = R X + t``, metres) and ``fisheye = false``, then a
  ``[metadata]`` table;
- OpenCV calibration, YAML or JSON as ``cv2.FileStorage`` writes and reads it:
  ``cameras``, a list of maps with ``name``, ``image_size`` [W, H], ``K`` (3x3),
  ``dist`` (1x5: k1, k2, p1, p2, k3), ``rvec`` (3x1), ``R`` (3x3) and ``t`` (3x1,
  metres), the same world-to-camera ``x_cam = R X + t``; then ``metadata``;
- TRC, as Pose2Sim's triangulation writes it for OpenSim: the header lines
  ``PathFileType 4 (X/Y/Z) <file>``, the ``DataRate ... OrigNumFrames`` names and
  values, ``Frame# Time <marker> ...`` and ``X1 Y1 Z1 ...``, then one
  tab-separated row per frame; metres, Y up (Pose2Sim's ``zup2yup``: the Z-up
  world's (x, y, z) is written as (y, z, x)); missing joints are empty cells;
- BVH: the 13 joints as a hierarchy (:data:`BVH_JOINTS`) rooted at the hips'
  midpoint, Y up as in the TRC, metres; fixed offsets = the person's median
  bone lengths, a root translation and per-joint rotations that aim each bone
  at the joints' positions (:func:`bvh_text`);
- CSV: one row per frame, ``frame, time, head_x, head_y, head_z, ...``; metres,
  the Z-up frame the joints were given in; empty cells where a joint is missing.

:func:`export_result` and :func:`export_calibration` give these from a result
(``posecal estimate``, ``GET /v1/jobs/{id}/result?format=``) and from a live
rig's calibration (``GET /v1/rigs/{rig}/calibration?format=``).
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from estimator.joints import JOINT_INDEX, JOINT_NAMES
from estimator.pinhole import PinholeCameras
from estimator.rig import segment_lengths

__all__ = ["BVH_JOINTS", "CALIBRATION_SUFFIXES", "MEDIA_TYPES", "TRC_MARKERS", "bvh_text", "calibration_format",
           "calibration_text", "csv_text", "export_calibration", "export_result", "result_joints", "rig_cameras",
           "trc_text", "write_calibration", "write_calibration_toml", "write_text", "write_trc"]

CALIBRATION_SUFFIXES: dict[str, str] = {".toml": "toml", ".yaml": "yaml", ".yml": "yaml", ".json": "json"}
"""Calibration file suffix -> format: the Pose2Sim / anipose TOML, or OpenCV's YAML or JSON."""

MEDIA_TYPES: dict[str, str] = {"json": "application/json", "trc": "text/plain", "bvh": "text/plain",
                               "csv": "text/csv", "toml": "application/toml", "yaml": "application/yaml"}
"""The media type of each export format (REST answers)."""

TRC_MARKERS: tuple[str, ...] = tuple(
    {"left": "L", "right": "R"}.get(name.partition("_")[0], "") + name.rpartition("_")[2].title()
    for name in JOINT_NAMES)
"""The 13 joints' marker names in the TRC, in :data:`estimator.joints.JOINT_NAMES` order, Pose2Sim's
spelling: ``Head``, ``LShoulder``, ``RShoulder``, ... ``RAnkle``."""


def _num(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"cannot write a non-finite number ({v}) to the calibration")
    return repr(float(v) + 0.0)  # no -0.0


def _array(values) -> str:
    a = np.asarray(values)
    if a.ndim == 1:
        return "[ " + ", ".join(_num(v) for v in a) + "]"
    return "[ " + ", ".join(_array(r) for r in a) + "]"


def write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path``, making its folder; all or nothing (a temporary file beside it, then
    renamed), so a reader never finds half a file."""
    path = Path(path)
    if path.exists() and not path.is_file():  # a device or a pipe (/dev/stdout): nothing to rename onto
        path.write_text(text)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        partial.write_text(text)
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)


def write_calibration_toml(path: Path, names: Sequence[str], sizes: np.ndarray, cameras: PinholeCameras, *,
                           metadata: dict[str, str | float | bool] | None = None) -> None:
    """Write cameras (world to camera, metres) as a Pose2Sim / anipose calibration TOML
    (:func:`calibration_text`)."""
    write_text(path, calibration_text("toml", names, sizes, cameras, metadata=metadata))


def calibration_format(path: Path) -> str:
    """The calibration format a file name asks for (:data:`CALIBRATION_SUFFIXES`); ValueError otherwise."""
    fmt = CALIBRATION_SUFFIXES.get(Path(path).suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: a calibration file ends in {', '.join(CALIBRATION_SUFFIXES)} (Pose2Sim / "
                         "anipose TOML, OpenCV YAML or JSON)")
    return fmt


def write_calibration(path: Path, names: Sequence[str], sizes: np.ndarray, cameras: PinholeCameras, *,
                      metadata: dict[str, str | float | bool] | None = None) -> None:
    """Write cameras in the format of the file's suffix (:func:`calibration_format`)."""
    write_text(path, calibration_text(calibration_format(path), names, sizes, cameras, metadata=metadata))


def calibration_text(fmt: str, names: Sequence[str], sizes: np.ndarray, cameras: PinholeCameras, *,
                     metadata: dict[str, str | float | bool] | None = None) -> str:
    """Cameras (world to camera, metres) as a calibration file: ``fmt`` ``"toml"`` (Pose2Sim / anipose),
    ``"yaml"`` or ``"json"`` (OpenCV, :func:`_opencv_text`).

    Parameters
    ----------
    names : sequence of str
        Camera names: each is a table's key and its ``name``.
    sizes : ndarray of shape (C, 2)
        Image (width, height) per camera.
    metadata : dict, optional
        Extra ``metadata`` entries besides ``adjusted = false`` and ``error`` (0.0 unless given).
    """
    meta = {"adjusted": False, "error": 0.0, **(metadata or {})}
    if fmt in ("yaml", "json"):
        return _opencv_text(fmt, names, sizes, cameras, meta)
    if fmt != "toml":
        raise ValueError(f"unknown calibration format {fmt!r}")
    rotvec = Rotation.from_matrix(cameras.rotations).as_rotvec()
    lines = []
    for c, name in enumerate(names):
        key = name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else json.dumps(str(name))
        lines += [f"[{key}]", f"name = {json.dumps(str(name))}",
                  f"size = {_array(np.asarray(sizes[c], float))}", f"matrix = {_array(cameras.matrices[c])}",
                  f"distortions = {_array(np.zeros(4))}", f"rotation = {_array(rotvec[c])}",
                  f"translation = {_array(cameras.translations[c])}", "fisheye = false", ""]
    lines.append("[metadata]")
    for key, value in meta.items():
        text = ("true" if value else "false") if isinstance(value, bool) else (
            _num(value) if isinstance(value, (int, float)) else json.dumps(str(value)))
        lines.append(f"{key} = {text}")
    return "\n".join(lines) + "\n"


def _opencv_text(fmt: str, names: Sequence[str], sizes: np.ndarray, cameras: PinholeCameras,
                 meta: dict[str, str | float | bool]) -> str:
    """The cameras as ``cv2.FileStorage`` writes them, ``fmt`` ``"yaml"`` or ``"json"`` (module docstring)."""
    import cv2

    rotvec = Rotation.from_matrix(cameras.rotations).as_rotvec()
    fs = cv2.FileStorage(f"calibration.{fmt}", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.startWriteStruct("cameras", cv2.FileNode_SEQ)
    for c, name in enumerate(names):
        fs.startWriteStruct("", cv2.FileNode_MAP)
        fs.write("name", str(name))
        fs.startWriteStruct("image_size", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
        for v in np.asarray(sizes[c]):
            fs.write("", int(round(float(v))))
        fs.endWriteStruct()
        for key, value in (("K", cameras.matrices[c]), ("dist", np.zeros((1, 5))), ("rvec", rotvec[c][:, None]),
                           ("R", cameras.rotations[c]), ("t", cameras.translations[c][:, None])):
            if not np.all(np.isfinite(value)):
                raise ValueError(f"cannot write a non-finite {key} of camera {name!r} to the calibration")
            fs.write(key, np.asarray(value, np.float64))
        fs.endWriteStruct()
    fs.endWriteStruct()
    fs.startWriteStruct("metadata", cv2.FileNode_MAP)
    for key, value in meta.items():
        fs.write(key, int(value) if isinstance(value, bool) else value if isinstance(value, (int, float)) else str(value))
    fs.endWriteStruct()
    return fs.releaseAndGetString()


def _frame_numbers(t: int, fps: float, frames: Sequence[int] | None) -> list[int]:
    """Each frame's number (default 1..T), checked against ``t`` frames and ``fps`` > 0."""
    numbers = list(range(1, t + 1)) if frames is None else [int(f) for f in frames]
    if len(numbers) != t or not fps > 0:
        raise ValueError(f"need one frame number per frame and fps > 0, got {len(numbers)} for {t}, fps {fps}")
    return numbers


def _zup_to_yup(x: np.ndarray) -> np.ndarray:
    """A Z-up world's (x, y, z) as Y-up (y, z, x): Pose2Sim's ``zup2yup`` (a proper rotation)."""
    return np.asarray(x, float)[..., [1, 2, 0]]


def write_trc(path: Path, joints_zup: np.ndarray, fps: float, frames: Sequence[int] | None = None) -> None:
    """Write joints (T, 13, 3) of a Z-up world in metres as an OpenSim TRC (Y up, :func:`trc_text`)."""
    write_text(path, trc_text(Path(path).name, joints_zup, fps, frames))


def trc_text(name: str, joints_zup: np.ndarray, fps: float, frames: Sequence[int] | None = None) -> str:
    """Joints (T, 13, 3) of a Z-up world in metres as an OpenSim TRC (Y up) named ``name``.

    ``frames`` are the source frame numbers (``Frame#``; default 1..T); ``Time``
    is ``(frame - first frame) / fps``.
    """
    x = np.asarray(joints_zup, float)
    t = len(x)
    numbers = _frame_numbers(t, fps, frames)
    yup = _zup_to_yup(x)
    header = [
        f"PathFileType\t4\t(X/Y/Z)\t{name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        "\t".join(map(str, [fps, fps, t, len(TRC_MARKERS), "m", fps, numbers[0], t])),
        "Frame#\tTime\t" + "\t\t\t".join(TRC_MARKERS) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(len(TRC_MARKERS))),
    ]
    return "\n".join(header + ["\t".join(r) for r in _rows(numbers, fps, yup)]) + "\n"


def _rows(numbers: list[int], fps: float, joints: np.ndarray) -> list[list[str]]:
    """Per frame: its number, its time ``(frame - first) / fps`` and its joints' coordinates (6 decimals,
    empty where missing)."""
    return [[str(n), f"{(n - numbers[0]) / fps:.6f}"] + ["" if not np.isfinite(v) else f"{v:.6f}" for v in x.ravel()]
            for n, x in zip(numbers, joints)]


def csv_text(joints: np.ndarray, fps: float, frames: Sequence[int] | None = None) -> str:
    """Joints (T, 13, 3), metres, as CSV in the frame they are given in: a header ``frame,time,head_x,head_y,
    head_z,...`` (:data:`~estimator.joints.JOINT_NAMES` order), then one row per frame; ``frames`` and ``time``
    as in :func:`trc_text`; an empty cell where a joint is missing."""
    x = np.asarray(joints, float)
    header = ["frame", "time"] + [f"{n}_{a}" for n in JOINT_NAMES for a in "xyz"]
    return "\n".join(",".join(r) for r in [header] + _rows(_frame_numbers(len(x), fps, frames), fps, x)) + "\n"


# ----------------------------------------------------------------------------- BVH

BVH_JOINTS: tuple[tuple[str, str, str, tuple[float, float, float], str, float], ...] = (
    ("Hips", "", "mid_hip", (0.0, 0.0, 0.0), "", 0.0),
    ("LeftUpLeg", "Hips", "left_hip", (1.0, 0.0, 0.0), "hip_width", 0.5),
    ("LeftLeg", "LeftUpLeg", "left_knee", (0.0, -1.0, 0.0), "left_thigh", 1.0),
    ("LeftFoot", "LeftLeg", "left_ankle", (0.0, -1.0, 0.0), "left_shank", 1.0),
    ("RightUpLeg", "Hips", "right_hip", (-1.0, 0.0, 0.0), "hip_width", 0.5),
    ("RightLeg", "RightUpLeg", "right_knee", (0.0, -1.0, 0.0), "right_thigh", 1.0),
    ("RightFoot", "RightLeg", "right_ankle", (0.0, -1.0, 0.0), "right_shank", 1.0),
    ("Spine", "Hips", "mid_hip", (0.0, 0.0, 0.0), "", 0.0),
    ("Neck", "Spine", "mid_shoulder", (0.0, 1.0, 0.0), "trunk", 1.0),
    ("LeftArm", "Neck", "left_shoulder", (1.0, 0.0, 0.0), "shoulder_width", 0.5),
    ("LeftForeArm", "LeftArm", "left_elbow", (1.0, 0.0, 0.0), "left_upper_arm", 1.0),
    ("LeftHand", "LeftForeArm", "left_wrist", (1.0, 0.0, 0.0), "left_forearm", 1.0),
    ("RightArm", "Neck", "right_shoulder", (-1.0, 0.0, 0.0), "shoulder_width", 0.5),
    ("RightForeArm", "RightArm", "right_elbow", (-1.0, 0.0, 0.0), "right_upper_arm", 1.0),
    ("RightHand", "RightForeArm", "right_wrist", (-1.0, 0.0, 0.0), "right_forearm", 1.0),
    ("Neck1", "Neck", "mid_shoulder", (0.0, 0.0, 0.0), "", 0.0),
    ("Head", "Neck1", "head", (0.0, 1.0, 0.0), "neck_head", 1.0),
)
"""The BVH hierarchy, parents first in the file's (depth-first) order: ``(name, parent, where it is, the
direction of its OFFSET from the parent in the rest pose, the segment of :data:`estimator.rig.SEGMENTS`
whose median length times the factor is the OFFSET's length)``. Where: one of the 13 joints, or the
midpoint of the hips or of the shoulders. Rest pose (all rotations zero): BVH axes x = the walker's left,
y up, z forward; legs down, arms out sideways. ``Spine`` and ``Neck1`` sit on their parent (zero OFFSET)
so that the trunk and the head turn apart from the hips' and the shoulders' lines."""


def bvh_text(joints_zup: np.ndarray, fps: float) -> str:
    """Joints (T, 13, 3) of a Z-up world in metres as a BVH of :data:`BVH_JOINTS`.

    Y up, metres (the TRC's axes: the world's (x, y, z) as (y, z, x)). OFFSETs
    are the person's median bone lengths; per frame the root's position is the
    hips' midpoint and its rotation the frame of the hip line (x) and the trunk
    (y, made perpendicular); the shoulders' joint (``Neck``) likewise from the
    shoulder line and the neck-head; every other joint turns by the least
    rotation (no twist) that points its one child's bone at that child's
    joint. Forward kinematics thus gives back the joints, exactly when the bone
    lengths are constant (each joint within its bone's deviation from the
    median otherwise). Rotations are ``Zrotation Xrotation Yrotation``
    (``R = Rz Rx Ry``, about moving axes, degrees). A missing joint is
    interpolated in time from the frames around it (BVH has no missing values);
    one never placed, or joints that coincide (no bone direction), is a
    ValueError. The leaves' End Sites have zero OFFSETs.
    """
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    y = _zup_to_yup(_filled(joints_zup))
    lengths = {k: float(np.median(v)) for k, v in segment_lengths(y).items()}
    pts = {n: y[:, j] for n, j in JOINT_INDEX.items()}
    pts["mid_hip"] = (pts["left_hip"] + pts["right_hip"]) / 2
    pts["mid_shoulder"] = (pts["left_shoulder"] + pts["right_shoulder"]) / 2
    parent = {n: p for n, p, *_ in BVH_JOINTS}
    at = {n: w for n, _, w, *_ in BVH_JOINTS}
    rest = {n: np.array(d) for n, _, _, d, *_ in BVH_JOINTS}  # zero: on the parent (no bone)
    offset = {n: rest[n] * (lengths[seg] * f if seg else 0.0) for n, _, _, _, seg, f in BVH_JOINTS}
    children = {n: [m for m, p, *_ in BVH_JOINTS if p == n] for n in parent}
    t = len(y)
    world: dict[str, np.ndarray] = {}  # each joint's rotation, BVH axes, (T, 3, 3)
    local: dict[str, np.ndarray] = {}
    for n, p, *_ in BVH_JOINTS:  # parents first
        up = world[p] if p else np.broadcast_to(np.eye(3), (t, 3, 3))
        bones = [k for k in children[n] if rest[k].any()]
        with np.errstate(invalid="ignore", divide="ignore"):  # coincident joints: NaN, refused below
            if len(bones) == 2:  # hips, shoulders: x from the (-x) second child to the (+x) first, y towards
                branch = next(k for k in children[n] if not rest[k].any())  # the zero-OFFSET branch's child
                towards = next(k for k in children[branch] if rest[k].any())
                world[n] = _frame(pts[at[bones[0]]] - pts[at[bones[1]]], pts[at[towards]] - pts[at[n]])
            elif len(bones) == 1:
                aim = np.einsum("tji,tj->ti", up, pts[at[bones[0]]] - pts[at[n]])  # in the parent's axes
                world[n] = up @ _swing(rest[bones[0]], aim)
            else:
                world[n] = up
        if not np.isfinite(world[n]).all():
            bad = int(np.flatnonzero(~np.isfinite(world[n]).all(axis=(1, 2)))[0])
            raise ValueError(f"frame {bad}: coincident joints at {n}, no bone direction to write")
        local[n] = np.swapaxes(up, 1, 2) @ world[n]
    with warnings.catch_warnings():  # gimbal lock: scipy warns, the angles still give the rotation
        warnings.simplefilter("ignore", UserWarning)
        angles = [Rotation.from_matrix(local[n]).as_euler("ZXY", degrees=True) for n in parent]
    motion = np.round(np.concatenate([pts["mid_hip"]] + angles, axis=1), 6) + 0.0  # no -0.000000
    lines = ["HIERARCHY"] + _bvh_joint("Hips", 0, offset, children) + [
        "MOTION", f"Frames: {t}", f"Frame Time: {1.0 / fps:.8g}"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in motion]
    return "\n".join(lines) + "\n"


def _bvh_joint(name: str, depth: int, offset: dict[str, np.ndarray], children: dict[str, list[str]]) -> list[str]:
    """The HIERARCHY lines of ``name`` and its descendants."""
    pad = "  " * depth
    channels = ("6 Xposition Yposition Zposition " if depth == 0 else "3 ") + "Zrotation Xrotation Yrotation"
    lines = [f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {name}", pad + "{",
             f"{pad}  OFFSET " + " ".join(f"{v:.6f}" for v in offset[name]), f"{pad}  CHANNELS {channels}"]
    for child in children[name]:
        lines += _bvh_joint(child, depth + 1, offset, children)
    if not children[name]:
        lines += [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET 0.000000 0.000000 0.000000", f"{pad}  }}"]
    return lines + [pad + "}"]


def _filled(joints: np.ndarray) -> np.ndarray:
    """Joints (T, 13, 3) with each missing one interpolated in time (held before its first and after its
    last frame); ValueError for a joint missing in every frame."""
    x = np.array(joints, float)
    frames = np.arange(len(x))
    if not len(x):
        raise ValueError("no frames")
    for j, name in enumerate(JOINT_NAMES):
        ok = np.isfinite(x[:, j]).all(axis=1)
        if not ok.any():
            raise ValueError(f"the joint {name!r} is never placed; BVH needs every joint")
        for a in range(3):
            x[:, j, a] = np.interp(frames, frames[ok], x[ok, j, a])
    return x


def _frame(x_dir: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotations (T, 3, 3) whose columns are ``x_dir`` normalised, ``up`` made perpendicular to it, and
    their cross product."""
    x = x_dir / np.linalg.norm(x_dir, axis=-1, keepdims=True)
    y = up - np.sum(up * x, axis=-1, keepdims=True) * x
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=-1)


def _swing(rest: np.ndarray, aim: np.ndarray) -> np.ndarray:
    """The least rotations (T, 3, 3) taking the unit vector ``rest`` (3,) to the directions ``aim`` (T, 3)."""
    v = aim / np.linalg.norm(aim, axis=-1, keepdims=True)
    axis = np.cross(rest, v)
    s = np.linalg.norm(axis, axis=-1)
    side = np.cross(rest, [0.0, 0.0, 1.0] if abs(rest[2]) < 0.9 else [1.0, 0.0, 0.0])  # for a half turn
    axis = np.where(s[:, None] > 1e-12, axis / np.maximum(s, 1e-300)[:, None], side / np.linalg.norm(side))
    return Rotation.from_rotvec(axis * np.arctan2(s, v @ rest)[:, None]).as_matrix()


# ----------------------------------------------------------------------------- from results


def result_joints(result: dict[str, Any]) -> tuple[np.ndarray, list[int], str]:
    """A result's 3D joints (docs/FORMATS.md, frames): the person's measured posture (``person_joints3d``)
    when the result has it (a self-calibrated rig), else the model body at the decoded phase
    (``joints3d``). Returns (T, 13, 3) in the person frame (x forward, y left, z up; metres; origin at
    each frame's joint centroid), NaN where null; each frame's ``index``; the field used."""
    frames = result.get("frames") or []
    if not frames:
        raise ValueError("the result has no frames")
    key = "person_joints3d" if any("person_joints3d" in f for f in frames) else "joints3d"
    out = np.full((len(frames), len(JOINT_NAMES), 3), np.nan)
    for k, frame in enumerate(frames):
        for j, point in enumerate(frame.get(key) or []):
            if point is not None:
                out[k, j] = point
    return out, [int(f["index"]) for f in frames], key


def rig_cameras(rig: dict[str, Any] | None, image_size: Sequence[int] | None = None
                ) -> tuple[list[str], np.ndarray, PinholeCameras]:
    """The pinhole cameras of a result's ``rig`` (docs/FORMATS.md, rig) with their names and image sizes.

    The world is the reference camera's frame (x its image u, y its image v, z its
    optical axis; metres at the given stature): ``R`` = the rig's rotation,
    ``t = -R centre_m``, ``K`` from ``focal_px`` and the centre of the camera's
    ``image_size`` (else ``image_size``). ValueError saying why when the rig has no
    metric cameras (a rig from the viewpoints or the scaled-orthographic model, or a
    camera left out of it).
    """
    if not rig:
        raise ValueError("the result has no rig")
    cams = rig.get("cameras") or {}
    if not any(c.get("focal_px") is not None for c in cams.values()):
        raise ValueError(f"the rig has no metric cameras (focal lengths, centres in metres): its source is "
                         f"{rig.get('source')!r}, without pinhole cameras (notes say why)")
    left_out = [n for n, c in cams.items() if any(c.get(k) is None for k in ("rotation", "focal_px", "centre_m"))]
    if left_out:
        raise ValueError(f"camera {', '.join(map(repr, left_out))} is not in the metric rig")
    sizes = [c.get("image_size") or image_size for c in cams.values()]
    if any(s is None for s in sizes):
        raise ValueError("the rig gives no image size (the principal point is its centre)")
    sizes = np.array(sizes, float)
    rotations = Rotation.from_matrix(np.array([c["rotation"] for c in cams.values()], float)).as_matrix()
    cameras = PinholeCameras.from_centres(np.array([c["focal_px"] for c in cams.values()], float), sizes / 2,
                                          rotations, np.array([c["centre_m"] for c in cams.values()], float))
    return list(cams), sizes, cameras


def _rig_text(fmt: str, rig: dict[str, Any] | None, body: dict[str, Any] | None, source: str,
              image_size: Sequence[int] | None = None) -> str:
    names, sizes, cameras = rig_cameras(rig, image_size)
    meta: dict[str, str | float | bool] = {"source": source, "reference_camera": rig.get("reference", names[0])}
    if body:
        meta["stature_m"] = float(body["stature_m"])
    return calibration_text(fmt, names, sizes, cameras, metadata=meta)


def export_result(result: dict[str, Any], fmt: str, name: str = "result.trc") -> str:
    """A batch result (docs/FORMATS.md) as ``fmt``: its 3D joints (:func:`result_joints`, at its ``fps``)
    as ``"trc"`` (named ``name`` in its header), ``"bvh"`` or ``"csv"``, or its rig (:func:`rig_cameras`)
    as a calibration, ``"toml"``, ``"yaml"`` or ``"json"`` (OpenCV's). ValueError with the reason when
    the result cannot give it."""
    if fmt in ("trc", "bvh", "csv"):
        joints, frames, _ = result_joints(result)
        fps = result.get("fps") or (result.get("sequence") or {}).get("fps")
        if not fps:
            raise ValueError("the result has no frame rate")
        if fmt == "trc":
            return trc_text(name, joints, float(fps), frames)
        return bvh_text(joints, float(fps)) if fmt == "bvh" else csv_text(joints, float(fps), frames)
    if fmt not in CALIBRATION_SUFFIXES.values():
        raise ValueError(f"unknown export format {fmt!r}")
    return _rig_text(fmt, result.get("rig"), result.get("body"), "posecal estimate",
                     (result.get("sequence") or {}).get("image_size"))


def export_calibration(calibration: dict[str, Any], fmt: str) -> str:
    """A live rig's calibration (``GET /v1/rigs/{rig}/calibration``) as a calibration file, ``fmt``
    ``"toml"``, ``"yaml"`` or ``"json"`` (:func:`calibration_text`); ValueError with the reason when it
    has no metric cameras."""
    return _rig_text(fmt, calibration.get("calibration"), calibration.get("body"), "posecal live rig")
