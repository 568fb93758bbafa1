"""Silhouette priors from an estimated walk (Izo–Grimson §7.1).

For each frame and camera of an estimated window the model body is rendered in
the decoded phase from the camera's estimated viewpoint, brought onto the
observed silhouette by the inverse of the matching registration (scale,
centroid, principal axis; §5) — or, where the silhouette is torn, placed by the
walker's extent fitted over the whole window (:func:`body_extent`) —
optionally nudged by the translation that best overlaps the observation, and softened into a per-pixel prior in full-frame
coordinates: 255 deep inside the body, 128 on the rendered outline, falling to
0 a few pixels outside, so a segmenter trusts the interior and stays unsure at
the edges where the model body and the real one differ. An evidence gate keeps
the prior near what was observed — close for a complete silhouette, farther
for a torn one — and :func:`explained` / :func:`weigh` measure and act on how
much of an observation a prior accounts for (a wrong prior explains little).

For live use :func:`predict_phases` continues the decoded HMM path at its mean
speed and :func:`predict_priors` renders priors for frames not seen yet, so a
prior can reach a capture agent before its frame.

A window's priors can also carry the walker's own silhouettes at the same
decoded phase a gait cycle away (``PriorConfig.same_phase``), where the model
body is not the walker's.

:func:`refine_silhouette` fuses a prior with a given binary silhouette when no
image is left to re-segment: holes the model explains are filled, blobs away
from the body are dropped. Fusion with raw frames lives in the capture
package's segmenter (``capture.segment.Segmenter.set_prior``).

This module is pure: arrays and dataclasses in and out; the renderer is passed in.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.optimize
import scipy.special

from .camera import Camera
from .cleanup import evenly_spaced
from .gait import GaitModel, load_gait
from .joints import N_JOINTS
from .pipeline import CameraTrack, WalkEstimate
from .registration import register
from .skeleton import BodyShape, forward_kinematics
from .windows import SegmentedWalk, window_tracks

__all__ = [
    "FEEDBACK",
    "Prior",
    "PriorConfig",
    "body_extent",
    "explained",
    "phase_speed",
    "predict_phases",
    "predict_priors",
    "prior_from_render",
    "priors_for_window",
    "refine_silhouette",
    "render_body",
    "rotate_prior",
    "soften",
    "trim_silhouette",
    "Trust",
    "trust_test",
    "trusted_priors",
    "turn_viewpoints",
    "walker_tracks",
    "weigh",
]


@dataclass(frozen=True)
class PriorConfig:
    """Options of the priors; one default each.

    Parameters
    ----------
    pixels_per_metre : float
        Scale of the orthographic render of the model body (it is then resampled
        onto the observation; 120 px/m gives a ~210 px tall body).
    band : float
        Width of the soft edge as a fraction of the body's height: the prior is
        ``255 * sigmoid(signed_distance / (band * height))``.
    inset : float
        Shift of the 50% level into the body, fraction of the height (0 = the
        rendered outline is the 128 level).
    rotate : bool
        Follow the observed principal axis (the full similarity of §5); off by
        default: a walker is upright, and a torn silhouette's axis is noise.
    search : float
        Translation search, fraction of the observed height, for the shift of the
        registered render that overlaps the observation most (0 = off).
    pad : float
        Margin of the prior's box around the observed box, fraction of the height.
    reach_min, reach_max : float
        Evidence gate, fractions of the height: the prior fades beyond
        ``reach`` of the observed foreground (its enclosed holes count as
        observed), with ``reach`` from ``reach_min`` for an observation of at
        least ``complete_ratio`` of the model body's area (bodies differ: a
        walker slimmer than the model is still complete) to ``reach_max`` for
        one of half its area or less. A
        complete silhouette needs no help and a misfit model would only add
        false foreground at its edges; a torn one needs the model to bridge
        gaps. ``reach_max = inf`` turns the gate off.
    torn, envelope : float
        A silhouette whose box is shorter than the window's extent of the walker
        (:func:`body_extent`) by more than ``torn`` (a fraction) is torn: the
        render is placed by that extent rather than registered onto it (a
        fragment's height and centroid say little about the body's).
        ``envelope`` is the quantile of the extent's fit (the top is the line
        below all but this fraction of the observed tops, the bottom likewise);
        ``torn = inf`` turns this off.
    body : BodyShape
        The model body (the estimator reports its joints).
    trust : bool
        Apply :func:`trust_test` where priors are made (:func:`priors_for_window`,
        :func:`predict_priors`): a prior from an estimate that does not explain
        the observations is not made at all. Every feedback path turns it on
        (:data:`FEEDBACK`: offline refine, REST refine jobs, live priors); off
        by default for the bare rendering (evaluations, ablations).
    max_spread_deg, min_flip_margin : float
        Trust test, per camera: the viewpoint cloud's semi-major axis at most
        ``max_spread_deg`` (a wider cloud is no viewpoint), and, where neither
        the motion cue, the other cameras' phase nor the earlier windows
        settled ahead/behind, a flip margin of at least ``min_flip_margin``.
    min_window_agreement, min_agreement : float
        Trust test on :attr:`Prior.agreement` (IoU of the registered render
        with the cleaned observation): the window's median at least
        ``min_window_agreement`` (a right estimate: 0.63-0.92 on damaged
        synthetic walks, its viewpoint turned by 90 deg: 0.37-0.51), each
        frame's own at least ``min_agreement`` (a frame whose walker the
        clean-up missed).
    min_view_margin : float
        Trust test: the window's median agreement must exceed by this much
        the best median agreement of the model rendered from the viewpoint
        turned by +-90 deg (on ``trust_window`` of its frames): data that fit a
        viewpoint 90 deg away as well do not establish this one.
    trust_window : int
        Frames rendered for the turned viewpoints; and, for live priors
        (:func:`predict_priors`, frames not seen yet), the window's last
        frames on which the agreement is measured.
    fill_reach, limb, limb_level : float, float, int
        Offline refinement of binary silhouettes (:func:`refine_silhouette`'s
        ``reach``, ``limb``, ``limb_level``): only the parts of the prior
        missing from the walker that are thicker than ``2 * limb`` x height
        (a cut limb, a hole) and the holes it encloses are filled, no band
        along the outline (``bench/eval_refine_damage.py``, docs/FEEDBACK.md).
    same_phase : bool
        :func:`priors_for_window`: raise each trusted prior to 255 where the
        walker's own silhouettes on the window's other frames at the same
        phase (within ``same_phase_cycle`` of a cycle: a gait cycle away)
        cover the pixel, at least ``same_phase_share`` of them and at least
        ``same_phase_frames`` frames, inside the model's support (prior at
        least ``same_phase_level``). The model body is not the walker's
        (another build, another stride); the walker a cycle earlier or later
        is, and a limb the segmenter lost on one frame is seldom lost at the
        same place a cycle later. Each silhouette is scaled by the ratio of
        the boxes' heights and placed by the box's top and centre.
    """

    pixels_per_metre: float = 120.0
    band: float = 0.015
    inset: float = 0.0
    rotate: bool = False
    search: float = 0.06
    pad: float = 0.1
    reach_min: float = 0.0
    reach_max: float = 0.2
    complete_ratio: float = 0.7
    torn: float = 0.1
    envelope: float = 0.1
    body: BodyShape = field(default_factory=BodyShape)
    trust: bool = False
    max_spread_deg: float = 35.0
    min_flip_margin: float = 0.1
    min_window_agreement: float = 0.6
    min_agreement: float = 0.5
    min_view_margin: float = 0.1
    trust_window: int = 4
    fill_reach: float = 0.0
    limb: float = 0.025
    limb_level: int = 160
    same_phase: bool = False
    same_phase_cycle: float = 0.05
    same_phase_share: float = 0.5
    same_phase_frames: int = 2
    same_phase_level: int = 64

    def __post_init__(self) -> None:
        if self.pixels_per_metre <= 0 or self.band <= 0:
            raise ValueError(f"pixels_per_metre and band must be positive, got {self.pixels_per_metre}, {self.band}")
        if self.search < 0 or self.pad < 0:
            raise ValueError(f"search and pad must be >= 0, got {self.search}, {self.pad}")
        if self.torn < 0 or not 0 < self.envelope < 0.5:
            raise ValueError(f"need torn >= 0 and 0 < envelope < 0.5, got {self.torn}, {self.envelope}")
        if not 0 <= self.reach_min <= self.reach_max:
            raise ValueError(f"need 0 <= reach_min <= reach_max, got {self.reach_min}, {self.reach_max}")


FEEDBACK = PriorConfig(trust=True, same_phase=True)
"""The configuration of every feedback path: priors only from estimates that pass :func:`trust_test`,
raised where the walker's own silhouettes at the same phase agree (``same_phase``)."""


