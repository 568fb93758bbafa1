"""Silhouette segmentation: adaptive background subtraction and clean-up.

Paper §7: an adaptive Stauffer–Grimson mixture-of-Gaussians background model
(OpenCV's MOG2 is of that family) is first learned from ``warmup_frames``
empty frames (the paper used 100); each later frame is classified per pixel,
cleaned with morphology, and one connected component is kept as the walker:
the one continuing the tracked walker, else the tallest (``pick``). The
result is the crop and its box in the full frame.

The model runs downscaled to ``model_width`` (160: a quarter of 640x480,
16x fewer pixels) and only finds *where* the walker is: every pixel within
``refine_px`` model pixels of its upsampled mask is then re-tested at full
resolution against a full-resolution running mean of the background, with
MOG2's own threshold on the noise variance measured next to the walker. Thin
limbs keep their full-resolution edges (docs/CAPTURE.md: IoU as good as the
full-resolution model, at a fraction of its cost). Sizes in pixels (closing,
update guard, minimum area, margin) are given for a ``reference_width``-wide
frame and scale with the frame, so a 320x240 camera segments like a 640x480 one.

The model keeps adapting (lighting drifts) but *selectively*: every
``update_every`` frames it learns from the frame with the walker's region
(dilated) replaced by the current background estimate, so a walker who keeps
covering the same pixels — walking towards the camera, or pass after pass on
the same path — is not absorbed into the background. The update runs in
:meth:`Segmenter.learn`, which the agent calls after publishing the frame's
silhouette (else the next ``apply`` does), off the latency path. Measured on the
synthetic camera, the plain ``learningRate=-1`` update lost up to 30 points of
IoU on such paths (docs/CAPTURE.md).

§7.1 feedback: the service registers rendered silhouettes with the input and
sends them back as a prior mask; inside a confident prior a pixel becomes
foreground on weaker evidence (a smaller colour distance to the background
model than MOG2's own test), which fills the holes plain backgrounding leaves.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Callable, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from estimator.cleanup import bounding_box
from estimator.prior import trust_factor

from .colours import ColourSplit
from .masks import filled
from .wire import Box, FeedbackMessage

__all__ = ["MAX_PRIORS", "PriorStats", "SegmentSettings", "Segmentation", "Segmenter", "default_warmup",
           "box_iou", "describe", "filled", "sample_indices"]

MAX_PRIORS = 64  # priors kept per segmenter, newest frame indices first
JOIN_STEP = 0.1  # a joined walker's height moves the learned one by at most this share (walking nearer)
TORN = 0.75  # a candidate shorter than this share of the walker's height may be a piece of them (stack_gap)


class SegmentSettings(BaseModel):
    """Segmentation parameters, one default each (laptop-friendly, 640x480)."""

    model_config = ConfigDict(frozen=True)

    background: Literal["bootstrap", "warmup"] = Field(
        "bootstrap", description="how the background is learned: 'bootstrap' = per-pixel "
        "temporal median of frames sampled over the first seconds (a re-readable file, "
        "Segmenter.bootstrap) or of the start-up buffer (live), so the scene need not be empty; "
        "'warmup' = the paper's MOG2 running average over empty start-up frames")
    warmup_frames: int = Field(100, ge=1, description="start-up frames collected before "
                               "segmenting when the background was not bootstrapped from a "
                               "re-read file (live cameras); with background='warmup' they "
                               "must be empty (paper: 100)")
    bootstrap_samples: int = Field(40, ge=3, description="frames sampled for the median "
                                   "background")
    bootstrap_seconds: float = Field(15.0, gt=0, description="span at the start of a file over "
                                     "which the samples are spread (the whole file if shorter)")
    bootstrap_outlier: float = Field(25.0, gt=0, description="a sampled pixel farther than this "
                                     "(grey levels, any channel) from the median is replaced by "
                                     "it when priming MOG2 (the rest teaches MOG2 the real noise)")
    bootstrap_still: float = Field(12.0, gt=0, description="start-up buffer: a pixel changing "
                                   "more than this since the previous frame is moving and "
                                   "counts less in the median")
    bootstrap_lit: float = Field(0.2, ge=0, le=1, description="a pixel whose median is a shadow "
                                 "(darker by a ratio in shadow_ratio, same chromaticity) of a value "
                                 "that at least this share of the samples agree on (within "
                                 "bootstrap_still) takes that lit value: a shadow that lay there in "
                                 "most samples, a walker's own or a dark-clad person's in place, is "
                                 "not the background (0 = off)")
    bootstrap_lit_width: int = Field(5, ge=1, description="... where such pixels make a region at "
                                     "least this wide (px, an opening): a fluttering tape's line "
                                     "keeps the median")
    bootstrap_lit_area: float = Field(0.25, gt=0, le=1, description="... and not when more than this "
                                      "share of the frame is brighter in that many samples: the light "
                                      "changed over the scene, and the median stays")
    shadows: bool = Field(True, description="drop shadow/reflection pixels at full resolution "
                          "(darker or brighter by a ratio in shadow_ratio, same chromaticity, "
                          "same texture) unless enclosed by the body, or unless they would "
                          "take most of it")
    shadow_ratio: tuple[float, float] = Field((0.4, 0.95), description="brightness ratio "
                                              "frame/background of a shadow")
    reflection_ratio: float = Field(1.15, ge=1, description="up to this ratio a brighter pixel "
                                    "with unchanged chromaticity and texture is a reflection "
                                    "(1 = off)")
    shadow_chroma: float = Field(0.08, gt=0, description="largest chromaticity distortion "
                                 "|I - rB| / |B| of a shadow pixel")
    shadow_rounds: int = Field(3, ge=1, description="the shadow test repeated on what it left, until it "
                               "removes nothing (at most this many times): the feet band is measured again, so a "
                               "long cast shadow whose far end set it is removed back to the feet")
    shadow_texture: float = Field(0.4, gt=0, description="largest gradient change (relative to "
                                  "the gradients present) of a shadow pixel")
    shadow_feet: float = Field(0.15, ge=0, le=0.5, description="in this lowest fraction of "
                               "each foreground blob's height the texture test is waived and "
                               "no shadow is re-admitted as enclosed: a contact shadow under "
                               "the feet is too small to show the ground's texture (0 = off)")
    ghost_frames: int = Field(10, ge=0, description="a foreground component that stays put "
                              "this many frames is tested for being a ghost (its edges are the "
                              "background model's, not the frame's) and absorbed; 0 = off")
    ghost_edge_ratio: float = Field(1.3, gt=0, description="ghost = mean background-model "
                                    "gradient on the component's outline above this many times "
                                    "the frame's")
    track_frames: int = Field(15, ge=0, description="frames the tracked walker's box is kept "
                              "while no component continues it; a component continuing it is "
                              "kept rather than the `pick`, chosen by overlap and by height "
                              "against the walker's median height over this many (at least 3) of its last "
                              "detections; the colour split's median area likewise")
    track_grow: float = Field(0.3, ge=0, description="the tracked box is grown by this fraction "
                              "of its size per side (per frame missed, plus one) to find its "
                              "continuation")
    model_width: int = Field(160, ge=0, description="width in pixels at which the background "
                             "model runs (frames no wider run at full resolution; 0 = always "
                             "full resolution); its mask is then refined at full resolution")
    refine_px: float = Field(2.0, ge=0, description="when the model runs downscaled, pixels "
                             "within this many *model* pixels of its upsampled mask are "
                             "re-tested at full resolution; 0 = plain upsampled mask")
    reference_width: int = Field(640, ge=1, description="frame width for which the pixel sizes "
                                 "below are given; they scale with the frame's width")
    refine_threshold: float = Field(16.0, gt=0, description="near the mask, foreground = squared "
                                    "colour distance to the full-resolution background above "
                                    "this many times the local noise variance (MOG2's test)")
    refine_floor: float = Field(28.0, ge=0, description="...and above this colour distance "
                                "(grey levels, channels combined): compression artefacts "
                                "along edges (MJPG's 8x8 blocks) exceed the flat-area noise")
    edge_split: bool = Field(True, description="at full resolution, a pixel on the walker's "
                             "edge is foreground only if its colour is nearer the walker's "
                             "nearby colour than the background's (edges where blur and "
                             "compression mix the two are split halfway, not at the noise level)")
    gain_compensation: bool = Field(True, description="divide the frame's global brightness "
                                    "change (median ratio to the background) out before "
                                    "classifying")
    history: int = Field(500, ge=1, description="MOG2 history length in frames (warm-up rate)")
    var_threshold: float = Field(16.0, gt=0, description="MOG2 squared Mahalanobis threshold")
    detect_shadows: bool = Field(False, description="MOG2's own shadow marking; off because dark "
                                 "clothing is then taken for shadow (see ``shadows``)")
    learning_rate: float = Field(0.04, gt=0, le=1, description="MOG2 rate of each selective update")
    update_every: int = Field(4, ge=1, description="frames between selective background updates")
    update_phase: int = Field(0, ge=0, description="offset of the update schedule; the agents of "
                              "a synchronised rig take different phases so that their updates "
                              "(the costliest frames) do not coincide")
    update_guard_px: int = Field(15, ge=1, description="dilation in reference pixels of the "
                                 "foreground kept out of the update (applied at model resolution)")
    open_px: int = Field(0, ge=0, description="opening kernel at model resolution (removes "
                         "speckle; thins limbs); 0 = off")
    close_px: int = Field(9, ge=0, description="closing kernel in reference pixels, applied at "
                          "full resolution (fills holes); 0 = off")
    fill_holes: float | None = Field(0.1, ge=0, le=1, description="fill each hole the walker's "
                                     "outline encloses that is at least this fraction of the walker's "
                                     "area with its holes (None = off, 0 = every hole): where the walker "
                                     "stood in most frames the background was bootstrapped from (walking "
                                     "towards or away from the camera), the background model holds the "
                                     "walker and only the outline differs; smaller holes are left, such "
                                     "as the gap between legs whose feet the closing joined "
                                     "(docs/CAPTURE.md)")
    stack_gap: float = Field(0.2, ge=0, le=1, description="a candidate shorter than three quarters of "
                             "the tracked walker's median height is joined by the pieces as short stacked above "
                             "or below it (overlapping it across at least half the narrower one's width, at most "
                             "this fraction of the joined height apart) when the join brings its height nearer "
                             "that median and not beyond 1.2 times it: a walker torn in two at the waist by a "
                             "shirt or trousers the colour of the ground behind (docs/CAPTURE.md); 0 = off")
    pick: Literal["tallest", "largest"] = Field("tallest", description="with no tracked walker to "
                                                "continue, the candidate kept: the tallest (ties: the larger), "
                                                "or the largest by area. People walking together, or a "
                                                "passer-by nearer the camera with their shadow, make one blob "
                                                "larger than the walker but rarely a taller one; by area such "
                                                "a pair was kept and then tracked for a whole clip "
                                                "(docs/ROBUSTNESS.md)")
    walker_choice: Literal["centred", "first"] = Field("centred", description="on a file "
                                                       "(capture.refine.segment_clip), the walker is "
                                                       "chosen over the whole clip: the one person "
                                                       "whose path stays nearest the image centre (the "
                                                       "cameras are aimed at the walk; capture/choose.py) "
                                                       "when clearly nearer than the one the track "
                                                       "started on; live, over the last 45 frames, every 5 "
                                                       "(capture.choose.LiveChoice); 'first' = the person "
                                                       "the track starts on")
    colour_split: bool = Field(True, description="cut off the tracked walker's blob the regions "
                               "whose colours are the other people's rather than the walker's (running "
                               "colour histograms of both; capture/colours.py): a passer-by touching the "
                               "walker is otherwise one blob with them (docs/ROBUSTNESS.md)")
    unmerge_jump: float = Field(0.12, ge=0, description="a change of the walker's blob height by more "
                                "than this fraction between consecutive frames is someone joining or "
                                "leaving them: the frames above the walker's own height, where another "
                                "person's box explains the extra rows, are cut back to it (on a file over "
                                "the whole clip, capture.refine.segment_clip; live from the frames before, "
                                "capture.merges.LiveUnmerge in the agent); 0 = off")
    track_colour: float = Field(4.0, ge=0, description="where two or more candidates continue the tracked "
                                "walker's box (after a merge with a passer-by, the parts), each one's score "
                                "(overlap times height ratio) is weighed by the Bhattacharyya coefficient of "
                                "its colours with the walker's learned colours to this power: the track stays "
                                "with the walker rather than the larger part (capture/colours.py); 0 = off "
                                "(also off when colour_split is False)")
    colour_ratio: float = Field(2.7, gt=1, description="a region is cut where its colours are this many "
                                "times likelier among the other people than on the walker")
    colour_window: float = Field(0.04, gt=0, description="the colour evidence is averaged over a square "
                                 "of this fraction of the walker's height")
    colour_rate: float = Field(0.2, gt=0, le=1, description="running-mean rate of the colour histograms")
    colour_frames: int = Field(5, ge=1, description="frames of the walker at its usual size its colours "
                               "are learned from before anything is cut")
    min_area: int = Field(600, ge=1, description="a candidate below this many "
                          "reference pixels = nothing")
    min_width: float = Field(12.0, ge=0, description="a candidate must be at least this wide "
                             "somewhere (reference pixels; the widest disc inside it): a torso "
                             "is, a fluttering tape, a wire or a sliver at the image border is "
                             "not; 0 = off")
    margin_px: int = Field(2, ge=0, description="margin in full-frame pixels around the "
                           "component in the crop")
    prior_level: int = Field(128, ge=1, le=255, description="prior value from which it is trusted")
    prior_diff: float = Field(6.0, ge=0, description="grey-level distance to the background "
                              "that counts as foreground inside a trusted prior (floor)")
    prior_noise_k: float = Field(1.5, ge=0, description="... and at least this many times the "
                                 "frame's mean distance (its noise level)")
    prior_threshold: float = Field(4.0, gt=0, description="inside a trusted prior, at full "
                                   "resolution: foreground above this many times the noise "
                                   "variance (refine_threshold's weaker twin)")
    prior_floor: float = Field(10.0, ge=0, description="... and above this colour distance "
                               "(refine_floor's weaker twin)")
    prior_max_age: int = Field(5, ge=0, description="frames after its frame_index a prior "
                               "stays valid")
    prior_max_age_ms: float = Field(2000.0, gt=0, description="a prior issued or received "
                                    "longer ago than this is stale and ignored")
    prior_check: bool = Field(True, description="check each prior against MOG2's own "
                              "foreground before using it (off: trust it as it is)")
    prior_check_level: int = Field(64, ge=1, le=255, description="prior value counted as "
                                   "covering the evidence in the agent-side check")
    prior_check_reach: float = Field(0.04, ge=0, description="... dilated by this fraction of "
                                     "the prior's height (a prediction a little off, e.g. in "
                                     "phase, still explains the evidence; a wrong one does not)")
    prior_min_coverage: float = Field(0.5, ge=0, le=1, description="a prior covering less "
                                      "of MOG2's own foreground near it is not used")
    prior_full_coverage: float = Field(0.8, ge=0, le=1, description="... and from this "
                                       "coverage on it is used at full strength")


@dataclass(frozen=True, slots=True)
class Segmentation:
    """The walker in one frame: ``mask`` is the crop (0/255) at ``box``; empty box = nothing."""

    mask: np.ndarray
    box: Box
    image_size: tuple[int, int]
    area: int
    used_prior: bool
    n_candidates: int = 0  # person-sized components seen (the tracked walker among them)
    candidates: tuple[tuple[int, int, int, int], ...] = ()  # their boxes (x, y, w, h), full frame
    plate: bool = False  # segmented against an image of the empty scene, not a background learned from the frames

    def full_mask(self) -> np.ndarray:
        """The crop pasted into a full-frame ``(height, width)`` canvas."""
        return self.box.paste(self.mask, self.image_size)

    @classmethod
    def nothing(cls, size: tuple[int, int], used_prior: bool = False,
                n_candidates: int = 0, plate: bool = False) -> Segmentation:
        """A frame of ``size`` in which no walker was found."""
        return cls(np.zeros((0, 0), np.uint8), Box(0, 0, 0, 0), size, 0, used_prior, n_candidates, plate=plate)


def _padded(rect: tuple[int, int, int, int], pad: int, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: ``rect`` (x, y, w, h) grown by ``pad`` pixels on every side,
    clipped to an image of ``size`` (width, height)."""
    x, y, w, h = rect
    return max(0, x - pad), max(0, y - pad), min(size[0], x + w + pad), min(size[1], y + h + pad)


