"""Read 2D keypoint files of OpenPose, MMPose / RTMPose and MediaPipe for ``posecal selfcal``.

The layouts (docs/FORMATS.md, "Keypoint input"):

- OpenPose / Pose2Sim: a folder ``INPUT/<cam>_json/`` (or ``INPUT/pose/<cam>_json/``)
  per camera, one ``<name><frame>.json`` per frame with ``people[].pose_keypoints_2d``
  = ``[x, y, c, ...]``; the camera is the folder's name without ``_json``, the frame
  the last run of digits in the file name.
- MMPose / RTMPose: one prediction JSON per camera (its stem is the camera):
  ``[{"frame_id", "instances": [{"keypoints": [[x, y], ...], "keypoint_scores"}]}]``
  as the inferencer saves a video, ``{"instance_info": [...]}`` as the demo scripts
  do, or ``{"predictions": [[instances], ...]}`` as the inferencer returns them.
- MediaPipe Pose: one JSON per camera, ``{"format": "mediapipe", "image_size": [W, H],
  "frames": [[{"x", "y", "visibility"} x 33] | [[...33], ...] | null, ...]}``,
  normalised coordinates unless ``"normalized": false`` (pixels).

Each camera's people are mapped onto the 13 joints and one person is followed
(:mod:`estimator.keypoints`); frames are aligned across cameras by number, and
only frames where at least two cameras see the person are kept.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimator.joints import N_JOINTS
from estimator.keypoints import SKELETONS, detect_skeleton, keypoints_to_joints, track_person

__all__ = ["KeypointError", "Keypoints", "camera_key", "camera_keypoints", "is_tracks_document", "keypoints_on", "keypoints_on_timeline",
           "match_cameras", "read_keypoints", "video_sizes"]


class KeypointError(ValueError):
    """Unreadable or unsupported keypoint input; the message names the file."""


@dataclass
class Keypoints:
    """Keypoints of one person in every camera, on posecal's 13 joints.

    Attributes
    ----------
    cameras : list of str
    tracks : ndarray of shape (C, T, 13, 2)
        Pixels, NaN where missing.
    confidence : ndarray of shape (C, T, 13)
        The detector's confidence, 0 where missing.
    frames : list of int
        The source frame number of each of the T frames.
    skeletons : dict of str to str
        Each camera's layout (a key of :data:`estimator.keypoints.SKELETONS`).
    format : str
        ``"openpose"``, ``"mmpose"`` or ``"mediapipe"``.
    """

    cameras: list[str]
    tracks: np.ndarray
    confidence: np.ndarray
    frames: list[int]
    skeletons: dict[str, str]
    format: str


@dataclass
class _Camera:
    """One camera's detections: per frame number, the people's keypoints (P, K, 2) and scores (P, K)."""

    name: str
    path: Path
    frames: dict[int, tuple[np.ndarray, np.ndarray]]
    files: dict[int, Path] | None = None  # per frame, when each frame has its own file


def is_tracks_document(doc: Any) -> bool:
    """True for posecal's own tracks JSON (``{"cameras": {...}}``)."""
    return isinstance(doc, dict) and isinstance(doc.get("cameras"), dict)


def read_keypoints(paths: Sequence[Path], *, min_confidence: float = 0.3,
                   image_size: tuple[int, int] | None = None, skeleton: str | None = None) -> Keypoints:
    """Read keypoint files or folders into tracks of one person per camera.

    Parameters
    ----------
    paths : sequence of Path
        One folder (OpenPose camera folders, or one JSON file per camera), or
        one JSON file per camera.
    min_confidence : float
        Keypoints below it are missing.
    image_size : (int, int), optional
        To convert MediaPipe's normalised coordinates when a file does not say.
    skeleton : str, optional
        The layout (a key of :data:`SKELETONS`); default: from the keypoint count.

    Raises
    ------
    KeypointError
        Naming the file or folder that is empty, unreadable or not understood.
    """
    paths = [Path(p) for p in paths]
    for p in paths:
        if not p.exists():
            raise KeypointError(f"no such file or folder: {p}")
    if len(paths) == 1 and paths[0].is_dir():
        fmt, cams = _read_folder(paths[0], image_size)
    elif all(p.is_file() for p in paths):
        loaded = [_read_camera_file(p, image_size) for p in paths]
        fmt, cams = loaded[0][0], [c for _, c in loaded]
    else:
        raise KeypointError(f"give one folder or one JSON file per camera, got {[str(p) for p in paths]}")
    names = [c.name for c in cams]
    if len(set(names)) != len(names):
        raise KeypointError(f"two cameras have the same name: {names}")
    if len(cams) < 2:
        raise KeypointError(f"need at least two cameras, found {len(cams)} in {', '.join(map(str, paths))}")
    return _assemble(fmt, cams, min_confidence, skeleton)