@dataclass(frozen=True)
class Prior:
    """A soft foreground prior for one frame of one camera.

    Attributes
    ----------
    frame_index : int
        Frame of the window (or a predicted frame after it).
    box : (int, int, int, int)
        ``(x, y, w, h)`` of ``mask`` in the full frame.
    image_size : (int, int)
        ``(width, height)`` of the full frame.
    mask : ndarray of shape (h, w), uint8
        0 = surely background / no opinion ... 255 = surely the walker.
    agreement : float
        IoU of the registered render (before softening and the evidence gate)
        with the observation it was registered onto (for a torn observation,
        placed by the extent: the fraction of it the render covers): how well
        the estimate explains this frame (:func:`trust_test`); NaN when unknown.
    """

    frame_index: int
    box: tuple[int, int, int, int]
    image_size: tuple[int, int]
    mask: np.ndarray = field(repr=False, compare=False)
    agreement: float = float("nan")

    def __post_init__(self) -> None:
        x, y, w, h = self.box
        if self.mask.dtype != np.uint8 or self.mask.shape != (h, w):
            raise ValueError(f"mask must be uint8 of shape ({h}, {w}), got {self.mask.dtype} {self.mask.shape}")
        if min(x, y, w, h) < 0 or x + w > self.image_size[0] or y + h > self.image_size[1]:
            raise ValueError(f"box {self.box} is not inside the image {self.image_size}")

    def full_mask(self) -> np.ndarray:
        """The prior pasted into a full-frame ``(height, width)`` canvas of zeros."""
        out = np.zeros(self.image_size[::-1], np.uint8)
        x, y, w, h = self.box
        out[y : y + h, x : x + w] = self.mask
        return out


# ------------------------------------------------------------------------ rendering


def render_body(
    phases: np.ndarray,
    azimuth_deg: float,
    elevation_deg: float,
    *,
    renderer,
    body: BodyShape | None = None,
    gait: GaitModel | None = None,
    pixels_per_metre: float = 120.0,
) -> list[np.ndarray]:
    """Orthographic silhouettes (uint8 0/255) of the model body at each phase.

    ``renderer`` is an :class:`estimator.render.Renderer` (its shape is used
    unless ``body`` is given and differs, which the caller should avoid).
    """
    body = body or renderer.shape
    gait = gait or load_gait()
    phases = np.atleast_1d(np.asarray(phases, float))
    skel = forward_kinematics(gait.angles(phases % 1.0), body)
    skel = skel - skel[:, :N_JOINTS].mean(axis=1, keepdims=True)
    side = int(np.ceil(1.5 * body.height * pixels_per_metre)) | 1  # the body, centred, with a margin
    cam = Camera(azimuth_deg, elevation_deg, distance=10.0, image_size=(side, side),
                 focal_px=pixels_per_metre, orthographic=True)
    return [renderer.render(j, cam)[0] for j in skel]


def soften(mask: np.ndarray, *, band_px: float, inset_px: float = 0.0) -> np.ndarray:
    """Soft prior of a binary mask: ``255 * sigmoid((signed distance - inset) / band)``, float32."""
    m = (mask > 0).astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    sd = np.where(m > 0, inside - 0.5, 0.5 - outside) - inset_px
    return (255.0 * scipy.special.expit(sd / max(band_px, 1e-3))).astype(np.float32)


def _inverse(m: np.ndarray) -> np.ndarray:
    a = np.vstack([m, [0.0, 0.0, 1.0]])
    return np.linalg.inv(a)[:2]


def _extent_map(rendered: np.ndarray, extent: tuple[float, float, float],
                origin: tuple[float, float]) -> tuple[np.ndarray | None, float]:
    """Similarity render pixels -> pixels relative to ``origin`` that puts the render's
    top row at the extent's top, its bottom row at the bottom and its centroid at the centre."""
    fg = rendered > 127
    rows = np.flatnonzero(fg.any(axis=1))
    cx, top, bottom = extent
    if rows.size == 0 or not bottom > top:
        return None, 0.0
    s = (bottom - top) / float(rows[-1] - rows[0] + 1)
    rc = float(np.nonzero(fg)[1].mean())
    m = np.array([[s, 0.0, cx - origin[0] - s * rc], [0.0, s, top - origin[1] - s * rows[0]]])
    return m, float(bottom - top)


