"""Self-calibration from 2D joint tracks (Wang–Leow §4): ground-truth recovery."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse
from scipy.spatial.transform import Rotation

from estimator._factorization import factorize, noise_sigma
from estimator._selfcal_core import (
    DEPTH_FLIP,
    adj3,
    geodesic_deg,
    kinematic_reflection,
    link_rows,
)
from estimator.camera import world_to_camera_rotation
from estimator.joints import JOINT_INDEX, N_JOINTS
from estimator.selfcal import (
    RIGID_LINKS,
    SelfCalibration,
    _euler_covariance,
    _laplace_covariance,
    _local_rotation_jacobian,
    _link_noise_poly,
    _omega_family,
    _pd_interval,
    _solve_beta,
    _temporal_prior,
    self_calibrate,
)
from estimator.selfcal_baselines import liebowitz_carlsson, tresadern_reid
from estimator.viewpoint import azimuth_difference_deg

MOCAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"
TEST2 = Rotation.from_euler("xyz", [-10, -60, 20], degrees=True).as_matrix()


@pytest.fixture(scope="module")
def walk() -> np.ndarray:
    """30 frames (every 4th at 120 Hz, skipping the first 20) of a real walk, metres."""
    path = MOCAP / "16_15.amc"
    if not path.exists():
        pytest.skip(f"mocap data not found at {path}")
    from estimator.mocap import read_motion

    return read_motion(path).person_frame()[20:140:4, :N_JOINTS]




def project(x: np.ndarray, rots: np.ndarray, scales, offsets=None) -> np.ndarray:
    """Scaled orthographic projection, (T, J, 3) -> (C, T, J, 2)."""
    scales = np.asarray(scales, dtype=float).reshape(len(rots), -1)
    y = np.einsum("cij,tkj->ctki", rots[:, :2], x) * scales[:, :, None, None]
    if offsets is not None:
        y = y + np.asarray(offsets, dtype=float)[:, None, None, :]
    return y


def truth_joints(x: np.ndarray, r0: np.ndarray, s0: float) -> np.ndarray:
    """True joints in camera 0's frame and pixels, per-frame centred."""
    p = s0 * np.einsum("ij,tkj->tki", r0, x)
    return p - p.mean(axis=1, keepdims=True)