def _detections(cam: _Camera) -> tuple[np.ndarray, np.ndarray]:
    """Every detection's keypoints and scores of a camera whose frames agree on the keypoint count (a
    frame's trailing keypoints that no one shows are trimmed from ``cam.frames`` first: padding)."""
    numbers = sorted(cam.frames)
    if not numbers or not any(len(cam.frames[f][0]) for f in numbers):
        raise KeypointError(f"{cam.path}: no person detected in any frame")
    counts = {f: cam.frames[f][0].shape[1] for f in numbers if len(cam.frames[f][0])}
    usual = max(set(counts.values()), key=list(counts.values()).count)
    for f, k in counts.items():  # trailing keypoints never seen (score 0) are padding, as in _stack
        kp, sc = cam.frames[f]
        if k > usual and not sc[:, usual:].any():
            cam.frames[f], counts[f] = (kp[:, :usual], sc[:, :usual]), usual
    odd = next((f for f, k in counts.items() if k != usual), None)
    if odd is not None:
        raise KeypointError(f"{(cam.files or {}).get(odd, cam.path)}: frame {odd} has {counts[odd]} keypoints "
                            f"per person, the other frames of camera {cam.name!r} {usual}")
    return (np.concatenate([cam.frames[f][0] for f in counts]),
            np.concatenate([cam.frames[f][1] for f in counts]))


def _skeletons(cams: list[_Camera], detections: list, min_confidence: float, skeleton: str | None) -> list:
    """Each camera's layout: ``skeleton`` if given, else detected once over every camera with the same
    keypoint count (one detector wrote them; a side view alone hardly tells BODY_25 from BODY_25B)."""
    out, by_count = [], {}
    for cam, (kp, _) in zip(cams, detections):
        try:
            if skeleton:
                skel = SKELETONS[skeleton]
            elif kp.shape[1] in by_count:
                skel = by_count[kp.shape[1]]
            else:
                same = [d for d in detections if d[0].shape[1] == kp.shape[1]]
                skel = by_count[kp.shape[1]] = detect_skeleton(
                    np.concatenate([d[0] for d in same]), np.concatenate([d[1] for d in same]),
                    min_confidence=min_confidence)
            if skel.n_keypoints != kp.shape[1]:
                raise ValueError(f"{skel.name} has {skel.n_keypoints} keypoints, the detections {kp.shape[1]}")
        except ValueError as exc:
            raise KeypointError(f"{cam.path}: {exc}") from None
        out.append(skel)
    return out


def _assemble(fmt: str, cams: list[_Camera], min_confidence: float, skeleton: str | None) -> Keypoints:
    per_cam, layouts = [], {}
    detections = [_detections(cam) for cam in cams]
    skeletons = _skeletons(cams, detections, min_confidence, skeleton)
    for cam, skel in zip(cams, skeletons):
        numbers = sorted(cam.frames)
        try:
            people = [keypoints_to_joints(*cam.frames[f], skel, min_confidence=min_confidence)
                      if len(cam.frames[f][0]) else (np.zeros((0, N_JOINTS, 2)), np.zeros((0, N_JOINTS)))
                      for f in numbers]
        except ValueError as exc:
            raise KeypointError(f"{cam.path}: {exc}") from None
        chosen = track_person([j for j, _ in people])
        joints = {f: (people[k][0][i], people[k][1][i]) for k, (f, i) in enumerate(zip(numbers, chosen)) if i >= 0}
        per_cam.append(joints)
        layouts[cam.name] = skel.name
    frames = sorted(set().union(*per_cam))
    tracks = np.full((len(cams), len(frames), N_JOINTS, 2), np.nan)
    conf = np.zeros((len(cams), len(frames), N_JOINTS))
    for c, joints in enumerate(per_cam):
        for t, f in enumerate(frames):
            if f in joints:
                tracks[c, t], conf[c, t] = joints[f]
    seen = (np.isfinite(tracks).all(axis=-1).sum(axis=2) >= 4).sum(axis=0) >= 2  # (T,)
    keep = np.nonzero(seen)[0]
    if len(keep) < 2:
        raise KeypointError(f"fewer than two frames where two cameras see the person "
                            f"({', '.join(str(c.path) for c in cams)})")
    return Keypoints([c.name for c in cams], tracks[:, keep], conf[:, keep], [frames[t] for t in keep],
                     layouts, fmt)