def _best_shift(observed: np.ndarray, predicted: np.ndarray, r: int) -> tuple[int, int]:
    """Integer shift (dx, dy) of ``predicted`` within +-r that overlaps ``observed`` most."""
    if r <= 0 or not predicted.any() or not observed.any():
        return 0, 0
    obs = cv2.copyMakeBorder((observed > 0).astype(np.float32), r, r, r, r, cv2.BORDER_CONSTANT, value=0)
    score = cv2.matchTemplate(obs, (predicted > 0).astype(np.float32), cv2.TM_CCORR)
    # Prefer small shifts among near-ties (a flat overlap landscape = no evidence).
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    score = score - 1e-3 * float(predicted.astype(bool).sum()) * np.hypot(xx, yy) / max(r, 1)
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    return int(ix - r), int(iy - r)


def prior_from_render(
    rendered: np.ndarray,
    observed: np.ndarray,
    box: np.ndarray,
    image_size: tuple[int, int],
    *,
    frame_index: int,
    config: PriorConfig | None = None,
    shift: tuple[float, float] = (0.0, 0.0),
    extent: tuple[float, float, float] | None = None,
) -> Prior | None:
    """Register a rendered silhouette onto an observed crop and soften it.

    Parameters
    ----------
    rendered : ndarray of shape (H, W), uint8
        The model body (any placement).
    observed : ndarray of shape (h, w), uint8
        The observed silhouette crop.
    box : ndarray of shape (4,)
        ``(x, y, w, h)`` of ``observed`` in the full frame.
    image_size : (int, int)
        Full frame ``(width, height)``.
    shift : (float, float)
        Extra translation in pixels (prediction of the motion to a later frame).
    extent : (float, float, float), optional
        The walker's full extent in this frame, ``(centre x, top, bottom)`` in
        full-frame pixels, from the whole window (:func:`body_extent`). When the
        observation is shorter than it by more than ``config.torn``, the render
        is placed by the extent (its height from top to bottom, its centroid at
        the centre) instead of being registered onto the torn observation.

    Returns
    -------
    Prior or None
        None when either silhouette is empty.

    Notes
    -----
    The map render -> observation is ``inv(T_obs) @ T_render`` with ``T`` the
    §5 registrations: equal heights along the principal axis, equal centroids,
    (with ``rotate``) equal axes.
    """
    config = config or PriorConfig()
    placed = _place(rendered, observed, box, image_size, config=config, shift=shift, extent=extent)
    if placed is None:
        return None
    binary, obs_box, (x0, y0), height, agreement = placed
    band = config.band * height
    soft = soften(binary.astype(np.uint8), band_px=band, inset_px=config.inset * height)
    if np.isfinite(config.reach_max) and binary.any():
        ratio = float(obs_box.sum()) / float(binary.sum())
        span = max(config.complete_ratio - 0.5, 1e-6)
        reach = config.reach_min + (config.reach_max - config.reach_min) * float(
            np.clip((config.complete_ratio - ratio) / span, 0.0, 1.0))
        soft *= _gate(obs_box, reach * height) / 255.0
    return Prior(frame_index, (x0, y0, binary.shape[1], binary.shape[0]), (int(image_size[0]), int(image_size[1])),
                 np.clip(soft + 0.5, 0, 255).astype(np.uint8), agreement)


def _place(rendered: np.ndarray, observed: np.ndarray, box: np.ndarray, image_size: tuple[int, int], *,
           config: PriorConfig, shift: tuple[float, float] = (0.0, 0.0),
           extent: tuple[float, float, float] | None = None) -> tuple | None:
    """The render placed as :func:`prior_from_render` places it, before softening.

    Returns ``(binary, observation, (x0, y0), height, agreement)``: the placed
    render and the observation in the prior's box (bool, uint8 0/1), the box's
    corner, the body's height in pixels and :attr:`Prior.agreement`; None when
    either silhouette is empty.
    """
    x, y, w, h = (float(v) for v in box)
    torn = extent is not None and h < (1.0 - config.torn) * (extent[2] - extent[1])
    if torn:
        # A torn observation: place the render by the window's extent of the walker.
        m, height = _extent_map(rendered, extent, (x, y))
        if m is None:
            return None
        wx0, wy0 = min(x, extent[0] - 0.4 * height), min(y, extent[1])  # the window: observation and extent
        wx1, wy1 = max(x + w, extent[0] + 0.4 * height), max(y + h, extent[2])
    else:
        _, tf = register([rendered, observed], rotate=config.rotate)
        if not tf.valid.all():
            return None
        a = np.vstack([tf.matrix[0], [0, 0, 1]])
        m = _inverse(tf.matrix[1]) @ a  # rendered pixels -> observed crop pixels
        height = float(tf.height[1])
        wx0, wy0, wx1, wy1 = x, y, x + w, y + h
    W, H = image_size
    pad = config.pad * height
    x0, y0 = int(max(0, np.floor(wx0 - pad + shift[0]))), int(max(0, np.floor(wy0 - pad + shift[1])))
    x1, y1 = int(min(W, np.ceil(wx1 + pad + shift[0]))), int(min(H, np.ceil(wy1 + pad + shift[1])))
    if x1 <= x0 or y1 <= y0:
        return None
    m = m.copy()
    m[:, 2] += (x - x0 + shift[0], y - y0 + shift[1])
    out_size = (x1 - x0, y1 - y0)
    binary = cv2.warpAffine(rendered, m, out_size, flags=cv2.INTER_LINEAR) > 127
    # The observation in the prior's box (moved along with a predicted shift).
    obs_box = np.zeros((y1 - y0, x1 - x0), np.uint8)
    ox, oy = int(round(x + shift[0])) - x0, int(round(y + shift[1])) - y0
    crop = (observed > 0).astype(np.uint8)[max(0, -oy) :, max(0, -ox) :]
    hh, ww = min(crop.shape[0], obs_box.shape[0] - max(oy, 0)), min(crop.shape[1], obs_box.shape[1] - max(ox, 0))
    if hh > 0 and ww > 0:
        obs_box[max(oy, 0) : max(oy, 0) + hh, max(ox, 0) : max(ox, 0) + ww] = crop[:hh, :ww]
    if config.search > 0 and not any(shift):
        dx, dy = _best_shift(obs_box, binary, int(round(config.search * height)))
        if dx or dy:
            m[:, 2] += (dx, dy)
            binary = cv2.warpAffine(rendered, m, out_size, flags=cv2.INTER_LINEAR) > 127
    # A torn observation is a fragment: agreement is how much of it the body covers (as in explained()).
    inter = float(np.count_nonzero(binary & (obs_box > 0)))
    union = np.count_nonzero(obs_box) if torn else np.count_nonzero(binary | (obs_box > 0))
    agreement = inter / max(1, union)
    return binary, obs_box, (x0, y0), height, agreement


