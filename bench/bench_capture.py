"""Benchmark: one capture agent, segment + publish throughput at 640x480 on one core.

The agent (``capture.agent.main``, unchanged) runs in this process pinned to
one core with ``os.sched_setaffinity`` and OpenCV limited to one thread; its
source hands over pre-rendered frames (the scripted scene of
``capture.scene``, or any source with ground truth such as the synthetic
camera) as fast as it is asked (``live=True``, so nothing paces it). A
receiver process pinned to the other core subscribes over Zenoh on 127.0.0.1,
scores every silhouette *as received* against the ground truth (IoU) and
reports capture-to-receive latency.

    .venv/bin/python bench/bench_capture.py [--frames 600] [--core 0] [--model-width 0] [--refine-px 0]
                                            [--no-colour-split]
    .venv/bin/python bench/bench_capture.py --source synthetic:seed=3,azimuth=90 --frames 300

Target (issue 6): >= 30 fps at 640x480 on one core; IoU is reported.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator

import numpy as np

TARGET_FPS = 30.0


def _free_endpoint() -> str:
    from service.server import free_port

    return f"tcp/127.0.0.1:{free_port()}"


def _frames(args: argparse.Namespace) -> list:
    """The scripted scene (100 empty frames, then walking) or a synthetic-camera spec."""
    if args.source == "scene":
        from capture.scene import SceneSpec, scene_frames

        spec = SceneSpec(width=args.width, height=args.height, frames=100 + args.frames, empty=100)
        return list(scene_frames(spec))
    from capture.sources import make_source

    with make_source(args.source) as source:
        frames, empty = [], None  # empty: frames before the first with a walker
        for frame in source:
            frames.append(frame)
            if empty is None and frame.mask.any():
                empty = len(frames) - 1
            if len(frames) >= min(len(frames) if empty is None else empty, 100) + args.frames:
                return frames
    return frames


def receiver(args: argparse.Namespace) -> None:
    """Subscribe, score every silhouette against the truth, print one JSON line."""
    import zenoh

    from capture.receiver import SilhouetteReceiver
    from capture.scene import iou
    from capture.zconfig import build_config

    masks = np.load(args.truth)["masks"]
    ious, latencies = [], []
    with zenoh.open(build_config(listen=[args.endpoint])) as session, \
            SilhouetteReceiver(session, "bench") as rx:
        print("ready", flush=True)
        deadline = time.monotonic() + args.timeout
        while len(latencies) < args.frames and time.monotonic() < deadline:
            item = rx.get(timeout=0.2)
            if item is None:
                continue
            latencies.append(item.latency_ns / 1e6)
            truth = masks[item.message.frame_index]
            if truth.any():
                ious.append(iou(item.message.full_mask(), truth))
        stats = rx.stats()
    print(json.dumps({"received": len(latencies), "rejected": stats.rejected, "lost": stats.lost,
                      "iou_mean": float(np.mean(ious)), "iou_min": float(np.min(ious)),
                      "iou_p5": float(np.percentile(ious, 5)), "scored": len(ious),
                      "lat_p50": float(np.percentile(latencies, 50)),
                      "lat_p99": float(np.percentile(latencies, 99))}), flush=True)


def agent(args: argparse.Namespace) -> int:
    import cv2

    from capture import agent as capture_agent
    from capture.sources import Frame, FrameSource
    from capture.zconfig import build_config

    class Prerendered(FrameSource):
        """Frames already in memory, stamped when handed over, like a camera buffer."""

        live = True
        fps = None

        def __init__(self, frames: list[Frame]) -> None:
            self.frames = frames

        def __iter__(self) -> Iterator[Frame]:
            for f in self.frames:
                yield Frame(f.image, f.index, time.time_ns())

    frames = _frames(args)
    if any(f.mask is None for f in frames):
        raise SystemExit(f"source {args.source} has no ground truth masks")
    warmup = min(100, next(k for k, f in enumerate(frames) if f.mask.any()))
    truth = tempfile.NamedTemporaryFile(suffix=".npz", delete=False)
    np.savez(truth, masks=np.stack([f.mask for f in frames]))
    truth.close()
    other = sorted(os.sched_getaffinity(0) - {args.core}) or [args.core]
    rx = subprocess.Popen([sys.executable, __file__, "--role", "receiver", "--endpoint",
                           args.endpoint, "--frames", str(len(frames) - warmup),
                           "--truth", truth.name], stdout=subprocess.PIPE, text=True,
                          preexec_fn=lambda: os.sched_setaffinity(0, {other[0]}))
    if rx.stdout.readline().strip() != "ready":
        raise SystemExit("receiver failed to start")
    os.sched_setaffinity(0, {args.core})
    cv2.setNumThreads(1)
    from capture.segment import SegmentSettings, describe

    overrides = {k: v for k, v in (("model_width", args.model_width),
                                   ("refine_px", args.refine_px)) if v is not None}
    if args.no_colour_split:
        overrides["colour_split"] = False
    segment = SegmentSettings(warmup_frames=warmup, **overrides)
    settings = capture_agent.AgentSettings(rig="bench", camera="c0", stats_interval_s=1e9,
                                           segment=segment)
    stats = capture_agent.main(build_config(connect=[args.endpoint]), settings,
                               source=Prerendered(frames))
    result = json.loads(rx.communicate(timeout=args.timeout)[0].strip().splitlines()[-1])
    os.unlink(truth.name)
    width, height = frames[0].size
    p50, p99 = stats.latency_percentiles()
    ok = stats.fps >= TARGET_FPS
    print(f"source {args.source}, {width}x{height}, {describe(segment, (width, height))}: {stats.sent} "
          f"segmented+published after {stats.warmup} warm-up, on core {args.core}, OpenCV "
          f"threads 1, load avg {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"throughput     {stats.fps:8.1f} fps   target >= {TARGET_FPS:.0f}   "
          f"ratio {stats.fps / TARGET_FPS:5.2f}x   {'MET' if ok else 'NOT MET'}")
    print(f"per frame      {1e3 / stats.fps:8.2f} ms wall, {1e3 * stats.cpu_s / stats.sent:.2f} ms "
          f"CPU (segment + encode + put; CPU-bound rate {stats.sent / stats.cpu_s:.0f} fps)")
    print(f"capture->publish p50 {p50:.2f} ms p99 {p99:.2f} ms (back-to-back, no pacing)")
    print(f"receiver: {result['received']}/{stats.sent} delivered, lost {result['lost']}, "
          f"rejected {result['rejected']}")
    print(f"silhouette IoU vs {args.source} ground truth (as received): mean "
          f"{result['iou_mean']:.3f} p5 {result['iou_p5']:.3f} min {result['iou_min']:.3f} "
          f"over {result['scored']} frames with a walker")
    return 0 if ok and result["received"] == stats.sent else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--role", choices=("agent", "receiver"), default="agent")
    parser.add_argument("--endpoint", default=None)
    parser.add_argument("--source", default="scene",
                        help="'scene' (scripted, default) or a source spec with ground truth, "
                             "e.g. synthetic:seed=3,azimuth=90")
    parser.add_argument("--truth", help=argparse.SUPPRESS)
    parser.add_argument("--frames", type=int, default=600, help="frames after warm-up")
    parser.add_argument("--width", type=int, default=640, help="scene only")
    parser.add_argument("--height", type=int, default=480, help="scene only")
    parser.add_argument("--core", type=int, default=0)
    parser.add_argument("--model-width", type=int, default=None,
                        help="background-model width, 0 = full (default: SegmentSettings')")
    parser.add_argument("--refine-px", type=float, default=None,
                        help="refinement band in model pixels (default: SegmentSettings')")
    parser.add_argument("--no-colour-split", action="store_true",
                        help="segment without the colour split (SegmentSettings.colour_split)")
    parser.add_argument("--timeout", type=float, default=120.0)
    args = parser.parse_args()
    args.endpoint = args.endpoint or _free_endpoint()
    logging.basicConfig(level=logging.WARNING)
    return agent(args) if args.role == "agent" else receiver(args) or 0


if __name__ == "__main__":
    sys.exit(main())
