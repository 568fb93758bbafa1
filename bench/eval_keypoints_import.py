"""``posecal selfcal`` on detector-like keypoints of a real walk, through the real command line.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_keypoints_import.py [--rigs 8] [--seed 0]

For each seeded random rig: 4 pinhole cameras (640x480 or 1280x720, focal
0.6-1.2 image widths, no distortion) 2.5-4 m from the middle of a 2 s stretch of
CMU walk 16_15 (60 frames at 30 Hz, about 2.2 m of walking), at 1.2-2.0 m
height, aimed near the walker with up to 3 deg of roll, each framing the walk
(at least 95 % of the joints inside the image; otherwise drawn again: a 1280x720
camera at 1.3 widths would need 4.6 m to show a standing person whole). The walk's joints plus
the keypoints a detector adds (nose, eyes and ears placed on the head, toes
from the mocap, heels 6 cm behind the ankles) are projected and given
detector-like errors: Gaussian 2.5 px, 5 % of keypoints missed (confidence 0,
as OpenPose writes them), 1 % of left/right pairs swapped, 2 % outliers
displaced by 20-60 px, confidences 0.5-0.95 (outliers 0.3-0.7), keypoints
outside the image missed (``--noise-share``, ``--outliers``, ``--outlier-share``,
``--swaps`` change them: ``--outlier-share`` scales the outliers' displacement
with the walker's image height, as a detector's wrong keypoint lies on the
person). They are written as OpenPose BODY_25 folders
(``<cam>_json/<cam>_<frame>.json``) and MMPose COCO-17 prediction files, and
``python -m service.cli selfcal`` runs on them as a user would:

- default: ``selfcal FOLDER --image-size W,H`` (the refined path, then pinhole cameras);
- known intrinsics: ``selfcal FOLDER --intrinsics calib.toml`` (the true focal lengths and
  principal points, as a Pose2Sim calibration TOML; kept fixed by the pinhole adjustment);
- scaled orthographic: ``selfcal FOLDER`` (the refined path without pinholes);
- closed form: ``selfcal FOLDER --method closed-form``.

Reported: the median and p90 over all camera pairs of all rigs of the geodesic
error of the relative rotation ``R_i R_j^T``, the median / p90 of the focal
length's relative error, the median error of the camera centres (3 per rig, in
the reference camera's frame, metres; ``--height`` is the mocap walker's stature
so the scale is not part of it) and of their distances from the reference camera,
how many runs failed, how many the command flagged unreliable (exit 1: its
pinhole cameras fit the keypoints poorly; they are not in the error columns,
their worst pair is given), how many it accepted although a camera pair is
more than 10 deg off, and how many started the bundle adjustment elsewhere than
from the closed form (``start``). The MMPose files of the
first rig must give the same rig as its OpenPose folders (the same 13 joints).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pinhole import PinholeCameras  # noqa: E402
from estimator.rig import stature_scale  # noqa: E402
from service.exports import write_calibration_toml  # noqa: E402
from estimator.skeleton import FULL_JOINT_NAMES  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MOCAP = ROOT.parent / "shared" / "data" / "mocap" / "16_15.amc"
J = {n: i for i, n in enumerate(FULL_JOINT_NAMES)}

# COCO-17 keypoint names; BODY_25 adds neck (1), mid hip (8) and the feet, in its own order.
COCO17 = ("nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
          "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
          "right_knee", "left_ankle", "right_ankle")
BODY25 = ("nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
          "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee",
          "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear", "left_big_toe", "left_small_toe",
          "left_heel", "right_big_toe", "right_small_toe", "right_heel")
KEYPOINTS = tuple(dict.fromkeys(COCO17 + BODY25))  # every keypoint generated, one index each
K = {n: i for i, n in enumerate(KEYPOINTS)}
PAIRS = [(K[n], K[n.replace("left_", "right_")]) for n in KEYPOINTS if n.startswith("left_")]


def keypoints_3d(positions: np.ndarray) -> np.ndarray:
    """Every detector keypoint (T, len(KEYPOINTS), 3) from the mocap's posecal joints (T, 20, 3), metres.

    The head joint is the middle of the skull: the ears are 5 cm below it on the
    head's axis (neck to head) and 7.5 cm to each side (the shoulders' left), the
    nose 10 cm in front of the ears' midpoint and 2 cm lower, the eyes 2 cm behind
    the nose, 3.5 cm up and 3 cm to each side.
    """
    p = positions
    get = lambda n: p[:, J[n]]  # noqa: E731
    axis = get("head") - get("neck")
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    left = get("left_shoulder") - get("right_shoulder")
    left -= axis * np.sum(left * axis, axis=-1, keepdims=True)
    left /= np.linalg.norm(left, axis=-1, keepdims=True)
    front = np.cross(left, axis)
    ears = get("head") - 0.05 * axis
    nose = ears + 0.10 * front - 0.02 * axis
    eyes = nose - 0.02 * front + 0.035 * axis
    out = {
        "nose": nose, "left_eye": eyes + 0.03 * left, "right_eye": eyes - 0.03 * left,
        "left_ear": ears + 0.075 * left, "right_ear": ears - 0.075 * left,
        "neck": (get("left_shoulder") + get("right_shoulder")) / 2,
        "mid_hip": (get("left_hip") + get("right_hip")) / 2,
    }
    for side in ("left", "right"):
        ankle, toe = get(f"{side}_ankle"), get(f"{side}_toe")
        foot = toe - ankle
        foot[..., 2] = 0.0
        foot /= np.maximum(np.linalg.norm(foot, axis=-1, keepdims=True), 1e-9)
        out[f"{side}_big_toe"] = toe + 0.02 * np.cross(foot, [0, 0, 1.0]) * (1 if side == "left" else -1)
        out[f"{side}_small_toe"] = toe - 0.03 * np.cross(foot, [0, 0, 1.0]) * (1 if side == "left" else -1)
        out[f"{side}_heel"] = ankle - 0.06 * foot - [0, 0, 0.05]
    return np.stack([out[n] if n in out else get(n) for n in KEYPOINTS], axis=1)


def look_at(centre: np.ndarray, target: np.ndarray, roll_deg: float) -> np.ndarray:
    f = target - centre
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    base = np.stack([r, np.cross(f, r), f])
    return Rotation.from_rotvec([0, 0, np.radians(roll_deg)]).as_matrix() @ base


def random_rig(rng: np.random.Generator, path: np.ndarray, body: np.ndarray,
               distance: tuple[float, float] = (2.5, 4.0)) -> dict:
    """4 cameras around the middle of the walk (``path``: (T, 3) hip centres) that frame the
    walker: a camera that would see less than 95 % of the 13 joints ``body`` (T, 13, 3) in its
    image is drawn again (a lab points its cameras at the walkway)."""
    mid = path.mean(axis=0)
    w, h = [(640, 480), (1280, 720)][rng.integers(2)]
    cams = []
    start = rng.uniform(0, 360)
    while len(cams) < 4:
        az = np.radians(start + 90 * len(cams) + rng.uniform(-20, 20))
        dist = rng.uniform(*distance)
        centre = np.array([mid[0] + dist * np.cos(az), mid[1] + dist * np.sin(az), rng.uniform(1.2, 2.0)])
        target = np.array([mid[0], mid[1], 0.9]) + rng.normal(0, 0.1, 3)
        cam = {"name": f"cam{len(cams) + 1:02d}", "R": look_at(centre, target, rng.uniform(-3, 3)),
               "C": centre, "f": rng.uniform(0.6, 1.2) * w, "size": (w, h)}
        q = (body - centre) @ cam["R"].T
        uv = cam["f"] * q[..., :2] / q[..., 2:] + np.array([w, h]) / 2
        if ((uv >= 0).all(-1) & (uv < [w, h]).all(-1)).mean() >= 0.95:
            cams.append(cam)
    return {"cameras": cams, "size": (w, h)}


def detections(rng: np.random.Generator, x: np.ndarray, cam: dict, noise_px: float = 2.5, swaps: float = 0.01,
               outliers: float = 0.02, outlier_px: tuple[float, float] = (20.0, 60.0)) -> np.ndarray:
    """Detector-like (T, len(KEYPOINTS), 3) [u, v, confidence] of points ``x`` (T, N, 3)."""
    q = (x - cam["C"]) @ cam["R"].T
    uv = cam["f"] * q[..., :2] / q[..., 2:] + np.array(cam["size"]) / 2
    t, n = uv.shape[:2]
    swap = rng.random((t, len(PAIRS))) < swaps
    for k, (a, b) in enumerate(PAIRS):
        uv[swap[:, k], a], uv[swap[:, k], b] = uv[swap[:, k], b].copy(), uv[swap[:, k], a].copy()
    uv += rng.normal(0, noise_px, uv.shape)
    conf = rng.uniform(0.5, 0.95, (t, n))
    outlier = rng.random((t, n)) < outliers
    ang = rng.uniform(0, 2 * np.pi, (t, n))
    uv += outlier[..., None] * rng.uniform(*outlier_px, (t, n, 1)) * np.stack([np.cos(ang), np.sin(ang)], -1)
    conf[outlier] = rng.uniform(0.3, 0.7, outlier.sum())
    inside = (q[..., 2] > 0.1) & (uv >= 0).all(-1) & (uv < cam["size"]).all(-1)
    missed = (rng.random((t, n)) < 0.05) | ~inside
    out = np.concatenate([uv, conf[..., None]], axis=-1)
    out[missed] = 0.0
    return out


def write_openpose(root: Path, name: str, det: np.ndarray) -> None:
    """BODY_25 files ``root/<name>_json/<name>_<frame>.json`` as OpenPose writes them."""
    folder = root / f"{name}_json"
    folder.mkdir(parents=True)
    idx = [K[n] for n in BODY25]
    for t, frame in enumerate(det):
        person = {"person_id": [-1], "pose_keypoints_2d": [round(float(v), 3) for v in frame[idx].ravel()]}
        (folder / f"{name}_{t:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": [person]}))


def write_mmpose(root: Path, name: str, det: np.ndarray) -> None:
    """COCO-17 predictions ``root/<name>.json`` as MMPose's inferencer saves a video."""
    root.mkdir(parents=True, exist_ok=True)
    idx = [K[n] for n in COCO17]
    frames = [{"frame_id": t, "instances": [{"keypoints": frame[idx, :2].round(3).tolist(),
                                             "keypoint_scores": frame[idx, 2].round(4).tolist()}]}
              for t, frame in enumerate(det)]
    (root / f"{name}.json").write_text(json.dumps(frames))


