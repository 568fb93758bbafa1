"""A walker joined by someone behind or in front, cut back to the walker.

Where the walker passes in front of (or behind) another person of about their
size, the two make one foreground blob, and the segmenter can only keep it
whole: the silhouette is the walker with another body standing on their head
(or under their feet). Registration scales that blob to the body's height, so
the walker comes out squashed, and every stage after it errs (on the composite
walks with walkers 120 px tall, 9-15 % of the frames; docs/ROBUSTNESS.md,
"A walker joined by someone behind").

A single frame cannot tell a joined blob from a tall walker, but the frames
around it can: one person's image height changes smoothly (a few per cent per
frame at 15 Hz), while a join or a parting changes the blob's height by the
other person's overhang at once, and the frame before a join (or after a
parting) shows that person beside the walker as a candidate of their own.

- :func:`unmerge` (a file, the whole clip): splits the frames into runs at
  such jumps, chains the jumps into a level per run, takes the runs at the
  lowest level as the walker alone (at least ``MergeTest.reference`` frames,
  upright), and cuts each run above it to the walker's height there
  (interpolated between the walker's frames on either side, or carried on at
  their trend past the last of them), where another person's box explains the
  extra rows in the walker's frame beside it.
- :class:`LiveUnmerge` (a live camera): the same test against the frames
  before only.

The cut keeps the end the jump left in place: the feet when the other person
is farther away, and so higher in the image; the head when nearer. A run
whose two ends both moved is left as it is.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from .segment import Segmentation, SegmentSettings, box_iou
from .wire import Box

__all__ = ["TREND", "LiveUnmerge", "MergeTest", "unmerge"]

TREND = 0.015
"""Largest change of the walker's log height per frame carried past their last frame alone (a walker
at 4 m walking at 1.5 m/s straight at a 15 Hz camera: 2.5 %)."""


Box4 = tuple[int, int, int, int]


def _box(s: Segmentation | None) -> Box4 | None:
    """The full-frame box (x, y, w, h) of the mask's pixels (None without any)."""
    if s is None or s.box.empty:
        return None
    x, y, w, h = cv2.boundingRect(s.mask)
    return None if w == 0 else (s.box.x + x, s.box.y + y, w, h)


def _levels(log_h: np.ndarray, jump: float) -> tuple[np.ndarray, np.ndarray]:
    """Run index per frame (split where the log height changes by more than ``log1p(jump)``) and each
    run's level: the sum of the jumps before it (the change within a run is the walker's own)."""
    d = np.diff(log_h)
    cut = np.abs(d) > np.log1p(jump)
    run = np.concatenate([[0], np.cumsum(cut)])
    levels = np.concatenate([[0.0], np.cumsum(d[cut])])
    return run, levels


def _anchor(joined: Box4, alone: Box4, tolerance: float) -> str | None:
    """Which end stayed between the ``joined`` blob's box and the walker's ``alone``: 'bottom',
    'top', or None when both or neither did."""
    h = alone[3]
    feet = abs((joined[1] + joined[3]) - (alone[1] + alone[3])) <= tolerance * h
    head = abs(joined[1] - alone[1]) <= tolerance * h
    return "bottom" if feet and not head else "top" if head and not feet else None


def _nearest_alone(frames: np.ndarray, alone: np.ndarray, reach: int) -> list[tuple[int, int]]:
    """``(end, alone frame)`` for each end of a joined run of ``frames`` that has a frame of the walker
    alone within ``reach`` frames beyond it."""
    ends = []
    for end, step in ((frames[0], -1), (frames[-1], 1)):
        beyond = np.arange(end + step, end + step * (reach + 1), step)
        beyond = beyond[(beyond >= 0) & (beyond < alone.size)]
        hit = beyond[alone[beyond]]
        if hit.size:
            ends.append((int(end), int(hit[0])))
    return ends


def _joined_by(joined: Box4, alone: Box4, others: tuple[Box4, ...], keep_feet: bool, cover: float = 0.5,
               upright: float = 1.2) -> bool:
    """Whether, in the frame where the walker is ``alone`` (their box; ``others``: the candidates'
    boxes there), another person's box spans at least ``cover`` of the rows the ``joined`` blob of
    the next (or previous) frame has beyond the walker (above their head when ``keep_feet``, else
    below their feet) and overlaps its columns.

    A person's box is at least ``upright`` times taller than wide: a piece of the walker torn
    off (their head and shoulders, the colour of what is behind them) is squatter."""
    (jx, jy, jw, jh), (ax, ay, aw, ah) = joined, alone
    lo, hi = (jy, ay) if keep_feet else (ay + ah, jy + jh)
    if hi - lo < 1:
        return False
    for cx, cy, cw, ch in others:
        if box_iou((cx, cy, cw, ch), (ax, ay, aw, ah)) > 0.5 or ch < upright * cw:
            continue  # the walker, or not a whole person
        rows = min(hi, cy + ch) - max(lo, cy)
        cols = min(jx + jw, cx + cw) - max(jx, cx)
        if rows >= cover * (hi - lo) and cols > 0:
            return True
    return False


