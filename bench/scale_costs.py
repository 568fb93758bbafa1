"""CPU cost of each live stage per camera, and how many cameras a core carries (docs/SCALING.md).

usage: python bench/scale_costs.py [--cameras 4,8,16] [--windows 6] [--json PATH]

One process pinned to one core (BLAS and OpenCV one thread), the default
model, synthetic 640x480 walks. CPU time (``time.process_time``), so that a
busy machine slows the run but not the figures much. Measured:

- **wire**: a silhouette message encoded (agent side) and decoded and
  validated (service side, the receiver's ``capture.wire.decode``);
- **estimate**: ``estimate_walk`` on live windows of 20 frames every 10, as
  the service runs them (a ``MatchCache`` carries each frame's matching to
  the next window), per window and camera, for each rig size;
- **feedback**: ``predict_priors`` for 20 frames ahead, per window and camera;
- **live rig**: the mNBP postures of 2 frames per window
  (``RigAccumulator.add``), per window and camera (the calibration itself,
  every 3rd window, is left out).

Then, per stage, the CPU one camera needs per second at 15 and 30 fps (a
window every 10 frames) and the cameras one core carries.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from _onecore import pin, single_threaded  # noqa: E402

single_threaded()

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from capture.wire import Box, SilhouetteMessage, decode, encode  # noqa: E402
from estimator.matchcache import MatchCache  # noqa: E402
from estimator.pipeline import crop_to_box, estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402
from estimator.windows import window_tracks  # noqa: E402

LENGTH, HOP = 20, 10


def cpu(fn, repeat: int = 1) -> float:
    """CPU seconds of one call of ``fn`` (the least of ``repeat``)."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def walk(cameras: int, frames: int, seed: int = 5):
    az = list(np.linspace(0, 360, cameras, endpoint=False) + 45.0)
    el = [10.0 + 5 * (k % 3) for k in range(cameras)]
    return synthesize(SynthSpec(n_cameras=cameras, n_frames=frames, seed=seed, azimuths=az, elevations=el))


def wire_ms(seq) -> tuple[float, float]:
    """Encode and decode of one silhouette message, ms (mean over the walk's crops)."""
    msgs = []
    for cam in seq.cameras:
        for k, s in enumerate(seq.silhouettes[cam]):
            c = crop_to_box(s)
            if c is not None:
                msgs.append(SilhouetteMessage(rig="r", camera=cam, frame_index=k, capture_ns=k + 1, box=Box(*map(int, c[1])),
                                              image_size=tuple(seq.image_size), epoch_ns=1, seq=k,
                                              mask=np.ascontiguousarray(c[0]), sync="index", publish_ns=k))
    payloads = []
    enc = cpu(lambda: payloads.extend(encode(m) for m in msgs))
    dec = cpu(lambda: [decode(p) for p in payloads[:len(msgs)]])
    return 1000 * enc / len(msgs), 1000 * dec / len(msgs)


