"""Keypoint import (OpenPose, MMPose, MediaPipe) and the exports of ``posecal selfcal``.

Every fixture is written by the test itself, in each format's layout, from
joints projected through known cameras.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator._selfcal_core import geodesic_deg
from estimator.joints import JOINT_INDEX, JOINT_NAMES, N_JOINTS
from estimator.keypoints import SKELETONS, detect_skeleton, keypoints_to_joints, track_person
from service.cli import main
from service.exports import TRC_MARKERS
from service.keypoints_io import read_keypoints

W, H = 640, 480


def _layout(name: str, joints: np.ndarray, conf: float = 0.9) -> np.ndarray:
    """(..., K, 3) [x, y, c] of a layout with the 13 joints where the layout maps them (both ears
    on the head, so that their midpoint is the head), BODY_25's neck and mid hip, and every other
    keypoint missing (0, 0, 0)."""
    skel = SKELETONS[name]
    out = np.zeros(joints.shape[:-2] + (skel.n_keypoints, 3))
    for j, src in enumerate(skel.sources):
        for i in src:
            out[..., i, :2] = joints[..., j, :]
            out[..., i, 2] = conf
    if name == "BODY_25":  # its neck and mid hip
        out[..., 1, :] = (out[..., 2, :] + out[..., 5, :]) / 2
        out[..., 8, :] = (out[..., 9, :] + out[..., 12, :]) / 2
    return out


def write_openpose(root, cameras, joints) -> None:
    """OpenPose BODY_25 folders ``root/<camera>_json`` of one file per frame, numbered from 0, from
    ``joints`` (cameras, frames, 13, 2): a NaN joint is missed (0, 0, 0 as OpenPose writes it)."""
    for cam, per_frame in zip(cameras, joints):
        folder = Path(root) / f"{cam}_json"
        folder.mkdir(parents=True)
        body = _layout("BODY_25", np.nan_to_num(per_frame, nan=-1.0))
        for t, people in enumerate(body):
            people = people.copy()
            people[(people[:, :2] < 0).any(-1)] = 0.0
            (folder / f"{cam}_{t:012d}_keypoints.json").write_text(
                json.dumps({"people": [{"pose_keypoints_2d": people.ravel().round(2).tolist()}]}))


def write_walk_videos(folder, views, frames: int, *, pose=None, seed: int = 5) -> list[Path]:
    """One small MJPG video per camera ``(name, azimuth)`` of the synthetic walker (12 empty frames,
    then a 30-frame pass; 320x240, 15 fps, 10 deg of elevation); with ``pose``, the renders' joints
    with a detector's 1 px of noise as OpenPose folders ``pose/<camera>_json``, numbered by each
    video's own frames."""
    import cv2

    from capture.synthetic import SyntheticSource

    rng = np.random.default_rng(seed)
    paths = []
    for cam, az in views:
        src = SyntheticSource.from_spec(f"seed=3,azimuth={az},elevation=10,empty=12,pass=30,gap=0,size=320x240")
        paths.append(Path(folder) / f"{cam}.avi")
        writer = cv2.VideoWriter(str(paths[-1]), cv2.VideoWriter_fourcc(*"MJPG"), 15, (320, 240))
        if pose is not None:
            (Path(pose) / f"{cam}_json").mkdir(parents=True)
        for i in range(frames):
            writer.write(src.render(i).image)
            truth = src.truth(i) if pose is not None else None
            people = []
            if truth is not None:
                _, joints2d = src._renderer.render(truth["joints"], src.camera)
                noisy = joints2d + rng.normal(0, 1.0, joints2d.shape)
                people = [{"pose_keypoints_2d": _layout("BODY_25", noisy).ravel().round(2).tolist()}]
            if pose is not None:
                (Path(pose) / f"{cam}_json" / f"{cam}_{i:012d}_keypoints.json").write_text(
                    json.dumps({"people": people}))
        writer.release()
        src.close()
    return paths


def _look_at(centre, target):
    f = np.asarray(target, float) - centre
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f])


