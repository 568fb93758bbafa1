"""Upload intake: unpack and validate a job's upload, checking before spending.

:func:`stage_upload` runs in the API's thread pool when a job is submitted,
so a bad upload is answered with a 4xx at once (:class:`UploadError`). Every
size is read from a header before the data it describes is touched: the zip's
directory (member count, declared sizes, paths and frame numbers) before
extracting, each PNG's ``IHDR`` before any is decoded, a video container's
frame size and count before its frames are. Extraction counts the bytes it
writes, so a member whose header lies cannot pass the limit either. The limits
are :class:`service.limits.UploadLimits` (docs/SERVICE.md, "Limits and refusals").
"""

from __future__ import annotations

import errno
import glob
import json
import lzma
import math
import os
import re
import shutil
import struct
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from capture.sources import PLATE_SUFFIXES
from capture.wire import png_size
from estimator.sequence import read_sequence

from .limits import UploadLimits

__all__ = ["VIDEO_EXTENSIONS", "StagedInput", "UploadError", "list_videos", "stage_keypoints", "stage_upload"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v")
_MAX_ZIP_MEMBERS = 200_000


def list_videos(folder: str | Path) -> dict[str, Path]:
    """The videos of a folder of one video per camera: camera name (the file's stem) -> path, sorted."""
    return {p.stem: p for p in sorted(Path(folder).iterdir())
            if p.suffix.lower() in VIDEO_EXTENSIONS and p.is_file()}
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")  # camera names (as on the wire)
_CHUNK = 1 << 20
# What reading a damaged or hostile zip raises (bz2 raises OSError; encrypted: RuntimeError).
_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, lzma.LZMAError, EOFError, OSError, ValueError,
               NotImplementedError, RuntimeError, struct.error, OverflowError)


