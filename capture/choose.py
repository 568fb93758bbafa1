"""Which of the people in a clip is the walker, chosen over the whole clip.

Frame by frame, the segmenter keeps one person-sized component: the one
continuing its track, else the tallest (``SegmentSettings.pick``). Live it
cannot look ahead. With a walker of the size of the people around them (50-120
px tall among passers-by, as in ``vtest.avi``), the tallest at the start is
often someone else, and a camera that follows someone else puts the walker on
the wrong side of the rig (docs/ROBUSTNESS.md, "People of the walker's
size"). A file can be looked at whole, and a rig's cameras are aimed at the walk, so
the walker's path runs through the middle of every image:

1. the first pass records every candidate's box in every frame
   (:attr:`capture.segment.Segmentation.candidates`);
2. :func:`choose`: the walker's path is the cheapest through them, one person
   kept through merges and splits, its cost the boxes' distances from the
   image centre, the frames it leaves out and the changes of its height;
3. :func:`guide`: the first pass stands when it followed that path, or when
   the path is not clearly (:data:`MARGIN`) nearer the centre than what it
   followed; otherwise the clip is segmented again with the path's boxes as
   the guide (:meth:`capture.segment.Segmenter.apply`), by
   :func:`capture.refine.segment_clip`.

Live, the agent cannot look ahead, but it can look back: :class:`LiveChoice`
runs the same choice over the last ``LIVE_WINDOW`` frames (at least twice
``LIVE_EVERY``) every ``LIVE_EVERY`` and, when the track has followed someone
other than the path through the middle since it last was on it (at least
``LIVE_OFF`` frames, nearer the centre by ``MARGIN`` over those frames, and not
less than ``LIVE_SHORTER`` of the followed person's height), moves the track
onto the path's newest box for the frames to come.

The choice is off with ``SegmentSettings.walker_choice = "first"`` (the
person the track starts on).

:func:`held_walker` reads the same path for a walker who hardly crosses the
image (walking straight at the camera, a treadmill): a background learned
from those frames holds them, and only an image of the empty scene can show
what is behind them (docs/CAPTURE.md, "An image of the empty scene").
"""

from __future__ import annotations

import collections

import numpy as np

from .segment import Segmentation, SegmentSettings, box_iou

__all__ = ["AGREE", "GAP", "LIVE_EVERY", "LIVE_OFF", "LIVE_SHORTER", "LIVE_WINDOW", "MARGIN", "NOBODY", "RESIZE",
           "LiveChoice", "choose", "guide", "held_path", "held_walker", "overlap", "path_cost", "walker_boxes"]

Box = tuple[int, int, int, int]

NOBODY = 0.5
"""Cost of a frame the walker's path leaves out (in the units of a box centre's distance from the image
centre): a path gains by taking a frame's box if that box is nearer the centre than this."""
GAP = 4
"""Frames the path may leave out between two of its boxes (the walker not detected there)."""
RESIZE = 1.0
"""Cost per unit of |log| of the box height's change between two of the path's boxes: where a group
splits, the path goes on with the part whose height continues the walker's."""
AGREE = 0.8
"""The first pass stands when its walker is on the chosen path in this fraction of the path's frames ...
"""
MARGIN = 0.12
"""... or when the chosen path is not nearer the image centre than the first pass's walker by this much
(mean cost per frame with someone in view, :func:`path_cost`): a walker who crosses the whole image is
followed from its first frames (as the tallest) and left for no one who is merely a little more central."""
LIVE_WINDOW = 45
"""Frames a live agent looks back over to choose the walker (:class:`LiveChoice`): 3 s at 15 fps."""
LIVE_EVERY = 5
"""Frames between a live agent's choices (the first after twice as many)."""
LIVE_OFF = 3
"""Frames the track must have been off the chosen path before a live agent moves it."""
LIVE_SHORTER = 0.5
"""A live agent does not move the track onto a path whose boxes are less than this share of the followed
person's height (medians over the frames judged): over 10 frames, a passer-by a third of a large walker's
height who crossed nearer the image centre was a cheaper path (composite walks at full size)."""
_SAME = 0.5  # boxes overlapping by this fraction of the smaller are the same person (or one merged into a group)


def overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over the smaller box's area, every box of ``a`` (N, 4) against every box of ``b`` (M, 4)."""
    ix = np.clip(np.minimum(a[:, None, 0] + a[:, None, 2], b[None, :, 0] + b[None, :, 2])
                 - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(a[:, None, 1] + a[:, None, 3], b[None, :, 1] + b[None, :, 3])
                 - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    smaller = np.minimum((a[:, 2] * a[:, 3])[:, None], (b[:, 2] * b[:, 3])[None, :])
    return ix * iy / np.maximum(smaller, 1.0)


def _off_centre(boxes: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Distance of each box's centre (boxes (N, 4)) from the image centre, in image widths and heights."""
    w, h = size
    return np.hypot((boxes[:, 0] + boxes[:, 2] / 2) / w - 0.5, (boxes[:, 1] + boxes[:, 3] / 2) / h - 0.5)


def choose(candidates: list[tuple[Box, ...]], size: tuple[int, int]) -> list[Box | None]:
    """The walker's box in each frame (None: not on the path), the cheapest path through the candidates.

    A path is one person: from frame to frame (or across at most :data:`GAP`
    frames it leaves out) its boxes overlap by half of the smaller, so it
    stays on the walker through the merges and splits that change their box,
    and never jumps to someone apart. It may start and end anywhere. Its cost
    is the sum of its boxes' distances from the image centre (in image widths
    and heights), :data:`NOBODY` for every frame it leaves out and
    :data:`RESIZE` times the changes of its boxes' height (|log|): the
    longest, most central, steadiest track. Solved exactly by dynamic
    programming over the frames.
    """
    T = len(candidates)
    boxes = [np.array(b, float).reshape(-1, 4) for b in candidates]
    cost: list[np.ndarray] = []  # per frame and candidate: the cheapest path ending there (frames before it too)
    back: list[np.ndarray] = []  # ... and where it came from: (frame, candidate), (-1, -1) = it starts here
    for t, cur in enumerate(boxes):
        best = np.full(len(cur), NOBODY * t)  # starting here: every earlier frame left out
        came = np.full((len(cur), 2), -1)
        gaps = [g for g in range(1, min(GAP + 1, t) + 1) if len(boxes[t - g])]
        if gaps and len(cur):  # the frames it may come from, nearest first (ties keep the nearest)
            prev = np.concatenate([boxes[t - g] for g in gaps])
            came_from = np.concatenate([np.stack([np.full(len(boxes[t - g]), t - g), np.arange(len(boxes[t - g]))], 1)
                                        for g in gaps])
            before = np.concatenate([cost[t - g] + NOBODY * (g - 1) for g in gaps])
            resize = RESIZE * np.abs(np.log(cur[None, :, 3] / prev[:, None, 3]))
            total = np.where(overlap(prev, cur) >= _SAME, before[:, None] + resize, np.inf)
            i = np.argmin(total, axis=0)
            lowest = total[i, np.arange(len(cur))]
            better = lowest < best
            best = np.where(better, lowest, best)
            came[better] = came_from[i[better]]
        cost.append(best + _off_centre(cur, size))
        back.append(came)
    ends = [(cost[t][j] + NOBODY * (T - 1 - t), t, j) for t in range(T) for j in range(len(cost[t]))]
    path: list[Box | None] = [None] * T
    if not ends:
        return path
    _, t, j = min(ends)
    while t >= 0:
        path[t] = candidates[t][j]
        t, j = (int(v) for v in back[t][j])
    return path


def path_cost(path: list[Box | None], size: tuple[int, int]) -> float:
    """Mean cost per frame of a path (:func:`choose`, without the changes of height): its boxes' distances
    from the image centre, :data:`NOBODY` where it has none."""
    boxes = np.array([b for b in path if b is not None], float).reshape(-1, 4)
    return float((_off_centre(boxes, size).sum() + NOBODY * (len(path) - len(boxes))) / len(path))


def walker_boxes(segs: list[Segmentation | None]) -> list[Box | None]:
    """Each frame's walker box (None where there is none): the guide that keeps a later pass on it."""
    return [None if s is None or s.box.empty else (s.box.x, s.box.y, s.box.w, s.box.h) for s in segs]


def _followed(segs: list[Segmentation | None], size: tuple[int, int]
              ) -> tuple[list[Box | None], list[Box | None], list[bool]]:
    """The chosen walker's path through ``segs`` (:func:`choose`), the first pass's walker as a path
    through the same candidates (the candidate its box came from), and per frame whether the two agree."""
    walker = choose([() if s is None else s.candidates for s in segs], size)
    followed = walker_boxes(segs)
    first = [None if f is None else max(s.candidates, key=lambda b: box_iou(f, b), default=None)
             for f, s in zip(followed, segs)]
    first = [b if b is not None and box_iou(f, b) >= 0.3 else None for f, b in zip(followed, first)]
    agree = [w is not None and f is not None and box_iou(f, w) >= 0.3 for f, w in zip(followed, walker)]
    return walker, first, agree


def _gain(segs: list[Segmentation | None], walker: list[Box | None], first: list[Box | None],
          size: tuple[int, int]) -> float:
    """How much nearer the image centre the chosen path is than the first pass's walker, per frame with
    someone in view (:func:`path_cost`)."""
    seen = [t for t, s in enumerate(segs) if s is not None and s.candidates]
    if not seen:
        return 0.0
    return path_cost([first[t] for t in seen], size) - path_cost([walker[t] for t in seen], size)


def guide(segs: list[Segmentation | None], settings: SegmentSettings) -> tuple[list[Box | None] | None, str | None]:
    """The chosen walker's box per frame, and a note saying so, when a first pass ``segs`` followed
    someone else (module docstring, step 3); ``(None, None)`` when the first pass stands."""
    size = next((s.image_size for s in segs if s is not None), None)
    if settings.walker_choice == "first" or size is None:
        return None, None
    walker, first, agree = _followed(segs, size)
    if all(b is None for b in walker):
        return None, None
    agreed = _agreed(walker, agree)
    if agreed >= AGREE or _gain(segs, walker, first, size) < MARGIN:
        return None, None
    return walker, _note(segs, agreed, "segmented again on it")


def _agreed(walker: list[Box | None], agree: list[bool]) -> float:
    """The share of the chosen path's frames on which the first pass followed it (:func:`_followed`)."""
    return float(np.mean([a for a, b in zip(agree, walker) if b is not None]))


def _note(segs: list[Segmentation | None], agreed: float, then: str) -> str:
    people = max(len(s.candidates) for s in segs if s is not None)
    return (f"up to {people} people in view; the walker is the one whose path stays nearest the image centre, "
            f"not the one the track started on (followed on {agreed:.0%} of its frames): {then}")


class LiveChoice:
    """The walker chosen live, looking back (module docstring): feed each frame's segmentation
    to :meth:`see`; it returns the box to guide the next frame onto
    (:meth:`capture.segment.Segmenter.apply`) when the track should move to another person,
    else None. ``switches`` counts the moves, ``note`` says the last; ``held`` is
    :func:`held_walker` of the frames of the last look back; ``since`` is, after a move, the first
    frame (``index`` given to :meth:`see`) of those it judged the track on someone else in (since it
    left the walker's path, or since the path began): from there to the move it was not the walker's."""

    def __init__(self, settings: SegmentSettings, *, window: int = LIVE_WINDOW, every: int = LIVE_EVERY) -> None:
        if window < 2 or every < 1:
            raise ValueError(f"window must be >= 2 and every >= 1, got {window} and {every}")
        self.settings, self.every = settings, every
        self._recent: collections.deque[Segmentation | None] = collections.deque(maxlen=window)
        self._indices: collections.deque[int] = collections.deque(maxlen=window)
        self._since = 0
        self.switches = 0
        self.since: int | None = None
        self.note: str | None = None
        self.held: str | None = None  # held_walker() of the last look back

    def see(self, seg: Segmentation | None, index: int | None = None) -> Box | None:
        """Take the frame ``index`` (default: one after the last); the box to move the track onto, or None."""
        self._indices.append(index if index is not None else (self._indices[-1] + 1 if self._indices else 0))
        self._recent.append(seg)
        self._since += 1
        if self._since < self.every or len(self._recent) < 2 * self.every:
            return None
        self._since = 0
        recent, indices = list(self._recent), list(self._indices)
        self.held = held_walker(recent)
        size = next((s.image_size for s in recent if s is not None), None)
        if self.settings.walker_choice == "first" or size is None:
            return None
        walker, first, agree = _followed(recent, size)
        gone = next((t for t in range(len(recent) - 1, -1, -1) if walker[t] is not None), -1) + 1
        if len(recent) - gone >= 2 * self.every:  # the path ended a while ago (they left): choose among the rest
            recent, indices = recent[gone:], indices[gone:]
            walker, first, agree = _followed(recent, size)
        if walker[-1] is None or agree[-1]:  # the walker not in the newest frame, or the track on them
            return None
        # Judged on the frames since the track left the path, or since the path began (someone who
        # came into view): a track that followed the walker for most of the look back and then
        # someone else moves as soon.
        began = next(t for t, b in enumerate(walker) if b is not None)
        left = max(began, next((t + 1 for t in range(len(recent) - 1, -1, -1) if agree[t]), 0))
        if len(recent) - left < LIVE_OFF or _gain(recent[left:], walker[left:], first[left:], size) < MARGIN:
            return None
        followed = [b[3] for b in first[left:] if b is not None]
        if followed and np.median([b[3] for b in walker[left:] if b is not None]) < LIVE_SHORTER * np.median(followed):
            return None
        self.switches += 1
        self.since = indices[left]  # what was judged: before the path began, the walker was not in view
        self.note = _note(recent, _agreed(walker, agree), "the track moved to it")
        return walker[-1]


HELD_TRAVEL = 0.5  # the walker's box centre crosses less than this many of its heights (p10-p90): held in place


def held_walker(segs: list[Segmentation | None]) -> str | None:
    """A note when the walker stayed in about the same place in the image over a clip (or the
    frames a live agent looks back over) whose background was learned from it, else None.

    A walker who walks towards or away from the camera and is in view in most
    of the frames the median is taken over is in the median: only the outline
    where they grew or shrank differs from it, and the silhouettes are partial
    (docs/ROBUSTNESS.md, "A walker held in the background": on the composite
    walks such cameras had a mean IoU of 0.60-0.68 against 0.84-0.95). Read from
    the segmentation itself: boxes in at least half of the frames whose centres
    cross less than ``HELD_TRAVEL`` of the box height between their 10th and
    90th percentiles.
    """
    travel = _travel(walker_boxes(segs))
    if travel is None or travel >= HELD_TRAVEL:
        return None
    return (f"the walker stayed in about the same place in the image (crossed {travel:.2f} of their height) "
            "in most of the clip, so the background learned from it holds them and their silhouettes are "
            "partial: give an image of the empty scene (<camera>.background.png beside a video, posecal "
            "capture --background-image), or record from before the walker comes into view")


def held_path(segs: list[Segmentation | None]) -> bool:
    """Whether the walker's path chosen through the candidates of ``segs`` (:func:`choose`, not the person
    the track followed) stayed in place as :func:`held_walker` reads it: against an image of the empty scene
    a walker held in the clip's background shows whole, where the clip's own pass may have followed someone
    crossing the view (docs/ROBUSTNESS.md, "A walker held in the background, behind a passer-by")."""
    size = next((s.image_size for s in segs if s is not None), None)
    if size is None:
        return False
    travel = _travel(choose([() if s is None else s.candidates for s in segs], size))
    return travel is not None and travel < HELD_TRAVEL


def _travel(boxes: list[Box | None]) -> float | None:
    """How far the boxes' centres cross (p10-p90) in their median heights, None where fewer than half of the
    frames (and 5) have one."""
    b = np.array([(x + w / 2, h) for x, _, w, h in filter(None, boxes)], float)
    if len(b) < max(5, len(boxes) / 2):
        return None
    return float(np.subtract(*np.percentile(b[:, 0], [90, 10])) / np.median(b[:, 1]))