def _holes(mask: np.ndarray) -> np.ndarray:
    """The background pixels of a 0/1 uint8 mask enclosed by its foreground (0/1 uint8)."""
    h, w = mask.shape
    background = cv2.copyMakeBorder((1 - mask).astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=1)
    cv2.floodFill(background, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 0)  # what remains 1 is enclosed
    return background[1:-1, 1:-1]


def _gate(observed: np.ndarray, reach_px: float) -> np.ndarray:
    """255 within ``reach_px`` of the observed foreground or its enclosed holes, fading outside."""
    filled = observed | _holes(observed)
    dist = cv2.distanceTransform(1 - filled, cv2.DIST_L2, 5)
    fade = 255.0 / (1.0 + np.exp(np.minimum(dist - reach_px - 1.0, 50.0)))  # 1-pixel fade beyond the reach
    return np.where(dist <= reach_px, np.float32(255.0), fade).astype(np.float32)


# ------------------------------------------------------------------------ trust


@dataclass(frozen=True)
class Trust:
    """Outcome of :func:`trust_test` for one camera's window.

    Attributes
    ----------
    camera : bool
        Whether the camera's estimate may give priors at all.
    frames : ndarray of shape (T,), bool
        Per frame of the window: its prior may be used (all False when
        ``camera`` is False).
    reason : str
        Why the camera is not trusted ("" when it is).
    """

    camera: bool
    frames: np.ndarray
    reason: str = ""


def trust_test(agreement: np.ndarray, *, spread_deg: float, flip: str, flip_margin: float,
               config: PriorConfig | None = None, window: np.ndarray | None = None,
               rival: float = float("nan")) -> Trust:
    """Whether priors from one camera's estimate can be trusted, per camera and per frame.

    A wrong estimate renders a body that does not look like the observed
    walker, so feedback from it would paint a wrong body into the silhouettes
    (issue 17): the camera is trusted only when its viewpoint is well defined
    (spread at most ``config.max_spread_deg``; ahead/behind settled by the
    motion cue, the other cameras' phase or the earlier windows, or by a
    margin of at least ``config.min_flip_margin``) and the
    rendered model agrees with the cleaned observations over the window
    (median :attr:`Prior.agreement` at least ``config.min_window_agreement``),
    better by ``config.min_view_margin`` than from the viewpoint turned by
    90 deg (``rival``); a frame of a trusted camera also needs its own
    agreement of at least ``config.min_agreement``.

    Parameters
    ----------
    agreement : ndarray of shape (T,)
        Per frame, the agreement of its prior (NaN: none or unknown, never trusted).
    spread_deg, flip, flip_margin
        The camera's :class:`estimator.viewpoint.Viewpoint` fields.
    window : ndarray, optional
        Agreements that stand for the window (default ``agreement``): for
        predicted frames, those of the window's last observed frames.
    rival : float
        Median agreement of the model rendered from the viewpoint turned by
        +-90 deg, the better one (NaN: not measured, not tested).
    """
    config = config or PriorConfig()
    agreement = np.asarray(agreement, float)
    median = _median(agreement if window is None else np.asarray(window, float))
    if not spread_deg <= config.max_spread_deg:
        reason = f"viewpoint spread {spread_deg:.0f} deg > {config.max_spread_deg:.0f}"
    elif flip not in ("motion", "cameras", "earlier") and not flip_margin >= config.min_flip_margin:
        reason = f"ahead/behind undecided (margin {flip_margin:.2f} < {config.min_flip_margin:.2f})"
    elif not median >= config.min_window_agreement:
        reason = f"model and silhouettes disagree (median IoU {median:.2f} < {config.min_window_agreement:.2f})"
    elif median - rival < config.min_view_margin:
        reason = f"a viewpoint turned by 90 deg fits as well (median IoU {rival:.2f} vs {median:.2f})"
    else:
        with np.errstate(invalid="ignore"):
            return Trust(True, agreement >= config.min_agreement)
    return Trust(False, np.zeros(agreement.shape, bool), reason)


def trusted_priors(priors: list[Prior], viewpoint, config: PriorConfig | None = None, *,
                   window: np.ndarray | None = None, rival: float = float("nan")) -> tuple[list[Prior], Trust]:
    """The priors of one camera that pass :func:`trust_test`, and the test's outcome.

    ``viewpoint``: the camera's :class:`estimator.viewpoint.Viewpoint`;
    ``window``, ``rival``: as in :func:`trust_test`. With ``window`` (predicted
    priors) every prior of a trusted camera is kept: a predicted frame has no
    observation of its own to agree with (the agent checks it against its
    evidence, :func:`weigh`).
    """
    agreement = np.array([p.agreement for p in priors], float)
    trust = trust_test(agreement, spread_deg=viewpoint.spread_deg, flip=viewpoint.flip,
                       flip_margin=viewpoint.flip_margin, config=config, window=window, rival=rival)
    keep = np.full(len(priors), trust.camera) if window is not None else trust.frames
    return [p for p, k in zip(priors, keep) if k], trust


def walker_tracks(estimate: WalkEstimate | SegmentedWalk, tracks: dict[str, CameraTrack]) -> dict[str, CameraTrack]:
    """The tracks as the estimate saw them: reduced to the walker by its clean-up.

    ``estimate.tracks`` (:func:`estimator.pipeline.estimate_walk`), per segment
    for a :class:`SegmentedWalk` (each segment's own frames); ``tracks`` as
    given where the estimate kept none (or of other frames). Priors are
    registered onto, and refined silhouettes restricted to, these tracks,
    never onto clutter.
    """
    if isinstance(estimate, WalkEstimate):
        cleaned = estimate.tracks or {}
        return {name: cleaned[name] if name in cleaned and len(cleaned[name].silhouettes) == len(t.silhouettes)
                else t for name, t in tracks.items()}
    out = {}
    for name, t in tracks.items():
        sils, boxes = list(t.silhouettes), t.boxes.copy()
        for seg in estimate.segments:
            cleaned = None if seg.estimate is None or not seg.estimate.tracks else seg.estimate.tracks.get(name)
            if cleaned is None:
                continue
            a, b = seg.first, seg.last + 1
            sils[a:b] = cleaned.silhouettes[a - seg.start : b - seg.start]
            boxes[a:b] = cleaned.boxes[a - seg.start : b - seg.start]
        out[name] = CameraTrack(sils, boxes, full_frame=t.full_frame, image_size=t.image_size)
    return out


