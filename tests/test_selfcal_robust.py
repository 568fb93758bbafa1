"""The refined self-calibration when the closed form fails, the input warnings, known intrinsics.

Issue 18: on detector-like keypoints of cameras 2.5-4 m from a walk the
scaled-orthographic closed form over all cameras can find no positive-definite
``Omega``; the refined path must then start elsewhere and still calibrate.
The data are generated here (the evaluation's own generator on the shared
CMU walk), not read from a committed file.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator._selfcal_core import geodesic_deg
from estimator.joints import N_JOINTS
from estimator.epipolar import epipolar_start, refine_from_starts
from estimator.keypoints import SKELETONS, keypoints_to_joints
from estimator.perspective import PerspectiveConfig, perspective_refine
from estimator.selfcal import RIGID_LINKS, input_warnings, self_calibrate

ROOT = Path(__file__).resolve().parents[1]
MOCAP = ROOT.parent / "shared" / "data" / "mocap" / "16_15.amc"


@pytest.fixture(scope="module")
def bench():
    if not MOCAP.exists():
        pytest.skip(f"mocap data not found at {MOCAP}")
    spec = importlib.util.spec_from_file_location("eval_keypoints_import", ROOT / "bench" / "eval_keypoints_import.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def stretch(bench):
    from estimator.mocap import read_motion

    return read_motion(MOCAP).positions[60:300:4]  # the evaluation's 2 s at 30 Hz, metres, z up


def _rig_tracks(bench, stretch, seed: int, index: int):
    """Rig ``index`` of the evaluation's seed ``seed`` and its BODY_25 detections on the 13 joints."""
    pts = bench.keypoints_3d(stretch)
    hips = (stretch[:, bench.J["left_hip"]] + stretch[:, bench.J["right_hip"]]) / 2
    rng = np.random.default_rng(seed)
    for _ in range(index + 1):
        rig = bench.random_rig(rng, hips, stretch[:, :N_JOINTS])
        dets = [bench.detections(rng, pts, c) for c in rig["cameras"]]
    body25 = [bench.K[n] for n in bench.BODY25]
    tracks = []
    for det in dets:
        kp = det[:, body25]
        seen = kp[..., 2] > 0
        joints, _ = keypoints_to_joints(np.where(seen[..., None], kp[..., :2], np.nan), kp[..., 2],
                                        SKELETONS["BODY_25"])
        tracks.append(joints)
    return rig, np.stack(tracks)


def _pair_errors(rig, rotations) -> np.ndarray:
    cams = rig["cameras"]
    return np.array([geodesic_deg(cams[i]["R"] @ cams[k]["R"].T, rotations[i] @ rotations[k].T)
                     for i in range(len(cams)) for k in range(i + 1, len(cams))])


def test_refined_path_calibrates_where_the_closed_form_fails(bench, stretch):
    """Rig 3 of the evaluation's seed 0: the closed form over all four cameras has no positive-definite
    Omega; the refined path starts from the chained camera pairs and the pinhole adjustment ends within
    a few degrees."""
    rig, tracks = _rig_tracks(bench, stretch, 0, 3)
    closed = self_calibrate(tracks)
    assert not closed and "not positive definite" in closed.reason
    assert not self_calibrate(tracks, refine=False, temporal_prior=True)  # the closed form alone still fails
    cal = self_calibrate(tracks, refine=True, upright=True)
    assert cal, cal.reason
    assert cal.start == "camera pairs" and cal.diagnostics["start"] == "camera pairs"
    assert "not positive definite" in cal.diagnostics["closed_form"]
    assert set(cal.diagnostics["fallback_starts"]) == {"camera pairs", "nearest positive-definite Omega"}
    sizes = np.tile(np.array(rig["size"], float), (4, 1))
    pin = perspective_refine(tracks, sizes, cal.rotations, cal.scales, list(RIGID_LINKS))
    err = _pair_errors(rig, pin.rotations)
    assert np.median(err) < 3.0 and err.max() < 5.0, err


def test_closed_form_start_is_named(bench, stretch):
    rig, tracks = _rig_tracks(bench, stretch, 0, 0)
    cal = self_calibrate(tracks, refine=True, upright=True)
    assert cal.start == "closed form" and "start" not in cal.diagnostics
    assert self_calibrate(tracks).start == "closed form"