def camera_key(name: str) -> str:
    """A camera name without case, separators or leading zeros: Pose2Sim calls the camera of the keypoint
    folder ``cam01_json`` ``cam_01`` in its calibration file; both give ``cam1``."""
    return re.sub(r"\d+", lambda m: str(int(m.group())), re.sub(r"[\W_]+", "", name.lower()))


def match_cameras(available: Iterable[str], wanted: Sequence[str]) -> dict[str, str]:
    """For each name of ``wanted``, the name of ``available`` that is the same camera: the same name, else
    the one equal up to :func:`camera_key` when that pairs them one to one; names without one are left out."""
    available = list(available)
    by_key: dict[str, list[str]] = {}
    for name in available:
        by_key.setdefault(camera_key(name), []).append(name)
    keys = [camera_key(w) for w in wanted]
    out = {}
    for name, key in zip(wanted, keys):
        if name in available:
            out[name] = name
        elif len(by_key.get(key, [])) == 1 and keys.count(key) == 1:
            out[name] = by_key[key][0]
    return out


def camera_keypoints(kp: Keypoints, camera: str) -> dict[int, np.ndarray]:
    """One camera's 13 joints (13, 2) per frame number (frames where it saw the person), the camera
    matched by name (:func:`match_cameras`): what a capture agent sends with its frames.

    Raises
    ------
    KeypointError
        No camera of the keypoints is ``camera``.
    """
    match = match_cameras(kp.cameras, [camera])
    if camera not in match:
        raise KeypointError(f"no camera {camera!r} among the keypoints' cameras {kp.cameras}")
    tracks = kp.tracks[kp.cameras.index(match[camera])]
    seen = np.isfinite(tracks).all(axis=2).any(axis=1)
    return {int(f): tracks[t] for t, f in enumerate(kp.frames) if seen[t]}


def keypoints_on(kp: Keypoints, cameras: Sequence[str], n_frames: int) -> dict[str, np.ndarray]:
    """Per recording camera, its keypoints' 13 joints on the recording's ``n_frames`` frames
    (n_frames, 13, 2), NaN where missed: cameras matched by name (:func:`match_cameras`), a
    keypoint frame number being the recording's frame index (keypoints beyond it are left out).

    Raises
    ------
    KeypointError
        No keypoint frame within the recording, or fewer than two cameras matched.
    """
    inside = np.array([0 <= f < n_frames for f in kp.frames], bool)  # Python ints: any size
    if not inside.any():
        raise KeypointError(f"frames {min(kp.frames)}-{max(kp.frames)}, the recording has 0-{n_frames - 1}")
    frames = np.array([f for f, i in zip(kp.frames, inside) if i], np.int64)
    out = {}
    for name, source in match_cameras(kp.cameras, list(cameras)).items():
        joints = np.full((n_frames, *kp.tracks.shape[2:]), np.nan)
        joints[frames] = kp.tracks[kp.cameras.index(source)][inside]
        out[name] = joints
    if len(out) < 2:
        raise KeypointError(f"cameras {kp.cameras} match fewer than two of the recording's ({', '.join(cameras)})")
    return out


