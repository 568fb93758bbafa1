"""Benchmark: the segmenter's background bootstrap at 640x480 on one core, with and without the lit background.

``Segmenter.bootstrap`` runs once per camera and file (or after a live
agent's start-up buffer): the per-pixel median of 40 samples, then
``bootstrap_lit``'s search for a shadow lying in the median
(``capture.segment._lit``, docs/CAPTURE.md "A shadow in the median"). Samples
are 40 frames of ``/work/shared/data/video/vtest.avi`` scaled to 640x480
(real passers-by and their shadows), in three cases:

- ``vtest``: the frames as they are (a few thousand candidate pixels);
- ``shadow``: a shadow (the ground at 0.6) lying over a sixth of the frame
  in 30 of the 40 samples, the case the rule is for;
- ``light``: the whole scene 1.3 times brighter in 12 samples (a change of
  light: every pixel is a candidate, and ``bootstrap_lit_area`` stops the
  search).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_bootstrap.py [--repeats 5] [--core 0]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_real_video import VIDEO, load_video  # noqa: E402
from capture.segment import Segmenter, SegmentSettings  # noqa: E402


def _frames(n: int) -> list[np.ndarray]:
    """``n`` frames of vtest.avi spread over it, scaled to 640x480."""
    video = load_video(VIDEO)
    return [cv2.resize(video[k], (640, 480), interpolation=cv2.INTER_LINEAR)
            for k in np.linspace(0, len(video) - 1, n).astype(int)]


def _cases(frames: list[np.ndarray]) -> dict[str, list[np.ndarray]]:
    shadow = [f.copy() for f in frames]
    for f in shadow[:30]:
        f[300:460, 100:400] = cv2.convertScaleAbs(f[300:460, 100:400], alpha=0.6)
    light = [cv2.convertScaleAbs(f, alpha=1.3) if k < 12 else f for k, f in enumerate(frames)]
    return {"vtest": frames, "shadow": shadow, "light": light}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--core", type=int, default=0)
    args = parser.parse_args(argv)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.core})
    cv2.setNumThreads(1)
    cases = _cases(_frames(40))
    print(f"Segmenter.bootstrap, 40 samples at 640x480, one core (core {args.core}), "
          f"median of {args.repeats} runs; load average {os.getloadavg()[0]:.2f}")
    print("| case | lit background off | on (default) | pixels changed by it |")
    print("|---|---|---|---|")
    for name, frames in cases.items():
        times, backgrounds = [], []
        for lit in (0.0, SegmentSettings().bootstrap_lit):  # off, then the default
            runs = []
            for _ in range(args.repeats):
                seg = Segmenter(SegmentSettings(bootstrap_lit=lit))
                t = time.perf_counter()
                seg.bootstrap(frames)
                runs.append(time.perf_counter() - t)
            times.append(float(np.median(runs)))
            backgrounds.append(seg.background_image())
        off, on = times
        changed = int(np.count_nonzero(np.any(backgrounds[0] != backgrounds[1], axis=-1)))
        print(f"| {name} | {off:.2f} s | {on:.2f} s (+{on - off:.2f}) | {changed} |")


if __name__ == "__main__":
    main()
