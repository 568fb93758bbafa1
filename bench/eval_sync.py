"""Offline synchronisation of recorded videos (``estimator.sync``, ``posecal sync``) against the truth.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_sync.py [--rigs 12] [--seed 0] [--videos 4]

Synthetic rigs: 3 cameras at random viewpoints (the paper's range) and random
frame rates from {15, 25, 30} fps, each recording 6 s of the same walk (a
random body and style, the CMU-fitted gait, 1280x720) from a start drawn in
[0, 2] s, so that the offsets between cameras reach ±2 s. The walker's pace is
varied three ways (``SynthSpec.cadence_variation``): 10 % slow changes of
cadence (people speeding up and slowing down), 5 %, and none at all (a
perfectly even pace, which leaves whole gait cycles undetermined: the
command must say so). Each camera is estimated alone from its silhouettes
(:func:`estimator.sync.camera_clock`) and the rig synchronised
(:func:`estimator.sync.synchronize`); the error is the offset's error in frames
of that camera. Reported per pace: the median and p90 of |error| over all
non-reference cameras, how many are off by a gait cycle or more ("wrong"), how
many the result flags ``ambiguous``, and how many are wrong without the flag.

Through real video files: ``--videos`` of the 10 %-pace rigs again, each camera
written as a video (the walker over a textured scene with sensor noise, out of
view for the first second) and run through ``posecal sync FOLDER`` as a user
would (background subtraction, then the same).

Real footage: ``vtest.avi`` (OpenCV's sample, 10 fps, people walking; shared
data) cut into "cameras" that start at different frames of the same recording
(the same view: a sanity check of the whole path on real segmentation, not of
viewpoint invariance), one of them at half the frame rate (every other frame).

Writes ``docs/img/sync_errors.png``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from capture.synthetic import write_recording  # noqa: E402
from estimator.pipeline import tracks_from_sequence  # noqa: E402
from estimator.sync import camera_clock, synchronize  # noqa: E402
from estimator.synth import SynthSpec, synthesize_recordings  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
VTEST = Path("/work/shared/data/video/vtest.avi")
PACES = (0.1, 0.05, 0.0)
RATES = (15.0, 25.0, 30.0)


def rig_clocks(seed: int, duration: float = 6.0) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Per camera its frame times on the walk's clock; the rates and starts drawn."""
    rng = np.random.default_rng(seed + 1000)
    fps = rng.choice(RATES, 3)
    starts = rng.uniform(0.0, 2.0, 3)
    return {f"c{i}": starts[i] + np.arange(int(duration * fps[i])) / fps[i] for i in range(3)}, fps, starts


def errors_of(offsets: dict[str, float], ambiguous: dict[str, bool], ref: str, fps: np.ndarray,
              starts: np.ndarray) -> list[tuple[float, bool]]:
    """(error in frames, flagged) per non-reference camera."""
    out = []
    for c, off in offsets.items():
        if c == ref:
            continue
        i, r = int(c[1:]), int(ref[1:])
        if off is None:  # not synchronised: counted as wrong (and flagged)
            out.append((np.inf, True))
            continue
        out.append(((off - (starts[i] - starts[r])) * fps[i], bool(ambiguous[c])))
    return out


def summary(rows: list[tuple[float, bool]], cycle_frames: float = 8.0) -> str:
    """Median / p90 |error|, wrong (a half cycle or more off: > ``cycle_frames`` frames at
    15-30 fps), flagged, wrong and not flagged."""
    e = np.abs([r[0] for r in rows])
    flagged = np.array([r[1] for r in rows])
    wrong = e > cycle_frames
    right = e[~wrong]
    return (f"n={len(e):3d}  |error| median {np.median(e):6.2f} p90 {np.percentile(e, 90):6.2f} frames; "
            f"right ones median {np.median(right) if right.size else np.nan:.3f} p90 "
            f"{np.percentile(right, 90) if right.size else np.nan:.3f}; wrong {wrong.sum()}, "
            f"flagged ambiguous {flagged.sum()}, wrong and not flagged {(wrong & ~flagged).sum()}")


