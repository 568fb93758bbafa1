"""Exemplar bank: packed Hamming distances and the (phase, viewpoint) lookup."""

import numpy as np
import pytest

from estimator.exemplars import ExemplarIndex, hamming, pack


def test_hamming_equals_eq8_on_binary_silhouettes():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(5, 64, 48)) > 0.6
    b = rng.uniform(size=(7, 64, 48)) > 0.4
    got = hamming(pack(a), pack(b))
    # eq. 8 with a binary "mean": sum(max(a' b, a b')) = number of differing pixels.
    expected = np.array([[np.sum(np.maximum(~x & y, x & ~y)) for y in b] for x in a])
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(hamming(pack(a), pack(a)).diagonal(), 0)


def test_rows_at_returns_every_phase_at_the_nearest_viewpoints():
    phase, az, el = (m.ravel() for m in np.meshgrid(np.arange(20) / 20, np.arange(0, 360, 5.0), [-10.0, 0.0, 10.0], indexing="ij"))
    n = len(phase)
    index = ExemplarIndex(bits=np.zeros((n, 4), np.uint8), phase=phase, azimuth_deg=az, elevation_deg=el, style=np.zeros(n, int))
    rows = index.rows_at(358.0, 2.0)
    assert rows.shape == (20, 6)
    assert set(np.round(az[rows.ravel()])) == {355.0, 0.0, 5.0}
    assert set(el[rows.ravel()]) == {0.0, 10.0}
    np.testing.assert_allclose(phase[rows[:, 0]], np.arange(20) / 20)


def test_bad_bank_rejected():
    with pytest.raises(ValueError, match="uint8"):
        ExemplarIndex(bits=np.zeros((3, 4)), phase=np.zeros(3), azimuth_deg=np.zeros(3), elevation_deg=np.zeros(3), style=np.zeros(3, int))
