"""Time of the online estimation path per frame and camera (target: <= 5 ms).

usage: python bench/bench_estimate.py [--cameras 4] [--frames 20] [--windows 20]

The path from silhouettes (full frames, as they arrive) to a window's result:
cropping, registration, cluster and exemplar matching, viewpoint fit, phase
evidence, HMM, joints. One process pinned to one core, the default model.
"""

from __future__ import annotations

import argparse
import time

from _onecore import pin, single_threaded  # noqa: E402

# One core: BLAS must not start threads that then fight over it.
single_threaded()

import numpy as np  # noqa: E402

from estimator.pipeline import estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

TARGET_MS = 5.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--windows", type=int, default=20)
    args = parser.parse_args()
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    seqs = [synthesize(SynthSpec(n_cameras=args.cameras, n_frames=args.frames, seed=s)) for s in range(4)]
    pin()
    estimate_walk(tracks_from_sequence(seqs[0]), model)  # warm-up
    times = []
    for w in range(args.windows):
        seq = seqs[w % len(seqs)]
        t0 = time.perf_counter()
        estimate_walk(tracks_from_sequence(seq), model)
        times.append((time.perf_counter() - t0) * 1000 / (args.cameras * args.frames))
    t = np.array(times)
    print(f"online path, {args.cameras} cameras x {args.frames} frames per window, {args.windows} windows, one core:")
    print(f"  per frame and camera: median {np.median(t):.2f} ms, p90 {np.percentile(t, 90):.2f} ms; "
          f"target <= {TARGET_MS} ms: ratio {np.median(t) / TARGET_MS:.2f} ({'met' if np.median(t) <= TARGET_MS else 'MISSED'})")
    print(f"  per window: median {np.median(t) * args.cameras * args.frames:.0f} ms")


if __name__ == "__main__":
    main()
