"""The Schur-complement Levenberg–Marquardt and the pinhole adjustment built on it.

- :func:`estimator.bundle.levenberg_marquardt` reaches the least-squares
  minimum that scipy's solver reaches, on a problem with shared and blocked
  parameters;
- the pinhole adjustment's analytic Jacobian equals finite differences
  (free and known focal lengths, weights, the rotation prior, the upright priors);
- Cauchy reweighting resists gross outliers that plain least squares follows;
- the rotation prior pulls cameras towards it in proportion to its weight;
- the scene keeps its scale (scaling it changes no reprojection but shrinks the bone residuals).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative
from scipy.spatial.transform import Rotation

import estimator.perspective as perspective
from estimator._selfcal_core import geodesic_deg
from estimator.bundle import levenberg_marquardt
from estimator.perspective import PerspectiveConfig, perspective_refine
from estimator.selfcal import RIGID_LINKS


def _circles(n_blocks: int, rng: np.random.Generator, chain: float = 0.0):
    """Noisy points on circles about one shared centre, a radius per block: each residual touches the
    shared centre and one block; with ``chain``, also the offsets' second differences, which join each
    block to the next two."""
    centre = np.array([1.0, -2.0])
    radius = rng.uniform(1.0, 3.0, n_blocks)
    angles = rng.uniform(0, 2 * np.pi, (n_blocks, 8))
    pts = centre + radius[:, None, None] * np.stack([np.cos(angles), np.sin(angles)], -1)
    pts += rng.normal(0, 0.05, pts.shape)

    def fun(p):  # per block a radius and an offset that a weak prior holds near 0
        c, r = p[:2], p[2:].reshape(n_blocks, 2)
        return np.concatenate([(np.linalg.norm(pts - c, axis=-1) - r[:, :1] - r[:, 1:]).ravel(), 0.3 * r[:, 1],
                               chain * (r[:-2, 1] - 2.0 * r[1:-1, 1] + r[2:, 1])])

    def jac(p):
        return scipy.sparse.csr_matrix(approx_derivative(fun, p, method="3-point"))

    x0 = np.concatenate([[0.0, 0.0], np.stack([np.full(n_blocks, 1.5), np.zeros(n_blocks)], 1).ravel()])
    return fun, jac, x0


def test_lm_reaches_the_least_squares_minimum():
    fun, jac, x0 = _circles(12, np.random.default_rng(0))
    ours = levenberg_marquardt(fun, jac, x0, block_start=2, block_size=2, n_blocks=12, max_nfev=100)
    ref = least_squares(fun, x0, jac=lambda p: jac(p).toarray(), method="lm", xtol=1e-12, ftol=1e-12)
    assert ours.converged
    assert ours.cost == pytest.approx(ref.cost, rel=1e-6)
    np.testing.assert_allclose(ours.x, ref.x, atol=1e-4)
    assert ours.nfev < 30


@pytest.mark.parametrize("n_blocks", [11, 12])
def test_lm_solves_blocks_chained_over_time(n_blocks):
    """A prior joining each block to the next two (a second difference) makes ``J^T J``
    block-pentadiagonal: the blocks are eliminated two at a time along the chain (an odd count fills
    the last pair) and the minimum is scipy's."""
    fun, jac, x0 = _circles(n_blocks, np.random.default_rng(2), chain=2.0)
    ours = levenberg_marquardt(fun, jac, x0, block_start=2, block_size=2, n_blocks=n_blocks, max_nfev=100)
    ref = least_squares(fun, x0, jac=lambda p: jac(p).toarray(), method="lm", xtol=1e-12, ftol=1e-12)
    assert ours.converged
    assert ours.cost == pytest.approx(ref.cost, rel=1e-6)
    np.testing.assert_allclose(ours.x, ref.x, atol=1e-4)
    offsets = ours.x[2:].reshape(n_blocks, 2)[:, 1]
    unchained = levenberg_marquardt(*_circles(n_blocks, np.random.default_rng(2))[:2], x0, block_start=2,
                                    block_size=2, n_blocks=n_blocks, max_nfev=100).x[2:].reshape(n_blocks, 2)[:, 1]
    assert np.abs(np.diff(offsets, 2)).sum() < 0.5 * np.abs(np.diff(unchained, 2)).sum()  # the chain held


