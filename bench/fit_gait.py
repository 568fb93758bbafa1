"""Fit the gait curves to the CMU walks and write ``estimator/data/gait_cmu.json``.

usage: python bench/fit_gait.py [--mocap DIR] [--out PATH] [--plot PNG]

Prints per-curve fit residuals (degrees / fraction of hip height) and plots the
fitted curves over the recorded samples.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from estimator.gait import _SIDED, fit_gait, motion_angles, motion_phase
from estimator.mocap import read_motion

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mocap", default=os.path.join(ROOT, "..", "shared", "data", "mocap"))
    parser.add_argument("--out", default=os.path.join(ROOT, "estimator", "data", "gait_cmu.json"))
    parser.add_argument("--plot", default=os.path.join(ROOT, "docs", "img", "gait_curves.png"))
    args = parser.parse_args()
    motions = [read_motion(os.path.join(args.mocap, f)) for f in ("16_15.amc", "07_05.amc")]
    model = fit_gait(motions)
    with open(args.out, "w") as fh:
        json.dump(model.to_json(), fh, indent=1)
    print(f"wrote {args.out}: {model.harmonics} harmonics, cadence {model.cadence:.3f} cycles/s, sources {model.sources}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["thigh", "shank", "foot", "upper_arm", "forearm", "pelvis_yaw", "pelvis_obliquity", "thorax_yaw", "lean", "bounce", "sway", "thigh_lat"]
    fig, axes = plt.subplots(3, 4, figsize=(16, 10))
    grid = np.linspace(0, 1, 200)
    print(f"{'curve':18s} {'rms residual':>14s}  unit")
    for ax, name in zip(axes.ravel(), names):
        unit, k = ("fraction of hip height", 1.0) if name in ("bounce", "sway") else ("deg", np.degrees(1.0))
        resid = []
        for m in motions:
            ph, ang = motion_phase(m), getattr(motion_angles(m), name)
            if name in _SIDED:
                ax.plot(ph, ang[:, 1] * k, ".", ms=1, alpha=0.4, label=f"{m.source} right")
                ax.plot((ph - 0.5) % 1, ang[:, 0] * k, ".", ms=1, alpha=0.4, label=f"{m.source} left (-0.5)")
                resid.append(ang[:, 1] - model.curve(name, ph))
                resid.append(ang[:, 0] - model.curve(name, ph - 0.5))
            else:
                ax.plot(ph, ang * k, ".", ms=1, alpha=0.4, label=m.source)
                resid.append(ang - model.curve(name, ph))
        r = np.concatenate(resid)
        rms = np.sqrt(np.median(r**2)) * k
        print(f"{name:18s} {rms:14.3f}  {unit} (root median square)")
        ax.plot(grid, model.curve(name, grid) * k, "k-", lw=2, label="fit")
        ax.set_title(f"{name} ({unit})")
        ax.set_xlabel("phase (0 = right heel strike)")
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(args.plot, dpi=80)
    print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
