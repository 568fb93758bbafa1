"""Silhouettes reduced to the walker before registration (estimator.cleanup), on damaged input."""

import numpy as np
import pytest

from estimator.cleanup import CleanupConfig, isolate_walker, select_walker, trim_below_feet, trim_shadow
from estimator.damage import DAMAGE_KINDS, blobs, damage, damage_sequence, holes, parse_damage
from estimator.pipeline import (EstimateConfig, _Cloud, _vote, clean_tracks, estimate_walk, tracks_from_sequence,
                                walker_score)
from estimator.sequence import Sequence
from estimator.synth import SynthSpec, synthesize
from estimator.viewpoint import azimuth_difference_deg


@pytest.fixture(scope="module")
def walk():
    return synthesize(SynthSpec(n_cameras=2, n_frames=24, seed=5, azimuths=(60.0, 150.0), elevations=(10.0, 10.0),
                                image_size=(320, 240)))


def damaged(seq, kind, seed=0):
    sils = damage_sequence(seq.silhouettes, kind, seed=seed, truth=seq.truth)
    return Sequence(seq.fps, seq.cameras, seq.image_size, sils, seq.truth)


def isolate(seq, cam, config=None):
    t = tracks_from_sequence(seq)[cam]
    return isolate_walker(t.silhouettes, t.boxes, image_size=seq.image_size, config=config)


def test_damage_is_reproducible_and_checked(walk):
    sil = walk.silhouettes["c0"][3]
    for kind in DAMAGE_KINDS:
        a = damage(sil, kind, np.random.default_rng(1))
        b = damage(sil, kind, np.random.default_rng(1))
        assert np.array_equal(a, b), kind
        assert a.shape == sil.shape and a.dtype == np.uint8
    assert not np.array_equal(damage(sil, "salt", np.random.default_rng(1)), sil)
    with pytest.raises(ValueError, match="unknown damage"):
        damage(sil, "smudge", np.random.default_rng(1))
    # one light casts one shadow: "all" has the one at the feet
    assert "shadow" in parse_damage("all") and "side_shadow" not in parse_damage("all")
    assert "low_wall" not in parse_damage("all") and "fixed_wall" not in parse_damage("all")


def test_a_fixed_wall_stays_on_one_row_of_each_camera_while_the_walker_moves(walk):
    """``fixed_wall`` hides every row below one row of each camera's frame (a real wall's edge),
    so the share of the walker hidden changes as the walker nears; ``low_wall`` hides one share."""
    def rows(s):
        return np.flatnonzero(s.any(axis=1))

    for kind, spread in (("fixed_wall", (0.05, 1.0)), ("low_wall", (0.0, 0.02))):
        walled = damage_sequence(walk.silhouettes, kind, seed=0)
        for cam, frames in walled.items():
            share = np.array([1 - np.ptp(rows(d)) / np.ptp(rows(s)) for d, s in zip(frames, walk.silhouettes[cam])])
            assert 0.1 < np.median(share) < 0.45 and spread[0] <= np.ptp(share) <= spread[1], (kind, cam)
            if kind == "fixed_wall":
                assert len({rows(d)[-1] for d in frames}) == 1, cam  # one row above the wall's edge


def test_combined_damage_is_sized_by_the_walker_and_blobs_stay_away_from_it():
    sil = np.zeros((240, 320), np.uint8)
    sil[60:200, 140:180] = 255  # a 140-px walker
    walker = (140, 60, 40, 140)
    tall = sil.copy()
    tall[200:240, 100:220] = 255  # ... with a shadow that makes its silhouette 180 px tall
    removed = [int(np.count_nonzero(tall) - np.count_nonzero(holes(tall, np.random.default_rng(s), box=walker)))
               for s in range(20)]
    assert max(removed) <= 3 * np.pi * (0.05 * 140 + 1) ** 2  # radius 5 % of the walker's height, not 9 px
    # a frame with no place half a walker's height from it gets no blob (it used to get one anywhere)
    small = np.zeros((150, 120), np.uint8)
    small[10:140, 40:80] = 255
    assert all(np.array_equal(blobs(small, np.random.default_rng(s)), small) for s in range(10))
    for s in range(10):
        out = blobs(sil, np.random.default_rng(s))
        ys, xs = np.nonzero(out & ~sil)
        gap = np.maximum(np.maximum(140 - xs, xs - 180), np.maximum(60 - ys, ys - 200))
        assert ys.size and gap.min() > 0.5 * 140 - 0.06 * 140 * 1.5 - 1
    # single kinds are drawn exactly as before: the walker is the whole silhouette
    for kind, draw in (("holes", holes), ("blobs", blobs)):
        assert np.array_equal(damage(sil, kind, np.random.default_rng(4)), draw(sil, np.random.default_rng(4)))