def _kernel(size: float) -> np.ndarray | None:
    """An elliptic kernel about ``size`` pixels wide, made odd so that it is centred
    (an even kernel's anchor is off centre and closing would shift the mask)."""
    n = round(size)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (n | 1, n | 1)) if n > 0 else None


@dataclass(frozen=True, slots=True)
class _Geometry:
    """The pixel sizes of :class:`SegmentSettings` resolved for one frame size."""

    size: tuple[int, int]  # full frame (width, height)
    model_size: tuple[int, int]  # where MOG2 runs
    refine_px: int  # full-frame pixels re-tested around the upsampled mask (0 = none)
    close_px: int
    min_area: int
    min_width: float  # full-frame pixels
    scale: float  # model / full resolution
    guard: np.ndarray | None  # update guard kernel, model resolution
    near: np.ndarray | None  # refinement band kernel, full resolution
    close: np.ndarray | None  # closing kernel, full resolution
    close_wide: np.ndarray | None  # a (2 close_px + 1) disc: the closing that gives shadow pixels back

    @property
    def downscaled(self) -> bool:
        return self.model_size != self.size

    @classmethod
    def of(cls, settings: "SegmentSettings", size: tuple[int, int]) -> "_Geometry":
        width, height = size
        scale = 1.0 if not settings.model_width else min(1.0, settings.model_width / width)
        model_size = (max(1, round(width * scale)), max(1, round(height * scale)))
        if model_size[0] >= width:
            model_size, scale = size, 1.0
        k = width / settings.reference_width  # reference pixels -> this frame's pixels
        refine = 0 if scale == 1.0 else int(np.ceil(settings.refine_px / scale))
        close = _kernel(settings.close_px * k)
        return cls(size, model_size, refine, 0 if close is None else close.shape[0],
                   max(1, round(settings.min_area * k * k)), settings.min_width * k, scale,
                   _kernel(max(1.0, settings.update_guard_px * k * scale)),
                   _kernel(2 * refine + 1) if refine else None,
                   close, None if close is None else _kernel(2 * close.shape[0] + 1))


@dataclass(slots=True)
class _StoredPrior:
    image_size: tuple[int, int]
    small: np.ndarray  # soft prior (uint8) at model resolution
    full: np.ndarray | None  # and at full resolution, when refining
    received: float  # time.monotonic()
    near_box: tuple[int, int, int, int]  # model resolution: where the check looks
    covering: np.ndarray  # in near_box: the pixels that cover evidence
    trusted: tuple[np.ndarray, np.ndarray | None]  # >= prior_level, model and full resolution


@dataclass(slots=True)
class PriorStats:
    """What became of the priors a segmenter was given (§7.1 loop health)."""

    received: int = 0
    stale: int = 0  # too old on arrival, or aged out unused
    used: int = 0  # frames segmented with a prior
    weakened: int = 0  # ... of which with a raised trust level (partial coverage)
    rejected: int = 0  # frames whose prior did not explain the evidence