def turn_viewpoints(estimate: WalkEstimate, angle_deg: float = 90.0) -> WalkEstimate:
    """The estimate with every camera's azimuth turned by ``angle_deg`` (a deliberately wrong estimate)."""
    cams = {name: dataclasses.replace(c, viewpoint=dataclasses.replace(
        c.viewpoint, azimuth_deg=(c.viewpoint.azimuth_deg + angle_deg) % 360.0))
        for name, c in estimate.cameras.items()}
    return dataclasses.replace(estimate, cameras=cams)


# ------------------------------------------------------------------------ windows


def priors_for_window(
    estimate: WalkEstimate | SegmentedWalk,
    tracks: dict[str, CameraTrack],
    image_sizes: dict[str, tuple[int, int]] | tuple[int, int],
    *,
    renderer,
    config: PriorConfig | None = None,
    gait: GaitModel | None = None,
    first_index: int = 0,
) -> dict[str, list[Prior]]:
    """Priors for every frame of every camera that has a silhouette and a viewpoint, but for a
    camera whose walker's lowest part is hidden (by something in front or the image's bottom
    edge: :mod:`estimator.occlusion`): a whole body drawn there would ask the segmenter for
    what the wall hides.

    Parameters
    ----------
    estimate : WalkEstimate or SegmentedWalk
        From :func:`estimator.pipeline.estimate_walk` on ``tracks``, or from
        :func:`estimator.windows.segment_walk` (each segment's frames get
        priors from that segment's estimate).
    tracks : dict of str to CameraTrack
        The window's silhouettes; their boxes must be full-frame positions.
    image_sizes : (int, int) or dict of str to (int, int)
        Full frame ``(width, height)``, one for all cameras or per camera.
    renderer : estimator.render.Renderer
        Draws the model body (``config.body`` is installed in it).
    first_index : int
        Frame index of the window's first frame (``Prior.frame_index``).

    Returns
    -------
    dict of str to list of Prior
        Per camera, in frame order; frames without data are skipped.
    """
    config = config or PriorConfig()
    gait = gait or load_gait()
    if isinstance(estimate, SegmentedWalk):
        merged: dict[str, list[Prior]] = {name: [] for name in tracks}
        for seg in estimate.segments:
            if seg.estimate is None:
                continue
            got = priors_for_window(seg.estimate, window_tracks(tracks, seg.start, seg.stop), image_sizes,
                                    renderer=renderer, config=config, gait=gait, first_index=first_index + seg.start)
            for name, ps in got.items():
                merged[name] += [p for p in ps if seg.first <= p.frame_index - first_index <= seg.last]
        return merged
    if renderer.shape != config.body:
        renderer.set_shape(config.body)
    out: dict[str, list[Prior]] = {}
    for name, track in walker_tracks(estimate, tracks).items():
        size = image_sizes[name] if isinstance(image_sizes, dict) else image_sizes
        cam = estimate.cameras.get(name)
        out[name] = []
        if cam is None or not np.isfinite(cam.viewpoint.azimuth_deg):
            continue
        if cam.cleanup is not None and cam.cleanup.hidden_by:  # not the wall: estimator.occlusion
            continue
        rows = _known_frames(track)
        out[name] = _window_priors(estimate, cam, track, rows, size, renderer=renderer, config=config, gait=gait,
                                   first_index=first_index)
        if config.trust and rows:
            sample = [rows[i] for i in evenly_spaced(len(rows), config.trust_window)]
            rival = _rival_agreement(estimate, cam, track, sample, size, renderer=renderer, config=config, gait=gait)
            out[name] = trusted_priors(out[name], cam.viewpoint, config, rival=rival)[0]
        if config.same_phase:
            out[name] = [_with_same_phase(p, p.frame_index - first_index, np.asarray(estimate.phase, float), track,
                                          config) for p in out[name]]
    return out


def _with_same_phase(prior: Prior, t: int, phase: np.ndarray, track: CameraTrack, config: PriorConfig) -> Prior:
    """``prior`` raised to 255 where the walker's silhouettes at the same phase agree (``config.same_phase``)."""
    d = np.abs((phase - phase[t] + 0.5) % 1.0 - 0.5)
    same = [s for s in _known_frames(track) if s != t and d[s] <= config.same_phase_cycle + 1e-9]
    if len(same) < config.same_phase_frames or not np.isfinite(track.boxes[t]).all():
        return prior
    x0, y0, w, h = prior.box
    bt = track.boxes[t]
    cover = np.zeros((h, w), np.float32)
    for s in same:
        bs = track.boxes[s]
        k = bt[3] / bs[3]
        # silhouette s's pixel (u, v) -> frame t: scaled about its box's top centre onto t's box's top centre
        m = np.array([[k, 0.0, bt[0] + bt[2] / 2 - k * bs[2] / 2 - x0], [0.0, k, bt[1] - y0]], np.float32)
        cover += cv2.warpAffine(track.silhouettes[s], m, (w, h), flags=cv2.INTER_LINEAR) > 127
    raise_ = (cover >= config.same_phase_share * len(same)) & (prior.mask >= config.same_phase_level)
    if not raise_.any():
        return prior
    return dataclasses.replace(prior, mask=np.where(raise_, np.uint8(255), prior.mask))


def _known_frames(track: CameraTrack) -> list[int]:
    """Frames of a track with a silhouette and a box."""
    return [t for t, s in enumerate(track.silhouettes) if s is not None and np.isfinite(track.boxes[t, 0])]


def _rival_agreement(estimate: WalkEstimate, cam, track: CameraTrack, rows: list[int], size: tuple[int, int], *,
                     renderer, config: PriorConfig, gait: GaitModel) -> float:
    """Best median agreement on frames ``rows`` of the model seen from the viewpoint turned by +-90 deg."""
    return max(_median(_window_agreement(estimate, cam, track, rows, size, renderer=renderer, config=config,
                                         gait=gait, turn=turn)) for turn in (-90.0, 90.0))


def _median(values: np.ndarray) -> float:
    """Median of the finite values; NaN when there are none."""
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else float("nan")


def _window_renders(estimate: WalkEstimate, cam, track: CameraTrack, rows: list[int], *, renderer,
                    config: PriorConfig, gait: GaitModel, turn: float = 0.0
                    ) -> list[tuple[int, np.ndarray, tuple | None]]:
    """``(frame, render, extent)`` for the window's frames ``rows`` of one camera, the model seen
    from its estimated viewpoint (``turn``: azimuth turned by this, the trust test's rivals)."""
    if not rows:
        return []
    renders = render_body(estimate.phase[rows], cam.viewpoint.azimuth_deg + turn, cam.viewpoint.elevation_deg,
                          renderer=renderer, body=config.body, gait=gait, pixels_per_metre=config.pixels_per_metre)
    extent = _window_extent(track, config)
    return [(t, r, None if extent is None else tuple(extent[t])) for t, r in zip(rows, renders)]