@pytest.fixture(scope="module")
def scene(mocap_dir):
    """A real walk (30 frames at 15 Hz) seen by 3 pinhole cameras 3-4 m away: truth and pixels."""
    from estimator.mocap import read_motion

    x = read_motion(Path(mocap_dir) / "16_15.amc").joints[60:300:8]
    mid = x.reshape(-1, 3).mean(axis=0)
    cams = []
    for az, dist, height, f in ((20, 3.5, 1.6, 560.0), (115, 3.0, 1.3, 620.0), (230, 4.0, 1.9, 700.0)):
        a = np.radians(az)
        c = mid + [dist * np.cos(a), dist * np.sin(a), height - mid[2]]
        cams.append((_look_at(c, mid), c, f))
    pix = np.stack([f * ((x - c) @ r.T)[..., :2] / ((x - c) @ r.T)[..., 2:] + [W / 2, H / 2] for r, c, f in cams])
    pix += np.random.default_rng(3).normal(0, 0.5, pix.shape)
    return {"x": x, "cams": cams, "pix": pix, "names": ["cam01", "cam02", "cam03"]}


def _write_openpose(root: Path, names, pix: np.ndarray, layout="BODY_25", extra_people=None) -> Path:
    for c, name in enumerate(names):
        folder = root / f"{name}_json"
        folder.mkdir(parents=True)
        for t, frame in enumerate(_layout(layout, pix[c])):
            people = [frame] + ([] if extra_people is None else extra_people(c, t))
            doc = {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": p.ravel().tolist()}
                                               for p in people]}
            (folder / f"trial_{t + 100:012d}_keypoints.json").write_text(json.dumps(doc))
    return root


def _geodesic_pairs(rotations: dict, names, cams) -> np.ndarray:
    """Errors of every camera pair's relative rotation, from ``R_c R_0^T`` per camera name."""
    est = [np.eye(3)] + [np.asarray(rotations[n]) for n in names[1:]]
    return np.array([geodesic_deg(cams[i][0] @ cams[k][0].T, est[i] @ est[k].T)
                     for i in range(len(cams)) for k in range(i + 1, len(cams))])


# ------------------------------------------------------------------ skeletons and mapping


@pytest.mark.parametrize(("name", "checks"), [
    ("COCO_17", {"left_knee": (13,), "right_wrist": (10,), "head": (3, 4)}),
    ("COCO_18", {"left_knee": (12,), "right_ankle": (10,), "head": (17, 16)}),
    ("BODY_25", {"left_knee": (13,), "right_hip": (9,), "head": (18, 17)}),
    ("BODY_25B", {"left_knee": (13,), "right_hip": (12,), "head": (3, 4)}),
    ("HALPE_26", {"left_ankle": (15,), "head": (3, 4)}),
    ("MEDIAPIPE_33", {"left_hip": (23,), "right_elbow": (14,), "head": (7, 8)}),
    ("COCO_133", {"right_shoulder": (6,)}),
])
def test_skeleton_tables(name, checks):
    skel = SKELETONS[name]
    for joint, src in checks.items():
        assert skel.sources[JOINT_INDEX[joint]] == src
    # Each keypoint at (index, 0): the mapped joints read back their sources' mean index.
    k = np.stack([np.arange(skel.n_keypoints, dtype=float), np.zeros(skel.n_keypoints)], axis=-1)
    joints, conf = keypoints_to_joints(k, np.ones(skel.n_keypoints), skel)
    assert np.allclose(joints[:, 0], [np.mean(s) for s in skel.sources]) and (conf == 1).all()
    # No source is used twice, and left stays left.
    flat = [i for s in skel.sources for i in s]
    assert len(flat) == len(set(flat))


def _person(rng, n=5) -> np.ndarray:
    """(n, 13, 2) plausible upright people, about 300 px tall."""
    base = np.array([[0, -150], [-40, -110], [40, -110], [-50, -50], [50, -50], [-55, 0], [55, 0],
                     [-25, 0], [25, 0], [-25, 70], [25, 70], [-25, 140], [25, 140]], float)
    return base + [320, 240] + rng.normal(0, 3, (n, N_JOINTS, 2))


@pytest.mark.parametrize(("count", "name"), [(17, "COCO_17"), (18, "COCO_18"), (26, "HALPE_26"),
                                             (33, "MEDIAPIPE_33"), (133, "COCO_133")])
def test_detect_skeleton_by_count(count, name):
    assert detect_skeleton(np.zeros((2, count, 2))).name == name


def test_detect_body25_from_body25b():
    rng = np.random.default_rng(0)
    people = _person(rng)
    b25 = _layout("BODY_25", people)
    assert detect_skeleton(b25[..., :2], b25[..., 2]).name == "BODY_25"
    b25b = _layout("BODY_25B", people)
    b25b[:, 1:3, :2] = people[:, None, 0] + [[8, 0], [-8, 0]]  # eyes by the head
    b25b[:, 1:3, 2] = 0.9
    assert detect_skeleton(b25b[..., :2], b25b[..., 2]).name == "BODY_25B"