@pytest.mark.parametrize("kind", ["salt", "blobs", "second_person", "salt+blobs+second_person"])
def test_clutter_is_removed_and_the_walker_kept(walk, kind):
    clean = tracks_from_sequence(walk)
    for cam in walk.cameras:
        sils, boxes, report = isolate(damaged(walk, kind), cam)
        ok = np.isfinite(boxes[:, 0])
        assert ok.sum() >= 0.9 * len(sils)
        # the walker's box, not the clutter's: within 2 px of the clean silhouette's on
        # nearly every frame (clutter that lands next to the walker joins it)
        close = np.abs(boxes[ok] - clean[cam].boxes[ok]).max(axis=1) <= 2
        assert close.mean() >= 0.9, kind
        assert report.cleaned > 0 and report.note()


def test_clean_input_passes_unchanged(walk):
    clean = tracks_from_sequence(walk)
    for cam in walk.cameras:
        sils, boxes, report = isolate(walk, cam)
        np.testing.assert_array_equal(boxes, clean[cam].boxes)
        assert all(np.array_equal(a, b) for a, b in zip(sils, clean[cam].silhouettes))
        assert report.note() is None and report.kept == len(sils)


def test_a_split_off_foot_stays_with_the_walker():
    sil = np.zeros((200, 120), np.uint8)
    sil[20:170, 40:80] = 255  # body
    sil[176:186, 50:75] = 255  # a foot below a 6-px gap (a cut ankle)
    sil[20:30, 5:15] = 255  # a blob away from the body
    sils, boxes, _ = isolate_walker([sil], np.array([[0, 0, 120, 200]], float))
    np.testing.assert_array_equal(boxes[0], [40, 20, 40, 166])


def test_a_walker_torn_by_a_hole_is_kept_whole_and_a_bystander_is_not_joined():
    sil = np.zeros((240, 320), np.uint8)
    sil[20:120, 100:140] = 255  # the body down to the knees (100 px)
    sil[136:170, 104:136] = 255  # the shins and feet, below a 16-px gap (a hole through both knees)
    sil[60:170, 180:212] = 255  # a bystander, one body width aside
    boxes = np.array([[0, 0, 320, 240]], float)
    sils, out, report = select_walker([sil], boxes)
    # 16 px is more than 12 % of the upper piece's height, but the pieces are stacked
    np.testing.assert_array_equal(out[0], [100, 20, 40, 150])
    assert not sils[0][100:116].any() and report.cleaned == 1  # the gap stays, the bystander is gone


def test_a_walker_torn_on_some_frames_is_joined_with_the_window_height():
    frames = []
    for t in range(9):
        sil = np.zeros((240, 320), np.uint8)
        sil[20:170, 100:140] = 255
        if t % 3 == 0:  # torn: a piece below and beside the body, 15 px off its corner (not stacked)
            sil[110:170, 100:140] = 0
            sil[125:170, 65:85] = 255
        frames.append(sil)
    boxes = np.tile([0.0, 0.0, 320.0, 240.0], (9, 1))
    _, out, _ = select_walker(frames, boxes)
    # 15 px: within 12 % of the window's walker (150 px), not of the 90-px piece left on a torn frame
    assert np.all(out[::3, 3] == 150) and np.all(out[::3, 0] == 65)


