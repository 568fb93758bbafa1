"""A walker joined by someone behind, cut back to the walker over the clip (capture.merges)."""

from __future__ import annotations

import numpy as np
import pytest

from capture.merges import LiveUnmerge, unmerge
from capture.refine import segment_clip
from capture.scene import SceneSpec, iou, scene_frames
from capture.segment import Segmentation, SegmentSettings
from capture.wire import Box

SIZE = (320, 240)


def _seg(boxes: list[tuple[int, int, int, int]], candidates: tuple = ()) -> Segmentation:
    """A segmentation whose blob is the union of filled ``boxes`` (x, y, w, h), with a 2 px margin."""
    x0 = min(b[0] for b in boxes) - 2
    y0 = min(b[1] for b in boxes) - 2
    x1 = max(b[0] + b[2] for b in boxes) + 2
    y1 = max(b[1] + b[3] for b in boxes) + 2
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    for x, y, w, h in boxes:
        mask[y - y0:y - y0 + h, x - x0:x - x0 + w] = 255
    return Segmentation(mask, Box(x0, y0, x1 - x0, y1 - y0), SIZE, int(np.count_nonzero(mask)), False,
                        len(candidates), tuple(candidates))


def _walk(n: int = 30) -> list[tuple[int, int, int, int]]:
    """The walker's box per frame: 30 px wide, 100 px tall growing by 0.5 px a frame, feet at row 200."""
    return [(100 + 2 * t, 200 - (100 + t // 2), 30, 100 + t // 2) for t in range(n)]


def _other(t: int) -> tuple[int, int, int, int]:
    """Someone farther away, 70 px tall, standing on the walker's head row band (higher in the image)."""
    return (100 + 2 * t, 40, 24, 70)


def _joined_clip(walker: list, joined: range) -> list[Segmentation]:
    """The walker with someone farther off on their head in the ``joined`` frames, beside them
    (a candidate of their own) in the others."""
    return [_seg([w, _other(t)]) if t in joined else _seg([w], candidates=(w, _other(t)))
            for t, w in enumerate(walker)]


def test_frames_where_someone_behind_stands_on_the_walkers_head_are_cut_back_to_the_walker():
    walker, joined = _walk(), range(10, 20)
    segs = _joined_clip(walker, joined)
    out, cut = unmerge(segs)
    assert cut == len(joined)
    for t in joined:
        full = out[t].full_mask() > 0
        rows = np.flatnonzero(full.any(axis=1))
        x, y, w, h = walker[t]
        assert rows[-1] + 1 == y + h  # the feet kept
        assert abs((rows[-1] + 1 - rows[0]) - 1.03 * h) <= 2  # the walker's height, and the margin
    assert all(out[t] is segs[t] for t in range(len(segs)) if t not in joined)


def test_a_walker_joined_below_by_someone_nearer_keeps_the_head():
    walker = _walk()
    below = [(100 + 2 * t, 190, 40, 130) for t in range(30)]  # someone nearer: larger, lower in the image
    segs = [_seg([w, below[t]]) if t >= 20 else _seg([w], candidates=(w, below[t])) for t, w in enumerate(walker)]
    out, cut = unmerge(segs)
    assert cut == 10
    for t in range(20, 30):
        rows = np.flatnonzero((out[t].full_mask() > 0).any(axis=1))
        assert rows[0] == walker[t][1] and rows[-1] + 1 - rows[0] <= 1.03 * walker[t][3] + 1


def _torn_legs() -> list[Segmentation]:
    """Legs lost against the ground for the first 10 frames, seen as a candidate of their own."""
    segs = []
    for t, (x, y, w, h) in enumerate(_walk()):
        torso = (x - 10, y, w + 20, h // 2)  # arms out: wider than half as tall
        legs = (x, y + h // 2, w, h - h // 2)
        segs.append(_seg([torso], candidates=(torso, legs)) if t < 10 else _seg([(x, y, w, h)]))
    return segs


def test_a_walker_torn_for_a_while_is_not_cut_to_the_torn_height():
    """The blob grows by a jump when the legs come back, but the short frames are squat (a torso
    is not a whole person), so nothing is cut, even with the legs seen as another candidate."""
    segs = _torn_legs()
    out, cut = unmerge(segs)
    assert cut == 0 and out == segs


def test_a_piece_of_the_walker_torn_off_is_not_someone_who_joined():
    """Head and shoulders lost against the background in the first frames, seen as a squat candidate
    of their own above the rest: when they join again the blob jumps, but no whole person was there."""
    walker = _walk()
    segs = []
    for t, (x, y, w, h) in enumerate(walker):
        head = (x - 5, y, w + 10, h // 3)
        rest = (x, y + h // 3, w, h - h // 3)
        segs.append(_seg([rest], candidates=(rest, head)) if t < 10 else _seg([(x, y, w, h)]))
    out, cut = unmerge(segs)
    assert cut == 0 and out == segs


def test_a_jump_no_one_else_explains_is_left_alone():
    """The same join without another person's box in the frames beside it: nothing is cut."""
    walker = _walk()
    segs = [_seg([w, _other(t)]) if 10 <= t < 20 else _seg([w]) for t, w in enumerate(walker)]
    out, cut = unmerge(segs)
    assert cut == 0 and out == segs


@pytest.mark.parametrize("jump", [0.0, 0.12])
def test_on_a_clip_a_walker_passing_in_front_of_someone_is_cut_back_when_on(jump):
    """The scripted scene's walker crosses the view while a person dressed alike walks the other
    way farther off, higher in the image: for a dozen frames they are one blob. With the cut on
    (the default) those frames are the walker again, and the note says so; off, they are not."""
    spec = SceneSpec(width=320, height=240, frames=160, empty=100, passer_behind=True)
    frames = list(scene_frames(spec))
    settings = SegmentSettings(background="warmup", warmup_frames=100, unmerge_jump=jump)
    segs, note = segment_clip(lambda: (f.image for f in frames), settings)
    walker = frames[spec.empty].mask
    tall = np.ptp(np.flatnonzero(walker.any(axis=1))) + 1
    joined = [f for f in frames if f.mask.any() and segs[f.index] is not None and not segs[f.index].box.empty
              and segs[f.index].box.h > 1.3 * tall]
    scores = [iou(segs[f.index].full_mask(), f.mask) for f in frames if f.mask.any()]
    if jump:
        assert not joined and note is not None and "joined the walker" in note
        assert np.mean(np.array(scores) > 0.8) > 0.95
    else:
        assert len(joined) >= 5  # the blob the cut undoes


def test_live_the_frames_after_a_join_are_cut_back_to_the_walker():
    """The first test's clip fed frame by frame: the join is cut from its first frame on, with
    the walker's height from the frames before (a live agent cannot look ahead)."""
    walker, joined = _walk(), range(10, 20)
    segs = _joined_clip(walker, joined)
    live = LiveUnmerge()
    out = [live.see(s) for s in segs]
    assert live.cut == len(joined)
    for t in joined:
        rows = np.flatnonzero((out[t].full_mask() > 0).any(axis=1))
        x, y, w, h = walker[t]
        assert rows[-1] + 1 == y + h and abs((rows[-1] + 1 - rows[0]) - h) <= 0.05 * h + 1
    assert all(out[t] is segs[t] for t in range(len(segs)) if t not in joined)


def test_live_a_walker_who_grows_back_from_torn_is_not_cut():
    segs = _torn_legs()
    live = LiveUnmerge()
    assert [live.see(s) for s in segs] == segs and live.cut == 0


def test_live_after_the_track_moves_to_another_person_their_height_is_no_join():
    """A live agent's track moves from one person to another (capture.choose.LiveChoice) who is
    taller, with their feet on the same row and beside the first in the frame before: without
    ``reset`` that is a join of the first and cut to their height; after it, the second is whole."""
    first = [(200, 110, 24, 90)] * 6
    second = (100, 75, 30, 125)  # feet at row 200 too
    segs = [_seg([b], candidates=(b, second)) for b in first] + [_seg([second], candidates=(first[-1], second))] * 3

    def fed(reset: bool) -> list[Segmentation]:
        live = LiveUnmerge()
        out = [live.see(s) for s in segs[:len(first)]]
        if reset:
            live.reset()
        return out + [live.see(s) for s in segs[len(first):]]

    assert any(o is not s for o, s in zip(fed(reset=False), segs))  # the case reset is for
    assert fed(reset=True) == segs
