"""service/exports.py read back by independent readers: the calibration TOML by a reader written
against aniposelib's documented loader, the OpenCV files by ``cv2.FileStorage``, the BVH by the
repository's own BVH forward kinematics (:func:`estimator.mocap.bvh_positions`); results and the
``posecal selfcal`` flags (issue 18)."""

from __future__ import annotations

import csv
import io
import json
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from estimator.gait import load_gait
from estimator.joints import JOINT_NAMES, N_JOINTS
from estimator.mocap import bvh_positions
from estimator.pinhole import PinholeCameras, project
from estimator.skeleton import BodyShape, forward_kinematics
from service.cli import main
from service.exports import (BVH_JOINTS, bvh_text, calibration_text, csv_text, export_calibration, export_result,
                             result_joints, rig_cameras)

W, H = 640, 480


def _walk(n: int = 30, fps: float = 15.0) -> np.ndarray:
    """The model's walk (constant bone lengths), (n, 13, 3) in a Z-up world, metres, walking along +x."""
    x = forward_kinematics(load_gait().angles(np.arange(n) / fps * 0.9), BodyShape(height=1.75))[:, :N_JOINTS]
    return x + np.c_[np.arange(n) / fps * 1.2, np.zeros(n), np.zeros(n)][:, None]


def _look_at(centre, target) -> np.ndarray:
    f = np.asarray(target, float) - centre
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f])


def _rig(mid: np.ndarray, azimuths=(20.0, 115.0, 230.0), focals=(560.0, 620.0, 700.0)) -> PinholeCameras:
    """Three pinhole cameras 3-4 m around ``mid``, looking at it."""
    rots, centres = [], []
    for az, dist, height in zip(azimuths, (3.5, 3.0, 4.0), (1.6, 1.3, 1.9)):
        a = np.radians(az)
        c = mid + [dist * np.cos(a), dist * np.sin(a), height - mid[2]]
        rots.append(_look_at(c, mid))
        centres.append(c)
    return PinholeCameras.from_centres(np.array(focals), np.tile([W / 2, H / 2], (3, 1)), np.array(rots),
                                       np.array(centres))


# ------------------------------------------------------------------ calibration files


def _anipose_load(text: str) -> list[dict]:
    """The cameras of a calibration TOML as aniposelib's ``CameraGroup.load`` reads them: every table but
    ``metadata``, in **sorted key order**, each through ``Camera.load_dict`` (``matrix``, ``rotation``,
    ``translation``, ``distortions``, ``name``, ``size``); a table with ``fisheye = true`` would be a
    ``FisheyeCamera``."""
    doc = tomllib.loads(text)
    cams = []
    for key in sorted(doc):
        if key == "metadata":
            continue
        d = doc[key]
        assert not d.get("fisheye", False)
        cams.append({"name": str(d["name"]), "size": tuple(d["size"]), "matrix": np.array(d["matrix"], float),
                     "dist": np.array(d["distortions"], float).ravel(),
                     "rvec": np.array(d["rotation"], float).ravel(), "tvec": np.array(d["translation"], float).ravel()})
    return cams


def _anipose_project(cam: dict, points: np.ndarray) -> np.ndarray:
    """aniposelib's ``Camera.project``: ``cv2.projectPoints`` with the camera's rvec, tvec, matrix, dist."""
    out, _ = cv2.projectPoints(points.reshape(-1, 1, 3), cam["rvec"], cam["tvec"], cam["matrix"], cam["dist"])
    return out.reshape(-1, 2)