class UploadError(ValueError):
    """A rejected upload: ``status`` is the HTTP code, ``str()`` the reason."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status


@dataclass(frozen=True)
class StagedInput:
    """A validated job input on disk.

    ``frame_counts``: per camera of a video upload, the frame count its
    container's header gives (0 = not given); the job compares it with the
    frames that decode.
    """

    kind: str  # "sequence" | "videos"
    path: Path  # the sequence folder, or the folder of <camera>.<ext> videos
    cameras: list[str]
    n_frames: int
    frame_counts: dict[str, int] = field(default_factory=dict)


def stage_upload(files: list[tuple[str, BinaryIO]], job_dir: Path, limits: UploadLimits) -> StagedInput:
    """Unpack and validate an upload into ``job_dir``; raise :class:`UploadError` if bad.

    ``files`` are ``(filename, file object)``: one ``.zip`` holding a sequence
    folder (``rig.json`` at its top or in its single top folder), or one video
    per camera named ``<camera>.<ext>``. The caller removes ``job_dir`` when
    this raises.
    """
    if not files:
        raise UploadError(422, "no files uploaded: send one zipped sequence folder or one video per camera")
    try:
        job_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # no inode left for the folder
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise UploadError(507, "no space left to store the upload") from None
        raise
    names = [Path(name or "").name for name, _ in files]
    if len(files) == 1 and names[0].lower().endswith(".zip"):
        return _stage_zip(files[0][1], job_dir, limits)
    if all(n.lower().endswith(VIDEO_EXTENSIONS + PLATE_SUFFIXES) for n in names) and \
            any(n.lower().endswith(VIDEO_EXTENSIONS) for n in names):
        return _stage_videos(files, job_dir, limits)
    raise UploadError(415, f"expected one .zip sequence folder or videos ({', '.join(VIDEO_EXTENSIONS)}), "
                           f"got {names}")


def stage_keypoints(fh: BinaryIO, job_dir: Path, limits: UploadLimits, staged: StagedInput) -> Path:
    """Unpack and check a zip of a detector's keypoints for the staged recording; the folder to read.

    The zip holds what :func:`service.keypoints_io.read_keypoints` reads
    (OpenPose ``<camera>_json`` folders, also under ``pose/``; or one MMPose or
    MediaPipe JSON file per camera), at its top or in its single top folder;
    frame numbers are the recording's frame indices, and at least two cameras
    must match the recording's by name. :class:`UploadError` (422) says what
    does not fit.
    """
    from .keypoints_io import KeypointError, keypoints_on, read_keypoints

    out = job_dir / "keypoints"
    _unzip(fh, out, limits, "keypoints: not a readable zip file")
    tops = [p for p in out.iterdir() if p.name != "__MACOSX"]
    root = tops[0] if len(tops) == 1 and tops[0].is_dir() and not tops[0].name.endswith("_json") else out
    try:
        kp = read_keypoints([root])
        # a video whose header gives no frame count (0): the frames are checked when it is decoded
        keypoints_on(kp, staged.cameras, staged.n_frames or max(kp.frames) + 1)
    except KeypointError as exc:
        raise UploadError(422, "keypoints: " + str(exc).replace(str(out) + os.sep, "").replace(str(out), ".")
                          ) from None
    except (ValueError, IndexError, TypeError, RecursionError, OverflowError) as exc:  # a file that lies
        raise UploadError(422, f"keypoints: not understood ({type(exc).__name__})") from None
    return root


# ------------------------------------------------------------------------------ zip


def _frame_number(stem: str) -> int | None:
    """The frame number of a PNG named ``<digits>.png`` (ASCII digits only), else None."""
    if not stem or not stem.isascii() or not stem.isdigit():
        return None
    return int(stem) if len(stem) <= 18 else 10 ** 18  # int() of a 5,000-digit name is refused


def _unzip(fh: BinaryIO, out: Path, limits: UploadLimits, unreadable: str) -> None:
    """Check a zip's directory (:func:`_check_members`), then extract it into ``out`` counting what is
    written; 400 with ``unreadable`` when it is not a zip."""
    try:
        zf = zipfile.ZipFile(fh)
    except _ZIP_ERRORS as exc:
        raise UploadError(400, f"{unreadable}: {exc}") from None
    with zf:
        members = zf.infolist()
        _check_members(members, out, limits)
        _extract(zf, members, out, limits)


def _stage_zip(fh: BinaryIO, job_dir: Path, limits: UploadLimits) -> StagedInput:
    out = job_dir / "input"
    _unzip(fh, out, limits, "the upload is not a readable zip file")
    folder = _find_sequence_root(out)
    _check_sequence_headers(folder, limits)
    try:
        seq = read_sequence(folder)
    except (ValueError, OverflowError, RecursionError) as exc:  # SequenceError names the file
        raise UploadError(422, str(exc).replace(str(out) + os.sep, "")) from None
    if all(s is None or not s.any() for sils in seq.silhouettes.values() for s in sils):
        raise UploadError(422, "the sequence holds no silhouette pixels")
    return StagedInput("sequence", folder, list(seq.cameras), seq.n_frames)


def _check_members(members: list[zipfile.ZipInfo], out: Path, limits: UploadLimits) -> None:
    """The zip's directory, before anything is extracted: count, declared sizes, paths, frame numbers."""
    if not members:
        raise UploadError(422, "the zip file is empty")
    if len(members) > _MAX_ZIP_MEMBERS:
        raise UploadError(413, f"the zip holds {len(members)} files, more than {_MAX_ZIP_MEMBERS}")
    declared = sum(m.file_size for m in members)
    if declared > limits.unpacked_bytes:
        raise UploadError(413, f"the zip expands to {declared} bytes, more than the limit of "
                               f"{limits.unpacked_bytes}")
    root = out.resolve()
    for m in members:
        if not (out / m.filename).resolve().is_relative_to(root):
            raise UploadError(400, f"zip member {m.filename!r} points outside the archive")
        path = PurePosixPath(m.filename)
        number = _frame_number(path.stem) if path.suffix.lower() == ".png" else None
        if number is not None and number >= limits.max_frames:
            raise UploadError(413, f"{m.filename}: frame number {path.stem} is beyond the limit of "
                                   f"{limits.max_frames} frames per camera")