def keypoints_on_timeline(kp: Keypoints, frames: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """:func:`keypoints_on` for recordings put on one timeline: ``frames`` gives, per camera, its
    own frame at each frame of the timeline (-1 where it has none;
    :func:`estimator.sync.timeline_frames`), as the keypoints are numbered by each video's
    own frames. Returns per matched camera (len(timeline), 13, 2), NaN where missed."""
    if not frames or all((k < 0).all() for k in frames.values()):
        raise KeypointError("no camera has a frame on the recording's timeline")
    own = keypoints_on(kp, list(frames), max(int(k.max(initial=-1)) + 1 for k in frames.values()))
    return {c: np.where((frames[c] >= 0)[:, None, None], j[np.maximum(frames[c], 0)], np.nan) for c, j in own.items()}


def video_sizes(root: Path, cameras: Sequence[str]) -> dict[str, tuple[tuple[int, int], Path]] | None:
    """Each camera's image size (width, height) and video, read from the videos next to its keypoints, or
    None unless every camera has exactly one.

    A Pose2Sim trial keeps its videos beside the keypoints (``videos/cam01.mp4`` next to
    ``pose/cam01_json``): the videos in ``root``, ``root/videos`` and, for a ``pose`` folder, its
    parent's ``videos``; a video is a camera's when its name, without case, separators or leading
    zeros, is the camera's or ends with it (``trial_cam01.mp4`` for ``cam01``). The size is the
    frame's as OpenCV decodes it.
    """
    from capture.sources import SourceError, VideoFileSource

    from .intake import list_videos

    root = Path(root)
    folders = [root, root / "videos"] + ([root.parent / "videos"] if root.name == "pose" else [])
    videos = [p for d in folders if d.is_dir() for p in list_videos(d).values()]
    out = {}
    for cam in cameras:
        mine = [p for p in videos if camera_key(p.stem).endswith(camera_key(cam))]
        if len(mine) != 1:
            return None
        try:
            with VideoFileSource(mine[0]) as source:
                size = source.size
        except SourceError:
            return None
        if size is None:
            return None
        out[cam] = size, mine[0]
    return out


# ------------------------------------------------------------------ folders and files


def _read_folder(root: Path, image_size) -> tuple[str, list[_Camera]]:
    for base in (root, root / "pose"):
        dirs = sorted(d for d in base.glob("*_json") if d.is_dir()) if base.is_dir() else []
        if dirs:
            return "openpose", [_read_openpose_camera(d) for d in dirs]
    files = sorted(p for p in root.glob("*.json") if p.is_file())
    if not files:
        raise KeypointError(f"{root}: no <camera>_json folders (OpenPose, also under pose/) and no "
                            f"JSON files (one per camera: MMPose or MediaPipe)")
    loaded = [_read_camera_file(p, image_size) for p in files]
    formats = {f for f, _ in loaded}
    if len(formats) > 1:
        raise KeypointError(f"{root}: the camera files mix formats {sorted(formats)}")
    return loaded[0][0], [c for _, c in loaded]


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KeypointError(f"cannot read {path}: {exc}") from None
    except RecursionError:
        raise KeypointError(f"cannot read {path}: it nests too deeply") from None


def _frame_number(path: Path) -> int:
    runs = re.findall(r"\d+", path.stem)
    if not runs:
        raise KeypointError(f"{path}: no frame number in the file name")
    return int(runs[-1])


def _read_openpose_camera(folder: Path) -> _Camera:
    files = sorted(folder.glob("*.json"))
    if not files:
        raise KeypointError(f"{folder}: no JSON files")
    frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    paths: dict[int, Path] = {}
    for path in files:
        number = _frame_number(path)
        paths[number] = path
        if number in frames:
            raise KeypointError(f"{path}: frame {number} appears twice in {folder}")
        doc = _load_json(path)
        if not isinstance(doc, dict) or not isinstance(doc.get("people"), list):
            raise KeypointError(f'{path}: expected an OpenPose object with "people": [...]')
        flat = []
        for k, person in enumerate(doc["people"]):
            values = person.get("pose_keypoints_2d") if isinstance(person, dict) else None
            arr = _numbers(values, path, f"people[{k}].pose_keypoints_2d")
            if arr.size % 3:
                raise KeypointError(f"{path}: people[{k}].pose_keypoints_2d has {arr.size} numbers, "
                                    f"not a multiple of 3 (x, y, c)")
            flat.append(arr.reshape(-1, 3))
        frames[number] = _stack(flat, path)
    return _Camera(folder.name[: -len("_json")], folder, frames, paths)


def _numbers(values: Any, path: Path, where: str) -> np.ndarray:
    """A list of numbers (or nested lists of them) as a float array; KeypointError naming the file."""
    try:
        if values is None:
            raise TypeError
        return np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise KeypointError(f"{path}: {where} must be numbers") from None


def _stack(people: list[np.ndarray], path: Path) -> tuple[np.ndarray, np.ndarray]:
    """People as (P, K, 3) [x, y, c] -> keypoints (P, K, 2), scores (P, K)."""
    if not people:
        return np.zeros((0, 0, 2)), np.zeros((0, 0))
    k = min(p.shape[0] for p in people)
    if any((p[k:, 2] != 0).any() for p in people):
        raise KeypointError(f"{path}: people with different keypoint counts "
                            f"{sorted({p.shape[0] for p in people})}")
    arr = np.stack([p[:k] for p in people])  # trailing keypoints never seen (c = 0) are padding
    return arr[..., :2], arr[..., 2]


def _read_camera_file(path: Path, image_size) -> tuple[str, _Camera]:
    doc = _load_json(path)
    if is_tracks_document(doc):
        raise KeypointError(f"{path}: a posecal tracks document holds every camera; give it alone")
    if isinstance(doc, dict) and doc.get("format") == "mediapipe" or _looks_mediapipe(doc):
        return "mediapipe", _Camera(path.stem, path, _mediapipe_frames(doc, path, image_size))
    return "mmpose", _Camera(path.stem, path, _mmpose_frames(doc, path))


def _looks_mediapipe(doc: Any) -> bool:
    frames = doc.get("frames") if isinstance(doc, dict) else doc
    if not isinstance(frames, list):
        return False
    for fr in frames:
        while isinstance(fr, list) and fr and isinstance(fr[0], list):
            fr = fr[0]
        if isinstance(fr, list) and fr:
            return isinstance(fr[0], dict) and "x" in fr[0] and "y" in fr[0]
    return False


def _mmpose_frames(doc: Any, path: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    if isinstance(doc, dict) and isinstance(doc.get("instance_info"), list):
        doc = doc["instance_info"]
    if isinstance(doc, dict) and isinstance(doc.get("predictions"), list):
        entries = [(i, inst) for i, inst in enumerate(doc["predictions"])]
    elif isinstance(doc, list) and all(isinstance(e, dict) and "instances" in e for e in doc):
        entries = [(e.get("frame_id", i), e["instances"]) for i, e in enumerate(doc)]
    elif isinstance(doc, list) and all(isinstance(e, dict) and "keypoints" in e for e in doc):
        entries = [(0, doc)]  # one image's instances
    else:
        raise KeypointError(f"{path}: not an MMPose prediction file (expected [{{\"frame_id\", \"instances\"}}], "
                            f"{{\"instance_info\": [...]}} or {{\"predictions\": [...]}}), nor MediaPipe landmarks")
    frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for number, instances in entries:
        if isinstance(number, bool) or not isinstance(number, int) or number in frames:
            raise KeypointError(f"{path}: bad or repeated frame_id {number!r}")
        if not isinstance(instances, list):
            raise KeypointError(f"{path}: frame {number}: instances must be a list")
        people = []
        for k, inst in enumerate(instances):
            if not isinstance(inst, dict) or "keypoints" not in inst:
                raise KeypointError(f"{path}: frame {number} instance {k}: no \"keypoints\"")
            kp = _numbers(inst["keypoints"], path, f"frame {number} instance {k} keypoints")
            if kp.ndim != 2 or kp.shape[1] < 2:
                raise KeypointError(f"{path}: frame {number} instance {k}: keypoints must be [[x, y], ...]")
            sc = (_numbers(inst["keypoint_scores"], path, f"frame {number} instance {k} keypoint_scores")
                  if "keypoint_scores" in inst else np.ones(len(kp)))
            if sc.shape != (len(kp),):
                raise KeypointError(f"{path}: frame {number} instance {k}: {len(kp)} keypoints "
                                    f"but {sc.size} keypoint_scores")
            people.append(np.column_stack([kp[:, :2], sc]))
        frames[number] = _stack(people, path)
    return frames


def _mediapipe_frames(doc: Any, path: Path, image_size) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    meta = doc if isinstance(doc, dict) else {}
    frames = meta.get("frames") if isinstance(doc, dict) else doc
    if not isinstance(frames, list):
        raise KeypointError(f'{path}: MediaPipe landmarks need "frames": [...]')
    normalised = meta.get("normalized", True)
    size = meta.get("image_size", image_size)
    if normalised:
        if size is None:
            raise KeypointError(f"{path}: normalised MediaPipe landmarks need the image size "
                                f"(\"image_size\" in the file or --image-size W,H)")
        scale = _numbers(size, path, "image_size")
        if scale.shape != (2,) or not (scale > 0).all():
            raise KeypointError(f"{path}: image_size must be [W, H], got {size!r}")
    else:
        scale = np.ones(2)
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for t, frame in enumerate(frames):
        if not frame:
            out[t] = _stack([], path)
            continue
        people = frame if isinstance(frame, list) and isinstance(frame[0], list) else [frame]
        rows = []
        for k, person in enumerate(people):
            if not isinstance(person, list) or not all(isinstance(p, dict) for p in person):
                raise KeypointError(f"{path}: frame {t} person {k}: expected a list of landmark objects")
            try:
                rows.append(np.array([[float(p["x"]) * scale[0], float(p["y"]) * scale[1],
                                       min(float(p.get("visibility", 1.0)), float(p.get("presence", 1.0)))]
                                      for p in person]))
            except (KeyError, TypeError, ValueError):
                raise KeypointError(f"{path}: frame {t} person {k}: each landmark needs numbers "
                                    f"\"x\", \"y\" (and \"visibility\")") from None
        out[t] = _stack(rows, path)
    return out
