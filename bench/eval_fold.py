"""Ahead or behind where the walker's size hardly changes: far, high cameras on oblique walks.

The feet's path (``MotionCue.fall``, docs/ROBUSTNESS.md) was added after four
windows of vtest.avi's real walkers came out on the wrong side of the
ahead/behind fold. This checks it on walks it was not chosen on: synthetic
walkers (the model's gait and the CMU walks, random bodies) seen by one camera
15-25 m away, 15-35 deg above them, at azimuths 20-70 deg from the walking
direction, on either side of it, ahead or behind (oblique: the fold matters,
the size changes little), each window of 20 frames estimated on its own, with
the feet's path and without it (``EstimateConfig.fall_min_elevation_deg``
infinite).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_fold.py [--walks 60] [--seed 5]
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from estimator.mocap import read_motion
from estimator.pipeline import EstimateConfig, estimate_walk, tracks_from_sequence
from estimator.skeleton import BodyShape
from estimator.synth import SynthSpec, synthesize
from estimator.viewpoint import azimuth_difference_deg
from estimator.windows import window_tracks

MOCAP = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "mocap")


def walks(n: int, seed: int):
    """``n`` one-camera walks of 40 frames: (sequence, true azimuth)."""
    rng = np.random.default_rng(seed)
    motions = sorted(f for f in os.listdir(MOCAP) if f.endswith(".amc")) if os.path.isdir(MOCAP) else []
    for k in range(n):
        # 20-70 deg off the walking axis (ahead, 0, or behind, 180), on either side of it
        az = float((rng.choice([0.0, 180.0]) + rng.choice([-1.0, 1.0]) * rng.uniform(20, 70)) % 360.0)
        shape = BodyShape(height=float(rng.uniform(1.5, 1.95)), leg_length=float(rng.uniform(0.9, 1.1)),
                          arm_length=float(rng.uniform(0.9, 1.1)), shoulder_width=float(rng.uniform(0.9, 1.1)))
        spec = SynthSpec(n_cameras=1, n_frames=40, seed=seed * 1000 + k, azimuths=(az,),
                         elevations=(float(rng.uniform(15, 35)),), distance=float(rng.uniform(15, 25)), shape=shape)
        motion = read_motion(os.path.join(MOCAP, motions[k % len(motions)])) if motions and k % 2 else None
        yield synthesize(spec, motion=motion), az


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--walks", type=int, default=60)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    configs = {"with the feet's path": EstimateConfig(), "without": EstimateConfig(fall_min_elevation_deg=np.inf)}
    errors: dict[str, list[float]] = {label: [] for label in configs}
    folds: dict[str, list[bool]] = {label: [] for label in configs}
    for seq, az in walks(args.walks, args.seed):
        full = tracks_from_sequence(seq)
        for a in (0, 20):
            tracks = window_tracks(full, a, a + 20)
            for label, config in configs.items():
                try:
                    vp = estimate_walk(tracks, model, config=config).cameras[seq.cameras[0]].viewpoint
                except ValueError:
                    continue
                err = abs(float(azimuth_difference_deg(vp.azimuth_deg, az)))
                errors[label].append(err)
                folds[label].append(abs(float(azimuth_difference_deg(vp.azimuth_deg, 180.0 - az))) < err)
    print(f"{args.walks} one-camera walks (model's gait and CMU, random bodies), cameras 15-25 m away, "
          f"15-35 deg above, 20-70 deg off the walking axis; windows of 20 frames:")
    for label, e in errors.items():
        e, f = np.array(e), np.array(folds[label])
        print(f"  {label:<22} {len(e)} windows: azimuth median {np.median(e):.1f}, p90 {np.percentile(e, 90):.1f} deg;"
              f" nearer the mirror 180 - azimuth (wrong side of the fold) {int(f.sum())} ({100 * f.mean():.1f} %)")


if __name__ == "__main__":
    main()
