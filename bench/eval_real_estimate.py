"""The estimator on real footage: viewpoints of the walkers of vtest.avi against their direction of travel.

No walker of ``/work/shared/data/video/vtest.avi`` (OpenCV's sample: one fixed
camera over a path and a lawn, 480x360, 10 fps, several people 45-120 px tall,
shadows) was made by posecal. It has no ground truth, but a walker's viewpoint
has a consequence in the image: the camera sees a walker who crosses the image
to the right from their right side (azimuth 180-360, DESIGN.md's convention:
90 = camera on the walker's left), one who comes down the image (towards the
camera) from the front (azimuth near 0) and one who goes up it from behind
(near 180). So:

1. the video is segmented as a capture agent segments a file (default
   settings: background bootstrapped, one walker tracked);
2. the tracked walker's frames are cut into *passes* where its box moves
   continuously (a jump of more than 0.35 of its height, or a change of size
   of more than 25 %, starts another: the tracker took another person), and
   passes into live windows (20 frames every 10), each estimated on its own
   (``estimate_walk``, one camera, the shipped model);
3. each window's direction of travel is the straight-line fit of the foot
   point (the box's bottom centre), in walker heights per frame; windows
   where the walker moves less than ``--min-speed`` are left out (standing);
4. reported: whether the viewpoint is on the side the travel says (left or
   right of the walker, where the travel across the image is clear; in front
   or behind, where the travel up or down the image is), and the angle
   between the viewpoint and the heading the travel gives on the ground,
   the image's vertical motion divided by ``sin(elevation)`` for the
   camera's assumed ``--elevation`` (the foreshortening of the ground; the
   angle depends on it, the sides do not), also with the ahead/behind fold
   set aside (the nearer of the azimuth and its mirror ``180 - azimuth``).

``--live`` runs the product's live path instead of step 2's windows:
``posecal serve`` on loopback and one ``posecal capture`` agent on the video
(which it plays at its 10 fps, about 80 s), the windows the service cuts (20
frames every 10 from the agent's first frame) read back over REST. A window
is scored as above when its frames lie in one pass of the same segmentation
(the agent's per-frame path is the one step 1 runs); the frames the service
left out as another person's (``window.other_person``) are left out of its
travel too. Also reported: the windows that span a change of person, the
windows estimated again (``window.revision``) and the cameras called out of
step (none here: one camera).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_real_estimate.py [--plot docs/img/real_video_viewpoints.png]
    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_real_estimate.py --live
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_real_video import VIDEO, load_video  # noqa: E402
from eval_real_video import segment as segment_clip  # noqa: E402

from capture.live import same_person  # noqa: E402
from capture.segment import SegmentSettings  # noqa: E402
from estimator.pipeline import CameraTrack, estimate_walk  # noqa: E402
from estimator.viewpoint import azimuth_difference_deg  # noqa: E402

WINDOW, HOP = 20, 10


def segment(video: np.ndarray) -> tuple[list, np.ndarray]:
    """The tracked walker's crop and full-frame box per frame (None / NaN where none), default settings."""
    found, _ = segment_clip(video, SegmentSettings())
    boxes = np.array([[np.nan] * 4 if s is None else [s.box.x, s.box.y, s.box.w, s.box.h] for s in found], float)
    return [None if s is None else s.mask for s in found], boxes


def passes(boxes: np.ndarray, min_frames: int = WINDOW) -> list[tuple[int, int]]:
    """Runs of frames (start, stop) where the box moves continuously (one person)."""
    out, start = [], None
    for t in range(len(boxes)):
        seen = bool(np.isfinite(boxes[t, 0]))
        if seen and start is not None and np.isfinite(boxes[t - 1, 0]):
            if not same_person(tuple(boxes[t - 1]), tuple(boxes[t]), 1):  # the agent's own test
                out.append((start, t))
                start = t
        elif seen and start is None:
            start = t
        elif not seen and start is not None:
            out.append((start, t))
            start = None
    if start is not None:
        out.append((start, len(boxes)))
    return [p for p in out if p[1] - p[0] >= min_frames]


