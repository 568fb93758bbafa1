"""Silhouette refinement feedback (§7.1, issue 8): IoU and downstream accuracy, raw vs refined.

The synthetic camera (two views of the same walker, a hardware-synchronised
rig) under hard conditions: clothing close to the background colour, sensor
noise, lighting drift and a static occluder (a post, drawn from frame 0 so the
background model learns it). Per condition:

1. pass 1: capture's segmenter without priors ("raw");
2. the walk estimated from the raw silhouettes (full default model);
3. priors rendered from that estimate (:mod:`estimator.prior`);
4. pass 2: the segmenter from scratch with each frame's prior ("refined"),
   and again with every prior turned 90 degrees about its centroid ("wrong");
5. the walk re-estimated from the refined silhouettes.

IoU is against the *visible* ground truth (the true mask minus the occluder:
no background subtraction can see behind a post). Viewpoint error is the
azimuth/elevation error of the estimate; phase error the mean circular error
(cycles) over frames with a walker.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_feedback.py [--quick]

Writes ``docs/img/feedback_iou.png``, ``docs/img/feedback_frames.png``,
``docs/img/feedback_example.png`` and ``docs/FEEDBACK.md``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from capture.refine import second_pass, segment, track_from_segmentations  # noqa: E402
from capture.scene import iou  # noqa: E402
from capture.segment import SegmentSettings  # noqa: E402
from capture.synthetic import SyntheticSource  # noqa: E402
from estimator.pipeline import estimate_walk  # noqa: E402
from estimator.prior import PriorConfig, priors_for_window, rotate_prior  # noqa: E402
from estimator.render import Renderer  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
VIEWS = (("c0", 90.0, 10.0), ("c1", 30.0, 20.0))
EMPTY, PASS, GAP = 30, 40, 10
TRIM = 0.1  # capture.refine.refine_cameras' default trim_reach


@dataclass(frozen=True)
class Condition:
    name: str
    contrast: float
    noise: float
    drift: float
    occluder: bool = False
    seed: int = 3


CONDITIONS = (
    Condition("clean (contrast 0.8)", 0.8, 3.0, 0.08),
    Condition("contrast 0.5", 0.5, 3.0, 0.08),
    Condition("contrast 0.35", 0.35, 3.0, 0.08, seed=5),
    Condition("contrast 0.25", 0.25, 3.0, 0.08),
    Condition("noise 10, contrast 0.5", 0.5, 10.0, 0.08, seed=5),
    Condition("drift 0.2, contrast 0.5", 0.5, 3.0, 0.2),
    Condition("drift 0.3, contrast 0.5", 0.5, 3.0, 0.3),
    Condition("occluder, contrast 0.6", 0.6, 3.0, 0.08, occluder=True),
    Condition("all: occluder, noise 8, drift 0.2, contrast 0.35", 0.35, 8.0, 0.2, occluder=True, seed=5),
    # Harder than the above since the segmenter divides out lighting drift:
    Condition("contrast 0.17", 0.17, 3.0, 0.08),
    Condition("contrast 0.16", 0.16, 3.0, 0.08),
)


def _occluder(width: int, height: int) -> np.ndarray:
    """A post and a low crate, drawn where the walker passes."""
    m = np.zeros((height, width), np.uint8)
    cv2.rectangle(m, (int(0.47 * width), 0), (int(0.47 * width) + 22, height), 255, -1)
    cv2.rectangle(m, (int(0.62 * width), int(0.70 * height)), (int(0.72 * width), height), 255, -1)
    return m


def _frames(cond: Condition, az: float, el: float, n: int):
    spec = (f"seed={cond.seed},azimuth={az},elevation={el},contrast={cond.contrast},noise={cond.noise},"
            f"drift={cond.drift},empty={EMPTY},pass={PASS},gap={GAP}")
    src = SyntheticSource.from_spec(spec)
    images, masks, phases = [], [], []
    occ = _occluder(src.spec.width, src.spec.height) if cond.occluder else None
    for k in range(n):
        f = src.render(k)
        image, mask = f.image, f.mask
        if occ is not None:  # lit by the scene's drifting light like everything else
            image = image.copy()
            image[occ > 0] = np.clip(np.array((70, 90, 110)) * src.gain(k), 0, 255).astype(np.uint8)
            mask = np.where(occ > 0, 0, mask).astype(np.uint8)
        truth = src.truth(k)
        images.append(image)
        masks.append(mask)
        phases.append(np.nan if truth is None else truth["phase"])
    src.close()
    return images, masks, np.array(phases)


def _ious(segs, masks) -> np.ndarray:
    out = np.full(len(masks), np.nan)
    for k, (s, m) in enumerate(zip(segs, masks)):
        if m.any():
            out[k] = 0.0 if s is None else iou(s.full_mask(), m)
    return out


def _errors(estimate, phases: np.ndarray) -> dict:
    az = [abs((estimate.cameras[c].viewpoint.azimuth_deg - a + 180) % 360 - 180) for c, a, _ in VIEWS]
    el = [abs(estimate.cameras[c].viewpoint.elevation_deg - e) for c, _, e in VIEWS]
    ok = np.isfinite(phases)
    d = np.abs((estimate.phase[ok] - phases[ok] + 0.5) % 1.0 - 0.5)
    return {"az": float(np.nanmean(az)), "el": float(np.nanmean(el)), "phase": float(d.mean()),
            "phase_ok": float((d <= 0.075).mean())}


def run_condition(cond: Condition, model, n: int, settings: SegmentSettings, config: PriorConfig) -> dict:
    # Frames in a fresh process each (spawned: the synthetic camera's renders
    # then do not depend on what this process rendered before), then the prior renderer.
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:
        data = {c: pool.apply(_frames, (cond, az, el, n)) for c, az, el in VIEWS}
    phases = data["c0"][2]
    raw = {c: segment(d[0], settings) for c, d in data.items()}
    tracks = {c: track_from_segmentations(s) for c, s in raw.items()}
    size = (data["c0"][0][0].shape[1], data["c0"][0][0].shape[0])
    est_raw = estimate_walk(tracks, model)
    with Renderer(config.body) as renderer:
        priors = priors_for_window(est_raw, tracks, size, renderer=renderer, config=config)
        # Ablation: every prior registered onto its own frame's silhouette, torn or not.
        per_frame = priors_for_window(est_raw, tracks, size, renderer=renderer,
                                      config=dataclasses.replace(config, torn=float("inf")))
    turned = {c: [rotate_prior(p) for p in priors[c]] for c in data}
    # The second pass as capture.refine.refine_cameras makes it, for each set of priors.
    refined, registered, wrong = ({c: second_pass(data[c][0], settings, ps[c], raw[c], trim_reach=TRIM) for c in data}
                                  for ps in (priors, per_frame, turned))
    trusting = settings.model_copy(update={"prior_check": False})
    unchecked = {c: segment(data[c][0], trusting, turned[c]) for c in data}
    est_ref = estimate_walk({c: track_from_segmentations(s) for c, s in refined.items()}, model)
    prior_iou = {c: np.array([iou(p.full_mask() >= 128, data[c][1][p.frame_index]) for p in priors[c]
                              if data[c][1][p.frame_index].any()]) for c in data}
    out = {"cond": cond, "cams": {}, "err_raw": _errors(est_raw, phases), "err_ref": _errors(est_ref, phases)}
    for c in data:
        out["cams"][c] = {"raw": _ious(raw[c], data[c][1]), "refined": _ious(refined[c], data[c][1]),
                          "wrong": _ious(wrong[c], data[c][1]), "wrong_unchecked": _ious(unchecked[c], data[c][1]),
                          "registered": _ious(registered[c], data[c][1]),
                          "prior": float(np.mean(prior_iou[c]))}
    gain = out["cams"]["c0"]["refined"] - out["cams"]["c0"]["raw"]
    k = int(np.nanargmax(gain))  # the frame feedback helped most: an example picture
    pri = {p.frame_index: p for p in priors["c0"]}
    out["example"] = (data["c0"][0][k], data["c0"][1][k], raw["c0"][k], pri.get(k), refined["c0"][k])
    return out


def _row(r: dict) -> list[str]:
    rows = []
    for c, m in r["cams"].items():
        raw, ref, wr = np.nanmean(m["raw"]), np.nanmean(m["refined"]), np.nanmean(m["wrong"])
        wu, rg = np.nanmean(m["wrong_unchecked"]), np.nanmean(m["registered"])
        rows.append(f"| {r['cond'].name} | {c} | {raw:.3f} | {ref:.3f} | {ref - raw:+.3f} | {rg - raw:+.3f} | "
                    f"{wr:.3f} | {wr - raw:+.3f} | {wu - raw:+.3f} | {m['prior']:.3f} |")
    return rows


def _verdict(results: list[dict]) -> list[str]:
    lines = []
    low, high, wrong = [], [], []
    for r in results:
        for c, m in r["cams"].items():
            raw, ref, wr = (float(np.nanmean(m[k])) for k in ("raw", "refined", "wrong"))
            if raw < 0.8:
                low.append((r["cond"].name, c, ref - raw))
            if raw >= 0.9:
                high.append((r["cond"].name, c, ref - raw))
            wrong.append((r["cond"].name, c, wr - raw))
    ok_low = bool(low) and all(g >= 0.05 for *_, g in low)
    ok_high = all(g >= -0.01 for *_, g in high)
    ok_wrong = all(g >= -0.02 for *_, g in wrong)
    lines.append(f"- raw IoU < 0.8 ({len(low)} camera-conditions): gain >= +0.05 in "
                 f"{sum(g >= 0.05 for *_, g in low)}/{len(low)}: "
                 f"{'MET' if ok_low else 'NOT MET' if low else 'NOT TESTED (no condition that hard)'}"
                 + ("" if ok_low else " (" + ", ".join(f"{n} {c} {g:+.3f}" for n, c, g in low if g < 0.05) + ")"))
    lines.append(f"- raw IoU >= 0.9 ({len(high)}): loss <= 0.01 in {sum(g >= -0.01 for *_, g in high)}/{len(high)}: "
                 f"{'MET' if ok_high else 'NOT MET'}")
    lines.append(f"- wrong prior (rotated 90 deg), {len(wrong)} camera-conditions: IoU drop <= 0.02 in "
                 f"{sum(g >= -0.02 for *_, g in wrong)}/{len(wrong)}: {'MET' if ok_wrong else 'NOT MET'}"
                 + ("" if ok_wrong else " (" + ", ".join(f"{n} {c} {g:+.3f}" for n, c, g in wrong if g < -0.02) + ")"))
    return lines


def _frame_bins(results: list[dict]) -> list[str]:
    raw = np.concatenate([m["raw"] for r in results for m in r["cams"].values()])
    ref = np.concatenate([m["refined"] for r in results for m in r["cams"].values()])
    wr = np.concatenate([m["wrong"] for r in results for m in r["cams"].values()])
    ok = np.isfinite(raw)
    raw, ref, wr = raw[ok], ref[ok], wr[ok]
    lines = ["| raw IoU of the frame | frames | raw | refined | gain | wrong prior | change |", "|---|---|---|---|---|---|---|"]
    for lo, hi in ((0.0, 0.6), (0.6, 0.8), (0.8, 0.9), (0.9, 1.01)):
        sel = (raw >= lo) & (raw < hi)
        if sel.any():
            lines.append(f"| [{lo:.1f}, {min(hi, 1.0):.1f}) | {sel.sum()} | {raw[sel].mean():.3f} | {ref[sel].mean():.3f} | "
                         f"{ref[sel].mean() - raw[sel].mean():+.3f} | {wr[sel].mean():.3f} | {wr[sel].mean() - raw[sel].mean():+.3f} |")
    return lines


def _plots(results: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels, raw, ref, wr = [], [], [], []
    for r in results:
        for c, m in r["cams"].items():
            labels.append(f"{r['cond'].name}\n{c}")
            raw.append(np.nanmean(m["raw"]))
            ref.append(np.nanmean(m["refined"]))
            wr.append(np.nanmean(m["wrong"]))
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(8, 0.75 * len(labels)), 4.5))
    ax.bar(x - 0.27, raw, 0.27, label="raw")
    ax.bar(x, ref, 0.27, label="with feedback")
    ax.bar(x + 0.27, wr, 0.27, label="wrong prior (90 deg)")
    ax.set_xticks(x, labels, rotation=70, fontsize=7, ha="right")
    ax.set_ylabel("mean silhouette IoU")
    ax.set_ylim(0, 1)
    ax.legend(loc="lower left")
    ax.set_title("Silhouette IoU against visible ground truth, synthetic camera")
    fig.tight_layout()
    fig.savefig(out / "feedback_iou.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5, 5))
    for r in results:
        rr = np.concatenate([m["raw"] for m in r["cams"].values()])
        ff = np.concatenate([m["refined"] for m in r["cams"].values()])
        ax.scatter(rr, ff, s=5, label=r["cond"].name)
    ax.plot([0, 1], [0, 1], "k--", lw=0.8)
    ax.set_xlabel("raw IoU (per frame)")
    ax.set_ylabel("IoU with feedback")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "feedback_frames.png", dpi=110)
    plt.close(fig)

    # Example: the frame of the hardest condition that feedback helped most.
    image, mask, raw_s, prior, ref_s = results[-1]["example"]
    ys, xs = np.nonzero(mask)
    if ys.size:
        y0, y1 = max(0, ys.min() - 30), min(mask.shape[0], ys.max() + 30)
        x0, x1 = max(0, xs.min() - 40), min(mask.shape[1], xs.max() + 40)
        tiles = [cv2.cvtColor(image, cv2.COLOR_BGR2RGB), mask, raw_s.full_mask() if raw_s else 0 * mask,
                 prior.full_mask() if prior else 0 * mask, ref_s.full_mask() if ref_s else 0 * mask]
        names = ["frame", "visible truth", "raw", "prior", "with feedback"]
        fig, axes = plt.subplots(1, 5, figsize=(10, 4))
        for a, t, nm in zip(axes, tiles, names):
            a.imshow(t[y0:y1, x0:x1], cmap=None if t.ndim == 3 else "gray")
            a.set_title(nm, fontsize=9)
            a.axis("off")
        fig.tight_layout()
        fig.savefig(out / "feedback_example.png", dpi=110)
        plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="first three conditions, one pass")
    parser.add_argument("--no-docs", action="store_true", help="print only")
    parser.add_argument("--prior-noise-k", type=float, default=None, help="override SegmentSettings.prior_noise_k")
    parser.add_argument("--prior-diff", type=float, default=None, help="override SegmentSettings.prior_diff")
    parser.add_argument("--band", type=float, default=None, help="override PriorConfig.band")
    parser.add_argument("--inset", type=float, default=None, help="override PriorConfig.inset")
    parser.add_argument("--reach-max", type=float, default=None, help="override PriorConfig.reach_max")
    parser.add_argument("--trim", type=float, default=None, help="override the trim reach (body heights)")
    parser.add_argument("--complete-ratio", type=float, default=None, help="override PriorConfig.complete_ratio")
    parser.add_argument("--only", type=str, default=None, help="comma-separated condition numbers")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    global TRIM
    if args.trim is not None:
        TRIM = args.trim
    from service.cli.model import get_default_model

    model = get_default_model()
    config = PriorConfig(**{k: v for k, v in (("band", args.band), ("inset", args.inset), ("reach_max", args.reach_max), ("complete_ratio", args.complete_ratio)) if v is not None})
    settings = SegmentSettings(warmup_frames=EMPTY, **{k: v for k, v in (
        ("prior_noise_k", args.prior_noise_k), ("prior_diff", args.prior_diff)) if v is not None})
    n = EMPTY + (1 if args.quick else 2) * (PASS + GAP)
    conds = CONDITIONS[:3] if args.quick else CONDITIONS
    if args.only:
        conds = [CONDITIONS[int(i)] for i in args.only.split(",")]
    results = []
    t0 = time.perf_counter()
    for cond in conds:
        results.append(run_condition(cond, model, n, settings, config))
        print(f"  {cond.name}: {time.perf_counter() - t0:.0f} s", flush=True)
    iou_table = ["| condition | camera | raw IoU | with feedback | gain | gain, registered per frame | wrong prior | change | "
                 "change, wrong prior unchecked | prior IoU (>=128) |",
                 "|---|---|---|---|---|---|---|---|---|---|"] + [line for r in results for line in _row(r)]
    down = ["| condition | azimuth err raw -> fb (deg) | elevation err raw -> fb | phase err raw -> fb (cycles) | phase within 0.075: raw -> fb |",
            "|---|---|---|---|---|"]
    for r in results:
        a, b = r["err_raw"], r["err_ref"]
        down.append(f"| {r['cond'].name} | {a['az']:.1f} -> {b['az']:.1f} | {a['el']:.1f} -> {b['el']:.1f} | "
                    f"{a['phase']:.3f} -> {b['phase']:.3f} | {a['phase_ok']:.2f} -> {b['phase_ok']:.2f} |")
    bins = _frame_bins(results)
    verdict = _verdict(results)
    print("\n".join(iou_table), "", "\n".join(bins), "", "\n".join(down), "", "\n".join(verdict), sep="\n")
    if args.no_docs:
        return
    img = ROOT / "docs" / "img"
    img.mkdir(parents=True, exist_ok=True)
    _plots(results, img)
    _report(results, iou_table, bins, down, verdict, n, config, settings)


def _report(results, iou_table, bins, down, verdict, n, config: PriorConfig, settings: SegmentSettings) -> None:
    text = f"""# Silhouette refinement feedback (Izo–Grimson §7.1, issue 8)

