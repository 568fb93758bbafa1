"""Offline silhouette refinement with model feedback (Izo–Grimson §7.1).

Two passes over each camera's frames: plain background subtraction, the walk
estimated from those silhouettes, priors rendered from the estimate
(:mod:`estimator.prior`), then background subtraction again from the start
with each frame's prior installed through :meth:`Segmenter.set_prior` — the
same fusion a live agent applies to the service's feedback messages.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from estimator.appearance import AppearanceModel
from estimator.pipeline import CameraTrack, WalkEstimate, crop_to_box, estimate_walk, tracks_from_sequence
from estimator.prior import (
    FEEDBACK,
    Prior,
    PriorConfig,
    explained,
    priors_for_window,
    refine_silhouette,
    trim_silhouette,
    walker_tracks,
    weigh,
)
from estimator.sequence import Sequence
from estimator.windows import SegmentedWalk

from .choose import guide, held_path, held_walker, walker_boxes
from .merges import MergeTest, unmerge
from .segment import Segmentation, Segmenter, SegmentSettings, sample_indices
from .sources import PLATE_SUFFIXES, VideoFileSource, read_plate
from .wire import Box, FeedbackMessage

__all__ = ["RefineResult", "RefinedSequence", "check_priors", "feedback_from_prior", "refine_cameras",
           "refine_sequence", "refine_videos", "second_pass", "segment", "track_from_segmentations", "trim",
           "segment_clip", "against_plate", "background_note", "plate_for", "plate_path", "plates_for",
           "video_frames"]


def feedback_from_prior(prior: Prior, *, rig: str = "offline", camera: str = "c0") -> FeedbackMessage:
    """The wire message carrying a prior to a segmenter."""
    return FeedbackMessage(rig=rig, camera=camera, frame_index=prior.frame_index, box=Box(*prior.box),
                           image_size=prior.image_size, mask=prior.mask)


def segment(frames: Iterable[np.ndarray], settings: SegmentSettings,
            priors: Iterable[Prior] = (), fps: float | None = None,
            guide: list[tuple[int, int, int, int] | None] | None = None,
            plate: np.ndarray | None = None) -> list[Segmentation | None]:
    """Segment BGR frames (index = position) with a fresh segmenter and the given priors.

    With ``settings.background = "bootstrap"`` (the default) the background is
    bootstrapped from frames sampled over the first ones (``fps`` places
    ``bootstrap_seconds``; 15 when unknown) and every frame is segmented, as
    the agent does a file; ``plate``, an image of the empty scene, is the
    background then (:meth:`capture.segment.Segmenter.bootstrap`). Each prior
    is installed just before its frame, as a live agent would have received
    it. ``guide`` (a box or None per frame) is the walker chosen over the
    whole clip (:func:`segment_clip`).
    """
    by_frame: dict[int, Prior] = {p.frame_index: p for p in priors}
    seg = Segmenter(settings, plate=plate)
    if settings.background == "bootstrap":
        # The agent's default for files: the background from frames sampled over the start
        # (looked ahead: at most 3 per sample are held), then every frame from 0.
        frames = iter(frames)
        head = list(itertools.islice(frames, 3 * settings.bootstrap_samples))
        if head:
            seg.bootstrap([head[i] for i in sample_indices(len(head), fps, settings)])
        frames = itertools.chain(head, frames)
    out: list[Segmentation | None] = []
    for k, image in enumerate(frames):
        p = by_frame.get(k)
        if p is not None:
            seg.set_prior(feedback_from_prior(p))
        out.append(seg.apply(image, k, None if guide is None or k >= len(guide) else guide[k]))
    return out


def segment_clip(frames: Callable[[], Iterable[np.ndarray]], settings: SegmentSettings,
                 fps: float | None = None, plate: np.ndarray | None = None
                 ) -> tuple[list[Segmentation | None], str | None]:
    """:func:`segment` a clip (``frames()`` yields its BGR frames, and can be called again) with its
    walker chosen over the whole clip (:mod:`capture.choose`): segmented again, guided, when the
    first pass followed someone else; the note saying so, else None.

    ``plate``, an image of the empty scene, is the background only where the walker stayed in
    place (:func:`held_walker`; segmented once more then, guided by the walker followed so far; or,
    where the walker followed crossed the view, where the path chosen through a pass against the plate
    stays in place, :func:`held_path`: the first pass followed a passer-by while the walker, held in
    the clip's background, showed in pieces):
    where the walker crosses the view, the background learned from the clip is the better one (it
    has the light of the moment and whoever stood still in it: docs/ROBUSTNESS.md, "A walker held
    in the background"); the walker is then chosen over the clip once more, on that pass, where the
    plate shows them whole (the first pass may have followed someone else, having only their pieces).

    Last, the frames where someone joined the walker's blob are cut back to the walker
    (:func:`capture.merges.unmerge`, ``settings.unmerge_jump``), and the note says how many.
    """
    segs = segment(frames(), settings, fps=fps)
    boxes, note = guide(segs, settings)
    if boxes is not None:
        segs = segment(frames(), settings, fps=fps, guide=boxes)
    against = None  # the pass against the plate, where the walker stayed in place
    if plate is not None and held_walker(segs):
        # on the walker followed so far: against the plate someone who stood still all along shows,
        # and a walker dressed like the ground shows partly (docs/ROBUSTNESS.md, "Small walkers")
        against = segment(frames(), settings, fps=fps, guide=_nearest(walker_boxes(segs)), plate=plate)
    elif plate is not None:
        # the first pass may have followed someone crossing the view while the walker, held in the clip's
        # background, showed in pieces: against the plate the path chosen through the candidates stays in place
        trial = segment(frames(), settings, fps=fps, plate=plate)
        against = trial if held_path(trial) else None
    if against is not None:
        segs = against
        boxes, chosen = guide(segs, settings)  # chosen again where the plate shows the walker whole
        if boxes is not None:
            segs, note = segment(frames(), settings, fps=fps, guide=boxes, plate=plate), chosen
    test = MergeTest.of(settings)
    if test is not None:
        segs, cut = unmerge(segs, test)
        if cut:
            joined = (f"{cut} frames where someone behind or in front joined the walker's silhouette were cut "
                      "back to the walker's height")
            note = joined if note is None else f"{note}; {joined}"
    return segs, note


def _nearest(boxes: list[tuple[int, int, int, int] | None]) -> list[tuple[int, int, int, int] | None]:
    """Each frame's box, or where there is none the nearest frame's: a walker held in place is where
    they were seen last (or first)."""
    seen = np.flatnonzero([b is not None for b in boxes])
    if not len(seen):
        return boxes
    return [boxes[int(seen[np.argmin(np.abs(seen - t))])] for t in range(len(boxes))]


def against_plate(segs: list[Segmentation | None]) -> bool:
    """Whether :func:`segment_clip` took the image of the empty scene as the clip's background (it
    decides per clip: where the walker followed stayed in place, :func:`held_walker`, or where the path
    chosen through a pass against the plate stays in place, :func:`held_path`), as the segmentations
    say (:attr:`capture.segment.Segmentation.plate`)."""
    return any(s is not None and s.plate for s in segs)


def background_note(segs: list[Segmentation | None], plate: Path | None) -> str | None:
    """What a camera's background was, for the result's notes: the image of the empty scene
    (``plate``, its file) where :func:`segment_clip` took it (:func:`against_plate`); a note that it
    was not needed where the walker crossed the view; the :func:`held_walker` advice where there
    was none; else None."""
    if plate is None:
        return held_walker(segs)
    if against_plate(segs):
        return (f"background: {plate.name}, the image of the empty scene (the walker, or the path through the "
                "people seen against it, stayed in about the same place in the image, so the background learned "
                "from the clip would hold them)")
    return (f"background: learned from the clip, not {plate.name}: the walker crossed the view, and the "
            "clip's background has the light of the moment and whoever stood still in it")


def track_from_segmentations(segs: list[Segmentation | None]) -> CameraTrack:
    """A camera track (tight crops, full-frame boxes) from segmenter output."""
    sils, boxes = [], []
    size = next((s.image_size for s in segs if s is not None), None)
    for s in segs:
        cropped = None if s is None or s.box.empty else crop_to_box(s.mask)
        if cropped is None:
            sils.append(None)
            boxes.append([np.nan] * 4)
        else:
            crop, b = cropped
            sils.append(crop)
            boxes.append([s.box.x + b[0], s.box.y + b[1], b[2], b[3]])
    return CameraTrack(sils, np.array(boxes, float).reshape(-1, 4), full_frame=True,
                       image_size=None if size is None else tuple(size))


def check_priors(priors: list[Prior], raw: list[Segmentation | None]) -> list[Prior]:
    """Keep, weaken or drop each prior by how much of the raw silhouette it explains.

    The consistency check of :func:`estimator.prior.explained` /
    :func:`estimator.prior.weigh` against the frame's segmentation without
    prior; a prior that contradicts the evidence is dropped. Frames without a
    raw silhouette keep theirs.
    """
    out = []
    for p in priors:
        s = raw[p.frame_index] if p.frame_index < len(raw) else None
        if s is None or s.box.empty:
            out.append(p)
            continue
        w = weigh(p, explained(p, s.full_mask()))
        if w is not None:
            out.append(w)
    return out


def second_pass(frames: Iterable[np.ndarray], settings: SegmentSettings, priors: list[Prior],
                raw: list[Segmentation | None], *, trim_reach: float | None = 0.1,
                plate: np.ndarray | None = None) -> list[Segmentation | None]:
    """Segment the frames again with their priors, then trim to the priors that explain ``raw``.

    The segmenter checks each prior against its own evidence as it goes (the
    agent-side check); the trim (:func:`trim`, skipped when ``trim_reach`` is
    None) uses the priors checked against the first pass (:func:`check_priors`).
    ``plate``: :func:`segment`'s.
    """
    segs = segment(frames, settings, priors, guide=walker_boxes(raw), plate=plate)  # the first pass's walker
    return segs if trim_reach is None else trim(segs, check_priors(priors, raw), reach=trim_reach)


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
            out.append(Segmentation.nothing(s.image_size, used_prior=True, plate=s.plate))
            continue
        crop, b = cropped
        out.append(Segmentation(crop, Box(*(int(v) for v in b)), s.image_size, int(np.count_nonzero(crop)), True,
                                plate=s.plate))
    return out


@dataclass
class RefineResult:
    """Both passes of :func:`refine_cameras`."""

    raw: dict[str, list[Segmentation | None]]
    refined: dict[str, list[Segmentation | None]]
    estimate: WalkEstimate | SegmentedWalk
    priors: dict[str, list[Prior]]
    image_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)  # camera -> whose walker was followed (segment_clip)


def refine_cameras(
    frames: dict[str, Callable[[], Iterable[np.ndarray]]],
    model: AppearanceModel,
    *,
    renderer,
    settings: SegmentSettings = SegmentSettings(),
    config: PriorConfig | None = None,
    prior_transform: Callable[[Prior], Prior] | None = None,
    trim_reach: float | None = 0.1,
    raw: dict[str, list[Segmentation | None]] | None = None,
    estimate: WalkEstimate | SegmentedWalk | None = None,
    progress: Callable[[float], None] | None = None,
    plates: dict[str, np.ndarray] | None = None,
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
        deliberately wrong prior); the segmenter then checks every prior
        against its own evidence, and the trim uses them checked against the
        first pass (:func:`check_priors`).
    trim_reach : float or None
        After the second pass, cut foreground farther than this many body
        heights from the prior (:func:`trim`); None = keep the segmenter's output.
    raw, estimate : optional
        The first pass's segmentations (per camera, as :func:`segment` returns
        them) and the walk estimated from them, when the caller has them already
        (a job that estimated from the same videos): neither is made again.
    progress : callable, optional
        Called with the fraction of the cameras segmented a second time, after each.

    Raises
    ------
    ValueError
        No silhouette in any camera (nothing to estimate from).
    """
    notes: dict[str, str] = {}
    if raw is None:
        raw = {}
        for name, make in frames.items():
            raw[name], note = segment_clip(make, settings, plate=(plates or {}).get(name))
            if note:
                notes[name] = note
    else:
        raw = dict(raw)
    sizes = {}
    for name in frames:
        first = next((s for s in raw[name] if s is not None), None)
        if first is None:
            raise ValueError(f"camera {name}: no frames after the warm-up of {settings.warmup_frames}")
        sizes[name] = first.image_size
    tracks = {name: track_from_segmentations(raw[name]) for name in frames}
    if estimate is None:
        estimate = estimate_walk(tracks, model)
    priors = priors_for_window(estimate, tracks, sizes, renderer=renderer, config=config or FEEDBACK)
    if prior_transform is not None:
        priors = {name: [prior_transform(p) for p in ps] for name, ps in priors.items()}
    refined = {}
    for k, (name, make) in enumerate(frames.items()):
        plate = (plates or {}).get(name) if against_plate(raw[name]) else None  # segment_clip's choice
        refined[name] = second_pass(make(), settings, priors[name], raw[name], trim_reach=trim_reach, plate=plate)
        if progress is not None:
            progress((k + 1) / len(frames))
    return RefineResult(raw, refined, estimate, priors, sizes, notes)


# ------------------------------------------------------------------ whole recordings


@dataclass
class RefinedSequence:
    """A recording's silhouettes refined with model feedback, and what it took.

    ``raw`` (the input silhouettes: arrays as a sequence folder holds them, or
    the first pass's segmentations of a video) and ``priors`` are kept as they
    came, crops included; :meth:`raw_frame` and :meth:`prior_frame` give one
    full frame at a time (Rerun shows raw, prior and refined side by side).
    """

    sequence: Sequence
    estimate: WalkEstimate | SegmentedWalk
    n_priors: int
    changed_pixels: int
    raw: dict[str, list[np.ndarray | Segmentation | None]]
    priors: dict[str, list[Prior]]
    notes: dict[str, str] = field(default_factory=dict)  # camera -> whose walker was followed

    def raw_frame(self, camera: str, k: int) -> np.ndarray | None:
        """Frame ``k``'s input silhouette of ``camera``, full frame (a crop at the origin)."""
        s = self.raw[camera][k]
        if s is None or isinstance(s, Segmentation):
            return None if s is None or s.box.empty else s.full_mask()
        return _at_origin(s, tuple(self.sequence.image_size))

    def prior_frame(self, camera: str, k: int) -> np.ndarray | None:
        """Frame ``k``'s prior of ``camera``, full frame, or None."""
        p = next((p for p in self.priors.get(camera, ()) if p.frame_index == k), None)
        return None if p is None else p.full_mask()


def _at_origin(sil: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A full-frame silhouette as is; a crop (no position known) pasted at the origin."""
    if (sil.shape[1], sil.shape[0]) == size:
        return sil
    frame = np.zeros(size[::-1], np.uint8)
    frame[: sil.shape[0], : sil.shape[1]] = sil
    return frame


def _walker_frame(track: CameraTrack, k: int, size: tuple[int, int]) -> np.ndarray | None:
    """Frame ``k`` of a (cleaned) track pasted at its box into a ``size`` canvas; None without one."""
    sil, box = track.silhouettes[k], track.boxes[k]
    if sil is None or not np.isfinite(box).all():
        return None
    b = Box(*(int(round(v)) for v in box))
    if sil.shape != (b.h, b.w):
        sil = cv2.resize(sil, (b.w, b.h), interpolation=cv2.INTER_NEAREST)
    return b.paste(sil, size)


def _changed(a: list[np.ndarray | None], b: list[np.ndarray | None]) -> int:
    return sum(int(np.count_nonzero((x > 0) != (y > 0))) for x, y in zip(a, b)
               if x is not None and y is not None and x.shape == y.shape)


def refine_sequence(seq: Sequence, model: AppearanceModel, *, renderer,
                    config: PriorConfig | None = None,
                    estimate: WalkEstimate | SegmentedWalk | None = None) -> RefinedSequence:
    """Silhouettes fused with the model's priors (no images left to re-segment).

    Estimate the walk (unless the caller has, ``estimate``), render priors
    (:func:`estimator.prior.priors_for_window`; with ``config.trust``, the
    default :data:`~estimator.prior.FEEDBACK`, only for frames that pass
    :func:`estimator.prior.trust_test`) and fuse each silhouette with its
    frame's prior (:func:`estimator.prior.refine_silhouette`, restricted to
    the walker the estimate's clean-up found: holes and cut limbs the model
    explains are filled, clutter dropped). A frame without a trusted prior is
    returned unchanged, so a wrong estimate changes nothing (issue 17). Crops
    (silhouettes smaller than the frame) are refined at the origin of a full
    canvas and cut back.

    Raises ValueError if nothing can be estimated.
    """
    tracks = tracks_from_sequence(seq)
    if estimate is None:
        estimate = estimate_walk(tracks, model)
    size = tuple(seq.image_size)
    # No image to weigh the prior against: the evidence gate is a torn silhouette's
    # everywhere, and refine_silhouette's fill rule (thick parts next to the walker) decides.
    config = config or FEEDBACK
    offline = dataclasses.replace(config, reach_min=config.reach_max)
    priors = priors_for_window(estimate, tracks, size, renderer=renderer, config=offline)
    walkers = walker_tracks(estimate, tracks)
    out = {}
    for cam in seq.cameras:
        by_frame = {p.frame_index: p for p in priors[cam]}
        out[cam] = []
        for k, sil in enumerate(seq.silhouettes[cam]):
            p = by_frame.get(k)
            walker = _walker_frame(walkers[cam], k, size)
            if sil is None or p is None or walker is None:
                out[cam].append(sil)
                continue
            refined = refine_silhouette(_at_origin(sil, size), p.full_mask(), walker=walker, reach=config.fill_reach,
                                        limb=config.limb, limb_level=config.limb_level)
            out[cam].append(refined[: sil.shape[0], : sil.shape[1]])
    changed = sum(_changed(seq.silhouettes[c], out[c]) for c in seq.cameras)
    refined_seq = Sequence(fps=seq.fps, cameras=list(seq.cameras), image_size=seq.image_size,
                           silhouettes=out, truth=seq.truth, extra=seq.extra)
    return RefinedSequence(refined_seq, estimate, sum(len(v) for v in priors.values()), changed,
                           dict(seq.silhouettes), priors)


def plate_path(video: str | os.PathLike) -> Path | None:
    """``<camera>.background.png`` (``.jpg``, ``.jpeg``) beside the video ``<camera>.<ext>``, if there is one."""
    video = Path(video)
    return next((p for suffix in PLATE_SUFFIXES if (p := video.with_name(video.stem + suffix)).is_file()), None)


def plate_for(video: str | os.PathLike) -> np.ndarray | None:
    """The image of the empty scene beside a video (:func:`plate_path`, BGR), or None when there is
    none (:class:`capture.segment.Segmenter`'s ``plate``).

    Raises ValueError (:class:`~capture.sources.SourceError`) naming the file when it cannot be read
    or is not the video's frame size.
    """
    path = plate_path(video)
    if path is None:
        return None
    with VideoFileSource(video) as source:
        return read_plate(path, source.size)


def plates_for(videos: dict[str, str | os.PathLike]) -> dict[str, np.ndarray]:
    """Each camera's :func:`plate_for` of its video, where it has one."""
    return {c: plate for c, p in videos.items() if (plate := plate_for(p)) is not None}


def video_frames(path: str | os.PathLike, max_frames: int | None = None) -> Callable[[], Iterator[np.ndarray]]:
    """A function that reopens the video and yields its BGR frames (one pass each call; at most
    ``max_frames``, None: all).

    Raises ValueError (:class:`~capture.sources.SourceError`) if it cannot be opened.
    """
    def frames() -> Iterator[np.ndarray]:
        with VideoFileSource(path) as source:
            yield from itertools.islice((frame.image for frame in source), max_frames)
    return frames


def _full(s: Segmentation | None) -> np.ndarray | None:
    return None if s is None or s.box.empty else s.full_mask()


def changed_pixels(raw: list[Segmentation | None], refined: list[Segmentation | None]) -> int:
    """Pixels that differ between two passes' silhouettes, over the frames where both found the
    walker (one full frame at a time)."""
    return sum(_changed([_full(a)], [_full(b)]) for a, b in zip(raw, refined))


def refined_sequence(result: RefineResult, fps: float, truth: dict | None = None) -> RefinedSequence:
    """Both passes of :func:`refine_cameras` as a :class:`RefinedSequence`: the refined
    silhouettes as full frames (what a job with ``refine=true`` serves)."""
    cameras = list(result.refined)
    sils = {c: [_full(s) for s in result.refined[c]] for c in cameras}
    changed = sum(changed_pixels(result.raw[c], result.refined[c]) for c in cameras)
    size = next(iter(result.image_sizes.values()))
    seq = Sequence(fps=fps, cameras=cameras, image_size=size, silhouettes=sils, truth=truth)
    return RefinedSequence(seq, result.estimate, sum(len(v) for v in result.priors.values()),
                           changed, result.raw, result.priors, result.notes)


def refine_videos(videos: dict[str, str | os.PathLike], model: AppearanceModel, *, renderer,
                  warmup: int, fps: float, config: PriorConfig | None = None,
                  truth: dict | None = None, raw: dict[str, list[Segmentation | None]] | None = None,
                  estimate: WalkEstimate | SegmentedWalk | None = None,
                  max_frames: int | None = None) -> RefinedSequence:
    """One video per camera, background-subtracted twice (:func:`refine_cameras`; the
    first pass and the estimate are reused when given; at most ``max_frames`` per video).

    Raises ValueError if a video cannot be read or nothing can be estimated.
    """
    result = refine_cameras({c: video_frames(p, max_frames) for c, p in videos.items()}, model,
                            renderer=renderer, settings=SegmentSettings(warmup_frames=warmup),
                            config=config, raw=raw, estimate=estimate,
                            plates=plates_for(videos))
    return refined_sequence(result, fps, truth)
