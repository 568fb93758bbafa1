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
def lawn():
    video = real.load_video()
    frames = real.crop(video, real.CLIPS["lawn"])
    masks, _ = real.run(frames, SegmentSettings())
    return frames, masks


def test_a_walker_in_view_from_frame_0_gets_silhouettes():
    video = real.load_video()[:60]
    frames = real.crop(video, real.CLIPS["path"])
    masks, _ = real.run(frames, SegmentSettings())
    assert masks[0] is not None  # bootstrapped, not learned into the background
    assert sum(m is not None for m in masks) >= 45  # measured 48 of 60 (people at the edges)


def test_empty_frames_give_empty_silhouettes(lawn):
    _, masks = lawn
    # frames 80-180 of the lawn crop: nobody in view (offline masks; checked by eye)
    assert sum(m is not None for m in masks[80:180]) <= 3


def test_reference_masks(lawn):
    _, masks = lawn
    ious = real.fixture_ious("lawn", masks)
    assert len(ious) == 3 and min(ious) > 0.65, ious  # measured 0.72-0.81


def _shadowed(spec: SceneSpec, shadow: float):
    """The scripted scene with a shadow (the background darkened by ``shadow``) cast beside
    the walker, its texture kept."""
    for f in scene_frames(spec):
        if f.mask.any():
            ys, xs = np.nonzero(f.mask)
            cast = np.zeros_like(f.mask)
            cv2.ellipse(cast, (int(xs.mean()) + 30, int(ys.max()) - 5), (40, 10), 0, 0, 360, 255, -1)
            cast[f.mask > 0] = 0
            image = f.image.astype(np.float32)
            image[cast > 0] *= shadow
            f.image = cv2.convertScaleAbs(image)
        yield f


@pytest.mark.xfail(reason="not done: the shadow test removes dark clothing (IoU 0.59 on the dark walker); shadows=False by default", strict=False)
@pytest.mark.parametrize("dark", [False, True])
def test_shadows_are_suppressed_without_losing_dark_clothing(dark):
    spec = SceneSpec(width=320, height=240, frames=130, empty=100,
                     walker_bgr=(30, 30, 30) if dark else SceneSpec.walker_bgr)
    out = {}
    for shadows in (False, True):
        seg = Segmenter(SegmentSettings(warmup_frames=100, shadows=shadows))
        out[shadows] = [iou(s.full_mask(), f.mask) for f in _shadowed(spec, 0.6)
                        if (s := seg.apply(f.image, f.index)) is not None and f.mask.any()]
    assert np.mean(out[True]) > 0.95, out[True]
    assert np.mean(out[True]) > np.mean(out[False]) + 0.05


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
