"""Silhouette priors (§7.1): rendering, registration onto observations, prediction, fusion, CLI."""

import dataclasses
import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from capture.scene import iou
from estimator.camera import Camera
from estimator.gait import GaitStyle, load_gait
from estimator.joints import N_JOINTS
from estimator.pipeline import CameraTrack, WalkEstimate, crop_to_box, estimate_walk, tracks_from_sequence
from estimator.prior import (
    Prior,
    PriorConfig,
    body_extent,
    extrapolate,
    predict_phases,
    predict_priors,
    prior_from_render,
    priors_for_window,
    refine_silhouette,
    render_body,
    rotate_prior,
    silhouette_centroids,
    soften,
)
from estimator.render import Renderer
from estimator.sequence import read_sequence, write_sequence
from estimator.skeleton import BodyShape, forward_kinematics
from estimator.synth import SynthSpec, synthesize
from service.cli import main

SIZE = (320, 240)


@pytest.fixture(scope="module")
def renderer():
    with Renderer(BodyShape()) as r:
        yield r


@pytest.fixture(scope="module")
def sequence():
    # The model's own body, so that a perfect prior is possible.
    return synthesize(SynthSpec(n_cameras=2, n_frames=16, seed=1, azimuths=(90.0, 40.0), elevations=(5.0, 20.0),
                                image_size=SIZE, shape=BodyShape()))


def _estimate(phase):
    phase = np.asarray(phase, float)
    T = len(phase)
    return WalkEstimate(phase=phase, states=np.round(phase * 20).astype(int) % 20, joints3d=np.zeros((T, N_JOINTS, 3)),
                        cameras={}, log_prob=0.0, half_cycle_margin=0.0)


def test_predict_phases_continues_the_path_across_the_cycle():
    est = _estimate((0.8 + 0.05 * np.arange(6)) % 1.0)
    np.testing.assert_allclose(predict_phases(est, 3), [0.1, 0.15, 0.2], atol=1e-9)
    assert predict_phases(est, 0).shape == (0,)
    with pytest.raises(ValueError, match="n_ahead"):
        predict_phases(est, -1)


def test_extrapolate_continues_a_straight_walk():
    t = np.arange(10.0)
    boxes = np.stack([100 + 4 * t, 50 + 0 * t, 40 + 0 * t, 120 + 0.5 * t], 1)
    boxes[3] = np.nan
    pred = extrapolate(boxes, 2)
    np.testing.assert_allclose(pred[:, 0], [140, 144], atol=1e-6)
    np.testing.assert_allclose(pred[:, 3], [125, 125.5], atol=1e-6)
    assert np.isnan(extrapolate(np.full((3, 4), np.nan), 2)).all()


def test_silhouette_centroids_follow_the_body_not_its_box():
    """A walker whose box widens on one side (a swinging leg) while the body stays put."""
    sils, boxes = [], []
    for t in range(4):
        sil = np.zeros((40, 10 + 4 * t), np.uint8)
        sil[:, :10] = 255  # the body: 10 px wide at x = 100 + 3 t
        sil[30:, 10:] = 255 if t else 0  # a leg swinging out to the right, 10 rows
        sils.append(sil)
        boxes.append([100 + 3 * t, 20, sil.shape[1], 40])
    sils.append(None)
    boxes.append([np.nan] * 4)
    c = silhouette_centroids(CameraTrack(sils, np.array(boxes, float), full_frame=True))
    assert np.isnan(c[4]).all()
    np.testing.assert_allclose(c[0], [104.5, 39.5])
    box_centre = np.array([b[0] + b[2] / 2 - 0.5 for b in boxes[:4]])
    # The body moves 3 px a frame; the box centre 5 (the leg adds 2), the centroid less.
    assert np.all(np.diff(box_centre) == 5) and np.all(np.diff(c[:4, 0]) < 4.2), c
    future = extrapolate(c, 2)  # a straight line through the known rows only
    assert future.shape == (2, 2) and np.isfinite(future).all()
    np.testing.assert_allclose(extrapolate(np.array([[0.0, 1.0], [2.0, 1.0], [np.nan, np.nan]]), 2),
                               [[6.0, 1.0], [8.0, 1.0]])


def test_soften_is_confident_inside_and_unsure_at_the_edge():
    m = np.zeros((60, 60), np.uint8)
    m[10:50, 20:40] = 255
    s = soften(m, band_px=2.0)
    assert s[30, 30] > 250 and s[30, 5] < 5
    assert 80 < s[30, 20] < 200  # on the outline