def test_the_shadow_cut_follows_the_walker_when_the_shadow_leaves_the_frame(walk, small_model):
    shadowed = damaged(walk, "shadow")
    clean = tracks_from_sequence(walk)
    score = lambda s: walker_score(small_model, s)  # noqa: E731
    for cam in walk.cameras:
        c = clean[cam]
        bottom = int(np.median(c.boxes[:, 1] + c.boxes[:, 3]) + 0.25 * np.median(c.boxes[:, 3]))
        assert bottom < 240
        # the frame ends 25 % of a walker's height below the median feet: the shadow leaves it
        # by a length that changes as the walker moves, and reaches the border on most frames
        sils = [s[:bottom] for s in shadowed.silhouettes[cam]]
        seq = Sequence(walk.fps, [cam], (320, bottom), {cam: sils}, None)
        track = tracks_from_sequence(seq)[cam]
        assert np.mean(track.boxes[:, 1] + track.boxes[:, 3] >= bottom) > 0.8
        out, reports = clean_tracks({cam: track}, score=score)
        b = out[cam].boxes
        assert "cut by the image border" not in reports[cam].skipped  # the walker is not, its shadow is
        ok = np.isfinite(b[:, 3])
        assert ok.mean() > 0.9
        err = np.abs(b[ok, 3] / c.boxes[ok, 3] - 1)
        # closer to the walker's height than any one fraction of the silhouettes' could be (the old cut)
        one = min(np.median(np.abs(f * track.boxes[:, 3] / c.boxes[:, 3] - 1)) for f in np.linspace(0.5, 1.0, 101))
        assert np.median(err) < min(one, 0.04) and np.percentile(err, 90) < 0.1, (np.median(err), one)
        # without the model the shadow stays, and the border test takes it for the walker's
        _, plain, report = isolate_walker(track.silhouettes, track.boxes, image_size=(320, bottom))
        assert report.waived == ["cut by the image border"] or report.skipped.get("cut by the image border", 0) > 0


def test_frames_whose_match_or_vote_is_an_outlier_count_less():
    rng = np.random.default_rng(3)
    az, el, w, frame, best = [], [], [], [], []
    for t in range(20):
        bad = t % 4 == 0  # 5 of 20 frames: a poor match that points 60 deg away
        centre = 0.0 if bad else 60.0
        a = centre + rng.normal(0, 3, 10)
        az.append(a % 360)
        el.append(np.full(10, 10.0))
        w.append(np.full(10, 0.1))
        frame.append(np.full(10, t))
        best.append(80.0 + rng.normal(0, 3) if bad else 40.0 + rng.normal(0, 3))
    cloud = _Cloud(np.concatenate(az), np.concatenate(el), np.concatenate(w), np.concatenate(frame), np.array(best))
    plain, _ = _vote(cloud, 20, None, EstimateConfig(frame_outlier_mads=np.inf, vote_outlier_deg=np.inf))
    assert abs(float(azimuth_difference_deg(plain.azimuth_deg, 60.0))) > 10  # one vote per frame: pulled
    for config in (EstimateConfig(), EstimateConfig(frame_outlier_mads=np.inf),
                   EstimateConfig(vote_outlier_deg=np.inf)):
        vp, weight = _vote(cloud, 20, None, config)
        assert abs(float(azimuth_difference_deg(vp.azimuth_deg, 60.0))) < 2
        assert np.all(weight[::4] < 0.1) and np.all(np.delete(weight, np.s_[::4]) > 0.5)


def test_a_larger_bystander_in_a_few_frames_does_not_take_over():
    frames, boxes = [], []
    for t in range(12):
        sil = np.zeros((240, 320), np.uint8)
        x = 40 + 5 * t  # the walker moves right
        sil[60:200, x:x + 40] = 255
        big = 70 if t in (4, 5) else 30  # a bystander, larger than the walker on two frames
        sil[20:20 + 4 * big, 250:250 + big] = 255
        frames.append(sil)
        boxes.append([0, 0, 320, 240])
    sils, out, report = isolate_walker(frames, np.array(boxes, float), config=CleanupConfig(size_tolerance=10))
    np.testing.assert_array_equal(out[:, 0], 40 + 5 * np.arange(12))
    assert report.several == 12


def test_frames_cut_by_the_border_are_skipped_unless_most_are():
    frames = []
    for t in range(10):
        sil = np.zeros((100, 200), np.uint8)
        x = 0 if t < 2 else 20 + 5 * t
        sil[10:90, x:x + 30] = 255
        frames.append(sil)
    boxes = np.tile([0.0, 0.0, 200.0, 100.0], (10, 1))
    _, out, report = isolate_walker(frames, boxes, image_size=(200, 100))
    assert np.isnan(out[:2, 0]).all() and np.isfinite(out[2:, 0]).all()
    assert report.skipped == {"cut by the image border": 2}
    _, out, report = isolate_walker(frames[:2] * 5, boxes, image_size=(200, 100))
    assert np.isfinite(out[:, 0]).all() and report.waived == ["cut by the image border"]


