"""The rig from silhouettes alone: camera-pair rotations three ways, against the truth.

Each synthetic walk (CMU motion, bodies 1.5-1.95 m with proportions +-10 %,
2-4 cameras, 30 frames at 15 Hz) is estimated by ``estimate_walk``; then the
relative rotation ``R_c R_0^T`` of every camera to camera 0 comes from

- ``viewpoints``: the Izo–Grimson azimuth and elevation of each camera;
- ``selfcal(model)``: Wang–Leow §4 self-calibration (``self_calibrate``,
  ``refine=True, upright=True``) on the model's joints placed on each silhouette;
- ``selfcal(mNBP)``: the same on the 2D postures measured by mNBP
  (``estimator.mnbp.measure_postures``): the first round of Wang–Leow's loop.

Geodesic error in degrees over all camera pairs (c, 0).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_rig_from_silhouettes.py [--sequences 12]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _onecore import single_threaded  # noqa: E402

single_threaded()

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from eval_mnbp import MOCAP, body  # noqa: E402
from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.camera import world_to_camera_rotation  # noqa: E402
from estimator.mnbp import measure_postures  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pipeline import estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.selfcal import self_calibrate  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402


def relative(rotations: list[np.ndarray]) -> list[np.ndarray]:
    return [r @ rotations[0].T for r in rotations[1:]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=12)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    motions = [read_motion(MOCAP / "16_15.bvh"), read_motion(MOCAP / "07_05.amc")]
    rng = np.random.default_rng(args.seed)
    errors: dict[str, list[float]] = {"viewpoints": [], "selfcal(model)": [], "selfcal(mNBP)": []}
    failed = {k: 0 for k in errors}
    for i in tqdm(range(args.sequences), desc="sequences"):
        spec = SynthSpec(n_cameras=int(rng.integers(2, 5)), n_frames=30, seed=1000 * args.seed + i, shape=body(rng))
        seq = synthesize(spec, motion=motions[i % 2])
        est = estimate_walk(tracks_from_sequence(seq), model)
        measured = measure_postures(est)
        cams = seq.cameras
        truth = relative([world_to_camera_rotation(seq.truth["cameras"][c]["azimuth_deg"],
                                                   seq.truth["cameras"][c]["elevation_deg"]) for c in cams])
        found = {"viewpoints": relative([world_to_camera_rotation(est.cameras[c].viewpoint.azimuth_deg,
                                                                  est.cameras[c].viewpoint.elevation_deg)
                                         for c in cams])}
        for name, joints in (("selfcal(model)", [measured.cameras[c].model_joints2d for c in cams]),
                             ("selfcal(mNBP)", [measured.cameras[c].joints2d for c in cams])):
            cal = self_calibrate(np.stack(joints), refine=True, upright=True)
            if cal:
                found[name] = list(cal.rotations[1:])
            else:
                failed[name] += 1
        for name, rots in found.items():
            errors[name] += [float(geodesic_deg(r, t)) for r, t in zip(rots, truth)]
    print(f"\n{args.sequences} walks, {len(errors['viewpoints'])} camera pairs\n")
    print("| rotations from | median | p90 | max | failed walks |\n|---|---|---|---|---|")
    for name, e in errors.items():
        print(f"| {name} | {np.median(e):.2f} | {np.percentile(e, 90):.2f} | {np.max(e):.2f} | {failed[name]} |")


if __name__ == "__main__":
    main()
