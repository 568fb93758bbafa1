"""Synthetic sequences: truth consistent with the images, deterministic, and the CLI."""

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from estimator.camera import Camera
from estimator.sequence import SequenceError, read_sequence, write_sequence
from estimator.synth import SynthSpec, synthesize
from service.cli import main

CHECK = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "tools", "check_conventions.py")


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("seq") / "walk"
    assert main(["synth", "--out", str(out), "--cameras", "3", "--frames", "12", "--seed", "7"]) == 0
    return out


def test_folder_layout(seq_dir):
    rig = json.loads((seq_dir / "rig.json").read_text())
    assert rig == {"fps": 15.0, "cameras": ["c0", "c1", "c2"], "image_size": [640, 480]}
    for cam in rig["cameras"]:
        files = sorted(os.listdir(seq_dir / cam))
        assert files == [f"{k:06d}.png" for k in range(12)]
        img = cv2.imread(str(seq_dir / cam / files[0]), cv2.IMREAD_UNCHANGED)
        assert img.shape == (480, 640) and img.dtype == np.uint8 and set(np.unique(img)) == {0, 255}
    assert (seq_dir / "preview.png").exists()


def test_truth_2d_is_projection_of_truth_3d(seq_dir):
    truth = json.loads((seq_dir / "truth.json").read_text())
    assert truth["joint_names"][0] == "head" and len(truth["frames"]) == 12
    for name, c in truth["cameras"].items():
        assert 0 <= c["azimuth_deg"] < 360 and -20 <= c["elevation_deg"] <= 35
        for fr in truth["frames"]:
            X = np.array(fr["joints3d"]) + np.array(fr["centroid_m"])
            cam = Camera(
                c["azimuth_deg"], c["elevation_deg"], distance=c["distance_m"], focal_px=c["focal_px"],
                target=tuple(np.array(c["position_m"]) - c["distance_m"] * _dir(c)),
            )
            np.testing.assert_allclose(cam.project(X), fr["joints2d"][name], atol=2e-3)
            np.testing.assert_allclose(np.mean(fr["joints3d"], axis=0), 0.0, atol=1e-4)


def _dir(c):
    a, e = np.radians(c["azimuth_deg"]), np.radians(c["elevation_deg"])
    return np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])


@pytest.mark.skipif(not os.path.exists(CHECK), reason="shared/tools/check_conventions.py not present")
def test_independent_convention_check(seq_dir):
    out = subprocess.run([sys.executable, CHECK, str(seq_dir)], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "OK" in out.stdout


def test_deterministic_for_a_seed():
    spec = SynthSpec(n_cameras=2, n_frames=4, seed=3, image_size=(320, 240))
    a, b = synthesize(spec), synthesize(spec)
    assert a.truth == b.truth
    for cam in a.cameras:
        for x, y in zip(a.silhouettes[cam], b.silhouettes[cam]):
            np.testing.assert_array_equal(x, y)
    c = synthesize(SynthSpec(n_cameras=2, n_frames=4, seed=4, image_size=(320, 240)))
    assert c.truth["cameras"] != a.truth["cameras"]


def test_fixed_viewpoints_and_walk_direction():
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=10, seed=1, azimuths=(90.0, 0.0), elevations=(0.0, 10.0)))
    cams = seq.truth["cameras"]
    assert cams["c0"]["azimuth_deg"] == 90.0 and cams["c1"]["elevation_deg"] == 10.0
    # Seen from the left (azimuth 90) the walker moves towards the image's left;
    # seen from ahead (azimuth 0) the walker approaches and grows.
    cx = [np.nonzero(s)[1].mean() for s in seq.silhouettes["c0"]]
    assert cx[-1] < cx[0] - 20
    h = [np.ptp(np.nonzero(s)[0]) for s in seq.silhouettes["c1"]]
    assert h[-1] > h[0]


def test_motion_driven_walk(mocap_dir):
    from estimator.mocap import read_motion

    m = read_motion(os.path.join(mocap_dir, "16_15.bvh"))
    seq = synthesize(SynthSpec(n_cameras=1, n_frames=20, seed=2, azimuths=(90.0,), elevations=(0.0,)), motion=m)
    phases = np.array([f["phase"] for f in seq.truth["frames"]])
    steps = np.diff(phases) % 1.0
    assert np.all(steps < 0.2) and steps.mean() > 0.02  # phase advances smoothly
    assert seq.truth["motion"] == "16_15.bvh"
    assert all((s > 0).sum() > 500 for s in seq.silhouettes["c0"])