def test_calibration_toml_reads_back_as_aniposelib_reads_it():
    names = ["cam_b", "cam_a", "cam_c"]  # not sorted: aniposelib orders the tables by key
    x = _walk(10).reshape(-1, 3)
    cams = _rig(x.mean(axis=0))
    text = calibration_text("toml", names, np.tile([W, H], (3, 1)), cams, metadata={"reference_camera": "cam_b"})
    loaded = _anipose_load(text)
    assert [c["name"] for c in loaded] == sorted(names)
    assert tomllib.loads(text)["metadata"] == {"adjusted": False, "error": 0.0, "reference_camera": "cam_b"}
    for c, name in enumerate(names):
        cam = next(d for d in loaded if d["name"] == name)
        assert cam["size"] == (W, H) and cam["dist"].shape == (4,) and not cam["dist"].any()
        np.testing.assert_allclose(cam["matrix"], cams.matrices[c], atol=1e-12)
        np.testing.assert_allclose(cv2.Rodrigues(cam["rvec"])[0], cams.rotations[c], atol=1e-12)
        np.testing.assert_allclose(cam["tvec"], cams.translations[c], atol=1e-12)
        np.testing.assert_allclose(_anipose_project(cam, x), project(cams.select(c), x)[0], atol=1e-6)


@pytest.mark.parametrize("fmt", ["yaml", "json"])
def test_opencv_calibration_reads_back_with_filestorage(tmp_path, fmt):
    names = ["c0", "side-1.b"]
    cams = _rig(np.array([0.0, 0.0, 1.0])).select([0, 2])
    sizes = np.array([[W, H], [1280, 720]])
    text = calibration_text(fmt, names, sizes, cams, metadata={"source": "test", "error": 1.5})
    path = tmp_path / f"calib.{fmt}"
    path.write_text(text)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    node = fs.getNode("cameras")
    assert node.size() == 2
    for c, name in enumerate(names):
        cam = node.at(c)
        assert cam.getNode("name").string() == name
        size = cam.getNode("image_size")
        assert [int(size.at(i).real()) for i in range(2)] == sizes[c].tolist()
        np.testing.assert_array_equal(cam.getNode("K").mat(), cams.matrices[c])
        np.testing.assert_array_equal(cam.getNode("R").mat(), cams.rotations[c])
        np.testing.assert_array_equal(cam.getNode("t").mat(), cams.translations[c][:, None])
        np.testing.assert_allclose(cv2.Rodrigues(cam.getNode("rvec").mat())[0], cams.rotations[c], atol=1e-12)
        assert cam.getNode("dist").mat().shape == (1, 5) and not cam.getNode("dist").mat().any()
    meta = fs.getNode("metadata")
    assert meta.getNode("source").string() == "test" and meta.getNode("error").real() == 1.5
    assert int(meta.getNode("adjusted").real()) == 0
    fs.release()
    if fmt == "json":
        assert json.loads(text)["cameras"][1]["name"] == "side-1.b"  # plain JSON too


# ------------------------------------------------------------------ BVH and CSV


def _bvh_joints(path: Path) -> dict[str, np.ndarray]:
    """Each of the 13 joints (T, 3) of a posecal BVH by forward kinematics, back in the Z-up world."""
    joints, ends, _ = bvh_positions(path)
    assert set(ends) == {"LeftFoot", "RightFoot", "LeftHand", "RightHand", "Head"}
    at = {name: where for name, _, where, *_ in BVH_JOINTS}
    return {at[n]: p[:, [2, 0, 1]] for n, p in joints.items() if at[n] in JOINT_NAMES}


def test_bvh_forward_kinematics_gives_back_the_joints(tmp_path):
    x = _walk(40)
    x[5:8, JOINT_NAMES.index("left_wrist")] = np.nan  # missed for 3 frames: interpolated
    x[20] = np.nan  # a frame with nothing
    path = tmp_path / "walk.bvh"
    path.write_text(bvh_text(x, 15.0))
    text = path.read_text()
    assert text.startswith("HIERARCHY\nROOT Hips\n") and "Frames: 40\nFrame Time: 0.066666667\n" in text
    back = _bvh_joints(path)
    assert set(back) == set(JOINT_NAMES)
    seen = np.isfinite(x).all(axis=2)
    for name, pos in back.items():
        j = JOINT_NAMES.index(name)
        err = np.linalg.norm(pos - x[:, j], axis=-1)[seen[:, j]]
        assert err.max() < 1e-4, (name, err.max())
        assert np.isfinite(pos).all()  # the gaps are filled
    wrist = back["left_wrist"][5:8]
    assert np.all(np.linalg.norm(wrist - x[[4, 8], JOINT_NAMES.index("left_wrist")].mean(0), axis=-1) < 0.2)
    # Offsets: the person's median bone lengths, in the rest pose's directions (y up, x the walker's left).
    thigh = np.median(np.linalg.norm(x[:, 7] - x[:, 9], axis=-1)[seen[:, 7] & seen[:, 9]])
    assert f"OFFSET 0.000000 -{thigh:.6f} 0.000000" in text