Generated by `OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_feedback.py`; numbers from
this machine (2 cores). Synthetic camera, walker seed per condition, two views
(c0: azimuth 90, elevation 10; c1: azimuth 30, elevation 20), {n} frames each
({EMPTY} empty for the background model, then passes of {PASS} frames with {GAP}-frame gaps).

## Method

1. **Raw**: capture's segmenter (`capture.segment.Segmenter`, MOG2 + selective update,
   warm-up {settings.warmup_frames} frames) without priors.
2. **Estimate** the walk from the raw silhouettes (`estimate_walk`, default model).
3. **Priors** (`estimator.prior.priors_for_window`): the model body
   (`BodyShape()`, the body the estimator reports) rendered orthographically at
   the decoded phase from the estimated viewpoint, mapped onto the observed
   silhouette by the inverse of the §5 registration (scale along the principal
   axis, centroid; `rotate={config.rotate}`: walkers are upright and a torn
   silhouette's axis is noise), shifted by up to {config.search:.0%} of the height to
   the translation that overlaps the observation most, and softened:
   `255 * sigmoid(signed distance / ({config.band} * height))` (outline = 128).
   **Torn silhouettes** (a box shorter by more than {config.torn:.0%} than the
   walker's extent in that frame) are not registered onto: the render is placed
   by the extent, which `estimator.prior.body_extent` fits over the window (the
   head's row as the lower envelope of the observed tops, the feet's as the upper
   envelope of the bottoms, the centre as the median line of the centroids: a
   few frames that see the head or the feet fix them for all). The column
   "gain, registered per frame" is the ablation: every prior registered onto its
   own frame's silhouette, as before.
   **Evidence gate**: the prior fades beyond `reach` of the observed foreground
   (enclosed holes count as observed), `reach` from {config.reach_min} x height for an
   observation of at least {config.complete_ratio} of the model body's area to {config.reach_max} x height for one of half
   its area or less. Without the gate the model body's misfit (another body
   shape, another gait style: the prior IoU column) added 200-400 false pixels
   per frame on clean input, an IoU loss of ~0.02.
4. **With feedback**: the segmenter from scratch, each frame's prior
   installed with `set_prior` before the frame (what a live agent receiving
   predictions does). The segmenter **checks** each prior against its own
   evidence (MOG2's foreground near the prior, before fusion; docs/CAPTURE.md,
   "Prior fusion": trusted as is at >= {settings.prior_full_coverage:.0%} coverage,
   not used below {settings.prior_min_coverage:.0%}, weakened in between), then fuses it: a
   model-resolution pixel whose prior is at least `prior_level` ({settings.prior_level}) becomes
   foreground when its colour distance to the background model exceeds
   max({settings.prior_diff}, {settings.prior_noise_k} x the frame's mean distance), and a full-resolution
   pixel there when its squared distance exceeds {settings.prior_threshold} x the noise variance
   (instead of {settings.refine_threshold}).
5. **Trim** (`capture.refine.trim`, offline only): foreground farther than
   {TRIM} x height from the prior's support is cut (drift blobs attached to
   the walker), with each prior first checked against the raw silhouette
   (`capture.refine.check_priors`: `estimator.prior.explained` / `weigh`, the
   same rule), so that a wrong prior cannot cut the walker.
6. **Wrong prior**: every prior turned 90 degrees about its centroid, then the
   same segmenter and trim; the "unchecked" column installs the turned priors
   in a segmenter whose check is off (`prior_check=False`) and does not trim.
7. Downstream: the walk re-estimated from the refined silhouettes.

Ground truth is the *visible* mask (true mask minus the occluder); the post
and crate are part of the background, so no segmenter (with or without
prior) can see behind them.

## Silhouette IoU (mean over frames with a walker)

{chr(10).join(iou_table)}

"prior IoU" is the prior thresholded at 128 against the truth: how well the
model body at the estimated pose and viewpoint covers this walker (a different
body shape and gait style than the model's).

Per frame, pooled over conditions and cameras:

{chr(10).join(bins)}

![IoU per condition](img/feedback_iou.png)
![per frame](img/feedback_frames.png)
![example](img/feedback_example.png)

## Targets

{chr(10).join(verdict)}

## Downstream: viewpoint and phase

{chr(10).join(down)}

Phase error is the mean circular error in cycles (0.05 = one of the paper's 20
phases); "within 0.075" the fraction of frames within 1.5 phases.

## Why the targets are (not) met

- **Most hard conditions are no longer hard.** Since the segmenter divides out
  the global lighting gain (docs/CAPTURE.md, "Lighting drift"), lighting drift
  of 20-30 % and clothing contrast down to 0.25 give raw IoU 0.87-0.99 (before:
  0.13-0.78 for contrast 0.25, drift 0.2 and drift 0.3, the six
  camera-conditions under 0.8 in the previous version of this report, where
  feedback gained +0.005 to +0.057). Two conditions were added to keep the
  < 0.8 target tested: clothing contrast 0.17 and 0.16.
- **Low raw IoU: the placement was the bottleneck.** At clothing contrast
  0.16-0.17 the walker is nearly invisible (raw IoU 0.26-0.41): the segmenter
  finds fragments of the body (at contrast 0.17, 84-99 % of what it finds is
  the walker, but only 36-41 % of the walker is found), and a prior
  registered onto a fragment's height and centroid is a small body in the wrong
  place. Measured on contrast 0.17 with the frames of this script: priors
  rendered at the *true* viewpoint and phase but registered per frame covered
  the walker no better (prior IoU 0.27 / 0.33, as from the estimate 40-50
  degrees off), while the true mask as prior gave 0.98 after fusion; the fusion
  only adds pixels with some colour evidence, so a prior needs to cover the
  walker, not to match it. Placing torn frames by the window's extent of the
  walker (Method, step 3) gives the gains in the table; the column
  "registered per frame" is what the previous registration gave. The estimate
  itself stays poor there (downstream table): two cameras that both see the
  walker this faintly do not pin the viewpoint.
- **Occluder**: a post splits the walker; the segmenter keeps one part, the
  prior is registered onto that part (wrong centroid and scale). The
  registration of a prior onto a partial silhouette is the weak point; fitting
  the prior's box to the *previous* frames' full boxes (the walker's height
  changes slowly) would fix the scale.
- **High raw IoU**: the gate keeps the prior inside the observation when the
  observation is as large as the model body, so complete silhouettes are
  nearly untouched.

The live loop (priors predicted ahead of the frames and sent to the agents)
is described in docs/SERVICE.md ("Live windows", step 6); its timing in
docs/BENCHMARKS.md (`bench/bench_feedback_live.py`).

## Notes and limits

- One feedback round. A second round (estimate on refined silhouettes, new
  priors) is possible with the same functions.
- The fusion rule (`prior_level`, `prior_diff`, `prior_noise_k`,
  `prior_threshold`) and the agent-side check are capture's defaults.
- The occluder is lit by the scene's drifting light like the rest of the scene
  (it was painted with a constant colour before, which no real post has; with
  gain compensation that unlit post became foreground).
- Frames of each condition are rendered in a fresh (spawned) process, so a
  condition's frames never depend on what was rendered before it (checked:
  identical hashes across runs). Raw IoU depends on `capture/segment.py`'s
  settings (quarter-resolution model, full-resolution refinement, gain
  compensation); rerun the script after changing it.
"""
    (ROOT / "docs" / "FEEDBACK.md").write_text(text)
    print("wrote docs/FEEDBACK.md and docs/img/feedback_*.png")


if __name__ == "__main__":
    main()
