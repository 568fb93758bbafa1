"""Silhouette segmentation: adaptive background subtraction and clean-up.

Paper §7: an adaptive Stauffer–Grimson mixture-of-Gaussians background model
(OpenCV's MOG2 is of that family) is first learned from ``warmup_frames``
empty frames (the paper used 100); each later frame is classified per pixel,
cleaned with morphology, and the largest connected component is kept as the
walker. The result is the crop and its box in the full frame.

The model keeps adapting (lighting drifts) but *selectively*: every
``update_every`` frames it learns from the frame with the walker's region
(dilated) replaced by the current background estimate, so a walker who keeps
covering the same pixels — walking towards the camera, or pass after pass on
the same path — is not absorbed into the background. Measured on the
synthetic camera, the plain ``learningRate=-1`` update lost up to 30 points of
IoU on such paths (docs/CAPTURE.md).

§7.1 feedback: the service registers rendered silhouettes with the input and
sends them back as a prior mask; inside a confident prior a pixel becomes
foreground on weaker evidence (a smaller colour distance to the background
model than MOG2's own test), which fills the holes plain backgrounding leaves.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .wire import Box, FeedbackMessage

__all__ = ["MAX_PRIORS", "SegmentSettings", "Segmentation", "Segmenter"]

MAX_PRIORS = 64  # priors kept per segmenter, newest frame indices first


class SegmentSettings(BaseModel):
    """Segmentation parameters, one default each (laptop-friendly, 640x480)."""

    model_config = ConfigDict(frozen=True)

    warmup_frames: int = Field(100, ge=1, description="empty frames learned before segmenting "
                               "(paper: 100)")
    scale: float = Field(1.0, gt=0, le=1, description="resolution at which the background model "
                         "runs (0.5 = 4x cheaper, coarser limbs); crop and box stay full-frame")
    history: int = Field(500, ge=1, description="MOG2 history length in frames (warm-up rate)")
    var_threshold: float = Field(16.0, gt=0, description="MOG2 squared Mahalanobis threshold")
    detect_shadows: bool = Field(False, description="mark shadows and drop them; off because dark "
                                 "clothing is then taken for shadow (the paper does not do it)")
    learning_rate: float = Field(0.04, gt=0, le=1, description="MOG2 rate of each selective update")
    update_every: int = Field(4, ge=1, description="frames between selective background updates")
    update_guard_px: int = Field(15, ge=1, description="dilation at model resolution of the "
                                 "foreground kept out of the update")
    open_px: int = Field(0, ge=0, description="opening kernel at model resolution (removes "
                         "speckle; thins limbs); 0 = off")
    close_px: int = Field(9, ge=0, description="closing kernel at full resolution (fills "
                          "holes); 0 = off")
    min_area: int = Field(150, ge=1, description="a largest component below this many "
                          "full-frame pixels = nothing")
    margin_px: int = Field(2, ge=0, description="margin around the component in the crop")
    prior_level: int = Field(128, ge=1, le=255, description="prior value from which it is trusted")
    prior_diff: float = Field(6.0, ge=0, description="grey-level distance to the background "
                              "that counts as foreground inside a trusted prior (floor)")
    prior_noise_k: float = Field(1.5, ge=0, description="... and at least this many times the "
                                 "frame's mean distance (its noise level)")
    prior_max_age: int = Field(5, ge=0, description="frames after its frame_index a prior "
                               "stays valid")


@dataclass(frozen=True, slots=True)
class Segmentation:
    """The walker in one frame: ``mask`` is the crop (0/255) at ``box``; empty box = nothing."""

    mask: np.ndarray
    box: Box
    image_size: tuple[int, int]
    area: int
    used_prior: bool

    def full_mask(self) -> np.ndarray:
        """The crop pasted into a full-frame ``(height, width)`` canvas."""
        out = np.zeros(self.image_size[::-1], np.uint8)
        if not self.box.empty:
            out[self.box.slices()] = self.mask
        return out


def _kernel(size: int) -> np.ndarray | None:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)) if size > 0 else None


class Segmenter:
    """MOG2 + morphology + largest component, with a prior-fusion hook.

    Not thread-safe for :meth:`apply`; :meth:`set_prior` may be called from
    another thread (the Zenoh feedback callback).
    """

    def __init__(self, settings: SegmentSettings = SegmentSettings()) -> None:
        self.settings = settings
        self._mog = cv2.createBackgroundSubtractorMOG2(
            history=settings.history, varThreshold=settings.var_threshold,
            detectShadows=settings.detect_shadows)
        self._open = _kernel(settings.open_px)
        self._guard = _kernel(settings.update_guard_px)
        self._since_update = 0
        self._close = _kernel(settings.close_px)
        self._learned = 0
        # frame_index -> (image size, trusted pixels at model resolution); the
        # service may send priors for frames it predicts, ahead of time.
        self._priors: dict[int, tuple[tuple[int, int], np.ndarray]] = {}
        self._lock = threading.Lock()

    @property
    def warming_up(self) -> bool:
        """True until ``warmup_frames`` frames have been learned."""
        return self._learned < self.settings.warmup_frames

    def _model_size(self, size: tuple[int, int]) -> tuple[int, int]:
        s = self.settings.scale
        return max(1, round(size[0] * s)), max(1, round(size[1] * s))

    def set_prior(self, prior: FeedbackMessage) -> None:
        """Install a prior mask (paper §7.1) for frames ``prior.frame_index`` onward.

        A frame uses the newest prior at or before its index that is at most
        ``prior_max_age`` frames old; priors for future frames wait (up to
        :data:`MAX_PRIORS` are kept).
        """
        small = cv2.resize(prior.full_mask(), self._model_size(prior.image_size),
                           interpolation=cv2.INTER_AREA) >= self.settings.prior_level
        with self._lock:
            self._priors[prior.frame_index] = (prior.image_size, small)
            while len(self._priors) > MAX_PRIORS:
                del self._priors[min(self._priors)]

    def _prior_for(self, index: int, size: tuple[int, int]) -> np.ndarray | None:
        with self._lock:
            for old in [k for k in self._priors if k < index - self.settings.prior_max_age]:
                del self._priors[old]
            usable = [k for k in self._priors if k <= index]
            if not usable:
                return None
            prior_size, small = self._priors[max(usable)]
        return small if prior_size == size else None

    def apply(self, image: np.ndarray, index: int) -> Segmentation | None:
        """Learn from or segment one BGR frame; None while warming up.

        Parameters
        ----------
        image : ndarray of shape (H, W, 3), uint8 BGR
        index : frame index, matched against a prior's ``frame_index``
        """
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {image.dtype} {image.shape}")
        size = (image.shape[1], image.shape[0])
        small = image if self.settings.scale == 1 else cv2.resize(
            image, self._model_size(size), interpolation=cv2.INTER_AREA)
        if self.warming_up:
            self._mog.apply(small, learningRate=-1)  # running average over the empty frames
            self._learned += 1
            return None
        raw = self._mog.apply(small, learningRate=0)  # classify only; learning is selective
        fg = cv2.compare(raw, 200, cv2.CMP_GT)  # 255 = foreground, 127 = shadow -> background
        prior = self._prior_for(index, size)
        background = None
        self._since_update += 1
        if self._since_update >= self.settings.update_every:
            # Guard MOG2's own foreground only: guarding the prior's additions too
            # would keep a wrong prior's region out of the model for good.
            background = self._mog.getBackgroundImage()
            self._update(small, fg, background)
        if prior is not None:
            if background is None:
                background = self._mog.getBackgroundImage()
            fg = self._fuse(fg, small, background, prior)
        if self._open is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._open)
        if fg.shape[::-1] != size:  # back to full resolution, smoothing the 2x2 steps
            fg = cv2.compare(cv2.resize(fg, size, interpolation=cv2.INTER_LINEAR), 127, cv2.CMP_GT)
        if self._close is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, self._close)
        return self._largest(fg, size, used_prior=prior is not None)

    def _update(self, image: np.ndarray, fg: np.ndarray, background: np.ndarray) -> None:
        """Learn from ``image`` with the (dilated) foreground replaced by the background."""
        composite = image.copy()
        cv2.copyTo(background, cv2.dilate(fg, self._guard), composite)
        self._mog.apply(composite, learningRate=self.settings.learning_rate)
        self._since_update = 0

    def _fuse(self, fg: np.ndarray, image: np.ndarray, background: np.ndarray,
              prior: np.ndarray) -> np.ndarray:
        """Foreground also where the prior is trusted and the pixel differs weakly."""
        diff = cv2.absdiff(image, background).max(axis=2)
        # Above the floor and above the frame's typical (mostly noise) difference,
        # so a noisy camera does not turn the whole prior into foreground.
        level = max(self.settings.prior_diff, self.settings.prior_noise_k * float(diff.mean()))
        weak = (diff > level) & prior
        return np.where(weak, np.uint8(255), fg)

    def _largest(self, fg: np.ndarray, size: tuple[int, int], *, used_prior: bool) -> Segmentation:
        # Label only inside the bounding rectangle of all foreground: usually a small
        # region around the walker, and labelling is the costliest step after MOG2.
        rx, ry, rw, rh = cv2.boundingRect(fg)
        if rw == 0 or rh == 0:
            return self._empty(size, used_prior)
        _, labels, stats, _ = cv2.connectedComponentsWithStats(
            fg[ry:ry + rh, rx:rx + rw], connectivity=8)
        best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        area = int(stats[best, cv2.CC_STAT_AREA])
        if area < self.settings.min_area:
            return self._empty(size, used_prior)
        x, y, w, h = (int(v) for v in stats[best, :4])  # in the labelled region
        m = self.settings.margin_px
        x0, y0 = max(0, rx + x - m), max(0, ry + y - m)  # crop box in the full frame
        x1, y1 = min(size[0], rx + x + w + m), min(size[1], ry + y + h + m)
        crop = np.zeros((y1 - y0, x1 - x0), np.uint8)
        ox, oy = rx + x - x0, ry + y - y0
        crop[oy:oy + h, ox:ox + w] = cv2.compare(labels[y:y + h, x:x + w], best, cv2.CMP_EQ)
        return Segmentation(crop, Box(x0, y0, x1 - x0, y1 - y0), size, area, used_prior)

    @staticmethod
    def _empty(size: tuple[int, int], used_prior: bool) -> Segmentation:
        return Segmentation(np.zeros((0, 0), np.uint8), Box(0, 0, 0, 0), size, 0, used_prior)