def test_bvh_handles_gimbal_lock_and_varying_bone_lengths(tmp_path, mocap_dir):
    """A thigh raised forward to the horizontal (ZXY's gimbal lock: X = -90 deg) still comes back; on a
    recording, whose bones vary a little, each joint comes back within that variation."""
    from estimator.mocap import read_motion

    x = _walk(4)
    hip, knee, ankle = (JOINT_NAMES.index(n) for n in ("left_hip", "left_knee", "left_ankle"))
    thigh, shank = (np.linalg.norm(x[1, a] - x[1, b]) for a, b in ((hip, knee), (knee, ankle)))
    x[1, knee] = x[1, hip] + [thigh, 0.0, 0.0]  # horizontal, forward
    x[1, ankle] = x[1, knee] + [0.0, 0.0, -shank]
    path = tmp_path / "lift.bvh"
    path.write_text(bvh_text(x, 30.0))
    for name, pos in _bvh_joints(path).items():
        assert np.abs(pos - x[:, JOINT_NAMES.index(name)]).max() < 1e-4, name
    rec = read_motion(Path(mocap_dir) / "16_15.amc").joints[::8][:60]
    path.write_text(bvh_text(rec, 15.0))
    for name, pos in _bvh_joints(path).items():
        assert np.linalg.norm(pos - rec[:, JOINT_NAMES.index(name)], axis=-1).max() < 0.01, name


def test_bvh_needs_every_joint_once():
    x = _walk(5)
    x[:, 0] = np.nan
    with pytest.raises(ValueError, match="'head' is never placed"):
        bvh_text(x, 15.0)


def test_csv_columns_units_and_missing_cells():
    x = _walk(3)
    x[1, 0] = np.nan
    rows = list(csv.reader(io.StringIO(csv_text(x, 30.0, frames=[10, 11, 13]))))
    assert rows[0][:5] == ["frame", "time", "head_x", "head_y", "head_z"]
    assert rows[0][-1] == "right_ankle_z" and len(rows[0]) == 2 + 3 * N_JOINTS
    assert [r[:2] for r in rows[1:]] == [["10", "0.000000"], ["11", "0.033333"], ["13", "0.100000"]]
    assert rows[2][2:5] == ["", "", ""]
    np.testing.assert_allclose(np.array(rows[3][2:], float).reshape(N_JOINTS, 3), x[2], atol=1e-6)


# ------------------------------------------------------------------ from results


def _result(x: np.ndarray, cams: PinholeCameras | None, names=("c0", "c1", "c2")) -> dict:
    """A batch result's parts the exports read: frames with person_joints3d, fps, rig and body."""
    frames = [{"index": 100 + k, "joints3d": None,
               "person_joints3d": [None if not np.isfinite(p).all() else p.tolist() for p in f]}
              for k, f in enumerate(x)]
    out = {"frames": frames, "fps": 15.0, "body": {"stature_m": 1.75, "segments": {}}}
    if cams is None:
        out["rig"] = {"reference": "c0", "source": "viewpoints",
                      "cameras": {n: {"rotation": np.eye(3).tolist(), "scale": 1.0} for n in names}}
        return out
    r0, c0 = cams.rotations[0], -cams.rotations[0].T @ cams.translations[0]
    rig = {}
    for c, n in enumerate(names):  # as Rig.to_dict writes them: relative to the reference, 6 decimals
        centre = -cams.rotations[c].T @ cams.translations[c]
        rig[n] = {"rotation": np.round(cams.rotations[c] @ r0.T, 6).tolist(), "scale": 1.0,
                  "focal_px": float(cams.matrices[c, 0, 0]), "centre_m": np.round(r0 @ (centre - c0), 3).tolist(),
                  "image_size": [W, H]}
    out["rig"] = {"reference": "c0", "source": "self-calibration", "cameras": rig}
    return out


