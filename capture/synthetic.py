"""The synthetic camera: the articulated walker rendered over a textured scene.

A frame source (``synthetic:k=v,...``) for tests, benchmarks and the demo, with
exact ground-truth masks. The walker of ``estimator`` (CMU-fitted gait, random
size and style from ``seed``) walks straight through the view again and again
— one *pass* of ``pass`` frames, then ``gap`` frames of empty scene — after
``empty`` frames of empty scene for the background model to learn (the paper
learned from 100). The image is a textured background under a slow lighting
drift, the walker's clothing blended over it (``contrast`` 1 = opaque, lower =
closer to the background colour), and Gaussian sensor noise.

Agents started with the same ``seed`` (and ``pass``/``gap``/``empty``/``fps``)
but different ``azimuth``/``elevation`` see the same walker at the same frame
index: a hardware-synchronised rig.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, fields

import numpy as np

from estimator.gait import GaitStyle, load_gait
from estimator.joints import N_JOINTS
from estimator.render import Renderer
from estimator.skeleton import BodyShape
from estimator.synth import place_cameras, walk

from .scene import textured_background
from .sources import Frame, FrameSource, SourceError, parse_options

__all__ = ["SyntheticSource", "SyntheticSpec", "composite", "write_recording"]


@dataclass(frozen=True)
class SyntheticSpec:
    """Parameters of the synthetic camera (the ``synthetic:`` spec keys)."""

    seed: int = 0
    azimuth: float = 90.0
    elevation: float = 10.0
    fps: float = 15.0
    frames: int = 0  # 0 = endless
    empty: int = 30
    pass_frames: int = 40
    gap: int = 10
    width: int = 640
    height: int = 480
    contrast: float = 0.8
    noise: float = 3.0
    drift: float = 0.08
    distance: float = 10.0

    def __post_init__(self) -> None:
        if self.fps <= 0 or self.pass_frames < 2 or self.gap < 0 or self.empty < 0 or self.frames < 0:
            raise SourceError("synthetic: fps > 0, pass >= 2, gap, empty, frames >= 0 required")
        if not 0 <= self.contrast <= 1:
            raise SourceError(f"synthetic: contrast must lie in [0, 1], got {self.contrast}")
        if self.width < 32 or self.height < 32:
            raise SourceError(f"synthetic: size must be at least 32x32, got {self.width}x{self.height}")


_NOISE_BANK = 7


def composite(background: np.ndarray, mask: np.ndarray, clothing: np.ndarray, contrast: float,
              noise: np.ndarray) -> np.ndarray:
    """The walker (``mask`` > 0) in ``clothing`` colour blended over ``background`` (float32
    BGR) by ``contrast``, plus ``noise``: the uint8 frame."""
    image = background.copy()
    inside = mask > 0
    image[inside] = (1 - contrast) * image[inside] + np.float32(contrast) * clothing
    image += noise
    return np.clip(image, 0, 255).astype(np.uint8)


def write_recording(path: str, silhouettes: list[np.ndarray | None], fps: float, *, seed: int = 0,
                    empty: int = 0, contrast: float = 0.8, noise: float = 3.0) -> None:
    """One camera's recording as a video (MJPG in .avi, else mp4v): full-frame silhouettes
    (``estimator.synth``) drawn over a textured scene with sensor noise; the walker is out
    of view in the first ``empty`` frames (the background is learned from them)."""
    import cv2

    h, w = next(s for s in silhouettes if s is not None).shape
    rng = np.random.default_rng(seed)
    background = textured_background(w, h, rng, saturation=0.35)
    clothing = rng.uniform(20, 235, 3).astype(np.float32)
    bank = rng.normal(0.0, noise, (_NOISE_BANK, h, w, 3)).astype(np.float32)
    code = "MJPG" if str(path).endswith(".avi") else "mp4v"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*code), fps, (w, h))
    if not writer.isOpened():
        raise OSError(f"cannot write video {path} with {code}")
    try:
        for k, sil in enumerate(silhouettes):
            mask = np.zeros((h, w), np.uint8) if sil is None or k < empty else sil
            writer.write(composite(background, mask, clothing, contrast, bank[k % _NOISE_BANK]))
    finally:
        writer.release()
_ALIASES = {"pass": "pass_frames", "az": "azimuth", "el": "elevation"}


class SyntheticSource(FrameSource):
    """Render the synthetic camera's frames (see the module docstring)."""

    live = False
    hardware_sync = True

    def __init__(self, spec: SyntheticSpec) -> None:
        self.spec = spec
        self.fps = spec.fps
        self.size = (spec.width, spec.height)
        rng = np.random.default_rng(spec.seed)
        self.shape = BodyShape.random(rng)
        self.style = GaitStyle.random(rng)
        self._start_phase = float(rng.uniform())
        self._clothing = rng.uniform(20, 235, 3).astype(np.float32)
        self._background = textured_background(spec.width, spec.height, rng, saturation=0.35)
        # Sensor noise: a bank of frames drawn once (a fresh 640x480x3 Gaussian
        # draw per frame costs more than rendering the walker).
        self._noise = rng.normal(0.0, spec.noise, (_NOISE_BANK, spec.height, spec.width, 3)).astype(np.float32)
        self._gait = load_gait()
        t = (np.arange(spec.pass_frames) - (spec.pass_frames - 1) / 2) / spec.fps
        self._pass_time = t
        world = walk(self._phase(np.zeros_like(t), t), self.shape, self.style, self._gait, time_s=t)
        self.camera = place_cameras(
            (spec.azimuth,),
            (spec.elevation,),
            centroids=world[:, :N_JOINTS].mean(axis=1),
            stature=self.shape.height,
            image_size=self.size,
            distance=spec.distance,
        )["c0"]
        self._renderer: Renderer | None = None

    @classmethod
    def from_spec(cls, spec: str) -> "SyntheticSource":
        """Build from ``k=v,...`` (keys of :class:`SyntheticSpec`; ``size=WxH``, ``pass=N``)."""
        opts = parse_options(spec)
        kwargs: dict[str, object] = {}
        types = {f.name: f.type for f in fields(SyntheticSpec)}
        for key, value in opts.items():
            if key == "size":
                try:
                    w, h = (int(v) for v in value.lower().split("x"))
                except ValueError:
                    raise SourceError(f"synthetic: size must be WxH, got {value!r}") from None
                kwargs["width"], kwargs["height"] = w, h
                continue
            name = _ALIASES.get(key, key)
            if name not in types:
                raise SourceError(f"synthetic: unknown key {key!r}; known: {', '.join(sorted(set(types) | {'size', 'pass'}))}")
            try:
                kwargs[name] = int(value) if types[name] in (int, "int") else float(value)
            except ValueError:
                raise SourceError(f"synthetic: {key} must be a number, got {value!r}") from None
        return cls(SyntheticSpec(**kwargs))

    def _phase(self, pass_index: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Walking phase at pass-local time t of a pass (the walker never stops)."""
        period = (self.spec.pass_frames + self.spec.gap) / self.spec.fps
        elapsed = pass_index * period + t - self._pass_time[0]
        return (self._start_phase + self.style.cadence * elapsed) % 1.0

    def truth(self, index: int) -> dict | None:
        """Ground truth of frame ``index``: phase and world joints, or None if the scene is empty."""
        k = index - self.spec.empty
        cycle = self.spec.pass_frames + self.spec.gap
        if k < 0 or k % cycle >= self.spec.pass_frames:
            return None
        p, j = divmod(k, cycle)
        t = self._pass_time[j : j + 1]
        phase = self._phase(np.array([p]), t)
        world = walk(phase, self.shape, self.style, self._gait, time_s=t)[0]
        return {"phase": float(phase[0]), "joints": world, "pass": p}

    def gain(self, index: int) -> float:
        """The scene's lighting at frame ``index`` (brightness factor; a 20 s cycle of ``drift``)."""
        return 1.0 + self.spec.drift * float(np.sin(2 * np.pi * index / (self.spec.fps * 20.0)))

    def render(self, index: int) -> Frame:
        """Frame ``index`` (deterministic: the same index gives the same image)."""
        spec = self.spec
        truth = self.truth(index)
        mask = np.zeros((spec.height, spec.width), np.uint8)
        if truth is not None:
            if self._renderer is None:
                self._renderer = Renderer(self.shape, image_size=self.size)
            mask, _ = self._renderer.render(truth["joints"], self.camera)
        image = composite(self._background * np.float32(self.gain(index)), mask, self._clothing, spec.contrast,
                          self._noise[(index * 7 + int(spec.azimuth)) % _NOISE_BANK])
        return Frame(image, index, 0, mask)

    def __iter__(self) -> Iterator[Frame]:
        index = 0
        while self.spec.frames == 0 or index < self.spec.frames:
            yield self.render(index)
            index += 1

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
