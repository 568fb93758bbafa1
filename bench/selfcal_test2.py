"""Wang–Leow Test 2 (§6.2) reproduced: self-calibration accuracy against noise.

Usage::

    .venv/bin/python bench/selfcal_test2.py [--trials 50] [--no-ba] [--seed 0]

A 30-frame real walk (CMU 16_15, every 4th frame at 120 Hz, a random window
per trial, skipping the first 20 frames) is projected orthographically into
two cameras; uniform noise U(-a, a) with ``a`` = 0..9 % of the body height in
the image is added to u and v of every joint. Per noise level and trial:
E3D (mean 3D joint error / body height), Es = |s_hat - s| and the error of
each XYZ Euler angle of the relative rotation, plus the SO(3) geodesic error,
for our closed form (§4.2, as in the paper; on Wiener-smoothed tracks; on
smoothed tracks with the noise-consistent beta), the closed form + bundle
adjustment (§4.3; maximum likelihood as in the paper, and MAP with the
temporal prior, the default of ``refine=True``; MAP with the prior that the
walker is upright, ``upright=True``), and the two baselines
(Liebowitz–Carlsson, Tresadern–Reid).

Experiments:

A. Test 2: relative rotation (-10, -60, 20) degrees, s = 1; camera 0 at
   azimuth 45, elevation 10 (a three-quarter view; see docs/SELFCAL.md).
B. The same with camera 0 in a pure side view (azimuth 90), the hardest case.
C. Random camera pairs (uniform rotations, viewing directions 25-155 degrees
   apart) and random relative scale s in [0.5, 2].
D. Three cameras (A plus a third at azimuth 200, elevation 15): the joint
   least-squares solution against the two-camera closed form.
E. Camera scales changing over the window: the fixed-scale closed form and
   the §4.3 path with and without the temporal prior.

Prints the tables, writes PNG plots to ``docs/img/`` and the report
``docs/SELFCAL.md``.
"""

from __future__ import annotations

import os

# Small matrices: BLAS threads only add overhead (and thrash on a shared 2-core box).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from estimator.camera import world_to_camera_rotation  # noqa: E402
from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.joints import N_JOINTS  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.selfcal import self_calibrate  # noqa: E402
from estimator.selfcal_baselines import liebowitz_carlsson, tresadern_reid  # noqa: E402
from estimator.viewpoint import azimuth_difference_deg  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MOCAP = ROOT.parent / "shared" / "data" / "mocap"
TEST2_EULER = np.array([-10.0, -60.0, 20.0])
LEVELS = np.arange(10) / 100.0
S0 = 130.0  # camera 0 pixels per metre: body height (head to ankle) ~195 px, as in the paper


METHODS = {
    "ours": lambda y: self_calibrate(y),
    "ours, smoothed": lambda y: self_calibrate(y, temporal_prior=True),
    "ours, denoised": lambda y: self_calibrate(y, temporal_prior=True, noise_model=True),
    "ours+BA, no temporal prior": lambda y: self_calibrate(y, refine=True, temporal_prior=False,
                                                           noise_model=False),
    "ours+BA": lambda y: self_calibrate(y, refine=True),
    "ours+BA, upright": lambda y: self_calibrate(y, refine=True, upright=True),
    "LC": lambda y: liebowitz_carlsson(y, on_indefinite="clip"),
    "TR": lambda y: tresadern_reid(y),
}


def draw_trial(x_all, rng, level, pair):
    """One trial's window, cameras and noisy tracks: ``(x, rots, scales, height, y)``.

    A random 30-frame window (every 4th frame), the cameras from ``pair(rng)``,
    orthographic tracks of every camera with U(-a, a) noise, ``a`` = ``level`` x
    the body height in that camera's image.
    """
    start = rng.integers(0, len(x_all) - 120)
    x = x_all[start:start + 120:4]
    rots, scales = pair(rng)
    scales = np.asarray(scales, dtype=float)
    height = np.mean(x[..., 2].max(1) - x[..., 2].min(1))
    y = np.einsum("cij,tkj->ctki", rots[:, :2], x) * scales[:, None, None, None]
    y = y + rng.uniform(-1, 1, y.shape) * (level * height * scales)[:, None, None, None]
    return x, rots, scales, height, y