def travel(boxes: np.ndarray) -> tuple[float, float, float]:
    """The foot point's image velocity (du, dv) in walker heights per frame, and the walker's height."""
    foot = np.stack([boxes[:, 0] + boxes[:, 2] / 2, boxes[:, 1] + boxes[:, 3]], axis=1)
    t = np.arange(len(boxes))
    h = float(np.median(boxes[:, 3]))
    return float(np.polyfit(t, foot[:, 0], 1)[0] / h), float(np.polyfit(t, foot[:, 1], 1)[0] / h), h


def heading_azimuth(du: float, dv: float, elevation_deg: float) -> float:
    """The azimuth the travel implies (DESIGN.md): to the image's right = 270, left = 90, down (towards
    the camera) = 0, up = 180; the vertical motion divided by sin(elevation) (ground foreshortening)."""
    return float(np.degrees(np.arctan2(-du, dv / np.sin(np.radians(elevation_deg)))) % 360.0)


def offline_rows(video: np.ndarray, crops: list, boxes: np.ndarray, runs: list[tuple[int, int]],
                 min_speed: float) -> list[tuple]:
    """Step 2: ``(first frame, height, du, dv, azimuth, elevation)`` of each moving window of each pass,
    estimated on its own."""
    from service.cli.model import get_default_model

    model = get_default_model(progress=True)
    rows = []
    for a, b in runs:
        for w0 in range(a, b - WINDOW + 1, HOP):
            box = boxes[w0:w0 + WINDOW]
            du, dv, h = travel(box)
            if np.hypot(du, dv) < min_speed:
                continue
            track = CameraTrack(crops[w0:w0 + WINDOW], box, full_frame=True, image_size=video.shape[2:0:-1])
            try:
                vp = estimate_walk({"c": track}, model).cameras["c"].viewpoint
            except ValueError:  # nothing estimable in the window
                continue
            rows.append((w0, h, du, dv, vp.azimuth_deg, vp.elevation_deg))
    return rows