def _extract(zf: zipfile.ZipFile, members: list[zipfile.ZipInfo], out: Path, limits: UploadLimits) -> None:
    """Extract, counting what is written: a member larger than it declared, or all of them
    beyond ``limits.unpacked_bytes``, stops it (a header can lie). Reading checks each CRC."""
    total = 0
    for m in members:
        target = out / m.filename
        try:
            if m.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            with open(target, "wb") as dst:
                src = _open_member(zf, m)
                written = 0
                while chunk := _read_member(src, m):
                    written += len(chunk)
                    total += len(chunk)
                    if written > m.file_size:
                        raise UploadError(400, f"corrupt zip file: {m.filename} expands beyond the "
                                               f"{m.file_size} bytes its header declares")
                    if total > limits.unpacked_bytes:
                        raise UploadError(413, f"the zip expands to more than the limit of "
                                               f"{limits.unpacked_bytes} bytes")
                    dst.write(chunk)
        except OSError as exc:  # writing: a full disk is ours, a bad name is the upload's
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise UploadError(507, f"no space left to unpack {m.filename}") from None
            raise UploadError(400, f"zip member {m.filename!r} cannot be unpacked: {exc.strerror}") from None


def _open_member(zf: zipfile.ZipFile, m: zipfile.ZipInfo):
    try:
        return zf.open(m)
    except _ZIP_ERRORS as exc:
        raise UploadError(400, f"corrupt zip file: {m.filename}: {exc}") from None


def _read_member(src, m: zipfile.ZipInfo) -> bytes:
    try:
        return src.read(_CHUNK)
    except _ZIP_ERRORS as exc:  # damage testzip() would find: bad CRC, bad deflate stream
        raise UploadError(400, f"corrupt zip file: {m.filename}: {exc}") from None


def _find_sequence_root(out: Path) -> Path:
    if (out / "rig.json").is_file():
        return out
    tops = [p for p in out.iterdir() if p.name != "__MACOSX"] if out.is_dir() else []
    if len(tops) == 1 and tops[0].is_dir() and (tops[0] / "rig.json").is_file():
        return tops[0]
    raise UploadError(422, "no rig.json at the top of the zip (or in its single top folder): "
                           "zip a sequence folder, see docs/FORMATS.md")


# --------------------------------------------------------------- sequence folder headers


def _read_json(path: Path, limits: UploadLimits) -> Any:
    """A small JSON file of the upload, or :class:`UploadError` naming it."""
    size = path.stat().st_size
    if size > limits.max_json_bytes:
        raise UploadError(413, f"{path.name} is {size} bytes, more than the limit of {limits.max_json_bytes}")
    try:
        return json.loads(path.read_bytes())
    except (ValueError, RecursionError) as exc:  # RecursionError: nested too deeply
        reason = "nests too deeply" if isinstance(exc, RecursionError) else f"is not valid JSON: {exc}"
        raise UploadError(422, f"{path.name} {reason}") from None


def _png_size(path: Path, shown: str) -> tuple[int, int]:
    """Width and height from a PNG's ``IHDR`` (the first chunk), without decoding it."""
    if not path.is_file():
        raise UploadError(422, f"{shown}: not a readable PNG")
    with open(path, "rb") as fh:
        size = png_size(fh.read(24))
    if size is None:
        raise UploadError(422, f"{shown}: not a readable PNG (no PNG header)")
    width, height = size
    if width == 0 or height == 0:
        raise UploadError(422, f"{shown}: not a readable PNG (its header says {width}x{height})")
    return width, height


