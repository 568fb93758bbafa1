"""A scripted test scene with exact ground truth, for tests and benchmarks.

A textured background (seeded noise, blurred into blobs) with a dark ellipse
"walker" crossing it, sensor noise and a slow lighting drift. The first
``empty`` frames have no walker, as the paper's background learning wants
(§7). Masks are known exactly, so segmentation IoU is measurable, and the
frames can be written as a video or a PNG folder to exercise the file sources.
This is not the synthetic camera (``capture/synthetic.py``), which renders the
articulated walker.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .sources import Frame

__all__ = ["SceneSpec", "iou", "scene_frames", "textured_background", "write_folder", "write_video"]


@dataclass(frozen=True)
class SceneSpec:
    """What to draw; defaults give a 640x480, 30 fps, 4 s clip."""

    width: int = 640
    height: int = 480
    frames: int = 120
    empty: int = 100
    fps: float = 30.0
    seed: int = 0
    noise_sigma: float = 3.0
    drift: float = 0.05  # relative brightness change over the clip
    crossing: int = 120  # frames per crossing of the view (~4 s at 30 fps: walking speed)
    walker_alpha: float = 0.7  # walker = blend of background and clothing colour (0 = invisible)
    walker_bgr: tuple[int, int, int] = (40, 50, 120)
    passer_behind: bool = False  # someone dressed alike walking the other way, farther off (higher in the image)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two same-shape masks (non-zero = inside)."""
    a, b = a > 0, b > 0
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def textured_background(width: int, height: int, rng: np.random.Generator, *, saturation: float = 1.0) -> np.ndarray:
    """A textured scene, float32 BGR (H, W, 3): coarse colour blobs plus fine grain.

    ``saturation`` < 1 mutes the blobs' colours towards their grey (a room
    rather than confetti).
    """
    small = rng.integers(40, 220, (height // 16 + 1, width // 16 + 1, 3)).astype(np.float32)
    small = saturation * small + (1.0 - saturation) * small.mean(axis=2, keepdims=True)
    base = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    fine = rng.normal(0, 12, (height, width, 3))
    return np.clip(base + fine, 0, 255).astype(np.float32)


def scene_frames(spec: SceneSpec = SceneSpec()) -> Iterator[Frame]:
    """Yield ``spec.frames`` frames with ground-truth masks; deterministic in ``seed``."""
    rng = np.random.default_rng(spec.seed)
    background = textured_background(spec.width, spec.height, rng)
    axes = (max(4, spec.width // 20), max(8, spec.height // 5))  # a tall narrow body
    for index in range(spec.frames):
        gain = 1.0 + spec.drift * index / max(1, spec.frames - 1)
        noise = rng.standard_normal(background.shape, dtype=np.float32)
        image = background * np.float32(gain) + noise * np.float32(spec.noise_sigma)
        mask = np.zeros((spec.height, spec.width), np.uint8)
        if index >= spec.empty:
            t = (index - spec.empty) % spec.crossing / spec.crossing  # repeated crossings
            centre = (int(spec.width * (0.15 + 0.7 * t)), int(spec.height * 0.55))
            cv2.ellipse(mask, centre, axes, 0, 0, 360, 255, -1)
            inside = mask > 0
            a = spec.walker_alpha  # clothing colour over the background texture
            image[inside] = (1 - a) * image[inside] + a * np.array(spec.walker_bgr, np.float32)
            if spec.passer_behind:  # their feet at the walker's head height; crossing it mid-clip
                other = np.zeros_like(mask)
                cv2.ellipse(other, (int(spec.width * (0.625 - 0.0053 * (index - spec.empty))), int(spec.height * 0.26)),
                            (max(3, spec.width // 27), max(6, spec.height // 6)), 0, 0, 360, 255, -1)
                seen = (other > 0) & ~inside  # behind the walker
                image[seen] = (1 - a) * image[seen] + a * np.array(spec.walker_bgr, np.float32)
        np.maximum(image, 0, out=image)
        yield Frame(cv2.convertScaleAbs(image), index, 0, mask)  # rounds, saturates at 255


def write_video(path: str | os.PathLike[str], spec: SceneSpec = SceneSpec(), *,
                fourcc: str | None = None) -> list[np.ndarray]:
    """Write the scene as a video and return the masks.

    ``fourcc`` defaults to MJPG for ``.avi`` and mp4v otherwise; XVID decodes
    in about a third of MJPG's time at 640x480, which matters in benchmarks.
    """
    path = Path(path)
    code = fourcc or ("MJPG" if path.suffix == ".avi" else "mp4v")
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*code), spec.fps,
                             (spec.width, spec.height))
    if not writer.isOpened():
        raise OSError(f"cannot write video {path} with {code}")
    masks = []
    try:
        for frame in scene_frames(spec):
            writer.write(frame.image)
            masks.append(frame.mask)
    finally:
        writer.release()
    return masks


def write_folder(path: str | os.PathLike[str], spec: SceneSpec = SceneSpec()) -> list[np.ndarray]:
    """Write the scene as ``000000.png``... (lossless); return the masks."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    masks = []
    for frame in scene_frames(spec):
        cv2.imwrite(str(path / f"{frame.index:06d}.png"), frame.image)
        masks.append(frame.mask)
    return masks
