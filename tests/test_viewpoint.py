"""Viewpoint ellipse on the circle, and the motion cue that settles ahead/behind."""

import numpy as np
import pytest

from estimator.synth import SynthSpec, synthesize
from estimator.viewpoint import (MotionCue, Viewpoint, elevation_from_path, estimate_viewpoint, head_points, motion_cue,
                                 with_path_elevation)


def cloud(rng, az, el, n=300, spread=6.0):
    return (az + rng.normal(0, spread, n)) % 360, el + rng.normal(0, spread / 2, n)


def test_centre_wraps_around_zero():
    rng = np.random.default_rng(0)
    a, e = cloud(rng, 358.0, 10.0)
    vp = estimate_viewpoint(a, e)
    assert abs((vp.azimuth_deg - 358.0 + 180) % 360 - 180) < 1.5
    assert vp.elevation_deg == pytest.approx(10.0, abs=1.0)
    assert 4 < vp.spread_deg < 9


@pytest.mark.parametrize("true_az", [30.0, 150.0, 210.0, 330.0])
def test_motion_settles_the_front_back_flip(true_az):
    rng = np.random.default_rng(1)
    # 60% of the cloud in the wrong mode (180 - a), the rest right.
    wrong = (180.0 - true_az) % 360
    a1, e1 = cloud(rng, true_az, 5.0, n=200)
    a2, e2 = cloud(rng, wrong, 5.0, n=300)
    a, e = np.concatenate([a1, a2]), np.concatenate([e1, e2])
    approaching = np.cos(np.radians(true_az)) > 0
    towards_left = np.sin(np.radians(true_az)) > 0
    cue = MotionCue(growth=0.01 if approaching else -0.01, travel=-0.05 if towards_left else 0.05, n_frames=30)
    vp = estimate_viewpoint(a, e, cue=cue)
    assert abs((vp.azimuth_deg - true_az + 180) % 360 - 180) < 3.0, vp
    assert vp.flip == "motion"
    # Without the cue the majority (wrong) mode wins, and the result says so.
    vp0 = estimate_viewpoint(a, e)
    assert abs((vp0.azimuth_deg - wrong + 180) % 360 - 180) < 3.0
    assert vp0.flip == "majority" and vp0.flip_margin < 0.5


def test_a_side_settled_elsewhere_overrides_the_cue():
    """``ahead`` (the side the other cameras' phase chose) folds the cloud there, whatever the cue."""
    rng = np.random.default_rng(2)
    a, e = cloud(rng, 40.0, 5.0, n=300)
    cue = MotionCue(growth=0.01, travel=-0.05, n_frames=30)  # approaching: ahead, 40 deg
    assert abs(estimate_viewpoint(a, e, cue=cue).azimuth_deg - 40.0) < 3.0
    behind = estimate_viewpoint(a, e, cue=cue, ahead=False)
    assert abs(behind.azimuth_deg - 140.0) < 3.0 and behind.flip == "cameras"
    assert abs(estimate_viewpoint(a, e, ahead=True).azimuth_deg - 40.0) < 3.0


def test_the_feet_rising_settle_behind_when_the_size_does_not_change():
    """A walker crossing a high camera's view obliquely, away from it (vtest.avi's failure): its
    height hardly changes, its feet rise up the image. With the cloud above the walker the feet
    settle ahead/behind; below it (the camera may be below the feet) and with the feet cut, they do not."""
    t = np.arange(20.0)
    h = np.full(20, 60.0)  # no growth
    boxes = np.stack([100 + 2.0 * t, 200 - 1.0 * t - h, np.full(20, 20.0), h], axis=1)  # feet rise 1 px/frame
    cue = motion_cue(boxes)
    assert cue.signs()[0] == 0 and cue.fall == pytest.approx(-1 / 60) and cue.fall_sign() == -1
    assert motion_cue(boxes, feet_cut=True).fall_sign() == 0
    rng = np.random.default_rng(3)
    a1, e1 = cloud(rng, 340.0, 5.0, n=300)  # the majority in front (wrong), the truth is 200 (behind, right)
    a2, e2 = cloud(rng, 200.0, 5.0, n=200)
    a, e = np.concatenate([a1, a2]), np.concatenate([e1, e2])
    vp = estimate_viewpoint(a, e + 15.0, cue=cue)  # the camera 15 deg above the walker
    assert abs((vp.azimuth_deg - 200.0 + 180) % 360 - 180) < 5.0 and vp.flip == "motion", vp
    low = estimate_viewpoint(a, e - 10.0, cue=cue)  # 10 deg below: the feet are not read
    assert np.cos(np.radians(low.azimuth_deg)) > 0 and low.flip != "motion"
    off = estimate_viewpoint(a, e + 15.0, cue=cue, fall_min_elevation_deg=np.inf)  # EstimateConfig's switch
    assert np.cos(np.radians(off.azimuth_deg)) > 0 and off.flip != "motion"


