"""Choosing the walker over a whole clip (capture.choose, capture.refine.segment_clip)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from capture.choose import GAP, choose, guide
from capture.refine import segment, segment_clip
from capture.scene import SceneSpec, iou, scene_frames
from capture.segment import Segmentation, SegmentSettings
from capture.wire import Box

SIZE = (640, 480)


def _box(cx: float, top: float, w: float, h: float) -> tuple[int, int, int, int]:
    return (int(cx - w / 2), int(top), int(w), int(h))


def test_the_path_through_the_middle_is_the_walker_not_the_taller_person_at_the_side():
    frames = [(_box(200 + 6 * t, 180, 40, 120), _box(40, 150 + t, 50, 160)) for t in range(40)]
    path = choose(frames, SIZE)
    assert path == [f[0] for f in frames]


def test_a_group_that_splits_goes_on_with_the_part_of_the_walkers_height():
    """Walker and a shorter passer-by cross the middle from either side, as far from it as each
    other in every frame, and make one box for frames 10-19: the path keeps the walker's height
    on both sides of the merge."""
    frames = []
    for t in range(30):
        walker = _box(260 + 4 * t, 180, 40, 120)
        other = _box(380 - 4 * t, 200, 30, 80)
        frames.append((_box(320, 180, 120, 120),) if 10 <= t < 20 else (other, walker)[::1 if t % 2 else -1])
    path = choose(frames, SIZE)
    assert all(path[t][3] == 120 for t in range(30))


def test_a_walker_missed_for_a_few_frames_is_not_left_for_someone_else():
    frames = [(() if 10 <= t < 10 + GAP else (_box(300 + t, 180, 40, 120),)) + (_box(560, 200, 40, 110),)
              for t in range(30)]
    path = choose(frames, SIZE)
    assert all(path[t] is None for t in range(10, 10 + GAP))
    assert all(path[t] == frames[t][0] for t in range(30) if not 10 <= t < 10 + GAP)


def test_nothing_in_view_is_no_path():
    assert choose([(), ()], SIZE) == [None, None]


def _followed(frames: list[tuple], k: int) -> list[Segmentation]:
    """A first pass that kept candidate ``k`` of every frame."""
    return [Segmentation(np.full((b[k][3], b[k][2]), 255, np.uint8), Box(*b[k]), SIZE, b[k][2] * b[k][3], False,
                         len(b), b) for b in frames]


def test_a_walker_crossing_the_image_is_not_left_for_someone_a_little_more_central():
    """The first pass followed the walker across the whole image; a short passer-by stands near the
    middle all along, nearer the centre on average but not by ``MARGIN``: the first pass stands."""
    frames = [(_box(80 + 12 * t, 150, 70, 220), _box(420, 250, 30, 70)) for t in range(40)]
    assert guide(_followed(frames, 0), SegmentSettings()) == (None, None)


def test_a_first_pass_on_someone_at_the_edge_is_moved_to_the_walker_in_the_middle():
    frames = [(_box(600, 100 + t, 40, 150), _box(300 + t, 180, 40, 120)) for t in range(40)]
    boxes, note = guide(_followed(frames, 0), SegmentSettings())
    assert boxes == [f[1] for f in frames] and "segmented again" in note
    assert guide(_followed(frames, 0), SegmentSettings(walker_choice="first")) == (None, None)


def _with_passer_by(spec: SceneSpec):
    """The scripted scene (its walker crossing the middle) with a taller person walking down the
    right edge from the first frame after the warm-up: the tallest when the track starts."""
    rng = np.random.default_rng(3)
    coat = rng.integers(20, 80, (spec.height, spec.width, 3), dtype=np.uint8)
    for f in scene_frames(spec):
        if f.index >= spec.empty:
            f.image = f.image.copy()
            inside = np.zeros(f.mask.shape, np.uint8)
            cv2.ellipse(inside, (290, 50 + int(1.5 * (f.index - spec.empty))), (14, 58), 0, 0, 360, 255, -1)
            f.image[inside > 0] = coat[inside > 0]
        yield f


@pytest.fixture(scope="module")
def passer_by():
    spec = SceneSpec(width=320, height=240, frames=160, empty=100)
    return list(_with_passer_by(spec))


def test_on_a_clip_the_walker_is_chosen_and_not_the_tallest_at_the_start(passer_by):
    settings = SegmentSettings(background="warmup", warmup_frames=100)
    walking = [f for f in passer_by if f.mask.any()]
    first = segment([f.image for f in passer_by], settings)
    assert np.mean([iou(first[f.index].full_mask(), f.mask) for f in walking]) < 0.2  # the person at the side
    chosen, note = segment_clip(lambda: (f.image for f in passer_by), settings)
    assert note is not None and "nearest the image centre" in note
    assert np.mean([iou(chosen[f.index].full_mask(), f.mask) > 0.8 for f in walking]) > 0.9
    assert guide(chosen, settings) == (None, None)  # the second pass followed the chosen walker


def test_walker_choice_first_keeps_the_track(passer_by):
    settings = SegmentSettings(background="warmup", warmup_frames=100, walker_choice="first")
    images = [f.image for f in passer_by]
    segs, note = segment_clip(lambda: iter(images), settings)
    assert note is None
    assert [s and s.box for s in segs] == [s and s.box for s in segment(images, settings)]


def test_refine_says_whose_walker_it_followed(passer_by, small_model):
    """The refine path (``posecal refine`` on videos) keeps the clip's note that the walker
    in the middle was followed rather than the tallest at the start."""
    from capture.refine import refine_cameras
    from estimator.prior import FEEDBACK
    from estimator.render import Renderer

    settings = SegmentSettings(background="warmup", warmup_frames=100)
    with Renderer(FEEDBACK.body) as renderer:
        result = refine_cameras({"c0": lambda: (f.image for f in passer_by)}, small_model, renderer=renderer,
                                settings=settings, config=FEEDBACK)
    assert list(result.notes) == ["c0"] and "nearest the image centre" in result.notes["c0"]


def test_live_the_track_moves_to_the_walker_after_a_look_back(passer_by):
    """A live agent cannot look ahead: it starts on the tallest (the person at the edge) and,
    looking back over the last frames (capture.choose.LiveChoice), moves the track onto the
    walker in the middle; the frames after that are the walker's. With the choice off
    (``walker_choice="first"``) it never moves."""
    from capture.choose import LIVE_EVERY
    from capture.live import LiveSegmenter
    from capture.segment import Segmenter

    def live(settings: SegmentSettings) -> tuple[list, int, str | None]:
        """The agent's per-frame path (capture.live): the segmentations, the moves, the last note."""
        path, out, moves = LiveSegmenter(Segmenter(settings)), [], 0
        for f in passer_by:
            out.append(path.apply(f.image, f.index))
            moves += path.learn()
        return out, moves, path.note

    walking = [f for f in passer_by if f.mask.any()]
    segs, moves, note = live(SegmentSettings(background="warmup", warmup_frames=100))
    assert moves == 1 and "the track moved to it" in note
    late = walking[2 * LIVE_EVERY + 1:]  # after the first look back that could move it
    assert late and np.mean([iou(segs[f.index].full_mask(), f.mask) > 0.8 for f in late]) > 0.9
    first, moves, _ = live(SegmentSettings(background="warmup", warmup_frames=100, walker_choice="first"))
    assert moves == 0
    assert np.mean([iou(first[f.index].full_mask(), f.mask) for f in late]) < 0.2  # still the person at the side