def test_prior_registers_the_render_onto_the_observation(renderer):
    body = BodyShape()
    phase = np.array([0.3])
    skel = forward_kinematics(load_gait().angles(phase), body)[0]
    cam = Camera(70.0, 10.0, distance=9.0, image_size=SIZE, focal_px=500.0, target=tuple(skel[:N_JOINTS].mean(0) + [0.4, 0, 0]))
    observed_full, _ = renderer.render(skel, cam)
    crop, box = crop_to_box(observed_full)
    rendered = render_body(phase, 70.0, 10.0, renderer=renderer)[0]
    assert rendered.shape[0] == rendered.shape[1] and rendered.any()
    prior = prior_from_render(rendered, crop, box, SIZE, frame_index=7)
    assert prior.frame_index == 7 and prior.image_size == SIZE and prior.mask.dtype == np.uint8
    full = prior.full_mask()
    # Same body, same pose: orthographic vs perspective at 9 m only.
    assert iou(full >= 128, observed_full) > 0.88
    assert full[observed_full == 0].mean() < 20
    wrong = rotate_prior(prior)
    assert iou(wrong.full_mask() >= 128, observed_full) < 0.5


def _fragments(sequence, seed=0):
    """Camera c0 torn as at low contrast: per frame only large random blobs, ~35% of the body."""
    rng = np.random.default_rng(seed)
    tracks = tracks_from_sequence(sequence)
    sils, boxes = [], []
    for full in sequence.silhouettes["c0"]:
        field = cv2.resize(rng.normal(size=(4, 4)), full.shape[::-1], interpolation=cv2.INTER_CUBIC)
        body = full > 0
        keep = body & (field > np.quantile(field[body], 0.65))
        crop, box = crop_to_box(keep.astype(np.uint8) * 255)
        sils.append(crop)
        boxes.append(box)
    return tracks["c0"], CameraTrack(sils, np.array(boxes, float), full_frame=True)


def test_body_extent_finds_the_whole_walker_from_fragments(sequence):
    whole, torn = _fragments(sequence)
    truth = body_extent(whole)
    ext = body_extent(torn)
    height = np.median(whole.boxes[:, 3])
    tops, bottoms = whole.boxes[:, 1], whole.boxes[:, 1] + whole.boxes[:, 3]
    # The fragments' own boxes are far off; the window's envelope is not.
    assert np.median(torn.boxes[:, 3]) < 0.75 * height
    assert np.abs(ext[:, 1] - tops).max() < 0.06 * height
    assert np.abs(ext[:, 2] - bottoms).max() < 0.06 * height
    assert np.abs(ext[:, 0] - truth[:, 0]).max() < 0.1 * height
    # Complete silhouettes give their own extent back.
    assert np.abs(truth[:, 2] - truth[:, 1] - height).max() < 0.06 * height
    with pytest.raises(ValueError, match="quantile"):
        body_extent(torn, quantile=0.5)


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_a_torn_observation_gets_the_whole_body_as_prior(sequence, renderer, seed):
    whole, torn = _fragments(sequence, seed=seed)
    ext = body_extent(torn)
    phase = np.array([sequence.truth["frames"][4]["phase"]])
    az, el = sequence.truth["cameras"]["c0"]["azimuth_deg"], sequence.truth["cameras"]["c0"]["elevation_deg"]
    rendered = render_body(phase, az, el, renderer=renderer)[0]
    truth = sequence.silhouettes["c0"][4]
    args = (rendered, torn.silhouettes[4], torn.boxes[4], SIZE)
    placed = iou(prior_from_render(*args, frame_index=4, extent=tuple(ext[4])).full_mask() >= 128, truth)
    registered = iou(prior_from_render(*args, frame_index=4).full_mask() >= 128, truth)
    # Registered onto the fragment the body is far too small or misplaced; the
    # window's extent places it (the evidence gate still keeps it near the fragment).
    assert placed > 0.55 and placed > registered + 0.2, (placed, registered)


