"""Reduce each silhouette of a camera track to the walker before registration.

Registration (Izo–Grimson §5) scales, centres and rotates a silhouette by
*all* its foreground pixels: one speck far from the walker stretches the box
to the whole frame, a bystander or a shadow moves the centroid and the
principal axis, and the matched viewpoint goes with them (docs/ROBUSTNESS.md:
0.2 % salt noise took the median azimuth error from 2 to 86 deg). Real
segmenters leave exactly such damage, so every window is cleaned first:

1. **Components.** Each frame's 8-connected components; every component at
   least ``candidate`` of the frame's largest seeds a candidate walker, to
   which the components within ``reach`` of its height (a foot cut off at the
   ankle, a forearm split from the body) and larger than ``min_part`` of it
   are joined. Specks and blobs farther away belong to no candidate.
2. **Continuity.** One candidate per frame, chosen by dynamic programming
   over the window: a switch between candidates costs their displacement in
   walker heights and their change of size, so a bystander or a blob larger
   than the walker in one frame does not take over; size breaks the tie.
3. **Plausibility.** A frame is skipped (treated as missing, so it cannot
   drag the viewpoint) when its walker touches the image border (cut by it),
   when its height differs from the median of its neighbours by more than
   ``size_tolerance`` (merged with clutter, or torn), or when it is wider
   than ``max_aspect`` times its height.

4. **Below the feet** (:func:`trim_below_feet`, needs the appearance model's
   score). A shadow or floor reflection joined to the feet is part of the
   walker's component and of its box, and no test above sees it. The body
   model does: the silhouettes cut at a fraction of their height from the
   top are scored against the appearance clusters, and the camera's window
   is cut where the score is clearly best. A clean walker scores best uncut
   (every clean window measured), so the cut costs nothing there.

The choices and their thresholds are measured in docs/ROBUSTNESS.md; what was
discarded is reported per camera (:class:`CleanupReport`) and in a window's
``notes``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["CleanupConfig", "CleanupReport", "isolate_walker", "trim_below_feet"]


@dataclass(frozen=True)
class CleanupConfig:
    """Thresholds of :func:`isolate_walker` (fractions are of the walker's own size).

    Parameters
    ----------
    candidate : float
        A component at least this fraction of the frame's largest (by area)
        seeds a candidate walker.
    reach : float
        Components whose box lies within this fraction of the candidate's
        height from its box join it.
    min_part : float
        ... if their area is at least this fraction of the candidate's seed.
    switch_cost : float
        Weight of a candidate's displacement (in walker heights per frame)
        and size change (log ratio) between frames in the continuity choice.
    size_weight : float
        Weight of a candidate's area short of the frame's largest (a fraction)
        in the same choice: a tie-break, so that a walker partly out of view
        is not given up for a whole bystander.
    size_tolerance : float
        Skip frames whose height differs from the median of the
        ``neighbours`` frames on each side by more than this fraction.
    neighbours : int
    max_aspect : float
        Skip frames whose walker is wider than this many times its height.
    skip_border : bool
        Skip frames whose walker touches the image border (full-frame tracks
        with a known image size only).
    min_kept : float
        A test that would leave fewer than this fraction of the frames with a
        walker is not applied (a walker whose shadow always reaches the border
        is better used than lost); the report says so.
    cuts : tuple of float
        :func:`trim_below_feet`: fractions of the height, from the top, at
        which the silhouettes are cut and scored (1 = uncut).
    cut_gain : float
        ... a cut is made only if it lowers the median score by this fraction.
    cut_frames : int
        ... scored on at most this many frames of the window, evenly spaced.
    """

    candidate: float = 0.3
    reach: float = 0.12
    min_part: float = 0.005
    switch_cost: float = 2.0
    size_weight: float = 0.2
    size_tolerance: float = 0.25
    neighbours: int = 5
    max_aspect: float = 1.3
    skip_border: bool = True
    min_kept: float = 0.3
    cuts: tuple[float, ...] = (1.0, 0.92, 0.85, 0.79, 0.74, 0.69, 0.65, 0.61, 0.57)
    cut_gain: float = 0.1
    cut_frames: int = 8


@dataclass
class CleanupReport:
    """What :func:`isolate_walker` did to one camera's window."""

    frames: int = 0  # frames with any foreground
    kept: int = 0
    cleaned: int = 0  # kept frames from which other foreground was removed
    several: int = 0  # frames with more than one candidate walker
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> frames
    waived: list[str] = field(default_factory=list)  # tests not applied: they would skip too many
    cut: float = 1.0  # fraction of the height kept by trim_below_feet
    kept_mask: np.ndarray | None = None  # (T,) bool

    def note(self) -> str | None:
        """One line for a window's notes, or None when nothing was removed."""
        parts = []
        if self.cleaned:
            parts.append(f"other foreground (specks, blobs, people) removed on {self.cleaned} of {self.frames} frames")
        if self.several:
            parts.append(f"several candidate walkers on {self.several} frames, the continuous one kept")
        for reason, n in sorted(self.skipped.items()):
            parts.append(f"{n} frames skipped ({reason})")
        for reason in self.waived:
            parts.append(f"most frames {reason}: kept all the same")
        if self.cut < 1.0:
            parts.append(f"cut at {self.cut:.0%} of its height: the rest below the feet did not fit a walker "
                         "(a shadow or reflection)")
        return "; ".join(parts) if parts else None


@dataclass
class _Candidate:
    box: np.ndarray  # (x, y, w, h) in the silhouette's pixels
    area: int
    ids: list[int]
    at: np.ndarray  # (x, y) of the silhouette in the full frame: box + at is where it is


def _gaps(boxes: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Chebyshev distance of each (x, y, w, h) box to box ``b`` (0 where they overlap)."""
    dx = np.maximum(np.maximum(boxes[:, 0] - (b[0] + b[2]), b[0] - (boxes[:, 0] + boxes[:, 2])), 0)
    dy = np.maximum(np.maximum(boxes[:, 1] - (b[1] + b[3]), b[1] - (boxes[:, 1] + boxes[:, 3])), 0)
    return np.maximum(dx, dy)


def _union(boxes: np.ndarray) -> np.ndarray:
    x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
    x1, y1 = (boxes[:, 0] + boxes[:, 2]).max(), (boxes[:, 1] + boxes[:, 3]).max()
    return np.array([x0, y0, x1 - x0, y1 - y0], float)


def _candidates(stats: np.ndarray, at: np.ndarray, config: CleanupConfig) -> list[_Candidate]:
    """Candidate walkers of one frame from its component statistics (row 0 = background)
    of a silhouette whose top-left corner is at ``at`` in the full frame."""
    boxes = stats[1:, :4].astype(float)
    areas = stats[1:, cv2.CC_STAT_AREA]
    if areas.size == 0:
        return []
    seeds = np.flatnonzero(areas >= config.candidate * areas.max())
    seeds = seeds[np.argsort(-areas[seeds])]
    out = []
    for s in seeds:
        near = (areas >= config.min_part * areas[s]) & (_gaps(boxes, boxes[s]) <= config.reach * boxes[s, 3])
        near[s] = True
        ids = np.flatnonzero(near)
        out.append(_Candidate(_union(boxes[ids]), int(areas[ids].sum()), (ids + 1).tolist(), at))
    return out


def _centres(cands: list[_Candidate]) -> np.ndarray:
    """(x, y, height) of each candidate's box centre in the full frame."""
    return np.array([[k.at[0] + k.box[0] + k.box[2] / 2, k.at[1] + k.box[1] + k.box[3] / 2, k.box[3]]
                     for k in cands])


def _choose(cands: list[list[_Candidate]], config: CleanupConfig) -> list[int]:
    """One candidate index per frame (-1 where none): the cheapest path (Viterbi)."""
    frames = [t for t, c in enumerate(cands) if c]
    choice = [-1] * len(cands)
    if not frames:
        return choice
    cost = None
    back = []
    prev_t = None
    for t in frames:
        c = cands[t]
        amax = max(k.area for k in c)
        unary = config.size_weight * np.array([1.0 - k.area / amax for k in c])
        if cost is None:
            cost = unary
        else:
            p = cands[prev_t]
            gap = t - prev_t
            pc, cc = _centres(p), _centres(c)
            h = np.maximum(0.5 * (pc[:, None, 2] + cc[None, :, 2]), 1.0)
            move = np.hypot(pc[:, None, 0] - cc[None, :, 0], pc[:, None, 1] - cc[None, :, 1]) / h / gap
            size = np.abs(np.log(np.maximum(cc[None, :, 2], 1) / np.maximum(pc[:, None, 2], 1)))
            total = cost[:, None] + config.switch_cost * (move + size)
            back.append(np.argmin(total, axis=0))
            cost = total.min(axis=0) + unary
        prev_t = t
    k = int(np.argmin(cost))
    for i in range(len(frames) - 1, -1, -1):
        choice[frames[i]] = k
        if i:
            k = int(back[i - 1][k])
    return choice


def _neighbour_median(values: np.ndarray, present: np.ndarray, n: int) -> np.ndarray:
    """Median of ``values`` over the ``n`` present frames on each side (the frame itself excluded)."""
    idx = np.flatnonzero(present)
    out = np.full(len(values), np.nan)
    for j, t in enumerate(idx):
        near = np.concatenate([idx[max(0, j - n):j], idx[j + 1:j + 1 + n]])
        if near.size:
            out[t] = np.median(values[near])
    return out


def isolate_walker(silhouettes: list[np.ndarray | None], boxes: np.ndarray, *,
                   image_size: tuple[int, int] | None = None,
                   config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, CleanupReport]:
    """The walker alone in each frame of one camera's window.

    Parameters
    ----------
    silhouettes : list of (ndarray of shape (h, w), uint8, or None)
        Per frame the silhouette crop (any non-zero pixel is foreground).
    boxes : ndarray of shape (T, 4)
        Each crop's ``(x, y, w, h)`` in the full frame (or in its own pixels).
    image_size : (int, int), optional
        ``(width, height)`` of the full frame; enables the border test.
    config : CleanupConfig, optional

    Returns
    -------
    silhouettes : list
        Tight crops of the walker's components, None for frames without one
        or skipped.
    boxes : ndarray of shape (T, 4)
        Their boxes in the same coordinates as the input's, NaN where None.
    report : CleanupReport
    """
    config = config or CleanupConfig()
    T = len(silhouettes)
    boxes = np.asarray(boxes, float)
    labelled: list[tuple[np.ndarray, np.ndarray] | None] = []
    cands: list[list[_Candidate]] = []
    for t, sil in enumerate(silhouettes):
        if sil is None or sil.size == 0:
            labelled.append(None)
            cands.append([])
            continue
        n, labels, stats, _ = cv2.connectedComponentsWithStats((sil > 0).view(np.uint8), connectivity=8)
        labelled.append((labels, stats))
        at = boxes[t, :2] if np.all(np.isfinite(boxes[t, :2])) else np.zeros(2)
        cands.append(_candidates(stats, at, config))
    choice = _choose(cands, config)
    report = CleanupReport(frames=sum(1 for c in cands if c))
    out_sils: list[np.ndarray | None] = [None] * T
    out_boxes = np.full((T, 4), np.nan)
    for t, k in enumerate(choice):
        if k < 0:
            continue
        labels, stats = labelled[t]
        c = cands[t][k]
        report.several += len(cands[t]) > 1
        x, y, w, h = (int(v) for v in c.box)
        sub = labels[y:y + h, x:x + w]
        keep = np.isin(sub, c.ids)
        report.cleaned += int(len(stats) - 1 > len(c.ids))
        out_sils[t] = np.where(keep, np.uint8(255), np.uint8(0))
        out_boxes[t] = [boxes[t, 0] + x, boxes[t, 1] + y, w, h]
    present = np.isfinite(out_boxes[:, 0])
    reasons = np.full(T, "", dtype=object)
    need = config.min_kept * present.sum()

    def flag(bad: np.ndarray, reason: str) -> None:
        bad = bad & (reasons == "")
        if (present & (reasons == "") & ~bad).sum() >= need:
            reasons[bad] = reason
        elif bad.any():
            report.waived.append(reason)

    b = out_boxes
    if image_size is not None and config.skip_border:
        W, H = image_size
        flag(present & ((b[:, 0] <= 0) | (b[:, 1] <= 0) | (b[:, 0] + b[:, 2] >= W) | (b[:, 1] + b[:, 3] >= H)),
             "cut by the image border")
    flag(present & (b[:, 2] > config.max_aspect * b[:, 3]), "wider than a walker")
    ok = present & (reasons == "")
    med = _neighbour_median(b[:, 3], ok, config.neighbours)
    flag(ok & np.isfinite(med) & (np.abs(b[:, 3] / np.where(np.isfinite(med), med, 1.0) - 1.0)
                                  > config.size_tolerance),
         "size unlike its neighbours: merged with clutter or torn")
    for t in np.flatnonzero(present & (reasons != "")):
        report.skipped[reasons[t]] = report.skipped.get(reasons[t], 0) + 1
        out_sils[t] = None
        out_boxes[t] = np.nan
    report.kept_mask = np.isfinite(out_boxes[:, 0])
    report.kept = int(report.kept_mask.sum())
    return out_sils, out_boxes, report


def trim_below_feet(silhouettes: list[np.ndarray | None], boxes: np.ndarray,
                    score: Callable[[list[np.ndarray]], np.ndarray], *,
                    config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, float]:
    """Cut a shadow or reflection joined to the feet off one camera's window.

    Every frame's silhouette is cut at each fraction of ``config.cuts`` of its
    height (from the top), ``score`` (lower = more like a walker, e.g. the
    eq. 8 distance to the nearest appearance cluster) rates the cut
    silhouettes of up to ``cut_frames`` frames, and the fraction with the
    lowest median score wins if it beats the uncut silhouettes by
    ``cut_gain``. One fraction serves the window: a shadow keeps its length
    relative to the walker over the second or two a window lasts (a window's
    median height would not do: a walker nearing a camera grows).

    Returns the silhouettes (tight crops), their boxes and the fraction kept.
    """
    config = config or CleanupConfig()
    present = [t for t, s in enumerate(silhouettes) if s is not None]
    if not present:
        return silhouettes, boxes, 1.0
    sample = [silhouettes[t] for t in np.array(present)[np.linspace(0, len(present) - 1,
                                                                  min(config.cut_frames, len(present))).astype(int)]]
    cuts = np.asarray(config.cuts, float)
    medians = np.array([np.median(score([s[:max(1, round(f * s.shape[0]))] for s in sample])) for f in cuts])
    uncut = medians[cuts == 1.0].min() if (cuts == 1.0).any() else np.inf
    best = int(np.argmin(medians))
    if not medians[best] < (1.0 - config.cut_gain) * uncut:
        return silhouettes, boxes, 1.0
    f = float(cuts[best])
    out, out_boxes = list(silhouettes), np.array(boxes, float)
    for t in present:
        s = silhouettes[t]
        rows = np.flatnonzero(s[:max(1, round(f * s.shape[0]))].any(axis=1))
        cols = np.flatnonzero(s[:rows[-1] + 1].any(axis=0))
        out[t] = s[:rows[-1] + 1, cols[0]:cols[-1] + 1]
        out_boxes[t] = [boxes[t, 0] + cols[0], boxes[t, 1], cols[-1] + 1 - cols[0], rows[-1] + 1]
    return out, out_boxes, f
