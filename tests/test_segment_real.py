"""The default segmenter on real footage (vtest.avi crops) and on scripted hard cases."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from capture.scene import SceneSpec, iou, scene_frames
from capture.segment import Segmenter, SegmentSettings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import eval_real_video as real  # noqa: E402

pytestmark = pytest.mark.skipif(not real.VIDEO.is_file(), reason="vtest.avi not available")


@pytest.fixture(scope="module")
def video():
    """vtest.avi, read once for the module."""
    return real.load_video()


@pytest.fixture(scope="module")
def lawn(video):
    frames = real.crop(video, real.CLIPS["lawn"])
    masks, _ = real.run(frames, SegmentSettings())
    return frames, masks


def test_a_walker_in_view_from_frame_0_gets_silhouettes(video):
    inview = real.crop(real.offline_masks(video), real.CLIPS["path"]).reshape(len(video), -1)
    inview = (inview > 0).sum(axis=1)[:60] >= 150  # the eval's definition (24 of 60)
    masks, _ = real.run(real.crop(video[:60], real.CLIPS["path"]), SegmentSettings())
    assert masks[0] is not None  # bootstrapped, not learned into the background
    assert inview.sum() >= 20 and all(masks[k] is not None for k in np.flatnonzero(inview))


def test_empty_frames_give_empty_silhouettes(lawn):
    _, masks = lawn
    # frames 80-180 of the lawn crop: nobody in view (offline masks; checked by eye)
    assert sum(m is not None for m in masks[80:180]) <= 3


@pytest.fixture(scope="module")
def path_clip(video):
    masks, _ = real.run(real.crop(video, real.CLIPS["path"]), SegmentSettings())
    return masks


def test_reference_masks(lawn, path_clip):
    ious = real.fixture_ious("lawn", lawn[1])
    assert len(ious) == 3 and min(ious) > 0.83 and np.mean(ious) >= 0.85, ious  # measured 0.86-0.91
    ious = real.fixture_ious("path", path_clip)
    # measured 0.83-0.94, mean 0.88 (0.83 without the feet band, 0.69 before the edge split)
    assert len(ious) == 4 and np.mean(ious) >= 0.85, ious


def test_a_fluttering_tape_is_nobody(path_clip):
    # frames 465-481 of the path crop: nobody in view, the barrier tape moves (checked by eye)
    assert sum(m is not None for m in path_clip[465:482]) == 0


def test_thin_moving_things_are_not_walkers():
    """A swinging wire (2 px) and a sliver at the border are refused; the walker is not."""
    seg = Segmenter(SegmentSettings(warmup_frames=100))
    seen = {"nobody": 0, "walker": 0}
    for f in scene_frames(SceneSpec(width=320, height=240, frames=130, empty=115)):
        image = f.image.copy()
        if f.index >= 100:  # after the warm-up: a wire swinging 10 px, a border sliver
            y = 30 + 10 * (f.index % 3)
            cv2.line(image, (20, y), (300, y + 6), (250, 250, 250), 2)
            image[:, 318:] = 255 - image[:, 318:]
        s = seg.apply(image, f.index)
        if s is None:
            continue
        if not f.mask.any():
            assert s.box.empty, (f.index, s.box)
            seen["nobody"] += 1
        else:
            assert iou(s.full_mask(), f.mask) > 0.9
            seen["walker"] += 1
    assert seen == {"nobody": 15, "walker": 15}


def _shadowed(spec: SceneSpec, shadow: float, *, contact: bool = False, long: float = 0.0):
    """The scripted scene with a shadow (the background darkened by ``shadow``) cast beside
    the walker, its texture kept; ``contact``: a small one around and under the feet instead;
    ``long``: one cast from the feet towards the camera, that share of the walker's height long."""
    for f in scene_frames(spec):
        if f.mask.any():
            ys, xs = np.nonzero(f.mask)
            cast = np.zeros_like(f.mask)
            if contact:
                cv2.ellipse(cast, (int(xs.mean()), int(ys.max())), (int(np.ptp(xs)) // 2 + 6, 4), 0, 0, 360, 255, -1)
            elif long:
                reach, feet = long * (np.ptp(ys) + 1) / 2, xs[ys >= ys.max() - 3]
                cv2.ellipse(cast, (int(feet.mean()), int(ys.max() + reach)),
                            (int(np.ptp(feet)) // 2 + 4, int(reach) + 2), 0, 0, 360, 255, -1)
            else:
                cv2.ellipse(cast, (int(xs.mean()) + 30, int(ys.max()) - 5), (40, 10), 0, 0, 360, 255, -1)
            cast[f.mask > 0] = 0
            image = f.image.astype(np.float32)
            image[cast > 0] *= shadow
            f.image = cv2.convertScaleAbs(image)
        yield f


@pytest.mark.parametrize("dark", [False, True])
def test_shadows_are_suppressed_without_losing_dark_clothing(dark):
    spec = SceneSpec(width=320, height=240, frames=130, empty=100, walker_alpha=1.0,
                     walker_bgr=(30, 30, 30) if dark else SceneSpec.walker_bgr)
    out = {}
    for shadows in (False, True):
        seg = Segmenter(SegmentSettings(warmup_frames=100, shadows=shadows))
        out[shadows] = [iou(s.full_mask(), f.mask) for f in _shadowed(spec, 0.6)
                        if (s := seg.apply(f.image, f.index)) is not None and f.mask.any()]
    # measured 0.944 (coloured) and 0.934 (dark) with, 0.68 without
    assert np.mean(out[True]) > 0.92, out[True]
    assert np.mean(out[True]) > np.mean(out[False]) + 0.2


@pytest.mark.parametrize("dark", [False, True])
def test_a_contact_shadow_under_the_feet_is_dropped(dark):
    """A few pixels of shadow around the feet: too small for the texture test, and
    closed into the body without the feet band (``shadow_feet``)."""
    spec = SceneSpec(width=320, height=240, frames=130, empty=100, walker_alpha=1.0,
                     walker_bgr=(30, 30, 30) if dark else SceneSpec.walker_bgr)
    out = {}
    for feet in (0.0, SegmentSettings().shadow_feet):
        seg = Segmenter(SegmentSettings(warmup_frames=100, shadow_feet=feet))
        out[feet] = [iou(s.full_mask(), f.mask) for f in _shadowed(spec, 0.6, contact=True)
                     if (s := seg.apply(f.image, f.index)) is not None and f.mask.any()]
    off, on = np.mean(out[0.0]), np.mean(out[SegmentSettings().shadow_feet])  # measured 0.92 -> 1.00
    assert on > off + 0.02 and on > 0.93, (off, on)


@pytest.mark.parametrize("dark", [False, True])
def test_a_long_shadow_below_the_feet_is_dropped_back_to_the_feet(dark):
    """Issue (composite walks, session 29): a cast shadow half the walker's height long joined at
    the feet put the feet band (``shadow_feet`` of the blob's height) at the shadow's far end;
    the part by the feet failed the texture test (edges) and stayed, 36 px below the feet here
    (20-40 px on the composite videos). The test repeated on what is left moves the band up."""
    spec = SceneSpec(width=320, height=240, frames=130, empty=100, walker_alpha=1.0,
                     walker_bgr=(30, 30, 30) if dark else SceneSpec.walker_bgr)
    below = {}
    for rounds in (1, SegmentSettings().shadow_rounds):
        seg = Segmenter(SegmentSettings(warmup_frames=100, shadow_rounds=rounds))
        below[rounds] = [np.flatnonzero(s.full_mask().any(axis=1))[-1] - np.flatnonzero(f.mask.any(axis=1))[-1]
                         for f in _shadowed(spec, 0.6, long=0.5) if (s := seg.apply(f.image, f.index)) is not None
                         and f.mask.any()]
    once, default = below[1], below[SegmentSettings().shadow_rounds]
    assert len(once) == len(default) == 30
    assert np.median(once) > 20, once  # measured 36 px
    assert max(abs(v) for v in default) <= 2, default  # measured 0


def test_a_walker_that_looks_like_a_shadow_is_kept_whole():
    """Dark and semi-transparent (the background's texture shows through): every
    shadow test passes on the body, so nothing may be removed."""
    spec = SceneSpec(width=320, height=240, frames=130, empty=100, walker_bgr=(30, 30, 30))
    out = {}
    for shadows in (False, True):
        seg = Segmenter(SegmentSettings(warmup_frames=100, shadows=shadows))
        out[shadows] = [iou(s.full_mask(), f.mask) for f in _shadowed(spec, 0.6)
                        if (s := seg.apply(f.image, f.index)) is not None and f.mask.any()]
    assert len(out[True]) == len(out[False]) == 30
    assert np.mean(out[True]) >= np.mean(out[False]) - 0.01


def _grey_shirt_over_grey_ground(frames: int = 130, empty: int = 100):
    """A plain grey path behind the walker's upper half, grass below; after ``empty`` frames a
    walker crosses: a shirt the path's grey darkened to 0.8 (a shadow's colour, and on plain
    ground a shadow's texture), blue legs, a dark head, the walker's own shadow (0.6) cast on
    the path beside the feet, all softened by a camera's blur. Yields (index, image, walker,
    shirt over the path, cast shadow), the masks bool."""
    rng = np.random.default_rng(3)
    path, grass = np.array([118.0, 124.0, 130.0], np.float32), np.array([60.0, 130.0, 80.0], np.float32)
    ground = np.empty((240, 320, 3), np.float32)
    ground[:120], ground[120:] = path, grass
    ground[190:] = path  # the path again under the feet, where the shadow falls
    for k in range(frames):
        image, shirt, cast = ground.copy(), np.zeros((240, 320), np.uint8), np.zeros((240, 320), np.uint8)
        walker = np.zeros_like(shirt)
        if k >= empty:
            x = 60 + 4 * (k - empty)
            cv2.ellipse(shirt, (x, 110), (16, 34), 0, 0, 360, 1, -1)
            legs, head = np.zeros_like(shirt), np.zeros_like(shirt)
            cv2.rectangle(legs, (x - 13, 135), (x - 3, 205), 1, -1)
            cv2.rectangle(legs, (x + 3, 135), (x + 13, 205), 1, -1)
            cv2.circle(head, (x, 66), 11, 1, -1)
            cv2.ellipse(cast, (x + 45, 203), (40, 7), 0, 0, 360, 1, -1)
            walker = shirt | legs | head
            cast[walker > 0] = 0
            image[cast > 0] *= 0.6
            image[shirt > 0] = 0.8 * path
            image[legs > 0] = (150, 70, 30)
            image[head > 0] = (40, 55, 80)
            shirt[120:] = 0  # over the grass the shirt is no shadow's colour
        image = cv2.GaussianBlur(image, (0, 0), 2.5) + rng.normal(0, 2, image.shape).astype(np.float32)
        yield k, cv2.convertScaleAbs(image), walker > 0, shirt > 0, cast > 0


def test_a_grey_shirt_over_grey_ground_is_not_a_shadow():
    """Issue (composite walks through a camera's optics, session 47): a pale grey shirt over a
    plain grey path passes the shadow's colour test and, the path being plain, its texture test;
    it sits at the top of the walker, so no closing encloses it, and it was dropped with the
    head above it (one camera's silhouettes half their height for 21 frames, its viewpoint
    154 deg off). A cast shadow reaches the feet; the shirt does not (blue legs between)."""
    seen = {}
    for shadows in (False, True):
        seg = Segmenter(SegmentSettings(warmup_frames=100, shadows=shadows))
        rows = []
        for k, image, walker, shirt, cast in _grey_shirt_over_grey_ground():
            s = seg.apply(image, k)
            if s is not None and walker.any():
                m = s.full_mask() > 0
                rows.append((iou(m, walker), (m & shirt).sum() / shirt.sum(), (m & cast).sum() / cast.sum()))
        seen[shadows] = np.array(rows)
    assert len(seen[True]) == len(seen[False]) == 30
    off, on = seen[False].mean(axis=0), seen[True].mean(axis=0)
    assert off[2] > 0.8  # the premise: without the shadow test the cast shadow is taken
    assert on[2] < 0.1, on  # the cast shadow goes (measured 0.025 of it left)
    # the shirt and the head stay: measured 0.925 of the shirt, walker IoU 0.849 (0.685 with the
    # shadow kept); before, 0.013 of the shirt and IoU 0.497, the head lost with it
    assert on[1] > 0.85 and on[0] > off[0] + 0.1, (on, off)


def test_the_tracked_walker_is_kept_when_a_bigger_second_person_appears():
    spec = SceneSpec(width=320, height=240, frames=130, empty=100)
    seg = Segmenter(SegmentSettings(warmup_frames=100))
    for f in scene_frames(spec):
        image = f.image
        if f.index >= 115:  # a bigger second "person" enters far from the walker
            image = image.copy()
            cv2.ellipse(image, (280, 120), (25, 60), 0, 0, 360, (20, 160, 20), -1)
        s = seg.apply(image, f.index)
        if s is not None and f.index >= 115:
            assert s.n_candidates == 2
            assert iou(s.full_mask(), f.mask) > 0.9


def _with_stander(spec: SceneSpec, leaves: int):
    """The scripted scene with a second person standing still (an opaque ellipse, own
    texture) far from the walker's path until frame ``leaves``."""
    rng = np.random.default_rng(1)
    coat = rng.integers(20, 90, (120, 40, 3), dtype=np.uint8)
    for f in scene_frames(spec):
        if f.index < leaves:
            f.image = f.image.copy()
            patch = f.image[20:140, 250:290]
            inside = np.zeros(patch.shape[:2], np.uint8)
            cv2.ellipse(inside, (20, 60), (18, 58), 0, 0, 360, 255, -1)
            patch[inside > 0] = coat[inside > 0]
        yield f


@pytest.mark.parametrize("ghost_frames", [10, 0])
def test_a_ghost_left_by_someone_in_the_bootstrap_is_absorbed(ghost_frames):
    """Someone who stood still through the whole bootstrap sample is in the median
    background; when they leave, their "ghost" (the background where they stood) is
    foreground. It stays put and its outline is the model's edge, not the frame's:
    after ``ghost_frames`` it is absorbed (with 0 = off it stays)."""
    spec = SceneSpec(width=320, height=240, frames=130, empty=60)
    frames = list(_with_stander(spec, leaves=40))
    seg = Segmenter(SegmentSettings(ghost_frames=ghost_frames))
    seg.bootstrap([f.image for f in frames[:40]])
    late = []
    for f in frames:
        s = seg.apply(f.image, f.index)
        if f.index >= 70:  # 30 frames after the stander left
            late.append(s)
    if ghost_frames:
        assert seg.ghosts >= 1
        assert all(s.n_candidates == 1 for s in late)
        assert np.mean([iou(s.full_mask(), f.mask) for s, f in zip(late, frames[70:])]) > 0.9
    else:
        assert seg.ghosts == 0 and all(s.n_candidates == 2 for s in late)


def _with_lying_shadow(spec: SceneSpec, leaves: int):
    """The scripted scene with a shadow (the ground darkened to 0.6, its texture kept) lying
    in one place until frame ``leaves``: as a walker's own does in most bootstrap samples when
    they stay in view (walking towards the camera) over a short recording."""
    for f in scene_frames(spec):
        if f.index < leaves:
            image = f.image.astype(np.float32)
            image[30:120, 240:300] *= 0.6
            f.image = cv2.convertScaleAbs(image)
        yield f


@pytest.mark.parametrize("lit", [0.0, SegmentSettings().bootstrap_lit])
def test_a_shadow_lying_in_most_bootstrap_samples_is_not_the_background(lit):
    """The shadow lies in 30 of the 40 samples, so the median holds it; once it is gone the
    lit ground is brighter than that background by a shadow's ratio. With ``bootstrap_lit``
    the 10 lit samples, which agree, are the background there; without it the lit ground is a
    second candidate for as long as it stays (ghost absorption off, to see the bootstrap alone)."""
    spec = SceneSpec(width=320, height=240, frames=130, empty=60)
    frames = list(_with_lying_shadow(spec, leaves=30))
    seg = Segmenter(SegmentSettings(ghost_frames=0, bootstrap_lit=lit))
    seg.bootstrap([f.image for f in frames[:40]])
    out = [(seg.apply(f.image, f.index), f) for f in frames]
    empty = [s for s, f in out[30:60]]  # the shadow gone, nobody in view yet
    walker = [(s, f) for s, f in out[70:] if f.mask.any()]
    if lit:
        assert all(s is None or s.box.empty for s in empty)
        assert all(s.n_candidates == 1 for s, _ in walker)
        assert np.mean([iou(s.full_mask(), f.mask) for s, f in walker]) > 0.9
    else:
        assert sum(not s.box.empty for s in empty if s is not None) > 20


def test_a_change_of_light_in_some_bootstrap_samples_keeps_the_median():
    """The sun out in 12 of 40 samples makes the whole scene a 'lit' value of the median: that is
    a change of light, not a shadow (``bootstrap_lit_area``), and the background stays the median."""
    frames = [f.image for f in scene_frames(SceneSpec(width=320, height=240, frames=40, empty=40))]
    frames = [cv2.convertScaleAbs(f, alpha=1.3) if k < 12 else f for k, f in enumerate(frames)]
    backgrounds = []
    for lit in (0.0, SegmentSettings().bootstrap_lit):
        seg = Segmenter(SegmentSettings(bootstrap_lit=lit))
        seg.bootstrap(frames)
        backgrounds.append(seg.background_image())
    np.testing.assert_array_equal(backgrounds[0], backgrounds[1])
    seg = Segmenter(SegmentSettings(bootstrap_lit_area=1.0))  # without the limit the minority's light wins
    seg.bootstrap(frames)
    assert np.mean(cv2.absdiff(seg.background_image(), backgrounds[0])) > 10
