"""Reduce each silhouette of a camera track to the walker before registration.

Registration (Izo–Grimson §5) scales, centres and rotates a silhouette by
*all* its foreground pixels: one speck far from the walker stretches the box
to the whole frame, a bystander or a shadow moves the centroid and the
principal axis, and the matched viewpoint goes with them (docs/ROBUSTNESS.md:
0.2 % salt noise took the median azimuth error from 2 to 86 deg). Real
segmenters leave exactly such damage, so every window is cleaned first, one
function per stage (:func:`estimator.pipeline.clean_tracks` runs them in
this order):

1. **Components** (:func:`select_walker`). Each frame's 8-connected
   components larger than ``min_part`` of its largest are grouped, largest
   first: a group takes the components within ``reach`` of its height from
   its box (``stack_reach`` for those above or below it: the pieces of a
   walker torn by a hole at the hip or a cut shin are stacked), at least the
   window's walker height, and grows until none is in reach. Groups of at
   least ``candidate`` of the largest are candidate walkers; specks and
   blobs farther away belong to none.
2. **Continuity** (same function). One candidate per frame, chosen by
   dynamic programming over the window: a switch between candidates costs
   their displacement in walker heights and their change of size, so a
   bystander or a blob larger than the walker in one frame does not take
   over; size breaks the tie.
3. **Below or beside the feet** (:func:`trim_shadow`, with the appearance
   model's score). A shadow or floor reflection joined to the feet is part
   of the walker's component and of its box, and no test above sees it. The
   body model does: the silhouettes cut at fractions of their height from
   the top (:func:`trim_below_feet`), or with the legs cut free of what lies
   a few tenths of the height to one side of the upper body
   (:func:`trim_beside_feet`: a low light at the walker's side casts the
   shadow away from the camera, rising from the feet beside the legs, which
   no row cut removes without them), are scored against the appearance
   examples; a window whose frames, cut one way, score clearly better is cut
   that way, each frame where its own score is best. A window that ends in a
   straight cut and fits better made up below it is taken to hide the
   walker's lowest part (:func:`hidden_feet`: a low wall in front), as is
   one whose walker stands on the image's bottom edge
   (:func:`on_bottom_edge`); such a walker is matched by its visible part
   (:mod:`estimator.occlusion`).
4. **Plausibility** (:func:`check_plausible`, after the cut). A frame is
   skipped (treated as missing, so it cannot drag the viewpoint) when its
   walker touches the image border (cut by it), when its height differs
   from the median of its neighbours by more than ``size_tolerance``
   (merged with clutter, or torn), or when it is wider than ``max_aspect``
   times its height.

:func:`isolate_walker` is stages 1, 2 and 4 (no model). The choices and
their thresholds are measured in docs/ROBUSTNESS.md; what was discarded is
reported per camera (:class:`CleanupReport`) and in a window's ``notes``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["CleanupConfig", "CleanupReport", "bounding_box", "check_plausible", "isolate_walker", "select_walker",
           "trim_below_feet", "trim_beside_feet", "trim_shadow", "hidden_feet", "fixed_edge", "astride_edge",
           "edge_share", "on_bottom_edge"]


@dataclass(frozen=True)
class CleanupConfig:
    """Thresholds of :func:`isolate_walker` (fractions are of the walker's own size).

    Parameters
    ----------
    candidate : float
        A group of components at least this fraction of the frame's largest
        group (by area) is a candidate walker.
    reach : float
        Components whose box lies within this fraction of a group's height
        (at least the window's median walker height) from its box join it ...
    stack_reach : float
        ... or within this fraction above or below it (overlapping it
        horizontally): the pieces of a torn walker.
    min_part : float
        Components smaller than this fraction of the frame's largest join no group.
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
    cut_frames : int
        ... on at most this many frames of the window, evenly spaced.
    cut_near : float
        ... each of them cut at its best within this fraction of its height
        of a straight line (over time) through their best cuts, or uncut;
    cut_gain : float
        ... the window is cut only if that lowers their summed score by this
        fraction of the uncut silhouettes'.
    cut_steps : tuple of float
        ... then every frame is cut at the best of these relative changes of
        the walker's length on that line (or not at all).
    cut_search : float
        The cuts are searched only when the sampled frames' median uncut
        score exceeds this (``walker_score``: eq. 8 pixels of the 64x48
        canvas). Measured over 12 walks x 9 damages (docs/ROBUSTNESS.md):
        clean, speckled, blotted walkers and a second person 22-83, holes
        and a cut limb 70-146 (searched, not cut), a shadow at the feet
        116-252; the search is 9 times the scoring, most of a clean window's
        clean-up. The same gate opens :func:`trim_beside_feet`'s search.
    side_cuts : tuple of float
        :func:`trim_beside_feet`: offsets, in fractions of the height, from
        the upper body's middle column beyond which the lower part of the
        silhouette is cut off on one side.
    side_from : float
        ... the lower part: rows below this fraction of the height from the
        top (the shadow of a low light rises at most about a third of the
        height from the feet; the arms stay above).
    side_gain : float
        ... the window is cut only if that lowers the sampled frames' summed
        score by this fraction of the uncut silhouettes'. Higher than
        ``cut_gain``: narrower legs fit the examples better on any real
        walker (on vtest.avi's walkers, 41-106 px tall, the gain reached 0.20-0.31
        on 12 of 29 windows, none with a visible shadow beside the legs),
        while a shadow cast 0.4-1 height sideways gained 0.47-0.87
        (docs/ROBUSTNESS.md, "A shadow cast sideways").
    hidden : tuple of float
        :func:`hidden_feet`: fractions of a whole body's height that may be
        hidden below the silhouette (its last row repeated downwards to make
        them up, and scored) ...
    hidden_flat : float
        ... tried only when, in the median sampled frame, at least this
        fraction of the columns of the lowest tenth of the silhouette end
        on its bottom row (a straight cut: 61-89 % on the damage model's
        walls, at most 45 % on every other damage) ...
    hidden_gain : float
        ... and reported when the best fraction lowers the sampled frames'
        summed score by this fraction of the silhouettes' own (walls on
        bench/eval_damage.py's seed 7: 0.26-0.74, bar one camera at 0.12;
        vtest.avi's walkers that end as flat, cut by nothing: 0.18).
    fixed_share, fixed_frames : float, int
        :func:`fixed_edge`: a camera's silhouettes end on an edge fixed in the
        image (a wall's top, the frame's bottom) when at least this share of
        the frames with one, and this many, end within a row of the same image
        row and end flat there (``hidden_flat``). A walker's feet move down or
        up the image as they near or recede and lift in every step; a wall's
        edge does not. Less than all the frames: a walker passes behind a
        bench or the end of a wall for part of a window.
    fixed_rows : int
        ... and only where a tenth of the median height of the frames on that
        row is at least this many pixel rows (a visible part of 60 px and
        more): below, a flat foot ends within a row of the bottom in most of
        the lowest tenth's columns as a straight cut does, and a small walker
        at one depth rests it on one row all the window, shorter than their
        other frames by a row or two where they have some
        (``bench/profile_window.py``'s side views of 27-47 px: 35 of 336
        windows x cameras; docs/ROBUSTNESS.md, "Flat feet on one row").
    edge_agree : float
        A walker behind the end of a fixed edge on some frames and whole on
        the others is taken as hidden only when the share the examples find
        (``hidden_matched``) and the share the whole frames' heights imply
        (:func:`edge_share`) agree within this: on ``vtest.avi`` a 60 px
        walker whose feet rested on one row for 8 frames fitted the examples
        best at 0.4, their heights said under 0.15.
    hidden_matched : tuple of float
        Fractions of the body searched for a walker hidden below (by
        something in front, as above, or by the image's bottom edge), which is
        then matched by its visible part (:mod:`estimator.occlusion`); if 0
        fits best, nothing is taken to be hidden (a shadow that reaches the
        bottom edge, or feet that only end flat).
    """

    candidate: float = 0.3
    reach: float = 0.12
    min_part: float = 0.005
    stack_reach: float = 0.25
    switch_cost: float = 2.0
    size_weight: float = 0.2
    size_tolerance: float = 0.25
    neighbours: int = 5
    max_aspect: float = 1.3
    skip_border: bool = True
    min_kept: float = 0.3
    cuts: tuple[float, ...] = (1.0, 0.92, 0.85, 0.79, 0.74, 0.69, 0.65, 0.61, 0.57)
    cut_gain: float = 0.2
    cut_near: float = 0.08
    cut_frames: int = 8
    cut_steps: tuple[float, ...] = (-0.06, -0.03, 0.0, 0.03, 0.06)
    cut_search: float = 95.0
    side_cuts: tuple[float, ...] = (0.12, 0.16, 0.2, 0.25, 0.3, 0.4)
    side_from: float = 0.5
    side_gain: float = 0.4
    hidden: tuple[float, ...] = (0.15, 0.25, 0.35, 0.45)
    hidden_flat: float = 0.6
    hidden_gain: float = 0.25
    fixed_share: float = 0.25
    fixed_frames: int = 6
    fixed_rows: int = 6
    edge_agree: float = 0.15
    hidden_matched: tuple[float, ...] = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)


@dataclass
class CleanupReport:
    """What the clean-up did to one camera's window."""

    frames: int = 0  # frames with any foreground
    kept: int = 0
    cleaned: int = 0  # kept frames from which other foreground was removed
    several: int = 0  # frames with more than one candidate walker
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> frames
    waived: list[str] = field(default_factory=list)  # tests not applied: they would skip too many
    cut: int = 0  # frames cut by trim_below_feet
    cut_kept: float = 1.0  # median fraction of their height kept
    side_cut: int = 0  # frames cut by trim_beside_feet
    hidden: float = 0.0  # the share of the body hidden below the silhouettes (estimator.occlusion)
    hidden_by: str = ""  # what hides it: "something in front" (hidden_feet) or "the image's bottom edge"
    on_edge: np.ndarray | None = None  # (T,) bool: frames ending on an edge fixed in the image (fixed_edge)
    astride: np.ndarray | None = None  # (T,) bool: frames with a part ending on that edge only (astride_edge)
    kept_mask: np.ndarray | None = None  # (T,) bool

    @property
    def fixed_edge(self) -> bool:
        """Whether some frames end on an edge fixed in the image (:func:`fixed_edge`)."""
        return self.on_edge is not None and bool(self.on_edge.any())

    def past_edge(self, *, half: bool = True) -> np.ndarray | None:
        """(T,) bool: behind an edge fixed in the image, the kept frames that show the walker whole
        (past its end: neither on it nor astride it), with ``half`` only when they are at least
        half of the kept frames; else None. Fewer lie at one end of the window, within a gait cycle
        whose bob passes for a growth (on seed 13's ``fixed_wall`` walks 7-16 such frames took 2
        cameras to the wrong side that the head alone kept right), and their heights' line says
        little of the frames behind the edge."""
        if not self.fixed_edge:
            return None
        kept = np.ones_like(self.on_edge) if self.kept_mask is None else self.kept_mask
        whole = kept & ~self.on_edge & (True if self.astride is None else ~self.astride)
        return whole if not half or whole.sum() >= 0.5 * kept.sum() else None

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
        if self.side_cut:
            parts.append(f"cut beside the feet on {self.side_cut} frames: what lay to one side of the legs did not "
                         "fit a walker (a shadow cast sideways)")
        if self.hidden_by:
            edge = int(self.on_edge.sum()) if self.fixed_edge else 0
            why = ("the walker stands on it" if self.hidden_by == "the image's bottom edge" else
                   f"{edge} of {self.frames} frames end on one image row, in a straight cut: a low wall, a bench "
                   "or a car?" if edge else "the silhouettes end in a straight cut, and fit the examples better made "
                   "up below it: a low wall, a bench or a car?")
            parts.append(f"the walker's lowest {self.hidden:.0%} looks hidden by {self.hidden_by} ({why}); matched "
                         "by the visible part (docs/ROBUSTNESS.md, \"A walker hidden below\")")
        if self.cut:
            parts.append(f"cut below the feet on {self.cut} frames (median {self.cut_kept:.0%} of the height kept): "
                         "the rest did not fit a walker (a shadow or reflection)")
        return "; ".join(parts) if parts else None


@dataclass
class _Candidate:
    box: np.ndarray  # (x, y, w, h) in the silhouette's pixels
    area: int
    ids: list[int]
    at: np.ndarray  # (x, y) of the silhouette in the full frame: box + at is where it is


def _gaps(boxes: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal and vertical gap of each (x, y, w, h) box to box ``b`` (0 where they overlap)."""
    dx = np.maximum(np.maximum(boxes[:, 0] - (b[0] + b[2]), b[0] - (boxes[:, 0] + boxes[:, 2])), 0)
    dy = np.maximum(np.maximum(boxes[:, 1] - (b[1] + b[3]), b[1] - (boxes[:, 1] + boxes[:, 3])), 0)
    return dx, dy


def bounding_box(boxes) -> np.ndarray:
    """The ``(x, y, w, h)`` box around ``(x, y, w, h)`` boxes (rows), of their dtype."""
    boxes = np.asarray(boxes)
    x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
    x1, y1 = (boxes[:, 0] + boxes[:, 2]).max(), (boxes[:, 1] + boxes[:, 3]).max()
    return np.array([x0, y0, x1 - x0, y1 - y0], boxes.dtype)


def _candidates(stats: np.ndarray, at: np.ndarray, config: CleanupConfig,
                height: float = 0.0) -> list[_Candidate]:
    """Candidate walkers of one frame from its component statistics (row 0 = background)
    of a silhouette whose top-left corner is at ``at`` in the full frame.

    The components of at least ``min_part`` of the largest are grouped, largest
    first: a group takes every free component within ``reach`` of its height
    (at least ``height``, the walker's in the window) from its box, or within
    ``stack_reach`` of it above or below it, and grows until none is left in
    reach (a walker torn into several pieces by holes or a cut limb is put
    back together, whichever piece is largest). Groups of at least
    ``candidate`` of the largest group's area are the candidates.
    """
    boxes = stats[1:, :4].astype(float)
    areas = stats[1:, cv2.CC_STAT_AREA].astype(float)
    if areas.size == 0:
        return []
    if areas.size == 1:  # one piece (most frames): the grouping below would find it alone
        return [_Candidate(boxes[0], int(areas[0]), [1], at)]
    free = areas >= config.min_part * areas.max()
    groups = []
    for s in np.argsort(-areas, kind="stable"):
        if not free[s]:
            if areas[s] < config.min_part * areas.max():
                break  # sorted: only specks are left
            continue
        free[s] = False
        ids, box = [int(s)], boxes[s]
        while True:
            dx, dy = _gaps(boxes, box)
            scale = max(box[3], height)
            near = free & ((np.maximum(dx, dy) <= config.reach * scale)
                           | ((dx <= 0) & (dy <= config.stack_reach * scale)))
            if not near.any():
                break
            free &= ~near
            ids += np.flatnonzero(near).tolist()
            box = bounding_box(boxes[ids])
        groups.append(_Candidate(box, int(areas[ids].sum()), [i + 1 for i in ids], at))
    largest = max(g.area for g in groups)
    return [g for g in groups if g.area >= config.candidate * largest]


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
    if all(len(cands[t]) == 1 for t in frames):  # nothing to choose between
        return [0 if c else -1 for c in cands]
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


def _components(sil: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """8-connected component labels of a silhouette and their statistics (row 0 = background),
    as ``cv2.connectedComponentsWithStats`` gives them; a silhouette of one piece (most
    frames) is labelled without the statistics pass, which costs several times the labelling."""
    mask = (sil > 0).view(np.uint8)
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    if n != 2:
        return cv2.connectedComponentsWithStats(mask, connectivity=8)[1:3]
    x, y, w, h = cv2.boundingRect(mask)
    area = cv2.countNonZero(mask)
    return labels, np.array([[0, 0, mask.shape[1], mask.shape[0], mask.size - area], [x, y, w, h, area]], np.int32)


def select_walker(silhouettes: list[np.ndarray | None], boxes: np.ndarray, *,
                  config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, CleanupReport]:
    """Stages 1 and 2: each frame's candidate walkers, and one of them per frame.

    Parameters and returns as :func:`isolate_walker`; no frame is skipped.
    """
    config = config or CleanupConfig()
    T = len(silhouettes)
    boxes = np.asarray(boxes, float)
    if boxes.shape != (T, 4):
        raise ValueError(f"boxes must have shape ({T}, 4), got {boxes.shape}")
    labelled: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
    cands: list[list[_Candidate]] = []
    for t, sil in enumerate(silhouettes):
        if sil is None or sil.size == 0:
            labelled.append(None)
            cands.append([])
            continue
        labels, stats = _components(sil)
        at = boxes[t, :2] if np.all(np.isfinite(boxes[t, :2])) else np.zeros(2)
        labelled.append((labels, stats, at))
        cands.append(_candidates(stats, at, config))
    # A walker torn on one frame is whole on others: group again with the window's height
    # (the median of each frame's tallest candidate) as the least reach.
    tallest = [max(k.box[3] for k in c) for c in cands if c]
    if tallest:
        height = float(np.median(tallest))
        cands = [[] if lab is None else _candidates(lab[1], lab[2], config, height) for lab in labelled]
    choice = _choose(cands, config)
    report = CleanupReport(frames=sum(1 for c in cands if c))
    out_sils: list[np.ndarray | None] = [None] * T
    out_boxes = np.full((T, 4), np.nan)
    for t, k in enumerate(choice):
        if k < 0:
            continue
        labels, stats, _ = labelled[t]
        c = cands[t][k]
        report.several += len(cands[t]) > 1
        x, y, w, h = (int(v) for v in c.box)
        part = labels[y:y + h, x:x + w]
        keep = part != 0 if len(c.ids) == len(stats) - 1 else np.isin(part, c.ids)
        report.cleaned += int(len(stats) - 1 > len(c.ids))
        out_sils[t] = np.where(keep, np.uint8(255), np.uint8(0))
        out_boxes[t] = [boxes[t, 0] + x, boxes[t, 1] + y, w, h]
    report.kept_mask = np.isfinite(out_boxes[:, 0])
    report.kept = int(report.kept_mask.sum())
    return out_sils, out_boxes, report


def check_plausible(silhouettes: list[np.ndarray | None], boxes: np.ndarray, report: CleanupReport, *,
                    image_size: tuple[int, int] | None = None,
                    config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, CleanupReport]:
    """Stage 4: skip the frames whose walker is cut by the image border, wider than a
    walker, or of a size unlike its neighbours'; ``report`` is updated in place.

    Run it on the walker alone (after :func:`trim_below_feet`): a shadow that
    reaches the border does not cut the walker.
    """
    config = config or CleanupConfig()
    T = len(silhouettes)
    out_sils, out_boxes = list(silhouettes), np.array(boxes, float)
    present = np.isfinite(out_boxes[:, 0]) & np.array([s is not None for s in silhouettes], bool)
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


def isolate_walker(silhouettes: list[np.ndarray | None], boxes: np.ndarray, *,
                   image_size: tuple[int, int] | None = None,
                   config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, CleanupReport]:
    """The walker alone in each frame of one camera's window (stages 1-3, no model).

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
    sils, out, report = select_walker(silhouettes, boxes, config=config)
    return check_plausible(sils, out, report, image_size=image_size, config=config)


def _top_rows(sil: np.ndarray, rows: int) -> tuple[np.ndarray, int] | None:
    """The tight crop of a silhouette's first ``rows`` rows and its first column; None if empty."""
    top = sil[:max(1, rows)]
    r = np.flatnonzero(top.any(axis=1))
    if r.size == 0:
        return None
    c = np.flatnonzero(top[:r[-1] + 1].any(axis=0))
    return top[:r[-1] + 1, c[0]:c[-1] + 1], int(c[0])


def _line(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Theil-Sen line ``y ~ a + b t`` (median of the pairwise slopes; a few wrong points do not move it)."""
    if t.size < 2:
        return float(np.median(y)), 0.0
    i, j = np.triu_indices(t.size, 1)
    b = float(np.median((y[j] - y[i]) / (t[j] - t[i])))
    return float(np.median(y - b * t)), b


def trim_shadow(silhouettes: list[np.ndarray | None], boxes: np.ndarray,
                score: Callable[[list[np.ndarray]], np.ndarray], *, config: CleanupConfig | None = None
                ) -> tuple[list[np.ndarray | None], np.ndarray, np.ndarray, np.ndarray]:
    """Stage 3: cut a shadow or reflection joined to the feet off one camera's window, below the
    feet (:func:`trim_below_feet`) or beside them (:func:`trim_beside_feet`), whichever lowers
    the sampled frames' summed score more. One light casts one shadow: a cut below the feet
    would also take a sideways shadow, with the legs; a cut beside them, part of one cast
    towards the camera.

    Returns the silhouettes (tight crops), their boxes, the fraction of each frame's height
    kept below the feet (1 = uncut, NaN where no silhouette) and which frames were cut beside
    them.
    """
    return _trim(silhouettes, boxes, score, config or CleanupConfig(), ("below", "beside"))


def trim_below_feet(silhouettes: list[np.ndarray | None], boxes: np.ndarray,
                    score: Callable[[list[np.ndarray]], np.ndarray], *,
                    config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, np.ndarray]:
    """A shadow or reflection joined to the feet cut off one camera's window (part of stage 3).

    ``score`` rates silhouettes (lower = more like a walker: the eq. 8
    distance to the nearest appearance example, :func:`estimator.pipeline.walker_score`).

    1. **Where are the feet?** Up to ``cut_frames`` frames of the window,
       evenly spaced, are cut at each fraction ``cuts`` of their height (from
       the top) and scored; the walker's length from its top at those frames
       (their best cut) is a straight line over the window (Theil-Sen): the
       walker's size changes steadily, while the silhouette's own height does
       not when the shadow leaves the frame.
    2. **Is there anything below them?** Each of those frames is cut at its
       best within ``cut_near`` of the line (or not cut); the window is cut
       only if that lowers their summed score by ``cut_gain`` of the uncut
       silhouettes' (a clean or merely damaged walker scores best uncut on
       most frames, so its line is its own height and nothing is gained).
    3. **Per frame**, the best of the cuts at ``cut_steps`` around the line
       (and of the uncut silhouette): the lowest foot moves with the stride.

    Searched only when the sampled frames' median uncut score exceeds
    ``cut_search`` (a walker as the examples are has nothing to cut).

    Returns
    -------
    silhouettes, boxes
        The cut silhouettes (tight crops) and their boxes.
    kept : ndarray of shape (T,)
        Fraction of each frame's height kept (1 = uncut), NaN where no silhouette.
    """
    out, boxes, kept, _ = _trim(silhouettes, boxes, score, config or CleanupConfig(), ("below",))
    return out, boxes, kept


def trim_beside_feet(silhouettes: list[np.ndarray | None], boxes: np.ndarray,
                     score: Callable[[list[np.ndarray]], np.ndarray], *,
                     config: CleanupConfig | None = None) -> tuple[list[np.ndarray | None], np.ndarray, np.ndarray]:
    """A shadow cast sideways cut off the legs of one camera's window (part of stage 3).

    A low light at the walker's side, in front of them, casts their shadow
    away from the camera: in the image it starts at the feet and rises to one
    side, beside the legs, never below them, so :func:`trim_below_feet` could
    remove it only with the legs. Here the lower part of each silhouette (rows
    below ``side_from`` of its height) is cleared beyond an offset from the
    upper body's middle column (``side_cuts``, fractions of the height), on
    the left or on the right, and scored with ``score`` as there:

    1. **Which side?** On up to ``cut_frames`` frames, the side whose cuts
       (each frame's best, or uncut) sum to the lower score. A shadow keeps
       its side over seconds.
    2. **Is anything there?** The window is cut only if that lowers the
       frames' summed score by ``side_gain`` of the uncut silhouettes'.
    3. **Per frame**, the best of that side's cuts and of the uncut
       silhouette: the feet move with the stride.

    Searched only when the sampled frames' median uncut score exceeds
    ``cut_search``, as :func:`trim_below_feet`. Returns the silhouettes
    (tight crops), their boxes and which frames were cut.
    """
    out, boxes, _, beside = _trim(silhouettes, boxes, score, config or CleanupConfig(), ("beside",))
    return out, boxes, beside


def _trim(silhouettes: list[np.ndarray | None], boxes: np.ndarray, score: Callable[[list[np.ndarray]], np.ndarray],
          config: CleanupConfig, kinds: tuple[str, ...]
          ) -> tuple[list[np.ndarray | None], np.ndarray, np.ndarray, np.ndarray]:
    """The cut of ``kinds`` ("below", "beside") that gains most on the sampled frames, if it gains
    ``cut_gain`` (``side_gain`` beside the feet): the silhouettes, boxes, height kept below the
    feet, frames cut beside them."""
    boxes = np.array(boxes, float)
    present = np.array([t for t, s in enumerate(silhouettes) if s is not None], int)
    kept = np.full(len(silhouettes), np.nan)
    kept[present] = 1.0
    beside = np.zeros(len(silhouettes), bool)
    searched = _searched(silhouettes, present, score, config)
    if searched is None:
        return list(silhouettes), boxes, kept, beside
    plans = {"below": (_below_plan, config.cut_gain), "beside": (_beside_plan, config.side_gain)}
    best = None
    for k in kinds:
        plan, least = plans[k]
        g, p = plan(silhouettes, *searched, score, config)
        if g >= least and (best is None or g > best[0]):
            best = (g, k, p)
    if best is None:
        return list(silhouettes), boxes, kept, beside
    _, kind, plan = best
    if kind == "below":
        out, boxes, kept = _below_apply(silhouettes, boxes, present, plan, score, config)
    else:
        out, boxes, beside = _beside_apply(silhouettes, boxes, present, plan, score, config.side_from)
    return out, boxes, kept, beside


def evenly_spaced(n: int, k: int) -> np.ndarray:
    """Indices of up to ``k`` of ``n`` items, evenly spaced from the first to the last."""
    return np.unique(np.linspace(0, n - 1, min(k, n)).astype(int))


def _sample(present: np.ndarray, config: CleanupConfig) -> np.ndarray:
    """Up to ``cut_frames`` of the frames ``present``, evenly spaced."""
    return present[evenly_spaced(present.size, config.cut_frames)]


def _searched(silhouettes: list[np.ndarray | None], present: np.ndarray,
              score: Callable[[list[np.ndarray]], np.ndarray],
              config: CleanupConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The frames a cut search samples (up to ``cut_frames`` of ``present``, evenly spaced, with a
    score) and their uncut scores (column 0 of an (n, 1) array); None when there is nothing to
    search for: no frame, or a median uncut score within ``cut_search`` (a walker as the
    examples are)."""
    if present.size == 0:
        return None
    sample = _sample(present, config)
    uncut = _scores(score, [[_top_rows(silhouettes[t], silhouettes[t].shape[0])] for t in sample])
    ok = np.isfinite(uncut[:, 0])
    if not ok.any() or np.median(uncut[ok, 0]) <= config.cut_search:
        return None
    return sample[ok], uncut[ok]


def _below_plan(silhouettes: list[np.ndarray | None], sample: np.ndarray, uncut: np.ndarray,
                score: Callable[[list[np.ndarray]], np.ndarray], config: CleanupConfig
                ) -> tuple[float, tuple[float, float]]:
    """:func:`trim_below_feet`'s steps 1-2 on the sampled frames: the gain of the window's cut
    (its summed score's fall, a fraction of the uncut one's) and the line of the walker's length."""
    height = np.array([silhouettes[t].shape[0] for t in sample], float)
    cuts = np.unique(np.concatenate([[1.0], np.clip(config.cuts, 0.05, 1.0)]))[::-1]  # uncut first
    trials = [[_top_rows(silhouettes[t], round(f * h)) for f in cuts[1:]] for t, h in zip(sample, height)]
    scores = np.concatenate([uncut, _scores(score, trials)], axis=1)
    # The walker's length from its top on those frames (their best cut), a straight line over the window.
    a, b = _line(sample.astype(float), cuts[np.argmin(scores, axis=1)] * height)
    # Each frame cut near the line (or not at all).
    near = np.abs(cuts[None, :] - ((a + b * sample) / height)[:, None]) <= config.cut_near
    along = np.minimum(np.where(near, scores, np.inf).min(axis=1), scores[:, 0])
    return 1.0 - along.sum() / scores[:, 0].sum(), (a, b)


def _below_apply(silhouettes: list[np.ndarray | None], boxes: np.ndarray, present: np.ndarray,
                 line: tuple[float, float], score: Callable[[list[np.ndarray]], np.ndarray],
                 config: CleanupConfig) -> tuple[list[np.ndarray | None], np.ndarray, np.ndarray]:
    """:func:`trim_below_feet`'s step 3: every frame cut at its best near the ``line``."""
    height = np.array([s.shape[0] if s is not None else 0 for s in silhouettes], float)
    kept = np.where(height > 0, 1.0, np.nan)
    a, b = line
    rows = np.round((a + b * present)[:, None] * (1.0 + np.asarray(config.cut_steps, float))[None, :])
    rows = np.concatenate([rows, height[present, None]], axis=1)  # and the uncut silhouette
    rows = np.clip(rows, 1, height[present, None]).astype(int)
    trials = [[_top_rows(silhouettes[t], r) for r in rr] for t, rr in zip(present, rows)]
    scores = _scores(score, trials)
    best = np.argmin(np.where(np.isfinite(scores), scores, np.inf), axis=1)
    out = list(silhouettes)
    for t, k, trial in zip(present, best, trials):
        if trial[k] is None or rows[present == t, k][0] >= height[t]:
            continue
        crop, dx = trial[k]
        out[t] = crop
        boxes[t] = [boxes[t, 0] + dx, boxes[t, 1], crop.shape[1], crop.shape[0]]
        kept[t] = crop.shape[0] / height[t]
    return out, boxes, kept


def _side_trials(sil: np.ndarray, offsets: np.ndarray, from_row: float
                 ) -> list[list[tuple[np.ndarray, int, int] | None]]:
    """``sil`` with its rows below ``from_row`` of its height cleared beyond each of ``offsets``
    (pixels) from the upper body's middle column, on the left (first list) and on the right
    (second): tight crops with their first column and row, None where nothing is left."""
    h = sil.shape[0]
    start = int(round(from_row * h))
    upper = sil[int(0.15 * h):max(start, int(0.15 * h) + 1)]
    middle = float(np.median(np.nonzero(upper if upper.any() else sil)[1]))
    col = np.arange(sil.shape[1])
    out = []
    for side in (-1.0, 1.0):
        row = []
        for d in offsets:
            trial = sil.copy()
            trial[start:, side * (col - middle) > d] = 0
            r, c = np.flatnonzero(trial.any(axis=1)), np.flatnonzero(trial.any(axis=0))
            row.append(None if r.size == 0 else (trial[r[0]:r[-1] + 1, c[0]:c[-1] + 1], int(c[0]), int(r[0])))
        out.append(row)
    return out


def _beside_plan(silhouettes: list[np.ndarray | None], sample: np.ndarray, uncut: np.ndarray,
                 score: Callable[[list[np.ndarray]], np.ndarray], config: CleanupConfig
                 ) -> tuple[float, tuple[int, np.ndarray]]:
    """:func:`trim_beside_feet`'s steps 1-2 on the sampled frames: the gain of the window's cut on
    its better side, and that side (0 left, 1 right) with the offsets in fractions of the height."""
    fractions = np.asarray(config.side_cuts, float)
    n = fractions.size
    trials = [sum(_side_trials(silhouettes[t], fractions * silhouettes[t].shape[0], config.side_from), [])
              for t in sample]
    scores = _scores(score, trials)  # (frames, left cuts + right cuts)
    along = np.minimum(np.stack([scores[:, :n].min(axis=1), scores[:, n:].min(axis=1)]), uncut[:, 0])
    side = int(np.argmin(along.sum(axis=1)))
    return 1.0 - along[side].sum() / uncut[:, 0].sum(), (side, fractions)


def _beside_apply(silhouettes: list[np.ndarray | None], boxes: np.ndarray, present: np.ndarray,
                  plan: tuple[int, np.ndarray], score: Callable[[list[np.ndarray]], np.ndarray],
                  from_row: float) -> tuple[list[np.ndarray | None], np.ndarray, np.ndarray]:
    """:func:`trim_beside_feet`'s step 3: every frame cut at its best offset on the window's side."""
    side, fractions = plan
    every = [_side_trials(silhouettes[t], fractions * silhouettes[t].shape[0], from_row)[side] for t in present]
    scores = _scores(score, [[(silhouettes[t], 0, 0)] + row for t, row in zip(present, every)])
    best = np.argmin(np.where(np.isfinite(scores), scores, np.inf), axis=1)
    out = list(silhouettes)
    cut = np.zeros(len(silhouettes), bool)
    for t, k, row in zip(present, best, every):
        if k == 0:
            continue
        crop, dx, dy = row[k - 1]
        out[t] = crop
        boxes[t] = [boxes[t, 0] + dx, boxes[t, 1] + dy, crop.shape[1], crop.shape[0]]
        cut[t] = True
    return out, boxes, cut


def hidden_feet(silhouettes: list[np.ndarray | None], score: Callable[[list[np.ndarray]], np.ndarray], *,
                config: CleanupConfig | None = None) -> float:
    """The share of the walker's body that looks hidden below one camera's silhouettes (0: none).

    A walker behind a low wall, a bench or a car ends in a straight cut above
    the feet, and registration would place and scale that shorter body as a
    whole one (docs/ROBUSTNESS.md, "A walker hidden below"). On windows that
    :func:`trim_below_feet` would search (``cut_search``) and whose sampled
    frames end flat (``hidden_flat``), each is made up below by each
    fraction of ``hidden`` (its last row repeated) and scored; one fraction
    for the window, reported if it gains ``hidden_gain``. This only tells
    that something is hidden: the estimate matches the visible part
    (:mod:`estimator.occlusion`, which searches the fraction again); the
    made-up legs were tried as the mend and not kept (real walkers' viewpoints turned).
    """
    config = config or CleanupConfig()
    present = np.array([t for t, s in enumerate(silhouettes) if s is not None], int)
    if present.size == 0 or np.median([_flat_bottom(silhouettes[t]) for t in _sample(present, config)]) \
            < config.hidden_flat:
        return 0.0  # first, as it costs no scoring
    searched = _searched(silhouettes, present, score, config)
    if searched is None:
        return 0.0
    sample, uncut = searched
    fractions = np.asarray(config.hidden, float)
    trials = [[(np.concatenate([s, np.repeat(s[-1:], int(round(s.shape[0] * f / (1.0 - f))), axis=0)]),)
               for f in fractions] for s in (silhouettes[t] for t in sample)]
    along = np.minimum(_scores(score, trials), uncut[:, :1])  # (frames, fractions)
    k = int(np.argmin(along.sum(axis=0)))
    return float(fractions[k]) if 1.0 - along[:, k].sum() / uncut[:, 0].sum() >= config.hidden_gain else 0.0


def fixed_edge(silhouettes: list[np.ndarray | None], boxes: np.ndarray, *,
               config: CleanupConfig | None = None, shorter: float = 0.05) -> np.ndarray:
    """The frames of one camera whose silhouette ends on an edge fixed in the image: a wall's top,
    a car's bonnet or the frame's bottom, in front of the walker. (T,) bool, all False for none.

    A wall moves with nothing: the silhouettes behind it end on one image row
    (within a row of the commonest bottom row of the frames that end flat, on
    ``fixed_share`` of the frames with a box and ``fixed_frames`` at least)
    while the walker nears or recedes, and end flat there (their median
    frame's lowest tenth, ``hidden_flat``). Neither alone is enough: a walker
    seen from the side keeps their feet near one row, and feet in a shoe can
    end flat. The frames on it are one stretch of the window (gaps of up to 2
    frames): the walker passes behind a wall once. The frames off that row
    show the walker whole (they passed the wall's end), so they must not end
    flat as well (a cut that moves with the walker, ``low_wall``, can rest on
    one row for a few frames), and the frames on it must be shorter than the
    line of the others' heights over time says, by ``shorter`` in the median
    (a shadow's or a cut limb's flat bottom on a few frames is not; frames
    astride the wall's end, :func:`astride_edge`, are left out of the line);
    with fewer than 3 others, nothing is checked. The frames on it must be
    tall enough for their flatness to tell (``fixed_rows``). Give it the
    frames of a plausible walker only (:func:`check_plausible`): on
    ``vtest.avi`` a window whose 12 frames wider than a walker rested on
    one row was taken for a wall. Behind the edge the visible height is not
    the walker's size (it shrinks as a walker comes nearer to a camera that
    looks over the wall), so :func:`estimator.occlusion.hidden_shares` gives
    each such frame its own share, and :func:`estimator.viewpoint.motion_cue`
    reads the growth from the other frames and the head. ``boxes`` are the silhouettes'
    ``(x, y, w, h)`` in the full frame.
    """
    config = config or CleanupConfig()
    b = np.asarray(boxes, float)
    out = np.zeros(len(silhouettes), bool)
    present = np.array([t for t, s in enumerate(silhouettes) if s is not None and np.isfinite(b[t, 3])], int)
    if present.size < config.fixed_frames:
        return out
    bottom = np.round(b[present, 1] + b[present, 3]).astype(int)
    flat = np.array([_flat_bottom(silhouettes[t]) for t in present])
    if not np.any(flat >= config.hidden_flat):
        return out
    rows = bottom[flat >= config.hidden_flat]  # the edge's row: the commonest of the frames that end flat
    row = rows[int(np.argmax(np.sum(np.abs(rows[:, None] - rows[None, :]) <= 1, axis=1)))]
    on = np.abs(bottom - row) <= 1
    if on.sum() < max(config.fixed_frames, config.fixed_share * present.size):
        return out
    if np.median(flat[on]) < config.hidden_flat or 0.1 * np.median(b[present[on], 3]) < config.fixed_rows:
        return out  # not flat, or too few rows to tell a straight cut from flat feet
    if np.any(np.diff(present[on]) > 3):  # not one stretch: feet that end flat on some steps
        return out
    if np.sum(~on) >= 3:  # the others show the walker whole: they do not end flat, and are taller
        if np.median(flat[~on]) >= config.hidden_flat:
            return out  # a cut that moves with the walker ends flat on every frame
        edge = np.zeros(len(silhouettes), bool)
        edge[present[on]] = True
        if edge_share(b, edge, whole=~edge & ~astride_edge(silhouettes, b, edge)) < shorter:
            return out
    out[present[on]] = True
    return out


def astride_edge(silhouettes: list[np.ndarray | None], boxes: np.ndarray, on_edge: np.ndarray, *,
                 least: float = 0.25) -> np.ndarray:
    """(T,) bool: the frames off a fixed edge (``on_edge``, :func:`fixed_edge`) that end on it in
    part: a walker astride a wall's end, one leg cut on the edge's row and the other below it.
    Their height is neither the walker's nor the edge's. A frame is astride when at least
    ``least`` of its pixels on the edge's last visible row (and 2) have nothing below them."""
    b = np.asarray(boxes, float)
    out = np.zeros(len(silhouettes), bool)
    if not np.any(on_edge):
        return out
    row = int(np.median(b[on_edge, 1] + b[on_edge, 3])) - 1  # the last row the edge lets show
    for t, s in enumerate(silhouettes):
        if s is None or on_edge[t] or not np.isfinite(b[t, 3]):
            continue
        r = row - int(b[t, 1])
        if not 0 <= r < s.shape[0] - 1:
            continue
        on = s[r] > 0
        ends = on & ~(s[r + 1:] > 0).any(axis=0)
        out[t] = ends.sum() >= max(2, least * on.sum())
    return out


def edge_share(boxes: np.ndarray, on_edge: np.ndarray, *, whole: np.ndarray | None = None) -> float:
    """The median share of the walker hidden on the frames ``on_edge`` (T,) bool, from the heights
    of the frames ``whole`` with a box (default: the others): a Theil-Sen line of their log
    heights over time, against the frames on the edge. NaN with fewer than 3 of them."""
    b = np.asarray(boxes, float)
    ok = np.isfinite(b[:, 3]) & (b[:, 3] > 0)
    whole, behind = ok & (~on_edge if whole is None else whole), ok & on_edge
    if whole.sum() < 3 or not behind.any():
        return float("nan")
    t, h = np.arange(len(b), dtype=float), np.log(np.where(ok, b[:, 3], 1.0))
    a, slope = _line(t[whole], h[whole])
    return float(1.0 - np.exp(np.median(h[behind] - (a + slope * t[behind]))))


def on_bottom_edge(boxes: np.ndarray, image_size: tuple[int, int]) -> bool:
    """Whether the walker stands on the image's bottom edge, cut by it, in at least half of the
    frames with a box (``(x, y, w, h)`` rows, NaN where none; ``image_size`` ``(width, height)``).
    :func:`check_plausible` skips such frames unless too few would be left."""
    b = np.asarray(boxes, float)
    ok = np.isfinite(b[:, 3])
    return bool(ok.any() and np.mean(b[ok, 1] + b[ok, 3] >= image_size[1]) >= 0.5)


def _flat_bottom(sil: np.ndarray) -> float:
    """The share of the columns of a silhouette's lowest tenth whose lowest pixel is on (or one
    row above) its bottom row: 1 for a straight horizontal cut."""
    band = sil[int(0.9 * sil.shape[0]):] > 0
    cols = np.flatnonzero(band.any(axis=0))
    if cols.size < 3:
        return 0.0
    low = band.shape[0] - 1 - np.argmax(band[::-1, cols], axis=0)
    return float(np.mean(low >= low.max() - 1))


def _scores(score: Callable[[list[np.ndarray]], np.ndarray],
            trials: list[list[tuple | None]]) -> np.ndarray:
    """``score`` of every trial (a crop first, then its offsets) in one call: (frames, trials), inf
    where a trial is empty."""
    flat = [c[0] for row in trials for c in row if c is not None]
    values = np.asarray(score(flat), float) if flat else np.zeros(0)
    out = np.full((len(trials), max((len(r) for r in trials), default=0)), np.inf)
    k = 0
    for i, row in enumerate(trials):
        for j, c in enumerate(row):
            if c is not None:
                out[i, j] = values[k]
                k += 1
    return out