def live_rows(boxes: np.ndarray, runs: list[tuple[int, int]], min_speed: float) -> list[tuple]:
    """``--live``: the rows of :func:`offline_rows` from the windows ``posecal serve`` estimated on the
    frames one ``posecal capture`` agent sent it from the video (module docstring)."""
    import shutil
    import tempfile

    from _service_proc import ServiceProcess
    from eval_live_composite import collect, run_walk

    work = Path(tempfile.mkdtemp(prefix="posecal-real-live-"))
    (work / "videos").mkdir()
    shutil.copy(VIDEO, work / "videos" / "c0.avi")
    try:
        with ServiceProcess(work / "service") as svc:
            agent = run_walk(svc, "vtest", work / "videos", ["c0"], timeout=600.0)
            windows, _ = collect(svc, "vtest")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    pass_of = np.full(len(boxes), -1)
    for k, (a, b) in enumerate(runs):
        pass_of[a:b] = k
    rows, counts = [], {"windows": len(windows), "across people": 0, "revised": 0, "out of step": 0}
    for w in windows:
        first, last = w["window"]["first_index"], w["window"]["last_index"]
        cam = w["cameras"].get("c0") or {}
        counts["revised"] += w["window"].get("revision", 0) > 0
        counts["out of step"] += any("out of step" in n for n in cam.get("notes", []))
        left_out = set((w["window"].get("other_person") or {}).get("c0", []))
        frames = [i for i in range(first, last + 1) if i not in left_out and i < len(boxes)
                  and np.isfinite(boxes[i, 0])]
        passes_in = set(pass_of[frames]) if frames else {-1}
        if len(passes_in) > 1 or -1 in passes_in:
            counts["across people"] += len(passes_in) > 1
            continue
        du, dv, h = travel(boxes[frames])
        if np.hypot(du, dv) < min_speed or cam.get("azimuth_deg") is None:
            continue
        rows.append((first, h, du, dv, cam["azimuth_deg"], cam["elevation_deg"]))
    print(f"live: one agent -> Zenoh -> `posecal serve`: {counts['windows']} windows; {counts['across people']} "
          f"span a change of the tracked person (not scored); {counts['revised']} estimated again; "
          f"{counts['out of step']} called out of step\n  {agent}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--min-speed", type=float, default=0.02, help="walker heights per frame (default 0.02)")
    ap.add_argument("--clear", type=float, default=0.015,
                    help="a travel component (heights per frame) clear enough to say a side (default 0.015)")
    ap.add_argument("--elevation", type=float, nargs="+", default=[10.0, 15.0, 20.0, 30.0],
                    help="the camera's assumed elevation(s) over the walkers, for the angle (default 10 15 20 "
                         "30: a camera at a first-floor window, people 15-40 m away, is 7-20 deg above them)")
    ap.add_argument("--plot", help="write a PNG: estimated azimuth against the travel's (at the second "
                                   "--elevation)")
    ap.add_argument("--live", action="store_true", help="the windows of `posecal serve` fed by a `posecal "
                                                        "capture` agent playing the video (module docstring)")
    args = ap.parse_args()
    video = load_video()
    crops, boxes = segment(video)
    runs = passes(boxes)
    rows = live_rows(boxes, runs, args.min_speed) if args.live else offline_rows(video, crops, boxes, runs,
                                                                                  args.min_speed)
    r = np.array(rows, float)
    print(f"vtest.avi: {len(runs)} passes of one tracked walker, {len(r)} moving windows of {WINDOW} frames "
          f"(walkers {r[:, 1].min():.0f}-{r[:, 1].max():.0f} px tall, median {np.median(r[:, 1]):.0f}; "
          f"estimated elevation median {np.median(r[:, 5]):.0f} deg)")
    az, du, dv = r[:, 4], r[:, 2], r[:, 3]
    lateral = np.abs(du) >= args.clear
    right_side = np.sin(np.radians(az)) < 0  # camera on the walker's right: azimuth 180-360
    ok_lr = right_side[lateral] == (du[lateral] > 0)
    depth = np.abs(dv) >= args.clear
    in_front = np.cos(np.radians(az)) > 0
    ok_fb = in_front[depth] == (dv[depth] > 0)
    print(f"  left / right of the walker as the travel across the image says: {ok_lr.sum()} of {lateral.sum()} "
          f"windows ({100 * ok_lr.mean():.0f} %)")
    print(f"  in front / behind as the travel up or down the image says:     {ok_fb.sum()} of {depth.sum()} "
          f"windows ({100 * ok_fb.mean():.0f} %)")
    for e in args.elevation:
        heading = np.array([heading_azimuth(a, b, e) for a, b in zip(du, dv)])
        err = np.abs(azimuth_difference_deg(az, heading))
        folded = np.minimum(err, np.abs(azimuth_difference_deg(180.0 - az, heading)))  # ahead/behind aside
        print(f"  angle to the travel's heading (camera elevation {e:.0f} deg): median {np.median(err):.1f}, "
              f"p90 {np.percentile(err, 90):.1f}, max {err.max():.1f} deg; ahead/behind set aside: median "
              f"{np.median(folded):.1f}, p90 {np.percentile(folded, 90):.1f}, max {folded.max():.1f}; "
              f"on the wrong side of the fold: {int(np.sum(err - folded > 1e-9))}")
    for w0, h, a, b, z, el in rows:
        print(f"    frames {int(w0):3d}-{int(w0) + WINDOW - 1:3d}  {h:5.1f} px  travel ({a:+.3f}, {b:+.3f}) "
              f"heights/frame  azimuth {z:5.1f}  elevation {el:4.1f}")
    if args.plot:
        _plot(args.plot, r, args.elevation[min(1, len(args.elevation) - 1)])


def _plot(path: str, r: np.ndarray, elevation: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = np.array([heading_azimuth(a, b, elevation) for a, b in zip(r[:, 2], r[:, 3])])
    fig, ax = plt.subplots(figsize=(5.5, 5))
    sc = ax.scatter(truth, r[:, 4], c=r[:, 1], cmap="viridis", s=28)
    ax.plot([0, 360], [0, 360], "k--", lw=0.8)
    ax.set(xlim=(0, 360), ylim=(0, 360), xticks=range(0, 361, 90), yticks=range(0, 361, 90),
           xlabel=f"azimuth from the travel in the image (camera elevation {elevation:.0f} deg)",
           ylabel="estimated azimuth (deg)", title="vtest.avi: live windows of real walkers")
    fig.colorbar(sc, ax=ax, label="walker height (px)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