def _check_sequence_headers(folder: Path, limits: UploadLimits) -> None:
    """What reading the sequence would cost, from rig.json and the PNG headers: 413 or 422
    naming the file before any PNG is decoded. What is missing is left to ``read_sequence``."""
    rig = _read_json(folder / "rig.json", limits)
    if (folder / "truth.json").is_file():
        _read_json(folder / "truth.json", limits)
    try:
        cameras = [str(c) for c in rig["cameras"]]
        width, height = (int(v) for v in rig["image_size"])
        fps = float(rig["fps"])
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise UploadError(422, f"rig.json needs fps, cameras and image_size [w, h] (finite numbers): "
                               f"{exc}, see docs/FORMATS.md") from None
    if not math.isfinite(fps):
        raise UploadError(422, f"rig.json: fps must be a finite number, got {fps}")
    if len(cameras) > limits.max_cameras:
        raise UploadError(413, f"rig.json names {len(cameras)} cameras, more than the limit of "
                               f"{limits.max_cameras}")
    for cam in cameras:
        if not _NAME.match(cam) or cam in (".", ".."):
            raise UploadError(422, f"rig.json: camera name {cam!r} must match {_NAME.pattern} "
                                   "(it names the camera's folder)")
    why = limits.image_refusal(width, height)
    if why is not None:
        raise UploadError(413, f"rig.json: image_size {why}")
    decoded = 0
    for cam in cameras:
        cam_dir = folder / cam
        if not cam_dir.is_dir():
            continue  # read_sequence names the missing folder
        for entry in os.scandir(cam_dir):
            stem, ext = os.path.splitext(entry.name)
            if ext.lower() != ".png":
                continue
            shown = f"{cam}/{entry.name}"
            number = _frame_number(stem)
            if number is None:
                raise UploadError(422, f"{shown}: frame files must be named by frame number, e.g. 000012.png")
            if number >= limits.max_frames:
                raise UploadError(413, f"{shown}: frame number {stem} is beyond the limit of "
                                       f"{limits.max_frames} frames per camera")
            w, h = _png_size(Path(entry.path), shown)
            why = limits.image_refusal(w, h)
            if why is not None:
                raise UploadError(413, f"{shown}: the PNG header says {why}")
            if w > width or h > height:
                raise UploadError(422, f"{shown}: {w}x{h} exceeds the image size {width}x{height} of rig.json")
            decoded += w * h
            if decoded > limits.decoded_bytes:
                raise UploadError(413, f"the sequence's PNGs hold more than {limits.decoded_bytes} pixels "
                                       f"(the limit), reached at {shown}")


# ---------------------------------------------------------------------------- videos


def _stage_videos(files: list[tuple[str, BinaryIO]], job_dir: Path, limits: UploadLimits) -> StagedInput:
    """One video per camera, and an image of the empty scene for any of them (``<camera>.background.png``,
    ``.jpg``, ``.jpeg``: the segmenter's background, :func:`capture.refine.plate_for`)."""
    plates = [(n, fh) for n, fh in files if Path(n or "").name.lower().endswith(PLATE_SUFFIXES)]
    files = [(n, fh) for n, fh in files if not Path(n or "").name.lower().endswith(PLATE_SUFFIXES)]
    if len(files) > limits.max_cameras:
        raise UploadError(413, f"{len(files)} videos, more than the limit of {limits.max_cameras} cameras")
    folder = job_dir / "videos"
    folder.mkdir(parents=True, exist_ok=True)
    cameras, sizes, counts = [], {}, {}
    for name, fh in files:
        path = Path(Path(name).name)
        cam = path.stem
        if not _NAME.match(cam) or cam in (".", ".."):
            raise UploadError(422, f"video {path.name!r}: the file name (without extension) is the "
                                   f"camera name and must match {_NAME.pattern}")
        if cam in cameras:
            raise UploadError(422, f"two videos for camera {cam!r}")
        target = folder / f"{cam}{path.suffix.lower()}"
        _store(fh, target, f"video {path.name}")
        sizes[cam], counts[cam] = probe_video(target, path.name, limits)
        cameras.append(cam)
    if len(set(sizes.values())) != 1:
        raise UploadError(422, f"videos of one rig must have the same frame size, got {sizes}")
    for name, fh in plates:
        _stage_plate(Path(Path(name).name), fh, folder, sizes)
    return StagedInput("videos", folder, cameras, max(counts.values()), frame_counts=counts)