@pytest.mark.parametrize("az", [0.0, 60.0, 90.0, 160.0, 250.0])
def test_motion_cue_from_rendered_walks(az):
    seq = synthesize(SynthSpec(n_cameras=1, n_frames=20, seed=5, azimuths=(az,), elevations=(5.0,), image_size=(320, 240)))
    boxes = []
    for s in seq.silhouettes["c0"]:
        v, u = np.nonzero(s)
        boxes.append([u.min(), v.min(), np.ptp(u) + 1, np.ptp(v) + 1])
    cue = motion_cue(np.array(boxes, float))
    cos_sign, sin_sign = cue.signs()
    c, s = np.cos(np.radians(az)), np.sin(np.radians(az))
    if abs(c) > 0.3:
        assert cos_sign == np.sign(c)
    if abs(s) > 0.3:
        assert sin_sign == np.sign(s)


def test_motion_cue_needs_three_boxes():
    assert motion_cue(np.full((5, 4), np.nan)) is None
    with pytest.raises(ValueError, match=r"\(T, 4\)"):
        motion_cue(np.zeros((5, 3)))


def test_bad_cloud_rejected():
    with pytest.raises(ValueError, match="non-empty"):
        estimate_viewpoint(np.array([]), np.array([]))


def _boxes_and_heads(silhouettes):
    """Tight crops, full-frame boxes and head points of full-frame silhouettes."""
    crops, boxes = [], []
    for s in silhouettes:
        v, u = np.nonzero(s)
        boxes.append([u.min(), v.min(), np.ptp(u) + 1, np.ptp(v) + 1])
        crops.append(s[v.min():v.max() + 1, u.min():u.max() + 1])
    boxes = np.array(boxes, float)
    return boxes, head_points(crops, boxes)


@pytest.mark.parametrize("az", [20.0, 60.0, 130.0, 240.0, 320.0])
def test_head_path_gives_the_growth_when_the_feet_are_damaged(az):
    """A shadow cut at a drifting length makes the silhouette's height shrink while the
    walker approaches (or grow while they recede); the head's perspective path is not fooled
    (near frontal views it may have no evidence: the head hardly moves in the image)."""
    seq = synthesize(SynthSpec(n_cameras=1, n_frames=30, seed=3, azimuths=(az,), elevations=(8.0,),
                               image_size=(320, 240)))
    boxes, heads = _boxes_and_heads(seq.silhouettes["c0"])
    clean = motion_cue(boxes, heads)
    truth = int(np.sign(np.cos(np.radians(az))))
    assert clean.signs()[0] == truth and clean.source == "head+height"
    damaged = boxes.copy()
    damaged[:, 3] *= np.linspace(1.0, 1.4, len(boxes)) if truth < 0 else np.linspace(1.4, 1.0, len(boxes))
    by_height = motion_cue(damaged)
    assert by_height.signs()[0] == -truth  # the height alone is fooled
    cue = motion_cue(damaged, heads, feet_cut=True)
    assert cue.source == "head" and cue.signs()[0] != -truth
    if abs(np.sin(np.radians(az))) > 0.5:  # the head crosses the image: its path decides
        assert cue.signs()[0] == truth
    assert np.isfinite(cue.growth_se) and cue.growth_se > 0
    # Uncut feet are believed over a conflicting head (a walker changing speed bends its path).
    assert motion_cue(damaged, heads).source == "height"


