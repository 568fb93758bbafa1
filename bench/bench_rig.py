"""Time of the rig from silhouettes (:func:`estimator.rig.calibrate_rig`), one core.

Usage::

    .venv/bin/python bench/bench_rig.py [--repeats 3]

On the walk of ``posecal synth --cameras 3 --frames 30 --seed 4 --motion
../shared/data/mocap/16_15.bvh`` (CMU motion, not the model's; pyrender
silhouettes): the mNBP postures it rests on (:func:`estimator.mnbp.measure_postures`),
then the rig (two scaled-orthographic bundle adjustments, the fusion with the
viewpoints, the pinhole adjustment, the epipolar tangents), without the
tangents, without the pinhole step, and
the second round of Wang–Leow's loop (``RigConfig(rounds=2)``). Median of
``--repeats`` runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _onecore import pin, single_threaded  # noqa: E402

single_threaded()

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from estimator.mnbp import measure_postures  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.pipeline import estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.rig import RigConfig, calibrate_rig  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

MOTION = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap" / "16_15.bvh"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    core = pin()
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=4), motion=read_motion(MOTION))
    est = estimate_walk(tracks_from_sequence(seq), model)
    t0 = time.perf_counter()
    measured = measure_postures(est)
    postures = time.perf_counter() - t0
    rows = {}
    for name, config in (("rig (default)", RigConfig()), ("rig without the epipolar tangents", RigConfig(tangents=None)),
                         ("rig without the pinhole step", RigConfig(perspective=False)),
                         ("rig, 2 rounds", RigConfig(rounds=2))):
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            rig = calibrate_rig(measured, config)
            times.append(time.perf_counter() - t0)
        rows[name] = (float(np.median(times)), rig.source)
    print(f"\n3 cameras x 30 frames, one core (CPU {core}); mNBP postures {postures:.2f} s\n")
    print("| stage | median s | source |\n|---|---|---|")
    for name, (t, source) in rows.items():
        print(f"| {name} | {t:.2f} | {source} |")


if __name__ == "__main__":
    main()