def test_a_frame_merged_with_clutter_is_skipped():
    frames = []
    for t in range(10):
        sil = np.zeros((300, 200), np.uint8)
        sil[40:200, 80:120] = 255
        if t == 6:
            sil[200:250, 60:140] = 255  # something joined to the feet on one frame
        frames.append(sil)
    _, out, report = isolate_walker(frames, np.tile([0.0, 0.0, 200.0, 300.0], (10, 1)))
    assert np.isnan(out[6, 0]) and np.isfinite(np.delete(out[:, 0], 6)).all()
    assert "size unlike its neighbours" in report.note()


def test_a_shadow_at_the_feet_is_cut_off_by_the_model(walk, small_model):
    clean = tracks_from_sequence(walk)
    shadowed = tracks_from_sequence(damaged(walk, "shadow"))
    score = lambda s: walker_score(small_model, s)  # noqa: E731
    for cam in walk.cameras:
        t = shadowed[cam]
        assert np.median(t.boxes[:, 3] / clean[cam].boxes[:, 3]) > 1.2  # the damage is real
        _, boxes, kept = trim_below_feet(t.silhouettes, t.boxes, score)
        assert np.mean(kept < 1.0) > 0.9
        assert np.median(np.abs(boxes[:, 3] / clean[cam].boxes[:, 3] - 1)) < 0.05
        # a clean window is not cut
        _, same, kept = trim_below_feet(clean[cam].silhouettes, clean[cam].boxes, score)
        assert np.all(kept == 1.0) and np.array_equal(same, clean[cam].boxes)


def test_a_shadow_cast_sideways_is_cut_beside_the_feet_not_below(walk, small_model):
    """A low light at the walker's side casts the shadow rising beside the legs: a cut below the
    feet would take the legs with it; the cut beside them leaves the walker's own outline."""
    clean = tracks_from_sequence(walk)
    shadowed = tracks_from_sequence(damaged(walk, "side_shadow"))
    score = lambda s: walker_score(small_model, s)  # noqa: E731
    for cam in walk.cameras:
        t, c = shadowed[cam], clean[cam]
        assert np.median(t.boxes[:, 2] / c.boxes[:, 2]) > 1.5  # the damage is real: twice as wide
        assert np.allclose(t.boxes[:, 3], c.boxes[:, 3], atol=1)  # and not below the feet
        out, boxes, kept, beside = trim_shadow(t.silhouettes, t.boxes, score)
        assert np.mean(beside) > 0.9 and np.all(kept == 1.0)
        assert np.median(np.abs(boxes[:, 2] / c.boxes[:, 2] - 1)) < 0.1
        assert np.median(np.abs(boxes[:, 3] / c.boxes[:, 3] - 1)) < 0.02
        # the cut below the feet alone takes the legs
        _, below, _ = trim_below_feet(t.silhouettes, t.boxes, score)
        assert np.median(below[:, 3] / c.boxes[:, 3]) < 0.9
        # a shadow at the feet is still cut below them, and a clean window not at all
        low = tracks_from_sequence(damaged(walk, "shadow"))[cam]
        _, boxes, kept, beside = trim_shadow(low.silhouettes, low.boxes, score)
        assert not beside.any() and np.mean(kept < 1.0) > 0.9
        assert np.median(np.abs(boxes[:, 3] / c.boxes[:, 3] - 1)) < 0.05
        same, boxes, kept, beside = trim_shadow(c.silhouettes, c.boxes, score)
        assert not beside.any() and np.all(kept == 1.0) and np.array_equal(boxes, c.boxes)


def test_a_walker_hidden_below_the_knees_is_said_and_left_as_seen(walk, small_model):
    """Behind a low wall the silhouettes end in a straight cut: the report says something in front
    hides the lowest part (the estimate then matches the visible part: tests/test_occlusion.py);
    the silhouettes are left as they are. Nothing else is taken for a wall."""
    score = lambda s: walker_score(small_model, s)  # noqa: E731
    walled = tracks_from_sequence(damaged(walk, "low_wall"))
    out, reports = clean_tracks(walled, score=score)
    for cam in walk.cameras:
        assert reports[cam].hidden_by == "something in front" and "looks hidden" in reports[cam].note()
        assert np.array_equal(out[cam].boxes, walled[cam].boxes)
    for kind in ("clean", "shadow", "holes"):
        t = tracks_from_sequence(walk if kind == "clean" else damaged(walk, kind))
        _, reports = clean_tracks(t, score=score)
        assert not any(r.hidden_by for r in reports.values()), kind