def test_lm_stops_at_max_nfev():
    fun, jac, x0 = _circles(5, np.random.default_rng(1))
    out = levenberg_marquardt(fun, jac, x0, block_start=2, block_size=2, n_blocks=5, max_nfev=2)
    assert out.nfev <= 2 and not out.converged


def _walk(n_frames: int = 8, seed: int = 0):
    """A small random rigid 'walker' (13 points, metres; constant bone lengths) turning and moving 5 m in
    front of three cameras 0, 40 and -70 deg apart, and its pixels."""
    rng = np.random.default_rng(seed)
    body = rng.normal(size=(13, 3)) * 0.3
    turn = Rotation.from_euler("y", np.linspace(0.0, 30.0, n_frames)[:, None], degrees=True).as_matrix()
    x = np.einsum("tab,jb->tja", turn, body) + np.stack([np.linspace(-0.5, 0.5, n_frames), np.zeros(n_frames),
                                                         np.full(n_frames, 5.0)], 1)[:, None]
    rots = np.stack([Rotation.from_euler("y", a, degrees=True).as_matrix() for a in (0, 40, -70)])
    walker = np.array([0.0, 0.0, 5.0])
    centres = walker - np.einsum("cba,b->ca", rots, walker)  # each camera sees the walker on its axis
    y = np.stack([perspective._project(x, Rotation.from_matrix(r).as_rotvec()[None], c[None], np.array([800.0]),
                                       np.array([[320.0, 240.0]]))[0] for r, c in zip(rots, centres)])
    return y, rots, rng


@pytest.mark.parametrize("focal", [None, 800.0])
@pytest.mark.parametrize("extras", ["none", "weights", "prior", "upright", "smooth"])
def test_pinhole_jacobian_matches_finite_differences(monkeypatch, focal, extras):
    y, rots, rng = _walk()
    y = y + rng.normal(0, 2.0, y.shape)
    y[1, 2, 3] = np.nan  # a missed joint
    seen = {}
    solver = perspective.levenberg_marquardt

    def spy(fun, jac, x0, **kwargs):
        seen.update(fun=fun, jac=jac, x0=x0)
        return solver(fun, jac, x0, **kwargs)

    monkeypatch.setattr(perspective, "levenberg_marquardt", spy)
    kwargs = {"weights": rng.uniform(0.5, 1.5, y.shape[:3])} if extras == "weights" else {}
    if extras == "prior":
        kwargs["rotation_prior"] = (np.stack([Rotation.from_euler("y", a, degrees=True).as_matrix()
                                              for a in (0, 45, -60)]), 300.0)
    perspective_refine(y, np.tile([640.0, 480.0], (3, 1)), rots, np.ones(3), list(RIGID_LINKS),
                       config=PerspectiveConfig(focal_px=focal, upright=1.0 if extras == "upright" else 0.0,
                                                upright_spread=np.inf, smooth=1.0 if extras == "smooth" else 0.0),
                       **kwargs)
    p = seen["x0"] + rng.normal(0, 0.05, seen["x0"].size)
    analytic = seen["jac"](p).toarray()
    numeric = approx_derivative(seen["fun"], p, method="3-point")
    assert np.abs(analytic - numeric).max() < 1e-6 * np.abs(numeric).max()


