"""The sequence folder of DESIGN.md: ``rig.json``, per-camera PNG silhouettes, ``truth.json``.

One reader and one writer, shared by ``posecal synth``, ``posecal estimate`` and
the REST API. Reading validates and raises :class:`SequenceError` with a message
that names the file and what was wrong.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["Sequence", "SequenceError", "read_sequence", "write_sequence"]


class SequenceError(ValueError):
    """A sequence folder that cannot be used, and why."""


@dataclass
class Sequence:
    """Silhouettes of several synchronized cameras.

    Attributes
    ----------
    fps : float
    cameras : list of str
    image_size : (int, int)
        (width, height) of the full frames.
    silhouettes : dict of str to list of (ndarray of shape (h, w), uint8, or None)
        Per camera, per frame: the silhouette (full frame, or a crop when its
        size differs from ``image_size``), or None where the camera has no data.
    truth : dict or None
        Ground truth in the result format of DESIGN.md, when known.
    """

    fps: float
    cameras: list[str]
    image_size: tuple[int, int]
    silhouettes: dict[str, list[np.ndarray | None]]
    truth: dict | None = None
    extra: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return max((len(v) for v in self.silhouettes.values()), default=0)

    def rig(self) -> dict:
        return {"fps": self.fps, "cameras": list(self.cameras), "image_size": list(self.image_size), **self.extra}


def write_sequence(path: str | os.PathLike, sequence: Sequence) -> None:
    """Write a sequence folder (creating it); frames that are None are not written.

    Frame PNGs and ``truth.json`` left in the folder by an earlier sequence are
    removed first, so the folder holds this sequence only.
    """
    os.makedirs(path, exist_ok=True)
    for cam in sequence.cameras:
        folder = os.path.join(path, cam)
        if os.path.isdir(folder):
            for name in os.listdir(folder):
                stem, ext = os.path.splitext(name)
                if ext.lower() == ".png" and stem.isdigit():
                    os.remove(os.path.join(folder, name))
    if sequence.truth is None and os.path.exists(os.path.join(path, "truth.json")):
        os.remove(os.path.join(path, "truth.json"))
    with open(os.path.join(path, "rig.json"), "w") as fh:
        json.dump(sequence.rig(), fh, indent=1)
    for cam in sequence.cameras:
        folder = os.path.join(path, cam)
        os.makedirs(folder, exist_ok=True)
        for k, sil in enumerate(sequence.silhouettes[cam]):
            if sil is not None and not cv2.imwrite(os.path.join(folder, f"{k:06d}.png"), sil):
                raise OSError(f"could not write {folder}/{k:06d}.png")
    if sequence.truth is not None:
        with open(os.path.join(path, "truth.json"), "w") as fh:
            json.dump(sequence.truth, fh)


def _load_json(path: str) -> dict:
    try:
        with open(path) as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise SequenceError(f"{path} is missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SequenceError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise SequenceError(f"{path} must hold a JSON object")
    return data


def _binary(folder: str, frames: dict[int, np.ndarray], n: int) -> list[np.ndarray | None]:
    """One camera's grayscale frames as 0/255 silhouettes (index = frame number).

    A pixel > 127 is the walker, but for masks of two values, 0 and one other, as segmentation
    tools write them in any encoding (0/1, a class index, a colour read as grey): that value.
    Two-valued masks whose walker covers more than half of every frame and all four of its
    borders are inverted (the walker written dark on light): a SequenceError says so.
    """
    values = np.flatnonzero(sum(np.bincount(f.ravel(), minlength=256) for f in frames.values()))
    two = values.size == 2 and values[0] == 0
    out = {k: np.where(f > (0 if two else 127), np.uint8(255), np.uint8(0)) for k, f in frames.items()}
    if two and all(_inverted(f) for f in out.values()):
        raise SequenceError(f"{folder}: the masks look inverted (value {values[1]} covers more than half of every "
                            "frame and touches all its borders): write the walker as the non-zero value on 0")
    return [out.get(k) for k in range(n)]


def _inverted(sil: np.ndarray) -> bool:
    """Whether a silhouette covers more than half its frame and all four borders."""
    border = sil[0].any() and sil[-1].any() and sil[:, 0].any() and sil[:, -1].any()
    return bool(border and np.count_nonzero(sil) > sil.size / 2)


def read_sequence(path: str | os.PathLike) -> Sequence:
    """Read and validate a sequence folder of PNG silhouettes."""
    path = os.fspath(path)
    if not os.path.isdir(path):
        raise SequenceError(f"{path} is not a folder")
    rig = _load_json(os.path.join(path, "rig.json"))
    try:
        fps = float(rig["fps"])
        cameras = [str(c) for c in rig["cameras"]]
        width, height = (int(v) for v in rig["image_size"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SequenceError(f"{path}/rig.json needs fps, cameras and image_size [w, h]: {exc}") from None
    if fps <= 0 or not cameras or width < 1 or height < 1:
        raise SequenceError(f"{path}/rig.json: fps and image size must be positive and cameras non-empty")
    if len(set(cameras)) != len(cameras):
        raise SequenceError(f"{path}/rig.json: camera names repeat: {cameras}")
    silhouettes: dict[str, list[np.ndarray | None]] = {}
    for cam in cameras:
        folder = os.path.join(path, cam)
        if not os.path.isdir(folder):
            raise SequenceError(f"{folder}: no folder for camera {cam!r}")
        frames: dict[int, np.ndarray] = {}
        for name in sorted(os.listdir(folder)):
            stem, ext = os.path.splitext(name)
            if ext.lower() != ".png":
                continue
            if not stem.isdigit():
                raise SequenceError(f"{folder}/{name}: frame files must be named by frame number, e.g. 000012.png")
            image = cv2.imread(os.path.join(folder, name), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise SequenceError(f"{folder}/{name}: not a readable PNG")
            if image.shape[0] > height or image.shape[1] > width:
                raise SequenceError(f"{folder}/{name}: {image.shape[1]}x{image.shape[0]} exceeds the image size {width}x{height}")
            frames[int(stem)] = image
        if not frames:
            raise SequenceError(f"{folder}: no PNG silhouettes for camera {cam!r}")
        silhouettes[cam] = _binary(folder, frames, max(frames) + 1)
    truth_path = os.path.join(path, "truth.json")
    truth = _load_json(truth_path) if os.path.exists(truth_path) else None
    extra = {k: v for k, v in rig.items() if k not in ("fps", "cameras", "image_size")}
    return Sequence(fps=fps, cameras=cameras, image_size=(width, height), silhouettes=silhouettes, truth=truth, extra=extra)