def test_the_cuts_are_searched_only_where_the_walker_does_not_fit(walk, small_model):
    """A window whose uncut silhouettes fit the examples costs one scoring of its sampled
    frames; a shadowed one is searched over every cut (CleanupConfig.cut_search)."""
    config = CleanupConfig()
    for name, expect_search in (("clean", False), ("shadow", True)):
        t = tracks_from_sequence(walk if name == "clean" else damaged(walk, "shadow"))[walk.cameras[0]]
        scored = []

        def score(sils):
            scored.append(len(sils))
            return walker_score(small_model, sils)

        trim_below_feet(t.silhouettes, t.boxes, score, config=config)
        assert scored[0] == config.cut_frames  # the uncut frames first
        assert (len(scored) > 1) == expect_search, name
        if expect_search:
            assert scored[1] == config.cut_frames * (len(config.cuts) - 1)


@pytest.mark.parametrize("kind", ["salt", "blobs", "shadow", "side_shadow", "second_person"])
def test_estimate_on_damaged_silhouettes_stays_near_the_clean_one(walk, small_model, kind):
    ref = estimate_walk(tracks_from_sequence(walk), small_model)
    est = estimate_walk(tracks_from_sequence(damaged(walk, kind)), small_model)
    before = estimate_walk(tracks_from_sequence(damaged(walk, kind)), small_model, config=EstimateConfig(cleanup=None))
    for cam in walk.cameras:
        a0, a1 = ref.cameras[cam].viewpoint.azimuth_deg, est.cameras[cam].viewpoint.azimuth_deg
        assert abs(float(azimuth_difference_deg(a1, a0))) <= 10, (kind, cam, a0, a1)
        assert est.cameras[cam].notes  # what was removed is said
    worst_before = max(abs(float(azimuth_difference_deg(before.cameras[c].viewpoint.azimuth_deg,
                                                        ref.cameras[c].viewpoint.azimuth_deg))) for c in walk.cameras)
    assert worst_before > 10  # and without the clean-up the damage does move the estimate
    result = est.to_result()
    assert any(result["cameras"][c]["notes"] for c in walk.cameras)


def test_a_limb_cut_on_every_frame_does_not_move_the_viewpoint(walk, small_model):
    # a forearm or shin erased on every frame (drawn afresh each frame); cf. docs/ROBUSTNESS.md
    tracks = tracks_from_sequence(damaged(walk, "cut_limb"))
    est = estimate_walk(tracks, small_model)
    plain = estimate_walk(tracks, small_model, config=EstimateConfig(frame_outlier_mads=np.inf, vote_outlier_deg=np.inf,
                                                                     phase_refine=False))
    truth = walk.truth["cameras"]
    err = [abs(float(azimuth_difference_deg(e.cameras[c].viewpoint.azimuth_deg, truth[c]["azimuth_deg"])))
           for e in (est, plain) for c in walk.cameras]
    assert max(err[:2]) <= 5.0, err
    assert max(err[2:]) > 10.0, err  # one vote per frame, each from every phase: the cut frames pull it away


def test_cli_synth_damage_and_estimate(small_model_path, tmp_path, capsys):
    from service.cli import main

    seq = tmp_path / "seq"
    assert main(["synth", "--out", str(seq), "--cameras", "2", "--frames", "16", "--seed", "3",
                 "--size", "320,240", "--damage", "salt+blobs"]) == 0
    out = tmp_path / "r.json"
    assert main(["estimate", str(seq), "--out", str(out), "--model", small_model_path]) == 0
    import json

    result = json.loads(out.read_text())
    assert any("removed" in n for c in result["cameras"].values() for n in c["notes"])
    capsys.readouterr()
    assert main(["synth", "--out", str(tmp_path / "x"), "--damage", "smudge"]) == 2
    assert "unknown damage" in capsys.readouterr().err


def test_a_silhouette_of_more_pieces_than_16_bit_labels_is_cleaned():
    """Speckle over a large crop (90,000 isolated pixels and a walker): labelled, not an error."""
    sil = np.zeros((600, 600), np.uint8)
    sil[::2, ::2] = 255
    sil[100:500, 250:350] = 255  # the walker
    sils, boxes, report = select_walker([sil], np.array([[0.0, 0.0, 600.0, 600.0]]))
    assert report.kept == 1 and report.cleaned == 1
    assert boxes[0, 3] >= 400  # the walker, not a speck