def synthetic(n: int, seed: int, model) -> dict[float, list[tuple[float, bool]]]:
    results: dict[float, list[tuple[float, bool]]] = {p: [] for p in PACES}
    for pace in PACES:
        t0 = time.perf_counter()
        for s in range(seed, seed + n):
            clocks, fps, starts = rig_clocks(s)
            recs = synthesize_recordings(SynthSpec(n_cameras=3, seed=s, cadence_variation=pace,
                                                   image_size=(1280, 720)), clocks)
            cl = {c: camera_clock(tracks_from_sequence(r)[c], model, r.fps) for c, r in recs.items()}
            res = synchronize(cl)
            results[pace] += errors_of(res.offsets_s, res.ambiguous, res.reference, fps, starts)
        print(f"pace variation {pace:4.2f}: {summary(results[pace])}  ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    return results


def through_videos(n: int, seed: int, model_path: str | None) -> list[tuple[float, bool]]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for s in range(seed, seed + n):
            clocks, fps, starts = rig_clocks(s, duration=7.0)
            recs = synthesize_recordings(SynthSpec(n_cameras=3, seed=s, cadence_variation=0.1,
                                                   image_size=(960, 540)), clocks)
            folder = Path(tmp) / f"rig{s}"
            folder.mkdir()
            for c, r in recs.items():
                write_recording(str(folder / f"{c}.avi"), r.silhouettes[c], r.fps, seed=s * 10 + int(c[1:]),
                                empty=int(r.fps))
            res = _posecal_sync([str(folder)], model_path)
            cams = res["cameras"]
            for note in res["notes"]:
                print(f"  rig {s}: {note}", flush=True)
            rows += errors_of({c: v["offset_s"] for c, v in cams.items()},
                              {c: v["ambiguous"] for c, v in cams.items()}, res["reference"], fps, starts)
    print(f"through videos (posecal sync): {summary(rows)}", flush=True)
    return rows


def _posecal_sync(args: list[str], model_path: str | None) -> dict:
    cmd = [sys.executable, "-m", "service.cli", "sync", *args] + (["--model", model_path] if model_path else [])
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if r.returncode not in (0, 1):
        raise RuntimeError(f"posecal sync failed ({r.returncode}): {r.stderr[-2000:]}")
    return json.loads(r.stdout)


def real_footage(model_path: str | None) -> list[str]:
    """vtest.avi cut at different starts (and one at half the rate): the offsets found."""
    import cv2

    if not VTEST.exists():
        return ["vtest.avi not found: skipped"]
    cap = cv2.VideoCapture(str(VTEST))
    fps = cap.get(cv2.CAP_PROP_FPS) or 10.0
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    lines = []
    cuts = {"a": (0, 1), "b": (13, 1), "c": (24, 1)}  # (first frame, step): offsets within ±2.5 s
    length = 500
    with tempfile.TemporaryDirectory() as tmp:
        for name, (first, step) in cuts.items():
            sel = frames[first:first + length:step]
            h, w = sel[0].shape[:2]
            writer = cv2.VideoWriter(str(Path(tmp) / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), fps / step,
                                     (w, h))
            for img in sel:
                writer.write(img)
            writer.release()
        res = _posecal_sync([tmp], model_path)
    ref = res["reference"]
    for c, v in res["cameras"].items():
        true = (cuts[c][0] - cuts[ref][0]) / fps
        err = None if v["offset_s"] is None else (v["offset_s"] - true) * v["fps"]
        lines.append(f"vtest {c} (starts at frame {cuts[c][0]}, every {cuts[c][1]}. frame, {v['fps']} fps): "
                     f"true {true:+.3f} s, found {v['offset_s']} s, error "
                     f"{'n/a' if err is None else f'{err:+.2f}'} frames, ambiguous {v['ambiguous']}")
    lines += [f"  note: {n}" for n in res["notes"]]
    for line in lines:
        print(line, flush=True)
    return lines


def plot(results: dict[float, list[tuple[float, bool]]], videos: list[tuple[float, bool]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for pace, rows in results.items():
        e = np.abs([r[0] for r in rows])
        axes[0].plot(np.sort(e), np.linspace(0, 1, len(e)), label=f"pace variation {pace:.0%}")
    if videos:
        e = np.abs([r[0] for r in videos])
        axes[0].plot(np.sort(e), np.linspace(0, 1, len(e)), "k--", label="10 %, through videos")
    axes[0].set_xscale("symlog", linthresh=1.0)
    axes[0].axvline(0.3, color="grey", lw=0.8)
    axes[0].set_xlabel("|offset error| (frames of the camera)")
    axes[0].set_ylabel("fraction of cameras")
    axes[0].legend(fontsize=8)
    axes[0].set_title("offset error, cumulative")
    for pace, rows in results.items():
        e = np.array([r[0] for r in rows])
        ok = np.abs(e) < 8
        axes[1].hist(e[ok], bins=np.linspace(-1, 1, 41), alpha=0.5, label=f"{pace:.0%}")
    axes[1].set_xlabel("offset error (frames), cameras within a half cycle")
    axes[1].legend(fontsize=8)
    axes[1].set_title("sub-frame accuracy")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rigs", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--videos", type=int, default=4, help="10 %%-pace rigs run through video files (0: none)")
    ap.add_argument("--model", help="appearance model file (default: the cached default model)")
    ap.add_argument("--plot", type=Path, default=ROOT / "docs" / "img" / "sync_errors.png")
    args = ap.parse_args(argv)
    from service.cli.model import get_default_model, model_from_arg

    model = model_from_arg(args.model) if args.model else get_default_model(progress=True)
    results = synthetic(args.rigs, args.seed, model)
    videos = through_videos(args.videos, args.seed, args.model) if args.videos else []
    real_footage(args.model)
    plot(results, videos, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
