"""A camera that sees the walker on only a few frames of a window: how far off its viewpoint is.

A live window holds 20 frames, but a camera's agent may have sent the
walker on only some of them: its first frames came late, its track was on
someone else for the rest (`window.other_person`), or the walker left its
view. Every walk of ``bench/eval_mnbp.py``'s sets (2-4 cameras, 15 Hz, not the
model's walk for ``cmu``; 20 frames) is estimated once per camera and count
``n``: that camera keeps its first ``n`` frames, the others all of theirs.
Its azimuth error against the truth is scored on exact silhouettes and on
silhouettes with every damage of ``estimator.damage`` at once (``all``), with
two configurations:

- ``cue``: the camera's own motion cue decides ahead/behind however few its
  frames (``settle_few_frames=0``), and no camera is set aside
  (``min_frames=0``): posecal before session 56;
- ``phase``: under ``EstimateConfig.settle_few_frames`` frames the other
  cameras' phase decides, as for a contested cue (``min_frames=0``, so every
  count is still scored).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_few_frames.py [--seed 7] [--sequences 6] \
        [--plot docs/img/few_frames.png]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _onecore import single_threaded  # noqa: E402

single_threaded()

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from eval_mnbp import MOCAP, items  # noqa: E402
from estimator.damage import damage_sequence  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pipeline import CameraTrack, EstimateConfig, estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.synth import synthesize  # noqa: E402

CONFIGS = {"cue": EstimateConfig(settle_few_frames=0, min_frames=0), "phase": EstimateConfig(min_frames=0)}
CONDITIONS = ("exact", "all")


def first_frames(track: CameraTrack, n: int) -> CameraTrack:
    """``track`` with only its first ``n`` frames."""
    kept = np.arange(len(track.silhouettes)) < n
    return dataclasses.replace(track, silhouettes=[s if k else None for k, s in zip(kept, track.silhouettes)],
                               boxes=np.where(kept[:, None], track.boxes, np.nan))


def evaluate(seed: int, sequences: int, counts: list[int], model) -> list[dict]:
    """One row per set, walk, condition, camera, frame count and configuration."""
    rows = []
    work = [(kind, k, spec, name) for kind in ("cmu", "model") for k, (spec, name) in enumerate(items(kind, sequences,
                                                                                                   seed))]
    motions: dict[str, object] = {}
    for kind, k, spec, name in tqdm(work, desc=f"seed {seed}", file=sys.stderr):
        motion = motions.setdefault(name, read_motion(MOCAP / name)) if name else None
        seq = synthesize(spec, motion=motion)
        for condition in CONDITIONS:
            s = seq if condition == "exact" else dataclasses.replace(
                seq, silhouettes=damage_sequence(seq.silhouettes, "all", seed=k, truth=seq.truth))
            tracks = tracks_from_sequence(s)
            for cam in tracks:
                truth = seq.truth["cameras"][cam]["azimuth_deg"]
                for n in counts:
                    window = {**tracks, cam: first_frames(tracks[cam], n)}
                    for config_name, config in CONFIGS.items():
                        az = estimate_walk(window, model, config=config).cameras[cam].viewpoint.azimuth_deg
                        rows.append({"set": kind, "condition": condition, "frames": n, "config": config_name,
                                     "error": float(abs((az - truth + 180.0) % 360.0 - 180.0))})
    return rows


def table(rows: list[dict], counts: list[int]) -> str:
    """Markdown: per frame count, the share over 30 deg and the p90, cue -> phase, exact and damaged."""
    out = ["| frames of the camera's walker | exact: over 30 deg, cue -> phase | exact: p90 (deg) | "
           "`all`: over 30 deg | `all`: p90 |", "|---|---|---|---|---|"]
    for n in counts:
        cells = []
        for condition in CONDITIONS:
            e = {c: np.array([r["error"] for r in rows if r["frames"] == n and r["condition"] == condition
                              and r["config"] == c]) for c in CONFIGS}
            cells += [f"{np.mean(e['cue'] > 30):.0%} -> {np.mean(e['phase'] > 30):.0%}",
                      f"{np.percentile(e['cue'], 90):.0f} -> {np.percentile(e['phase'], 90):.0f}"]
        out.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def plot(path: Path, rows: list[dict], counts: list[int]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2), sharey=True)
    for ax, condition in zip(axes, CONDITIONS):
        for config, colour in (("cue", "tab:grey"), ("phase", "tab:blue")):
            share = [np.mean([r["error"] > 30 for r in rows if r["frames"] == n and r["condition"] == condition
                              and r["config"] == config]) for n in counts]
            ax.plot(counts, share, "o-", color=colour, label=f"ahead/behind by the {config}")
        ax.set_title("exact silhouettes" if condition == "exact" else "every damage at once (all)")
        ax.set_xlabel("frames of the camera's walker (of 20)")
        ax.legend(fontsize=7)
    axes[0].set_ylabel("viewpoints over 30 deg off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--sequences", type=int, default=6, help="walks per set (cmu, model)")
    parser.add_argument("--frames", default="2,3,4,5,6,8,10,20", help="the camera's frame counts")
    parser.add_argument("--plot", type=Path, default=None)
    args = parser.parse_args()
    from service.cli.model import get_default_model

    counts = [int(n) for n in args.frames.split(",")]
    rows = evaluate(args.seed, args.sequences, counts, get_default_model(progress=True))
    cameras = sum(r["frames"] == counts[0] and r["condition"] == "exact" and r["config"] == "cue" for r in rows)
    print(f"seed {args.seed}: {cameras} cameras of {2 * args.sequences} walks (CMU motions and the model's walk), "
          "20 frames; each camera cut to its first n frames in turn\n")
    print(table(rows, counts))
    if args.plot:
        plot(args.plot, rows, counts)


if __name__ == "__main__":
    main()
