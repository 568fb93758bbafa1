"""How precise is a Test 2 median, and what do the walker priors buy? (docs/SELFCAL.md)

Usage::

    .venv/bin/python bench/selfcal_priors.py [--trials 200] [--level 5] [--jobs 2]

Test 2's geometry (camera 0 at azimuth 45, elevation 10; relative rotation
(-10, -60, 20) deg, s = 1; uniform noise U(-a, a), ``a`` = level x body
height) on both CMU walks: 07_05, on which the priors were designed, and
16_15, the Test 2 walk. Each trial draws its own 30-frame window and noise
from ``seed + trial`` (not Test 2's draws), and every method sees the same
tracks. Prints per walk and method the median geodesic error with its
bootstrap standard error, the interquartile range and the median error about
each Euler axis (the paper's E_rx, E_ry, E_rz).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from multiprocessing import Pool  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from selfcal_test2 import MOCAP, draw_trial, fixed_pair  # noqa: E402

from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.joints import N_JOINTS  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.selfcal import SYMMETRIC_RATIOS, self_calibrate  # noqa: E402
from estimator.viewpoint import azimuth_difference_deg  # noqa: E402

SYMMETRIC = tuple(((a,), (b,), 1.0, 0.02) for a, b, _ in SYMMETRIC_RATIOS)
METHODS = {
    "MAP BA": {"refine": True},
    "upright x0.7": {"refine": True, "upright": 0.7},
    "upright": {"refine": True, "upright": True},
    "upright x1.5": {"refine": True, "upright": 1.5},
    "upright + left = right (2 %)": {"refine": True, "upright": True,
                                     "body_proportions": SYMMETRIC},
}


def trial(args: tuple) -> dict[str, np.ndarray]:
    """One window and noise draw; per method (E_rx, E_ry, E_rz, geodesic) in degrees."""
    seed, level, x_all = args
    _, rots, _, _, y = draw_trial(x_all, np.random.default_rng(seed), level, fixed_pair(45))
    y = y[:2]
    rel = rots[1] @ rots[0].T
    euler = Rotation.from_matrix(rel).as_euler("xyz", degrees=True)
    out = {}
    for name, kw in METHODS.items():
        res = self_calibrate(y, **kw)
        if not res:
            out[name] = np.full(4, np.nan)
            continue
        axes = np.abs(azimuth_difference_deg(res.euler_xyz_deg[1], euler))
        out[name] = np.r_[axes, geodesic_deg(res.rotations[1], rel)]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=200)
    p.add_argument("--level", type=float, default=5.0, help="noise, percent of body height")
    p.add_argument("--seed", type=int, default=5000)
    p.add_argument("--jobs", type=int, default=2)
    args = p.parse_args(argv)
    t0 = time.time()
    print(f"noise {args.level:g} %, {args.trials} trials per walk; median geodesic [bootstrap se] "
          "(q25, q75); median E_rx / E_ry / E_rz (deg)")
    for walk in ("07_05", "16_15"):
        x_all = read_motion(MOCAP / f"{walk}.amc").person_frame()[20:, :N_JOINTS]
        jobs = [(args.seed + k, args.level / 100.0, x_all) for k in range(args.trials)]
        with Pool(args.jobs) as pool:
            rows = pool.map(trial, jobs)
        boot = np.random.default_rng(0).integers(0, args.trials, (1000, args.trials))
        print(f"\n{walk}" + (" (priors designed here)" if walk == "07_05" else " (Test 2 walk)"))
        for name in METHODS:
            e = np.array([r[name] for r in rows])
            med = np.nanmedian(e, axis=0)
            se = np.nanmedian(e[boot, 3], axis=1).std()
            q25, q75 = np.nanpercentile(e[:, 3], [25, 75])
            print(f"  {name:30s} {med[3]:5.2f} [{se:.2f}] ({q25:.2f}, {q75:.2f});"
                  f"  {med[0]:.2f} / {med[1]:.2f} / {med[2]:.2f}")
    print(f"\n{time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