def test_live_a_track_that_leaves_the_walker_moves_back_within_a_few_frames():
    """The track followed the walker in the middle for 30 frames, then the person at the edge
    (a merge and split took it over): the look back judges the frames since it left the path,
    so it moves back at the first look back with ``LIVE_OFF`` frames off. Judged over the whole
    look back (``guide``, 30 of 35 frames agreeing) it would stand."""
    from capture.choose import LIVE_EVERY, LIVE_OFF, LiveChoice

    frames = [(_box(600, 100 + t, 40, 150), _box(300 + t, 180, 40, 120)) for t in range(50)]
    segs = [_followed(frames[t:t + 1], 1 if t < 30 else 0)[0] for t in range(50)]
    choice = LiveChoice(SegmentSettings())
    moved = next(t for t in range(50) if choice.see(segs[t], 100 + t) is not None)
    assert 30 + LIVE_OFF - 1 <= moved <= 30 + LIVE_OFF + LIVE_EVERY
    assert choice.switches == 1 and "the track moved to it" in choice.note
    assert choice.since == 130  # the first frame off the walker, in the indices it was given (the wire's track_from)
    assert guide(segs[moved + 1 - 35:moved + 1], SegmentSettings()) == (None, None)


def test_live_a_track_off_the_path_for_a_frame_or_two_stays():
    from capture.choose import LIVE_OFF, LiveChoice

    frames = [(_box(600, 100 + t, 40, 150), _box(300 + t, 180, 40, 120)) for t in range(30)]
    off = range(30 - (LIVE_OFF - 1), 30)  # the last frames, fewer than LIVE_OFF
    segs = [_followed(frames[t:t + 1], 0 if t in off else 1)[0] for t in range(30)]
    choice = LiveChoice(SegmentSettings())
    assert all(choice.see(s) is None for s in segs) and choice.switches == 0


def test_live_the_track_is_not_moved_onto_someone_far_shorter_in_the_middle():
    """A large walker off the image centre and a passer-by a third of their height crossing it: the
    passer-by's path is nearer the centre by far more than ``MARGIN``, but a camera aimed at the walk
    does not frame its walker that small (``LIVE_SHORTER``); a person of the walker's height there is
    moved to."""
    from capture.choose import LiveChoice

    def moves(height: int) -> int:
        frames = [(_box(520, 100, 70, 240), _box(300 + t, 200, 20, height)) for t in range(40)]
        choice = LiveChoice(SegmentSettings())
        for s in [_followed(frames[t:t + 1], 0)[0] for t in range(40)]:
            choice.see(s)
        return choice.switches

    assert moves(80) == 0
    assert moves(200) >= 1