@pytest.mark.parametrize("seed", [0, 3])  # the window's last frame is a fragment
def test_predicted_priors_after_torn_frames_cover_the_walker(small_model, sequence, renderer, seed):
    whole, torn = _fragments(sequence, seed=seed)
    est = estimate_walk({"c0": whole}, small_model)
    n = 12
    window = dataclasses.replace(est, phase=est.phase[:n])

    def predicted(track, torn_at):
        head = CameraTrack(track.silhouettes[:n], track.boxes[:n], full_frame=True)
        ahead = predict_priors(window, {"c0": head}, SIZE, 3, renderer=renderer, config=PriorConfig(torn=torn_at))
        return np.mean([iou(p.full_mask() >= 128, sequence.silhouettes["c0"][p.frame_index]) for p in ahead["c0"]])

    assert torn.boxes[n - 1, 3] < 0.6 * whole.boxes[n - 1, 3]
    complete = predicted(whole, 0.1)
    placed, registered = predicted(torn, 0.1), predicted(torn, float("inf"))
    # After a torn last frame the prediction placed by the window's extent is nearly
    # as good as after a complete one; registered onto the fragment it is not. (Since
    # predicted frames are gated at the widest reach, session 37, the complete one
    # went from IoU 0.49 to 0.60 and the placed one stayed at 0.41-0.42: 0.7 -> 0.65.)
    assert placed > 0.65 * complete and placed > registered + 0.15, (placed, registered, complete)


def test_prior_checks_its_box():
    with pytest.raises(ValueError, match="shape"):
        Prior(0, (0, 0, 4, 4), (10, 10), np.zeros((3, 4), np.uint8))
    with pytest.raises(ValueError, match="inside"):
        Prior(0, (8, 0, 4, 4), (10, 10), np.zeros((4, 4), np.uint8))


def test_priors_for_window_cover_the_observed_walker(small_model, sequence, renderer):
    tracks = tracks_from_sequence(sequence)
    est = estimate_walk(tracks, small_model)
    priors = priors_for_window(est, tracks, SIZE, renderer=renderer, first_index=100)
    for cam in sequence.cameras:
        assert [p.frame_index for p in priors[cam]] == list(range(100, 116))
        ious = [iou(p.full_mask() >= 128, sequence.silhouettes[cam][p.frame_index - 100]) for p in priors[cam]]
        assert np.median(ious) > 0.7, ious
    ahead = predict_priors(est, tracks, SIZE, 3, renderer=renderer, first_index=100)
    assert [p.frame_index for p in ahead["c0"]] == [116, 117, 118]
    # The walker keeps moving: the predicted prior is displaced along the box motion.
    last = priors["c0"][-1]
    dx = (ahead["c0"][0].box[0] + ahead["c0"][0].box[2] / 2) - (last.box[0] + last.box[2] / 2)
    step = np.nanmedian(np.diff(tracks["c0"].boxes[:, 0] + tracks["c0"].boxes[:, 2] / 2))
    assert abs(dx - step) < max(3.0, abs(step))


def test_predicted_priors_keep_the_limbs_of_frames_not_seen_yet(small_model, renderer):
    """A prediction's only evidence is the window's last silhouette, whose legs and arms are
    elsewhere by the predicted frame: gated tightly by it (as a complete frame of the window
    is), the priors lost the swinging limbs (mean coverage of the true silhouette 0.55, IoU
    0.47 here)."""
    style, shape = GaitStyle(stride=1.15, arm_swing=1.4, leg_lift=1.2), BodyShape(height=1.8, girth=0.9)
    covered, ious = [], []
    for seed in (1, 2, 3):  # a walker whose body and gait are not the model's
        seq = synthesize(SynthSpec(n_cameras=2, n_frames=26, seed=seed, image_size=SIZE, style=style, shape=shape))
        head = {c: CameraTrack(t.silhouettes[:16], t.boxes[:16], full_frame=True)
                for c, t in tracks_from_sequence(seq).items()}
        ahead = predict_priors(estimate_walk(head, small_model), head, SIZE, 10, renderer=renderer)
        for cam, priors in ahead.items():
            assert [p.frame_index for p in priors] == list(range(16, 26))
            for p in priors:
                mask, truth = p.full_mask() >= 128, seq.silhouettes[cam][p.frame_index] > 0
                covered.append(np.count_nonzero(mask & truth) / np.count_nonzero(truth))
                ious.append(iou(mask, truth))
    # Medians per camera and seed: 0.61-0.94 covered, IoU 0.45-0.70 (not a blob over everything).
    assert np.mean(covered) > 0.65 and np.mean(ious) > 0.5, (np.mean(covered), np.mean(ious))


def _true_prior(sequence, renderer, k: int):
    """Camera c0's silhouette of frame ``k`` and the prior rendered at its true phase and
    viewpoint, registered onto it."""
    truth = sequence.silhouettes["c0"][k]
    crop, box = crop_to_box(truth)
    phase = np.array([sequence.truth["frames"][k]["phase"]])
    az, el = sequence.truth["cameras"]["c0"]["azimuth_deg"], sequence.truth["cameras"]["c0"]["elevation_deg"]
    return truth, prior_from_render(render_body(phase, az, el, renderer=renderer)[0], crop, box, SIZE,
                                    frame_index=k)