def test_results_export_their_joints_and_their_metric_rig():
    x = _walk(12)
    cams = _rig(x.reshape(-1, 3).mean(axis=0))
    result = _result(x, cams)
    joints, frames, key = result_joints(result)
    assert key == "person_joints3d" and frames[0] == 100 and np.allclose(joints, x)
    trc = export_result(result, "trc", "job.trc")
    assert trc.startswith("PathFileType\t4\t(X/Y/Z)\tjob.trc\n") and "\n100\t0.000000\t" in trc
    assert export_result(result, "csv").splitlines()[1].startswith("100,0.000000,")
    assert export_result(result, "bvh").startswith("HIERARCHY")
    # The rig: the reference camera's frame; the same relative poses and projections as the cameras.
    names, sizes, back = rig_cameras(result["rig"])
    assert names == ["c0", "c1", "c2"] and sizes.tolist() == [[W, H]] * 3
    moved = cams.moved(cams.rotations[0], -cams.rotations[0].T @ cams.translations[0])
    world = (x.reshape(-1, 3) - (-cams.rotations[0].T @ cams.translations[0])) @ cams.rotations[0].T
    np.testing.assert_allclose(project(back, world), project(moved, world), atol=0.5)  # centres to the mm
    toml = tomllib.loads(export_result(result, "toml"))
    assert list(toml) == ["c0", "c1", "c2", "metadata"] and toml["c0"]["rotation"] == [0.0, 0.0, 0.0]
    assert toml["metadata"]["source"] == "posecal estimate" and toml["metadata"]["stature_m"] == 1.75
    assert "%YAML" in export_result(result, "yaml")


def test_a_result_says_why_it_cannot_give_a_format():
    x = _walk(5)
    result = _result(x, None)
    for fmt in ("toml", "yaml"):
        with pytest.raises(ValueError, match="no metric cameras.*'viewpoints'"):
            export_result(result, fmt)
    cams = _rig(x.reshape(-1, 3).mean(axis=0))
    partial = _result(x, cams)
    partial["rig"]["cameras"]["c2"].update(rotation=None, focal_px=None, centre_m=None)
    with pytest.raises(ValueError, match="camera 'c2' is not in the metric rig"):
        export_result(partial, "toml")
    old = _result(x, cams)
    for cam in old["rig"]["cameras"].values():
        del cam["image_size"]
    with pytest.raises(ValueError, match="no image size"):
        export_result(old, "toml")
    old["sequence"] = {"image_size": [W, H], "fps": 15.0}  # posecal estimate's results have it
    assert export_result(old, "toml")
    with pytest.raises(ValueError, match="no rig"):
        export_calibration({"calibration": None}, "toml")
    del result["fps"]
    with pytest.raises(ValueError, match="no frame rate"):
        export_result(result, "trc")


# ------------------------------------------------------------------ posecal selfcal


@pytest.fixture(scope="module")
def tracks_doc() -> dict:
    """The walk seen by the three pinhole cameras: a tracks JSON in pixels."""
    x = _walk(30)
    pix = project(_rig(x.reshape(-1, 3).mean(axis=0)), x)
    pix += np.random.default_rng(1).normal(0, 0.3, pix.shape)
    return {"joint_names": list(JOINT_NAMES), "cameras": {n: pix[c].tolist() for c, n in enumerate(("a", "b", "c"))}}