def run_trials(x_all, rng, *, trials, methods, pair, cams=2):
    """Returns {method: {metric: (levels, trials) array}}, LC non-PD counts, failures."""
    out = {m: {k: np.full((len(LEVELS), trials), np.nan) for k in
               ("e3d", "es", "ex", "ey", "ez", "geo", "sx", "sy", "sz", "m2", "pgeo")} for m in methods}
    non_pd = np.zeros(len(LEVELS), dtype=int)
    failed = {m: np.zeros(len(LEVELS), dtype=int) for m in methods}
    for li, level in enumerate(LEVELS):
        for k in range(trials):
            x, rots, scales, height, y = draw_trial(x_all, rng, level, pair)
            y = y[:cams]
            truth = scales[0] * np.einsum("ij,tkj->tki", rots[0], x)
            truth -= truth.mean(axis=1, keepdims=True)
            rel = rots[1] @ rots[0].T
            s_true = scales[1] / scales[0]
            euler_true = Rotation.from_matrix(rel).as_euler("xyz", degrees=True)
            for m in methods:
                res = METHODS[m](y)
                if m == "LC":
                    non_pd[li] += not res.diagnostics.get("omega_positive_definite", True)
                if not res:
                    failed[m][li] += 1
                    continue
                d = out[m]
                d["e3d"][li, k] = np.nanmean(np.linalg.norm(res.joints3d - truth, axis=-1)) / (
                    scales[0] * height)
                d["es"][li, k] = abs(res.scales[1] - s_true)
                e = azimuth_difference_deg(res.euler_xyz_deg[1], euler_true)
                d["ex"][li, k], d["ey"][li, k], d["ez"][li, k] = np.abs(e)
                if res.euler_xyz_cov is not None and level > 0:  # the reported posterior
                    d["sx"][li, k], d["sy"][li, k], d["sz"][li, k] = res.euler_xyz_std_deg[1]
                    d["m2"][li, k] = e @ np.linalg.solve(res.euler_xyz_cov[1], e)
                    d["pgeo"][li, k] = posterior_geodesic(res, seed=k)
                d["geo"][li, k] = geodesic_deg(res.rotations[1], rel)
    return out, non_pd, failed


def run_varying(x_all, rng, *, trials):
    """Experiment E: camera scales change linearly over the window (walker moving in depth)."""
    names = ("closed form (fixed-scale model)", "sec. 4.3, no temporal prior",
             "sec. 4.3 (per-frame U + BA)")
    out = {m: {k: np.full((len(LEVELS), trials), np.nan) for k in ("geo", "es")} for m in names}
    rel = Rotation.from_euler("xyz", TEST2_EULER, degrees=True).as_matrix()
    ra = world_to_camera_rotation(45, 10)
    rots = np.stack([ra, rel @ ra])
    for li, level in enumerate(LEVELS):
        for k in range(trials):
            start = rng.integers(0, len(x_all) - 120)
            x = x_all[start:start + 120:4]
            t = len(x)
            scales = S0 * np.stack([np.linspace(1.0, 1.3, t), np.linspace(1.2, 0.9, t)])  # (2, T)
            height = np.mean(x[..., 2].max(1) - x[..., 2].min(1))
            y = np.einsum("cij,tkj->ctki", rots[:, :2], x) * scales[:, :, None, None]
            y = y + rng.uniform(-1, 1, y.shape) * (level * height * scales)[:, :, None, None]
            s_true = scales[1] / scales[0]
            for m, kw in zip(names, ({}, {"scales": "varying", "temporal_prior": False},
                                     {"scales": "varying"})):
                res = self_calibrate(y, **kw)
                if not res:
                    continue
                out[m]["geo"][li, k] = geodesic_deg(res.rotations[1], rel)
                est = res.frame_scales[:, 1] if res.frame_scales is not None else res.scales[1]
                out[m]["es"][li, k] = np.median(np.abs(est - s_true) / s_true)
    return out


def fixed_pair(azimuth):
    rel = Rotation.from_euler("xyz", TEST2_EULER, degrees=True).as_matrix()
    ra = world_to_camera_rotation(azimuth, 10)

    def pair(rng):
        return np.stack([ra, rel @ ra, world_to_camera_rotation(200, 15)]), [S0, S0, S0]

    return pair


def random_pair(rng):
    while True:
        r = Rotation.random(2, random_state=rng).as_matrix()
        if 25 < np.degrees(np.arccos(np.clip(r[0, 2] @ r[1, 2], -1, 1))) < 155:
            return r, [S0, S0 * rng.uniform(0.5, 2.0)]


def stats(a: np.ndarray) -> tuple[float, float, float, float]:
    a = a[np.isfinite(a)]
    if a.size == 0:
        return (np.nan,) * 4
    q25, q50, q75, q90 = np.percentile(a, [25, 50, 75, 90])
    return q50, q25, q75, q90