def _pinhole_tracks(stretch, centres, focal, size, rng, noise_px=1.0):
    """Pinhole projections (C, T, 13, 2) of the walk's 13 joints, cameras aimed at the walk's middle."""
    x = stretch[:, :N_JOINTS]
    target = np.append(x[..., :2].reshape(-1, 2).mean(axis=0), 0.9)
    rots = []
    for c in centres:
        f = target - c
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        rots.append(np.stack([r, np.cross(f, r), f]))
    rots = np.stack(rots)
    q = np.einsum("cab,ctjb->ctja", rots, x[None] - np.asarray(centres)[:, None, None, :])
    uv = focal * q[..., :2] / q[..., 2:] + np.array(size) / 2
    return uv + rng.normal(0, noise_px, uv.shape), rots


def _ring(distance: float, azimuths_deg, height: float = 1.5) -> np.ndarray:
    az = np.radians(azimuths_deg)
    return np.stack([distance * np.cos(az), distance * np.sin(az), np.full(len(az), height)], axis=1)


def test_focal_lengths_are_reported_poorly_determined_far_away(stretch):
    """At 3 m the walker's perspective fixes the focal length (posterior and error under 1 %, no note);
    at 60 m with a long lens, 10 frames and 5 px of noise it hardly does, and the note says so."""
    from service.cli.selfcal import FOCAL_LOG_STD, WEAK_PERSPECTIVE, _focal_notes

    mid = np.append(stretch[:, 0, :2].mean(axis=0), 0.0)
    out = {}
    for name, dist, focal, noise, step in (("near", 3.0, 800.0, 1.0, 1), ("far", 60.0, 12000.0, 5.0, 6)):
        tracks, rots = _pinhole_tracks(stretch[::step], mid + _ring(dist, [0, 80, 170, 260]), focal, (1280, 720),
                                       np.random.default_rng(0), noise)
        rel = rots @ rots[0].T
        pin = perspective_refine(tracks, np.tile([1280.0, 720.0], (4, 1)), rel, np.ones(4), list(RIGID_LINKS))
        out[name] = (pin, np.abs(pin.focal_px / focal - 1.0))
    near, far = out["near"][0], out["far"][0]
    assert near.focal_log_std.max() < FOCAL_LOG_STD and out["near"][1].max() < 0.01
    assert np.nanmax(far.depth_spread()) < WEAK_PERSPECTIVE < np.nanmax(near.depth_spread())
    assert out["far"][1].max() > 0.05  # what the note is for
    assert _focal_notes(near, list("abcd")) == []
    assert any("little perspective" in n for n in _focal_notes(far, list("abcd")))


def test_known_focal_lengths_and_principal_points_stay_fixed(stretch):
    rng = np.random.default_rng(1)
    mid = np.append(stretch[:, 0, :2].mean(axis=0), 0.0)
    tracks, rots = _pinhole_tracks(stretch, mid + _ring(3.0, [0, 100, 200]), 900.0, (1280, 720), rng)
    tracks[1] += [5.0, -3.0]  # camera 1's principal point is off the image centre
    rel = rots @ rots[0].T
    start = Rotation.from_rotvec([0.0, 0.05, 0.0]).as_matrix() @ rel  # a few degrees off
    config = PerspectiveConfig(focal_px=(900.0, 900.0, 900.0),
                               principal_px=((640.0, 360.0), (645.0, 357.0), (640.0, 360.0)))
    pin = perspective_refine(tracks, np.tile([1280.0, 720.0], (3, 1)), start, np.ones(3), list(RIGID_LINKS),
                             config=config)
    assert np.allclose(pin.focal_px, 900.0) and pin.focal_log_std is None
    assert pin.rmse_px < 2.0
    assert max(geodesic_deg(a, b) for a, b in zip(pin.rotations, rel)) < 1.0
    with pytest.raises(ValueError, match="focal_px"):
        perspective_refine(tracks, np.tile([1280.0, 720.0], (3, 1)), rel, np.ones(3), list(RIGID_LINKS),
                           config=PerspectiveConfig(focal_px=(900.0, 900.0)))


# ------------------------------------------------------------------ the epipolar start