def random_pair(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two random camera rotations whose viewing directions differ by 25-155 degrees."""
    while True:
        r = Rotation.random(2, random_state=rng).as_matrix()
        angle = np.degrees(np.arccos(np.clip(r[0, 2] @ r[1, 2], -1, 1)))
        if 25 < angle < 155:
            return r[0], r[1]


# ------------------------------------------------------------------ exact recovery


def test_test2_geometry_noise_free(walk):
    ra = world_to_camera_rotation(90, 10)
    rots = np.stack([ra, TEST2 @ ra])
    y = project(walk, rots, [130.0, 130.0], [(320, 240), (300, 200)])
    res = self_calibrate(y)
    assert res, res.reason
    assert res.method == "wang-leow"
    assert geodesic_deg(res.rotations[1], TEST2) < 0.01
    assert abs(res.scales[1] - 1.0) < 1e-4
    np.testing.assert_allclose(res.euler_xyz_deg[1], [-10, -60, 20], atol=0.01)
    err = np.linalg.norm(res.joints3d - truth_joints(walk, ra, 130.0), axis=-1).mean()
    assert err < 1e-6 * 130
    assert res.reflection_confidence > 0.9
    assert res.diagnostics["beta_range"][0] < res.diagnostics["beta"] < res.diagnostics["beta_range"][1]


def random_case(walk: np.ndarray, rng: np.random.Generator):
    """Noise-free tracks of ``walk`` in a random camera pair with a random relative scale:
    ``(R_a, R_b, s, tracks)``."""
    ra, rb = random_pair(rng)
    s = rng.uniform(0.5, 2.0)
    return ra, rb, s, project(walk, np.stack([ra, rb]), [100.0, 100.0 * s], rng.uniform(0, 500, (2, 2)))


@pytest.mark.parametrize("seed", range(6))
def test_exact_recovery_random_rotations_and_scales(walk, seed):
    rng = np.random.default_rng(seed)
    ra, rb, s, y = random_case(walk, rng)
    res = self_calibrate(y)
    assert res, res.reason
    assert geodesic_deg(res.rotations[1], rb @ ra.T) < 0.01
    assert abs(res.scales[1] - s) < 1e-4 * s
    np.testing.assert_allclose(res.joints3d, truth_joints(walk, ra, 100.0), atol=1e-5)
    np.testing.assert_allclose(res.rotations[0], np.eye(3))


def test_three_cameras_least_squares(walk):
    rng = np.random.default_rng(7)
    rots = np.stack([world_to_camera_rotation(60, 5), world_to_camera_rotation(150, 20), world_to_camera_rotation(250, -10)])
    scales = [90.0, 120.0, 70.0]
    res = self_calibrate(project(walk, rots, scales, rng.uniform(0, 300, (3, 2))))
    assert res and res.method == "wang-leow-lsq"
    rel = rots @ rots[0].T
    assert geodesic_deg(res.rotations, rel).max() < 0.01
    np.testing.assert_allclose(res.scales, np.array(scales) / scales[0], rtol=1e-6)
    assert res.diagnostics["camera_residual"] < 1e-9


def test_three_cameras_noise_is_no_worse_than_two(walk):
    """Extra views over-determine Omega^-1; with noise they should help, not hurt."""
    rng = np.random.default_rng(3)
    rots = np.stack([world_to_camera_rotation(45, 10), TEST2 @ world_to_camera_rotation(45, 10), world_to_camera_rotation(200, 15)])
    clean = project(walk, rots, [130.0, 130.0, 130.0])
    e2, e3 = [], []
    for _ in range(8):
        y = clean + rng.uniform(-2.0, 2.0, clean.shape)
        e2.append(geodesic_deg(self_calibrate(y[:2]).rotations[1], TEST2))
        e3.append(geodesic_deg(self_calibrate(y).rotations[1], TEST2))
    assert np.median(e3) <= np.median(e2)


def test_varying_scales_section_4_3(walk):
    ra = world_to_camera_rotation(45, 10)
    rots = np.stack([ra, TEST2 @ ra])
    t = len(walk)
    sa = 120.0 * np.linspace(1.0, 1.4, t)
    sb = 150.0 * np.linspace(1.2, 0.9, t)
    y = project(walk, rots, np.stack([sa, sb]))

    def length(a, b):
        return np.linalg.norm(walk[0, JOINT_INDEX[a]] - walk[0, JOINT_INDEX[b]])

    ratios = [((JOINT_INDEX[f"left_{p}"], JOINT_INDEX[f"left_{q}"]),
               (JOINT_INDEX[f"right_{p}"], JOINT_INDEX[f"right_{q}"]),
               length(f"left_{p}", f"left_{q}") / length(f"right_{p}", f"right_{q}"))
              for p, q in [("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle")]]
    res = self_calibrate(y, scales="varying", length_ratios=ratios)
    assert res, res.reason
    assert res.method == "wang-leow-varying"
    assert geodesic_deg(res.rotations[1], TEST2) < 0.01
    np.testing.assert_allclose(res.frame_scales[:, 1], sb / sa, rtol=1e-4)
    assert res.diagnostics["frames_solved"] == t
    # A frame one camera missed whole: no closed form there, the others still solve it.
    y[1, 5] = np.nan
    res = self_calibrate(y, scales="varying", length_ratios=ratios)
    assert res, res.reason
    assert res.diagnostics["frames_solved"] == t - 1
    assert geodesic_deg(res.rotations[1], TEST2) < 0.01


def test_bundle_adjustment_keeps_exact_solution(walk):
    ra = world_to_camera_rotation(30, 15)
    rots = np.stack([ra, TEST2 @ ra])
    res = self_calibrate(project(walk, rots, [100.0, 80.0]), refine=True)
    assert res and res.method == "wang-leow+ba"
    assert geodesic_deg(res.rotations[1], TEST2) < 0.01
    assert abs(res.scales[1] - 0.8) < 1e-4


# ------------------------------------------------------------------ noise: temporal prior, noise model


def _test2_tracks(walk, level, seed):
    """Test 2 geometry (camera 0 at azimuth 45), U(-a, a) noise, a = level x body height."""
    ra = world_to_camera_rotation(45, 10)
    clean = project(walk, np.stack([ra, TEST2 @ ra]), [130.0, 130.0])
    a = level * 130.0 * np.mean(walk[..., 2].max(1) - walk[..., 2].min(1))
    return clean + np.random.default_rng(seed).uniform(-a, a, clean.shape), a


@pytest.mark.parametrize("level", [0.01, 0.05, 0.09])
def test_noise_sigma_from_rank3_residual(walk, level):
    sig = []
    for seed in range(4):
        y, a = _test2_tracks(walk, level, seed)
        f = factorize(y)
        sig.append(noise_sigma(f) * f.norm / (a / np.sqrt(3)))  # std of U(-a, a)
    assert 0.85 < np.median(sig) < 1.15, sig
    f = factorize(_test2_tracks(walk, 0.0, 0)[0])
    assert noise_sigma(f) * f.norm < 1e-9
    op, smoother, _ = _temporal_prior(_test2_tracks(walk, 0.0, 0)[0] / f.norm, f)
    assert op is None and smoother is None  # noise-free: no prior, no smoothing


@pytest.mark.parametrize("seed", range(3))
def test_temporal_prior_and_noise_model_keep_noise_free_exact(walk, seed):
    rng = np.random.default_rng(seed)
    ra, rb, s, y = random_case(walk, rng)
    for kw in ({"temporal_prior": True, "noise_model": True}, {"refine": True}):
        res = self_calibrate(y, **kw)
        assert res, res.reason
        assert geodesic_deg(res.rotations[1], rb @ ra.T) < 0.01
        assert abs(res.scales[1] - s) < 1e-4 * s
        np.testing.assert_allclose(res.joints3d, truth_joints(walk, ra, 100.0), atol=1e-4)


def test_temporal_prior_and_noise_model_reduce_rotation_error(walk):
    """Test 2 at 5 % noise, 8 noise draws: the paper's closed form is ~13 deg off (mostly
    bias); smoothing in time more than halves that, the noise model cuts it again."""
    err = {"paper": [], "smoothed": [], "denoised": []}
    for seed in range(8):
        y, _ = _test2_tracks(walk, 0.05, seed)
        for name, kw in (("paper", {}), ("smoothed", {"temporal_prior": True}),
                         ("denoised", {"temporal_prior": True, "noise_model": True})):
            err[name].append(geodesic_deg(self_calibrate(y, **kw).rotations[1], TEST2))
    med = {k: float(np.median(v)) for k, v in err.items()}
    assert med["smoothed"] < 0.65 * med["paper"], med
    assert med["denoised"] < 0.5 * med["paper"], med
    assert med["denoised"] < 7.0, med


def test_link_noise_poly_is_the_expected_noise_part_of_f4(walk):
    """Monte Carlo: mean over noise draws of f4(noisy) - f4(clean) = 2 sigma^2 v4 (M_hat fixed)."""
    ra = world_to_camera_rotation(45, 10)
    clean = project(walk, np.stack([ra, TEST2 @ ra]), [130.0, 130.0])
    fact = factorize(clean)
    m, p = fact.motion[0], fact.structure[0]
    t, j = walk.shape[:2]
    a_, b_, _ = _omega_family(m)
    lo, hi, _ = _pd_interval(a_, b_)
    valid = np.ones((t, j), bool)
    rng = np.random.default_rng(5)
    sigma = 0.03  # normalised units
    wc = m @ p  # centred rank-3 measurement matrix (2C, T*J)
    for beta in np.linspace(lo, hi, 5)[1:-1]:
        k = adj3(a_ + beta * b_)
        kvec = k[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]

        def f4(struct, kvec=kvec):
            return float(np.sum((link_rows(struct.T.reshape(t, j, 3), valid, RIGID_LINKS, []) @ kvec) ** 2))

        base = f4(p)
        gain, v4 = [], []
        for _ in range(200):
            noise = rng.normal(0, sigma, wc.shape).reshape(-1, t, j)
            noise -= noise.mean(axis=2, keepdims=True)  # the tracks are centred per frame
            pn = np.linalg.lstsq(m, wc + noise.reshape(wc.shape), rcond=None)[0]
            gain.append(f4(pn) - base)
            v4.append(np.polyval(_link_noise_poly(a_, b_, m, pn.T.reshape(t, j, 3), valid,
                                                  RIGID_LINKS, sigma), beta))
        assert np.mean(gain) == pytest.approx(2 * sigma**2 * np.mean(v4), rel=0.1)


def _check_jacobians(monkeypatch, selfcal_mod, rng) -> list[int]:
    """Make every least_squares call of ``selfcal_mod`` first compare its analytic
    Jacobian with central differences near the start; returns the residual sizes seen."""
    checked: list[int] = []
    real = selfcal_mod.least_squares

    def check(fun, p0, jac, **kw):
        p = p0 + rng.normal(size=p0.shape) * 0.05
        eps = 1e-6
        num = np.stack([(fun(p + eps * e) - fun(p - eps * e)) / (2 * eps) for e in np.eye(p.size)], 1)
        np.testing.assert_allclose(jac(p).toarray(), num, atol=1e-6)
        checked.append(fun(p).size)
        return real(fun, p0, jac=jac, **kw)

    monkeypatch.setattr(selfcal_mod, "least_squares", check)
    return checked


def test_map_bundle_adjustment_jacobian(walk, monkeypatch):
    """The analytic Jacobian of the temporal prior residuals matches central differences."""
    import estimator.selfcal as selfcal_mod

    rng = np.random.default_rng(2)
    c, t, j = 2, 6, N_JOINTS
    rots = np.stack([np.eye(3), Rotation.random(random_state=1).as_matrix()])
    x = rng.normal(size=(t, j, 3))
    op = rng.normal(size=(t - 1, t))
    checked = _check_jacobians(monkeypatch, selfcal_mod, rng)
    for per_frame in (False, True):
        scales = np.exp(rng.normal(size=(c, t)) * 0.1) if per_frame else np.repeat([[1.0], [1.3]], t, axis=1)
        y = np.einsum("cij,tkj->ctki", rots[:, :2], x) * scales[:, :, None, None]
        y = y + rng.normal(size=y.shape) * 0.1
        obs = np.ones((c, t, j), bool)
        obs[1, 2, 3] = False
        selfcal_mod._bundle_adjust(y, obs, rots, scales, x, np.zeros((c, t, 2)), RIGID_LINKS,
                                   per_frame_scales=per_frame, max_nfev=2, prior_op=op)
    assert len(checked) == 2


def test_temporal_prior_option_validation(walk):
    y, _ = _test2_tracks(walk, 0.02, 0)
    with pytest.raises(ValueError, match="temporal_prior"):
        self_calibrate(y, temporal_prior=-1.0)
    res = self_calibrate(y, refine=True)
    assert res.diagnostics["temporal_prior"]["noise_sigma"] > 0
    assert res.diagnostics["beta_via"].endswith("noise-consistent")
    plain = self_calibrate(y)
    assert "temporal_prior" not in plain.diagnostics and plain.diagnostics["beta_via"] == "sextic"


# ------------------------------------------------------------------ the sextic


@pytest.mark.parametrize("noise", [0.0, 1.0, 4.0, 10.0])
def test_sextic_root_is_global_minimum_of_dense_search(walk, noise):
    """The root of f6 (eq. 14) equals a dense search of F(beta) computed directly."""
    rng = np.random.default_rng(11)
    ra = world_to_camera_rotation(70, 10)
    y = project(walk, np.stack([ra, TEST2 @ ra]), [130.0, 130.0])
    y = y + rng.uniform(-noise, noise, y.shape)
    from estimator._factorization import factorize

    fact = factorize(y)
    a, b, _ = _omega_family(fact.motion[0])
    g = link_rows(fact.structure[0].T.reshape(len(walk), N_JOINTS, 3),
                  np.ones((len(walk), N_JOINTS), bool), RIGID_LINKS, [])
    sol = _solve_beta(a, b, g)
    assert not sol.reason and sol.via == "sextic"
    grid = np.linspace(sol.lo, sol.hi, 40001)[1:-1]
    omega = np.linalg.inv(a + grid[:, None, None] * b)  # Omega(beta) without the polynomials
    vec = omega[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
    f_dense = np.sum((vec @ g.T) ** 2, axis=1)
    best = grid[np.argmin(f_dense)]
    step = grid[1] - grid[0]
    assert abs(sol.beta - best) <= 2 * step
    f_root = np.sum((np.linalg.inv(a + sol.beta * b)[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]] @ g.T) ** 2)
    assert f_root <= f_dense.min() * (1 + 1e-9) + 1e-300
    # The polynomial form agrees with the direct one.
    np.testing.assert_allclose(np.polyval(sol.f4, grid) / np.polyval(sol.f3, grid) ** 2, f_dense,
                               rtol=1e-6, atol=1e-12 * f_dense.max())
    # Positive definite exactly inside the range.
    eig = np.linalg.eigvalsh(a + grid[:, None, None] * b)
    assert (eig[:, 0] > 0).all()
    for outside in (sol.lo - 1e-3 * (sol.hi - sol.lo), sol.hi + 1e-3 * (sol.hi - sol.lo)):
        assert np.linalg.eigvalsh(a + outside * b)[0] < 0


# ------------------------------------------------------------------ reflection


def test_kinematic_prior_on_truth_and_its_mirror(walk):
    flip, conf = kinematic_reflection(walk)
    assert not flip and conf > 0.9
    flip, conf = kinematic_reflection(walk @ DEPTH_FLIP)
    assert flip and conf > 0.9


@pytest.mark.parametrize("azimuth", [0, 60, 120, 200, 300])
def test_reflection_resolved_for_many_viewpoints(walk, azimuth):
    """Cholesky leaves the Necker twin (D R D, depth reversed); the prior must pick the truth."""
    ra = world_to_camera_rotation(azimuth, 15)
    rb = TEST2 @ ra
    res = self_calibrate(project(walk, np.stack([ra, rb]), [100.0, 100.0]))
    twin = DEPTH_FLIP @ TEST2 @ DEPTH_FLIP
    assert geodesic_deg(res.rotations[1], TEST2) < 0.01
    assert geodesic_deg(res.rotations[1], twin) > 1.0
    assert res.reflection_confidence > 0.8


def test_straight_limbs_give_no_confidence(walk):
    x = walk.copy()
    for side in ("left", "right"):
        for a, m, b in (("hip", "knee", "ankle"), ("shoulder", "elbow", "wrist")):
            i, k, j = (JOINT_INDEX[f"{side}_{n}"] for n in (a, m, b))
            x[:, k] = 0.5 * (x[:, i] + x[:, j])
    assert kinematic_reflection(x)[1] == pytest.approx(0.5)


# ------------------------------------------------------------------ masks


def test_missing_joints_are_masked(walk):
    rng = np.random.default_rng(5)
    ra = world_to_camera_rotation(45, 10)
    y = project(walk, np.stack([ra, TEST2 @ ra]), [130.0, 130.0], [(320, 240), (300, 200)])
    drop = rng.random(y.shape[:3]) < 0.1
    y[drop] = np.nan
    y[1, 3] = np.nan  # camera 1 lost a whole frame
    y[:, 5, JOINT_INDEX["head"]] = np.nan  # head unseen by every camera in frame 5
    res = self_calibrate(y)
    assert res, res.reason
    assert res.diagnostics["imputation_iterations"] > 0
    assert geodesic_deg(res.rotations[1], TEST2) < 0.01
    assert abs(res.scales[1] - 1.0) < 1e-4
    seen2 = (~np.isnan(y[..., 0])).sum(axis=0) >= 2
    assert np.array_equal(np.isfinite(res.joints3d).all(axis=-1), seen2)
    truth = truth_joints(walk, ra, 130.0)
    # Origins differ by where the imputed joints went: compare shapes per frame.
    w = seen2[..., None]
    est = res.joints3d - np.nansum(np.where(w, res.joints3d, 0), 1, keepdims=True) / np.maximum(w.sum(1, keepdims=True), 1)
    tru = truth - np.sum(np.where(w, truth, 0), 1, keepdims=True) / np.maximum(w.sum(1, keepdims=True), 1)
    np.testing.assert_allclose(est[seen2], tru[seen2], atol=1e-3)


def test_masks_with_noise_still_close(walk):
    rng = np.random.default_rng(8)
    ra = world_to_camera_rotation(45, 10)
    clean = project(walk, np.stack([ra, TEST2 @ ra]), [130.0, 130.0])
    y = clean + rng.uniform(-0.5, 0.5, clean.shape)
    y[rng.random(y.shape[:3]) < 0.05] = np.nan
    res = self_calibrate(y)
    assert res and geodesic_deg(res.rotations[1], TEST2) < 3.0


# ------------------------------------------------------------------ baselines


@pytest.mark.parametrize("method", [liebowitz_carlsson, tresadern_reid])
def test_baselines_recover_noise_free(walk, method):
    ra = world_to_camera_rotation(45, 10)
    res = method(project(walk, np.stack([ra, TEST2 @ ra]), [100.0, 130.0]))
    assert res, res.reason
    assert geodesic_deg(res.rotations[1], TEST2) < 0.05
    assert abs(res.scales[1] - 1.3) < 1e-3


def test_liebowitz_carlsson_reports_indefinite_omega(walk):
    rng = np.random.default_rng(2)
    ra = world_to_camera_rotation(90, 10)
    clean = project(walk, np.stack([ra, TEST2 @ ra]), [130.0, 130.0])
    seen = {True: 0, False: 0}
    for _ in range(12):
        y = clean + rng.uniform(-15, 15, clean.shape)
        fail = liebowitz_carlsson(y)
        clip = liebowitz_carlsson(y, on_indefinite="clip")
        pd = clip.diagnostics["omega_positive_definite"]
        seen[pd] += 1
        assert bool(fail) == pd and bool(clip)
        if not pd:
            assert "not positive definite" in fail.reason
    assert seen[False] > 0  # heavy noise: the failure mode of section 4.1 does occur
    with pytest.raises(ValueError, match="on_indefinite"):
        liebowitz_carlsson(clean, on_indefinite="ignore")


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("shape", "match"),
    [((2, 5, 12, 2), r"shape \(C, T, 13, 2\)"), ((2, 5, 13, 3), r"shape \(C, T, 13, 2\)"),
     ((5, 13, 2), r"shape \(C, T, 13, 2\)"), ((1, 5, 13, 2), "two cameras"),
     ((2, 1, 13, 2), "two frames")],
)
def test_bad_shapes(shape, match):
    with pytest.raises(ValueError, match=match):
        self_calibrate(np.zeros(shape))


def test_bad_options(walk):
    y = project(walk, np.stack([world_to_camera_rotation(0, 0), world_to_camera_rotation(90, 0)]), [1.0, 1.0])
    with pytest.raises(ValueError, match="scales"):
        self_calibrate(y, scales="sometimes")
    with pytest.raises(ValueError, match="link"):
        self_calibrate(y, links=[(0, 13)])
    with pytest.raises(ValueError, match="ratio"):
        self_calibrate(y, length_ratios=[((0, 1), (1, 2), -1.0)])
    with pytest.raises(ValueError, match="length_ratios"):
        self_calibrate(y, scales="varying", length_ratios=[])
    y[0] = np.nan
    with pytest.raises(ValueError, match="at least 4 joints"):
        self_calibrate(y)


def test_planar_motion_is_a_failed_estimate():
    rng = np.random.default_rng(0)
    x = np.zeros((10, N_JOINTS, 3))
    x[..., :2] = rng.normal(size=(10, N_JOINTS, 2))  # everything in one plane
    rots = np.stack([world_to_camera_rotation(20, 10), world_to_camera_rotation(80, 30)])
    res = self_calibrate(project(x, rots, [50.0, 50.0]))
    assert not res
    assert "planar" in res.reason
    with pytest.raises(ValueError, match="failed"):
        res.euler_xyz_deg  # noqa: B018


def test_identical_views_fail(walk):
    r = world_to_camera_rotation(45, 10)
    roll = Rotation.from_euler("z", 30, degrees=True).as_matrix() @ r  # same view, rolled
    res = self_calibrate(project(walk, np.stack([r, roll]), [100.0, 100.0]))
    assert not res and res.reason


def test_result_validates_rotations():
    with pytest.raises(ValueError, match="det"):
        SelfCalibration(np.stack([np.eye(3), -np.eye(3)]), np.ones(2), np.zeros((2, 13, 3)))
    assert not SelfCalibration.failed("because")


# ------------------------------------------------------------------ prior knowledge of the walker

_THIGHS = ((JOINT_INDEX["left_hip"], JOINT_INDEX["left_knee"]),
           (JOINT_INDEX["right_hip"], JOINT_INDEX["right_knee"]))
_SHINS = ((JOINT_INDEX["left_knee"], JOINT_INDEX["left_ankle"]),
          (JOINT_INDEX["right_knee"], JOINT_INDEX["right_ankle"]))


def test_walker_priors_keep_noise_free_exact(walk):
    """Upright and (deliberately wrong) proportion priors vanish without noise."""
    rng = np.random.default_rng(3)
    ra, rb = random_pair(rng)
    y = project(walk, np.stack([ra, rb]), [100.0, 80.0], rng.uniform(0, 500, (2, 2)))
    res = self_calibrate(y, refine=True, upright=True, body_proportions=[(_THIGHS, _SHINS, 1.3, 0.01)])
    assert res, res.reason
    assert geodesic_deg(res.rotations[1], rb @ ra.T) < 0.01
    assert abs(res.scales[1] - 0.8) < 1e-4
    np.testing.assert_allclose(res.joints3d, truth_joints(walk, ra, 100.0), atol=1e-4)


def test_walker_prior_jacobians(monkeypatch):
    """The analytic Jacobian of the length-ratio and perpendicularity residuals matches
    central differences (with the temporal prior, whose rows come before them)."""
    import estimator.selfcal as selfcal_mod

    rng = np.random.default_rng(4)
    c, t, j = 2, 5, N_JOINTS
    rots = np.stack([np.eye(3), Rotation.random(random_state=3).as_matrix()])
    x = rng.normal(size=(t, j, 3))
    scales = np.repeat([[1.0], [1.2]], t, axis=1)
    y = np.einsum("cij,tkj->ctki", rots[:, :2], x) * scales[:, :, None, None] + rng.normal(size=(c, t, j, 2)) * 0.1
    checked = _check_jacobians(monkeypatch, selfcal_mod, rng)
    lp = selfcal_mod._length_prior([(_THIGHS, _SHINS, 1.1, 0.05), (_THIGHS[:1], _THIGHS[1:], 1.0, 0.02)],
                                   RIGID_LINKS, 0.1)
    ap = selfcal_mod._angle_prior(selfcal_mod.UPRIGHT_PRIORS, 0.1, 3.0)
    for length_prior, angle_prior in ((None, None), (lp, ap)):
        selfcal_mod._bundle_adjust(y, np.ones((c, t, j), bool), rots, scales, x, np.zeros((c, t, 2)),
                                   RIGID_LINKS, per_frame_scales=False, max_nfev=2,
                                   prior_op=rng.normal(size=(t - 1, t)),
                                   length_prior=length_prior, angle_prior=angle_prior)
    assert checked[1] == checked[0] + 2 + 3  # two length ratios, three angles


def test_upright_prior_reduces_rotation_error(walk):
    """Test 2 at 5 % noise, 6 noise draws: the upright prior lowers the median error of
    the MAP bundle adjustment (50 trials: docs/SELFCAL.md)."""
    err = {False: [], True: []}
    for seed in range(6):
        y, _ = _test2_tracks(walk, 0.05, seed)
        for up in (False, True):
            err[up].append(geodesic_deg(self_calibrate(y, refine=True, upright=up).rotations[1], TEST2))
    med = {k: float(np.median(v)) for k, v in err.items()}
    assert med[True] < 0.8 * med[False], med


def test_walker_prior_option_validation(walk):
    y, _ = _test2_tracks(walk, 0.02, 0)
    with pytest.raises(ValueError, match="upright"):
        self_calibrate(y, refine=True, upright=-1.0)
    with pytest.raises(ValueError, match="body proportion"):
        self_calibrate(y, refine=True, body_proportions=[(_THIGHS, _SHINS, 1.0, 0.0)])
    with pytest.raises(ValueError, match="bad link"):
        self_calibrate(y, refine=True, body_proportions=[(((0, 13),), _SHINS, 1.0, 0.05)])


# ------------------------------------------------------------------ posterior uncertainty


def test_laplace_covariance_is_the_inverse_gauss_newton_hessian():
    jac = scipy.sparse.random(60, 12, density=0.4, random_state=1) + scipy.sparse.eye(60, 12)
    full = 0.3**2 * np.linalg.inv((jac.T @ jac).toarray())
    np.testing.assert_allclose(_laplace_covariance(jac, 0.3, 5), full[:5, :5], rtol=1e-9)
    assert not _laplace_covariance(jac, 0.0, 5).any()  # noise-free: no uncertainty
    # A parameter no residual touches: the others keep their covariance, unless it is one of them.
    free_last = scipy.sparse.csr_matrix(np.hstack([jac.toarray(), np.zeros((60, 1))]))
    np.testing.assert_allclose(_laplace_covariance(free_last, 0.3, 5), full[:5, :5], rtol=1e-6)
    free_first = scipy.sparse.csr_matrix(np.hstack([np.zeros((60, 1)), jac.toarray()]))
    got = _laplace_covariance(free_first, 0.3, 5)
    assert np.isnan(got[0]).all() and np.isnan(got[:, 0]).all()  # only the free one is unknown
    np.testing.assert_allclose(got[1:, 1:], full[:4, :4], rtol=1e-6)
    np.testing.assert_allclose(_laplace_covariance(jac, 0.3, 5, dense=False), full[:5, :5], rtol=1e-9)


@pytest.mark.parametrize("euler", [[-10, -60, 20], [170, 10, -175]])
def test_euler_covariance_matches_sampled_rotations(euler):
    """The linear propagation agrees with the covariance of Euler angles of sampled rotations
    ``exp(omega) R``, also where an angle wraps at 180 degrees."""
    rng = np.random.default_rng(3)
    rots = np.stack([np.eye(3), Rotation.from_euler("xyz", euler, degrees=True).as_matrix()])
    a = rng.normal(size=(3, 3))
    cov_w = np.radians(1.0) ** 2 * (a @ a.T + np.eye(3))
    got = _euler_covariance(rots, cov_w)
    assert not got[0].any()
    samples = (Rotation.from_rotvec(rng.multivariate_normal(np.zeros(3), cov_w, 20000))
               * Rotation.from_matrix(rots[1]))
    sampled = np.cov(azimuth_difference_deg(samples.as_euler("xyz", degrees=True), euler).T)
    np.testing.assert_allclose(got[1], sampled, rtol=0.1, atol=0.05 * np.abs(sampled).max())


def test_local_rotation_jacobian_beyond_pi():
    """Rotation vectors longer than pi (where the bundle adjustment may leave them) map to the
    right rotation errors."""
    rng = np.random.default_rng(4)
    rv = np.array([0.3, -1.0, 2.0])
    rv *= (np.pi + 0.3) / np.linalg.norm(rv)
    cov_rv = np.radians(1.0) ** 2 * np.diag([1.0, 2.0, 0.5])
    d = rng.multivariate_normal(np.zeros(3), cov_rv, 20000)
    w = (Rotation.from_rotvec(rv + d) * Rotation.from_rotvec(rv).inv()).as_rotvec()
    g = _local_rotation_jacobian(rv[None])
    np.testing.assert_allclose(g @ cov_rv @ g.T, np.cov(w.T), rtol=0.1, atol=0.05 * cov_rv.max())


def test_reported_uncertainty_zero_without_noise_absent_without_refine(walk):
    y, _ = _test2_tracks(walk, 0.0, 0)
    res = self_calibrate(y, refine=True)
    assert res.euler_xyz_cov.shape == (2, 3, 3) and np.abs(res.euler_xyz_cov).max() < 1e-12
    assert res.rotvec_cov.shape == (2, 3, 3) and np.abs(res.rotvec_cov).max() < 1e-12
    assert res.scale_std.shape == (2,) and res.scale_std.max() < 1e-12
    closed = self_calibrate(y)
    assert closed.euler_xyz_cov is None and closed.euler_xyz_std_deg is None and closed.rotvec_cov is None


@pytest.mark.parametrize("scales", ["fixed", "varying"])
def test_reported_uncertainty_with_a_joint_no_camera_sees(walk, scales):
    """Maximum likelihood (no temporal prior): the tracks leave the position of a head no camera
    sees undetermined, and a frame where camera 1 sees one joint its scale (section 4.3); the
    rotation's uncertainty stays as it was, the undetermined scale is NaN."""
    y, _ = _test2_tracks(walk, 0.03, 0)
    kw = dict(refine=True, temporal_prior=False, noise_model=False, scales=scales)
    full = self_calibrate(y, **kw)
    y[:, 5, JOINT_INDEX["head"]] = np.nan
    y[0, 7, JOINT_INDEX["left_wrist"]] = np.nan
    if scales == "varying":
        y[1, 9, 1:] = np.nan
    res = self_calibrate(y, **kw)
    # Varying: a frame's scale less is different data, so a different optimum; same size.
    rtol = 0.05 if scales == "fixed" else 0.25
    np.testing.assert_allclose(res.euler_xyz_std_deg[1], full.euler_xyz_std_deg[1], rtol=rtol)
    if scales == "fixed":
        assert np.isfinite(res.scale_std).all()


