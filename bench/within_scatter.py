"""Within-scatter criterion (Izo–Grimson §4.2, eqs. 6–7) over a k-means sweep.

usage: python bench/within_scatter.py [--source auto|body|stick] [--ks 10,20,...] [--out PNG]

Runs k-means (one initialisation per k, seeded) on the registered joint vectors
that the model clusters, prints tr[S_W] for each k and the knee chosen by
``estimator.appearance.choose_n_clusters``, and plots the curve.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(__file__))

from threadpoolctl import threadpool_limits  # noqa: E402

from _appearance_data import training_examples  # noqa: E402
from estimator.appearance import choose_n_clusters, within_scatter_curve  # noqa: E402

DEFAULT_KS = (5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 125, 150, 175, 200, 250, 300, 400, 500)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="auto")
    parser.add_argument("--ks", default=",".join(map(str, DEFAULT_KS)))
    parser.add_argument("--out", default="docs/img/appearance_within_scatter.png")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    ks = [int(k) for k in args.ks.split(",")]
    ex, src = training_examples(source=args.source)
    t0 = time.perf_counter()
    with threadpool_limits(1):
        tr = within_scatter_curve(ex, ks, rng=args.seed)
    dt = time.perf_counter() - t0
    knee = choose_n_clusters(ks, tr)
    # Over the paper's own range (up to 100), for comparison.
    sub = [i for i, k in enumerate(ks) if k <= 100]
    knee100 = choose_n_clusters([ks[i] for i in sub], tr[sub]) if len(sub) >= 3 else None
    print(f"examples: {len(ex)} from {src}; k-means sweep of {len(ks)} values in {dt:.1f} s (one core)")
    print("     k   tr[S_W] (body heights^2)   per example")
    for k, t in zip(ks, tr):
        print(f"  {k:4d}   {t:12.3f}               {t / len(ex):.5f}")
    print(f"knee of the curve over k in [{ks[0]}, {ks[-1]}]: N = {knee}")
    if knee100 is not None:
        print(f"knee over k in [{ks[0]}, 100] (the paper's range): N = {knee100}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    ax.plot(ks, tr, "o-", ms=3)
    ax.axvline(knee, color="C1", ls="--", label=f"knee N = {knee}")
    ax.axvline(100, color="C2", ls=":", label="paper N = 100")
    ax.set_xlabel("k (k-means clusters)")
    ax.set_ylabel("tr[S_W] (eq. 7), body heights$^2$")
    ax.set_title(f"Within-scatter, {len(ex)} examples")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    fig.savefig(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
