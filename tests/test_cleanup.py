"""Silhouettes reduced to the walker before registration (estimator.cleanup), on damaged input."""

import numpy as np
import pytest

from estimator.cleanup import CleanupConfig, isolate_walker, trim_below_feet
from estimator.damage import DAMAGE_KINDS, damage, damage_sequence
from estimator.pipeline import EstimateConfig, estimate_walk, tracks_from_sequence, walker_score
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
        _, boxes, f = trim_below_feet(t.silhouettes, t.boxes, score)
        assert f < 1.0
        assert np.median(np.abs(boxes[:, 3] / clean[cam].boxes[:, 3] - 1)) < 0.1
        # a clean window is not cut
        _, same, f = trim_below_feet(clean[cam].silhouettes, clean[cam].boxes, score)
        assert f == 1.0 and np.array_equal(same, clean[cam].boxes)


@pytest.mark.parametrize("kind", ["salt", "blobs", "shadow", "second_person"])
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