def test_growth_is_evidence_only_when_significant():
    assert MotionCue(growth=0.001, travel=0.0, n_frames=30, growth_se=0.0005).signs()[0] == 0
    assert MotionCue(growth=0.001, travel=0.0, n_frames=30, growth_se=0.0002).signs()[0] == 1
    assert MotionCue(growth=-0.001, travel=0.0, n_frames=30, growth_se=0.0002).signs()[0] == -1


def test_motion_cue_checks_the_heads_shape():
    with pytest.raises(ValueError, match="heads"):
        motion_cue(np.ones((5, 4)), np.ones((4, 2)))


def test_head_points_skip_missing_frames_and_few_heads_fall_back_to_the_height():
    crop = np.zeros((50, 20), np.uint8)
    crop[:, 5:15] = 255
    crop[0:4, 8:12] = 255
    boxes = np.array([[100.0 + 3 * t, 40.0, 20.0, 50.0] for t in range(8)])
    heads = head_points([crop, None, *[crop] * 6], boxes)
    assert np.isnan(heads[1]).all() and np.allclose(heads[0], [109.5, 41.5])  # top 8 %: the 4-px head
    assert np.allclose(np.diff(heads[2:, 0]), 3.0)
    boxes[:, 3] = 50.0  # constant whole-pixel heights: no growth, but a finite error (no false certainty)
    cue = motion_cue(boxes, np.where(np.arange(8)[:, None] < 3, heads, np.nan))  # 3 heads: not enough
    assert cue.source == "height" and cue.growth == 0.0 and cue.growth_se > 0 and cue.signs()[0] == 0


@pytest.mark.parametrize("az", [20.0, 140.0, 230.0, 320.0, 80.0])
@pytest.mark.parametrize("el", [-15.0, 30.0])
def test_the_heads_path_tells_the_elevation(az, el):
    """A walker moving along a straight line moves down the image by ``sin e cos a`` for ``-sin a``
    across it: at the true azimuth the head's path gives the elevation within 2 deg (4 deg within 10
    deg of a side view, where the path is nearly level whatever the elevation), and says so."""
    seq = synthesize(SynthSpec(n_cameras=1, n_frames=30, seed=3, azimuths=(az,), elevations=(el,),
                               image_size=(320, 240)))
    cue = motion_cue(*_boxes_and_heads(seq.silhouettes["c0"]))
    e, se = elevation_from_path(cue, az, 0.0)
    side = abs(az % 180 - 90) <= 10
    assert abs(e - el) <= (4.0 if side else 2.0) and 0 < se < 3.0
    # an uncertain azimuth widens the error; one that may lie across the side view leaves no sign
    assert elevation_from_path(cue, az, 5.0)[1] > se
    assert np.isnan(elevation_from_path(cue, az, 6.0 if side else 90.0)[0])


def test_the_paths_elevation_joins_the_shapes_by_their_errors():
    """The shape's elevation 20 deg off with 12 deg of spread moves most of the way to the path's,
    whose error is smaller; without a path, or with one that says nothing, nothing moves."""
    seq = synthesize(SynthSpec(n_cameras=1, n_frames=30, seed=3, azimuths=(40.0,), elevations=(25.0,),
                               image_size=(320, 240)))
    cue = motion_cue(*_boxes_and_heads(seq.silhouettes["c0"]))
    shape = Viewpoint(42.0, 5.0, np.diag([64.0, 144.0]), 12.0, "motion", 1.0, 500)
    joined = with_path_elevation(shape, cue)
    assert joined.elevation_from == "shape+path" and joined.azimuth_deg == shape.azimuth_deg
    assert abs(joined.elevation_deg - 25.0) < 0.35 * 20.0 and joined.covariance[1, 1] < shape.covariance[1, 1]
    assert joined.to_dict()["elevation_from"] == "shape+path"
    assert with_path_elevation(shape, None) is shape
    level = MotionCue(growth=0.0, travel=0.05, n_frames=30)  # no head path measured
    assert with_path_elevation(shape, level) is shape
    side = with_path_elevation(Viewpoint(95.0, 5.0, np.diag([64.0, 144.0]), 12.0, "motion", 1.0, 500), cue)
    assert side.elevation_from == "shape" and side.elevation_deg == 5.0