def test_selfcal_writes_every_export(tmp_path, tracks_doc):
    (tmp_path / "t.json").write_text(json.dumps(tracks_doc))
    out = {ext: tmp_path / "out" / f"walk.{ext}" for ext in ("yaml", "json", "trc", "bvh", "csv")}
    for calib in ("yaml", "json"):
        assert main(["selfcal", str(tmp_path / "t.json"), "--image-size", f"{W},{H}", "--out",
                     str(tmp_path / "r.json"), "--export-calibration", str(out[calib]), "--export-trc", str(out["trc"]),
                     "--export-bvh", str(out["bvh"]), "--export-csv", str(out["csv"]), "--fps", "15"]) == 0
        fs = cv2.FileStorage(str(out[calib]), cv2.FILE_STORAGE_READ)
        assert fs.getNode("cameras").size() == 3 and fs.getNode("cameras").at(1).getNode("name").string() == "b"
        fs.release()
    rows = list(csv.reader(out["csv"].open()))
    joints = np.array([[float(v) for v in r[2:]] for r in rows[1:]]).reshape(-1, N_JOINTS, 3)
    assert len(joints) == 30 and [r[0] for r in rows[1:3]] == ["1", "2"]
    head_up = np.median(joints[:, 0, 2] - joints[:, 11:13, 2].mean(axis=1))
    assert 1.3 < head_up < 1.8  # z up, metres at the stature
    back = _bvh_joints(out["bvh"])  # the same joints as the CSV, within the bones' variation
    assert max(np.linalg.norm(p - joints[:, JOINT_NAMES.index(n)], axis=-1).max() for n, p in back.items()) < 0.03


def test_selfcal_export_codes(tmp_path, tracks_doc, capsys):
    (tmp_path / "t.json").write_text(json.dumps(tracks_doc))
    base = ["selfcal", str(tmp_path / "t.json"), "--image-size", f"{W},{H}", "--out", str(tmp_path / "r.json")]
    assert main(base + ["--export-calibration", str(tmp_path / "c.txt")]) == 2  # usage: checked first
    assert ".toml, .yaml, .yml, .json" in capsys.readouterr().err and not (tmp_path / "r.json").exists()
    headless = json.loads(json.dumps(tracks_doc))
    for frames in headless["cameras"].values():
        for f in frames:
            f[0] = None  # the head never seen: a calibration, a TRC, but no BVH (exit 1)
    (tmp_path / "h.json").write_text(json.dumps(headless))
    code = main(["selfcal", str(tmp_path / "h.json"), "--image-size", f"{W},{H}", "--out", str(tmp_path / "h-r.json"),
                 "--export-calibration", str(tmp_path / "h.toml"), "--export-bvh", str(tmp_path / "h.bvh")])
    assert code == 1 and "'head' is never placed" in capsys.readouterr().err
    assert (tmp_path / "h.toml").exists() and not (tmp_path / "h.bvh").exists()


def test_a_file_is_written_whole_or_not_at_all(tmp_path):
    """``write_text`` (results, exports): a write that fails leaves the file as it was and no partial
    file beside it (an unserialisable result once left half a JSON file for the next reader)."""
    from service.exports import write_text

    path = tmp_path / "deep" / "result.json"
    write_text(path, '{"old": 1}')
    assert path.read_text() == '{"old": 1}'

    with pytest.raises(UnicodeEncodeError):  # a lone surrogate: no encoding writes it
        write_text(path, '{"new": "' + "x" * 10000 + '\udc80"}')
    assert path.read_text() == '{"old": 1}'
    assert sorted(p.name for p in path.parent.iterdir()) == ["result.json"]
    write_text(path, '{"new": 2}')
    assert path.read_text() == '{"new": 2}'
    write_text(Path("/dev/null"), "nothing")  # not a file: written through, not replaced
    assert Path("/dev/null").is_char_device()
