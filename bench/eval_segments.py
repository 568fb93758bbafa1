"""Recordings longer than a window: one window for all of it against segments per heading.

usage: python bench/eval_segments.py [--trials 40] [--seed 0] [--model PATH] [--report docs/SEGMENTS.md]

Per trial, on the default appearance model:

- a straight walk (60 frames at 15 Hz, two cameras at random azimuths);
- a turn: 40 frames, then the walker turns by 60-180 degrees (random) and walks
  40 more (``estimator.synth.synthesize_turns``).

Each is estimated as one window (``estimate_walk`` on every frame) and by
``estimator.windows.segment_walk`` (20-frame windows every 10, a change = 3
windows agreeing more than 30 degrees away). Prints the azimuth error per camera
and frame against the truth of the frame's stretch (the viewpoint of the
segment reporting the frame; for one window its single viewpoint), the share of
frames whose phase is within 0.1 cycle, and the number of segments; writes
the table to ``docs/SEGMENTS.md``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from tqdm import tqdm

from estimator.appearance import load_model
from estimator.pipeline import estimate_walk, tracks_from_sequence
from estimator.synth import SynthSpec, synthesize, synthesize_turns
from estimator.viewpoint import azimuth_difference_deg
from estimator.windows import segment_walk


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _phase_hits(phase, truth) -> np.ndarray:
    return np.abs((np.asarray(phase, float) - np.asarray(truth) + 0.5) % 1.0 - 0.5) <= 0.1


def _stretches(seq) -> list[tuple[int, int, dict]]:
    truth = seq.truth
    if "segments" in truth:
        return [(s["first_index"], s["last_index"], s["cameras"]) for s in truth["segments"]]
    return [(0, seq.n_frames - 1, truth["cameras"])]


def evaluate(seq, model) -> dict[str, dict]:
    """Azimuth errors per (stretch, camera) and phase hits per frame, for both methods."""
    tracks = tracks_from_sequence(seq)
    truth_phase = [f["phase"] for f in seq.truth["frames"]]
    whole = estimate_walk(tracks, model)
    walk = segment_walk(tracks, model)
    result = walk.to_result()
    out = {"one window": {"az": [], "phase": _phase_hits(whole.phase, truth_phase), "segments": 1},
           "segments": {"az": [], "phase": _phase_hits([f["phase"] for f in result["frames"]], truth_phase),
                        "segments": len(walk.segments)}}
    for first, last, cams in _stretches(seq):
        for cam, t in cams.items():
            err = abs(azimuth_difference_deg(whole.cameras[cam].viewpoint.azimuth_deg, t["azimuth_deg"]))
            out["one window"]["az"] += [err] * (last + 1 - first)
            for f in result["frames"][first:last + 1]:  # each frame judged by the segment reporting it
                seg = result["segments"][f["segment"]]
                out["segments"]["az"].append(abs(azimuth_difference_deg(seg["cameras"][cam]["azimuth_deg"],
                                                                        t["azimuth_deg"])))
    return out


REPORT = """# Recordings longer than a window: segments per heading

*Written by `OPENBLAS_NUM_THREADS=1 python bench/eval_segments.py --trials {trials} --seed {seed}`
({minutes:.1f} min, default appearance model).*

A batch job or `posecal estimate` on a recording longer than one window
estimates it window by window (20 frames every 10) and cuts it where three
consecutive windows agree on viewpoints more than 30 deg from the current ones
(`estimator.windows.segment_walk`); each segment is then estimated as one
window. Per trial: a straight walk of 60 frames, and a walk of 40 frames, a
turn of 60-180 deg (random side), 40 more frames (two cameras at random
azimuths, 15 Hz, 640x480). Errors per camera and frame against the truth of the
frame's stretch; "one window" is the whole recording as one window (what jobs
did before).

{table}

A straight walk stays one segment, so nothing changes there. Across a turn one
window cannot hold both viewpoints, and its phase falls to a coin toss; the
segments follow the turn. Their p90 comes from the frames near the turn that
the segment before it still reports (a cut lands on a window boundary, every
10 frames) and from segments of a single window.
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", help="appearance model (default: the cached default model)")
    ap.add_argument("--report", default=os.path.join(ROOT, "docs", "SEGMENTS.md"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.model:
        model = load_model(args.model)
    else:
        from service.cli.model import get_default_model

        model = get_default_model()
    rng = np.random.default_rng(args.seed)
    stats = {(kind, m): {"az": [], "phase": [], "segments": []} for kind in ("straight", "turn")
             for m in ("one window", "segments")}
    for k in tqdm(range(args.trials), desc="trials"):
        az = rng.uniform(0.0, 360.0, 2)
        turn = rng.uniform(60.0, 180.0) * rng.choice([-1, 1])
        spec = dict(n_cameras=2, elevations=(5.0, 15.0))
        cases = {"straight": synthesize(SynthSpec(n_frames=60, seed=1000 + k, azimuths=tuple(az), **spec)),
                 "turn": synthesize_turns([SynthSpec(n_frames=40, seed=2000 + k, azimuths=tuple(az), **spec),
                                           SynthSpec(n_frames=40, seed=3000 + k,
                                                     azimuths=tuple((az + turn) % 360.0), **spec)])}
        for kind, seq in cases.items():
            for m, r in evaluate(seq, model).items():
                s = stats[(kind, m)]
                s["az"] += list(r["az"]); s["phase"].append(r["phase"]); s["segments"].append(r["segments"])
    lines = ["| walk | method | azimuth error median (deg) | p90 | phase within 0.1 cycle | segments (median, max) |",
             "|---|---|---|---|---|---|"]
    for (kind, m), s in stats.items():
        az, ph, ns = np.array(s["az"]), np.concatenate(s["phase"]), np.array(s["segments"])
        lines.append(f"| {kind} | {m} | {np.median(az):.1f} | {np.percentile(az, 90):.1f} | {ph.mean():.3f} | "
                     f"{np.median(ns):.0f}, {ns.max()} |")
    table = "\n".join(lines)
    print(table)
    with open(args.report, "w") as fh:
        fh.write(REPORT.format(trials=args.trials, seed=args.seed, table=table,
                               minutes=(time.perf_counter() - t0) / 60))
    print(f"wrote {args.report}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
