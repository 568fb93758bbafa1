"""Time of ``posecal selfcal FOLDER --image-size W,H`` (the default path on keypoints), one core.

Usage::

    .venv/bin/python bench/bench_selfcal_keypoints.py [--frames 100] [--rigs 5] [--seed 0]

For each of ``--rigs`` random 4-camera rigs of the keypoint evaluation
(``bench/eval_keypoints_import.py``: CMU walk 16_15, cameras 2.5-4 m away,
detector-like BODY_25 keypoints written as OpenPose folders), ``--frames``
frames at 30 Hz. Times the command in-process (reading the folders, the
calibration and the JSON, after imports) and per stage: the closed form, the
epipolar start, the pinhole bundle adjustment from each start; and the
scaled-orthographic bundle adjustment the default skips. The issue's target:
4 cameras x 100 frames in <= 2 s on one core.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _onecore import pin, single_threaded  # noqa: E402

single_threaded()

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import eval_keypoints_import as ev  # noqa: E402
from estimator.epipolar import epipolar_start  # noqa: E402
from estimator.perspective import perspective_refine  # noqa: E402
from estimator.selfcal import RIGID_LINKS, self_calibrate  # noqa: E402
from service.cli import main as cli_main  # noqa: E402
from service.cli.selfcal import _calibration_frames  # noqa: E402
from service.keypoints_io import read_keypoints  # noqa: E402


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--rigs", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    core = pin()
    motion = ev.read_motion(ev.MOCAP)
    stretch = motion.positions[60:60 + 2 * args.frames:2]  # 30 Hz
    pts = ev.keypoints_3d(stretch)
    hips = (stretch[:, ev.J["left_hip"]] + stretch[:, ev.J["right_hip"]]) / 2
    rng = np.random.default_rng(args.seed)
    rows = {k: [] for k in ("command", "closed form", "epipolar start", "pinhole from closed form",
                            "pinhole from epipolar", "scaled-orthographic bundle adjustment (skipped)")}
    for r in range(args.rigs):
        rig = ev.random_rig(rng, hips, stretch[:, :13])
        w, h = rig["size"]
        dets = {c["name"]: ev.detections(rng, pts, c) for c in rig["cameras"]}
        with tempfile.TemporaryDirectory() as tmp:
            for name, det in dets.items():
                ev.write_openpose(Path(tmp) / "pose", name, det)
            out = Path(tmp) / "r.json"
            with contextlib.redirect_stderr(io.StringIO()):
                code, dt = timed(cli_main, ["selfcal", tmp, "--image-size", f"{w},{h}", "--out", str(out)])
            rows["command"].append(dt)
            kp = read_keypoints([Path(tmp)], image_size=(w, h))
        used = _calibration_frames(kp.tracks.shape[1], 60)  # the command's --max-frames 60 for keypoints
        y = kp.tracks[:, used]
        sizes = np.tile([w, h], (4, 1)).astype(float)
        cf, dt = timed(self_calibrate, y, refine=False, temporal_prior=True)
        rows["closed form"].append(dt)
        start, dt = timed(epipolar_start, y, sizes)
        rows["epipolar start"].append(dt)
        if cf:
            rows["pinhole from closed form"].append(
                timed(perspective_refine, y, sizes, cf.rotations, cf.scales, list(RIGID_LINKS))[1])
        if start is not None:
            rows["pinhole from epipolar"].append(
                timed(perspective_refine, y, sizes, None, None, list(RIGID_LINKS), initial=start)[1])
        if r < 2:  # slow: two rigs are enough to show what the default saves
            rows["scaled-orthographic bundle adjustment (skipped)"].append(
                timed(self_calibrate, y, refine=True, upright=True)[1])
        print(f"rig {r} ({w}x{h}): exit {code}, command {rows['command'][-1]:.2f} s", flush=True)
    print()
    print(f"4 cameras x {args.frames} frames (calibrated on {len(used)}), {args.rigs} rigs, one core (CPU {core})")
    print()
    print("| stage | median s | max s |")
    print("|---|---|---|")
    for k, v in rows.items():
        if v:
            print(f"| {k} | {np.median(v):.2f} | {np.max(v):.2f} |")


if __name__ == "__main__":
    main()
