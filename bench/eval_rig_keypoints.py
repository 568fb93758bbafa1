"""The rig from a pose detector's keypoints beside the silhouettes: three ways, against the truth.

What ``posecal estimate --keypoints``, REST jobs with keypoints and the live rig
fed by agents that send keypoints do: :func:`estimator.rig.calibrate_rig` with
``keypoints`` and :meth:`RigConfig.for_keypoints` (the viewpoints estimated from
the silhouettes start and check it). Each synthetic walk (CMU motion, bodies
1.5-1.95 m with proportions +-10 %, 2-4 cameras 4-15 m away, 30 frames at
15 Hz) is estimated by ``estimate_walk``; its renders' joints get a detector's
errors (:func:`estimator.damage.detector_keypoints`: Gaussian noise of
``--noise-share`` of the walker's image height, 2 % of the joints displaced by
10-20 % of it, 5 % missed). Geodesic error of each camera's rotation to camera 0,
in degrees, over all pairs (c, 0):

- ``viewpoints``: the Izo–Grimson azimuth and elevation of each camera;
- ``keypoints alone``: what ``posecal selfcal`` does with the same keypoints and
  the image size (closed form, else the refined scaled-orthographic
  adjustment, then :func:`estimator.epipolar.refine_from_starts` with the
  upright priors; no silhouettes);
- ``calibrate_rig, before session 26``: ``RigConfig.for_keypoints`` as it was
  (no epipolar start, no upright priors, the 45 deg check against the viewpoints);
- ``calibrate_rig (default)``: as it is.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_rig_keypoints.py [--sequences 12] [--seed 11] \
        [--noise-share 0.02]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_mnbp import MOCAP, body  # noqa: E402
from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.damage import detector_keypoints  # noqa: E402
from estimator.epipolar import refine_from_starts  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.perspective import KEYPOINT_REWEIGHT, KEYPOINT_SETTINGS, PerspectiveConfig  # noqa: E402
from estimator.pipeline import estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.rig import RigConfig, calibrate_rig, rotations_from_viewpoints, viewpoint_rotations  # noqa: E402
from estimator.selfcal import RIGID_LINKS, self_calibrate  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

BEFORE = RigConfig.for_keypoints(pinhole=PerspectiveConfig(reweight=KEYPOINT_REWEIGHT), pinhole_epipolar_start=False,
                                 max_disagreement_deg=45.0)


def keypoints_alone(kp: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """The rotations ``posecal selfcal --image-size W,H`` finds from the keypoints alone."""
    cal = self_calibrate(kp, refine=False, temporal_prior=True) or self_calibrate(kp, refine=True, upright=True)
    sizes = np.tile(np.array(image_size, float), (len(kp), 1))
    pin, _ = refine_from_starts(kp, sizes, cal.rotations, cal.scales, list(RIGID_LINKS),
                                config=PerspectiveConfig(**KEYPOINT_SETTINGS))
    return pin.rotations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=12)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--noise-share", type=float, default=0.02,
                        help="the detector's Gaussian noise, share of the walker's image height (default 0.02)")
    args = parser.parse_args()
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    motions = [read_motion(MOCAP / "16_15.bvh"), read_motion(MOCAP / "07_05.amc")]
    rng = np.random.default_rng(args.seed)
    ways = ("viewpoints", "keypoints alone", "calibrate_rig, before session 26", "calibrate_rig (default)")
    errors: dict[str, list[float]] = {w: [] for w in ways}
    by_cameras: dict[int, dict[str, list[float]]] = {}
    for i in tqdm(range(args.sequences), desc="walks", file=sys.stderr):
        spec = SynthSpec(n_cameras=int(rng.integers(2, 5)), n_frames=30, seed=1000 * args.seed + i,
                         shape=body(rng), distance=float(rng.uniform(4.0, 15.0)))
        seq = synthesize(spec, motion=motions[i % 2])
        est = estimate_walk(tracks_from_sequence(seq), model)
        cams = seq.cameras
        truth = rotations_from_viewpoints([(seq.truth["cameras"][c]["azimuth_deg"],
                                            seq.truth["cameras"][c]["elevation_deg"]) for c in cams])
        exact = np.stack([[f["joints2d"][c] for f in seq.truth["frames"]] for c in cams]).astype(float)
        kp = detector_keypoints(exact, np.random.default_rng(spec.seed), noise_share=args.noise_share)
        found = {"viewpoints": viewpoint_rotations(est), "keypoints alone": keypoints_alone(kp, seq.image_size),
                 "calibrate_rig, before session 26": calibrate_rig(est, BEFORE, keypoints=kp).rotations,
                 "calibrate_rig (default)": calibrate_rig(est, RigConfig.for_keypoints(), keypoints=kp).rotations}
        for way, rots in found.items():
            e = [float(geodesic_deg(r, t)) for r, t in zip(rots[1:], truth[1:])]
            errors[way] += e
            by_cameras.setdefault(len(cams), {w: [] for w in ways})[way] += e
    print(f"\n{args.sequences} walks (seed {args.seed}), {len(errors['viewpoints'])} camera pairs, detector noise "
          f"{args.noise_share:.0%} of the walker's height, 2 % gross, 5 % missed\n")
    print("| rotations from | median | p90 | max | " + " | ".join(f"{n} cameras: median / max"
                                                             for n in sorted(by_cameras)) + " |")
    print("|---|---|---|---|" + "---|" * len(by_cameras))
    for way, e in errors.items():
        e = np.asarray(e)
        per = [np.asarray(by_cameras[n][way]) for n in sorted(by_cameras)]
        print(f"| {way} | {np.median(e):.2f} | {np.percentile(e, 90):.2f} | {e.max():.2f} | "
              + " | ".join(f"{np.median(p):.2f} / {p.max():.2f}" for p in per) + " |")


if __name__ == "__main__":
    main()