def run_cli(inputs: Path, *extra: str) -> tuple[dict | None, float, str]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.json"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "service.cli", "selfcal", str(inputs), "--out", str(out), *extra],
                              capture_output=True, text=True, cwd=ROOT)
        dt = time.perf_counter() - t0
        if proc.returncode == 1 and out.is_file():  # written, but flagged unreliable
            return json.loads(out.read_text()), dt, "unreliable"
        if proc.returncode != 0:
            return None, dt, proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "?"
        return json.loads(out.read_text()), dt, ""


def write_intrinsics(path: Path, rig: dict) -> None:
    """The rig's true intrinsics (and poses) as a Pose2Sim calibration TOML, for ``--intrinsics``."""
    cams = rig["cameras"]
    sizes = np.array([c["size"] for c in cams], float)
    pin = PinholeCameras.from_centres(np.array([c["f"] for c in cams]), sizes / 2, np.stack([c["R"] for c in cams]),
                                      np.stack([c["C"] for c in cams]))
    write_calibration_toml(path, [c["name"] for c in cams], sizes, pin)


def image_height(body: np.ndarray, cam: dict) -> float:
    """The walker's median image height (pixels) in camera ``cam``: the vertical extent of the 13 joints."""
    q = (body - cam["C"]) @ cam["R"].T
    v = cam["f"] * q[..., 1] / q[..., 2]
    return float(np.median(v.max(axis=1) - v.min(axis=1)))


