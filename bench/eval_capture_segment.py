"""Segmentation variants against ground truth: the table in docs/CAPTURE.md.

Runs the segmenter with several settings over the synthetic camera (a side
and an oblique view) and the scripted scene, on one core with one OpenCV
thread, and prints mean IoU per input and the mean time per frame: the
segmentation itself (on the latency path) and with the deferred background
update (``Segmenter.learn``, which the agent runs after publishing).

    .venv/bin/python bench/eval_capture_segment.py [--frames 230]
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np

from capture.scene import SceneSpec, iou, scene_frames
from capture.segment import Segmenter, SegmentSettings
from capture.sources import make_source

# (name, SegmentSettings overrides, plain MOG2 update instead of the selective one)
VARIANTS = [
    ("MOG2 defaults (shadows on, learningRate=-1), open 3",
     dict(model_width=0, detect_shadows=True, open_px=3), True),
    ("shadows off, open 3", dict(model_width=0, open_px=3), True),
    ("shadows off, no opening", dict(model_width=0), True),
    ("+ selective update every 4 frames, full resolution", dict(model_width=0), False),
    ("same, model 160 px wide, mask upsampled", dict(refine_px=0), False),
    ("**+ full-resolution refinement (default)**", {}, False),
]


class _Plain(Segmenter):
    """The non-selective variant at full resolution: MOG2 learns from every frame."""

    def apply(self, image, index):  # noqa: D102 - same contract as Segmenter.apply
        if self.warming_up:
            return super().apply(image, index)
        g = self._geometry_for((image.shape[1], image.shape[0]))
        raw = self._mog.apply(image, learningRate=-1)
        fg = cv2.compare(raw, 200, cv2.CMP_GT)
        if self._open is not None:
            fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, self._open)
        return self._largest(fg, g, used_prior=False)  # closes, keeps the largest


def _frames(spec: str, n: int) -> list:
    with make_source(spec) as source:
        return [f for _, f in zip(range(n), source)]


def _score(frames: list, settings: SegmentSettings,
           plain: bool) -> tuple[float, list[tuple[float, float]]]:
    """Mean IoU over frames with a walker; (apply, apply + learn) seconds per frame."""
    seg = (_Plain if plain else Segmenter)(settings)
    ious, times = [], []
    for f in frames:
        t = time.perf_counter()
        out = seg.apply(f.image, f.index)
        t_apply = time.perf_counter() - t
        seg.learn()  # the deferred background update, as the agent does after publishing
        if out is None:
            continue
        times.append((t_apply, time.perf_counter() - t))
        if f.mask.any():
            ious.append(iou(out.full_mask(), f.mask))
    return float(np.mean(ious)), times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=230)
    parser.add_argument("--core", type=int, default=0)
    args = parser.parse_args()
    os.sched_setaffinity(0, {args.core})
    cv2.setNumThreads(1)
    inputs = {
        "synthetic side": (_frames("synthetic:seed=3,azimuth=90", args.frames), 30),
        "synthetic oblique": (_frames("synthetic:seed=5,azimuth=30,elevation=30", args.frames), 30),
        "scene": (list(scene_frames(SceneSpec(frames=args.frames + 70))), 100),
    }
    print(f"mean IoU vs ground truth, 640x480; load avg {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} cores (ms/frame is load-sensitive)\n")
    print("| variant | " + " | ".join(inputs) + " | ms/frame, 1 core: segment (+ update) |")
    print("|---" * (len(inputs) + 2) + "|")
    for name, overrides, plain in VARIANTS:
        row, times = [], []
        for frames, warmup in inputs.values():
            settings = SegmentSettings(**{**overrides, "warmup_frames": warmup})
            score, t = _score(frames, settings, plain)
            row.append(f"{score:.3f}")
            times += t
        apply, total = np.mean(times, axis=0) * 1e3
        print(f"| {name} | " + " | ".join(row) + f" | {apply:.1f} ({total:.1f}) |")


if __name__ == "__main__":
    main()