def test_refine_silhouette_fills_holes_and_drops_far_blobs(sequence, renderer):
    truth, prior = _true_prior(sequence, renderer, 5)
    damaged = truth.copy()
    ys, xs = np.nonzero(truth)
    cy, cx = int(ys.mean()), int(xs.mean())
    damaged[cy - 6 : cy + 6, cx - 3 : cx + 3] = 0  # a hole in the torso
    cv2.circle(damaged, (10, 10), 5, 255, -1)  # a blob far away
    fixed = refine_silhouette(damaged, prior.full_mask())
    assert iou(fixed, truth) > iou(damaged, truth) + 0.02
    assert fixed[10, 10] == 0 and fixed[cy, cx] == 255
    with pytest.raises(ValueError, match="same shape"):
        refine_silhouette(damaged, prior.full_mask()[:-1])


def test_estimator_prior_imports_no_capture_or_network():
    code = ("import sys, estimator.prior; bad = [m for m in ('capture', 'fastapi', 'zenoh', 'rerun') if m in sys.modules];"
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_cli_refine_silhouette_sequence(small_model_path, sequence, tmp_path):
    damaged = {c: [s.copy() for s in sils] for c, sils in sequence.silhouettes.items()}
    for sils in damaged.values():
        for s in sils:
            ys, xs = np.nonzero(s)
            s[int(ys.mean()) - 5 : int(ys.mean()) + 5, int(xs.mean()) - 2 : int(xs.mean()) + 2] = 0
    src = tmp_path / "seq"
    write_sequence(src, type(sequence)(fps=sequence.fps, cameras=sequence.cameras, image_size=sequence.image_size,
                                       silhouettes=damaged, truth=sequence.truth))
    out = tmp_path / "out"
    assert main(["refine", str(src), "--out", str(out), "--model", small_model_path]) == 0
    refined = read_sequence(out)
    for c in sequence.cameras:
        before = np.mean([iou(a, b) for a, b in zip(damaged[c], sequence.silhouettes[c])])
        after = np.mean([iou(a, b) for a, b in zip(refined.silhouettes[c], sequence.silhouettes[c])])
        assert after > before, (c, before, after)
    summary = json.loads((out / "refine.json").read_text())
    assert summary["input"] == "silhouettes" and len(summary["estimate"]["frames"]) == 16
    assert main(["refine", str(tmp_path / "nope"), "--out", str(out)]) == 2
    os.makedirs(tmp_path / "empty")
    assert main(["refine", str(tmp_path / "empty"), "--out", str(out)]) == 2


def test_a_prior_that_does_not_explain_the_evidence_is_weakened_or_dropped(sequence, renderer):
    from estimator.prior import explained, weigh

    truth, prior = _true_prior(sequence, renderer, 3)
    assert explained(prior, truth) > 0.9 and weigh(prior, explained(prior, truth)) is prior
    wrong = rotate_prior(prior)
    assert explained(wrong, truth) < 0.5 and weigh(wrong, explained(wrong, truth)) is None
    half = weigh(prior, 0.65)
    assert half.mask.max() < prior.mask.max() and half.box == prior.box
    assert np.isnan(explained(prior, np.zeros_like(truth)))


def test_cli_refine_videos(small_model_path, tmp_path):
    from capture.synthetic import SyntheticSource

    src = SyntheticSource.from_spec("seed=2,azimuth=80,elevation=10,size=320x240,empty=20,pass=24,gap=2,contrast=0.5")
    seq = tmp_path / "vid"
    seq.mkdir()
    writer = cv2.VideoWriter(str(seq / "c0.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (320, 240))
    for k in range(46):
        writer.write(src.render(k).image)
    writer.release()
    src.close()
    out = tmp_path / "out"
    assert main(["refine", str(seq), "--out", str(out), "--model", small_model_path, "--warmup", "20"]) == 0
    refined = read_sequence(out)
    assert refined.cameras == ["c0"] and refined.image_size == (320, 240)
    assert sum(s is not None for s in refined.silhouettes["c0"]) >= 20
    assert json.loads((out / "refine.json").read_text())["input"] == "video"
    # A job's second pass decodes no more frames per video than its first (its max_frames)
    from capture.refine import video_frames

    assert sum(1 for _ in video_frames(seq / "c0.avi", 7)()) == 7
    assert sum(1 for _ in video_frames(seq / "c0.avi")()) == 46