@pytest.mark.parametrize("known_focal", [True, False])
def test_epipolar_start_recovers_a_close_rig(stretch, known_focal):
    """Cameras 3 m from the walk (1 px of noise): essential matrices, triangulation and resection
    put every camera within a few degrees, with or without the focal lengths."""
    rng = np.random.default_rng(2)
    mid = np.append(stretch[:, 0, :2].mean(axis=0), 0.0)
    tracks, rots = _pinhole_tracks(stretch, mid + _ring(3.0, [10, 95, 185, 280]), 800.0, (1280, 720), rng)
    sizes = np.tile([1280.0, 720.0], (4, 1))
    start = epipolar_start(tracks, sizes, focal_px=np.full(4, 800.0) if known_focal else None)
    assert start is not None
    rel = rots @ rots[0].T
    err = [geodesic_deg(a, b) for a, b in zip(start.rotations, rel)]
    assert max(err) < (3.0 if known_focal else 10.0), err
    assert np.isfinite(start.joints3d).all() and start.joints3d.shape == tracks.shape[1:3] + (3,)
    # In perspective_refine's units: the walker's mean depth in camera 0 is its focal length.
    assert np.mean(start.joints3d[..., 2]) == pytest.approx(start.focal_px[0], rel=1e-6)
    # A start: the bundle adjustment from it lands on the cameras.
    config = PerspectiveConfig(focal_px=800.0 if known_focal else None)
    pin = perspective_refine(tracks, sizes, None, None, list(RIGID_LINKS), config=config, initial=start)
    assert max(geodesic_deg(a, b) for a, b in zip(pin.rotations, rel)) < 0.5


def test_epipolar_start_needs_shared_joints(stretch):
    rng = np.random.default_rng(3)
    mid = np.append(stretch[:, 0, :2].mean(axis=0), 0.0)
    tracks, _ = _pinhole_tracks(stretch[:10], mid + _ring(3.0, [0, 90]), 800.0, (1280, 720), rng)
    tracks[1, :, 2:] = np.nan  # the second camera sees 2 joints per frame: 20 shared, fewer than 24
    assert epipolar_start(tracks, np.tile([1280.0, 720.0], (2, 1))) is None


def test_epipolar_start_rescues_a_rig_the_orthographic_start_leaves_off(bench, stretch):
    """Rig 14 of the evaluation's seed 0: from the scaled-orthographic rig the pinhole adjustment stops
    about 4.6 deg off in the median pair; from the epipolar start it ends within 1 deg, and fits better,
    so it is the one kept (the command's settings: its outliers reweighted away)."""
    from estimator.perspective import KEYPOINT_REWEIGHT

    rig, tracks = _rig_tracks(bench, stretch, 0, 14)
    cal = self_calibrate(tracks, refine=True, upright=True)
    sizes = np.tile(np.array(rig["size"], float), (4, 1))
    ortho = perspective_refine(tracks, sizes, cal.rotations, cal.scales, list(RIGID_LINKS))
    best, start = refine_from_starts(tracks, sizes, cal.rotations, cal.scales, list(RIGID_LINKS),
                                     config=PerspectiveConfig(reweight=KEYPOINT_REWEIGHT))
    assert np.median(_pair_errors(rig, ortho.rotations)) > 3.0
    assert start == "epipolar"  # the race (plain least squares, 15 evaluations each) chose it by its fit
    assert np.median(_pair_errors(rig, best.rotations)) < 1.0


# ------------------------------------------------------------------ input warnings


def _ortho(x: np.ndarray, rots: np.ndarray, scale: float = 100.0) -> np.ndarray:
    return scale * np.einsum("cij,tkj->ctki", rots[:, :2], x)


def _views(*euler_deg) -> np.ndarray:
    return Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()


def _body(stretch) -> np.ndarray:
    """The walk's joints in a y-down frame facing the cameras, centred per frame."""
    x = stretch[::2, :N_JOINTS] @ np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]).T
    return x - x.mean(axis=1, keepdims=True)


def test_no_warnings_on_a_good_rig(stretch):
    rots = _views([0, 0, 0], [10, 70, 5], [-5, 140, 0])
    rng = np.random.default_rng(2)
    cal = self_calibrate(_ortho(_body(stretch), rots) + rng.normal(0, 0.5, (3, 30, 13, 2)), refine=True)
    assert cal and cal.notes == ()


def test_warns_two_cameras_along_the_same_axis(stretch):
    rots = _views([0, 0, 0], [2, 5, 1], [-5, 90, 0])
    rng = np.random.default_rng(3)
    cal = self_calibrate(_ortho(_body(stretch), rots) + rng.normal(0, 0.3, (3, 30, 13, 2)), refine=True)
    assert cal, cal.reason
    assert any("cameras 0 and 1 look along nearly the same axis" in n for n in cal.notes), cal.notes


