"""``posecal selfcal``: the JSON formats of docs/FORMATS.md and exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.camera import world_to_camera_rotation
from estimator._selfcal_core import geodesic_deg
from estimator.joints import JOINT_NAMES, N_JOINTS
from service.cli import main

MOCAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"
TEST2 = Rotation.from_euler("xyz", [-10, -60, 20], degrees=True).as_matrix()
POSECAL = Path(sys.executable).with_name("posecal")




@pytest.fixture(scope="module")
def tracks() -> np.ndarray:
    """(2, 30, 13, 2) pixels of a real walk seen by the Test 2 camera pair."""
    path = MOCAP / "16_15.amc"
    if not path.exists():
        pytest.skip(f"mocap data not found at {path}")
    from estimator.mocap import read_motion

    x = read_motion(path).person_frame()[20:140:4, :N_JOINTS]
    ra = world_to_camera_rotation(45, 10)
    rots = np.stack([ra, TEST2 @ ra])
    return np.einsum("cij,tkj->ctki", rots[:, :2], x) * np.array([150.0, 120.0])[:, None, None, None] + 300


def write(tmp_path: Path, doc, name="tracks.json") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def as_doc(y: np.ndarray, names=("left", "right")) -> dict:
    cams = {}
    for c, name in enumerate(names):
        cams[name] = [[None if np.isnan(p).any() else [float(p[0]), float(p[1])] for p in frame]
                      for frame in y[c]]
    return {"joint_names": list(JOINT_NAMES), "cameras": cams}


def test_selfcal_writes_result(tmp_path, tracks):
    y = tracks.copy()
    y[0, 2, 4] = np.nan
    y[:, 7, 0] = np.nan  # head lost in both views: null in the 3D output
    out = tmp_path / "result.json"
    assert main(["selfcal", str(write(tmp_path, as_doc(y))), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["joint_names"] == list(JOINT_NAMES)
    assert res["reference_camera"] == "left"
    assert list(res["cameras"]) == ["right"]
    cam = res["cameras"]["right"]
    assert geodesic_deg(np.array(cam["rotation"]), TEST2) < 0.01
    np.testing.assert_allclose(cam["euler_xyz_deg"], [-10, -60, 20], atol=0.01)
    assert cam["scale"] == pytest.approx(0.8, abs=1e-4)
    assert res["method"] == "wang-leow+ba" and cam["euler_xyz_std_deg"] == [0.0, 0.0, 0.0]  # the refined default
    assert cam["rotvec_covariance_rad2"] == [[0.0] * 3] * 3
    assert 0.5 <= res["reflection_confidence"] <= 1
    assert len(res["frames"]) == 30 and res["frames"][3]["index"] == 3
    assert res["frames"][7]["joints3d"][0] is None
    frame2 = res["frames"][2]["joints3d"]
    assert frame2[4] is None  # seen by one camera only: no 3D
    assert all(len(p) == 3 for k, p in enumerate(frame2) if k != 4)


def test_closed_form_is_kept_as_published(tmp_path, tracks):
    out = tmp_path / "closed.json"
    assert main(["selfcal", str(write(tmp_path, as_doc(tracks))), "--out", str(out), "--method", "closed-form"]) == 0
    res = json.loads(out.read_text())
    cam = res["cameras"]["right"]
    assert res["method"] == "wang-leow" and "euler_xyz_std_deg" not in cam  # closed form only: no posterior
    assert "rotvec_covariance_rad2" not in cam
    assert geodesic_deg(np.array(cam["rotation"]), TEST2) < 0.01


def test_pinhole_cameras_with_the_image_size(tmp_path, capsys):
    """Joints of a perspective render: with --image-size the cameras are pinholes, exact here,
    their centres in metres at the stature (the render's body is the model's, 1.75 m)."""
    from estimator.synth import SynthSpec, synthesize

    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=12, azimuths=(20.0, 95.0, 230.0),
                               elevations=(10.0, 25.0, 0.0), image_size=(640, 480)))
    y = np.stack([[f["joints2d"][c] for f in seq.truth["frames"]] for c in seq.cameras]).astype(float)
    path = write(tmp_path, as_doc(y, names=seq.cameras))
    out = tmp_path / "pin.json"
    assert main(["selfcal", str(path), "--out", str(out), "--image-size", "640,480"]) == 0
    res = json.loads(out.read_text())
    truth = {c: seq.truth["cameras"][c] for c in seq.cameras}
    r0 = world_to_camera_rotation(truth["c0"]["azimuth_deg"], truth["c0"]["elevation_deg"])
    for c in ("c1", "c2"):
        cam = res["cameras"][c]
        rc = world_to_camera_rotation(truth[c]["azimuth_deg"], truth[c]["elevation_deg"])
        assert geodesic_deg(np.array(cam["rotation"]), rc @ r0.T) < 0.5
        assert cam["focal_px"] == pytest.approx(truth[c]["focal_px"], rel=0.03)
        baseline = np.linalg.norm(np.subtract(truth[c]["position_m"], truth["c0"]["position_m"]))
        assert np.linalg.norm(cam["centre_m"]) == pytest.approx(baseline, rel=0.1)
    assert res["method"].endswith("+pinhole") and res["reprojection_rms_px"] < 0.1
    assert set(res["scaled_orthographic"]) == {"c1", "c2"}
    assert not any(n.startswith("two cameras") for n in res["notes"])
    pair = write(tmp_path, as_doc(y[:2], names=seq.cameras[:2]), name="pair.json")
    assert main(["selfcal", str(pair), "--out", str(out), "--image-size", "640,480"]) == 0
    assert any(n.startswith("two cameras: the rotation between two views") for n in json.loads(out.read_text())["notes"])
    assert "posecal selfcal: warning: two cameras" in capsys.readouterr().err
    for bad, message in ((["--image-size", "640x480"], "W,H"),
                         (["--image-size", "640,480", "--method", "closed-form"], "refined path")):
        assert main(["selfcal", str(path), *bad]) == 2
        assert message in capsys.readouterr().err


def test_joint_subset_order_and_nan(tmp_path, tracks):
    """joint_names in another order; absent joints and NaN coordinates are missing."""
    names = list(JOINT_NAMES[1:])[::-1]  # no head, reversed
    idx = [JOINT_NAMES.index(n) for n in names]
    cams = {c: [[list(map(float, tracks[k, f, j])) for j in idx] for f in range(30)]
            for k, c in enumerate("ab")}
    cams["a"][4][0] = [float("nan"), 1.0]
    text = json.dumps({"joint_names": names, "cameras": cams})  # writes NaN literals
    out = tmp_path / "r.json"
    assert main(["selfcal", str(write(tmp_path, text)), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert geodesic_deg(np.array(res["cameras"]["b"]["rotation"]), TEST2) < 0.05
    assert all(f["joints3d"][0] is None for f in res["frames"])  # head never seen


def test_varying_scale_option(tmp_path, tracks):
    out = tmp_path / "r.json"
    assert main(["selfcal", str(write(tmp_path, as_doc(tracks))), "--out", str(out),
                 "--varying-scale"]) == 0
    cam = json.loads(out.read_text())["cameras"]["right"]
    assert len(cam["frame_scales"]) == 30
    assert "euler_xyz_std_deg" in cam and "scale_std" not in cam  # per-frame scales: no single std
    assert np.shape(cam["rotvec_covariance_rad2"]) == (3, 3)
    assert geodesic_deg(np.array(cam["rotation"]), TEST2) < 0.01


def test_refine_upright_option(tmp_path, tracks, capsys):
    doc = write(tmp_path, as_doc(tracks))
    out = tmp_path / "r.json"
    assert main(["selfcal", str(doc), "--out", str(out), "--refine", "--upright"]) == 0
    cam = json.loads(out.read_text())["cameras"]["right"]
    assert geodesic_deg(np.array(cam["rotation"]), TEST2) < 0.01  # noise-free: still exact
    assert cam["euler_xyz_std_deg"] == [0.0, 0.0, 0.0] and cam["scale_std"] == 0.0
    noisy = tracks + np.random.default_rng(0).uniform(-6, 6, tracks.shape)  # 3 % of the height
    assert main(["selfcal", str(write(tmp_path, as_doc(noisy))), "--out", str(out), "--refine"]) == 0
    cam = json.loads(out.read_text())["cameras"]["right"]
    assert all(0.05 < v < 10 for v in cam["euler_xyz_std_deg"]) and 0 < cam["scale_std"] < 0.05
    err = np.abs(np.array(cam["euler_xyz_deg"]) - [-10, -60, 20])
    assert np.all(err < 4 * np.array(cam["euler_xyz_std_deg"])), (err, cam["euler_xyz_std_deg"])
    # The same posterior as a rotation-vector covariance (radians^2): R_true = exp(omega) R, omega inside
    # its 99.9 % ellipsoid (chi2(3)), and the same size as the Euler angles' away from gimbal lock.
    cov = np.array(cam["rotvec_covariance_rad2"])
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    omega = Rotation.from_matrix(TEST2 @ np.array(cam["rotation"]).T).as_rotvec()
    assert omega @ np.linalg.solve(cov, omega) < 16.27
    assert 0.2 < np.degrees(np.sqrt(np.trace(cov))) / np.linalg.norm(cam["euler_xyz_std_deg"]) < 5
    assert main(["selfcal", str(doc), "--upright"]) == 2
    assert "--upright needs --refine" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d["cameras"].pop("right"), "two cameras"),
        (lambda d: [v.__delitem__(slice(1, None)) for v in d["cameras"].values()], "two frames"),
        (lambda d: d["cameras"]["right"].pop(), "different frame counts"),
        (lambda d: d.__setitem__("joint_names", ["nose"] + d["joint_names"][1:]), "unknown joint"),
        (lambda d: d["cameras"]["left"][0].pop(), "expected 13 joints"),
        (lambda d: d["cameras"]["left"][0].__setitem__(0, [1, "x"]), "numbers"),
        (lambda d: d.__setitem__("cameras", []), "cameras"),
    ],
)
def test_bad_input_exit_2(tmp_path, tracks, capsys, mutate, message):
    doc = as_doc(tracks)
    mutate(doc)
    assert main(["selfcal", str(write(tmp_path, doc)), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    assert "posecal selfcal: error:" in err and message in err
    assert not (tmp_path / "r.json").exists()


def test_planar_motion_exit_1(tmp_path, capsys):
    """Valid tracks of a flat body: the computation cannot be done (exit 1, not 2: the input reads)."""
    rng = np.random.default_rng(0)
    x = np.zeros((10, N_JOINTS, 3))
    x[..., :2] = rng.normal(size=(10, N_JOINTS, 2))
    rots = np.stack([world_to_camera_rotation(20, 10), world_to_camera_rotation(80, 30)])
    y = np.einsum("cij,tkj->ctki", rots[:, :2], x) * 50
    assert main(["selfcal", str(write(tmp_path, as_doc(y)))]) == 1
    assert "planar" in capsys.readouterr().err


def test_unreadable_files_exit_2(tmp_path, capsys):
    assert main(["selfcal", str(tmp_path / "missing.json")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["selfcal", str(write(tmp_path, "{not json"))]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_console_script(tmp_path, tracks):
    if not POSECAL.exists():
        pytest.skip("posecal console script not installed next to the interpreter")
    path = write(tmp_path, as_doc(tracks))
    ok = subprocess.run([str(POSECAL), "selfcal", str(path)], capture_output=True, text=True,
                        timeout=60)
    assert ok.returncode == 0, ok.stderr
    assert "euler_xyz_deg" in json.loads(ok.stdout)["cameras"]["right"]
    bad = subprocess.run([str(POSECAL), "selfcal", str(write(tmp_path, {"cameras": {"a": []}}, "b.json"))],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "two cameras" in bad.stderr


def test_an_unreliable_pinhole_rig_is_written_and_exits_1(tmp_path, tracks, capsys):
    """Keypoints no rigid body explains (each camera's joints shuffled per frame): the pinhole cameras
    cannot fit them, the result says so (reliable false, a note) and the command exits 1 (the
    computation failed; 2 is for bad input)."""
    rng = np.random.default_rng(0)
    y = tracks.copy()
    for c in range(2):
        for t in range(y.shape[1]):
            y[c, t] = y[c, t, rng.permutation(N_JOINTS)]
    out = tmp_path / "result.json"
    code = main(["selfcal", str(write(tmp_path, as_doc(y))), "--out", str(out), "--image-size", "640,480"])
    err = capsys.readouterr().err
    assert code == 1 and "unreliable" in err, (code, err)
    res = json.loads(out.read_text())
    assert res["reliable"] is False and any("probably wrong" in n for n in res["notes"])
    good = tmp_path / "good.json"
    assert main(["selfcal", str(write(tmp_path, as_doc(tracks), "t2.json")), "--out", str(good),
                 "--image-size", "640,480"]) == 0
    assert json.loads(good.read_text())["reliable"] is True


def test_rotations_also_as_rotation_vectors(tmp_path, tracks):
    out = tmp_path / "result.json"
    assert main(["selfcal", str(write(tmp_path, as_doc(tracks))), "--out", str(out)]) == 0
    cam = json.loads(out.read_text())["cameras"]["right"]
    assert np.allclose(Rotation.from_rotvec(cam["rotvec"]).as_matrix(), cam["rotation"], atol=1e-9)