def table(title, res, methods, metric, unit, fmt="{:.2f}", non_pd=None, failed=None) -> str:
    label = {"geo": "geodesic rotation error", "e3d": "E3D", "es": "Es"}.get(metric, metric)
    lines = [f"**{title}** — {label}" + (f" ({unit})" if unit else "") + ": median [q25, q75] p90", ""]
    head = "| noise | " + " | ".join(methods) + (" | LC Omega not PD |" if non_pd is not None else " |")
    lines += [head, "|" + "---|" * (len(methods) + 1 + (non_pd is not None))]
    for li, level in enumerate(LEVELS):
        cells = []
        for m in methods:
            q50, q25, q75, q90 = stats(res[m][metric][li])
            cell = f"{fmt.format(q50)} [{fmt.format(q25)}, {fmt.format(q75)}] {fmt.format(q90)}"
            if failed is not None and failed[m][li]:
                cell += f" ({failed[m][li]} failed)"
            cells.append(cell)
        extra = f" {non_pd[li]} |" if non_pd is not None else ""
        lines.append(f"| {level:.0%} | " + " | ".join(cells) + " |" + extra)
    return "\n".join(lines) + "\n"


def posterior_geodesic(res, seed: int, n: int = 500) -> float:
    """Median geodesic distance from camera 1's estimate of rotations drawn from its posterior
    (Gaussian in the Euler angles): the error the posterior expects (own generator: the trial
    draws stay as they were)."""
    draws = np.random.default_rng(seed).multivariate_normal(
        res.euler_xyz_deg[1], res.euler_xyz_cov[1], n)
    rots = Rotation.from_euler("xyz", draws, degrees=True).as_matrix()
    return float(np.median(geodesic_deg(rots, res.rotations[1][None])))


def uncertainty_table(res, methods) -> str:
    """How the reported posterior (``euler_xyz_std_deg``) compares with the actual Euler errors."""
    lines = ["**A. Test 2** — reported uncertainty against the actual error (Euler x / y / z, "
             "degrees): median reported std; the actual error's robust std (1.4826 x median "
             "absolute error, the std for Gaussian errors, not swayed by a rare flip); share of trials within the reported "
             "±1.96 std; share inside the reported 95 % ellipsoid (Mahalanobis² < 7.81, "
             "χ²₃); median geodesic error, actual and as the posterior expects it (median over "
             "trials of the median distance of 500 draws from the posterior)", ""]
    lines += ["| noise | method | reported std | error (robust std) | within ±1.96 std | "
              "inside 95 % ellipsoid | geodesic: actual / posterior |",
              "|---|---|---|---|---|---|---|"]
    for li, level in enumerate(LEVELS[1:], start=1):
        for m in methods:
            d = {k: res[m][k][li] for k in ("ex", "ey", "ez", "sx", "sy", "sz", "m2")}
            ok = np.isfinite(d["m2"])
            if not ok.any():
                continue
            err = np.stack([d["ex"], d["ey"], d["ez"]])[:, ok]
            std = np.stack([d["sx"], d["sy"], d["sz"]])[:, ok]
            fmt = "{:.2f} / {:.2f} / {:.2f}"
            lines.append(f"| {level:.0%} | {m} | {fmt.format(*np.median(std, axis=1))} | "
                         f"{fmt.format(*1.4826 * np.median(err, axis=1))} | "
                         f"{fmt.format(*np.mean(err <= 1.96 * std, axis=1))} | "
                         f"{np.mean(d['m2'][ok] < 7.81):.2f} | "
                         f"{np.median(res[m]['geo'][li][ok]):.2f} / {np.median(res[m]['pgeo'][li][ok]):.2f} |")
    return "\n".join(lines) + "\n"


def medians(res, methods, metric) -> str:
    lines = ["| noise | " + " | ".join(methods) + " |", "|" + "---|" * (len(methods) + 1)]
    for li, level in enumerate(LEVELS):
        lines.append(f"| {level:.0%} | " + " | ".join(
            f"{np.nanmedian(res[m][metric][li]):.4g}" for m in methods) + " |")
    return "\n".join(lines) + "\n"