def test_detect_body25_in_side_views():
    """Seen from the side the shoulders and the hips overlap: their widths vanish, and an offset measured
    in widths took BODY_25 for BODY_25B (two cameras of a 4-camera rig). In units of the person's size
    the side view decides like any other, for both layouts."""
    rng = np.random.default_rng(1)
    people = _person(rng, 40)
    people[:, 1:, 0] = 320 + (people[:, 1:, 0] - 320) * 0.05  # a side view: left and right nearly coincide
    b25 = _layout("BODY_25", people)
    b25[:, [1, 8], :2] += rng.normal(0, 3, (40, 2, 2))  # the detector's own neck and mid hip
    assert detect_skeleton(b25[..., :2], b25[..., 2]).name == "BODY_25"
    noisy = b25.copy()  # a detector's noise of 3 % of the height on every keypoint
    noisy[..., :2] += rng.normal(0, 9, noisy[..., :2].shape) * (noisy[..., 2:] > 0)
    assert detect_skeleton(noisy[..., :2], noisy[..., 2]).name == "BODY_25"
    b25b = _layout("BODY_25B", people)
    b25b[:, 1:3, :2] = people[:, None, 0] + [[8, 0], [6, 0]]  # eyes by the head, in front
    b25b[:, 1:3, 2] = 0.9
    assert detect_skeleton(b25b[..., :2], b25b[..., 2]).name == "BODY_25B"


def test_unknown_keypoint_count():
    with pytest.raises(ValueError, match="unknown keypoint count 21"):
        detect_skeleton(np.zeros((1, 21, 2)))


def test_low_confidence_and_missing_become_missing():
    rng = np.random.default_rng(1)
    k = _layout("COCO_17", _person(rng, 1))[0]
    k[13, 2] = 0.2  # left knee below the threshold
    k[15, :] = 0.0  # left ankle missed, as OpenPose writes it
    k[4, 2] = 0.1  # one ear: no head
    k[6, 2] = 0.35  # right shoulder kept, its confidence carried
    joints, conf = keypoints_to_joints(k[:, :2], k[:, 2], SKELETONS["COCO_17"], min_confidence=0.3)
    for name in ("left_knee", "left_ankle", "head"):
        assert np.isnan(joints[JOINT_INDEX[name]]).all() and conf[JOINT_INDEX[name]] == 0
    assert np.isfinite(joints[JOINT_INDEX["right_shoulder"]]).all()
    assert conf[JOINT_INDEX["right_shoulder"]] == pytest.approx(0.35)
    assert np.isfinite(joints).all(axis=-1).sum() == N_JOINTS - 3
    # The threshold is an option: at 0.5 the right shoulder goes too.
    joints, _ = keypoints_to_joints(k[:, :2], k[:, 2], SKELETONS["COCO_17"], min_confidence=0.5)
    assert np.isnan(joints[JOINT_INDEX["right_shoulder"]]).all()


def test_track_person_follows_one_person():
    rng = np.random.default_rng(2)
    big = _person(rng, 20) + np.arange(20)[:, None, None] * [6.0, 0.0]  # walks right, 6 px per frame
    small = (_person(rng, 20) - [320, 240]) * 0.5 + [600, 200] - np.arange(20)[:, None, None] * [4.0, 0.0]
    frames = []
    for t in range(20):
        people = [small[t], big[t]] if t % 2 else [big[t], small[t]]  # detector order changes
        if t == 7:
            people = [small[t]]  # the tracked person is lost for a frame: nobody, not the other one
        frames.append(np.stack(people))
    chosen = track_person(frames)
    assert chosen[7] == -1
    for t in range(20):
        if t != 7:
            assert np.allclose(frames[t][chosen[t]], big[t])


def test_track_person_keeps_the_subject_when_a_passer_by_is_larger_at_first():
    """A passer-by nearer the camera is the largest person on the first frames and then leaves; the
    subject, smaller but there throughout, is the one followed."""
    rng = np.random.default_rng(3)
    subject = _person(rng, 20) * 0.6 + [100, 60]
    passer = (_person(rng, 20) - [320, 240]) * 1.4 + [480, 240] + np.arange(20)[:, None, None] * [30.0, 0.0]
    frames = [np.stack([passer[t], subject[t]]) if t < 4 else subject[t][None] for t in range(20)]
    chosen = track_person(frames)
    assert all(np.allclose(frames[t][chosen[t]], subject[t]) for t in range(20))


