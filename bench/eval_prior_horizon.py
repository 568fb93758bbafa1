"""Live priors (§7.1) against the true silhouettes, by how far ahead of their window they are.

The live service renders priors for frames it has not seen (:func:`estimator.prior.predict_priors`):
``skip`` frames after the window (the frames captured while it works) and on. How good
a prior is therefore depends on its horizon, and the horizon on the machine's speed
(lag 0.5 s at 15 fps: priors 8-27 frames ahead). Walks that are not the model's
(the two CMU walks in turn, random bodies; every third walk the gait model), 2
cameras, 58 frames at 15 Hz; windows of 20 frames every 4, each predicting the next
30; exact silhouettes (the prediction alone is measured, not segmentation).

Per horizon: the IoU of the prior (>= 128) with the true silhouette, and the share of
the true silhouette it covers (what the agent's check, ``capture.segment``, asks of a
prior on its own foreground).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_prior_horizon.py [--walks 12]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from capture.scene import iou  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pipeline import CameraTrack, estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.prior import FEEDBACK, predict_priors  # noqa: E402
from estimator.render import Renderer  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

MOCAP = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "mocap"
FRAMES, WINDOW, AHEAD, EVERY = 58, 20, 30, 4  # 58 frames: the shorter CMU walk at 15 Hz
SHOWN = (1, 5, 10, 15, 20, 25, 30)


def evaluate(n_walks: int, model) -> dict[int, dict[str, list[float]]]:
    """Per horizon (frames after the window's last), the IoU and coverage of each prior."""
    motions = [read_motion(MOCAP / "16_15.bvh"), read_motion(MOCAP / "07_05.amc"), None]
    renderer = Renderer(FEEDBACK.body)
    out: dict[int, dict[str, list[float]]] = {}
    for seed in range(n_walks):
        spec = SynthSpec(n_cameras=2, n_frames=FRAMES, seed=seed)
        motion = motions[seed % 3]
        seq = synthesize(spec) if motion is None else synthesize(spec, motion=motion)
        tracks = tracks_from_sequence(seq)
        for start in range(0, FRAMES - WINDOW - AHEAD + 1, EVERY):
            window = {c: CameraTrack(t.silhouettes[start:start + WINDOW], t.boxes[start:start + WINDOW],
                                     full_frame=True) for c, t in tracks.items()}
            est = estimate_walk(window, model)
            priors = predict_priors(est, window, tuple(spec.image_size), AHEAD, renderer=renderer,
                                    config=FEEDBACK, first_index=start)
            for cam, ps in priors.items():
                for p in ps:
                    mask, truth = p.full_mask() >= 128, seq.silhouettes[cam][p.frame_index] > 0
                    row = out.setdefault(p.frame_index - start - WINDOW + 1, {"iou": [], "covered": []})
                    row["iou"].append(iou(mask, truth))
                    row["covered"].append(np.count_nonzero(mask & truth) / max(1, np.count_nonzero(truth)))
        print(f"walk {seed + 1}/{n_walks}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--walks", type=int, default=12)
    args = ap.parse_args()
    from service.cli.model import get_default_model

    rows = evaluate(args.walks, get_default_model(progress=True))
    print(f"\n{args.walks} walks, priors per horizon (median / p10):")
    print("| frames ahead | priors | IoU with the truth | share of the truth covered |")
    print("|---|---|---|---|")
    for h in SHOWN:
        if h in rows:
            i, c = np.array(rows[h]["iou"]), np.array(rows[h]["covered"])
            print(f"| {h} | {i.size} | {np.median(i):.3f} / {np.percentile(i, 10):.3f} "
                  f"| {np.median(c):.3f} / {np.percentile(c, 10):.3f} |")


if __name__ == "__main__":
    main()
