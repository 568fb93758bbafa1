"""A live camera's silhouettes, frame by frame: what an agent runs on each frame it grabs.

A file is segmented with the whole clip in view (:func:`capture.refine.segment_clip`);
a live camera only has the frames before. Per frame:

1. :meth:`capture.segment.Segmenter.apply` keeps one person's blob (the track,
   moved where the last look back said);
2. :class:`capture.merges.LiveUnmerge` cuts it back to the walker when someone
   just joined them;
3. after the silhouette is sent (off the capture-to-publish path, :meth:`LiveSegmenter.learn`),
   the segmenter's background update and :class:`capture.choose.LiveChoice`'s
   look back, which may move the track onto another person for the next frame;
   the join test then forgets the old person's height.

Every silhouette carries the person the track is on (:attr:`LiveSegmenter.track_id`,
the wire's ``track_id``): one more at each move of the look back and each time the
segmenter, having lost its track, starts one on someone who does not continue it
(:func:`same_person`: one walker left the view and another came in), so that the
service does not estimate a window on two people.

:func:`segment_recording` runs it over a recording held in memory, as an agent runs it over a
file; ``bench/eval_composite.py --segment-only`` measures it against the file's path on the
composite walks (docs/ROBUSTNESS.md, "The live track moves back sooner"), and
``bench/eval_real_video.py`` on real footage.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .choose import LiveChoice
from .merges import LiveUnmerge
from .segment import Segmentation, Segmenter, SegmentSettings, sample_indices

__all__ = ["LiveSegmenter", "same_person", "segment_recording"]

Box4 = tuple[int, int, int, int]

SAME_GAP = 15
"""Frames a track may be lost for and still be picked up again as the same person (:func:`same_person`)."""


def same_person(last: Box4, box: Box4, gap: int) -> bool:
    """Whether a track started on ``box`` (x, y, w, h) ``gap`` frames after the last track's ``last`` box
    goes on with the same person: within :data:`SAME_GAP` frames, its centre within 0.35 of the taller's
    height of the last one's and its log height within 0.25 (``bench/eval_real_estimate.py`` cuts a
    recording into passes of one person with it)."""
    if gap > SAME_GAP:
        return False
    step = np.hypot(box[0] + box[2] / 2 - last[0] - last[2] / 2, box[1] + box[3] / 2 - last[1] - last[3] / 2)
    return bool(step <= 0.35 * max(last[3], box[3]) and abs(np.log(box[3] / last[3])) <= 0.25)


class LiveSegmenter:
    """The live path over one :class:`~capture.segment.Segmenter` (module docstring): :meth:`apply` each
    frame, send the silhouette, then :meth:`learn`. The segmenter's settings switch the look back
    (``walker_choice``) and the join test (``unmerge_jump``) on and off."""

    def __init__(self, segmenter: Segmenter) -> None:
        self.segmenter = segmenter
        settings = segmenter.settings
        self.choice = LiveChoice(settings) if settings.walker_choice == "centred" else None
        self.unmerge = LiveUnmerge.of(settings)
        self._onto: tuple[int, int, int, int] | None = None
        self._last: Segmentation | None = None
        self._index = -1
        self._seen: tuple[Box4, int] | None = None  # the last walker's box and frame
        self._others = 0  # tracks started on someone who did not continue the last one
        self._from: int | None = None  # the current track's track_from

    def apply(self, image: np.ndarray, index: int) -> Segmentation | None:
        """This frame's silhouette (None while the segmenter warms up)."""
        started = self.segmenter.tracks_started
        seg = self.segmenter.apply(image, index, self._onto)
        self._index = index
        if seg is not None and not seg.box.empty:
            box = (seg.box.x, seg.box.y, seg.box.w, seg.box.h)
            if self.segmenter.tracks_started > started and self._onto is None and self._seen is not None \
                    and not same_person(self._seen[0], box, index - self._seen[1]):
                self._others, self._from = self._others + 1, None  # someone else: from their first frame
            self._seen = (box, index)
        if seg is not None and self.unmerge is not None:
            seg = self.unmerge.see(seg)
        self._last = seg
        return seg

    def learn(self) -> bool:
        """The background update and the look back over the frames so far; True when the track
        moves to another person from the next frame on (:attr:`note` says why)."""
        self.segmenter.learn()
        self._onto = None if self.choice is None or self._last is None else self.choice.see(self._last, self._index)
        if self._onto is not None:
            self._from = self.choice.since
            self._seen = (self._onto, self._index)  # the person moved onto, whoever the segmenter starts on next
            if self.unmerge is not None:
                self.unmerge.reset()
        return self._onto is not None

    @property
    def cut(self) -> int:
        """Frames cut back to the walker where someone joined them."""
        return 0 if self.unmerge is None else self.unmerge.cut

    @property
    def track_id(self) -> int:
        """The person the track is on (the wire's ``track_id``): 0 from the start, one more at each move of
        the look back and each track started on someone else (module docstring)."""
        return self._others + (0 if self.choice is None else self.choice.switches)

    @property
    def track_from(self) -> int | None:
        """After a move of the look back, the first frame the track followed someone else before it (the
        wire's ``track_from``: the service leaves out, and revises, the windows that held those frames);
        None on the first track and on a track started on someone else (the frames before were another
        walker's: the service leaves them out of the windows that hold frames of this one)."""
        return self._from

    @property
    def note(self) -> str | None:
        """Why the track last moved."""
        return None if self.choice is None else self.choice.note

    @property
    def held(self) -> str | None:
        """The last look back's note that the walker stayed in place (:func:`capture.choose.held_walker`)."""
        return None if self.choice is None else self.choice.held


def segment_recording(frames: Sequence[np.ndarray], settings: SegmentSettings, fps: float | None = None,
                      plate: np.ndarray | None = None) -> list[Segmentation | None]:
    """Each BGR frame's silhouette (None where there is none) as an agent segments a recording:
    with ``settings.background = "bootstrap"`` the background from frames sampled over its first
    ``bootstrap_seconds`` (``plate``, an image of the empty scene, instead when given), then
    :class:`LiveSegmenter` over every frame from 0; with ``"warmup"`` the segmenter learns from the
    first frames as it goes."""
    segmenter = Segmenter(settings, plate=plate)
    if settings.background == "bootstrap":
        segmenter.bootstrap([frames[i] for i in sample_indices(len(frames), fps, settings)])
    live, out = LiveSegmenter(segmenter), []
    for k, image in enumerate(frames):
        out.append(live.apply(image, k))
        live.learn()
    return out