def _window_priors(estimate: WalkEstimate, cam, track: CameraTrack, rows: list[int], size: tuple[int, int], *,
                   renderer, config: PriorConfig, gait: GaitModel, first_index: int) -> list[Prior]:
    """Priors (untested) of the window's frames ``rows`` of one camera, each registered onto its silhouette."""
    out = [prior_from_render(r, track.silhouettes[t], track.boxes[t], size, frame_index=first_index + t,
                             config=config, extent=e)
           for t, r, e in _window_renders(estimate, cam, track, rows, renderer=renderer, config=config, gait=gait)]
    return [p for p in out if p is not None]


def _window_agreement(estimate: WalkEstimate, cam, track: CameraTrack, rows: list[int], size: tuple[int, int], *,
                      renderer, config: PriorConfig, gait: GaitModel, turn: float = 0.0) -> np.ndarray:
    """:attr:`Prior.agreement` of the window's frames ``rows`` (NaN where none), without making the priors."""
    placed = [_place(r, track.silhouettes[t], track.boxes[t], size, config=config, extent=e)
              for t, r, e in _window_renders(estimate, cam, track, rows, renderer=renderer, config=config, gait=gait,
                                             turn=turn)]
    return np.array([np.nan if p is None else p[-1] for p in placed], float)


def body_extent(track: CameraTrack, *, quantile: float = 0.1, max_gap: int = 3,
                centroids: np.ndarray | None = None) -> np.ndarray:
    """The walker's full extent per frame, ``(centre x, top, bottom)``, robust to torn silhouettes.

    A torn silhouette (low contrast, an occluder) is a fragment of the body: its
    top lies at or below the head, its bottom at or above the feet, its
    centroid somewhere inside. Over a run of frames (known frames at most
    ``max_gap`` apart) the walker moves steadily, so each is a straight line in
    time: the centre is the median regression line of the centroids' x, the
    top the lower envelope of the observed tops and the bottom the upper
    envelope of the bottoms (:func:`_envelope_line`: a few frames that see the
    head or the feet are enough). Complete silhouettes give their own extent
    back (up to the head's bob).

    ``centroids``: the track's :func:`silhouette_centroids`, when the caller has them.

    Returns
    -------
    ndarray of shape (T, 3)
        NaN for frames outside any run.
    """
    if not 0 < quantile < 0.5:
        raise ValueError(f"quantile must be in (0, 0.5), got {quantile}")
    boxes = np.asarray(track.boxes, float)
    centroids = silhouette_centroids(track) if centroids is None else centroids
    known = np.flatnonzero(np.isfinite(boxes).all(axis=1) & np.isfinite(centroids).all(axis=1))
    out = np.full((len(boxes), 3), np.nan)
    for run in np.split(known, np.flatnonzero(np.diff(known) > max_gap) + 1) if known.size else ():
        t, span = run.astype(float), np.arange(run[0], run[-1] + 1)
        ax, bx = _median_line(t, centroids[run, 0])
        drift = _median_line(t, centroids[run, 1])[1]
        out[span, 0] = ax + bx * span
        at, bt = _envelope_line(t, boxes[run, 1], quantile, drift)
        ab, bb = _envelope_line(t, -(boxes[run, 1] + boxes[run, 3]), quantile, -drift)
        out[span, 1] = at + bt * span
        out[span, 2] = -(ab + bb * span)
    return out


def _window_extent(track: CameraTrack, config: PriorConfig,
                   centroids: np.ndarray | None = None) -> np.ndarray | None:
    """:func:`body_extent` with the config's quantile, or None when torn placement is off."""
    if not np.isfinite(config.torn):
        return None
    return body_extent(track, quantile=config.envelope, centroids=centroids)


def _envelope_line(t: np.ndarray, y: np.ndarray, q: float, slope: float, *, near: float = 0.3,
                   iterations: int = 2) -> tuple[float, float]:
    """Lower envelope ``a + b t`` of noisy points that lie on or above a line.

    From a first slope (the body's drift), the ``near`` fraction of points
    closest to the envelope — the frames that do see the head (or the feet) —
    give the slope by median regression, when they span a third of the run;
    the offset is the ``q`` quantile of the points about it.
    """
    b = slope
    for _ in range(iterations):
        r = y - b * t
        close = r <= np.quantile(r, near)
        if close.sum() >= 3 and np.ptp(t[close]) >= np.ptp(t) / 3:
            b = _median_line(t[close], y[close])[1]
    return float(np.quantile(y - b * t, q)), float(b)


