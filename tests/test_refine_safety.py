"""Feedback that cannot hurt (issue 17): offline refine on damaged silhouettes, the trust test."""

import os
import sys

import numpy as np
import pytest

from estimator.damage import DAMAGE_KINDS
from estimator.pipeline import estimate_walk, tracks_from_sequence
from estimator.prior import FEEDBACK, PriorConfig, priors_for_window, trust_test, trusted_priors, turn_viewpoints
from estimator.render import Renderer

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))
from eval_refine_damage import damaged, evaluate, make_sequences  # noqa: E402


@pytest.fixture(scope="module")
def model():
    from service.cli.model import get_default_model

    return get_default_model()


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