def test_warns_a_camera_that_sees_too_few_frames(stretch):
    rots = _views([0, 0, 0], [10, 70, 5], [-5, 140, 0])
    tracks = _ortho(_body(stretch), rots) + np.random.default_rng(4).normal(0, 0.5, (3, 30, 13, 2))
    tracks[2, 6:] = np.nan  # camera 2 sees 6 of 30 frames
    cal = self_calibrate(tracks, refine=True)
    assert cal, cal.reason
    assert [n for n in cal.notes if n.startswith("camera 2 sees the walker")] and len(cal.notes) == 1, cal.notes


def test_warns_near_planar_motion(stretch):
    body = _body(stretch)
    body[..., 2] *= 0.03  # a flat figure: almost no depth
    rots = _views([0, 0, 0], [10, 40, 5], [-5, -35, 0])
    cal = self_calibrate(_ortho(body, rots) + np.random.default_rng(5).normal(0, 0.05, (3, 30, 13, 2)))
    assert cal, cal.reason
    assert any(n.startswith("near-planar motion") for n in cal.notes), cal.notes
    assert input_warnings(_ortho(_body(stretch), rots), rots, _body(stretch)) == []


# ------------------------------------------------------------------ posecal selfcal --intrinsics / --focal


@pytest.fixture(scope="module")
def render():
    """Exact 2D joints of a perspective render (3 cameras, 640x480) as a tracks JSON document."""
    from estimator.synth import SynthSpec, synthesize

    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=12, azimuths=(20.0, 95.0, 230.0),
                               elevations=(10.0, 25.0, 0.0), image_size=(640, 480)))
    y = np.stack([[f["joints2d"][c] for f in seq.truth["frames"]] for c in seq.cameras]).astype(float)
    doc = {"cameras": {c: [[[float(v) for v in p] for p in frame] for frame in y[k]]
                       for k, c in enumerate(seq.cameras)}}
    return seq, doc


def _calib_toml(path: Path, seq, focal_scale: float = 1.0, drop: str | None = None) -> Path:
    lines = []
    for c in seq.cameras:
        if c == drop:
            continue
        f = seq.truth["cameras"][c]["focal_px"] * focal_scale
        lines += [f"[{c}]", f'name = "{c}"', "size = [ 640.0, 480.0]",
                  f"matrix = [ [ {f}, 0.0, 320.0], [ 0.0, {f}, 240.0], [ 0.0, 0.0, 1.0]]", ""]
    path.write_text("\n".join(lines))
    return path


def test_cli_intrinsics_are_kept(tmp_path, render, capsys):
    import json

    from service.cli import main

    seq, doc = render
    tracks = tmp_path / "tracks.json"
    tracks.write_text(json.dumps(doc))
    out = tmp_path / "r.json"
    calib = _calib_toml(tmp_path / "calib.toml", seq)
    assert main(["selfcal", str(tracks), "--out", str(out), "--intrinsics", str(calib),
                 "--export-calibration", str(tmp_path / "out.toml")]) == 0
    res = json.loads(out.read_text())
    assert res["intrinsics"] == "given" and res["start"] == "closed form"
    for c in ("c1", "c2"):
        assert res["cameras"][c]["focal_px"] == pytest.approx(seq.truth["cameras"][c]["focal_px"])
    assert res["reprojection_rms_px"] < 0.5
    # --focal: one focal length for every camera (the render's cameras share theirs)
    f = seq.truth["cameras"]["c0"]["focal_px"]
    assert main(["selfcal", str(tracks), "--out", str(out), "--image-size", "640,480", "--focal", str(f)]) == 0
    res = json.loads(out.read_text())
    assert res["intrinsics"] == "given" and res["reference_focal_px"] == pytest.approx(f)
    for bad, message in ((["--intrinsics", str(_calib_toml(tmp_path / "part.toml", seq, drop="c2"))], "no camera 'c2'"),
                         (["--intrinsics", str(tmp_path / "missing.toml")], "no such file"),
                         (["--focal", "800"], "--image-size"),
                         (["--intrinsics", str(calib), "--focal", "800"], "not both")):
        assert main(["selfcal", str(tracks), *bad]) == 2
        assert message in capsys.readouterr().err


