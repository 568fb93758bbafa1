"""2D posture by mNBP (Wang–Leow §3) against the model placement, on walks that are not the model's.

Every sequence is synthesised (pyrender silhouettes, ground-truth joints),
estimated by ``estimate_walk`` (Izo–Grimson: viewpoints, phase, the model's
joints placed on each silhouette), then each camera's frames go through
``estimator.mnbp.posture_sequences`` (all its cameras at once) started from that placement. Errors are
per joint, frame and camera, in units of the walker's image height (the
silhouette crop's rows), against the rendered truth.

Sets (2-4 cameras, 15 Hz, cameras 8-12 m away):

- ``cmu``: driven by the two CMU recordings in ../shared/data/mocap (not
  the gait model), bodies drawn with stature 1.5-1.95 m and every proportion
  within +-10 %;
- ``stylised``: the gait model with exaggerated arm swing (x1.8), short
  steps (stride x0.7) and high knees (leg lift x1.3), the same bodies;
- ``model``: the gait model with its usual random style (in distribution).

With ``--rig``, each walk's rig is calibrated as ``posecal estimate`` does
(:func:`estimator.rig.calibrate_rig` on :func:`estimator.mnbp.measure_postures`)
and each camera's rotation to camera 0 is scored against the truth
(geodesic, degrees, every pair (c, 0)).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_mnbp.py [--sequences 6] [--seed 7] [--rig] \
        [--plot docs/img/mnbp_errors.png]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _onecore import single_threaded  # noqa: E402

single_threaded()

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from estimator.gait import GaitStyle  # noqa: E402
from estimator.joints import JOINT_NAMES, MIRROR  # noqa: E402
from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.mnbp import MNBPConfig, measure_postures, posture_sequences  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pipeline import estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.skeleton import BodyShape  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

MOCAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"
SETS = ("cmu", "stylised", "model")


def body(rng: np.random.Generator) -> BodyShape:
    """Stature 1.5-1.95 m, every proportion within +-10 %."""
    u = lambda: float(rng.uniform(0.9, 1.1))  # noqa: E731
    return BodyShape(height=float(rng.uniform(1.5, 1.95)), leg_length=u(), arm_length=u(),
                     trunk_length=u(), shoulder_width=u(), hip_width=u(), girth=float(rng.uniform(0.85, 1.2)))


def items(kind: str, n: int, seed: int) -> list[tuple[SynthSpec, str | None]]:
    rng = np.random.default_rng([seed, SETS.index(kind)])
    out = []
    for i in range(n):
        cams = int(rng.integers(2, 5))
        s = 1000 * seed + 100 * SETS.index(kind) + i
        if kind == "cmu":
            out.append((SynthSpec(n_cameras=cams, n_frames=20, seed=s, shape=body(rng)),
                        ("16_15.bvh", "07_05.amc")[i % 2]))
        elif kind == "stylised":
            out.append((SynthSpec(n_cameras=cams, n_frames=20, seed=s, shape=body(rng),
                                  style=GaitStyle(stride=0.7, leg_lift=1.3, arm_swing=1.8, cadence=1.0)), None))
        else:
            out.append((SynthSpec(n_cameras=cams, n_frames=20, seed=s), None))
    return out


def swapped(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per frame: the left/right-mirrored labelling is nearer the truth than the labelling given."""
    d = np.nanmean(np.linalg.norm(est - truth, axis=-1), axis=-1)
    m = np.nanmean(np.linalg.norm(est[:, list(MIRROR)] - truth, axis=-1), axis=-1)
    return m < d