def test_reweighting_resists_gross_outliers():
    """10 % of the joints 40-80 px off: plain least squares bends the rig, two Cauchy rounds do not."""
    y, rots, rng = _walk(n_frames=20, seed=3)
    noisy = y + rng.normal(0, 1.0, y.shape)
    bad = rng.random(y.shape[:3]) < 0.10
    ang = rng.uniform(0, 2 * np.pi, y.shape[:3])
    noisy += (bad * rng.uniform(40, 80, y.shape[:3]))[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    start = np.stack([Rotation.from_rotvec([0.0, 0.05, 0.02]).as_matrix() @ r for r in rots])
    start[0] = np.eye(3)
    err = {}
    for rounds in (0, 2):
        pin = perspective_refine(noisy, np.tile([640.0, 480.0], (3, 1)), start, np.ones(3), list(RIGID_LINKS),
                                 config=PerspectiveConfig(focal_px=800.0, reweight=rounds))
        err[rounds] = max(geodesic_deg(a, b) for a, b in zip(pin.rotations, rots))
    assert err[2] < 0.5 * err[0], err
    assert err[2] < 1.0, err


def test_rotation_prior_pulls_in_proportion_to_its_weight():
    """A prior 5 deg off the truth: weight 0 leaves the truth, a heavy one reaches the prior, a light one lies
    between."""
    y, rots, rng = _walk(n_frames=10, seed=4)
    y = y + rng.normal(0, 1.0, y.shape)
    prior = rots.copy()
    prior[1] = Rotation.from_rotvec([0.0, np.radians(5.0), 0.0]).as_matrix() @ rots[1]
    gap = {}
    for weight in (0.0, 300.0, 1e6):
        pin = perspective_refine(y, np.tile([640.0, 480.0], (3, 1)), rots, np.ones(3), list(RIGID_LINKS),
                                 config=PerspectiveConfig(focal_px=800.0), rotation_prior=(prior, weight))
        gap[weight] = (geodesic_deg(pin.rotations[1], rots[1]), geodesic_deg(pin.rotations[1], prior[1]))
    assert gap[0.0][0] < 0.5
    assert gap[1e6][1] < 0.1
    assert gap[0.0][1] > gap[300.0][1] > gap[1e6][1]  # nearer the prior as its weight grows
    assert gap[300.0][0] > 0.5  # and it moved off the data's answer


def test_the_scene_keeps_its_scale():
    """Joints, centres and bone lengths scaled together reproject the same; the mean bone length is
    held at its start, so the exact solver does not shrink the scene to nothing (it did: 960 -> 0.18)."""
    y, rots, rng = _walk(n_frames=20, seed=5)
    y = y + rng.normal(0, 1.0, y.shape)
    pin = perspective_refine(y, np.tile([640.0, 480.0], (3, 1)), rots, np.ones(3), list(RIGID_LINKS),
                             config=PerspectiveConfig(focal_px=800.0))
    lengths = np.linalg.norm(pin.joints3d[:, [a for a, _ in RIGID_LINKS]] - pin.joints3d[:, [b for _, b in RIGID_LINKS]],
                             axis=-1)
    depth = np.linalg.norm(pin.joints3d.reshape(-1, 3).mean(axis=0))
    assert 0.5 * 800.0 < depth < 2.0 * 800.0, depth  # where the start put it: at camera 0's focal length
    assert np.all(lengths.std(axis=0) < 0.05 * lengths.mean(axis=0)), lengths.std(axis=0)


def test_the_smooth_motion_joins_only_frames_one_step_apart():
    """``frame_times``: the prior joins three frames only where both gaps are the commonest step; frames
    with no such neighbours are adjusted as without it."""
    assert perspective._evenly_timed(np.arange(5)).tolist() == [1, 2, 3]
    assert perspective._evenly_timed([0, 2, 4, 6, 10, 12, 14, 16, 18, 24]).tolist() == [1, 2, 5, 6, 7]
    y, rots, rng = _walk(n_frames=12, seed=6)
    y = y + rng.normal(0, 2.0, y.shape)
    run = {}
    for name, smooth, times in (("off", 0.0, None), ("on", 1.0, None), ("apart", 1.0, np.cumsum(np.arange(1, 13)))):
        run[name] = perspective_refine(y, np.tile([640.0, 480.0], (3, 1)), rots, np.ones(3), list(RIGID_LINKS),
                                       config=PerspectiveConfig(focal_px=800.0, smooth=smooth), frame_times=times)
    np.testing.assert_allclose(run["apart"].joints3d, run["off"].joints3d, atol=1e-6)
    assert np.abs(run["on"].joints3d - run["off"].joints3d).max() > 1e-3
    with pytest.raises(ValueError, match="frame_times"):
        perspective_refine(y, np.tile([640.0, 480.0], (3, 1)), rots, np.ones(3), list(RIGID_LINKS),
                           config=PerspectiveConfig(focal_px=800.0, smooth=1.0), frame_times=np.arange(5))