def centre_errors(doc: dict, rig: dict) -> tuple[list[float], list[float], list[float]]:
    """Errors (m) of cameras 1..'s centres in the reference camera's frame, of their distances to it, and the
    angle (deg) between the estimated and true directions from it (the translation direction)."""
    cams = rig["cameras"]
    pos, dist, dirs = [], [], []
    for c in cams[1:]:
        truth = cams[0]["R"] @ (c["C"] - cams[0]["C"])
        est = np.array(doc["cameras"][c["name"]]["centre_m"])
        pos.append(float(np.linalg.norm(est - truth)))
        dist.append(abs(float(np.linalg.norm(est) - np.linalg.norm(truth))))
        cos = est @ truth / max(np.linalg.norm(est) * np.linalg.norm(truth), 1e-12)
        dirs.append(float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))))
    return pos, dist, dirs


def errors(doc: dict, rig: dict) -> tuple[list[float], list[float]]:
    """Geodesic errors of every camera pair's relative rotation; relative focal errors (pinhole only)."""
    cams = rig["cameras"]
    est = [np.eye(3)] + [np.array(doc["cameras"][c["name"]]["rotation"]) for c in cams[1:]]
    rot = []
    for i in range(len(cams)):
        for k in range(i + 1, len(cams)):
            truth = cams[i]["R"] @ cams[k]["R"].T
            rot.append(float(geodesic_deg(truth, est[i] @ est[k].T)))
    foc = []
    if "reference_focal_px" in doc:
        f_est = [doc["reference_focal_px"]] + [doc["cameras"][c["name"]]["focal_px"] for c in cams[1:]]
        foc = [abs(f / c["f"] - 1) for f, c in zip(f_est, cams)]
    return rot, foc