def _walker_heights(log_h: np.ndarray, alone: np.ndarray, near: int = 10) -> np.ndarray:
    """The walker's log height in every frame from the frames where they are alone: linear
    between two such frames; before the first and after the last, carried on from the line
    through those within ``near`` frames of it, at a slope of at most :data:`TREND` per frame."""
    t = np.arange(log_h.size)
    ts = t[alone]
    out = np.interp(t, ts, log_h[alone])
    for edge, side, beyond in ((ts[0], ts[ts <= ts[0] + near], t < ts[0]),
                               (ts[-1], ts[ts >= ts[-1] - near], t > ts[-1])):
        if not beyond.any() or side.size < 3:
            continue  # held at the edge's height
        slope, level = np.polyfit(side - edge, log_h[side], 1)
        out[beyond] = level + float(np.clip(slope, -TREND, TREND)) * (t[beyond] - edge)
    return out


@dataclass(frozen=True)
class MergeTest:
    """When a jump in the walker's blob is someone joining them, and how the cut is made.

    Parameters
    ----------
    jump : float
        A change of the blob's height between consecutive frames larger than this fraction is a join
        or a parting; runs more than this above the lowest level are joined.
    reference : int
        Frames at the lowest level needed before any frame is cut (fewer: nothing is).
    tolerance : float
        An end of the blob moved by at most this fraction of the height stayed in place.
    margin : float
        The cut keeps this fraction of the walker's height beyond it (a raised hand, a bob).
    reach : int
        A joined run is compared with the walker alone at most this many frames beyond its ends.
    upright : float
        The walker alone is at least this many times taller than wide (median over those frames);
        where the lowest level is squatter, it is a part of the walker (the legs, a torso) and
        nothing is cut.
    """

    jump: float = 0.12
    reference: int = 3
    tolerance: float = 0.06
    margin: float = 0.03
    reach: int = 3
    upright: float = 2.0

    @classmethod
    def of(cls, settings: SegmentSettings) -> MergeTest | None:
        """The test a segmenter with ``settings`` runs (``unmerge_jump``), None when it is off."""
        return cls(jump=settings.unmerge_jump) if settings.unmerge_jump else None


def unmerge(segs: list[Segmentation | None], test: MergeTest = MergeTest()
            ) -> tuple[list[Segmentation | None], int]:
    """``segs`` (one clip's segmentations in frame order, :func:`capture.refine.segment`) with the
    frames where someone joined the walker cut back to the walker, and how many."""
    boxes = [_box(s) for s in segs]
    size = np.array([(np.nan, np.nan) if b is None else b[2:] for b in boxes], float).reshape(-1, 2)
    out, n_cut = list(segs), 0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.isfinite(size[:, 1]).astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):  # each stretch of frames with a silhouette
        log_h = np.log(size[a:b, 1])
        run, levels = _levels(log_h, test.jump)
        excess = levels - levels.min()
        low = excess < 0.5 * np.log1p(test.jump)
        alone = low[run]
        if alone.sum() < test.reference or alone.all():
            continue
        if np.median(size[a:b][alone, 1] / size[a:b][alone, 0]) < test.upright:
            continue  # the lowest level is not a whole person (legs, a torso): torn, not joined
        walker = _walker_heights(log_h, alone)
        for r in np.flatnonzero(excess > np.log1p(test.jump)):
            frames = np.flatnonzero(run == r)
            ends = [(a + f, a + g) for f, g in _nearest_alone(frames, alone, test.reach)]
            anchors = {_anchor(boxes[f], boxes[g], test.tolerance) for f, g in ends}
            if not ends or len(anchors) != 1 or None in anchors:
                continue
            keep_feet = anchors.pop() == "bottom"
            if not any(_joined_by(boxes[f], boxes[g], segs[g].candidates, keep_feet) for f, g in ends):
                continue  # no one else there to have joined: the walker was short (torn, hidden) instead
            for f in frames:
                height = np.exp(walker[f]) * (1 + test.margin)
                if height >= np.exp(log_h[f]):
                    continue
                cut = _cut(segs[a + f], boxes[a + f], height, keep_feet)
                if cut is not None:
                    out[a + f], n_cut = cut, n_cut + 1
    return out, n_cut