@pytest.mark.parametrize("upright", [False, True])
def test_reported_uncertainty_covers_the_error(walk, upright):
    """Test 2 at 4 % noise, 12 noise draws: the true Euler angles lie inside the reported 95 %
    ellipsoid in at least 10 of 12, and so does the true rotation in the rotation-vector one
    (``rotvec_cov``: ``R_true = exp(omega) R``), the reported standard deviation is the size of the
    actual error (RMS within 0.5-1.5x), and it grows with the noise (bench: docs/SELFCAL.md)."""
    m2, m2_rotvec, err, std, std_low = [], [], [], [], []
    truth = Rotation.from_matrix(TEST2).as_euler("xyz", degrees=True)
    for seed in range(12):
        y, _ = _test2_tracks(walk, 0.04, seed)
        res = self_calibrate(y, refine=True, upright=upright)
        e = azimuth_difference_deg(res.euler_xyz_deg[1], truth)
        m2.append(e @ np.linalg.solve(res.euler_xyz_cov[1], e))
        omega = Rotation.from_matrix(TEST2 @ res.rotations[1].T).as_rotvec()
        m2_rotvec.append(omega @ np.linalg.solve(res.rotvec_cov[1], omega))
        err.append(e)
        std.append(res.euler_xyz_std_deg[1])
        if seed < 3:
            low = self_calibrate(_test2_tracks(walk, 0.01, seed)[0], refine=True, upright=upright)
            std_low.append(low.euler_xyz_std_deg[1])
        assert 0 < res.scale_std[1] < 0.05
    assert np.sum(np.array(m2) < 7.81) >= 10, m2  # chi2(3) 95 % quantile
    assert np.sum(np.array(m2_rotvec) < 7.81) >= 10, m2_rotvec
    ratio = np.sqrt(np.mean(np.square(err), axis=0)) / np.median(std, axis=0)
    assert np.all((ratio > 0.5) & (ratio < 1.5)), ratio
    assert np.all(np.median(std[:3], axis=0) > 2.5 * np.median(std_low, axis=0))