METHODS = {"default (--image-size)": "pinhole", "--intrinsics (true K)": "intrinsics",
           "refined, no --image-size": "ortho", "--method closed-form": "closed"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rigs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mocap", type=Path, default=MOCAP)
    ap.add_argument("--distance", default="2.5,4.0", help="cameras' distance from the walk's middle, MIN,MAX metres")
    ap.add_argument("--noise-share", default=None,
                    help="Gaussian noise as a share of the walker's image height, MIN,MAX drawn per rig "
                         "(default: 2.5 px)")
    ap.add_argument("--outliers", type=float, default=0.02, help="share of keypoints displaced (by 20-60 px, or as --outlier-share says)")
    ap.add_argument("--outlier-share", default=None,
                    help="outliers' displacement as a share of the walker's image height, MIN,MAX (default: "
                         "20-60 px, which is 0.06-0.17 of the median walker at 2.5-4 m)")
    ap.add_argument("--swaps", type=float, default=0.01, help="share of left/right pairs swapped")
    ap.add_argument("--methods", default=",".join(METHODS.values()),
                    help=f"comma-separated subset of {','.join(METHODS.values())}")
    args = ap.parse_args()
    distance = tuple(float(v) for v in args.distance.split(","))
    share = None if args.noise_share is None else tuple(float(v) for v in args.noise_share.split(","))
    far = None if args.outlier_share is None else tuple(float(v) for v in args.outlier_share.split(","))
    methods = {label: key for label, key in METHODS.items() if key in args.methods.split(",")}
    motion = read_motion(args.mocap)
    stretch = motion.positions[60:300:4]  # 2 s at 30 Hz
    pts = keypoints_3d(stretch)
    hips = (stretch[:, J["left_hip"]] + stretch[:, J["right_hip"]]) / 2
    height = 1.75 / stature_scale(stretch[:, :13], 1.75)  # the mocap walker's stature, m
    rng = np.random.default_rng(args.seed)
    rows = {m: {"rot": [], "foc": [], "pos": [], "dist": [], "dirs": [], "fail": 0, "time": [], "starts": 0,
                "flagged": [], "wrong": 0, "epipolar": 0} for m in methods}
    same_as_mmpose = None
    for r in range(args.rigs):
        rig = random_rig(rng, hips, stretch[:, :13], distance)
        w, h = rig["size"]
        tall = {c["name"]: image_height(stretch[:, :13], c) for c in rig["cameras"]}
        noise = {c: 2.5 if share is None else rng.uniform(*share) * h_c for c, h_c in tall.items()}
        jump = {c: (20.0, 60.0) if far is None else tuple(np.multiply(far, h_c)) for c, h_c in tall.items()}
        dets = {c["name"]: detections(rng, pts, c, noise[c["name"]], args.swaps, args.outliers, jump[c["name"]])
                for c in rig["cameras"]}
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "pose"
            for name, det in dets.items():
                write_openpose(root, name, det)
            write_intrinsics(Path(tmp) / "calib.toml", rig)
            runs = {"pinhole": ("--image-size", f"{w},{h}"), "ortho": (), "closed": ("--method", "closed-form"),
                    "intrinsics": ("--intrinsics", str(Path(tmp) / "calib.toml"))}
            runs = {k: (*v, "--height", f"{height:.4f}") for k, v in runs.items()}
            for label, key in methods.items():
                doc, dt, err = run_cli(Path(tmp), *runs[key])
                rows[label]["time"].append(dt)
                if doc is None:
                    rows[label]["fail"] += 1
                    print(f"rig {r} {label}: failed: {err}", flush=True)
                    continue
                rot, foc = errors(doc, rig)
                if err == "unreliable":  # exit 1: the command itself says the rig is not to be used
                    rows[label]["flagged"].append(float(np.max(rot)))
                    print(f"rig {r} {label}: flagged unreliable (worst pair {np.max(rot):.1f} deg)", flush=True)
                    continue
                rows[label]["wrong"] += bool(np.max(rot) > 10.0)
                pos, dist, dirs = centre_errors(doc, rig) if "reference_focal_px" in doc else ([], [], [])
                rows[label]["rot"] += rot
                rows[label]["foc"] += foc if key != "intrinsics" else []
                rows[label]["pos"] += pos
                rows[label]["dist"] += dist
                rows[label]["dirs"] += dirs
                rows[label]["epipolar"] += doc.get("pinhole_start") == "epipolar"
                rows[label]["starts"] += doc.get("start", "closed form") != "closed form"
                print(f"rig {r} ({w}x{h}) {label}: pairs {np.round(rot, 1).tolist()} focal "
                      f"{np.round(100 * np.array(foc), 1).tolist()} % centres {np.round(pos, 2).tolist()} m "
                      f"dir {np.round(dirs, 1).tolist()} deg start {doc.get('start')!r}/{doc.get('pinhole_start')!r} notes {len(doc.get('notes', []))}  {dt:.1f} s", flush=True)
                if r == 0 and key == "pinhole":
                    mm = Path(tmp) / "mmpose"
                    for name, det in dets.items():
                        write_mmpose(mm, name, det)
                    doc_mm, _, err = run_cli(mm, *runs[key])
                    same_as_mmpose = doc_mm is not None and all(
                        np.allclose(doc_mm["cameras"][n]["rotation"], doc["cameras"][n]["rotation"], atol=1e-6)
                        for n in doc["cameras"])
    print()
    noise_text = "2.5 px" if share is None else f"{100 * share[0]:g}-{100 * share[1]:g} % of the walker's height"
    print(f"CMU 16_15, {args.rigs} rigs x 6 camera pairs, seed {args.seed}; BODY_25 OpenPose folders; cameras "
          f"{distance[0]:g}-{distance[1]:g} m away; noise {noise_text}, {100 * args.outliers:g} % outliers "
          + ("(20-60 px)" if far is None else f"({100 * far[0]:g}-{100 * far[1]:g} % of the walker's height)")
          + f", {100 * args.swaps:g} % left/right swaps")
    print()
    print("| method | median rot. err. (deg) | p90 (deg) | median focal err. | p90 focal | median centre err. (m) "
          "| median distance err. (m) | translation direction median / p90 (deg) | failed "
          "| flagged unreliable (exit 1; their worst pair, median) "
          "| accepted but wrong (worst pair > 10 deg) | other start | epipolar start kept | s / run |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for label, row in rows.items():
        rot, foc, pos, dist, dirs = (np.array(row[k]) for k in ("rot", "foc", "pos", "dist", "dirs"))
        f_med = f"{100 * np.median(foc):.1f} %" if foc.size else "—"
        f_p90 = f"{100 * np.percentile(foc, 90):.1f} %" if foc.size else "—"
        r_med = f"{np.median(rot):.2f}" if rot.size else "—"
        r_p90 = f"{np.percentile(rot, 90):.2f}" if rot.size else "—"
        p_med = f"{np.median(pos):.2f}" if pos.size else "—"
        d_med = f"{np.median(dist):.2f}" if dist.size else "—"
        t_dir = f"{np.median(dirs):.2f} / {np.percentile(dirs, 90):.2f}" if dirs.size else "—"
        flagged = (f"{len(row['flagged'])} ({np.median(row['flagged']):.0f} deg)" if row["flagged"] else "0")
        print(f"| {label} | {r_med} | {r_p90} | {f_med} | {f_p90} | {p_med} | {d_med} | {t_dir} | "
              f"{row['fail']}/{args.rigs} | {flagged} | {row['wrong']} | {row['starts']} | {row['epipolar']} | "
              f"{np.median(row['time']):.1f} |")
    print()
    print(f"MMPose COCO-17 files of rig 0 give the same rotations as its OpenPose folders: {same_as_mmpose}")


if __name__ == "__main__":
    main()