def _cut(s: Segmentation, box: Box4, height: float, keep_feet: bool) -> Segmentation | None:
    """``s`` (its pixels' box ``box``) keeping the ``height`` rows at its bottom (``keep_feet``) or
    top, cropped again with the margin it had."""
    top, left = box[1] - s.box.y, box[0] - s.box.x  # in the crop
    pad = min(top, left)
    mask = s.mask.copy()
    keep = int(round(height))
    if keep_feet:
        mask[: top + box[3] - keep] = 0
    else:
        mask[top + keep:] = 0
    ys, xs = np.nonzero(mask)
    if not ys.size:
        return None
    h, w = mask.shape
    y0, y1 = max(0, ys.min() - pad), min(h, ys.max() + 1 + pad)
    x0, x1 = max(0, xs.min() - pad), min(w, xs.max() + 1 + pad)
    crop = np.ascontiguousarray(mask[y0:y1, x0:x1])
    box = Box(s.box.x + int(x0), s.box.y + int(y0), int(x1 - x0), int(y1 - y0))
    return dataclasses.replace(s, mask=crop, box=box, area=int(np.count_nonzero(crop)))  # the rest as it was


class LiveUnmerge:
    """:func:`unmerge` for a live camera, which cannot look ahead.

    Frame by frame, a jump of the walker's blob above their height in the frame before, after at
    least ``reference`` frames alone without a jump, with one end in place and another person's
    box there the frame before (:func:`_joined_by`), starts a join. Until the blob comes back
    within ``jump`` of the walker's height (carried on at the trend of their last frames alone, at
    most :data:`TREND` per frame) or the kept end moves, each frame is cut back to it. A join that
    starts before the walker was seen alone cannot be told, and is left.

    ``see`` takes the segmenter's output (:meth:`capture.segment.Segmenter.apply`) and returns it,
    or it cut; ``cut`` counts the frames cut; ``reset`` when the track moves to another person.
    """

    def __init__(self, test: MergeTest = MergeTest(), near: int = 10) -> None:
        self.test, self.cut = test, 0
        self._alone: list[tuple[Segmentation, Box4]] = []  # the last ``near`` frames alone, their pixels' boxes
        self._near = near
        self._joined: tuple[bool, float, float] | None = None  # keep feet, walker's log height, its slope
        self._kept: Box4 | None = None  # the last output's pixels' box
        self._missed = 0

    @classmethod
    def of(cls, settings: SegmentSettings) -> LiveUnmerge | None:
        """The cut a segmenter with ``settings`` runs live (``unmerge_jump``), None when it is off."""
        test = MergeTest.of(settings)
        return None if test is None else cls(test)

    def reset(self) -> None:
        """Forget the walker's frames: the track moved to another person (:class:`capture.choose.LiveChoice`),
        whose height says nothing of a join."""
        self._alone, self._joined, self._kept = [], None, None

    def see(self, seg: Segmentation) -> Segmentation:
        box = _box(seg)
        if box is None:
            self._missed += 1
            if self._missed > self.test.reach:
                self.reset()
            return seg
        self._missed = 0
        out = self._continue(seg, box) if self._joined is not None else self._start(seg, box)
        if out is seg:  # the walker alone: the frames since the last jump tell their height
            self._joined = None
            if self._alone and abs(np.log(box[3] / self._alone[-1][1][3])) > np.log1p(self.test.jump):
                self._alone = []
            self._alone = [*self._alone[1 - self._near:], (seg, box)]
        self._kept = box if out is seg else _box(out)
        return out

    def _start(self, seg: Segmentation, box: Box4) -> Segmentation:
        """A join starting at this frame, cut; else ``seg``."""
        t = self.test
        if len(self._alone) < t.reference or self._kept is None:
            return seg
        last, last_box = self._alone[-1]
        if np.log(box[3] / last_box[3]) <= np.log1p(t.jump) \
                or np.median([b[3] / b[2] for _, b in self._alone]) < t.upright:
            return seg
        anchor = _anchor(box, self._kept, t.tolerance)
        if anchor is None or not _joined_by(box, last_box, last.candidates, anchor == "bottom"):
            return seg
        hs = np.log([b[3] for _, b in self._alone])
        slope = float(np.clip(np.polyfit(np.arange(hs.size), hs, 1)[0], -TREND, TREND)) if hs.size >= 3 else 0.0
        self._joined = (anchor == "bottom", float(hs[-1]), slope)
        return self._continue(seg, box)

    def _continue(self, seg: Segmentation, box: Box4) -> Segmentation:
        """This frame cut back to the walker while the join lasts; ``seg`` once it has ended."""
        keep_feet, walker, slope = self._joined
        walker += slope
        moved = _anchor(box, self._kept, self.test.tolerance) != ("bottom" if keep_feet else "top")
        if moved or np.log(box[3]) - walker <= np.log1p(self.test.jump):
            return seg  # parted, or the kept end moved: the walker alone (or someone else) again
        out = _cut(seg, box, np.exp(walker) * (1 + self.test.margin), keep_feet)
        if out is None:
            return seg
        self._joined = (keep_feet, walker, slope)
        self.cut += 1
        return out