def _trunk_hip_deviation_deg(joints3d: np.ndarray) -> np.ndarray:
    """Per frame, how far the trunk (hips' to shoulders' centre) is from perpendicular to the hip line."""
    from estimator.joints import JOINT_INDEX as J

    trunk = (joints3d[:, J["left_shoulder"]] + joints3d[:, J["right_shoulder"]]
             - joints3d[:, J["left_hip"]] - joints3d[:, J["right_hip"]]) / 2
    hips = joints3d[:, J["left_hip"]] - joints3d[:, J["right_hip"]]
    cos = np.sum(trunk * hips, axis=1) / np.linalg.norm(trunk, axis=1) / np.linalg.norm(hips, axis=1)
    return np.degrees(np.arcsin(np.abs(cos)))


def test_upright_priors_hold_a_distant_walkers_body_and_leave_a_near_one_alone(stretch):
    """The per-frame upright priors (``PerspectiveConfig.upright``) act only where the perspective is
    weak: at 3 m the adjustment is the same with them; at 15 m with noise of 3 % of the walker's height
    the trunk comes out nearer perpendicular to the hip line, as the walker's was, and the rig nearer
    the truth."""
    mid = np.append(stretch[:, 0, :2].mean(axis=0), 0.0)
    truth = np.median(_trunk_hip_deviation_deg(stretch[:, :N_JOINTS]))
    for dist, focal, noise in ((3.0, 800.0, 1.0), (15.0, 2000.0, 7.0)):
        tracks, rots = _pinhole_tracks(stretch, mid + _ring(dist, [0, 80, 170, 260]), focal, (1280, 720),
                                       np.random.default_rng(1), noise)
        rel = rots @ rots[0].T
        runs = {u: perspective_refine(tracks, np.tile([1280.0, 720.0], (4, 1)), rel, np.ones(4),
                                      list(RIGID_LINKS), config=PerspectiveConfig(reweight=2, upright=u))
                for u in (0.0, 1.0)}
        dev = {u: np.median(_trunk_hip_deviation_deg(r.joints3d)) for u, r in runs.items()}
        err = {u: np.median([geodesic_deg(r.rotations[i] @ r.rotations[k].T, rel[i] @ rel[k].T)
                             for i in range(4) for k in range(i + 1, 4)]) for u, r in runs.items()}
        assert not runs[0.0].upright and runs[1.0].upright == (dist > 5)
        if dist < 5:
            np.testing.assert_allclose(runs[1.0].rotations, runs[0.0].rotations, atol=1e-9)
        else:
            assert dev[1.0] < 0.5 * dev[0.0] and dev[1.0] < truth + 2.0, (dev, truth)  # 6.4 -> 0.4 deg
            assert err[1.0] < 0.9 * err[0.0], err  # camera pairs 2.1 -> 1.5 deg


def test_smooth_motion_takes_a_detectors_noise_off_the_posture_and_leaves_exact_tracks(stretch):
    """The walker's smooth motion (``PerspectiveConfig.smooth``): a detector's noise is independent
    from frame to frame, the walk's joints are not, so with it the posture comes out nearer the truth
    (mean joint distance per frame after a similarity alignment) near and far (5 px at 3 m: 16 -> 9
    mm; 7 px at 15 m: 43 -> 25 mm); exact tracks read no noise, and the prior stays off them."""
    from estimator.rig import aligned_error

    mid = np.append(stretch[:, 0, :2].mean(axis=0), 0.0)
    truth = stretch[:, :N_JOINTS]
    for dist, focal, noise in ((3.0, 800.0, 5.0), (15.0, 2000.0, 7.0), (3.0, 800.0, 0.0)):
        tracks, rots = _pinhole_tracks(stretch, mid + _ring(dist, [0, 80, 170, 260]), focal, (1280, 720),
                                       np.random.default_rng(0), noise)
        rel = rots @ rots[0].T
        runs = {s: perspective_refine(tracks, np.tile([1280.0, 720.0], (4, 1)), rel, np.ones(4), list(RIGID_LINKS),
                                      config=PerspectiveConfig(reweight=2, upright=1.0, smooth=s)) for s in (0.0, 1.0)}
        err = {s: np.median(aligned_error(r.joints3d, truth)) for s, r in runs.items()}
        if noise:
            assert err[1.0] < 0.7 * err[0.0], err
        else:
            np.testing.assert_allclose(runs[1.0].rotations, runs[0.0].rotations, atol=1e-6)
            assert err[1.0] < 1e-4, err
