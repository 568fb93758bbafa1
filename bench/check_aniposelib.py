"""aniposelib itself reads a calibration posecal exported, and triangulates the Pose2Sim demo's keypoints with it.

aniposelib (0.8.0) needs opencv-contrib-python, numba and jax, which do not
sit beside posecal's headless OpenCV, so this runs in a separate environment
and imports nothing of posecal's::

    .venv/bin/posecal selfcal tests/fixtures/pose2sim_balancing --image-size 1088,1920 --height 1.72 \\
        --export-calibration /tmp/Calib.toml --out /tmp/rig.json
    python3 -m venv /tmp/anienv
    /tmp/anienv/bin/pip install --no-deps aniposelib
    /tmp/anienv/bin/pip install numpy scipy toml tqdm numba jax pandas opencv-contrib-python-headless
    /tmp/anienv/bin/python bench/check_aniposelib.py /tmp/Calib.toml

Prints the cameras as ``CameraGroup.load`` reads them, their relative
rotations' errors against the fixture's Qualisys calibration, and the
reprojection error of ``CameraGroup.triangulate`` on every BODY_25B keypoint
(confidence >= 0.3; the person with the widest keypoints in each file) through
the given calibration; ``--reference`` runs the same through the Qualisys
calibration (its cameras renamed as the keypoint folders) for comparison.
"""

from __future__ import annotations

import argparse
import glob
import json
import re
import tempfile
import tomllib
from pathlib import Path

import numpy as np
from aniposelib.cameras import CameraGroup
from scipy.spatial.transform import Rotation

FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "pose2sim_balancing"
QUALISYS = FIXTURE / "calibration" / "Calib_qualisys.toml"


def keypoints(names: list[str]) -> np.ndarray:
    """(C, F * 25, 2) keypoints of every frame any camera saw, NaN where missing."""
    files = glob.glob(str(FIXTURE / "pose" / "*_json" / "*.json"))
    frames = sorted({int(re.findall(r"\d+", Path(p).stem)[-1]) for p in files})
    pts = np.full((len(names), len(frames), 25, 2), np.nan)
    for c, name in enumerate(names):
        for t, f in enumerate(frames):
            path = FIXTURE / "pose" / f"{name}_json" / f"{name}.{f:04d}.json"
            if not path.exists():
                continue
            people = [np.array(p["pose_keypoints_2d"][:75]).reshape(25, 3) for p in json.loads(path.read_text())["people"]]
            if people:
                kp = max(people, key=lambda k: np.ptp(k[k[:, 2] > 0, 0]) if (k[:, 2] > 0).sum() > 1 else 0.0)
                ok = kp[:, 2] >= 0.3
                pts[c, t, ok] = kp[ok, :2]
    return pts.reshape(len(names), -1, 2)


def check(path: Path, label: str) -> None:
    group = CameraGroup.load(str(path))
    names = group.get_names()
    print(f"{label}: cameras {names}, sizes {[c.get_size() for c in group.cameras]}")
    truth = [t for t in tomllib.loads(QUALISYS.read_text()).values() if isinstance(t, dict) and "rotation" in t]
    rt = [Rotation.from_rotvec(np.ravel(t["rotation"])).as_matrix() for t in truth]
    re_ = [Rotation.from_rotvec(np.ravel(c.get_rotation())).as_matrix() for c in group.cameras]
    errs = [np.degrees((Rotation.from_matrix(rt[i] @ rt[k].T) * Rotation.from_matrix(re_[i] @ re_[k].T).inv()).magnitude())
            for i in range(len(rt)) for k in range(i + 1, len(rt))]
    print(f"  camera pairs against Qualisys: {np.round(errs, 2).tolist()} deg (median {np.median(errs):.2f})")
    pts = keypoints(names)
    p3 = group.triangulate(pts, progress=False)
    err = np.linalg.norm(group.reprojection_error(p3, pts, mean=False), axis=-1)
    print(f"  triangulated keypoints reproject: median {np.nanmedian(err):.1f} px, p90 {np.nanpercentile(err, 90):.1f} px "
          f"({np.isfinite(err).sum()} observations)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibration", type=Path, help="a calibration TOML posecal exported for the fixture")
    ap.add_argument("--reference", action="store_true", help="the same through the Qualisys calibration")
    args = ap.parse_args()
    check(args.calibration, "posecal's calibration")
    if args.reference:
        names = iter(f"cam{k:02d}" for k in range(1, 100))
        text = re.sub(r'^name = ".*"$', lambda m: f'name = "{next(names)}"', QUALISYS.read_text(), flags=re.M)
        with tempfile.TemporaryDirectory() as tmp:
            renamed = Path(tmp) / "qualisys.toml"
            renamed.write_text(text)
            check(renamed, "Qualisys calibration (cameras named as the keypoint folders)")

if __name__ == "__main__":
    main()