def test_sequence_round_trip_and_errors(tmp_path):
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=3, seed=0, image_size=(160, 120)))
    seq.silhouettes["c1"][1] = None  # a missing frame
    write_sequence(tmp_path / "s", seq)
    back = read_sequence(tmp_path / "s")
    assert back.cameras == ["c0", "c1"] and back.silhouettes["c1"][1] is None
    np.testing.assert_array_equal(back.silhouettes["c0"][2], seq.silhouettes["c0"][2])
    (tmp_path / "s" / "c0" / "000001.png").write_bytes(b"not a png")
    with pytest.raises(SequenceError, match="not a readable PNG"):
        read_sequence(tmp_path / "s")
    with pytest.raises(SequenceError, match="rig.json is missing"):
        read_sequence(tmp_path)


@pytest.mark.parametrize("value", [1, 15, 76])  # 0/1, a class index, a red walker read as grey
def test_two_valued_masks_are_read_as_silhouettes(tmp_path, value):
    """Segmentation tools write masks as 0 and one value, often not 255: read with the > 127 rule
    they would be empty frames. A soft mask (0-255) keeps that rule, so its faint pixels are not
    the walker; inverted masks are refused with a reason."""
    import cv2

    seq = synthesize(SynthSpec(n_cameras=2, n_frames=3, seed=0, image_size=(160, 120)))
    write_sequence(tmp_path / "s", seq)
    for k in range(3):
        cv2.imwrite(str(tmp_path / "s" / "c0" / f"{k:06d}.png"), (seq.silhouettes["c0"][k] > 0).astype(np.uint8) * value)
        soft = np.where(seq.silhouettes["c1"][k] > 0, 200, 40).astype(np.uint8)  # faint everywhere
        cv2.imwrite(str(tmp_path / "s" / "c1" / f"{k:06d}.png"), soft)
    back = read_sequence(tmp_path / "s")
    for k in range(3):
        np.testing.assert_array_equal(back.silhouettes["c0"][k], seq.silhouettes["c0"][k])
        np.testing.assert_array_equal(back.silhouettes["c1"][k], seq.silhouettes["c1"][k])
    for k in range(3):  # the walker dark on light
        cv2.imwrite(str(tmp_path / "s" / "c0" / f"{k:06d}.png"), (seq.silhouettes["c0"][k] == 0).astype(np.uint8) * value)
    with pytest.raises(SequenceError, match="masks look inverted"):
        read_sequence(tmp_path / "s")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--cameras", "0"], "positive integer"),
        (["--frames", "x"], "positive integer"),
        (["--azimuths", "10,abc"], "comma-separated"),
        (["--cameras", "2", "--azimuths", "10"], "one value per camera"),
        (["--elevations", "95,0"], "elevations"),
        (["--motion", "/nonexistent/walk.bvh"], "No such file"),
    ],
)
def test_cli_bad_arguments_exit_2(tmp_path, argv, message):
    out = subprocess.run(
        [sys.executable, "-m", "service.cli", "synth", "--out", str(tmp_path / "o"), "--frames", "2", *argv],
        capture_output=True, text=True,
    )
    assert out.returncode == 2, out.stderr
    assert message in out.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("az, el", [(0.0, 35.0), (180.0, 30.0)])
def test_walk_stays_in_frame_for_head_on_elevated_cameras(az, el):
    seq = synthesize(SynthSpec(n_cameras=1, n_frames=40, seed=1, azimuths=(az,), elevations=(el,), distance=8.0))
    s = np.array(seq.silhouettes["c0"])
    assert not s[:, [0, -1], :].any() and not s[:, :, [0, -1]].any()


def test_rewriting_a_folder_leaves_no_stale_frames(tmp_path):
    long = synthesize(SynthSpec(n_cameras=1, n_frames=6, seed=0, image_size=(160, 120)))
    short = synthesize(SynthSpec(n_cameras=1, n_frames=3, seed=1, image_size=(160, 120)))
    write_sequence(tmp_path / "s", long)
    short.truth = None
    write_sequence(tmp_path / "s", short)
    back = read_sequence(tmp_path / "s")
    assert len(back.silhouettes["c0"]) == 3 and back.truth is None