def plot(res, methods, path: Path, title: str, metrics) -> None:
    ncols = min(3, len(metrics))
    nrows = -(-len(metrics) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.3 * nrows), squeeze=False)
    x = LEVELS * 100
    for ax in axes.ravel()[len(metrics):]:
        ax.set_visible(False)
    for ax, (metric, label) in zip(axes.ravel(), metrics):
        for m in methods:
            a = res[m][metric]
            med = np.nanmedian(a, axis=1)
            lo, hi = np.nanpercentile(a, 25, axis=1), np.nanpercentile(a, 75, axis=1)
            (line,) = ax.plot(x, med, marker="o", ms=3, label=m)
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15)
        if metric in ("e3d", "es"):
            ax.set_yscale("symlog", linthresh=1e-3)
        ax.set_xlabel("2D noise (% of body height)")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-ba", action="store_true", help="skip the (slow) closed form + BA rows")
    p.add_argument("--mocap", type=Path, default=MOCAP / "16_15.amc")
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "SELFCAL.md")
    p.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    args = p.parse_args(argv)

    x_all = read_motion(args.mocap).person_frame()[20:, :N_JOINTS]
    base = ["ours", "ours, denoised", "LC", "TR"]
    with_ba = (["ours", "ours, smoothed", "ours, denoised"]
               + ([] if args.no_ba else ["ours+BA, no temporal prior", "ours+BA", "ours+BA, upright"])
               + ["LC", "TR"])
    t0 = time.time()
    sections = {}
    figs = [("e3d", "E3D / height"), ("es", "Es = |s - s_true|"), ("ex", "E_rx (deg)"),
            ("ey", "E_ry (deg)"), ("ez", "E_rz (deg)"), ("geo", "geodesic (deg)")]

    rng = np.random.default_rng(args.seed)
    res_a, npd_a, fail_a = run_trials(x_all, rng, trials=args.trials, methods=with_ba,
                                      pair=fixed_pair(45))
    plot(res_a, with_ba, args.img / "selfcal_test2.png",
         "Test 2: rotation (-10, -60, 20) deg, s = 1, camera 0 at azimuth 45", figs)
    sections["A"] = (table("A. Test 2", res_a, with_ba, "geo", "degrees", non_pd=npd_a, failed=fail_a)
                     + "\n" + table("A. Test 2", res_a, with_ba, "e3d", "fraction of height", "{:.3f}")
                     + "\n" + table("A. Test 2", res_a, with_ba, "es", "|s_hat - s|", "{:.4f}")
                     + "\nMedian error of each Euler angle (degrees), x / y / z:\n\n"
                     + "\n".join(f"- **{m}**: " + ", ".join(
                         f"{lv:.0%}: {np.nanmedian(res_a[m]['ex'][i]):.2f}/"
                         f"{np.nanmedian(res_a[m]['ey'][i]):.2f}/{np.nanmedian(res_a[m]['ez'][i]):.2f}"
                         for i, lv in enumerate(LEVELS)) for m in with_ba) + "\n")
    posterior = [m for m in with_ba if np.isfinite(res_a[m]["m2"]).any()]
    sections["A_uncertainty"] = uncertainty_table(res_a, posterior) if posterior else ""
    print(sections["A"], sections["A_uncertainty"], flush=True)

    rng = np.random.default_rng(args.seed + 1)
    res_b, npd_b, fail_b = run_trials(x_all, rng, trials=args.trials, methods=base, pair=fixed_pair(90))
    plot(res_b, base, args.img / "selfcal_test2_side.png",
         "Test 2 with camera 0 in a side view (azimuth 90)", figs)
    sections["B"] = table("B. Side view", res_b, base, "geo", "degrees", non_pd=npd_b, failed=fail_b)
    print(sections["B"], flush=True)

    rng = np.random.default_rng(args.seed + 2)
    res_c, npd_c, fail_c = run_trials(x_all, rng, trials=args.trials, methods=base, pair=random_pair)
    plot(res_c, base, args.img / "selfcal_random.png",
         "Random camera pairs, s in [0.5, 2]", [figs[0], figs[1], figs[5]])
    sections["C"] = (table("C. Random pairs", res_c, base, "geo", "degrees", non_pd=npd_c, failed=fail_c)
                     + "\n" + table("C. Random pairs", res_c, base, "es", "|s_hat - s|", "{:.4f}"))
    print(sections["C"], flush=True)

    rng = np.random.default_rng(args.seed + 3)
    res_d2, _, _ = run_trials(x_all, rng, trials=args.trials, methods=["ours"], pair=fixed_pair(45))
    rng = np.random.default_rng(args.seed + 3)  # same windows and noise, plus a third view
    res_d3, _, _ = run_trials(x_all, rng, trials=args.trials, methods=["ours"], pair=fixed_pair(45), cams=3)
    res_d = {"2 cameras": res_d2["ours"], "3 cameras (lsq)": res_d3["ours"]}
    sections["D"] = ("**D. Three cameras** — geodesic error of camera 1 (degrees), median\n\n"
                     + medians(res_d, list(res_d), "geo"))
    print(sections["D"], flush=True)

    rng = np.random.default_rng(args.seed + 4)
    res_e = run_varying(x_all, rng, trials=max(5, args.trials // 2))
    names_e = list(res_e)
    plot(res_e, names_e, args.img / "selfcal_varying.png",
         "Changing scales (sec. 4.3): s0 x1.0 -> 1.3, s1 x1.2 -> 0.9 over the window",
         [("geo", "geodesic (deg)"), ("es", "median |s_t - s_t,true| / s_t,true")])
    sections["E"] = (table("E. Changing scales", res_e, names_e, "geo", "degrees")
                     + "\n" + table("E. Changing scales", res_e, names_e, "es",
                                    "median relative error of the per-frame scale", "{:.4f}"))
    print(sections["E"], flush=True)
    elapsed = time.time() - t0
    print(f"elapsed {elapsed:.0f} s")

    targets = check_targets(res_a, npd_a)
    print(targets)
    write_doc(args.doc, sections, targets, args.trials, elapsed)
    return 0


def _median_se(x: np.ndarray, n_boot: int = 2000) -> float:
    """Bootstrap standard error of the median (fixed seed: the report is reproducible)."""
    x = x[np.isfinite(x)]
    idx = np.random.default_rng(0).integers(0, x.size, size=(n_boot, x.size))
    return float(np.std(np.median(x[idx], axis=1)))


def check_targets(res, npd) -> str:
    """The issue's targets on experiment A.

    The issue measures the rotation error about each axis (the paper's E_rj,
    its Fig. 3c-e); the geodesic error, our stricter summary, is listed too.
    """
    i0, i5 = 0, 5
    ok = []
    ours = [m for m in res if m.startswith("ours")]
    axes = ("ex", "ey", "ez")
    geo0 = max(np.nanmax(res[m][k][i0]) for m in ours for k in axes + ("geo",))
    s0 = max(np.nanmax(res[m]["es"][i0]) for m in ours)
    ok.append(("noise 0: rotation error < 0.01 deg (max over trials, our methods, axes and geodesic)",
               f"{geo0:.2e} deg", geo0 < 0.01))
    ok.append(("noise 0: abs(s - 1) < 1e-4 (max over trials and our methods)", f"{s0:.2e}", s0 < 1e-4))
    med = {m: np.array([np.nanmedian(res[m][k][i5]) for k in axes]) for m in res}
    best = min(ours, key=lambda m: med[m].max())
    se = [_median_se(res[best][k][i5]) for k in axes]

    def xyz(v) -> str:
        return " / ".join(f"{x:.2f}" for x in v)

    ok.append(("noise 5%: median rotation error about each axis <= 3 deg, E_rx / E_ry / E_rz "
               "(paper's closed form)", f"{xyz(med['ours'])} deg", med["ours"].max() <= 3))
    ok.append((f"noise 5%: median rotation error about each axis <= 3 deg, E_rx / E_ry / E_rz "
               f"(best of ours: {best}; [bootstrap standard error])",
               f"{xyz(med[best])} deg [{xyz(se)}]", med[best].max() <= 3))
    ok.append((f"noise 5%: {best} no worse than LC and TR on any axis",
               f"{xyz(med[best])}; LC {xyz(med['LC'])}; TR {xyz(med['TR'])}",
               bool(np.all(med[best] <= np.minimum(med["LC"], med["TR"])))))
    geo = {m: np.nanmedian(res[m]["geo"][i5]) for m in res}
    ok.append(("noise 5%: median geodesic error (stricter than the target; reported, not the target's "
               "measure)", f"paper's closed form {geo['ours']:.2f}, {best} {geo[best]:.2f}, "
               f"LC {geo['LC']:.2f}, TR {geo['TR']:.2f}", None))
    ok.append(("noise 5%: ours no worse than LC and TR (median geodesic)",
               f"paper's closed form {geo['ours']:.2f}, {best} {geo[best]:.2f}",
               max(geo["ours"], geo[best]) <= min(geo["LC"], geo["TR"])))
    mark = {True: "yes", False: "**no**", None: "—"}
    lines = ["| target | measured | met |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {mark[c]} |" for a, b, c in ok]
    return "\n".join(lines) + "\n"


def write_doc(path: Path, sections: dict, targets: str, trials: int, elapsed: float) -> None:
    text = (ROOT / "bench" / "selfcal_report_template.md").read_text()
    for key, body in sections.items():
        text = text.replace(f"{{{{{key}}}}}", body)
    text = text.replace("{{TARGETS}}", targets).replace("{{TRIALS}}", str(trials))
    text = text.replace("{{ELAPSED}}", f"{elapsed:.0f}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
