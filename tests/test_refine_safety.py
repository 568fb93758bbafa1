"""Feedback that cannot hurt (issue 17): offline refine on damaged silhouettes, the trust test."""

import os
import sys

import numpy as np
import pytest

import dataclasses

from estimator.damage import DAMAGE_KINDS
from estimator.pipeline import CameraTrack, estimate_walk, tracks_from_sequence
from estimator.prior import (FEEDBACK, Prior, PriorConfig, _with_same_phase, priors_for_window, trust_test,
                             trusted_priors, turn_viewpoints)
from estimator.render import Renderer

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))
from eval_refine_damage import damaged, evaluate, make_sequences  # noqa: E402


@pytest.fixture(scope="module")
def model(small_model):
    """The small test model: the feedback must be safe with a coarser model than the default
    one too (bench/eval_refine_damage.py measures the default model; CI need not build it)."""
    return small_model


@pytest.fixture(scope="module")
def renderer():
    with Renderer(FEEDBACK.body) as r:
        yield r


@pytest.fixture(scope="module")
def sequences():
    return make_sequences(2)


@pytest.fixture(scope="module")
def rows(sequences, model, renderer):
    return evaluate(sequences, model, renderer, FEEDBACK, log=lambda *_: None)


@pytest.mark.parametrize("kind", DAMAGE_KINDS)
def test_refine_does_not_lower_the_mean_iou(rows, kind):
    r = rows[kind]
    assert r["refined"].mean() >= r["input"].mean() - 1e-9


@pytest.mark.parametrize("kind", ["holes", "cut_limb"])
def test_refine_repairs_holes_and_cut_limbs(rows, kind):
    r = rows[kind]
    assert r["refined"].mean() > r["input"].mean() + 0.01


def test_a_wrong_estimate_changes_nothing(rows):
    assert {k: r["changed_wrong"] for k, r in rows.items()} == {k: 0 for k in rows}


def test_trust_test_rejects_a_wrong_estimate_and_accepts_a_right_one(sequences, model, renderer):
    seq = damaged(sequences[0], "holes", seed=7)
    tracks = tracks_from_sequence(seq)
    right = estimate_walk(tracks, model)
    untested = PriorConfig(trust=False)
    for est, expected in ((right, True), (turn_viewpoints(right, 90.0), False)):
        priors = priors_for_window(est, tracks, tuple(seq.image_size), renderer=renderer, config=untested)
        trusted = priors_for_window(est, tracks, tuple(seq.image_size), renderer=renderer, config=FEEDBACK)
        for cam in seq.cameras:
            _, trust = trusted_priors(priors[cam], est.cameras[cam].viewpoint, FEEDBACK)
            assert trust.camera or not expected, (cam, trust.reason)  # window agreement alone
            assert bool(trusted[cam]) is expected, cam  # with the turned-viewpoint comparison


def test_trust_test_on_numbers():
    good = np.array([0.85, 0.8, 0.3, np.nan, 0.9])
    t = trust_test(good, spread_deg=10.0, flip="motion", flip_margin=0.05)
    assert t.camera and t.frames.tolist() == [True, True, False, False, True]
    assert not trust_test(good, spread_deg=60.0, flip="motion", flip_margin=0.9).camera
    assert not trust_test(good, spread_deg=10.0, flip="majority", flip_margin=0.02).camera
    assert not trust_test(good * 0.6, spread_deg=10.0, flip="motion", flip_margin=0.5).camera
    bad = trust_test(good, spread_deg=10.0, flip="motion", flip_margin=0.5, rival=0.8)
    assert not bad.camera and not bad.frames.any() and "90 deg" in bad.reason
    # Predicted frames: the window's agreement decides.
    assert trust_test(np.full(3, np.nan), spread_deg=10.0, flip="motion", flip_margin=0.5, window=good).camera


def test_the_walker_at_the_same_phase_raises_the_prior_inside_the_model_only():
    body = np.zeros((100, 40), np.uint8)
    body[:, 10:30] = 255
    limb = body.copy()
    limb[60:100, 30:40] = 255  # a shin, lost on frame 0
    other = body.copy()
    other[60:100, 0:10] = 255  # the other phase: the shin elsewhere
    blob = limb.copy()
    blob[0:10, 0:8] = 255  # a speck the model does not support
    sils = [body, other, limb, blob]
    boxes = np.tile([50.0, 20.0, 40.0, 100.0], (4, 1))
    track = CameraTrack(sils, boxes, image_size=(200, 150))
    phase = np.array([0.0, 0.5, 0.0, 0.02])
    mask = np.zeros((100, 40), np.uint8)
    mask[:, 10:30] = 255
    mask[50:100, 28:40] = 150  # the model's shin, less sure
    prior = Prior(0, (50, 20, 40, 100), (200, 150), mask)
    config = dataclasses.replace(FEEDBACK, same_phase=True)
    out = _with_same_phase(prior, 0, phase, track, config)
    assert np.all(out.mask[60:100, 30:40] == 255)  # both frames at phase 0 have the shin, inside the model
    assert np.all(out.mask[0:10, 0:8] == 0) and np.all(out.mask[60:100, 0:10] == 0)  # not the speck, not phase 0.5
    assert np.array_equal(out.mask[:50], mask[:50])
    # too few frames at the same phase: the prior is the model's
    unchanged = _with_same_phase(prior, 0, phase, track, dataclasses.replace(config, same_phase_frames=3))
    assert np.array_equal(unchanged.mask, mask)


def test_the_same_phase_walker_repairs_cut_limbs_better_than_the_model_alone(sequences, model, renderer, rows):
    alone = evaluate(sequences, model, renderer, dataclasses.replace(FEEDBACK, same_phase=False), ["cut_limb"],
                     wrong=False, log=lambda *_: None)["cut_limb"]
    assert rows["cut_limb"]["refined"].mean() > alone["refined"].mean() + 0.003