def _live_moves(frames: list[tuple], followed: list[int]) -> tuple[list[int], int | None]:
    """The frames at which a live look back moves a track that kept candidate ``followed[t]`` of frame t,
    and the first frame off the walker its last move said (``LiveChoice.since``)."""
    from capture.choose import LiveChoice

    choice = LiveChoice(SegmentSettings())
    segs = [_followed(frames[t:t + 1], followed[t])[0] for t in range(len(frames))]
    return [t for t, s in enumerate(segs) if choice.see(s) is not None], choice.since


def test_live_a_walker_who_comes_into_view_is_moved_to_soon():
    """The track is on a person at the image's edge; the walker comes into view in the middle at frame
    20: judged on the frames since the walker's path began (not the 20 before, where it has none), the
    track moves at the first look with ``LIVE_OFF`` frames of it."""
    from capture.choose import LIVE_EVERY, LIVE_OFF

    edge = [_box(600, 100 + t, 40, 150) for t in range(45)]
    frames = [(edge[t],) if t < 20 else (edge[t], _box(300 + t, 180, 40, 130)) for t in range(45)]
    moved, since = _live_moves(frames, [0] * 45)
    assert moved and 20 + LIVE_OFF - 1 <= moved[0] <= 20 + LIVE_OFF + LIVE_EVERY
    assert since == 20  # judged from the walker's first frame (before it, they were not in view)


def test_live_after_the_walker_left_the_next_one_in_the_middle_is_moved_to():
    """The walker in the middle is followed for 20 frames and leaves; the track goes on with a person
    at the edge; a walker comes into the middle at frame 30. The look back chooses among the frames
    after the first walker's path ended (over all of them, that path is still the cheapest)."""
    from capture.choose import LIVE_EVERY

    edge = [_box(600, 100 + t, 40, 150) for t in range(50)]
    frames = [(edge[t], _box(300 + t, 180, 40, 130)) if t < 20 or t >= 30 else (edge[t],) for t in range(50)]
    followed = [1 if t < 20 else 0 for t in range(50)]
    moved, since = _live_moves(frames, followed)
    assert moved and 30 <= moved[0] <= 30 + 3 * LIVE_EVERY
    assert since == 30  # the person at the edge from the second walker's first frame (the first left at 20)


def _people_in_turn(gap: int) -> list[np.ndarray]:
    """A textured scene, empty for 60 frames; a person (a dark upright block, 24 x 80 px) crosses it to the
    right edge and leaves; ``gap`` frames later another comes in from the left edge."""
    from capture.scene import textured_background

    rng = np.random.default_rng(0)
    background = textured_background(320, 240, rng)
    frames = []
    for t in range(60 + 60 + gap + 30):
        image = background + rng.normal(0, 3, background.shape)
        k = t - 60
        x = 150 + 4 * k if 0 <= k < 60 else 4 * (k - 60 - gap) if k >= 60 + gap else None
        if x is not None and x < 320:
            image[100:180, max(0, x):min(320, x + 24)] = (40, 50, 120)
        frames.append(np.clip(image, 0, 255).astype(np.uint8))
    return frames


def test_a_track_started_on_someone_who_does_not_continue_the_last_is_another_person():
    """One walker leaves the view at the right and another comes in at the left 20 frames later: the
    segmenter starts a new track on the second, which does not continue the first (:func:`same_person`),
    so the silhouettes from then on are of another person (``track_id`` one more, no ``track_from``: the
    service leaves the first one's frames out of a window that holds the second's)."""
    from capture.live import SAME_GAP, LiveSegmenter, same_person
    from capture.segment import Segmenter

    live = LiveSegmenter(Segmenter(SegmentSettings(background="warmup", warmup_frames=50)))
    ids = []
    for k, image in enumerate(_people_in_turn(gap=20)):
        seg = live.apply(image, k)
        live.learn()
        ids.append((live.track_id, live.track_from, seg is not None and not seg.box.empty))
    first = next(k for k, (_, _, seen) in enumerate(ids) if seen)
    second = next(k for k in range(first + 60, len(ids)) if ids[k][2])  # the second walker's first frame
    assert {i[:2] for i in ids[first:second]} == {(0, None)}
    assert {i[:2] for i in ids[second:]} == {(1, None)}
    # the same person picked up again: near, about as tall, soon
    assert same_person((100, 50, 20, 80), (104, 52, 21, 78), gap=3)
    assert not same_person((100, 50, 20, 80), (160, 52, 21, 78), gap=3)  # elsewhere
    assert not same_person((100, 50, 20, 80), (100, 70, 20, 60), gap=3)  # a quarter shorter
    assert not same_person((100, 50, 20, 80), (104, 52, 21, 78), gap=SAME_GAP + 1)  # long gone
