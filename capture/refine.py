"""Offline silhouette refinement with model feedback (Izo–Grimson §7.1).

Two passes over each camera's frames: plain background subtraction, the walk
estimated from those silhouettes, priors rendered from the estimate
(:mod:`estimator.prior`), then background subtraction again from the start
with each frame's prior installed through :meth:`Segmenter.set_prior` — the
same fusion a live agent applies to the service's feedback messages.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from estimator.appearance import AppearanceModel
from estimator.pipeline import CameraTrack, WalkEstimate, crop_to_box, estimate_walk
from estimator.prior import Prior, PriorConfig, explained, priors_for_window, trim_silhouette, weigh

from .segment import Segmentation, Segmenter, SegmentSettings
from .wire import Box, FeedbackMessage

__all__ = ["RefineResult", "check_priors", "trim", "feedback_from_prior", "refine_cameras", "segment",
           "track_from_segmentations"]


def feedback_from_prior(prior: Prior, *, rig: str = "offline", camera: str = "c0") -> FeedbackMessage:
    """The wire message carrying a prior to a segmenter."""
    return FeedbackMessage(rig=rig, camera=camera, frame_index=prior.frame_index, box=Box(*prior.box),
                           image_size=prior.image_size, mask=prior.mask)


def segment(frames: Iterable[np.ndarray], settings: SegmentSettings,
            priors: Iterable[Prior] = ()) -> list[Segmentation | None]:
    """Segment BGR frames (index = position) with a fresh segmenter and the given priors.

    Each prior is installed just before its frame, as a live agent would have
    received it.
    """
    by_frame: dict[int, Prior] = {p.frame_index: p for p in priors}
    seg = Segmenter(settings)
    out: list[Segmentation | None] = []
    for k, image in enumerate(frames):
        p = by_frame.get(k)
        if p is not None:
            seg.set_prior(feedback_from_prior(p))
        out.append(seg.apply(image, k))
    return out


def track_from_segmentations(segs: list[Segmentation | None]) -> CameraTrack:
    """A camera track (tight crops, full-frame boxes) from segmenter output."""
    sils, boxes = [], []
    for s in segs:
        cropped = None if s is None or s.box.empty else crop_to_box(s.mask)
        if cropped is None:
            sils.append(None)
            boxes.append([np.nan] * 4)
        else:
            crop, b = cropped
            sils.append(crop)
            boxes.append([s.box.x + b[0], s.box.y + b[1], b[2], b[3]])
    return CameraTrack(sils, np.array(boxes, float).reshape(-1, 4), full_frame=True)


def check_priors(priors: list[Prior], raw: list[Segmentation | None]) -> list[Prior]:
    """Keep, weaken or drop each prior by how much of the raw silhouette it explains.

    The consistency check of :func:`estimator.prior.explained` /
    :func:`estimator.prior.weigh` against the frame's segmentation without
    prior: a prior that contradicts the evidence is replaced by an empty one
    (installing nothing would let the segmenter fall back to an older frame's
    prior, displaced by the walker's motion).
    """
    out = []
    for p in priors:
        s = raw[p.frame_index] if p.frame_index < len(raw) else None
        if s is None or s.box.empty:
            out.append(p)
            continue
        w = weigh(p, explained(p, s.full_mask()))
        out.append(w if w is not None else Prior(p.frame_index, p.box, p.image_size, np.zeros_like(p.mask)))
    return out


def trim(segs: list[Segmentation | None], priors: list[Prior], *, reach: float = 0.1) -> list[Segmentation | None]:
    """Cut each segmentation to within ``reach`` body heights of its (checked) prior.

    See :func:`estimator.prior.trim_silhouette`; frames without a prior, or
    with an empty (dropped) one, are left as they are.
    """
    by_frame = {p.frame_index: p for p in priors}
    out: list[Segmentation | None] = []
    for k, s in enumerate(segs):
        p = by_frame.get(k)
        if s is None or s.box.empty or p is None or not p.mask.any():
            out.append(s)
            continue
        full = trim_silhouette(s.full_mask(), p.full_mask(), reach=reach)
        cropped = crop_to_box(full)
        if cropped is None:
            out.append(Segmentation(np.zeros((0, 0), np.uint8), Box(0, 0, 0, 0), s.image_size, 0, True))
            continue
        crop, b = cropped
        out.append(Segmentation(crop, Box(*(int(v) for v in b)), s.image_size, int(np.count_nonzero(crop)), True))
    return out


@dataclass
class RefineResult:
    """Both passes of :func:`refine_cameras`."""

    raw: dict[str, list[Segmentation | None]]
    refined: dict[str, list[Segmentation | None]]
    estimate: WalkEstimate
    priors: dict[str, list[Prior]]
    image_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)


def refine_cameras(
    frames: dict[str, Callable[[], Iterable[np.ndarray]]],
    model: AppearanceModel,
    *,
    renderer,
    settings: SegmentSettings = SegmentSettings(),
    config: PriorConfig | None = None,
    prior_transform: Callable[[Prior], Prior] | None = None,
    trim_reach: float | None = 0.1,
) -> RefineResult:
    """Segment, estimate, render priors, segment again with them.

    Parameters
    ----------
    frames : dict of str to callable
        Per camera, a function returning a fresh iterable of BGR frames (called
        twice: one per pass; a video is simply reopened).
    model : AppearanceModel
    renderer : estimator.render.Renderer
    prior_transform : callable, optional
        Applied to each prior before the second pass (the evaluation's
        deliberately wrong prior); then every prior is checked against the
        first pass (:func:`check_priors`).
    trim_reach : float or None
        After the second pass, cut foreground farther than this many body
        heights from the prior (:func:`trim`); None = keep the segmenter's output.

    Raises
    ------
    ValueError
        No silhouette in any camera (nothing to estimate from).
    """
    raw, sizes = {}, {}
    for name, make in frames.items():
        raw[name] = segment(make(), settings)
        first = next((s for s in raw[name] if s is not None), None)
        if first is None:
            raise ValueError(f"camera {name}: no frames after the warm-up of {settings.warmup_frames}")
        sizes[name] = first.image_size
    tracks = {name: track_from_segmentations(s) for name, s in raw.items()}
    estimate = estimate_walk(tracks, model)
    priors = priors_for_window(estimate, tracks, sizes, renderer=renderer, config=config)
    if prior_transform is not None:
        priors = {name: [prior_transform(p) for p in ps] for name, ps in priors.items()}
    refined = {}
    for name, make in frames.items():
        checked = check_priors(priors[name], raw[name])
        segs = segment(make(), settings, checked)
        refined[name] = trim(segs, checked, reach=trim_reach) if trim_reach is not None else segs
    return RefineResult(raw, refined, estimate, priors, sizes)
