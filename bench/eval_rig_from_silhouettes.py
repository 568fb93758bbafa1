"""The rig from silhouettes alone: camera-pair rotations three ways, against the truth.

Each synthetic walk (CMU motion, bodies 1.5-1.95 m with proportions +-10 %,
2-4 cameras, 30 frames at 15 Hz) is estimated by ``estimate_walk``; then the
relative rotation ``R_c R_0^T`` of every camera to camera 0 comes from

- ``viewpoints``: the Izo–Grimson azimuth and elevation of each camera;
- ``selfcal(model)``: Wang–Leow §4 self-calibration (``self_calibrate``,
  ``refine=True, upright=True``) on the model's joints placed on each silhouette;
- ``selfcal(mNBP)``: the same on the 2D postures measured by mNBP
  (``estimator.mnbp.measure_postures``): the first round of Wang–Leow's loop;
- ``rig (default)``: :func:`estimator.rig.calibrate_rig` on the mNBP postures
  (what ``posecal estimate`` reports): the scaled-orthographic bundle
  adjustment from two starts, fused with the viewpoints, then pinhole cameras,
  then the cameras refined on the silhouettes' epipolar tangents
  (:mod:`estimator.frontier`; ``rig.epipolar_tangents`` in the result);
- ``rig, 2 rounds``: the same with a second round of Wang–Leow's loop (§5:
  3D mNBP over all views with the pinhole cameras, a short 2D correction
  per view, the pinhole adjustment again; ``RigConfig(rounds=2)``);
- ``true 2D joints``: the self-calibration, and the pinhole adjustment after
  it, on the renders' exact joints: what the camera model alone allows;
- ``rig from keypoints``: :func:`estimator.rig.calibrate_rig` on a pose
  detector's keypoints in place of the mNBP postures
  (``RigConfig.for_keypoints()``, what ``posecal estimate --keypoints`` does):
  the renders' joints with :func:`estimator.damage.detector_keypoints`'s
  errors (1 % of the walker's height of noise, 2 % gross, 5 % missed).

Geodesic error in degrees over all camera pairs (c, 0); per walk, how much
worse than the viewpoints' rig the default is (its worst pair). The default
rig's 3D posture against the truth: per frame after a similarity alignment
(Procrustes with scale), mean over the 13 joints, divided by the true
stature; the model's posture (``joints3d`` of the gait model at the decoded
phase) the same way. Segment lengths relative to stature against the truth's.
The 2D joints per frame and camera against the renders' (divided by the
walker's image height, as ``bench/eval_mnbp.py``): the model placed on the
silhouette, each view's mNBP alone, and what the result reports
(:func:`estimator.rig.attach_rig`: the rig's 3D posture projected into each
camera).

``--damage KIND`` (a kind of :mod:`estimator.damage`: ``salt``, ``blobs``,
``holes``, ``cut_limb``, ``shadow``, ``second_person``, kinds joined by ``+``,
or ``all``) damages every camera's silhouettes as ``bench/eval_damage.py``
does before anything else runs (the same walks and cameras as without it):
the whole path (clean-up, viewpoints, mNBP, the rig) then works on them. The
rows on the renders' exact joints are the same with or without damage.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_rig_from_silhouettes.py [--sequences 12] [--damage all] \
        [--plot docs/img/rig_errors.png]
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
from estimator.gait import GaitStyle  # noqa: E402
from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.damage import damage_sequence, detector_keypoints, parse_damage  # noqa: E402
from estimator.mnbp import measure_postures  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pipeline import estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.sequence import Sequence  # noqa: E402
from estimator.perspective import perspective_refine  # noqa: E402
from estimator.rig import (RigConfig, aligned_error, attach_rig, calibrate_rig,  # noqa: E402
                           rotations_from_viewpoints, segment_lengths, similarity_aligned, viewpoint_rotations)
from estimator.selfcal import RIGID_LINKS, self_calibrate  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402


STYLISED = GaitStyle(stride=0.7, leg_lift=1.3, arm_swing=1.8, cadence=1.0)  # as bench/eval_mnbp.py


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=12)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--gait", choices=("cmu", "stylised"), default="cmu",
                        help="the CMU walks (default) or the model's gait stylised (arm swing x1.8, "
                             "short steps, high knees), on random bodies either way")
    parser.add_argument("--frames", type=int, default=30, help="frames per walk (15 Hz)")
    parser.add_argument("--damage", help="damage every silhouette first (estimator.damage kinds, e.g. all)")
    parser.add_argument("--plot", type=Path, help="write a PNG: the rotation and 2D error distributions, and the "
                                                  "first walk's person posture over the truth")
    args = parser.parse_args()
    if args.damage:
        parse_damage(args.damage)  # an unknown kind stops here, before the model loads
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    motions = [read_motion(MOCAP / "16_15.bvh"), read_motion(MOCAP / "07_05.amc")]
    rng = np.random.default_rng(args.seed)
    errors: dict[str, list[float]] = {"viewpoints": [], "selfcal(model)": [], "selfcal(mNBP)": [],
                                      "rig (default)": [], "rig, 2 rounds": [], "true 2D joints: selfcal": [],
                                      "true 2D joints: + pinhole": [], "rig from keypoints": []}
    failed = {k: 0 for k in errors}
    worse, e3d, e3d_two, e3d_model, seg_err, sources = [], [], [], [], [], []
    e2d: dict[str, list[np.ndarray]] = {"model placement": [], "mNBP, each view alone": [],
                                        "reported (default rig)": [], "reported (2 rounds)": []}
    lost = 0
    overlay = None  # the first walk's middle frame: (person posture aligned to the truth, the truth)
    for i in tqdm(range(args.sequences), desc="sequences"):
        spec = SynthSpec(n_cameras=int(rng.integers(2, 5)), n_frames=args.frames, seed=1000 * args.seed + i,
                         shape=body(rng), style=STYLISED if args.gait == "stylised" else None)
        seq = synthesize(spec, motion=motions[i % 2] if args.gait == "cmu" else None)
        if args.damage:
            seq = Sequence(seq.fps, seq.cameras, seq.image_size,
                           damage_sequence(seq.silhouettes, args.damage, seed=spec.seed, truth=seq.truth), seq.truth)
        try:
            est = estimate_walk(tracks_from_sequence(seq), model)
        except ValueError:  # nothing left of the walker in some camera: the walk fails as a whole
            lost += 1
            continue
        measured = measure_postures(est)
        cams = seq.cameras
        truth = list(rotations_from_viewpoints([(seq.truth["cameras"][c]["azimuth_deg"],
                                                 seq.truth["cameras"][c]["elevation_deg"]) for c in cams])[1:])
        found = {"viewpoints": list(viewpoint_rotations(est)[1:])}
        for name, joints in (("selfcal(model)", [measured.cameras[c].model_joints2d for c in cams]),
                             ("selfcal(mNBP)", [measured.cameras[c].joints2d for c in cams])):
            cal = self_calibrate(np.stack(joints), refine=True, upright=True)
            if cal:
                found[name] = list(cal.rotations[1:])
            else:
                failed[name] += 1
        exact = np.stack([[f["joints2d"][c] for f in seq.truth["frames"]] for c in cams]).astype(float)
        cal = self_calibrate(exact, refine=True, upright=True)
        found["true 2D joints: selfcal"] = list(cal.rotations[1:])
        found["true 2D joints: + pinhole"] = list(perspective_refine(
            exact, np.tile(seq.image_size, (len(cams), 1)), cal.rotations, cal.scales, list(RIGID_LINKS)).rotations[1:])
        found["rig from keypoints"] = list(calibrate_rig(est, RigConfig.for_keypoints(), keypoints=detector_keypoints(
            exact, np.random.default_rng(spec.seed))).rotations[1:])
        rig = calibrate_rig(measured)
        sources.append(rig.source)
        found["rig (default)"] = list(rig.rotations[1:])
        two = calibrate_rig(measured, RigConfig(rounds=2))
        found["rig, 2 rounds"] = list(two.rotations[1:])
        pair = {}
        for name, rots in found.items():
            pair[name] = [float(geodesic_deg(r, t)) for r, t in zip(rots, truth)]
            errors[name] += pair[name]
        worse.append(max(pair["rig (default)"]) - max(pair["viewpoints"]))
        stature = seq.truth["body"]["height"]
        true3d = np.array([f["joints3d"] for f in seq.truth["frames"]])
        if rig.joints3d is not None:
            e3d += list(aligned_error(rig.joints3d, true3d) / stature)
            if overlay is None:
                mid = len(true3d) // 2
                overlay = (similarity_aligned(rig.joints3d[mid:mid + 1], true3d[mid:mid + 1])[0], true3d[mid], i)
            true_len = {k: np.median(v) / stature for k, v in segment_lengths(true3d).items()}
            seg_err += [abs(rig.segments_m[k] / rig.height_m - true_len[k]) / true_len[k] for k in true_len]
        if two.joints3d is not None:
            e3d_two += list(aligned_error(two.joints3d, true3d) / stature)
        e3d_model += list(aligned_error(est.joints3d, true3d) / stature)
        for name, result in (("reported (default rig)", attach_rig(measured, rig)),
                             ("reported (2 rounds)", attach_rig(measured, two))):
            for cam in cams:
                true2d = np.array([f["joints2d"][cam] for f in seq.truth["frames"]], float)
                height = np.array([np.nan if s is None else s.shape[0] for s in est.tracks[cam].silhouettes])
                pairs = [(name, result.cameras[cam].joints2d)]
                if name.endswith("default rig)"):
                    pairs += [("model placement", measured.cameras[cam].model_joints2d),
                              ("mNBP, each view alone", measured.cameras[cam].joints2d)]
                for key, j in pairs:
                    e2d[key].append((np.linalg.norm(j - true2d, axis=-1) / height[:, None]).ravel())
    damaged = f", silhouettes damaged by {args.damage}" if args.damage else ""
    print(f"\n{args.sequences} walks of {args.frames} frames{damaged}, {len(errors['viewpoints'])} camera pairs"
          f"{f'; {lost} walks not estimated at all' if lost else ''}\n")
    print("| rotations from | median | p90 | max | failed walks |\n|---|---|---|---|---|")
    for name, e in errors.items():
        print(f"| {name} | {np.median(e):.2f} | {np.percentile(e, 90):.2f} | {np.max(e):.2f} | {failed[name]} |")
    worse = np.array(worse)
    print(f"\ndefault rig from self-calibration on {sources.count('self-calibration')} of {len(sources)} walks; "
          f"worst pair worse than the viewpoints' by > 2 deg on {int((worse > 2).sum())} walks "
          f"(max {worse.max():+.1f} deg)")
    for name, e in (("person (default rig)", e3d), ("person (2 rounds)", e3d_two), ("model walk", e3d_model)):
        e = np.array(e, float)
        e = e[np.isfinite(e)]
        if e.size:
            print(f"3D posture error / stature, {name}: median {np.median(e):.4f}, p90 {np.percentile(e, 90):.4f} "
                  f"({e.size} frames)")
    for name, e in e2d.items():
        e = np.concatenate(e) if e else np.array([])
        e = e[np.isfinite(e)]
        if e.size:
            print(f"2D joint error / walker image height, {name}: median {np.median(e):.4f}, "
                  f"p90 {np.percentile(e, 90):.4f} ({e.size} joints)")
    if args.plot:
        plot(args.plot, errors, e2d, overlay, args)
    if seg_err:
        print(f"segment lengths relative to stature, error: median {100 * np.median(seg_err):.1f} %, "
              f"p90 {100 * np.percentile(seg_err, 90):.1f} %")


def plot(path: Path, rotations: dict[str, list[float]], e2d: dict[str, list[np.ndarray]], overlay, args) -> None:
    """Rotation errors and 2D joint errors as cumulative distributions; one frame's person
    posture (aligned) over the truth, seen from the side and from the front."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from estimator.joints import BONES

    fig, ax = plt.subplots(1, 4, figsize=(17, 4), gridspec_kw={"width_ratios": [1.3, 1.3, 0.7, 0.7]})
    for name in ("viewpoints", "selfcal(mNBP)", "rig (default)", "rig, 2 rounds"):
        e = np.sort(rotations[name])
        ax[0].plot(e, np.arange(1, e.size + 1) / e.size, label=f"{name} (median {np.median(e):.1f})")
    ax[0].set(xlabel="camera-pair rotation error (deg)", ylabel="fraction of pairs", xlim=(0, 30))
    for name, parts in e2d.items():
        e = np.concatenate(parts) if parts else np.array([])
        e = np.sort(e[np.isfinite(e)])
        if e.size:
            ax[1].plot(e, np.arange(1, e.size + 1) / e.size, label=f"{name} (median {np.median(e):.3f})")
    ax[1].set(xlabel="2D joint error / walker height", xlim=(0, 0.1))
    for a, x in ((ax[0], (3, 6)), (ax[1], (0.02, 0.05))):
        for v in x:
            a.axvline(v, color="k", lw=0.5, ls=":")
        a.legend(fontsize=7, loc="lower right")
    if overlay is not None:
        est, true, walk = overlay
        for a, (k, name) in zip(ax[2:], ((0, "side (x forward)"), (1, "front (y left)"))):
            for pts, style in ((true, "k-"), (est, "C3-")):
                for i, j in BONES:
                    a.plot(pts[[i, j], k], pts[[i, j], 2], style, lw=1.5)
            a.set(title=f"walk {walk}, {name}", aspect="equal", xticks=[], yticks=[])
        ax[2].plot([], [], "k-", label="truth")
        ax[2].plot([], [], "C3-", label="person (rig), aligned")
        ax[2].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.02))
    title = f"{args.gait} walks, seed {args.seed}" + (f", damage {args.damage}" if args.damage else "")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    print(f"plot: {path}")


if __name__ == "__main__":
    main()