def evaluate(kind: str, n: int, seed: int, model, config: MNBPConfig, rig: bool = False) -> dict[str, list]:
    rows = {"model": [], "mnbp": [], "swap_model": [], "swap_mnbp": [], "ms": [], "rig": []}
    motions = {}
    for spec, motion_name in tqdm(items(kind, n, seed), desc=kind, leave=False):
        motion = motions.setdefault(motion_name, read_motion(MOCAP / motion_name)) if motion_name else None
        seq = synthesize(spec, motion=motion)
        tracks = tracks_from_sequence(seq)
        est = estimate_walk(tracks, model)
        names = list(est.cameras)
        t0 = time.perf_counter()
        measured, _ = posture_sequences([tracks[n].silhouettes for n in names], [tracks[n].boxes for n in names],
                                        [est.cameras[n].joints2d for n in names], config=config)
        rows["ms"].append((time.perf_counter() - t0) * 1e3 / sum(len(tracks[n].silhouettes) for n in names))
        for cam, joints in zip(names, measured):
            c = est.cameras[cam]
            truth = np.array([f["joints2d"][cam] for f in seq.truth["frames"]])
            height = np.array([np.nan if s is None else s.shape[0] for s in tracks[cam].silhouettes])
            for name, j in (("model", c.joints2d), ("mnbp", joints)):
                rows[name].append(np.linalg.norm(j - truth, axis=-1) / height[:, None])
                rows[f"swap_{name}"].append(swapped(j, truth))
        if rig:
            from estimator.rig import calibrate_rig, rotations_from_viewpoints

            found = calibrate_rig(measure_postures(est, config))
            true = rotations_from_viewpoints([(seq.truth["cameras"][c]["azimuth_deg"],
                                               seq.truth["cameras"][c]["elevation_deg"]) for c in names])
            rows["rig"] += [float(geodesic_deg(r, t)) for r, t in zip(found.rotations[1:], true[1:])]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=6, help="per set")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--config", default="{}", help='MNBPConfig fields as JSON, e.g. \'{"n_iterations": 8}\'')
    parser.add_argument("--sets", default=",".join(SETS))
    parser.add_argument("--rig", action="store_true", help="also calibrate each walk's rig and score its rotations")
    args = parser.parse_args()
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    config = MNBPConfig(**json.loads(args.config))
    print(f"mNBP {config}; load avg {os.getloadavg()[0]:.2f}\n")
    print("| set | frames x cameras | model placement median / p90 | mNBP median / p90 | "
          "L/R swaps model / mNBP | mNBP ms per frame and camera |")
    print("|---|---|---|---|---|---|")
    results = {}
    for kind in args.sets.split(","):
        r = evaluate(kind, args.sequences, args.seed, model, config, rig=args.rig)
        results[kind] = r
        em, ep = np.concatenate(r["model"]), np.concatenate(r["mnbp"])
        sm, sp = np.concatenate(r["swap_model"]), np.concatenate(r["swap_mnbp"])
        print(f"| {kind} | {len(em)} | {np.nanmedian(em):.4f} / {np.nanpercentile(em, 90):.4f} | "
              f"{np.nanmedian(ep):.4f} / {np.nanpercentile(ep, 90):.4f} | {sm.mean():.1%} / {sp.mean():.1%} | "
              f"{np.median(r['ms']):.0f} |")
    if args.rig:
        print("\nRig (default, `calibrate_rig` on the mNBP postures): rotation to camera 0 against the truth, deg\n")
        print("| set | pairs | median | p90 | max |\n|---|---|---|---|---|")
        for kind, r in results.items():
            e = np.array(r["rig"])
            print(f"| {kind} | {len(e)} | {np.median(e):.2f} | {np.percentile(e, 90):.2f} | {e.max():.2f} |")
    print("\nPer joint, median (cmu + stylised):\n")
    print("| joint | model | mNBP |\n|---|---|---|")
    em = np.concatenate([e for k in ("cmu", "stylised") if k in results for e in results[k]["model"]])
    ep = np.concatenate([e for k in ("cmu", "stylised") if k in results for e in results[k]["mnbp"]])
    for j, name in enumerate(JOINT_NAMES):
        print(f"| {name} | {np.nanmedian(em[:, j]):.4f} | {np.nanmedian(ep[:, j]):.4f} |")
    if args.plot:
        plot(args.plot, results)


def plot(path: Path, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4 * len(results), 3.2), sharey=True)
    for ax, (kind, r) in zip(axes, results.items()):
        for name, colour in (("model", "tab:grey"), ("mnbp", "tab:blue")):
            e = np.concatenate(r[name]).ravel()
            e = np.sort(e[np.isfinite(e)])
            ax.plot(e, np.linspace(0, 1, len(e)), color=colour,
                    label=f"{'model placement' if name == 'model' else 'mNBP'} (median {np.median(e):.3f})")
        ax.axvline(0.02, color="k", lw=0.5, ls=":")
        ax.axvline(0.05, color="k", lw=0.5, ls=":")
        ax.set_xlim(0, 0.1)
        ax.set_title(kind)
        ax.set_xlabel("2D joint error / walker height")
        ax.legend(fontsize=7, loc="lower right")
    axes[0].set_ylabel("fraction of joints")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
