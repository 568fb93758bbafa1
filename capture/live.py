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

``bench/eval_composite.py --segment-only`` measures this path against the file's
on the composite walks (docs/ROBUSTNESS.md, "The live track moves back sooner").
"""

from __future__ import annotations

import numpy as np

from .choose import LiveChoice
from .merges import LiveUnmerge
from .segment import Segmentation, Segmenter

__all__ = ["LiveSegmenter"]


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

    def apply(self, image: np.ndarray, index: int) -> Segmentation | None:
        """This frame's silhouette (None while the segmenter warms up)."""
        seg = self.segmenter.apply(image, index, self._onto)
        if seg is not None and self.unmerge is not None:
            seg = self.unmerge.see(seg)
        self._last = seg
        return seg

    def learn(self) -> bool:
        """The background update and the look back over the frames so far; True when the track
        moves to another person from the next frame on (:attr:`note` says why)."""
        self.segmenter.learn()
        self._onto = None if self.choice is None or self._last is None else self.choice.see(self._last)
        if self._onto is not None and self.unmerge is not None:
            self.unmerge.reset()
        return self._onto is not None

    @property
    def cut(self) -> int:
        """Frames cut back to the walker where someone joined them."""
        return 0 if self.unmerge is None else self.unmerge.cut

    @property
    def note(self) -> str | None:
        """Why the track last moved."""
        return None if self.choice is None else self.choice.note

    @property
    def held(self) -> str | None:
        """The last look back's note that the walker stayed in place (:func:`capture.choose.held_walker`)."""
        return None if self.choice is None else self.choice.held