def _store(fh: BinaryIO, target: Path, shown: str) -> None:
    """Copy an uploaded file to ``target``; a full disk is ours (507, naming ``shown``), and the
    caller removes the job's folder."""
    try:
        with open(target, "wb") as out:
            shutil.copyfileobj(fh, out, _CHUNK)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise UploadError(507, f"no space left to store {shown}") from None
        raise


def _stage_plate(path: Path, fh: BinaryIO, folder: Path, sizes: dict[str, tuple[int, int]]) -> None:
    """Store ``<camera>.background.<ext>`` beside its camera's video, checked: an image of that video's size."""
    import cv2

    cam, ext = path.name[:path.name.lower().rindex(".background")], path.suffix.lower()
    if cam not in sizes:
        raise UploadError(422, f"{path.name}: an image of the empty scene for camera {cam!r}, which has no video")
    target = folder / f"{cam}.background{ext}"
    if any(folder.glob(f"{glob.escape(cam)}.background.*")):
        raise UploadError(422, f"two images of the empty scene for camera {cam!r}")
    _store(fh, target, path.name)
    size = _image_size(target)  # from the header: a 100000 x 100000 image is refused before it is decoded
    if size is not None and size != tuple(sizes[cam]):
        raise UploadError(422, f"{path.name} is {size[0]}x{size[1]}, its video {sizes[cam][0]}x{sizes[cam][1]}: "
                               "the image of the empty scene must be the video's frame size")
    if size is None or cv2.imread(str(target), cv2.IMREAD_COLOR) is None:
        raise UploadError(422, f"{path.name}: not a readable image (PNG or JPEG)")


def _image_size(path: Path) -> tuple[int, int] | None:
    """Width and height of a PNG (its ``IHDR``) or a JPEG (its first start-of-frame marker) from the
    header, without decoding; None when it is neither."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    if (size := png_size(head)) is not None:
        return size
    if head[:2] != b"\xff\xd8":
        return None
    k = 2
    while k + 9 <= len(head) and head[k] == 0xFF:
        marker, length = head[k + 1], struct.unpack(">H", head[k + 2:k + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn: precision, height, width
            height, width = struct.unpack(">HH", head[k + 5:k + 9])
            return width, height
        k += 2 + length
    return None


def _prop(cap, prop: int) -> int:
    value = cap.get(prop)
    return int(value) if math.isfinite(value) and value > 0 else 0


def probe_video(path: Path, shown: str, limits: UploadLimits | None) -> tuple[tuple[int, int], int]:
    """``((width, height), frame count)`` of a video from its container's header, checked
    against ``limits`` (None: no limits, ``posecal estimate``'s own files) before a frame is
    decoded; then its first frame must decode.

    A count of 0 means the container does not give one (the job then decodes at
    most ``limits.max_frames``).
    """
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise UploadError(422, f"video {shown!r} cannot be decoded (no stream OpenCV can open)")
        width, height = _prop(cap, cv2.CAP_PROP_FRAME_WIDTH), _prop(cap, cv2.CAP_PROP_FRAME_HEIGHT)
        count = _prop(cap, cv2.CAP_PROP_FRAME_COUNT)
        why = None if limits is None else limits.image_refusal(width, height)
        if why is not None:
            raise UploadError(413, f"video {shown!r}: its header says frames of {why}")
        if limits is not None and count > limits.max_frames:
            raise UploadError(413, f"video {shown!r}: its header counts {count} frames, more than the "
                                   f"limit of {limits.max_frames} per camera")
        ok, frame = cap.read()
    except cv2.error as exc:
        raise UploadError(422, f"video {shown!r} cannot be decoded: {exc}") from None
    finally:
        cap.release()
    if not ok or frame is None:
        raise UploadError(422, f"video {shown!r} cannot be decoded")
    size = (frame.shape[1], frame.shape[0])
    why = None if limits is None else limits.image_refusal(*size)
    if why is not None:  # a header without a size, or a wrong one
        raise UploadError(413, f"video {shown!r}: frames of {why}")
    return size, count