def default_warmup(n_frames: int) -> int:
    """Background frames to learn from a recording of ``n_frames`` (0 = unknown) when
    nobody said: a quarter of it, at most the paper's 100."""
    return max(1, min(100, n_frames // 4 if n_frames else 30))


def sample_indices(n_frames: int, fps: float | None, settings: SegmentSettings) -> list[int]:
    """Frame indices to bootstrap the background from: ``bootstrap_samples`` spread evenly
    over the first ``bootstrap_seconds`` of a recording of ``n_frames`` (all of it if
    shorter; 15 fps when unknown)."""
    span = min(n_frames, max(1, round(settings.bootstrap_seconds * (fps or 15.0))))
    if span <= 0:
        return []
    return sorted({int(round(v)) for v in np.linspace(0, span - 1, min(span, settings.bootstrap_samples))})


def _median(stack: np.ndarray, moving: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel median of ``stack`` (N, H, W, 3) uint8, preferring samples not ``moving``.

    Moving samples (N, H, W bool) are replaced by alternately 0 and 255: the
    median of the whole set is then the median of the still samples (exactly
    for an even count), without a masked median's cost. Pixels moving in most
    samples keep their values (nothing better is known there).
    """
    if moving is not None and moving.any():
        moving = moving & (moving.sum(axis=0) < 0.8 * len(stack))[None]
        rank = np.cumsum(moving, axis=0)  # alternate low/high over each pixel's moving samples
        stack = stack.copy()
        stack[moving & (rank % 2 == 1)] = 0
        stack[moving & (rank % 2 == 0)] = 255
    return np.median(stack, axis=0).astype(np.float32)


def _lit(stack: np.ndarray, median: np.ndarray, moving: np.ndarray | None,
         settings: SegmentSettings, block: int = 1 << 15) -> np.ndarray:
    """The bootstrap ``median`` (H, W, 3 float32) given, where it is a shadow of a value enough samples
    show lit, that lit value.

    A walker who stays in view for most of the samples (walking towards the
    camera, or slowly) leaves their cast shadow in the median wherever it lay
    in more than half of them; the frames in which it had moved on then show
    the ground *brighter* than the background, by a shadow's ratio, and that
    region is taken for foreground beside the walker (docs/CAPTURE.md). A
    pixel's sample is *lit* when the median is a shadow of it: the sample
    brighter by a ratio in ``1 / shadow_ratio``, the two colours' angle
    small (``|f - r m| / |f|`` under ``shadow_chroma``), and brighter by more
    than ``bootstrap_still`` grey levels in some channel, so noise is not a
    light. Where at least ``bootstrap_lit`` of the samples (and 3) are lit,
    not ``moving``, and agree (the median over them of each one's largest
    channel deviation from their median within ``bootstrap_still``: a ground,
    not passers-by), and such pixels make a region ``bootstrap_lit_width``
    wide (a tape fluttering over a path is a line), the lit samples' median
    is the background. A dark-clad person standing on paler ground of the
    same hue is replaced the same way. When more than ``bootstrap_lit_area``
    of the frame would be tested, the light changed over the scene (sun and
    cloud, exposure) and the median stays: a lit minority is not the
    background then. Candidates are processed ``block`` pixels at a time.
    """
    h, w = median.shape[:2]
    need = max(settings.bootstrap_lit * len(stack), 3.0)
    brighter = np.zeros((h, w), np.int32)  # lit needs brighter: only those pixels are tested
    for k, sample in enumerate(stack):
        up = np.any(sample.astype(np.float32) - median > settings.bootstrap_still, axis=-1)
        brighter += up if moving is None else up & ~moving[k]
    ys, xs = np.nonzero(brighter >= need)
    if not ys.size or ys.size > settings.bootstrap_lit_area * h * w:
        return median
    lo, hi = 1.0 / settings.shadow_ratio[1], 1.0 / settings.shadow_ratio[0]
    value = np.full((ys.size, 3), np.nan, np.float32)
    for b in range(0, ys.size, block):
        by, bx = ys[b:b + block], xs[b:b + block]
        f = stack[:, by, bx].astype(np.float32)  # (N, P, 3)
        m = median[by, bx]
        r = np.einsum("npc,pc->np", f, m) / (np.einsum("pc,pc->p", m, m) + 1.0)
        dist = f - r[..., None] * m
        chroma = np.einsum("npc,npc->np", dist, dist) / np.maximum(np.einsum("npc,npc->np", f, f), 1.0)
        lit = (r >= lo) & (r <= hi) & (chroma < settings.shadow_chroma ** 2) \
            & ((f - m).max(axis=-1) > settings.bootstrap_still)
        if moving is not None:
            lit &= ~moving[:, by, bx]
        count = lit.sum(axis=0)
        values = np.where(lit[..., None], f, np.nan)
        mid = _median_of_finite(values, count)
        spread = _median_of_finite(np.abs(values - mid).max(axis=-1), count)
        good = (count >= need) & (spread <= settings.bootstrap_still)
        value[b:b + block][good] = mid[good]
    found = np.isfinite(value[:, 0])
    changed = np.zeros((h, w), np.uint8)
    changed[ys[found], xs[found]] = 1
    # a shadow is a region: lines (a fluttering tape, a kerb's edge) keep the median
    changed = cv2.morphologyEx(changed, cv2.MORPH_OPEN, _kernel(settings.bootstrap_lit_width))
    keep = found & (changed[ys, xs] > 0)
    out = median.copy()
    out[ys[keep], xs[keep]] = value[keep]
    return out


def _median_of_finite(values: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Median over axis 0 of ``values`` with ``count`` finite entries per column, the rest NaN (NaN where
    none): sorting puts NaN last, so it is the middle of the first ``count`` rows (``np.nanmedian``'s
    value, several times faster)."""
    ordered = np.sort(values, axis=0)
    c = count.reshape(count.shape + (1,) * (values.ndim - 1 - count.ndim))
    low = np.take_along_axis(ordered, (np.maximum(c, 1) - 1)[None] // 2, axis=0)[0]
    high = np.take_along_axis(ordered, np.minimum(c // 2, len(values) - 1)[None], axis=0)[0]
    return np.where(c > 0, (low + high) / 2, np.nan)


def describe(settings: SegmentSettings, size: tuple[int, int]) -> str:
    """One line on how frames of ``size`` are segmented (for logs and benchmarks)."""
    g = _Geometry.of(settings, size)
    return (f"model {g.model_size[0]}x{g.model_size[1]}, refine {g.refine_px} px, "
            f"close {g.close_px} px")


class Segmenter:
    """Downscaled MOG2 + full-resolution refinement + clean-up, with a prior-fusion hook.

    Not thread-safe for :meth:`apply` and :meth:`learn`; :meth:`set_prior` may
    be called from another thread (the Zenoh feedback callback).
    """

    def __init__(self, settings: SegmentSettings = SegmentSettings(), *, plate: np.ndarray | None = None) -> None:
        self.settings = settings
        self.plate = plate  # an image of the empty scene: the bootstrapped background (bootstrap())
        self._against_plate = False  # the plate is the background (bootstrap() took it)
        self._mog = cv2.createBackgroundSubtractorMOG2(
            history=settings.history, varThreshold=settings.var_threshold,
            detectShadows=settings.detect_shadows)
        self._open = _kernel(settings.open_px)
        self._geometry: _Geometry | None = None  # of the last frame size seen
        self._since_update = settings.update_phase % settings.update_every
        self._pending: tuple | None = None  # the selective update learn() still owes
        self._learned = 0
        # Full-resolution running mean of the background (float32 BGR), kept only
        # when the model runs downscaled: the refinement compares against it.
        self._full_bg: np.ndarray | None = None
        # Brightness of the model's background on a coarse grid (for the gain estimate).
        self._bg_level: np.ndarray | None = None
        # frame_index -> prior; the service sends priors ahead of time.
        self._priors: dict[int, _StoredPrior] = {}
        self._lock = threading.Lock()
        self.prior_stats = PriorStats()
        # Background bootstrap: the start-up buffer (sampled frames, their moving pixels),
        # and each bootstrap sample's noise around the median at model resolution, kept to
        # re-prime MOG2 when a ghost is absorbed.
        self._buffer: list[np.ndarray] = []
        self._buffer_moving: list[np.ndarray] = []
        self._previous: np.ndarray | None = None
        self._residuals: list[np.ndarray] = []
        self._track: tuple[int, int, int, int] | None = None  # last tracked walker box
        self._track_missed = 0
        self.tracks_started = 0  # tracks begun: on the first person, each lost track's next, each guided move
        # The tracked walker's blob (box height, area) over its last track_frames (at least 3) detections.
        self._walker: deque[tuple[float, float]] = deque(maxlen=max(3, settings.track_frames))
        self._colours = ColourSplit(ratio=settings.colour_ratio, window=settings.colour_window,
                                    rate=settings.colour_rate, frames=settings.colour_frames)
        self._static: list[list] = []  # [box, frames seen in place] per still component
        self.ghosts = 0  # ghost regions absorbed into the background

    @property
    def warming_up(self) -> bool:
        """True until the background is known (bootstrapped, or ``warmup_frames`` learned)."""
        return self._learned < self.settings.warmup_frames

    def background_image(self) -> np.ndarray | None:
        """The background model as a BGR uint8 copy, for viewing: full resolution when
        refining, else MOG2's (model resolution); None while warming up."""
        if self.warming_up:
            return None
        if self._full_bg is not None:
            return cv2.convertScaleAbs(self._full_bg)
        return self._mog.getBackgroundImage()

    def bootstrap(self, images: Sequence[np.ndarray],
                  moving: Sequence[np.ndarray] | None = None) -> None:
        """Learn the background from frames that need not be empty; segment from then on.

        The background is the per-pixel temporal median of ``images`` (BGR uint8,
        spread over the first seconds: whoever walks is elsewhere in most of
        them), preferring samples where the pixel is not ``moving`` (bool masks,
        optional); where the median is a shadow of a value enough samples agree
        on, that lit value (``bootstrap_lit``, :func:`_lit`). MOG2 is primed
        with the samples in which pixels far from the median
        (``bootstrap_outlier``) are replaced by it, so it learns the real noise
        but not the walkers; the full-resolution background is that median.

        The segmenter's ``plate``, an image of the empty scene (BGR uint8, the
        frames' size), is the background instead of the median: a walker who
        stays in the same place in the image for most of the samples (walking
        towards or away from the camera, on a treadmill) is in the median, and
        only the plate shows what is behind them. The samples still give MOG2
        the noise.
        """
        if not len(images):
            raise ValueError("bootstrap needs at least one frame")
        stack = np.stack(images)
        g = self._geometry_for((stack.shape[2], stack.shape[1]))
        moving = None if moving is None else np.stack(moving)
        if self.plate is not None:
            if self.plate.shape != stack.shape[1:] or self.plate.dtype != np.uint8:
                raise ValueError(f"the background plate must be a BGR uint8 image of the frames' size "
                                 f"{stack.shape[2]}x{stack.shape[1]}, got shape {self.plate.shape} {self.plate.dtype}")
            median = self.plate.astype(np.float32)
            self._against_plate = True
        else:
            median = _median(stack, moving)
            if self.settings.bootstrap_lit > 0:
                median = _lit(stack, median, moving, self.settings)
        self._full_bg = median if g.refine_px else None
        med_small = self._small(median.astype(np.uint8), g)
        residuals = []
        for image in stack:
            small = self._small(image, g)
            far = cv2.compare(cv2.absdiff(small, med_small).max(axis=2), self.settings.bootstrap_outlier,
                              cv2.CMP_GT)
            residual = cv2.subtract(small, med_small, dtype=cv2.CV_16S)
            residual[far > 0] = 0
            residuals.append(residual)
        self._residuals = residuals
        self._prime(med_small)
        self._learned = self.settings.warmup_frames
        self._buffer, self._buffer_moving, self._previous = [], [], None

    @staticmethod
    def _small(image: np.ndarray, g: _Geometry) -> np.ndarray:
        return cv2.resize(image, g.model_size, interpolation=cv2.INTER_AREA) if g.downscaled else image

    def _prime(self, base: np.ndarray) -> None:
        """A fresh MOG2 fed ``base`` (model resolution) plus each bootstrap sample's noise."""
        s = self.settings
        self._mog = cv2.createBackgroundSubtractorMOG2(
            history=s.history, varThreshold=s.var_threshold, detectShadows=s.detect_shadows)
        base16 = base.astype(np.int16)
        for residual in self._residuals:
            self._mog.apply(cv2.convertScaleAbs(cv2.add(base16, residual, dtype=cv2.CV_16S)),
                            learningRate=-1)
        self._bg_level = self._level(self._mog.getBackgroundImage())

    def _collect(self, image: np.ndarray, small: np.ndarray) -> None:
        """Start-up buffer of a live source: keep about ``bootstrap_samples`` of the first
        ``warmup_frames`` frames with their moving pixels, then bootstrap from them."""
        s = self.settings
        step = max(1, -(-s.warmup_frames // s.bootstrap_samples))
        if self._learned % step == 0:
            moving = np.zeros(image.shape[:2], bool)
            if self._previous is not None:
                change = cv2.compare(cv2.absdiff(small, self._previous).max(axis=2), s.bootstrap_still,
                                     cv2.CMP_GT)
                change = cv2.dilate(change, _kernel(3))
                moving = cv2.resize(change, (image.shape[1], image.shape[0]),
                                    interpolation=cv2.INTER_NEAREST) > 0
            self._buffer.append(image.copy())
            self._buffer_moving.append(moving)
        self._previous = small.copy()
        self._learned += 1
        if not self.warming_up:
            self.bootstrap(self._buffer, self._buffer_moving)

    def _geometry_for(self, size: tuple[int, int]) -> _Geometry:
        g = self._geometry
        if g is None or g.size != size:
            g = self._geometry = _Geometry.of(self.settings, size)
        return g

    def set_prior(self, prior: FeedbackMessage, *, now_ns: int | None = None) -> bool:
        """Install a prior mask (paper §7.1) for frames ``prior.frame_index`` onward.

        A frame uses the newest prior at or before its index that is at most
        ``prior_max_age`` frames old and was received at most
        ``prior_max_age_ms`` ago; priors for future frames wait (up to
        :data:`MAX_PRIORS` are kept). A prior issued (``issued_ns``, the
        sender's wall clock) longer ago than ``prior_max_age_ms`` is stale and
        not installed. Returns whether it was installed.
        """
        s = self.settings
        now_ns = time.time_ns() if now_ns is None else now_ns
        with self._lock:
            self.prior_stats.received += 1
            if prior.issued_ns and now_ns - prior.issued_ns > s.prior_max_age_ms * 1e6:
                self.prior_stats.stale += 1
                return False
        full = prior.full_mask()
        g = _Geometry.of(s, prior.image_size)  # not cached: another thread
        small = cv2.resize(full, g.model_size, interpolation=cv2.INTER_AREA) if g.downscaled else full
        full = full if g.refine_px else None
        # For the check at use (see _trust): the prior's box grown by half, and
        # what in it counts as covering the evidence (dilated: a prediction a few
        # pixels off, e.g. in phase, still explains it).
        x, y, w, h = cv2.boundingRect(cv2.compare(small, 0, cv2.CMP_GT))
        x0, y0 = max(0, x - w // 2), max(0, y - h // 2)
        x1, y1 = min(small.shape[1], x + w + w // 2), min(small.shape[0], y + h + h // 2)
        covering = np.zeros((y1 - y0, x1 - x0), np.uint8)  # empty for an empty prior
        if covering.size:
            covering = cv2.compare(small[y0:y1, x0:x1], s.prior_check_level, cv2.CMP_GE)
            reach = round(s.prior_check_reach * h)
            if reach > 0:
                covering = cv2.dilate(covering, _kernel(2 * reach + 1))
        trusted = (cv2.compare(small, s.prior_level, cv2.CMP_GE),
                   None if full is None else cv2.compare(full, s.prior_level, cv2.CMP_GE))
        stored = _StoredPrior(prior.image_size, small, full, time.monotonic(),
                              (x0, y0, x1 - x0, y1 - y0), covering, trusted)
        with self._lock:
            self._priors[prior.frame_index] = stored
            while len(self._priors) > MAX_PRIORS:
                del self._priors[min(self._priors)]
        return True

    def _prior_for(self, index: int, size: tuple[int, int]) -> _StoredPrior | None:
        s = self.settings
        oldest = time.monotonic() - s.prior_max_age_ms / 1e3
        with self._lock:
            for old in [k for k, p in self._priors.items()
                        if k < index - s.prior_max_age or p.received < oldest]:
                if self._priors.pop(old).received < oldest:
                    self.prior_stats.stale += 1
            usable = [k for k in self._priors if k <= index]
            if not usable:
                return None
            stored = self._priors[max(usable)]
        return stored if stored.image_size == size else None

    def _trust(self, fg: np.ndarray, stored: _StoredPrior,
               g: _Geometry) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The prior's trusted pixels, or None if it does not explain the evidence.

        The agent-side check of §7.1's loop (the twin of
        :func:`estimator.prior.explained` and :func:`~estimator.prior.weigh`, on
        MOG2's own foreground near the prior, before fusion): the prior's value
        is scaled by :func:`~estimator.prior.trust_factor` of its coverage, and
        the pixels still at ``prior_level`` are trusted (none left: not used).
        Without enough foreground to judge, it is trusted. A wrong estimate
        therefore cannot impose its silhouette against the camera's own
        evidence, and the loop cannot run away.
        """
        s = self.settings
        f = 1.0
        if s.prior_check:
            x, y, w, h = stored.near_box
            near = fg[y:y + h, x:x + w]
            n = cv2.countNonZero(near) if near.size else 0
            if n >= g.min_area * g.scale * g.scale:
                coverage = cv2.countNonZero(cv2.bitwise_and(near, stored.covering)) / n
                f = trust_factor(coverage, low=s.prior_min_coverage, high=s.prior_full_coverage)
            if f is None or s.prior_level / max(f, 1e-6) > 255:
                self.prior_stats.rejected += 1
                return None
        self.prior_stats.used += 1
        if f == 1.0:
            return stored.trusted
        self.prior_stats.weakened += 1
        level = int(np.ceil(s.prior_level / f))
        return (cv2.compare(stored.small, level, cv2.CMP_GE),
                None if stored.full is None else cv2.compare(stored.full, level, cv2.CMP_GE))

    def apply(self, image: np.ndarray, index: int,
              guide: tuple[int, int, int, int] | None = None) -> Segmentation | None:
        """Learn from or segment one BGR frame; None while warming up.

        The selective background update a frame calls for is deferred to
        :meth:`learn` (the agent calls it after publishing, off the
        capture-to-publish path) or else to the start of the next ``apply``:
        the model that classifies each frame is the same either way.

        Parameters
        ----------
        image : ndarray of shape (H, W, 3), uint8 BGR
        index : frame index, matched against a prior's ``frame_index``
        guide : (x, y, w, h), optional
            The walker's box in this frame as chosen over a whole clip
            (:func:`capture.refine.segment_clip`): the candidate overlapping it
            most (box IoU at least 0.3) is kept, whatever the track says.
        """
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {image.dtype} {image.shape}")
        self.learn()
        size = (image.shape[1], image.shape[0])
        g = self._geometry_for(size)
        small = self._small(image, g)
        if self.warming_up and self.settings.background == "bootstrap":
            self._collect(image, small)
            return None
        if self.warming_up:
            self._mog.apply(small, learningRate=-1)  # running average over the empty frames
            if g.refine_px:
                if self._full_bg is None or self._full_bg.shape[:2] != image.shape[:2]:
                    self._full_bg = image.astype(np.float32)
                else:
                    cv2.accumulateWeighted(image, self._full_bg, 1.0 / (self._learned + 1))
            self._learned += 1
            if not self.warming_up:
                self._bg_level = self._level(self._mog.getBackgroundImage())
            return None
        gain = self._gain(small)
        if gain != 1.0:  # divide the global lighting change out before classifying
            small = cv2.convertScaleAbs(small, alpha=1.0 / gain)
        raw = self._mog.apply(small, learningRate=0)  # classify only; learning is selective
        fg = cv2.compare(raw, 200, cv2.CMP_GT)  # 255 = foreground, 127 = shadow -> background
        stored = self._prior_for(index, size)
        prior = None if stored is None else self._trust(fg, stored, g)
        background = None
        if prior is not None:
            background = self._mog.getBackgroundImage()
        self._since_update += 1
        if self._since_update >= self.settings.update_every:
            # Guard MOG2's own foreground only: guarding the prior's additions too
            # would keep a wrong prior's region out of the model for good. Copies:
            # the source may reuse its buffers before learn() runs.
            self._pending = (small.copy(), fg, image.copy() if g.refine_px else None, background, gain)
            self._since_update = 0
        if prior is not None:
            fg = self._fuse(fg, small, background, prior[0])
        if self._open is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._open)
        noise = None
        if g.downscaled:  # back to full resolution, smoothing the steps
            fg = cv2.compare(cv2.resize(fg, size, interpolation=cv2.INTER_LINEAR), 127, cv2.CMP_GT)
            if g.refine_px:
                fg, noise = self._refine(fg, image, None if prior is None else prior[1], g, gain)
        return self._largest(fg, g, used_prior=prior is not None, image=image, gain=gain, guide=guide,
                             noise=noise)

    @staticmethod
    def _level(image: np.ndarray) -> np.ndarray:
        """Brightness (channel sum + 1, float32) on a grid of about 80 columns."""
        step = max(1, image.shape[1] // 80)
        return image[::step, ::step].sum(axis=2, dtype=np.float32) + 1.0

    def _gain(self, small: np.ndarray) -> float:
        """The frame's global brightness relative to the background model (median ratio).

        Lighting that drifts faster than the selective update follows (clouds,
        auto-exposure) scales the whole frame; dividing it out keeps MOG2's test
        about the walker. The walker covers a minority of pixels, so the median
        ignores it. 1.0 when off, unknown, or within 1 %.
        """
        if not self.settings.gain_compensation or self._bg_level is None:
            return 1.0
        level = self._level(small)
        if level.shape != self._bg_level.shape:
            return 1.0
        gain = float(np.median(level / self._bg_level))
        return gain if abs(gain - 1.0) > 0.01 and gain > 0 else 1.0

    def learn(self) -> None:
        """Run the pending selective background update, if any (cheap no-op otherwise).

        Learns from the frame with the (dilated) foreground replaced by the
        background estimate, at model resolution and, when refining, into the
        full-resolution background at the same rate.
        """
        if self._pending is None:
            return
        small, fg, image, background, gain = self._pending
        self._pending = None
        if background is None:
            background = self._mog.getBackgroundImage()
        guard = cv2.dilate(fg, self._geometry.guard)
        composite = small.copy()
        cv2.copyTo(background, guard, composite)
        self._mog.apply(composite, learningRate=self.settings.learning_rate)
        if self.settings.gain_compensation:
            self._bg_level = self._level(self._mog.getBackgroundImage())
        if image is not None and self._full_bg is not None:
            keep = cv2.compare(cv2.resize(guard, (image.shape[1], image.shape[0]),
                                          interpolation=cv2.INTER_NEAREST), 0, cv2.CMP_EQ)
            if gain != 1.0:
                image = cv2.convertScaleAbs(image, alpha=1.0 / gain)
            cv2.accumulateWeighted(image, self._full_bg, self.settings.learning_rate, mask=keep)

    def _refine(self, fg: np.ndarray, image: np.ndarray, prior: np.ndarray | None,
                g: _Geometry, gain: float = 1.0) -> tuple[np.ndarray, tuple[tuple[float, ...], float] | None]:
        """Re-test at full resolution every pixel within ``refine_px`` model pixels of the mask;
        with the mask, the lighting offset and noise variance measured (None on an empty mask).

        A pixel is foreground if its squared colour distance to the
        full-resolution background exceeds ``refine_threshold`` times the noise
        variance (MOG2's test), after removing the lighting offset; offset and
        noise are measured on the sure background around the walker (outside
        the dilated mask, inside the bounding rectangle, the only region
        processed). Thin limbs that the downscaled model blurs get their
        full-resolution edges back. Inside a trusted prior the weaker
        ``prior_threshold`` / ``prior_floor`` test adds pixels (§7.1); the
        union then passes the edge split again (the walker's colour from the
        evidence alone) and the shadow test, so that a model body wider than
        the walker does not paint a rim or the cast shadow back on
        (docs/CAPTURE.md, "Fusion"). The shadow test is repeated while it
        removes something, at most ``shadow_rounds`` times.
        """
        rx, ry, rw, rh = cv2.boundingRect(fg)
        if rw == 0 or rh == 0:
            return fg, None
        pad = 2 * g.refine_px + g.close_px  # room for the dilation, the noise sample, closing
        x0, y0, x1, y1 = _padded((rx, ry, rw, rh), pad, fg.shape[1::-1])
        coarse = fg[y0:y1, x0:x1]
        near = cv2.dilate(coarse, g.near)  # the pixels re-tested
        d = _difference(image[y0:y1, x0:x1], self._full_bg[y0:y1, x0:x1], gain)
        # Lighting moves between updates: remove the local offset measured on the sure
        # background (outside the dilated mask), whose spread is then the noise.
        offset, spread = cv2.meanStdDev(d, mask=cv2.bitwise_not(near))
        offset = tuple(float(v) for v in offset.ravel())
        d2 = _squared(d, offset)
        # Variance summed over channels, bounded like MOG2's (4..75 by default).
        var = min(max(float(np.sum(spread ** 2)), self._mog.getVarMin()), self._mog.getVarMax())
        level = max(self.settings.refine_threshold * var, self.settings.refine_floor ** 2)
        refined = cv2.bitwise_and(cv2.compare(d2, level, cv2.CMP_GT), near)
        frame = image[y0:y1, x0:x1].astype(np.float32) * np.float32(1.0 / gain)  # gain divided out
        if self.settings.edge_split:
            refined = self._split_edges(refined, frame, d2)
        if prior is not None:
            # Inside a trusted prior weaker evidence will do, at full resolution too (§7.1).
            weak = cv2.compare(d2, max(self.settings.prior_threshold * var, self.settings.prior_floor ** 2),
                               cv2.CMP_GT)
            seen = refined
            refined = cv2.bitwise_or(seen, cv2.bitwise_and(weak, cv2.bitwise_and(prior[y0:y1, x0:x1], near)))
            if self.settings.edge_split:  # the walker's colour from the evidence alone
                refined = self._split_edges(refined, frame, d2, interior=cv2.erode(seen, _kernel(5)))
        evidence = self._shadow_evidence(frame, self._full_bg[y0:y1, x0:x1], var, refined) \
            if self.settings.shadows else None
        if evidence is not None:  # the pixels' evidence is the mask's to weigh, round after round
            feet = None
            for _ in range(self.settings.shadow_rounds):
                out, feet = self._drop_shadows(refined, *evidence, g, feet)
                if out is refined:
                    break  # nothing removed
                refined = out
                if feet is None:
                    break  # without a feet band the next round removes only what this one gave back
                feet, before = self._feet_band(refined, g), feet
                if np.array_equal(feet, before):
                    break  # the same band: so too
        fg[y0:y1, x0:x1] = refined
        return fg, (offset, var)

    @staticmethod
    def _split_edges(fg: np.ndarray, frame: np.ndarray, d2: np.ndarray,
                     interior: np.ndarray | None = None) -> np.ndarray:
        """Keep an edge pixel of ``fg`` only where it is nearer the walker's colour than
        the background's (a region, full resolution; ``frame`` float32 with the gain
        divided out, ``d2`` = squared distance to the background, offset removed).

        Motion blur, defocus and compression (MJPG's 4:2:0 chroma) mix body
        and background over 1-3 px; a noise-level test takes every mixed
        pixel, so silhouettes grow by that band wherever the contrast is high
        (a dark coat on grass: ~0.75 IoU against careful masks). The walker's
        colour near each pixel is the mean of the interior (``fg`` eroded by
        a 5 px kernel, unless given) over a 9 px window; where no interior is
        that close the pixel is kept.
        """
        if interior is None:
            interior = cv2.erode(fg, _kernel(5))
        if not cv2.countNonZero(interior):
            return fg
        weight = cv2.boxFilter(interior, cv2.CV_32F, (9, 9), normalize=False) / 255.0
        body = cv2.boxFilter(cv2.bitwise_and(frame, frame, mask=interior), cv2.CV_32F, (9, 9),
                             normalize=False)
        body /= np.maximum(weight, 1.0)[..., None]
        to_body = cv2.transform(cv2.multiply(frame - body, frame - body), np.ones((1, 3), np.float32))
        nearer_bg = (d2 < to_body) & (weight > 0) & (interior == 0)
        out = fg.copy()
        out[nearer_bg] = 0
        return out

    def _shadow_evidence(self, frame: np.ndarray, background: np.ndarray, var: float,
                         fg: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Per pixel of a region (full resolution; ``frame`` float32 with the gain divided out):
        whether its colour is a shadow's or a reflection's of the background, and whether the
        background's texture is still there; None where no pixel of ``fg`` has such a colour
        (nothing to drop).

        A pixel's colour is a shadow's if it is the background's scaled by a ratio
        ``r`` in ``shadow_ratio`` (or up to ``reflection_ratio`` brighter), with
        little chromaticity distortion ``|I - rB| / |B|``; the texture is there
        when the local gradients of ``I`` are close to ``r`` times the
        background's. Neither depends on the mask, so :meth:`_refine` computes
        them once for all of :meth:`_drop_shadows`' rounds, which only shrink
        ``fg``: the texture is measured only on the bounding rectangle of
        ``fg``'s shadow-coloured pixels (padded by the 3 px the gradients and
        their 5 px mean reach, so exactly as on the whole region) and is False
        elsewhere.
        """
        s = self.settings
        bb = cv2.transform(cv2.multiply(background, background), np.ones((1, 3), np.float32)) + 1.0
        r = cv2.transform(cv2.multiply(frame, background), np.ones((1, 3), np.float32)) / bb
        dist = cv2.subtract(frame, cv2.multiply(background, cv2.merge([r, r, r])))
        chroma = cv2.transform(cv2.multiply(dist, dist), np.ones((1, 3), np.float32)) / bb
        lo, hi = s.shadow_ratio
        dark = ((r >= lo) & (r <= hi)) | ((r > 1.0) & (r <= s.reflection_ratio))
        shadow = dark & (chroma < s.shadow_chroma ** 2)
        bx, by, bw, bh = cv2.boundingRect(cv2.bitwise_and(fg, shadow.view(np.uint8)))
        if bw == 0:
            return None
        pad = 3  # Sobel's 1 px and the 5 px mean's 2 px
        x0, y0, x1, y1 = _padded((bx, by, bw, bh), pad, frame.shape[1::-1])
        sub = (slice(y0, y1), slice(x0, x1))
        gi, gb = cv2.cvtColor(frame[sub], cv2.COLOR_BGR2GRAY), cv2.cvtColor(background[sub], cv2.COLOR_BGR2GRAY)
        rs = r[sub]
        change = np.zeros_like(gi)
        present = np.zeros_like(gi)
        for dx, dy in ((1, 0), (0, 1)):
            a = cv2.Sobel(gi, cv2.CV_32F, dx, dy, ksize=3)
            b = cv2.multiply(cv2.Sobel(gb, cv2.CV_32F, dx, dy, ksize=3), rs)
            change += cv2.absdiff(a, b)
            present += cv2.absdiff(a, 0) + cv2.absdiff(b, 0)
        k = (5, 5)
        floor = 8.0 * np.sqrt(var / 3.0)  # the gradient operator's response to noise alone
        same_texture = np.zeros(shadow.shape, bool)
        same_texture[sub] = cv2.blur(change, k) < s.shadow_texture * cv2.blur(present, k) + floor
        return shadow, same_texture

    def _drop_shadows(self, fg: np.ndarray, shadow_colour: np.ndarray, same_texture: np.ndarray,
                      g: _Geometry, feet: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Remove shadow and reflection pixels from ``fg`` (a region, full resolution), given each
        pixel's evidence (:meth:`_shadow_evidence`: a shadow's colour, the background's texture).

        A pixel is shadow if it has a shadow's colour and the background's
        texture. Uniformly dark clothing on a plain background passes
        those tests too, so shadow pixels enclosed by the remaining body (within
        the closing of the rest, twice ``close_px``) are kept: a shadow is cast
        *beside* the walker, clothing is inside it. Opaque clothing fails the
        texture test (it hides the background's texture); a walker who shows
        the background through (thin, semi-transparent, or a reflection) may
        pass both, so when the tests would remove most of the foreground
        nothing is removed: never worse than no suppression. At the feet
        (:meth:`_feet_band`) colour alone decides. :meth:`_refine` runs it
        again on what it left (``shadow_rounds``), so that the band, measured
        on a blob with a long cast shadow at first, climbs back to the feet.
        The closing is computed only around the pixels it may give back
        (their bounding rectangle padded by the closing's reach), which is
        exactly the closing of the whole region there.

        A shadow lies on the ground the walker stands on (:func:`_cast`): a
        shadow-coloured stretch that rests on the rest of the body and does
        not reach the feet band is kept (a grey shirt over a grey path passes
        the colour and, on plain ground, the texture tests, above legs or a
        lower shirt of another colour).

        Returns the mask (``fg`` itself when nothing is removed) and the feet
        band it used (``feet``, computed when not given; None without one).
        """
        s = self.settings
        coloured = cv2.bitwise_and(fg, shadow_colour.view(np.uint8))  # 0/1: only these can go
        if not cv2.countNonZero(coloured):
            return fg, feet
        if feet is None and s.shadow_feet > 0:
            feet = self._feet_band(fg, g)
        texture = same_texture.view(np.uint8)
        removed = cv2.bitwise_and(coloured, texture if feet is None else cv2.bitwise_or(texture, feet.view(np.uint8)))
        if not cv2.countNonZero(removed):
            return fg, feet
        removed = cv2.bitwise_and(removed, _cast(coloured, fg, feet, max(1, g.close_px)))
        bx, by, bw, bh = cv2.boundingRect(removed)
        if bw == 0:
            return fg, feet
        body = cv2.bitwise_and(fg, cv2.compare(removed, 0, cv2.CMP_EQ))
        if 2 * cv2.countNonZero(body) < cv2.countNonZero(fg):
            return fg, feet  # most of it "shadow": a walker that looks like one (see docstring)
        if not g.close_px:
            return body, feet
        reach = 2 * g.close_px  # a closing by a (2 close_px + 1) disc looks this far
        x0, y0, x1, y1 = _padded((bx, by, bw, bh), reach, fg.shape[1::-1])
        enclosed = cv2.morphologyEx(body[y0:y1, x0:x1], cv2.MORPH_CLOSE, g.close_wide)
        box = (slice(by, by + bh), slice(bx, bx + bw))
        back = (removed[box] > 0) & (enclosed[by - y0:by - y0 + bh, bx - x0:bx - x0 + bw] > 0)
        if feet is not None:
            back &= ~feet[box]
        body[box][back] = 255
        return body, feet

    def _feet_band(self, fg: np.ndarray, g: _Geometry) -> np.ndarray:
        """The lowest ``shadow_feet`` of each foreground blob's height (bool mask).

        Blobs are those of ``fg`` closed vertically (``4 close_px + 1`` rows),
        so a walker split across the waist (a belt the colour of the
        background) is one blob with one band, at the feet.

        Where a walker meets the ground, the contact shadow is a few pixels
        around and between the feet: every pixel of it is near its own edge or
        a shoe's, so the texture test (background gradients still present)
        fails there, and the closing that keeps dark clothing re-admits it
        (vtest's path, 50 px walkers: most of what the silhouette had too much).
        """
        joined = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, np.ones((4 * g.close_px + 1, 1), np.uint8)) \
            if g.close_px else fg
        n, labels, stats, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
        start = stats[:, cv2.CC_STAT_TOP] + stats[:, cv2.CC_STAT_HEIGHT] * (1.0 - self.settings.shadow_feet)
        start[0] = np.inf  # the background label
        return np.arange(fg.shape[0])[:, None] >= start[labels]

    def _fuse(self, fg: np.ndarray, image: np.ndarray, background: np.ndarray,
              prior: np.ndarray) -> np.ndarray:
        """Foreground also where the prior is trusted and the pixel differs weakly."""
        diff = cv2.absdiff(image, background).max(axis=2)
        # Above the floor and above the frame's typical (mostly noise) difference,
        # so a noisy camera does not turn the whole prior into foreground.
        level = max(self.settings.prior_diff, self.settings.prior_noise_k * float(diff.mean()))
        weak = cv2.bitwise_and(cv2.compare(diff, level, cv2.CMP_GT), prior)
        return cv2.bitwise_or(fg, weak)

    def _largest(self, fg: np.ndarray, g: _Geometry, *, used_prior: bool,
                 image: np.ndarray | None = None, gain: float = 1.0,
                 guide: tuple[int, int, int, int] | None = None,
                 noise: tuple[tuple[float, ...], float] | None = None) -> Segmentation:
        """Close holes, keep the tracked walker's component (else the tallest, ``pick``) with the
        pieces of them stacked on it (:meth:`_groups`), crop it.

        Closing and labelling run only inside the bounding rectangle of all
        foreground (plus room for the closing kernel): usually a small region
        around the walker. With a convex kernel the closing stays inside that
        rectangle, so the result equals closing the whole frame. Components of
        at least ``min_area`` are candidates; one that stayed put for
        ``ghost_frames`` and whose outline is the background model's rather
        than the frame's is a ghost, absorbed into the background and dropped.
        """
        size = g.size
        rx, ry, rw, rh = cv2.boundingRect(fg)
        if rw == 0 or rh == 0:
            return self._nobody(size, used_prior, 0)
        if g.close is not None:
            m = g.close_px
            x0, y0, x1, y1 = _padded((rx, ry, rw, rh), m, size)
            region = cv2.morphologyEx(fg[y0:y1, x0:x1], cv2.MORPH_CLOSE, g.close)
            rx, ry = x0, y0
        else:
            region = fg[ry:ry + rh, rx:rx + rw]
        _, labels, stats, _ = cv2.connectedComponentsWithStats(region, connectivity=8)
        candidates = [k for k in range(1, len(stats)) if stats[k, cv2.CC_STAT_AREA] >= g.min_area
                      and self._wide(labels, stats, k, g)]
        if image is not None and self.settings.ghost_frames and self._residuals \
                and self._full_bg is not None:
            candidates = self._drop_ghosts(candidates, labels, stats, (rx, ry), image, gain, g)
        if not candidates:
            return self._nobody(size, used_prior, 0)
        groups = self._groups(candidates, stats, g)  # a torn walker's pieces joined
        boxes = {k: _shifted(bounding_box(stats[groups[k], :4]), rx, ry) for k in candidates}
        best = self._continuing(boxes, self._likeness(labels, stats, groups, image, (rx, ry)))
        guided = None if guide is None else max(boxes, key=lambda k: box_iou(boxes[k], guide))
        if guided is not None and box_iou(boxes[guided], guide) < 0.3:
            guided = None  # no candidate is the clip's walker here
        if guided is not None and guided != best:
            best = None  # the clip's walker, not the track's: a new track on it
        if best is None:  # a new track
            key = cv2.CC_STAT_HEIGHT if self.settings.pick == "tallest" else cv2.CC_STAT_AREA
            best = guided if guided is not None else \
                max(candidates, key=lambda k: (stats[k, key], stats[k, cv2.CC_STAT_AREA]))
            self._walker.clear()
            self._colours.reset()
            groups[best] = [best]  # no walker's height to join pieces to
            self.tracks_started += 1
        parts = groups[best]
        x, y, w, h = (int(v) for v in bounding_box(stats[parts, :4]))  # in the labelled region
        self._track, self._track_missed = _shifted((x, y, w, h), rx, ry), 0
        window = labels[y:y + h, x:x + w]
        blob = cv2.compare(window, best, cv2.CMP_EQ) if len(parts) == 1 else \
            np.isin(window, parts).astype(np.uint8) * 255
        x, y = rx + x, ry + y  # the blob's box in the full frame
        if len(parts) > 1 and image is not None and noise is not None:  # noise: refined against _full_bg
            blob = self._bridged(blob, image[y:y + h, x:x + w], self._full_bg[y:y + h, x:x + w], gain, g, noise)
        areas = [a for _, a in self._walker]
        area = int(stats[best, cv2.CC_STAT_AREA])
        if self.settings.colour_split and image is not None:
            others = [k for k in candidates if k != best]
            if others:
                self._colours.see_others(image[ry:ry + labels.shape[0], rx:rx + labels.shape[1]],
                                         np.isin(labels, others))
            cut = self._colours.split(blob, image[y:y + h, x:x + w],
                                      median_area=float(np.median(areas)) if len(areas) >= 3 else np.inf)
            if cut is not blob:  # the box tightened around what is left
                bx, by, w, h = cv2.boundingRect(cut)
                blob, x, y = cut[by:by + h, bx:bx + w], x + bx, y + by
        if len(parts) == 1:  # the walker's height once cut off the others
            self._walker.append((h, area))
        else:  # a join is measured by it, and moves it by at most JOIN_STEP: torn frames do not make it short
            tall, usual = np.median(np.array(self._walker, float), axis=0)
            self._walker.append((float(np.clip(h, (1 - JOIN_STEP) * tall, (1 + JOIN_STEP) * tall)), usual))
        if self.settings.fill_holes is not None:
            blob = filled(blob, self.settings.fill_holes)
        m = self.settings.margin_px
        x0, y0, x1, y1 = _padded((x, y, w, h), m, size)  # the crop: the box and the margin, in the frame
        crop = cv2.copyMakeBorder(blob, y - y0, y1 - y - h, x - x0, x1 - x - w, cv2.BORDER_CONSTANT, value=0)
        return Segmentation(crop, Box(x0, y0, x1 - x0, y1 - y0), size, cv2.countNonZero(blob), used_prior,
                            len(candidates), tuple(dict.fromkeys(boxes[k] for k in candidates)),
                            plate=self._against_plate)

    def _groups(self, candidates: list[int], stats: np.ndarray, g: _Geometry) -> dict[int, list[int]]:
        """Each candidate component with the pieces stacked on it that make it the walker's height
        (``stack_gap``; the candidate alone where none does, or no walker is tracked yet).

        Clothing the colour of the ground behind tears a walker at the waist
        or the hips: head and torso above, legs below, each its own component,
        and the track kept one. A candidate shorter than ``TORN`` of the
        walker's median height over its last detections is joined by such a
        piece (a component as short, above or below it: widths overlapping by
        half the narrower, apart by at most ``stack_gap`` of the joined height,
        or overlapping by up to a quarter of it where an arm hangs beside the
        hips) when that brings its height nearer the median and not beyond 1.2
        times it: two people one above the other in the image are taller than
        one. Nearest the median first, while one qualifies.
        """
        if not self.settings.stack_gap or len(self._walker) < 3:
            return {k: [k] for k in candidates}
        tall = float(np.median([t for t, _ in self._walker]))
        pieces = [k for k in range(1, len(stats)) if 4 * stats[k, cv2.CC_STAT_AREA] >= g.min_area
                  and stats[k, cv2.CC_STAT_HEIGHT] < TORN * tall]  # a whole walker is not a piece
        return {k: self._stacked(k, stats, [p for p in pieces if p != k], tall) for k in candidates}

    def _stacked(self, best: int, stats: np.ndarray, pieces: list[int], tall: float) -> list[int]:
        """Component ``best`` and the ``pieces`` joined to it (:meth:`_groups`)."""
        parts, box = [best], tuple(stats[best, :4])
        while pieces and box[3] < TORN * tall:  # about whole: a leg lifted, a head bowed, not torn
            x, y, w, h = box
            joined = []
            for k in pieces:
                kx, ky, kw, kh = stats[k, :4]
                uh = bounding_box([box, stats[k, :4]])[3]
                gap = max(ky - (y + h), y - (ky + kh))
                if min(x + w, kx + kw) - max(x, kx) >= 0.5 * min(w, kw) \
                        and -0.25 * uh <= gap <= self.settings.stack_gap * uh \
                        and uh <= 1.2 * tall and abs(np.log(uh / tall)) < abs(np.log(h / tall)):
                    joined.append((abs(np.log(uh / tall)), k))
            if not joined:
                break
            k = min(joined)[1]
            parts.append(k)
            pieces = [p for p in pieces if p != k]
            box = bounding_box([box, stats[k, :4]])
        return parts

    def _bridged(self, blob: np.ndarray, frame: np.ndarray, background: np.ndarray, gain: float,
                 g: _Geometry, noise: tuple[tuple[float, ...], float]) -> np.ndarray:
        """A torn walker's stacked pieces (:meth:`_groups`) joined across the rows between them.

        What tore the walker is clothing the colour of the ground behind: those
        rows hold the walker, only weakly different from the background. In the
        gap's rows, inside the convex hull of the few rows bordering it, the pixels that pass
        the weak test of a trusted prior (``prior_threshold`` times the frame's
        noise variance ``noise``, measured by :meth:`_refine` with the lighting
        offset, and ``prior_floor``) are added, then closed (``close_px``)
        within the hull: the torso the head and the legs frame, not a guess of
        its shape.
        """
        rows = np.flatnonzero(blob.any(axis=1))
        gaps = np.flatnonzero(np.diff(rows) > 1)
        if not gaps.size:
            return blob
        hull = np.zeros_like(blob)
        for i in gaps:
            border = [r for r in (*range(max(rows[i] - 2, rows[0]), rows[i] + 1),
                                  *range(rows[i + 1], min(rows[i + 1] + 3, rows[-1] + 1))) if blob[r].any()]
            ys, xs = np.nonzero(blob[border])
            points = np.stack([xs, np.asarray(border)[ys]], axis=1).astype(np.int32)
            spanned = np.zeros_like(blob)
            cv2.fillConvexPoly(spanned, cv2.convexHull(points), 255)
            hull[rows[i] + 1:rows[i + 1]] = spanned[rows[i] + 1:rows[i + 1]]  # the gap's rows only
        (offset, var), s = noise, self.settings
        d2 = _squared(_difference(frame, background, gain), offset)
        weak = cv2.compare(d2, max(s.prior_threshold * var, s.prior_floor ** 2), cv2.CMP_GT)
        torso = cv2.bitwise_or(blob, cv2.bitwise_and(weak, hull))
        if g.close is not None:
            torso = cv2.bitwise_and(cv2.morphologyEx(torso, cv2.MORPH_CLOSE, g.close), hull)
        return cv2.bitwise_or(blob, torso)

    @staticmethod
    def _wide(labels: np.ndarray, stats: np.ndarray, k: int, g: _Geometry) -> bool:
        """Whether component ``k`` holds a disc of ``min_width`` (distance transform)."""
        if not g.min_width:
            return True
        x, y, w, h = (int(v) for v in stats[k, :4])
        if min(w, h) < g.min_width:
            return False
        comp = cv2.copyMakeBorder(cv2.compare(labels[y:y + h, x:x + w], k, cv2.CMP_EQ),
                                  1, 1, 1, 1, cv2.BORDER_CONSTANT)
        return 2.0 * cv2.minMaxLoc(cv2.distanceTransform(comp, cv2.DIST_L2, 5))[1] >= g.min_width

    def _nobody(self, size: tuple[int, int], used_prior: bool, n: int) -> Segmentation:
        """No walker in this frame; the tracked box ages (forgotten after ``track_frames``)."""
        self._track_missed += 1
        if self._track_missed > self.settings.track_frames:
            self._track = None
            self._walker.clear()
        return Segmentation.nothing(size, used_prior, n, self._against_plate)

    def _likeness(self, labels: np.ndarray, stats: np.ndarray, groups: dict[int, list[int]],
                  image: np.ndarray | None, origin: tuple[int, int]) -> Callable[[int], float] | None:
        """How much a candidate's colours are the tracked walker's (:meth:`ColourSplit.likeness` of its
        pieces' pixels; ``labels`` and ``stats`` the region's components at ``origin`` of ``image``), once
        the walker's colours are learned and ``track_colour`` is on; else None."""
        if not (self.settings.colour_split and self.settings.track_colour) or image is None \
                or not self._colours.ready:
            return None
        rx, ry = origin

        def like(k: int) -> float:
            x, y, w, h = (int(v) for v in bounding_box(stats[groups[k], :4]))
            pieces = np.isin(labels[y:y + h, x:x + w], groups[k])
            return self._colours.likeness(image[ry + y:ry + y + h, rx + x:rx + x + w][pieces])
        return like

    def _continuing(self, boxes: dict[int, tuple[int, int, int, int]],
                    like: Callable[[int], float] | None = None) -> int | None:
        """The candidate that best continues the tracked walker, if any overlaps its grown box.

        The score is the overlap (the intersection with the grown box over the
        union of the candidate's and the tracked box's own areas, not
        :func:`box_iou` with the grown box) times the ratio of the candidate's
        height to the walker's median height over its last ``track_frames`` (at least 3)
        detections (the smaller over the larger). By overlap alone, a walker torn
        in two by clothing the colour of the ground lost the track to the
        piece passers-by had joined, and the track then went on with them
        (docs/ROBUSTNESS.md); the walker's height changes slowly. Where two or
        more overlap it, each score is also weighed by ``like`` (:meth:`_likeness`)
        to the power ``track_colour``: when a merged blob parts, both parts lie in
        the merged box, and the larger one took the track (docs/ROBUSTNESS.md,
        "After a merge, the part in the walker's colours"). Where no part has any of
        the walker's colours (every weighed score 0), overlap and height decide.
        """
        if self._track is None or self._track_missed > self.settings.track_frames:
            return None
        x, y, w, h = self._track
        grow = self.settings.track_grow * (1 + self._track_missed)
        gx, gy = x - grow * w, y - grow * h
        gw, gh = w * (1 + 2 * grow), h * (1 + 2 * grow)
        tall = float(np.median([t for t, _ in self._walker])) if self._walker else float(h)
        scores = {}
        for k, (bx, by, bw, bh) in boxes.items():
            ix = max(0.0, min(gx + gw, bx + bw) - max(gx, bx))
            iy = max(0.0, min(gy + gh, by + bh) - max(gy, by))
            overlap = ix * iy / (bw * bh + w * h - ix * iy)  # IoU with the grown box
            if overlap > 0:
                scores[k] = overlap * min(bh, tall) / max(bh, tall)
        if len(scores) > 1 and like is not None:
            weighed = {k: v * like(k) ** self.settings.track_colour for k, v in scores.items()}
            if max(weighed.values()) > 0:  # else none has the walker's colours: by overlap and height
                scores = weighed
        return max(scores, key=scores.get) if scores else None

    def _drop_ghosts(self, candidates: list[int], labels: np.ndarray, stats: np.ndarray,
                     origin: tuple[int, int], image: np.ndarray, gain: float,
                     g: _Geometry) -> list[int]:
        """Candidates minus ghosts, which are absorbed into the background.

        A component whose box stays put (IoU > 0.8 with last frame's) for
        ``ghost_frames`` frames is tested, then every ``ghost_frames`` frames:
        on its outline the background model's gradient is compared with the
        frame's. Where the model was wrong (someone stood there at bootstrap)
        the outline is an edge of the model, not of the frame; a walker who
        stands still has the frame's edges, so is never absorbed.
        """
        s = self.settings
        ox, oy = origin
        still, keep = [], []
        for k in candidates:
            box = (ox + int(stats[k, 0]), oy + int(stats[k, 1]), int(stats[k, 2]), int(stats[k, 3]))
            seen = next((n for b, n in self._static if box_iou(b, box) > 0.8), 0) + 1
            still.append([box, seen])
            ghost = self._ghost(labels, k, stats, origin, image, gain) \
                if seen % s.ghost_frames == 0 else None
            if ghost is not None:
                self._absorb(*ghost, g)
                continue
            keep.append(k)
        self._static = still
        return keep

    def _ghost(self, labels: np.ndarray, k: int, stats: np.ndarray, origin: tuple[int, int],
               image: np.ndarray, gain: float) -> tuple | None:
        """``(slices, component mask, frame patch)`` if component ``k`` is a ghost, else None."""
        x, y, w, h = (int(v) for v in stats[k, :4])
        x0, y0 = max(0, x - 2), max(0, y - 2)
        comp = cv2.compare(labels[y0:y + h + 2, x0:x + w + 2], k, cv2.CMP_EQ)
        ring = cv2.morphologyEx(comp, cv2.MORPH_GRADIENT, _kernel(3))
        sl = (slice(origin[1] + y0, origin[1] + y0 + comp.shape[0]),
              slice(origin[0] + x0, origin[0] + x0 + comp.shape[1]))
        frame = cv2.cvtColor(image[sl], cv2.COLOR_BGR2GRAY).astype(np.float32) / np.float32(gain)
        model = cv2.cvtColor(self._full_bg[sl], cv2.COLOR_BGR2GRAY)
        edges = [cv2.mean(cv2.magnitude(cv2.Sobel(a, cv2.CV_32F, 1, 0), cv2.Sobel(a, cv2.CV_32F, 0, 1)),
                          mask=ring)[0] for a in (frame, model)]
        if edges[1] <= self.settings.ghost_edge_ratio * max(edges[0], 1.0):
            return None
        return sl, cv2.dilate(comp, _kernel(5)), image[sl].astype(np.float32) * np.float32(1.0 / gain)

    def _absorb(self, sl: tuple[slice, slice], mask: np.ndarray, patch: np.ndarray,
                g: _Geometry) -> None:
        """Copy the frame into the background under ``mask`` (full resolution), re-prime MOG2."""
        cv2.copyTo(patch, mask, self._full_bg[sl])
        base = self._small(cv2.convertScaleAbs(self._full_bg), g)
        self._prime(base)
        self._static = []
        self.ghosts += 1


def _difference(image: np.ndarray, background: np.ndarray, gain: float) -> np.ndarray:
    """``image`` (uint8 BGR) with the global ``gain`` divided out, less ``background`` (float32)."""
    return cv2.addWeighted(image, 1.0 / gain, background, -1.0, 0.0, dtype=cv2.CV_32F)


def _squared(difference: np.ndarray, offset: tuple[float, ...]) -> np.ndarray:
    """Squared colour distance, channels summed, of a :func:`_difference` less the local
    lighting ``offset`` (BGR)."""
    d = cv2.subtract(difference, offset + (0.0,))
    return cv2.transform(cv2.multiply(d, d), np.ones((1, 3), np.float32))


def _cast(coloured: np.ndarray, fg: np.ndarray, feet: np.ndarray | None, reach: int) -> np.ndarray:
    """Which shadow-coloured pixels may be a cast shadow (0/1 uint8 mask of ``coloured``).

    ``coloured`` (0/1 uint8) holds the shadow-coloured pixels of ``fg``. A
    shadow lies on the ground from where the walker stands: below its
    8-connected stretches is ground, or the stretch reaches the feet band
    (``feet``, bool, or None). A stretch that rests on the rest of ``fg``
    (in most of its columns, foreground of another colour within ``reach``
    pixels below its lowest pixel: a belt's seam may part them) and does not
    reach the feet band is clothing, not a shadow, if it is at least a
    ``2 reach`` square's area (smaller stretches are edges' noise). Computed
    on the bounding rectangle of ``coloured`` and the ``reach`` rows below it.
    """
    x, y, w, h = cv2.boundingRect(coloured)
    cast = np.zeros_like(coloured)
    if w == 0:
        return cast
    n, labels = cv2.connectedComponents(coloured[y:y + h, x:x + w], connectivity=8)
    ys, xs = np.nonzero(labels)
    stretch = labels[ys, xs]
    key = stretch * w + xs  # one per stretch and column
    by_column = np.lexsort((-ys, key))  # grouped by it, the lowest pixel first
    key = key[by_column]
    first = by_column[np.r_[True, key[1:] != key[:-1]]]
    label, col, low = stretch[first], xs[first], ys[first]
    y1 = min(y + h + reach, fg.shape[0])
    body = cv2.bitwise_and(cv2.compare(fg[y:y1, x:x + w], 0, cv2.CMP_GT),
                           cv2.compare(coloured[y:y1, x:x + w], 0, cv2.CMP_EQ))
    under = cv2.dilate(body, np.ones((reach, 1), np.uint8), anchor=(0, 0))  # row r: body in rows r..r+reach-1
    below = low + 1
    on_body = below < under.shape[0]
    on_body[on_body] = under[below[on_body], col[on_body]] > 0
    rests = np.bincount(label[on_body], minlength=n) > 0.5 * np.bincount(label, minlength=n)
    rests &= np.bincount(stretch, minlength=n) >= (2 * reach) ** 2  # less is an edge's noise
    if feet is not None:
        rests[labels[feet[y:y + h, x:x + w]]] = False  # reaching the feet band: a shadow may start there
    keep = (~rests).astype(np.uint8)
    keep[0] = 0
    cast[y:y + h, x:x + w] = keep[labels]
    return cast


def _shifted(box, dx: int, dy: int) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` moved by ``(dx, dy)``, as ints."""
    return int(box[0]) + dx, int(box[1]) + dy, int(box[2]), int(box[3])


def box_iou(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> float:
    """IoU of two ``(x, y, w, h)`` boxes."""
    ix = max(0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / (a[2] * a[3] + b[2] * b[3] - inter) if inter else 0.0