def test_track_person_is_not_lost_after_a_frame_with_few_joints():
    """A frame where the detector saw only the head and shoulders gives a small box; the gate is measured
    on the track's usual size, not on that box, so the subject is found again on the next frame (on the
    Pose2Sim demo with 30 % of its keypoints removed, a camera otherwise followed the bystander)."""
    rng = np.random.default_rng(4)
    subject = _person(rng, 20)
    bystander = (_person(rng, 20) - [320, 240]) * 0.5 + [600, 240]
    frames = []
    for t in range(20):
        seen = subject[t].copy()
        if t == 5:
            seen[3:] = np.nan  # the head and the shoulders only
        frames.append(np.stack([seen, bystander[t]]))
    chosen = track_person(frames)
    assert (chosen == 0).all(), chosen


# ------------------------------------------------------------------ file formats


def test_openpose_folder_and_pose_subfolder(tmp_path, scene):
    pix = scene["pix"]
    for root in (tmp_path / "a", tmp_path / "b" / "pose"):
        _write_openpose(root, scene["names"], pix)
    for given in (tmp_path / "a", tmp_path / "b"):
        kp = read_keypoints([given])
        assert kp.format == "openpose" and kp.cameras == scene["names"]
        assert kp.skeletons == {n: "BODY_25" for n in scene["names"]}
        assert kp.frames == list(range(100, 100 + pix.shape[1]))
        assert np.allclose(kp.tracks, pix) and np.allclose(kp.confidence, 0.9)


def test_openpose_multi_person_keeps_the_same_person(tmp_path, scene):
    pix = scene["pix"]

    def bystander(c, t):  # a smaller person standing at the image's right edge, listed first half the time
        return [_layout("BODY_25", (pix[c, 0] - pix[c, 0].mean(0)) * 0.4 + [W - 60, H / 2])]

    root = _write_openpose(tmp_path, scene["names"], pix, extra_people=bystander)
    for c, name in enumerate(scene["names"]):  # shuffle the order of people in odd frames
        for t, path in enumerate(sorted((root / f"{name}_json").glob("*.json"))):
            if t % 2:
                doc = json.loads(path.read_text())
                doc["people"].reverse()
                path.write_text(json.dumps(doc))
    kp = read_keypoints([root])
    assert np.allclose(kp.tracks, pix)


def _mmpose_instances(frame13: np.ndarray) -> list:
    k = _layout("COCO_17", frame13)
    return [{"keypoints": k[:, :2].tolist(), "keypoint_scores": k[:, 2].tolist(), "bbox": [[0, 0, 1, 1]],
             "bbox_score": 0.99}]


@pytest.mark.parametrize("layout", ["video", "instance_info", "predictions"])
def test_mmpose_files(tmp_path, scene, layout):
    pix = scene["pix"]
    for c, name in enumerate(scene["names"]):
        frames = [_mmpose_instances(f) for f in pix[c]]
        doc = {"video": [{"frame_id": t, "instances": inst} for t, inst in enumerate(frames)],
               "instance_info": {"meta_info": {"dataset_name": "coco"},
                                 "instance_info": [{"frame_id": t + 1, "instances": i} for t, i in enumerate(frames)]},
               "predictions": {"predictions": frames}}[layout]
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    for given in ([tmp_path], sorted(tmp_path.glob("*.json"))):  # a folder, or one file per camera
        kp = read_keypoints(given)
        assert kp.format == "mmpose" and kp.cameras == scene["names"]
        assert set(kp.skeletons.values()) == {"COCO_17"} and np.allclose(kp.tracks, pix)


