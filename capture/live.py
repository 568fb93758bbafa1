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

__all__ = ["LiveSegmenter", "segment_recording"]


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

    def apply(self, image: np.ndarray, index: int) -> Segmentation | None:
        """This frame's silhouette (None while the segmenter warms up)."""
        seg = self.segmenter.apply(image, index, self._onto)
        self._index = index
        if seg is not None and self.unmerge is not None:
            seg = self.unmerge.see(seg)
        self._last = seg
        return seg

    def learn(self) -> bool:
        """The background update and the look back over the frames so far; True when the track
        moves to another person from the next frame on (:attr:`note` says why)."""
        self.segmenter.learn()
        self._onto = None if self.choice is None or self._last is None else self.choice.see(self._last, self._index)
        if self._onto is not None and self.unmerge is not None:
            self.unmerge.reset()
        return self._onto is not None

    @property
    def cut(self) -> int:
        """Frames cut back to the walker where someone joined them."""
        return 0 if self.unmerge is None else self.unmerge.cut

    @property
    def track_id(self) -> int:
        """The person the track is on: 0 from the start, one more at each move (the wire's ``track_id``)."""
        return 0 if self.choice is None else self.choice.switches

    @property
    def track_from(self) -> int | None:
        """After a move, the first frame the track followed someone else before it (the wire's
        ``track_from``: the service leaves out, and revises, the windows that held those frames)."""
        return None if self.choice is None else self.choice.since

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