def live_windows(seq, model, windows: int) -> tuple[float, list]:
    """Mean CPU ms of ``estimate_walk`` per live window (cached across windows), and the estimates."""
    full = tracks_from_sequence(seq)
    cache = MatchCache()
    times, ests = [], []
    for k in range(windows + 1):
        tracks = window_tracks(full, k * HOP, k * HOP + LENGTH)
        t0 = time.process_time()
        ests.append(estimate_walk(tracks, model, cache=cache))
        if k:  # the first window has nothing cached: the service's steady state is the rest
            times.append(time.process_time() - t0)
    return 1000 * float(np.median(times)), ests


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", default="4,8,16")
    ap.add_argument("--windows", type=int, default=6)
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    from estimator.prior import FEEDBACK, predict_priors
    from estimator.render import Renderer
    from estimator.rig import RigAccumulator, RigConfig
    from service.cli.model import get_default_model

    cv2.setNumThreads(1)
    model = get_default_model(progress=True)
    sizes = [int(c) for c in args.cameras.split(",")]
    frames = LENGTH + HOP * args.windows
    pin()
    fig: dict = {"estimate_ms_per_window": {}}
    seq4 = walk(4, frames)
    enc, dec = wire_ms(seq4)
    fig["wire_ms"] = {"encode": round(enc, 3), "decode": round(dec, 3)}
    for n in sizes:
        ms, _ = live_windows(seq4 if n == 4 else walk(n, frames), model, args.windows)
        fig["estimate_ms_per_window"][n] = round(ms, 1)
    # Feedback and posture on the 4-camera windows, per camera.
    full = tracks_from_sequence(seq4)
    est = estimate_walk(window_tracks(full, 0, LENGTH), model)
    renderer = Renderer(FEEDBACK.body)
    size = tuple(seq4.image_size)
    predict_priors(est, est.tracks, size, LENGTH, renderer=renderer, config=FEEDBACK)  # warm-up
    fb = cpu(lambda: predict_priors(est, est.tracks, size, LENGTH, renderer=renderer, config=FEEDBACK), repeat=3)
    fig["feedback_ms_per_window_camera"] = round(1000 * fb / 4, 1)
    # The live rig's work per window: mNBP postures of 2 of its frames (RigAccumulator.add).
    rig_cpu = []
    for k in range(3):
        acc = RigAccumulator(RigConfig(), frames_per_window=2)
        w = estimate_walk(window_tracks(full, k * HOP, k * HOP + LENGTH), model)
        rig_cpu.append(cpu(lambda: acc.add(w, k * HOP)))
    fig["live_rig_ms_per_window_camera"] = round(1000 * float(np.median(rig_cpu)) / 4, 1)
    fig["mnbp_ms_per_frame_camera"] = round(fig["live_rig_ms_per_window_camera"] / 2, 1)

    print(f"CPU on one core, 640x480 synthetic walks, live windows of {LENGTH} frames every {HOP}:")
    print(f"  wire: encode {enc:.3f} ms, decode + validate {dec:.3f} ms per silhouette message")
    for n, ms in fig["estimate_ms_per_window"].items():
        print(f"  estimate_walk, {n:2d} cameras: {ms:6.1f} ms per window ({ms / n:.2f} ms per camera, "
              f"{ms / (n * LENGTH):.2f} ms per frame and camera)")
    print(f"  feedback priors ({LENGTH} ahead): {fig['feedback_ms_per_window_camera']:.1f} ms per window and camera")
    print(f"  live rig postures (mNBP, 2 frames per window): {fig['live_rig_ms_per_window_camera']:.1f} ms per "
          f"window and camera ({fig['mnbp_ms_per_frame_camera']:.1f} ms per frame)")
    largest = max(fig["estimate_ms_per_window"])
    est_cam = fig["estimate_ms_per_window"][largest] / largest
    stages = {"decode (service main process)": lambda fps: dec * fps,
              f"estimate (as at {largest} cameras)": lambda fps: est_cam * fps / HOP,
              "feedback priors": lambda fps: fig["feedback_ms_per_window_camera"] * fps / HOP,
              "live rig postures": lambda fps: fig["live_rig_ms_per_window_camera"] * fps / HOP}
    fig["per_camera_second_ms"], fig["cameras_per_core"] = {}, {}
    print("\nper camera: CPU ms per second of video, and cameras one core carries")
    print(f"  {'stage':<34} {'15 fps':>8} {'per core':>9} {'30 fps':>8} {'per core':>9}")
    for name, f in stages.items():
        a, b = f(15.0), f(30.0)
        fig["per_camera_second_ms"][name] = {"15": round(a, 1), "30": round(b, 1)}
        fig["cameras_per_core"][name] = {"15": round(1000 / a, 1), "30": round(1000 / b, 1)}
        print(f"  {name:<34} {a:8.1f} {1000 / a:9.1f} {b:8.1f} {1000 / b:9.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(fig, indent=1))


if __name__ == "__main__":
    main()
