"""Registration (common height, centroid, principal axis) and the eq. 8 distance."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimator._stick_examples import make_examples, style_table
from estimator.registration import distance, register, register_shares, transform_points

STYLES = style_table(4, rng=1)


def _walkers(n=12, *, px_per_m=75.0, crop=(160, 112), seed=0):
    g = np.random.default_rng(seed)
    return make_examples(
        g.uniform(0, 1, n), g.uniform(0, 360, n), g.uniform(-20, 35, n), g.integers(0, 4, n),
        styles=STYLES, crop=crop, px_per_m=px_per_m,
    )


@pytest.fixture(scope="module")
def walkers():
    return _walkers()


@pytest.fixture(scope="module")
def means(walkers):
    """Continuous 'cluster means': blurred registered silhouettes of other walkers."""
    reg, _ = register(_walkers(30, seed=5).silhouettes)
    return np.stack([cv2.GaussianBlur(r, (7, 7), 1.5) for r in reg]).clip(0, 1)


def _mismatch(a, b):
    """Fraction of foreground pixels that differ between two registered binaries."""
    return np.abs(a - b).sum(axis=(-1, -2)) / np.maximum(a.sum(axis=(-1, -2)), 1)


def test_output_shape_values_and_fit(walkers):
    reg, tf = register(walkers.silhouettes, size=(64, 48))
    assert reg.shape == (len(walkers), 64, 48) and reg.dtype == np.float32
    assert set(np.unique(reg)) <= {0.0, 1.0}
    assert tf.valid.all()
    # Height is normalised: the foreground spans ~0.8 * 64 rows, centroid at the centre.
    rows = np.flatnonzero(reg.any(axis=2).sum(0))
    assert rows.size > 0
    for r in reg:
        ys = np.flatnonzero(r.any(1))
        assert abs((ys[-1] - ys[0] + 1) - 0.8 * 64) <= 2.5
        yy, xx = np.nonzero(r)
        assert abs(yy.mean() - 31.5) < 1.0 and abs(xx.mean() - 23.5) < 1.0
    # Nothing touches the border (the canvas holds a whole walker).
    assert reg[:, [0, -1], :].sum() == 0 and reg[:, :, [0, -1]].sum() == 0


def test_translation_invariance(walkers, means):
    sil = walkers.silhouettes
    big = np.zeros((len(sil), 300, 260), np.uint8)
    big[:, 57 : 57 + sil.shape[1], 91 : 91 + sil.shape[2]] = sil
    a, _ = register(sil)
    b, _ = register(big)
    np.testing.assert_array_equal(a, b)  # integer shifts: identical registration
    # Sub-pixel shift (re-drawn, so rasterisation differs): distances barely move.
    shifted = _walkers(px_per_m=75.0, crop=(170, 120))
    c, _ = register(shifted.silhouettes)
    assert np.median(_mismatch(a, c)) < 0.05
    da, dc = distance(a, means), distance(c, means)
    assert np.all(np.abs(da - dc) <= 0.1 * da)
    assert (da.argmin(1) == dc.argmin(1)).mean() >= 0.9


@pytest.mark.parametrize("factor", [0.3, 0.5, 1.7, 3.0])
def test_scale_invariance(means, factor):
    # The same silhouettes resampled by `factor` (area-averaged and re-thresholded
    # when shrinking): registration must undo the scale.
    hi = _walkers(px_per_m=150.0, crop=(320, 224)).silhouettes
    interp = cv2.INTER_AREA if factor < 1 else cv2.INTER_NEAREST
    scaled = np.stack([cv2.resize(s, None, fx=factor, fy=factor, interpolation=interp) for s in hi])
    scaled = np.where(scaled >= 128, 255, 0).astype(np.uint8)
    a, ta = register(hi)
    b, tb = register(scaled)
    np.testing.assert_allclose(tb.scale * factor, ta.scale, rtol=0.03)
    assert np.median(_mismatch(a, b)) < 0.06
    da, db = distance(a, means), distance(b, means)
    assert np.median(np.abs(da - db) / da) < 0.05
    assert (da.argmin(1) == db.argmin(1)).mean() >= 0.9


@pytest.mark.parametrize("angle", [-8.0, -3.0, 4.0, 10.0])
def test_small_rotation_invariance(walkers, means, angle):
    sil = np.zeros((len(walkers), 200, 200), np.uint8)
    sil[:, 20:180, 44:156] = walkers.silhouettes
    rot = cv2.getRotationMatrix2D((100.0, 100.0), angle, 1.0)
    turned = np.stack([cv2.warpAffine(s, rot, (200, 200), flags=cv2.INTER_NEAREST) for s in sil])
    a, ta = register(sil)
    b, tb = register(turned)
    # cv2's positive angle is counter-clockwise on screen, i.e. towards -v from +u.
    np.testing.assert_allclose(((tb.angle_deg - ta.angle_deg + angle) + 45) % 90 - 45, 0, atol=0.5)
    assert np.median(_mismatch(a, b)) < 0.08
    da, db = distance(a, means), distance(b, means)
    assert np.median(np.abs(da - db) / da) < 0.1
    # Without axis alignment, rotation shows up in the distance.
    c, _ = register(turned, rotate=False)
    a0, _ = register(sil, rotate=False)
    if abs(angle) >= 8:
        assert np.median(_mismatch(a0, c)) > np.median(_mismatch(a, b))


def test_transform_points_maps_centroid_and_joints(walkers):
    reg, tf = register(walkers.silhouettes)
    c = transform_points(tf, tf.centroid[:, None, :])
    np.testing.assert_allclose(c[:, 0], np.broadcast_to([23.5, 31.5], (len(walkers), 2)), atol=1e-9)
    j = transform_points(tf, walkers.joints2d)
    assert j.shape == (len(walkers), 13, 2)
    # Joints land on the registered silhouette (most of them, a joint may sit on an edge).
    u = np.clip(np.round(j[..., 0]).astype(int), 0, 47)
    v = np.clip(np.round(j[..., 1]).astype(int), 0, 63)
    on = reg[np.arange(len(reg))[:, None], v, u]
    assert on.mean() > 0.9
    # Similarity: the linear part is a scaled rotation.
    lin = tf.matrix[:, :, :2]
    gram = lin @ np.swapaxes(lin, 1, 2)
    np.testing.assert_allclose(gram, tf.scale[:, None, None] ** 2 * np.eye(2), rtol=1e-9, atol=1e-12)


def test_empty_and_mixed_sizes():
    s1 = np.zeros((50, 30), np.uint8)
    s2 = np.zeros((90, 70), np.uint8)
    cv2.ellipse(s2, (35, 45), (10, 30), 0, 0, 360, 255, -1)
    reg, tf = register([s1, s2, s2 > 0])
    assert tf.valid.tolist() == [False, True, True]
    assert reg[0].sum() == 0 and np.isnan(tf.matrix[0]).all()
    np.testing.assert_array_equal(reg[1], reg[2])  # bool or 0/255, same result


def test_invalid_input():
    with pytest.raises(ValueError, match=r"\(T, H, W\)"):
        register(np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="height_fraction"):
        register(np.zeros((1, 10, 10), np.uint8), height_fraction=1.5)
    with pytest.raises(ValueError, match="size"):
        register(np.zeros((1, 10, 10), np.uint8), size=(2, 2))
    with pytest.raises(ValueError, match="same"):
        distance(np.zeros((1, 8, 8)), np.zeros((3, 8, 9)))


def test_distance_is_eq8():
    g = np.random.default_rng(3)
    a = (g.random((7, 16, 12)) < 0.4).astype(np.float32)
    b = g.random((5, 16, 12)).astype(np.float32)
    b[0] = 0.0
    b[1] = 1.0
    d = distance(a, b)
    # Literal eq. 8: sum(max(s_b' * s_c, s_b * s_c')), ' = 1 - s.
    lit = np.maximum((1 - a)[:, None] * b[None], a[:, None] * (1 - b)[None]).sum(axis=(2, 3))
    np.testing.assert_allclose(d, lit, rtol=1e-5, atol=1e-3)
    assert d.shape == (7, 5) and d.dtype == np.float32
    # Against an all-zero or all-one mean it is the Hamming distance.
    np.testing.assert_allclose(d[:, 0], a.sum(axis=(1, 2)))
    np.testing.assert_allclose(d[:, 1], (1 - a).sum(axis=(1, 2)))
    # A single 2-D silhouette works too.
    np.testing.assert_allclose(distance(a[3], b), d[3:4], rtol=1e-5)


def test_identical_binary_silhouettes_have_distance_zero(walkers):
    reg, _ = register(walkers.silhouettes)
    d = distance(reg, reg)  # each binary silhouette against itself as a 0/1 "mean"
    np.testing.assert_array_equal(np.diag(d), 0.0)
    off = d[~np.eye(len(d), dtype=bool)]
    assert (off > 0).all()


def test_register_shares_is_register_at_each_share(walkers):
    """One measurement per silhouette, placed at several hidden shares: the same canvases as
    :func:`register` gives at each share (and an empty silhouette invalid at all of them)."""
    sils = [*walkers.silhouettes[:5], np.zeros((40, 30), np.uint8)]
    shares = (0.0, 0.1, 0.35)
    out, valid = register_shares(sils, shares, top=9.5)
    assert out.shape == (3, 6, 64, 48) and valid.tolist() == [True] * 5 + [False]
    for k, f in enumerate(shares):
        ref, tf = register(sils, hidden=f, top=9.5)
        assert np.array_equal(out[k], ref) and np.array_equal(valid, tf.valid)
    with pytest.raises(ValueError, match="hidden shares"):
        register_shares(sils, (0.2, 1.0), top=9.5)