@pytest.mark.parametrize("normalised", [True, False])
def test_mediapipe_files(tmp_path, scene, normalised):
    pix = scene["pix"]
    for c, name in enumerate(scene["names"]):
        k = _layout("MEDIAPIPE_33", pix[c])
        scale = np.array([W, H]) if normalised else np.ones(2)
        frames = [[{"x": p[0] / scale[0], "y": p[1] / scale[1], "z": 0.0, "visibility": p[2]} for p in f] for f in k]
        frames[3] = None  # no detection in that frame
        doc = {"format": "mediapipe", "normalized": normalised, "frames": frames}
        if c == 0 and normalised:
            doc["image_size"] = [W, H]  # the others take --image-size
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    kp = read_keypoints([tmp_path], image_size=(W, H))
    assert kp.format == "mediapipe" and set(kp.skeletons.values()) == {"MEDIAPIPE_33"}
    assert 3 not in kp.frames and np.allclose(kp.tracks, np.delete(pix, 3, axis=1))
    if normalised:
        with pytest.raises(ValueError, match="cam02.json: normalised MediaPipe landmarks need the image size"):
            read_keypoints([tmp_path])


# ------------------------------------------------------------------ the command line


def _bad(tmp_path, capsys, argv, *needles):
    assert main(["selfcal", *map(str, argv), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    assert "posecal selfcal: error:" in err
    for n in needles:
        assert str(n) in err, (n, err)
    assert not (tmp_path / "r.json").exists()


def test_bad_keypoint_input_exit_2(tmp_path, capsys, scene):
    empty = tmp_path / "empty"
    empty.mkdir()
    _bad(tmp_path, capsys, [empty], empty, "no <camera>_json folders")
    root = _write_openpose(tmp_path / "op", scene["names"], scene["pix"])
    broken = sorted((root / "cam02_json").glob("*.json"))[4]
    broken.write_text("{not json")
    _bad(tmp_path, capsys, [root], "cannot read", broken)
    broken.write_text(json.dumps({"people": [{"pose_keypoints_2d": [1.0] * 21 * 3}]}))
    _bad(tmp_path, capsys, [root], broken, "21 keypoints")
    for path in (root / "cam02_json").glob("*.json"):
        path.write_text(json.dumps({"people": [{"pose_keypoints_2d": [1.0] * 21 * 3}]}))
    _bad(tmp_path, capsys, [root], root / "cam02_json", "unknown keypoint count 21")
    (root / "cam03_json" / "notes.json").write_text("{}")
    _bad(tmp_path, capsys, [root], root / "cam03_json" / "notes.json", "no frame number")
    empty_cam = tmp_path / "op2" / "cam01_json"
    empty_cam.mkdir(parents=True)
    (tmp_path / "op2" / "cam02_json").mkdir()
    _bad(tmp_path, capsys, [tmp_path / "op2"], empty_cam, "no JSON files")
    one = tmp_path / "one.json"
    one.write_text(json.dumps([{"frame_id": 0, "instances": _mmpose_instances(scene["pix"][0, 0])}]))
    _bad(tmp_path, capsys, [one], "two cameras", one)
    _bad(tmp_path, capsys, [root, "--min-confidence", "1.5"], "--min-confidence")


def test_selfcal_from_openpose_as_good_as_tracks(tmp_path, scene):
    """The same joints as OpenPose folders and as a tracks JSON give the same rig, near the truth."""
    names, pix = scene["names"], scene["pix"]
    root = _write_openpose(tmp_path / "op", names, pix)
    tracks = {"joint_names": list(JOINT_NAMES), "cameras": {n: pix[c].tolist() for c, n in enumerate(names)}}
    (tmp_path / "tracks.json").write_text(json.dumps(tracks))
    docs = {}
    for key, given in (("openpose", root), ("tracks", tmp_path / "tracks.json")):
        out = tmp_path / f"{key}.json"
        assert main(["selfcal", str(given), "--image-size", f"{W},{H}", "--out", str(out)]) == 0
        docs[key] = json.loads(out.read_text())
    errs = {k: _geodesic_pairs({n: d["cameras"][n]["rotation"] for n in names[1:]}, names, scene["cams"])
            for k, d in docs.items()}
    assert errs["openpose"].max() < 1.0 and errs["tracks"].max() < 1.0, errs
    assert abs(np.median(errs["openpose"]) - np.median(errs["tracks"])) < 0.2
    op = docs["openpose"]
    assert op["input"] == {"format": "openpose", "skeletons": {n: "BODY_25" for n in names}, "min_confidence": 0.3}
    assert [f["frame"] for f in op["frames"]] == [100 + f["index"] for f in op["frames"]]
    focal = [op["reference_focal_px"]] + [op["cameras"][n]["focal_px"] for n in names[1:]]
    assert np.allclose(focal, [f for _, _, f in scene["cams"]], rtol=0.05)


def _read_trc(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    lines = path.read_text().split("\n")
    rows = [ln.split("\t") for ln in lines[5:] if ln]
    data = np.array([[float(v) if v else np.nan for v in r] for r in rows])
    return lines[:5], data[:, :2], data[:, 2:].reshape(len(rows), -1, 3)


def test_exports_round_trip(tmp_path, scene):
    names, pix = scene["names"], scene["pix"]
    root = _write_openpose(tmp_path / "op", names, pix)
    toml_path, trc_path = tmp_path / "out" / "Calib.toml", tmp_path / "out" / "walk.trc"
    assert main(["selfcal", str(root), "--image-size", f"{W},{H}", "--max-frames", "20", "--out",
                 str(tmp_path / "r.json"), "--export-calibration", str(toml_path), "--export-trc",
                 str(trc_path), "--fps", "30"]) == 0
    calib = tomllib.loads(toml_path.read_text())
    assert list(calib) == names + ["metadata"]
    assert calib["metadata"]["adjusted"] is False and calib["metadata"]["reference_camera"] == "cam01"
    header, times, joints_yup = _read_trc(trc_path)
    # Header lines as OpenSim and Pose2Sim read them.
    assert header[0] == "PathFileType\t4\t(X/Y/Z)\twalk.trc"
    assert header[1].split("\t") == ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
                                     "OrigDataStartFrame", "OrigNumFrames"]
    assert header[2].split("\t") == ["30.0", "30.0", str(pix.shape[1]), "13", "m", "30.0", "100", str(pix.shape[1])]
    assert header[3].split("\t")[:5] == ["Frame#", "Time", "Head", "", ""]
    assert header[3].count("\t") == header[4].count("\t") == 1 + 3 * 13  # 2 + 3 x 13 cells each
    assert [c for c in header[3].split("\t")[2:] if c] == list(TRC_MARKERS)
    assert header[4].split("\t")[2:5] == ["X1", "Y1", "Z1"] and header[4].split("\t")[-1] == "Z13"
    # Every frame (the calibration used 20 of them), Frame# from the file names, time from --fps.
    assert joints_yup.shape == (pix.shape[1], 13, 3) and np.isfinite(joints_yup).all()
    assert np.allclose(times[:, 0], 100 + np.arange(pix.shape[1])) and np.allclose(times[:, 1], np.arange(30) / 30)
    # Y up: the head above the ankles by about the walker's height.
    head_y = joints_yup[:, 0, 1] - joints_yup[:, 11:13, 1].mean(axis=1)
    assert 1.3 < np.median(head_y) < 1.8
    world = joints_yup[..., [2, 0, 1]]  # Pose2Sim's zup2yup undone: (X, Y, Z) = (y, z, x)
    for c, name in enumerate(names):
        cam = calib[name]
        assert cam["name"] == name and cam["size"] == [W, H] and cam["fisheye"] is False
        assert cam["distortions"] == [0.0, 0.0, 0.0, 0.0]
        k, r = np.array(cam["matrix"]), Rotation.from_rotvec(cam["rotation"]).as_matrix()
        assert k.shape == (3, 3) and np.allclose(k[:, 2], [W / 2, H / 2, 1])
        h = (world @ r.T + cam["translation"]) @ k.T
        err = np.linalg.norm(h[..., :2] / h[..., 2:] - pix[c], axis=-1)
        assert np.median(err) < 2.0 and err.max() < 8.0, (name, np.median(err), err.max())
    # The rig in the file: relative rotations as in the truth, baselines in metres.
    rots = {n: Rotation.from_rotvec(calib[n]["rotation"]).as_matrix() for n in names}
    rel = {n: rots[n] @ rots[names[0]].T for n in names[1:]}
    assert _geodesic_pairs(rel, names, scene["cams"]).max() < 1.0
    centres = {n: -rots[n].T @ calib[n]["translation"] for n in names}
    true_c = [c for _, c, _ in scene["cams"]]
    d_est = np.linalg.norm(centres[names[0]] - centres[names[1]])
    assert d_est == pytest.approx(np.linalg.norm(true_c[0] - true_c[1]), rel=0.15)


def test_exports_need_image_size(tmp_path, capsys, scene):
    root = _write_openpose(tmp_path / "op", scene["names"], scene["pix"])
    _bad(tmp_path, capsys, [root, "--export-calibration", tmp_path / "c.toml"], "--image-size")
    assert not (tmp_path / "c.toml").exists()
