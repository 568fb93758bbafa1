"""How well does the best-matching cluster tell viewpoint and phase? (Izo–Grimson §5)

usage: python bench/eval_appearance.py [--source auto|body|stick] [--n 1000] [--seed 7]
                                      [--clusters 100] [--size 64,48]
                                      [--sweep-sizes 32x24,48x36,64x48,96x72]
                                      [--sweep-clusters 30,70,100,200] [--out PNG]

Fresh silhouettes (random body shape and gait style, off-grid phase and
viewpoint, camera distance and focal length: seeds other than the model's) are
matched against every cluster mean (eq. 8); the best cluster's mean viewpoint
and mean phase are compared with the truth. Errors are printed as percentiles
and plotted as distributions, raw and folded over the silhouette's twin
(phase + 1/2, azimuth 180 - az, elevation -el): under orthographic projection
and a left/right symmetric gait that twin casts the same silhouette, so no silhouette distance can tell them apart (§3 step 4 resolves
it with the direction of motion in the image).

An "oracle" row assigns each fresh example to the GMM component of its true
registered joints (what clustering alone permits), for comparison.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(__file__))

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from _appearance_data import fresh_examples, model_for  # noqa: E402
from estimator import _cluster  # noqa: E402
from estimator.appearance import joint_features  # noqa: E402

PCTS = (10, 25, 50, 75, 90)


def _ang(a, b, period):
    return np.abs((a - b + period / 2) % period - period / 2)


def errors(model, clusters, ex):
    """Per-example errors (azimuth deg, elevation deg, phase cycles), raw and folded."""
    vp = model.cluster_viewpoint[clusters]
    ph = model.cluster_phase[clusters]
    az_raw = _ang(vp[:, 0], ex.azimuth_deg, 360.0)
    el_raw = np.abs(vp[:, 1] - ex.elevation_deg)
    ph_raw = _ang(ph, ex.phase, 1.0)
    az_tw = _ang(vp[:, 0], 180.0 - ex.azimuth_deg, 360.0)
    el_tw = np.abs(vp[:, 1] + ex.elevation_deg)
    ph_tw = _ang(ph, ex.phase + 0.5, 1.0)
    # Fold: the hypothesis (truth or twin) that is closer in azimuth and phase.
    use_twin = az_tw / 180.0 + ph_tw / 0.5 < az_raw / 180.0 + ph_raw / 0.5
    return {
        "raw": (az_raw, el_raw, ph_raw),
        "folded": (np.where(use_twin, az_tw, az_raw), np.where(use_twin, el_tw, el_raw),
                   np.where(use_twin, ph_tw, ph_raw)),
        "twin_fraction": float(use_twin.mean()),
    }


def oracle_clusters(model, ex):
    reg, tf = model.register(ex.silhouettes)
    x = joint_features(ex.joints2d, tf, size=model.size, height_fraction=model.params.height_fraction)
    centre = x.mean(0)
    sym = _cluster._Sym(x.shape[1])
    xc = x - centre
    logp = _cluster._log_resp(xc, sym.outer(xc), model.gmm_weights, model.gmm_means - centre,
                              model.gmm_covariances, sym)
    return logp.argmax(1)


def _row(name, e):
    az, el, ph = e
    q = lambda v: "/".join(f"{p:.0f}" if v is not ph else f"{p:.3f}" for p in np.percentile(v, PCTS))  # noqa: E731
    return f"  {name:<22} az {q(az):<22} el {q(el):<18} phase {q(ph)}"


def time_match(model, sils, n=300):
    with threadpool_limits(1):
        for i in range(20):
            model.match(sils[i : i + 1])
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(n):
            model.match(sils[i % len(sils) : i % len(sils) + 1])
        return (time.perf_counter() - t0) / n * 1e3, (time.process_time() - c0) / n * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="auto")
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--clusters", type=int, default=100)
    parser.add_argument("--size", default="64,48")
    parser.add_argument("--sweep-sizes", default="")
    parser.add_argument("--sweep-clusters", default="")
    parser.add_argument("--out", default="docs/img/appearance_eval.png")
    parser.add_argument("--means-out", default="", help="also plot cluster means to this PNG")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split(","))
    fresh_src = "stick" if args.source == "stick" else "body"
    t0 = time.perf_counter()
    ex = fresh_examples(args.n, seed=args.seed, source=fresh_src)
    print(f"fresh examples: {len(ex)} ({fresh_src}, seed {args.seed}, {len(np.unique(ex.style))} bodies) "
          f"in {time.perf_counter() - t0:.1f} s")
    model, train, src = model_for(source=args.source, n_clusters=args.clusters, size=size)
    print(f"model: {model.n_clusters} clusters, canvas {model.size[0]}x{model.size[1]}, "
          f"{model.n_examples} examples from {src}")
    best, _ = model.match(ex.silhouettes)
    e = errors(model, best, ex)
    eo = errors(model, oracle_clusters(model, ex), ex)
    print(f"errors, percentiles {PCTS} (azimuth and elevation in degrees, phase in cycles; "
          f"1/20 cycle = one of the paper's phases):")
    print(_row("matched, raw", e["raw"]))
    print(_row("matched, folded", e["folded"]))
    print(_row("oracle GMM, raw", eo["raw"]))
    print(_row("oracle GMM, folded", eo["folded"]))
    print(f"  folded onto the twin: {100 * e['twin_fraction']:.0f} % of matches")
    az, el, ph = e["folded"]
    print(f"  folded: azimuth within 20 deg {100 * np.mean(az <= 20):.0f} %, "
          f"elevation within 10 deg {100 * np.mean(el <= 10):.0f} %, "
          f"phase within 0.1 cycle {100 * np.mean(ph <= 0.1):.0f} %")
    _plot(args.out, e, eo, f"{model.n_clusters} clusters, {model.size[0]}x{model.size[1]}; "
          f"{len(ex)} fresh walkers")
    if args.means_out:
        _plot_means(args.means_out, model)

    sweep = []
    for s in [tuple(int(v) for v in t.split("x")) for t in args.sweep_sizes.split(",") if t]:
        sweep.append((args.clusters, s))
    for k in [int(v) for v in args.sweep_clusters.split(",") if v]:
        sweep.append((k, size))
    if sweep:
        print("sweep (folded medians / 90th percentiles; ms per silhouette, one call each, wall/cpu):")
        for k, s in sweep:
            m, _, _ = model_for(source=args.source, n_clusters=k, size=s, verbose=False)
            b, _ = m.match(ex.silhouettes)
            az, el, ph = errors(m, b, ex)["folded"]
            wall, cpu = time_match(m, ex.silhouettes)
            print(f"  N={k:<4d} {s[0]:>3d}x{s[1]:<3d} az {np.median(az):5.1f}/{np.percentile(az, 90):5.1f}  "
                  f"el {np.median(el):4.1f}/{np.percentile(el, 90):4.1f}  "
                  f"phase {np.median(ph):.3f}/{np.percentile(ph, 90):.3f}  "
                  f"match {wall:.3f}/{cpu:.3f} ms")


def _plot_means(path, model, n=40):
    """Cluster means in order of mean azimuth, labelled with (azimuth, elevation, phase)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vp, ph = model.cluster_viewpoint, model.cluster_phase
    pick = np.argsort(vp[:, 0])[np.linspace(0, model.n_clusters - 1, n).astype(int)]
    cols = 10
    fig, axes = plt.subplots(n // cols, cols, figsize=(cols * 1.1, n // cols * 1.55), dpi=110)
    for ax, k in zip(axes.ravel(), pick):
        ax.imshow(model.means[k], cmap="gray", vmin=0, vmax=1)
        ax.set_title(f"{vp[k, 0]:.0f}/{vp[k, 1]:.0f}/{ph[k]:.2f}", fontsize=6)
        ax.axis("off")
    fig.suptitle("cluster means (mean azimuth / elevation / phase)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    print(f"wrote {path}")


def _plot(path, e, eo, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.3), dpi=110)
    names = ("azimuth error (deg)", "elevation error (deg)", "phase error (cycles)")
    bins = (np.linspace(0, 180, 37), np.linspace(0, 55, 23), np.linspace(0, 0.5, 21))
    for i, ax in enumerate(axes):
        ax.hist(e["raw"][i], bins[i], histtype="step", label="matched, raw")
        ax.hist(e["folded"][i], bins[i], histtype="stepfilled", alpha=0.4, label="matched, folded")
        ax.hist(eo["folded"][i], bins[i], histtype="step", ls="--", label="oracle GMM, folded")
        ax.set_xlabel(names[i])
    axes[0].set_ylabel("fresh silhouettes")
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