def _median_line(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Median (least absolute deviations) regression line ``y ~ a + b t``, as a linear program."""
    n = t.size
    if n < 3 or np.ptp(t) == 0:
        return float(np.median(y)), 0.0
    # min 1'u + 1'v  s.t.  a + b t + u - v = y,  u, v >= 0
    c = np.concatenate([[0.0, 0.0], np.ones(2 * n)])
    a_eq = np.hstack([np.ones((n, 1)), t[:, None], np.eye(n), -np.eye(n)])
    res = scipy.optimize.linprog(c, A_eq=a_eq, b_eq=y, bounds=[(None, None)] * 2 + [(0, None)] * (2 * n),
                                 method="highs")
    if not res.success:
        return float(np.median(y)), 0.0
    return float(res.x[0]), float(res.x[1])


def predict_phases(estimate: WalkEstimate, n_ahead: int, *, n_states: int | None = None) -> np.ndarray:
    """Phases of the ``n_ahead`` frames after the window, continuing the decoded path.

    The speed is the decoded HMM path's mean advance per frame (states unwrapped
    on the cycle; the cyclic feed-forward HMM only moves forward).

    Returns
    -------
    ndarray of shape (n_ahead,), phases in [0, 1)
    """
    if n_ahead < 0:
        raise ValueError(f"n_ahead must be >= 0, got {n_ahead}")
    phase = np.asarray(estimate.phase, float)
    if phase.size == 0:
        raise ValueError("the estimate has no frames")
    speed = phase_speed(phase)
    return (phase[-1] + speed * np.arange(1, n_ahead + 1)) % 1.0


def phase_speed(phase: np.ndarray) -> float:
    """Mean forward advance of a phase path per frame (cycles per frame, >= 0)."""
    phase = np.asarray(phase, float)
    if phase.size < 2:
        return 0.0
    d = np.diff(phase) % 1.0  # forward only
    d = np.where(d > 0.5, d - 1.0, d)  # a backward step (should not happen) counts as such
    return float(max(0.0, d.mean()))


def extrapolate(values: np.ndarray, n_ahead: int, *, history: int = 8) -> np.ndarray:
    """The next ``n_ahead`` rows of a per-frame series, by a straight-line fit (per column)
    to its last ``history`` known rows (NaN = unknown); NaN when none is known."""
    values = np.asarray(values, float)
    known = np.flatnonzero(np.isfinite(values).all(axis=1))[-history:]
    T, d = values.shape
    if known.size == 0:
        return np.full((n_ahead, d), np.nan)
    if known.size == 1:
        return np.repeat(values[known], n_ahead, axis=0)
    future = np.arange(T, T + n_ahead, dtype=float)
    coef = np.polynomial.polynomial.polyfit(known.astype(float), values[known], 1)  # (2, d)
    return coef[0] + future[:, None] * coef[1]


def silhouette_centroids(track: CameraTrack) -> np.ndarray:
    """Full-frame centroid ``(x, y)`` of each frame's silhouette, NaN where there is none.

    The walker's motion in the image is followed by its centroid rather than its
    box, whose centre swings with the legs and arms.
    """
    out = np.full((len(track.silhouettes), 2), np.nan)
    for t, sil in enumerate(track.silhouettes):
        box = track.boxes[t]
        if sil is None or not np.isfinite(box).all():
            continue
        m = cv2.moments((sil > 0).astype(np.uint8), binaryImage=True)
        if m["m00"] > 0:
            out[t] = (box[0] + (m["m10"] / m["m00"] + 0.5) * box[2] / sil.shape[1] - 0.5,
                      box[1] + (m["m01"] / m["m00"] + 0.5) * box[3] / sil.shape[0] - 0.5)
    return out


def predict_priors(
    estimate: WalkEstimate,
    tracks: dict[str, CameraTrack],
    image_sizes: dict[str, tuple[int, int]] | tuple[int, int],
    n_ahead: int,
    *,
    renderer,
    config: PriorConfig | None = None,
    gait: GaitModel | None = None,
    first_index: int = 0,
    skip: int = 0,
) -> dict[str, list[Prior]]:
    """Priors for ``n_ahead`` frames after the window, from ``skip`` frames past its end
    (live feedback, §7.1: the frames captured while the priors are made need none).

    The phase continues the HMM path (:func:`predict_phases`); the body is
    registered onto the camera's last silhouette (placed by the window's
    :func:`body_extent` if that silhouette is torn), then moved with the motion
    of the silhouette's centroid extrapolated from the window (:func:`extrapolate`).
    The silhouettes are the estimate's cleaned ones (:func:`walker_tracks`); with
    ``config.trust`` a camera whose estimate fails :func:`trust_test` on the
    window's last ``config.trust_window`` frames gets no priors.

    The evidence gate reaches its widest (``reach_max``) whatever the last
    silhouette's completeness: that silhouette is the only evidence and its limbs
    are elsewhere by the predicted frame, so a tight gate cut the predicted legs
    and arms. The agent checks each prior against its own frame before use
    (``capture.segment``).
    """
    if skip < 0:
        raise ValueError(f"skip must be >= 0, got {skip}")
    config = config or PriorConfig()
    gait = gait or load_gait()
    if renderer.shape != config.body:
        renderer.set_shape(config.body)
    phases = predict_phases(estimate, skip + n_ahead)[skip:]
    T = len(estimate.phase)
    ahead = dataclasses.replace(config, reach_min=config.reach_max)
    out: dict[str, list[Prior]] = {}
    for name, track in walker_tracks(estimate, tracks).items():
        size = image_sizes[name] if isinstance(image_sizes, dict) else image_sizes
        cam = estimate.cameras.get(name)
        out[name] = []
        known = _known_frames(track)
        if cam is None or not np.isfinite(cam.viewpoint.azimuth_deg) or not known or n_ahead == 0:
            continue
        if config.trust:  # the window's last frames stand for the predicted ones
            recent = known[-config.trust_window:]
            window = _window_agreement(estimate, cam, track, recent, size, renderer=renderer, config=config, gait=gait)
            rival = _rival_agreement(estimate, cam, track, recent, size, renderer=renderer, config=config, gait=gait)
            if not trusted_priors([], cam.viewpoint, config, window=window, rival=rival)[1].camera:
                continue
        last = known[-1]
        centroids = silhouette_centroids(track)
        # Predicted centroid minus the last observed one.
        shifts = extrapolate(centroids, skip + n_ahead)[skip:] - centroids[last]
        renders = render_body(phases, cam.viewpoint.azimuth_deg, cam.viewpoint.elevation_deg,
                              renderer=renderer, body=config.body, gait=gait,
                              pixels_per_metre=config.pixels_per_metre)
        lb = track.boxes[last]
        extent = _window_extent(track, config, centroids)
        extent = None if extent is None else tuple(extent[last])
        for k, r in enumerate(renders):
            p = prior_from_render(r, track.silhouettes[last], lb, size, frame_index=first_index + T + skip + k,
                                  config=ahead, shift=(float(shifts[k, 0]), float(shifts[k, 1])), extent=extent)
            if p is not None:
                out[name].append(p)
    return out


def rotate_prior(prior: Prior, angle_deg: float = 90.0) -> Prior:
    """The prior turned by ``angle_deg`` about its weighted centroid (a deliberately wrong prior)."""
    full = prior.full_mask()
    m = cv2.moments(full)
    if m["m00"] == 0:
        return prior
    c = (m["m10"] / m["m00"], m["m01"] / m["m00"])
    rot = cv2.getRotationMatrix2D(c, angle_deg, 1.0)
    turned = cv2.warpAffine(full, rot, prior.image_size, flags=cv2.INTER_LINEAR)
    x, y, w, h = cv2.boundingRect((turned > 0).astype(np.uint8))
    if w == 0:
        return prior
    return Prior(prior.frame_index, (x, y, w, h), prior.image_size, turned[y : y + h, x : x + w].copy())


# ------------------------------------------------------------------------ fusion


def explained(prior: Prior, silhouette: np.ndarray, *, level: int = 64) -> float:
    """Fraction of an observed silhouette's foreground that the prior covers (value >= ``level``).

    A prior that does not explain the evidence — wrong viewpoint, wrong
    placement, a stale prediction — covers little of it, while a right prior
    covers even a torn silhouette's fragments. NaN for an empty silhouette.

    Parameters
    ----------
    silhouette : ndarray of shape (H, W)
        Full-frame observation (e.g. the segmenter's output without prior).
    """
    if silhouette.shape != prior.image_size[::-1]:
        raise ValueError(f"silhouette must have shape {prior.image_size[::-1]}, got {silhouette.shape}")
    fg = silhouette > 0
    n = int(np.count_nonzero(fg))
    if n == 0:
        return float("nan")
    return float(np.count_nonzero(fg & (prior.full_mask() >= level))) / n


def weigh(prior: Prior, coverage: float, *, low: float = 0.5, high: float = 0.8) -> Prior | None:
    """The prior scaled by how well it explains the evidence; None below ``low``.

    ``coverage`` from :func:`explained`: at or above ``high`` the prior is kept
    as is, between ``low`` and ``high`` its values shrink linearly (fewer pixels
    reach a segmenter's trust level), below ``low`` it is dropped. NaN (no
    observation to check against) keeps it.
    """
    f = trust_factor(coverage, low=low, high=high)
    if f is None:
        return None
    if f == 1.0:
        return prior
    return dataclasses.replace(prior, mask=(prior.mask * f + 0.5).astype(np.uint8))


def trust_factor(coverage: float, *, low: float = 0.5, high: float = 0.8) -> float | None:
    """How far to trust a prior that covers ``coverage`` of the evidence (:func:`weigh`).

    1 at or above ``high`` (or NaN: nothing to check against), None (do not use)
    below ``low``, linear in between.
    """
    if not np.isfinite(coverage) or coverage >= high:
        return 1.0
    if coverage < low:
        return None
    return (coverage - low) / (high - low)


def trim_silhouette(silhouette: np.ndarray, prior: np.ndarray, *, reach: float = 0.1, level: int = 64) -> np.ndarray:
    """Drop foreground farther than ``reach`` x the prior's height from the prior's support.

    For offline refinement after a segmenter that only *adds* foreground under
    a prior: background the model cannot explain (lighting drift, shadows,
    a second mover) is cut away; within ``reach`` of the model body the
    observation is kept as it is. An empty prior leaves the silhouette alone.

    Parameters
    ----------
    silhouette, prior : ndarray of shape (H, W), uint8
        Full frame; ``prior`` soft 0..255 (:meth:`Prior.full_mask`).
    """
    if silhouette.shape != prior.shape:
        raise ValueError(f"silhouette and prior must have the same shape, got {silhouette.shape} and {prior.shape}")
    support = (prior >= level).astype(np.uint8)
    rows = np.flatnonzero(support.any(axis=1))
    if rows.size == 0:
        return np.where(silhouette > 0, np.uint8(255), np.uint8(0))
    dist = cv2.distanceTransform(1 - support, cv2.DIST_L2, 3)
    keep = dist <= reach * float(rows[-1] - rows[0] + 1)
    return np.where((silhouette > 0) & keep, np.uint8(255), np.uint8(0))


def refine_silhouette(
    silhouette: np.ndarray,
    prior: np.ndarray,
    *,
    fill_level: int = 200,
    keep_level: int = 64,
    reach: float = 0.04,
    walker: np.ndarray | None = None,
    limb: float = 0.0,
    limb_level: int = 160,
) -> np.ndarray:
    """Fuse a binary silhouette with a soft prior when no image is left (offline, §7.1).

    With ``walker`` (the silhouette reduced to the walker, e.g. by the
    estimator's clean-up) the result is restricted to it: the walker, the
    observed pixels the prior is sure of, and the filled parts; nothing else
    of the silhouette (clutter) is kept, and nothing far from the walker added.

    Parameters
    ----------
    silhouette : ndarray of shape (H, W), uint8
        Observed silhouette (non-zero = foreground), full frame.
    prior : ndarray of shape (H, W), uint8
        Soft prior on the same frame (:meth:`Prior.full_mask`).
    fill_level : int
        Prior value from which a missing pixel is filled if it lies in a hole
        enclosed by the observation or ...
    reach : float
        ... if it lies within ``reach * height`` of observed foreground (the
        model explains a hole or a thin gap, it does not invent a limb far from
        any evidence).
    keep_level : int
        Connected components of the observation touching no pixel with a prior
        of at least this value are dropped (blobs far from the body). The
        largest component is always kept. Not used with ``walker``.
    walker : ndarray of shape (H, W), optional
        The walker's part of ``silhouette``.
    limb : float
        Also filled: the parts of the prior (at least ``limb_level``) missing
        from the observation that are thicker than ``2 * limb * height`` and
        touch it — a cut forearm or shin, a hole — but not the thin slivers
        where the model body is wider than the walker; 0 turns this off.

    Returns
    -------
    ndarray of shape (H, W), uint8 0/255
    """
    silhouette = np.asarray(silhouette)
    prior = np.asarray(prior)
    if silhouette.shape != prior.shape:
        raise ValueError(f"silhouette and prior must have the same shape, got {silhouette.shape} and {prior.shape}")
    fg = (silhouette > 0).astype(np.uint8)
    sure = prior >= fill_level
    if walker is not None:
        if walker.shape != silhouette.shape:
            raise ValueError(f"walker must have the silhouette's shape {silhouette.shape}, got {walker.shape}")
        fg = ((walker > 0) | (fg.astype(bool) & sure)).astype(np.uint8)
    if not fg.any():
        return fg * 255
    if walker is None:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
        keep = np.zeros(n, bool)
        keep[np.unique(labels[(prior >= keep_level) & (labels > 0)])] = True
        keep[1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))] = True
        keep[0] = False
        fg = keep[labels].astype(np.uint8)
    rows = np.flatnonzero(fg.any(axis=1))
    height = float(rows[-1] - rows[0] + 1)
    dist = cv2.distanceTransform(1 - fg, cv2.DIST_L2, 3)
    fill = sure & ((dist <= reach * height) | (_holes(fg) > 0))
    if limb > 0:
        r = max(1, int(round(limb * height)))
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        missing = ((prior >= limb_level) & (fg == 0)).astype(np.uint8)
        n, labels = cv2.connectedComponents(cv2.morphologyEx(missing, cv2.MORPH_OPEN, disc), connectivity=8)
        touching = np.zeros(n, bool)
        touching[np.unique(labels[(dist <= r + 1.5) & (labels > 0)])] = True
        # The thick parts, and the seam between them and the walker the opening took.
        fill |= (cv2.dilate(touching[labels].astype(np.uint8), disc) & missing) > 0
    return (fg.astype(bool) | fill).astype(np.uint8) * 255
